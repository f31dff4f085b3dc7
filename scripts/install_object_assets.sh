#!/usr/bin/env bash
# The large object packages for the full chairs/cars sets (nvs.data.render): fetched with `apt-get download` and
# only the folders the renderer reads extracted under data/assets/<package>/ (the package's own paths kept).
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
)

for pkg in flightgear-data-base ufoai-data sweethome3d; do
  out="$DEST/$pkg"
  # The stamp holds the member list: a changed list re-extracts.
  if [ -f "$out/.complete" ] && [ "$(cat "$out/.complete")" = "${MEMBERS[$pkg]}" ]; then
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
    # Only the cars and chairs of the 240 MB model archive: unpack them and drop the archive.
    pk3="$out.partial/usr/share/games/ufoai/base/0models.pk3"
    python3 - "$pk3" "$out.partial/usr/share/games/ufoai/base" <<'EOF'
import sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as z:
    for m in z.namelist():
        if m.startswith(("models/objects/cars/", "models/objects/furniture/chairs/")) and not m.endswith("/"):
            z.extract(m, sys.argv[2])
EOF
    rm -f "$pk3"
  fi
  rm -f "$deb"
  rm -rf "$out" && mv "$out.partial" "$out"
  printf '%s' "${MEMBERS[$pkg]}" > "$out/.complete"
  echo "object assets: $pkg -> $out ($(du -sh "$out" | cut -f1), $(( $(date +%s) - t0 )) s)"
done
