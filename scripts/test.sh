#!/usr/bin/env bash
# The whole test suite — the README's test command, and what CI runs.
#
#   ./scripts/test.sh
#
# 1. installs what the tests need on a fresh Debian machine (idempotent, fast when present);
# 2. checks the formatting (rustfmt.toml) and the lints (clippy, warnings are errors; also
#    the build without the emulator, --no-default-features), then
#    builds every binary (process-level tests start `cncgw` and `sim-drives`);
# 3. runs every test of the workspace on the host;
# 4. runs each cargo-fuzz target for FUZZ_SECONDS (default 40 s each, 4 targets: under
#    3 minutes; scripts/fuzz.sh, a crash fails the run);
# 5. runs the vcan tier: `sim-drives --bus vcan0` and `cncgw run --bus vcan0` as separate
#    processes over SocketCAN — on the host kernel where it has vcan, otherwise inside a
#    throwaway User-Mode Linux guest (scripts/vmrun). It never skips: no vcan, no pass;
# 6. prints the reliability report (scripts/report.py): scenarios run, faults injected,
#    stops within bound, data lost, panics, fuzz executions per target, from what the tests
#    wrote to $CNCGW_REPORT_DIR (default build/report, emptied first). Data lost or a panic
#    fails the run.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"

step() { printf '\n==> %s\n' "$*"; }

# Runs of `cncgw run` keep the machine's power-off state (common variables); tests keep
# theirs here, not in the user's ~/.local/state.
export CNCGW_STATE_DIR="${CNCGW_STATE_DIR:-$ROOT/build/test-state}"

# The reliability report: every test that injects faults appends a line here
# (sim_drives::report::Scenario::record), scripts/fuzz.sh its executions.
export CNCGW_REPORT_DIR="${CNCGW_REPORT_DIR:-$ROOT/build/report}"
rm -rf "$CNCGW_REPORT_DIR"
mkdir -p "$CNCGW_REPORT_DIR"
report() { python3 "$ROOT/scripts/report.py" "$CNCGW_REPORT_DIR"; }
# A run that fails part-way still shows what it had measured.
trap 'rc=$?; if [ $rc -ne 0 ]; then printf "\n==> reliability report (the run failed)\n"; report || true; fi' EXIT

step "installing test prerequisites"
./scripts/install-test-deps.sh --python   # --python: build/venv for the python canopen peer test

step "format and lints (cargo fmt --check, clippy -D warnings)"
cargo fmt --all -- --check
cargo clippy --workspace --all-targets --quiet -- -D warnings
# A production build may leave the emulator out (feature `embedded`): it must still build.
cargo clippy -p cncgw --lib --bins --no-default-features --quiet -- -D warnings

step "building"
cargo build --workspace --bins --quiet

step "host tests (every crate of the workspace)"
if cargo nextest --version >/dev/null 2>&1; then
    cargo nextest run --workspace --no-fail-fast
else
    cargo test --workspace --no-fail-fast
fi
# Doc tests are not run by nextest.
cargo test --workspace --doc --quiet

step "fuzzing: each target for ${FUZZ_SECONDS:-40}s"
./scripts/fuzz.sh "${FUZZ_SECONDS:-40}"

# The host's steal time (/proc/stat, cpu line, 8th value) and all ticks, as "steal total".
steal_ticks() { awk '/^cpu / { t = 0; for (i = 2; i <= 9; i++) t += $i; print $9, t; exit }' /proc/stat; }
# "N % (S of T ticks)" of steal since steal_ticks printed $1.
steal_since() {
    local a b
    read -r -a a <<< "$1"; read -r -a b <<< "$(steal_ticks)"
    awk -v s=$((b[0] - a[0])) -v t=$((b[1] - a[1])) 'BEGIN { printf "%.1f %% (%d of %d ticks)", t ? 100 * s / t : 0, s, t }'
}
# Wait (at most 3 minutes) until 10 s pass with under 1 % of the VM's time stolen.
wait_for_calm() {
    local i s
    for i in $(seq 18); do
        s=$(steal_ticks); sleep 10
        if awk -v p="$(steal_since "$s")" 'BEGIN { exit !(p + 0 < 1) }'; then
            echo "vcan tier: host calm (steal $(steal_since "$s") over 10 s)"; return
        fi
        echo "vcan tier: host still stealing time ($(steal_since "$s") over 10 s): waiting"
    done
}
# Each failed test's reason, from libtest's output in $1: its alarm and its panic.
why_failed() {
    echo "vcan tier: why:"
    grep -aE "^alarm [0-9]+:|panicked at" -A1 "$1" | grep -av "^--$" | cut -c1-400 | sed 's/^/    /' || true
}

step "vcan tier (SocketCAN, separate processes)"
exe=$(cargo test --test vcan_tier --no-run --message-format=json 2>/dev/null \
      | grep '"name":"vcan_tier"' | grep '"test":true' \
      | sed -n 's/.*"executable":"\([^"]*\)".*/\1/p' | tail -n 1)
[ -x "$exe" ] || { echo "vcan tier: could not build tests/vcan_tier.rs" >&2; exit 1; }
# One retry of the tests that failed, as nextest gives the host's real-time tests
# (.config/nextest.toml): the guest runs master and drives in real time on a VM whose host
# deschedules it now and then — one fresh-clone run (2026-12-02) lost 4 of 7 to one such
# episode (heartbeat timeouts, 0x8611, a node leaving operational), the next three runs 1 of 7,
# 0, 0; another lost the same test on both tries. So the retry waits for the host's steal time
# to calm first (an episode lasts minutes, not seconds), and the host's steal over each try is
# printed. A test that fails twice fails the run; one that passes on its retry is named FLAKY.
vcan_log=$(mktemp)
steal_start=$(steal_ticks)
if ! ./scripts/run-vcan-tier.sh "$exe" --ignored --nocapture --test-threads=1 2>&1 | tee "$vcan_log"; then
    echo "vcan tier: the host stole $(steal_since "$steal_start") of this VM's time during the run"
    failed=$(sed -n '/^test result/q; s/^    \([a-z0-9_]*\)$/\1/p' "$vcan_log" | sort -u)
    [ -n "$failed" ] || { echo "vcan tier: failed, and no failed test is named: not retried" >&2; exit 1; }
    why_failed "$vcan_log"
    wait_for_calm
    printf '\nvcan tier: retrying once: %s\n' "$(echo $failed)"
    steal_start=$(steal_ticks)
    # shellcheck disable=SC2086 # one argument per test name
    if ! ./scripts/run-vcan-tier.sh "$exe" --ignored --nocapture --test-threads=1 --exact $failed 2>&1 | tee "$vcan_log"; then
        echo "vcan tier: the host stole $(steal_since "$steal_start") of this VM's time during the retry"
        why_failed "$vcan_log"
        exit 1
    fi
    printf '\nvcan tier: FLAKY (failed, then passed on its retry): %s\n' "$(echo $failed)"
fi
rm -f "$vcan_log"

step "reliability report"
report

step "all tiers passed"
