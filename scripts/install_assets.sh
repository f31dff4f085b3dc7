#!/usr/bin/env bash
# Install the Debian packages the renderer reads (nvs.data.render): real 3-D models and TORCS tracks,
# assimp (AC3D -> OBJ for TORCS cars) and Mesa's software EGL/OSMesa; and the browser the viewer's test drives.
# Idempotent: exits at once when all are present.
set -euo pipefail
export DEBIAN_FRONTEND=noninteractive

PACKAGES=(
  sweethome3d-furniture   # chairs and cars (.sh3f catalogs: OBJ+MTL+textures), CC0 / CC-BY
  torcs-data              # cars (AC3D .acc + SGI .rgb) and road tracks, Free Art License / GPL-2+
  trigger-rally-data      # rally cars (textured OBJ), GPL-2 / CC
  assimp-utils            # `assimp export car.acc car.obj`
  libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libosmesa6   # headless software rendering (llvmpipe)
  chromium                # headless browser for the viewer's test (Playwright launches /usr/bin/chromium)
)

missing=()
for p in "${PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "assets: all ${#PACKAGES[@]} packages already installed"
  exit 0
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
echo "assets: installing ${missing[*]}"
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
echo "assets: done"
