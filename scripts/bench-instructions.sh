#!/usr/bin/env bash
# Instructions one step loop executes at two commits, side by side: sim-core's
# `examples/model_cost`, built at each commit from a temporary worktree, run under valgrind's
# cachegrind. A count, not a time: the same on a busy host as on a quiet one, so it resolves
# changes of a few percent that the wall clock here cannot (the host's speed moves by up to
# 1.6× within an hour). It counts work, not latency: a division and an addition are one
# instruction each, so a change that shortens dependency chains shows only in the timings.
#
#   scripts/bench-instructions.sh BASE [HEAD] [-- model_cost args]
#   scripts/bench-instructions.sh 7efa6d9                   # 1000 10 dense takeoff, against HEAD
#   scripts/bench-instructions.sh 7efa6d9 HEAD -- 100 10 dense takeoff
#
# Both runs fly the same scene from the same seed; where a commit changes the bits, the swarms
# part ways as the run goes (their crash counts are printed beside the counts).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
base=${1:?usage: scripts/bench-instructions.sh BASE [HEAD] [-- model_cost args]}
shift
head=HEAD
if [ $# -gt 0 ] && [ "$1" != "--" ]; then
    head=$1
    shift
fi
[ "${1:-}" != "--" ] || shift
args=("$@")
[ ${#args[@]} -gt 0 ] || args=(1000 10 dense takeoff)
command -v valgrind >/dev/null || { echo "bench-instructions: needs valgrind (apt install valgrind)" >&2; exit 1; }

out=$(mktemp -d)
worktrees=()
cleanup() {
    for wt in "${worktrees[@]}"; do git worktree remove --force "$wt" 2>/dev/null || true; done
    rm -rf "$out"
}
trap cleanup EXIT

# Each commit's own model_cost (older commits may lack flags this one has); the dependencies
# are built once, in this checkout's target directory.
bins=()
for rev in "$base" "$head"; do
    sha=$(git rev-parse --short "$rev")
    wt="$out/wt-$sha"
    git worktree add --quiet --detach "$wt" "$sha"
    worktrees+=("$wt")
    [ -f "$wt/crates/sim-core/examples/model_cost.rs" ] \
        || { echo "bench-instructions: $sha has no crates/sim-core/examples/model_cost.rs" >&2; exit 1; }
    (cd "$wt" && CARGO_TARGET_DIR="$root/target" cargo build --release --locked --quiet -p sim-core --example model_cost)
    cp "$root/target/release/examples/model_cost" "$out/model_cost-$sha"
    bins+=("$sha")
done

# Both at once (one core each); cachegrind's count does not depend on what runs beside it.
for sha in "${bins[@]}"; do
    valgrind --tool=cachegrind --cache-sim=no --cachegrind-out-file="$out/cg-$sha.out" \
        "$out/model_cost-$sha" "${args[@]}" >"$out/run-$sha.json" 2>"$out/vg-$sha.txt" &
done
wait

echo "scripts/bench-instructions.sh $base $head -- ${args[*]}  ($(date -u +%F))"
printf '%-10s %18s %10s  %s\n' commit instructions crashed digest
declare -A ir
for sha in "${bins[@]}"; do
    ir[$sha]=$(grep -E 'I +refs:' "$out/vg-$sha.txt" | tr -d ',' | awk '{print $NF}')
    crashed=$(sed -E 's/.*"crashed": ([0-9]+).*/\1/' "$out/run-$sha.json")
    digest=$(sed -E 's/.*"digest": "([0-9a-f]+)".*/\1/' "$out/run-$sha.json")
    printf '%-10s %18s %10s  %s\n' "$sha" "${ir[$sha]}" "$crashed" "$digest"
done
awk -v a="${ir[${bins[0]}]}" -v b="${ir[${bins[1]}]}" \
    'BEGIN { printf "%s / %s: %.3f (%+.1f %% instructions)\n", "head", "base", b / a, 100 * (b - a) / a }'
