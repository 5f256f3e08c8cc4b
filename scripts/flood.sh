#!/usr/bin/env bash
# The flood test at full length, on a release build:
#
#   scripts/flood.sh [SECONDS] [RATE]      (default 60 s at 10,000 per second per stream)
#
# `twinswarm run --realtime` with 100 copters and two twins, logging, on Zenoh and on an Ivy
# bus (loopback), while the test sends RATE commands/s on Zenoh and RATE Paparazzi texts/s on
# Zenoh and on Ivy (crates/cli/tests/flood.rs). Prints one line: every input accounted for
# (accepted, rejected, ignored, dropped), overruns, RSS at the start and the end. CI runs the
# same test for 5 s on the debug build.
set -euo pipefail
cd "$(dirname "$0")/.."
secs="${1:-60}"
rate="${2:-10000}"
cargo test --release --locked -p twinswarm --test flood --no-run
FLOOD_SECONDS="$secs" FLOOD_RATE="$rate" \
  cargo test --release --locked -p twinswarm --test flood -- --nocapture 2>&1 | grep -E '^flood|test result|panicked|assert'
