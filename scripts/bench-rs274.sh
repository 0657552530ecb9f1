#!/usr/bin/env bash
# Throughput of `cncgw plan` against LinuxCNC's standalone interpreter `rs274 -g` on the same
# G1 program (the shared subset: G21, then `G1 X.. Z.. F..` lines, absolute, metric), run
# side by side in one invocation. Prints blocks/s and peak RSS of both and the ratio.
#
#   scripts/bench-rs274.sh [BLOCKS]      (default 1000000)
#
# Installs Debian's linuxcnc-uspace (which ships /usr/bin/rs274) when rs274 is missing; never
# part of the test suite. Both programs write their output to /dev/null. `G98` in the header
# is per-minute feed for cncgw and the canned-cycle return level (a no-op here) for LinuxCNC.
set -euo pipefail

N=${1:-1000000}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
WORK=${TMPDIR:-/tmp}/cncgw-bench-rs274
mkdir -p "$WORK"

if ! command -v rs274 >/dev/null 2>&1; then
    echo "rs274 not found: installing linuxcnc-uspace" >&2
    if ! apt-cache policy linuxcnc-uspace 2>/dev/null | grep -q 'Candidate: [0-9]'; then
        echo "linuxcnc-uspace is not available from apt here; candidates:" >&2
        apt-cache search rs274 >&2 || true
        exit 1
    fi
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO=sudo
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y --no-install-recommends linuxcnc-uspace >&2
fi
[ -x /usr/bin/time ] || { echo "/usr/bin/time (package 'time') is needed for peak RSS" >&2; exit 1; }

echo "building cncgw (release)…" >&2
(cd "$ROOT" && cargo build --release -q --bin cncgw)
CNCGW="$ROOT/target/release/cncgw"

PROG="$WORK/g1_$N.ngc"
if [ ! -s "$PROG" ]; then
    awk -v n="$N" 'BEGIN {
        print "G21"; print "G98";
        for (i = 0; i < n; i++) {
            printf "G1 X%.3f Z%.3f F%d\n", 20 + (i % 400) * 0.05, -((i % 1000) * 0.025), 100 + (i % 7) * 50;
        }
        print "M30";
    }' > "$PROG"
fi
BLOCKS=$((N + 3))

# run NAME CMD… → prints "NAME seconds rss_kb"
measure() {
    local name=$1; shift
    local log="$WORK/$name.time"
    /usr/bin/time -v "$@" > /dev/null 2> "$log" || { echo "$name failed:" >&2; tail -5 "$log" >&2; exit 1; }
    local wall rss
    wall=$(awk -F': ' '/Elapsed \(wall clock\)/ { n = split($2, t, ":"); s = 0; for (i = 1; i <= n; i++) s = s * 60 + t[i]; print s }' "$log")
    rss=$(awk -F': ' '/Maximum resident set size/ { print $2 }' "$log")
    echo "$name $wall $rss"
}

# Warm the page cache so that neither pays for reading the file from disk.
cat "$PROG" > /dev/null

read -r _ t_rs rss_rs < <(measure rs274 rs274 -g "$PROG" /dev/null)
read -r _ t_us rss_us < <(measure cncgw "$CNCGW" plan "$PROG" --format jsonl)

awk -v b="$BLOCKS" -v tr="$t_rs" -v rr="$rss_rs" -v tu="$t_us" -v ru="$rss_us" 'BEGIN {
    if (tr <= 0) tr = 0.01; if (tu <= 0) tu = 0.01;
    printf "program: %d blocks of G1 X Z F\n", b;
    printf "%-14s %12s %10s %12s\n", "", "blocks/s", "wall s", "peak RSS MB";
    printf "%-14s %12.0f %10.2f %12.1f\n", "rs274 -g", b / tr, tr, rr / 1024;
    printf "%-14s %12.0f %10.2f %12.1f\n", "cncgw plan", b / tu, tu, ru / 1024;
    printf "throughput ratio cncgw/rs274: %.1fx (goal >= 10x)\n", tr / tu;
}'
