#!/usr/bin/env bash
# Run the cargo-fuzz targets of fuzz/ (interp, config, eds, frames).
#
#   scripts/fuzz.sh [SECONDS] [TARGET...]   each target for SECONDS (default 30), all by default
#   scripts/fuzz.sh --minimize [TARGET...]  merge what fuzzing found into fuzz/corpus/TARGET,
#                                           minimized (cargo fuzz cmin), to commit
#
# Stable toolchain: `cargo fuzz … -s none` (coverage instrumentation only, no sanitizer) needs
# no nightly flags; the targets are safe Rust, so panics (including integer overflow: debug
# assertions are on) are what they find. On nightly, FUZZ_SANITIZER=address adds ASan.
# cargo-fuzz itself comes from scripts/install-test-deps.sh.
#
# Corpora: fuzz/corpus/TARGET (committed, read here) and build/fuzz-corpus/TARGET (where
# libFuzzer writes new inputs; not committed). A crash input is copied to
# fuzz/crashes/TARGET/, which tests/interp/fuzz_regress.rs replays in the normal suite: commit it
# with the fix. With CNCGW_REPORT_DIR set, one line per target goes to
# $CNCGW_REPORT_DIR/fuzz.jsonl: {"target", "seconds", "executions", "crashes"}.
#
# Exit status: 0 when no target crashed, 1 otherwise.
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
SAN=${FUZZ_SANITIZER:-none}
MINIMIZE=0
SECS=30
if [ "${1:-}" = --minimize ]; then
    MINIMIZE=1
    shift
elif [[ "${1:-}" =~ ^[0-9]+$ ]]; then
    SECS=$1
    shift
fi

cd "$ROOT/fuzz"
command -v cargo-fuzz >/dev/null 2>&1 || {
    echo "fuzz.sh: cargo-fuzz is not installed: run scripts/install-test-deps.sh (or cargo install cargo-fuzz)" >&2
    exit 2
}
TARGETS=("$@")
if [ ${#TARGETS[@]} -eq 0 ]; then
    mapfile -t TARGETS < <(cargo fuzz list)
fi

echo "fuzz.sh: building ${TARGETS[*]} (sanitizer: $SAN)" >&2
cargo fuzz build -s "$SAN" >&2

if [ "$MINIMIZE" = 1 ]; then
    for t in "${TARGETS[@]}"; do
        mkdir -p "$ROOT/build/fuzz-corpus/$t" "corpus/$t"
        out=$(mktemp -d)
        cargo fuzz run -s "$SAN" "$t" "$out" "corpus/$t" "$ROOT/build/fuzz-corpus/$t" -- \
            -set_cover_merge=1 -rss_limit_mb=2048 -max_len=4096 -timeout=10 >"$ROOT/build/fuzz-$t-merge.log" 2>&1
        # Named seeds (with an extension: the examples, config/*.toml…) stay as they are;
        # libFuzzer names its inputs by the SHA-1 of their content, so drop the seeds' copies.
        for s in corpus/"$t"/*.*; do
            [ -e "$s" ] && rm -f "$out/$(sha1sum <"$s" | cut -d' ' -f1)"
        done
        find "corpus/$t" -maxdepth 1 -type f ! -name '*.*' -delete
        cp "$out"/* "corpus/$t"/ 2>/dev/null || true
        rm -rf "$out"
        echo "$t: $(ls "corpus/$t" | wc -l) inputs, $(du -sh --apparent-size "corpus/$t" | cut -f1)" >&2
    done
    exit 0
fi

status=0
for t in "${TARGETS[@]}"; do
    mkdir -p "$ROOT/build/fuzz-corpus/$t" "artifacts/$t"
    log="$ROOT/build/fuzz-$t.log"
    echo "== fuzzing $t for ${SECS}s" >&2
    # One job (the machine is shared); -timeout: an input taking 10 s is a hang, reported.
    set +e
    cargo fuzz run -s "$SAN" "$t" "$ROOT/build/fuzz-corpus/$t" "corpus/$t" -- \
        -max_total_time="$SECS" -timeout=10 -rss_limit_mb=2048 -max_len=4096 \
        -print_final_stats=1 >"$log" 2>&1
    rc=$?
    set -e
    crashes=0
    for f in artifacts/"$t"/crash-* artifacts/"$t"/oom-* artifacts/"$t"/timeout-* artifacts/"$t"/slow-unit-*; do
        [ -e "$f" ] || continue
        mkdir -p "crashes/$t"
        cp "$f" "crashes/$t/"
        rm -f "$f"
        crashes=$((crashes + 1))
        echo "$t: crash input kept as fuzz/crashes/$t/$(basename "$f")" >&2
    done
    if [ "$rc" != 0 ] && [ "$crashes" = 0 ]; then
        crashes=1   # libFuzzer failed without an artifact: count it, show the log
    fi
    execs=$(awk '/stat::number_of_executed_units/ { print $2 }' "$log" | tail -1)
    rate=$(awk '/stat::average_exec_per_sec/ { print $2 }' "$log" | tail -1)
    echo "$t: ${execs:-0} executions in ${SECS}s (${rate:-?}/s), crashes: $crashes" >&2
    if [ "$crashes" != 0 ]; then
        status=1
        grep -E 'panicked|ERROR: libFuzzer|SUMMARY|deadly signal' "$log" | head -5 >&2 || tail -20 "$log" >&2
    fi
    if [ -n "${CNCGW_REPORT_DIR:-}" ]; then
        mkdir -p "$CNCGW_REPORT_DIR"
        printf '{"target":"%s","seconds":%s,"executions":%s,"crashes":%s}\n' \
            "$t" "$SECS" "${execs:-0}" "$crashes" >>"$CNCGW_REPORT_DIR/fuzz.jsonl"
    fi
done
exit $status
