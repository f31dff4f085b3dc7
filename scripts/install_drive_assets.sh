#!/usr/bin/env bash
# Extract the SuperTuxKart data the drive renderer reads (python -m nvs.data.render drive; sources=stk):
# race tracks, shared textures, library objects and the copyright file, from Debian's supertuxkart-data
# (628 MB .deb, 705 MB installed; CC-BY-SA / GPL, see /usr/share/doc/supertuxkart-data/copyright).
# The package is fetched with `apt-get download` and only those folders are unpacked (561 MB) into the path the
# package would use, without installing it (its fonts dependencies are not needed). Measured here: download
# 8 s, extraction 32 s. TORCS tracks come from scripts/install_assets.sh. Not part of `make setup`: only the
# full drive render needs this. Idempotent: exits at once when the data is present.
set -euo pipefail
export DEBIAN_FRONTEND=noninteractive

# ROOT=/some/dir extracts under that directory instead of / (for trying the script; the renderer reads /usr/...).
ROOT=${ROOT:-/}
STK="${ROOT%/}/usr/share/games/supertuxkart/data"
MARKER="$STK/.nvs-extracted"
if [ -f "$MARKER" ] || { [ "$ROOT" = / ] && dpkg-query -W -f='${Status}' supertuxkart-data 2>/dev/null | grep -q "install ok installed"; }; then
  echo "drive assets: supertuxkart-data already present under $STK"
  exit 0
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
chmod 777 "$tmp"  # apt-get download writes as the _apt user where it can
start=$(date +%s)
echo "drive assets: downloading supertuxkart-data"
(cd "$tmp" && apt-get download -q supertuxkart-data 2>&1 | grep -v "^W: Download is performed unsandboxed" || true)
deb=$(ls "$tmp"/supertuxkart-data_*.deb 2>/dev/null | head -n 1)
if [ -z "$deb" ]; then
  echo "drive assets: apt-get download supertuxkart-data failed (run apt-get update?)" >&2
  exit 1
fi
echo "drive assets: extracting tracks, textures, library, models into $STK"
dpkg-deb --fsys-tarfile "$deb" | $SUDO tar -x -C "$ROOT" --wildcards \
  './usr/share/games/supertuxkart/data/tracks/*' './usr/share/games/supertuxkart/data/textures/*' \
  './usr/share/games/supertuxkart/data/library/*' './usr/share/games/supertuxkart/data/models/*' \
  './usr/share/doc/supertuxkart-data/*'
echo "$(basename "$deb")" | $SUDO tee "$MARKER" >/dev/null
echo "drive assets: done in $(( $(date +%s) - start )) s ($(du -sh "$STK" | cut -f1) on disk)"
