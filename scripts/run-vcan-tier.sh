#!/usr/bin/env bash
# Run the vcan test tier: CMD must find vcan0 (and vcan1) up, and must fail rather than
# skip when it does not (CNCGW_VCAN_REQUIRED=1).
#
#   scripts/run-vcan-tier.sh CMD [ARGS...]      e.g. scripts/run-vcan-tier.sh cargo test --test vcan_tier
#
# Decides where, and says so in one line starting with "vcan tier:":
#   - natively, if vcan0 exists or can be created on the host kernel;
#   - otherwise in a throwaway guest kernel via scripts/vmrun (the host's / read-only with a
#     tmpfs overlay: writes vanish, except in the VCAN_TIER_RW dirs (space-separated;
#     default: the cargo target dir, so a `cargo test` run in the guest keeps its build).
# Exits with CMD's status (vmrun: 124 timeout, 125 guest failure).
set -euo pipefail

HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
ROOT=$(cd "$HERE/.." && pwd)
[ $# -gt 0 ] || { awk 'NR > 1 && !/^#/ { exit } NR > 1 && !/shellcheck/ { sub(/^# ?/, ""); print }' "$0" >&2; exit 2; }
export CNCGW_VCAN_REQUIRED=1

have_link() { ip link show dev "$1" >/dev/null 2>&1; }

# Make vcanN on the host if the kernel can; false if it cannot (no CAN, no vcan, no rights).
make_vcan() {
    if ! have_link "$1"; then ip link add dev "$1" type vcan 2>/dev/null || return 1; fi
    ip link set "$1" up 2>/dev/null
}

# Does the host kernel have SocketCAN? socket(AF_CAN) autoloads can.ko when it exists.
host_has_can() {
    if [ -x /usr/bin/python3 ]; then
        /usr/bin/python3 -c 'import socket; socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)' \
            2>/dev/null
    else
        modprobe -q can 2>/dev/null || true
        [ -d /proc/net/can ]
    fi
}

if command -v ip >/dev/null; then
    if ! have_link vcan0; then modprobe -q vcan 2>/dev/null || true; fi
    if make_vcan vcan0; then
        make_vcan vcan1 || true
        echo "vcan tier: native vcan0 on the host kernel ($(uname -r))"
        exec "$@"
    fi
fi

if host_has_can; then
    why="host kernel has SocketCAN but vcan0 cannot be created here (no vcan module or no CAP_NET_ADMIN)"
else
    why="host kernel has no SocketCAN"
fi
# --info builds the guest assets on first use (its log goes to stderr) and names the kernel.
guest=$("$HERE/vmrun" --info) || { echo "vcan tier: cannot start a guest: run scripts/install-test-deps.sh" >&2; exit 125; }
echo "vcan tier: in a $guest, $why"

RW_ARGS=()
for d in ${VCAN_TIER_RW-${CARGO_TARGET_DIR:-$ROOT/target}}; do RW_ARGS+=(--rw "$d"); done
# The guest is one host process running both the master's cycle loop and the emulated
# drives in real time: give it priority over whatever else the host runs (as root we can).
NICE=()
if [ "$(id -u)" = 0 ] && command -v nice >/dev/null; then NICE=(nice -n -10); fi
exec "${NICE[@]}" "$HERE/vmrun" "${RW_ARGS[@]}" -- "$@"
