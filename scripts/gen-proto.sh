#!/usr/bin/env bash
# Compiles crates/bridge/proto/twinswarm.proto into the descriptor set every log embeds
# (crates/bridge/proto/twinswarm.fds, imports included, no source info), with the protoc of
# PyPI grpcio-tools (pinned in tests/python/requirements.txt). Run it after editing the
# .proto; tests/python/test_mcap_log.py checks the two agree.
#
#   scripts/gen-proto.sh [OUT.fds]
set -euo pipefail
cd "$(dirname "$0")/.."
py=${PYTHON:-.venv/bin/python}
out=${1:-crates/bridge/proto/twinswarm.fds}
"$py" -m grpc_tools.protoc -Icrates/bridge/proto --include_imports \
  --descriptor_set_out="$out" crates/bridge/proto/twinswarm.proto
