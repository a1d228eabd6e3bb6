#!/usr/bin/env bash
# Seeds the corpus from the measured files and runs every fuzz target for RUNS executions
# (default 10^6), one after the other; libFuzzer's final statistics go to logs/<target>.log
# and a one-line summary per target to logs/summary.txt.
#
#   cd fuzz && ./run.sh [RUNS] [TARGET...]
#
# Needs cargo-fuzz (`cargo install cargo-fuzz`) and a nightly toolchain. On stable only,
# `cargo fuzz run -s none ...` builds without sanitizers (add `+stable` and `-s none` below).
set -euo pipefail
cd "$(dirname "$0")"
RUNS=${1:-1000000}
shift || true
TARGETS=("$@")
[ ${#TARGETS[@]} -eq 0 ] && TARGETS=(sxm sm4 iso28600 raw gsf read_any)
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-/work/target-fuzz}
MEASURED=${MEASURED:-../../shared/data/measured}
mkdir -p logs
cargo +nightly run --quiet --release --bin seed -- "$MEASURED" corpus
for t in "${TARGETS[@]}"; do
    start=$(date +%s)
    status=0
    cargo +nightly fuzz run -O "$t" "corpus/$t" -- \
        -runs="$RUNS" -max_len=16384 -rss_limit_mb=2048 -timeout=10 -print_final_stats=1 \
        > "logs/$t.log" 2>&1 || status=$?
    end=$(date +%s)
    execs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "logs/$t.log" | grep -o '[0-9]*$' || echo '?')
    crashes=$(ls "artifacts/$t" 2>/dev/null | grep -c '^crash-\|^oom-\|^timeout-' || true)
    echo "$t execs=$execs seconds=$((end - start)) exit=$status artifacts=$crashes" | tee -a logs/summary.txt
done
