#!/usr/bin/env bash
# Throughput of `cncgw plan` against LinuxCNC's standalone interpreter `rs274 -g` on the same
# G1 program (the shared subset: G21, then `G1 X.. Z.. F..` lines, absolute, metric), run
# side by side in one invocation. Prints blocks/s (by CPU time and by wall time), peak RSS of
# both and the ratio, and the peak RSS of both on a program a tenth as long (cncgw streams the
# file: its memory does not grow with the program's length).
#
#   scripts/bench-rs274.sh [BLOCKS]      (default 1000000)
#
# Measured 2026-11-22 on this 2-core machine (load ≈ 1.1; rs274 runs at 93 000–104 000
# blocks/s here, not the ≈ 280 000 the issue quotes), median of 3 interleaved rounds:
#                 blocks/s (CPU)  CPU s   peak RSS 1M / 100k blocks
#   rs274 -g           93 458     10.70   16.0 / 15.8 MB
#   cncgw plan      1 000 003      1.00    6.0 /  6.0 MB   → 10.7× (10.6× by wall time)
#     production    1 265 827      0.79    5.2 MB          → 13.5× (release + fat LTO)
#   interpreter     1 428 576      0.70    3.3 MB          → 15.3× (file bytes → moves, no output)
# (before streaming: cncgw plan 3.7× by CPU time, 36.5 MB peak RSS growing with the length;
# before the block decoder's memo and the byte parser's rewrite: 8.3×.)
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

echo "building cncgw (release, and production = release + fat LTO)…" >&2
(cd "$ROOT" && cargo build --release -q --bin cncgw --example interp_throughput && cargo build --profile production -q --bin cncgw)
CNCGW="$ROOT/target/release/cncgw"
CNCGW_LTO="$ROOT/target/production/cncgw"
INTERP="$ROOT/target/release/examples/interp_throughput"

gen() { # gen BLOCKS FILE
    [ -s "$2" ] && return 0
    awk -v n="$1" 'BEGIN {
        print "G21"; print "G98";
        for (i = 0; i < n; i++) {
            printf "G1 X%.3f Z%.3f F%d\n", 20 + (i % 400) * 0.05, -((i % 1000) * 0.025), 100 + (i % 7) * 50;
        }
        print "M30";
    }' > "$2"
}
PROG="$WORK/g1_$N.ngc"
gen "$N" "$PROG"
BLOCKS=$((N + 3))
# A program a tenth as long, to show that peak memory does not grow with the length.
N10=$((N / 10))
PROG10="$WORK/g1_$N10.ngc"
gen "$N10" "$PROG10"

# measure NAME CMD… → prints "wall_s cpu_s rss_kb" (cpu = user + system: on a machine shared
# with other work the wall time also counts the time spent waiting for a core).
measure() {
    local name=$1; shift
    local log="$WORK/$name.time"
    /usr/bin/time -v "$@" > /dev/null 2> "$log" || { echo "$name failed:" >&2; tail -5 "$log" >&2; exit 1; }
    awk -F': ' '
        /Elapsed \(wall clock\)/ { n = split($2, t, ":"); s = 0; for (i = 1; i <= n; i++) s = s * 60 + t[i]; wall = s }
        /User time/ { cpu += $2 } /System time/ { cpu += $2 }
        /Maximum resident set size/ { rss = $2 }
        END { print wall, cpu, rss }' "$log"
}

# Warm the page cache so that neither pays for reading the file from disk.
cat "$PROG" "$PROG10" > /dev/null

# ROUNDS rounds, the three programs one after the other in each (so that a change of load
# hits all of them alike); each one's median round is reported.
ROUNDS=${ROUNDS:-3}
: > "$WORK/rounds"
for r in $(seq "$ROUNDS"); do
    echo "rs274 $(measure rs274 rs274 -g "$PROG" /dev/null)" >> "$WORK/rounds"
    echo "cncgw $(measure cncgw "$CNCGW" plan "$PROG" --format jsonl)" >> "$WORK/rounds"
    echo "cncgwp $(measure cncgwp "$CNCGW_LTO" plan "$PROG" --format jsonl)" >> "$WORK/rounds"
    echo "interp $(measure interp "$INTERP" "$PROG")" >> "$WORK/rounds"
done
# median NAME → "wall_s cpu_s rss_kb" of the round with the median CPU time
median() {
    grep "^$1 " "$WORK/rounds" | sort -k3 -g | awk -v n="$ROUNDS" 'NR == int((n + 1) / 2) { print $2, $3, $4 }'
}
echo "CPU seconds per round:" >&2
for t in rs274 cncgw cncgwp interp; do
    echo "  $t: $(grep "^$t " "$WORK/rounds" | awk '{ printf "%s ", $3 }')" >&2
done
read -r w_rs c_rs rss_rs < <(median rs274)
read -r w_us c_us rss_us < <(median cncgw)
read -r w_up c_up rss_up < <(median cncgwp)
read -r w_in c_in rss_in < <(median interp)
read -r _ _ rss_rs10 < <(measure rs274_10 rs274 -g "$PROG10" /dev/null)
read -r _ _ rss_us10 < <(measure cncgw_10 "$CNCGW" plan "$PROG10" --format jsonl)

awk -v b="$BLOCKS" -v wr="$w_rs" -v cr="$c_rs" -v rr="$rss_rs" -v wu="$w_us" -v cu="$c_us" -v ru="$rss_us" \
    -v rr10="$rss_rs10" -v ru10="$rss_us10" -v wp="$w_up" -v cp="$c_up" -v rp="$rss_up" -v n10="$((N10 + 3))" -v wi="$w_in" -v ci="$c_in" -v ri="$rss_in" 'BEGIN {
    if (wi <= 0) wi = 0.01; if (ci <= 0) ci = 0.01;
    if (wr <= 0) wr = 0.01; if (wu <= 0) wu = 0.01; if (cr <= 0) cr = 0.01; if (cu <= 0) cu = 0.01;
    printf "program: %d blocks of G1 X Z F (output to /dev/null; cncgw: plan --format jsonl); median of the rounds\n", b;
    printf "%-12s %14s %14s %8s %8s %14s %14s\n", "", "blocks/s cpu", "blocks/s wall", "cpu s", "wall s", "RSS MB", "RSS MB (1/10)";
    printf "%-12s %14.0f %14.0f %8.2f %8.2f %14.1f %14.1f\n", "rs274 -g", b / cr, b / wr, cr, wr, rr / 1024, rr10 / 1024;
    if (wp <= 0) wp = 0.01; if (cp <= 0) cp = 0.01;
    printf "%-12s %14.0f %14.0f %8.2f %8.2f %14.1f %14.1f\n", "cncgw plan", b / cu, b / wu, cu, wu, ru / 1024, ru10 / 1024;
    printf "%-12s %14.0f %14.0f %8.2f %8.2f %14.1f\n", "  production", b / cp, b / wp, cp, wp, rp / 1024;
    printf "%-12s %14.0f %14.0f %8.2f %8.2f %14.1f\n", "interpreter", b / ci, b / wi, ci, wi, ri / 1024;
    printf "(interpreter = file bytes to canonical moves without output: examples/interp_throughput.rs)\n";
    printf "throughput ratio cncgw plan/rs274: %.1fx by CPU time, %.1fx by wall time (goal >= 10x; release build)\n", cr / cu, wr / wu;
    printf "throughput ratio cncgw plan/rs274: %.1fx by CPU time, %.1fx by wall time (production build: release + fat LTO)\n", cr / cp, wr / wp;
    printf "throughput ratio interpreter/rs274: %.1fx by CPU time, %.1fx by wall time\n", cr / ci, wr / wi;
    printf "peak RSS: cncgw %.1f MB for %d blocks, %.1f MB for %d blocks\n", ru / 1024, b, ru10 / 1024, n10;
}'
