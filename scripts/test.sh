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

# Under CI (a fresh clone, built once): no incremental compilation of the workspace's crates. It
# only writes caches that a fresh clone never reads, and a build without it is faster. Every
# cargo command below, and maturin's, sees the same setting, so they share their artifacts.
case "${CI:-}" in true|TRUE|True|1) export CARGO_INCREMENTAL=0 ;; esac

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

# The Paparazzi ground segment and the Python virtual environment are set up in the background
# while cargo builds: they wait mostly on apt, PyPI and disk, and nothing of cargo's needs them.
# Their output goes to target/setup.log, shown when the Rust tests are about to run (the tests
# then have the machine to themselves) or when this script ends early.
setup_log="$PWD/target/setup.log"
(
  set -euo pipefail
  echo "==> Paparazzi ground segment (link, server) for tests/python/test_paparazzi_ground.py"
  # Built from ../shared/paparazzi into target/paparazzi: apt packages on a new machine (~80 s),
  # then ~35 s of building; build.sh keeps a finished build (target/paparazzi/.built holds the
  # source tarball's hash) and then returns at once. Without ../shared/paparazzi those tests
  # skip loudly (a line in $TWINSWARM_SKIP_LOG), or fail under CI=true.
  if [ -f ../shared/paparazzi/build.sh ]; then
    pprz_start=$(date +%s)
    bash ../shared/paparazzi/build.sh target/paparazzi
    echo "paparazzi: ready in $(( $(date +%s) - pprz_start )) s"
  else
    echo "../shared/paparazzi/build.sh not found: the Paparazzi ground-segment tests will skip (fail under CI=true)"
  fi
  # After Paparazzi's apt packages (python3-venv among them, on a new machine).
  echo "==> python: .venv with tests/python/requirements.txt"
  venv_start=$(date +%s)
  if [ ! -x .venv/bin/python ]; then
    python3 -m venv .venv
  fi
  .venv/bin/python -m pip install --quiet --disable-pip-version-check -r tests/python/requirements.txt
  echo "python: .venv ready in $(( $(date +%s) - venv_start )) s"
) > "$setup_log" 2>&1 &
setup_pid=$!
setup_waited=""
# wait_for_setup: wait for the background setup, print its log, fail if it failed.
wait_for_setup() {
  local status=0
  setup_waited=1
  wait "$setup_pid" || status=$?
  cat "$setup_log"
  if [ "$status" -ne 0 ]; then
    echo "error: the background setup (Paparazzi, .venv) failed with exit code $status; its log is above ($setup_log)" >&2
    exit "$status"
  fi
}
# On an early exit (a failed check), let the setup finish (never leave apt half done) and show it.
trap 'if [ -z "$setup_waited" ]; then wait "$setup_pid" 2>/dev/null || true; echo "---- background setup ($setup_log) ----"; cat "$setup_log"; fi' EXIT

say "cargo fmt --check"
cargo fmt --all -- --check

say "import circles (scripts/check-imports.py: none beyond scripts/import-cycles.allow)"
python3 scripts/check-imports.py

say "no function over 150 lines outside tests (scripts/long-functions.py)"
python3 scripts/long-functions.py --over 150 --max 150

# clippy in the builds below, not in a build of its own: clippy-driver (rustc with clippy's
# lints) compiles the workspace's crates, every dependency is compiled once (a `cargo clippy`
# beforehand checked each of them again, about 250 s of a cold run), and `-D warnings` makes
# any lint or warning a failed build. The lints are those of `cargo clippy --workspace
# --all-targets -- -D warnings` (lib, bins, tests, benches and examples here, crates/py in
# maturin's build below), which stays the command to run by hand. Exported for every cargo
# command below and for maturin, so that they share one build.
say "clippy: clippy-driver compiles the workspace's crates below, -D warnings"
RUSTC_WORKSPACE_WRAPPER="$(command -v clippy-driver)" || { echo "error: clippy-driver not found (rustup component add clippy)" >&2; exit 1; }
export RUSTC_WORKSPACE_WRAPPER
export RUSTFLAGS="${RUSTFLAGS:+$RUSTFLAGS }-D warnings"
echo "RUSTC_WORKSPACE_WRAPPER=$RUSTC_WORKSPACE_WRAPPER RUSTFLAGS=$RUSTFLAGS"

say "cargo test --no-run (build every crate's tests, benches as tests; with clippy's lints)"
# crates/py is left out of cargo's build and test: it has no Rust tests (its tests are Python's,
# below), and maturin builds it below in any case (linted there), with PyO3 configured
# for the venv's Python; built here too, PyO3 and the extension were compiled twice. Leaving it
# out changes no other crate's features (cargo's unit graph, checked).
cargo test --workspace --exclude twinswarm-py --all-targets --locked --no-run
# The examples (cargo test builds none) with the same profile and features as the tests, so
# nothing of the above is built again.
cargo build --workspace --exclude twinswarm-py --all-targets --locked

say "cargo test --doc"
cargo test --workspace --doc --locked

say "waiting for the background setup (Paparazzi, .venv)"
wait_for_setup

say "cargo test (every crate, every test; benches run once as tests)"
cargo test --workspace --exclude twinswarm-py --all-targets --locked

say "python package: pip install ./crates/py (the test profile, not release)"
# The README's `pip install ./crates/py`, built with the test profile: a release build of the
# extension would take longer than every test together. The maturin of tests/python's
# requirements builds it in place, into this repository's target/, reusing the workspace
# build above for every dependency: only PyO3 and the extension are compiled here.
py_build_log="$PWD/target/py-build.log"
if ! PATH="$PWD/.venv/bin:$PATH" MATURIN_PEP517_ARGS="--profile dev" \
  .venv/bin/python -m pip install -v --disable-pip-version-check --no-build-isolation --force-reinstall --no-deps ./crates/py \
  > "$py_build_log" 2>&1; then
  tail -80 "$py_build_log" >&2
  echo "error: pip install ./crates/py failed (its whole output: $py_build_log)" >&2
  exit 1
fi
# cargo resolves features for the packages it builds: were crates/py to ask other features of a
# shared dependency than the workspace does, maturin (which builds crates/py alone) would compile
# that dependency and all above it (Rapier, Zenoh, sim-core, bridge...) a second time, minutes
# of a cold run. crates/py/Cargo.toml names the features the rest of the workspace turns on.
rebuilt=$(sed -nE 's/^ *Compiling ([^ ]+) .*/\1/p' "$py_build_log" | grep -vE '^(twinswarm-py|pyo3.*|target-lexicon)$' | sort -u | paste -sd' ' - || true)
if [ -n "$rebuilt" ]; then
  echo "warning: pip install ./crates/py compiled again what the workspace build had built: $rebuilt."
  echo "  Their features for crates/py differ from the workspace's; add what the workspace turns on to"
  echo "  crates/py/Cargo.toml (compare \`cargo tree -e features -i CRATE\` with and without -p twinswarm-py)."
fi
echo "python package: $(grep -cE '^ *Compiling ' "$py_build_log" || true) crates compiled"

say "python: independent clients and peers (tests/python: eclipse-zenoh, mcap, ivy-python, Paparazzi, NPS)"
# Two workers (pytest-xdist): most of these tests wait on real time (real-time runs, buses,
# timeouts), so two at once take about the time of the longest file, test_nps.py (its aircraft
# builds and lockstep flights). --dist loadfile keeps each file on one worker (test_nps.py's
# tests share one Paparazzi tree; conftest.py refuses other modes and starts with test_nps.py).
pytest_status=0
TWINSWARM_BIN="$PWD/target/debug/twinswarm" .venv/bin/python -m pytest -q --durations=12 \
  -n 2 --dist loadfile --no-loadscope-reorder tests/python || pytest_status=$?
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
