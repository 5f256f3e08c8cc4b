#!/usr/bin/env bash
# The Python package's speed against the CLI and the pybullet peer, side by side in one run
# (scripts/bench-python.py says what is measured). Builds the release binary and installs the
# release wheel into .venv-bench (with pybullet, from PyPI) first.
#
#   scripts/bench-python.sh [bench-python.py options]     e.g. --n 100 --only dense
set -euo pipefail
cd "$(dirname "$0")/.."
venv=.venv-bench
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
"$venv/bin/pip" install --quiet --disable-pip-version-check pybullet numpy maturin==1.16.0 eclipse-zenoh==1.10.2 \
    gymnasium==1.4.0 pettingzoo==1.27.0
cargo build --release --locked -p twinswarm
PATH="$PWD/$venv/bin:$PATH" "$venv/bin/pip" install --quiet --disable-pip-version-check --no-build-isolation \
    --force-reinstall --no-deps ./crates/py
# VectorEnv and step_many run on RAYON_NUM_THREADS threads (default 2); everything else on one.
# PIN_CORE=C pins the measurements (not the build) to core C (scripts/bench-peers.sh: core 0).
pin=()
[ -z "${PIN_CORE:-}" ] || pin=(taskset -c "$PIN_CORE")
RAYON_NUM_THREADS=${RAYON_NUM_THREADS:-2} "${pin[@]}" "$venv/bin/python" scripts/bench-python.py "$@"
