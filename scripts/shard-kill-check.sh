#!/usr/bin/env bash
# One process against a sharded cluster with one shard killed and restarted from its
# checkpoint: every copter must end with the one-process digest (docs/sharding.md).
#   scripts/shard-kill-check.sh [KIND] [N] [SECONDS] [SHARDS] [SEED]
# KIND is a `twinswarm scene` kind (dense: the take-off among pillars; boxes: among boxes).
# Defaults: dense 2000 60 2 5. Shard 1 is SIGKILLed once a checkpoint of every shard exists.
set -euo pipefail
cd "$(dirname "$0")/.."
kind=${1:-dense} n=${2:-2000} secs=${3:-60} shards=${4:-2} seed=${5:-5}
bin=${TWINSWARM_BIN:-target/release/twinswarm}
[ -x "$bin" ] || cargo build --release -p twinswarm
work=target/shard-kill-check/$kind-$n-$secs-$shards-$seed
rm -rf "$work" && mkdir -p "$work"
"$bin" scene "$kind" --n "$n" --seed "$seed" > "$work/scene.toml"
every=$(( secs / 4 ))

# "ID DIGEST" per copter, in id order; fails unless there are as many as the scene has (`boxes`
# leaves out the copters that would start on a box).
copters=$(grep -c '^\[\[copter\]\]' "$work/scene.toml")
digests() {
    python3 - "$1" "$copters" <<'PY'
import json, sys
copters = json.load(open(sys.argv[1]))["copters"]
assert len(copters) == int(sys.argv[2]), f"{sys.argv[1]}: {len(copters)} copters, expected {sys.argv[2]}"
for c in sorted(copters, key=lambda c: c["id"]):
    print(c["id"], c["digest"])
PY
}

"$bin" run "$work/scene.toml" --no-bus --no-log --duration "$secs" --json > "$work/one.json"
"$bin" cluster "$work/scene.toml" --shards "$shards" --no-bus --duration "$secs" --json \
    --log-dir "$work/logs" --checkpoint-every "$every" --checkpoint-dir "$work/ckpt" \
    > "$work/cluster.json" 2> "$work/cluster.err" &
cluster=$!
victim=""
while kill -0 "$cluster" 2>/dev/null; do
    have=$(ls "$work/ckpt" 2>/dev/null | grep -c "tick" || true)
    if [ -z "$victim" ] && [ "$have" -ge "$shards" ]; then
        victim=$(sed -n "s|^cluster: shard 1/$shards started, pid \([0-9]*\).*|\1|p" "$work/cluster.err" | head -1)
        kill -9 "$victim" && echo "killed shard 1/$shards (pid $victim) with $have checkpoints on disk"
    fi
    sleep 0.5
done
wait "$cluster" || { cat "$work/cluster.err" >&2; exit 1; }
restarts=$(python3 -c 'import json,sys; print(len(json.load(open(sys.argv[1])).get("restarts", [])))' "$work/cluster.json")
digests "$work/one.json" > "$work/one.txt"
digests "$work/cluster.json" > "$work/cluster.txt"
differ=$(diff "$work/one.txt" "$work/cluster.txt" | grep -c '^<' || true)
echo "$kind n $n ${secs} s seed $seed: $shards shards, restarts $restarts, copters differing from one process: $differ"
[ -n "$victim" ] && [ "$restarts" -ge 1 ] && [ "$differ" -eq 0 ]  # the files stay in $work
