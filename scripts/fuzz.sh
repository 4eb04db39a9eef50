#!/usr/bin/env bash
# Fuzzes the four input readers with cargo-fuzz (libFuzzer; needs the nightly toolchain):
#   weights_bytes  safetensors bytes → Matcher (and a small match)
#   pair_file      features pair file bytes → Features
#   image_bytes    encoded image bytes → XFeat keypoints
#   config_json    config JSON → Config (small valid ones build and match)
# Usage: bash scripts/fuzz.sh [SECONDS_PER_TARGET | -runs=N] [TARGET ...]
#   bash scripts/fuzz.sh 1800                 # the budget of the reliability issue
#   bash scripts/fuzz.sh -runs=1000000 config_json
# Seeds are committed in fuzz/corpus/<target>; new inputs go to fuzz/work/<target>
# (ignored); a crash is written to fuzz/artifacts/<target>/ and fails the script.
set -euo pipefail
cd "$(dirname "$0")/../fuzz"
budget=${1:-60}
shift || true
targets=("$@")
[ ${#targets[@]} -eq 0 ] && targets=(weights_bytes pair_file image_bytes config_json)
if [[ "$budget" == -runs=* ]]; then limit=("$budget"); else limit=(-max_total_time="$budget"); fi
for t in "${targets[@]}"; do
  mkdir -p "work/$t" "artifacts/$t"
  echo "== $t (${limit[*]}, RSS limit 2048 MB)"
  log="work/$t.log"
  status=0
  cargo +nightly fuzz run --release "$t" "work/$t" "corpus/$t" -- "${limit[@]}" -rss_limit_mb=2048 \
    -timeout=30 -artifact_prefix="artifacts/$t/" -print_final_stats=1 > "$log" 2>&1 || status=$?
  grep -E "^(stat::number_of_executed_units|stat::peak_rss_mb|Done [0-9]+ runs|SUMMARY)" "$log" || true
  if [ "$status" -ne 0 ] || ls "artifacts/$t"/crash-* "artifacts/$t"/oom-* "artifacts/$t"/timeout-* >/dev/null 2>&1; then
    echo "FAILED: $t (exit $status); the end of $log:" >&2
    tail -30 "$log" >&2
    exit 1
  fi
done
