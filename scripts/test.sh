#!/usr/bin/env bash
# The one test command: installs what the tests need, then runs every check and test.
#   scripts/test.sh
# Safe to run on a fresh machine and in CI (.ci/run calls it).
set -euo pipefail
cd "$(dirname "$0")/.."

# Tests that skip for want of ../shared/data (Rust and pytest) append a line `test<TAB>path`
# here; the count goes into the last line. Under CI=true they fail instead.
export TWINSWARM_SKIP_LOG="$PWD/target/skipped-shared-data.txt"
mkdir -p target && : > "$TWINSWARM_SKIP_LOG"

# Each phase says how long the one before it took, and the end gives the whole, so a CI log
# shows where its minutes go (docs/testing.md).
test_start=$(date +%s)
phase_start=$test_start
say() {
  local now
  now=$(date +%s)
  if [ "$now" -gt "$test_start" ]; then printf '    (%d s)\n' $((now - phase_start)); fi
  phase_start=$now
  printf '\n==> %s\n' "$*"
}

say "toolchain"
cargo --version
for comp in rustfmt clippy; do
  if ! rustup component list --installed 2>/dev/null | grep -q "^${comp}"; then
    echo "installing rustup component ${comp}"
    rustup component add "${comp}"
  fi
done

say "cargo fmt --check"
cargo fmt --all -- --check

say "import circles (scripts/check-imports.py: none beyond scripts/import-cycles.allow)"
python3 scripts/check-imports.py

say "no function over 150 lines outside tests (scripts/long-functions.py)"
python3 scripts/long-functions.py --over 150 --max 150

say "cargo clippy --all-targets -- -D warnings"
cargo clippy --workspace --all-targets --locked -- -D warnings

say "cargo test (every crate, every test; benches built and run once as tests)"
cargo test --workspace --all-targets --locked

say "cargo test --doc"
cargo test --workspace --doc --locked

say "Paparazzi ground segment (link, server) for tests/python/test_paparazzi_ground.py"
# Built from ../shared/paparazzi into target/paparazzi: apt packages on a new machine (~80 s),
# then ~35 s of building; build.sh keeps a finished build (target/paparazzi/.built holds the
# source tarball's hash) and then returns at once. Without ../shared/paparazzi those tests skip
# loudly (a line in $TWINSWARM_SKIP_LOG), or fail under CI=true.
if [ -f ../shared/paparazzi/build.sh ]; then
  pprz_start=$(date +%s)
  bash ../shared/paparazzi/build.sh target/paparazzi
  echo "paparazzi: ready in $(( $(date +%s) - pprz_start )) s"
else
  echo "../shared/paparazzi/build.sh not found: the Paparazzi ground-segment tests will skip (fail under CI=true)"
fi

say "python: independent clients and peers (tests/python: eclipse-zenoh, mcap, ivy-python)"
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install --quiet --disable-pip-version-check -r tests/python/requirements.txt
# Same targets and features as the test run above, so nothing is rebuilt.
cargo build --workspace --all-targets --locked

say "python package: pip install ./crates/py (the test profile, not release)"
# The README's `pip install ./crates/py`, built with the test profile: a release build of the
# extension would take longer than every test together. The maturin of tests/python's
# requirements builds it in place, into this repository's target/.
PATH="$PWD/.venv/bin:$PATH" MATURIN_PEP517_ARGS="--profile dev" \
  .venv/bin/python -m pip install --quiet --disable-pip-version-check --no-build-isolation --force-reinstall --no-deps ./crates/py
pytest_status=0
TWINSWARM_BIN="$PWD/target/debug/twinswarm" .venv/bin/python -m pytest -q --durations=12 tests/python || pytest_status=$?
if [ "$pytest_status" -eq 5 ]; then
  echo "error: pytest collected no tests in tests/python" >&2
  exit 1
elif [ "$pytest_status" -ne 0 ]; then
  echo "error: python tests failed (pytest exit code $pytest_status)" >&2
  exit "$pytest_status"
fi

skipped=$(($(wc -l < "$TWINSWARM_SKIP_LOG")))
skip_note=""
if [ "$skipped" -gt 0 ]; then
  skip_note=" ($skipped shared-data tests skipped: $(cut -f2 "$TWINSWARM_SKIP_LOG" | sort -u | paste -sd, -) absent)"
fi
say "done in $(( $(date +%s) - test_start )) s"
echo "all checks passed: fmt, clippy, cargo tests, doc tests, python tests (Zenoh client, MCAP reader, replay, Ivy peers, Paparazzi's link and server, the Python package, PettingZoo and Gymnasium conformance, lockstep)$skip_note"
