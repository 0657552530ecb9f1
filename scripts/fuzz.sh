#!/usr/bin/env bash
# Run every cargo-fuzz target of fuzz/ for SECONDS each (default 30).
#
#   scripts/fuzz.sh [SECONDS]
#
# Installs cargo-fuzz from crates.io when missing. cargo-fuzz needs nightly compiler flags
# (-Zsanitizer); on the stable toolchain RUSTC_BOOTSTRAP=1 unlocks them. The corpus lives in
# fuzz/corpus/TARGET (the committed seeds are the *.nc files there; what libFuzzer adds is
# git-ignored). A crash input is copied to tests/interp_fuzz_cases/ where
# tests/interp_robust.rs replays it in the normal test suite; commit it with the fix.
set -euo pipefail

SECS=${1:-30}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT/fuzz"

if ! cargo fuzz --version >/dev/null 2>&1; then
    echo "installing cargo-fuzz…" >&2
    cargo install cargo-fuzz
fi
export RUSTC_BOOTSTRAP=1

status=0
for target in $(cargo fuzz list); do
    mkdir -p "corpus/$target" "artifacts/$target"
    echo "== fuzzing $target for ${SECS}s" >&2
    log="artifacts/$target/last-run.log"
    # -jobs/-workers 1: the machine is shared. rss_limit guards against runaway memory.
    if cargo fuzz run "$target" "corpus/$target" -- \
        -max_total_time="$SECS" -rss_limit_mb=2048 -max_len=4096 -print_final_stats=1 2>&1 | tee "$log" | grep -E '^(#[0-9]+ +DONE|stat::number_of_executed_units|stat::average_exec_per_sec|==[0-9]+==|SUMMARY|thread .* panicked)' >&2; then
        :
    fi
    if grep -qE 'panicked|SUMMARY: |deadly signal|ERROR: libFuzzer' "$log"; then
        status=1
        mkdir -p "$ROOT/tests/interp_fuzz_cases"
        for f in artifacts/"$target"/crash-* artifacts/"$target"/oom-* artifacts/"$target"/timeout-*; do
            [ -e "$f" ] || continue
            cp "$f" "$ROOT/tests/interp_fuzz_cases/$target-$(basename "$f").nc"
            echo "crash input saved as tests/interp_fuzz_cases/$target-$(basename "$f").nc" >&2
        done
    fi
    execs=$(awk '/stat::number_of_executed_units/ { print $2 }' "$log" | tail -1)
    rate=$(awk '/stat::average_exec_per_sec/ { print $2 }' "$log" | tail -1)
    echo "$target: ${execs:-?} executions in ${SECS}s, ${rate:-?} exec/s" >&2
done
exit $status
