#!/usr/bin/env bash
# A screenshot of Foxglove Studio showing a live twinswarm run (docs/foxglove-live.png).
#
#   scripts/foxglove-shot/run.sh [TWINSWARM_BINARY] [OUT.png]
#
# Foxglove Studio here is the prebuilt browser bundle that the npm package
# @foxglove/studio-base@1.48.0 (MPL-2.0, the last open-source Studio) ships in assets/; index.html
# and main.js mount its <App> the way upstream's studio-web does. Needs Node.js with npm and
# Debian's chromium (apt-get install chromium). Everything listens on 127.0.0.1.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
bin="${1:-$root/target/release/twinswarm}"
out="${2:-$root/docs/foxglove-live.png}"
work="${FOXGLOVE_SHOT_DIR:-${TMPDIR:-/tmp}/twinswarm-foxglove-shot}"
[ -x "$bin" ] || { echo "no twinswarm binary at $bin (cargo build --release)" >&2; exit 1; }
[ -x "${CHROMIUM:-/usr/bin/chromium}" ] || { echo "no chromium: apt-get install chromium" >&2; exit 1; }

mkdir -p "$work/web"
cp "$here/package.json" "$here/index.html" "$here/main.js" "$here/shot.mjs" "$work/"
cp "$here/index.html" "$here/main.js" "$work/web/"
(cd "$work" && npm install --no-audit --no-fund --loglevel=error >/dev/null)
if [ ! -d "$work/studio-base/package/assets" ]; then
  mkdir -p "$work/studio-base"
  (cd "$work/studio-base" && npm pack --silent @foxglove/studio-base@1.48.0 >/dev/null && tar xzf foxglove-studio-base-1.48.0.tgz)
fi
ln -sfn "$work/studio-base/package/assets" "$work/web/assets"
cp "$work/node_modules/react/umd/react.production.min.js" "$work/node_modules/react-dom/umd/react-dom.production.min.js" "$work/web/"

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
http_port="$(free_port)"
ws_port="$(free_port)"
python3 "$here/serve.py" "$work/web" "$http_port" &
server=$!
"$bin" run --realtime --no-bus --no-log --foxglove "127.0.0.1:$ws_port" --duration 600 >"$work/run.log" 2>&1 &
run=$!
trap 'kill $server $run 2>/dev/null || true' EXIT
sleep 2
(cd "$work" && node shot.mjs "http://127.0.0.1:$http_port" "ws://127.0.0.1:$ws_port" "$out")
