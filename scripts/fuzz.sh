#!/usr/bin/env bash
# Coverage-guided fuzzing of every input path with AFL++, on stable Rust.
#
#   scripts/fuzz.sh [EXECS_PER_TARGET] [TARGET...]
#
# Default: 1,000,000 executions for each target of crates/fuzz (scene, messages_xml, conf_xml,
# pairing_xml, telemetry_xml, ivy_text, ivy_wire, zenoh_json, mcap, plot, log, log_merge,
# foxglove_client, ghost_batch, pprz_log), one after the other on one core. Prints one line per target
# (executions, corpus size, crashes, hangs), writes it to target/afl/report.tsv, and appends
# it, with the commit fuzzed and the date, to the record in crates/fuzz/RESULTS.md.
#
# How: Debian's afl++ (apt-get install afl++) provides afl-fuzz and its compiler runtime;
# rustc's own SanitizerCoverage pass (stable flags) instruments the code, the way cargo-afl
# does; the `afl` crate gives the persistent-mode loop. The corpus of each run is merged
# back into crates/fuzz/corpus/<target> (minimised with afl-cmin) so that CI's smoke pass
# (`cargo test -p twinswarm-fuzz`) replays it. Every crash and hang is copied into
# crates/fuzz/regressions/<target>/ (the smoke pass then fails on it until it is fixed).
set -euo pipefail
cd "$(dirname "$0")/.."

execs="${1:-1000000}"
shift || true
all=(scene messages_xml conf_xml pairing_xml telemetry_xml ivy_text ivy_wire zenoh_json mcap plot log log_merge
  foxglove_client ghost_batch pprz_log)
targets=("$@")
[ "${#targets[@]}" -gt 0 ] || targets=("${all[@]}")

if ! command -v afl-fuzz >/dev/null; then
  echo "afl-fuzz not found: installing Debian's afl++"
  apt-get install -y afl++ >/dev/null
fi
rt_obj=/usr/lib/afl/afl-compiler-rt.o
[ -f "$rt_obj" ] || { echo "error: $rt_obj missing (afl++ from Debian expected)" >&2; exit 1; }

work="${FUZZ_WORK:-target/afl}"
mkdir -p "$work/rt"
ar rcs "$work/rt/libafl-llvm-rt.a" "$rt_obj"

# The code fuzzed: the commit checked out when the harness is built.
# (What this script writes itself, the record, corpora and regressions, does not count as a change.)
commit="$(git rev-parse --short HEAD)$(git diff --quiet HEAD -- crates scripts Cargo.lock ':!crates/fuzz/RESULTS.md' \
  ':!crates/fuzz/corpus' ':!crates/fuzz/regressions' || echo -dirty)"
echo "==> building the instrumented harness (release, sancov, $work) at $commit"
RUSTFLAGS="--cfg fuzzing -C debug-assertions -C overflow-checks \
  -C passes=sancov-module -C llvm-args=-sanitizer-coverage-level=3 \
  -C llvm-args=-sanitizer-coverage-trace-pc-guard -C llvm-args=-sanitizer-coverage-prune-blocks=0 \
  -C llvm-args=-sanitizer-coverage-trace-compares \
  -L $PWD/$work/rt -l static=afl-llvm-rt" \
  cargo build --release --locked -p twinswarm-fuzz --features afl --bin twinswarm-afl --target-dir "$work/build"
bin="$work/build/release/twinswarm-afl"

# Seeds: the checked-in corpus, the regressions, and the project's own files of each kind.
seeds_of() {
  case "$1" in
    scene) ls assets/scenes/*.toml ;;
    messages_xml) echo assets/paparazzi/messages.xml ;;
    conf_xml) echo assets/paparazzi/conf.xml ;;
    pairing_xml) ls assets/pairing/*.xml ;;
    telemetry_xml) echo assets/paparazzi/telemetry.xml ;;
    plot) ls crates/fuzz/corpus/mcap/* ;;
  esac
  find "crates/fuzz/corpus/$1" "crates/fuzz/regressions/$1" -type f -size +0 2>/dev/null || true
}

# The record: one row per campaign, appended to crates/fuzz/RESULTS.md.
results=crates/fuzz/RESULTS.md
record() {
  printf '| %s | %s | %s | %s | %s | %s | %s | %s | %s |\n' "$1" "$2" "$3" "$(( $2 / ($3 > 0 ? $3 : 1) ))" \
    "$4" "$5" "$6" "$commit" "$(date -u +%Y-%m-%d)" >> "$results"
}

export AFL_SKIP_CPUFREQ=1 AFL_I_DONT_CARE_ABOUT_MISSING_CRASHES=1 AFL_NO_UI=1 AFL_QUIET=1
export AFL_NO_AFFINITY=1 AFL_IGNORE_UNKNOWN_ENVS=1
report="$work/report.tsv"
printf 'target\texecs\tcorpus\tcrashes\thangs\tseconds\texecs_per_s\n' > "$report"
for t in "${targets[@]}"; do
  in="$work/in/$t" out="$work/out/$t"
  rm -rf "$in" "$out"
  mkdir -p "$in" "$work/out"
  seeds_of "$t" | sort -u | while read -r f; do cp "$f" "$in/"; done
  "$bin" --seeds "$t" "$in"
  echo "==> $t: $execs executions from $(ls "$in" | wc -l) seed(s)"
  start=$(date +%s)
  # -E: stop after that many executions; -t: 2 s per input (the file targets read a log).
  afl-fuzz -i "$in" -o "$out" -E "$execs" -t 2000 -m none -- "$bin" "$t" >"$work/$t.log" 2>&1 || {
    echo "afl-fuzz failed on $t; see $work/$t.log" >&2
    tail -20 "$work/$t.log" >&2
    exit 1
  }
  secs=$(( $(date +%s) - start ))
  stats="$out/default/fuzzer_stats"
  get() { awk -F' *: ' -v k="$1" '$1==k {print $2}' "$stats"; }
  done_execs=$(get execs_done)
  corpus=$(get corpus_count)
  crashes=$(get saved_crashes)
  hangs=$(get saved_hangs)
  printf '%s\t%s\t%s\t%s\t%s\t%s\t%s\n' "$t" "$done_execs" "$corpus" "$crashes" "$hangs" "$secs" \
    "$(( done_execs / (secs > 0 ? secs : 1) ))" >> "$report"
  echo "    $done_execs executions in ${secs} s; corpus $corpus; crashes $crashes; hangs $hangs"
  record "$t" "$done_execs" "$secs" "$corpus" "$crashes" "$hangs"
  # Every crash and hang becomes a regression file.
  for kind in crashes hangs; do
    for f in "$out/default/$kind"/id:*; do
      [ -f "$f" ] || continue
      mkdir -p "crates/fuzz/regressions/$t"
      cp "$f" "crates/fuzz/regressions/$t/${kind%es}-$(sha1sum "$f" | cut -c1-16)"
    done
  done
  # Keep the new coverage: minimise the queue into the checked-in corpus (small files only).
  if [ "${FUZZ_KEEP_CORPUS:-1}" = 1 ]; then
    mkdir -p "$work/cmin/$t"
    rm -rf "$work/cmin/$t"
    AFL_PATH=/usr/lib/afl afl-cmin -i "$out/default/queue" -o "$work/cmin/$t" -t 2000 -m none -- "$bin" "$t" \
      >"$work/$t.cmin.log" 2>&1 || true
    # At most 100 files of under 8 KiB each: the smoke pass replays them in CI.
    # (`head` closes the pipe early: no pipefail here.)
    (
      set +o pipefail
      find "$work/cmin/$t" -type f -size -8k -printf '%s %p\n' 2>/dev/null | sort -n | head -100 |
        while read -r _ f; do
          cp "$f" "crates/fuzz/corpus/$t/$(sha1sum "$f" | cut -c1-16)"
        done
    )
  fi
done
echo
column -t "$report"
if awk -F'\t' 'NR>1 && ($4>0 || $5>0) {bad=1} END {exit !bad}' "$report"; then
  echo "crashes or hangs found: see $work/out/<target>/default/{crashes,hangs}" >&2
  exit 1
fi
