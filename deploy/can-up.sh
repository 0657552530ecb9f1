#!/bin/sh
# Bring a SocketCAN interface up for cncgw: bitrate, a transmit queue deep enough for a
# burst of SDO and PDO frames, and automatic recovery from bus-off.
#
#   deploy/can-up.sh [IFACE] [BITRATE]      (as root; defaults: can0 1000000)
#
# The same as `ip link set can0 up type can bitrate 1000000` plus txqueuelen and
# restart-ms. Idempotent: the interface is taken down first (settings cannot change while
# it is up). Run by cncgw-can@.service at boot, or by hand after plugging the adapter in.
set -eu

IFACE=${1:-can0}
BITRATE=${2:-1000000}
# Frames the kernel may queue for sending: the default (10) drops frames when a start-up
# writes many SDOs while PDOs run; 1000 covers the worst burst with room to spare.
TXQUEUELEN=${TXQUEUELEN:-1000}
# After bus-off, restart the controller after this many ms (0 = stay off until taken down).
RESTART_MS=${RESTART_MS:-100}

command -v ip >/dev/null || { echo "can-up: \`ip\` not found: apt-get install iproute2" >&2; exit 1; }
if ! ip link show "$IFACE" >/dev/null 2>&1; then
    echo "can-up: no interface $IFACE: is the adapter plugged in and its driver loaded? (\`ip -br link\`, \`dmesg | grep -i can\`)" >&2
    exit 1
fi

ip link set "$IFACE" down
ip link set "$IFACE" type can bitrate "$BITRATE" restart-ms "$RESTART_MS"
ip link set "$IFACE" txqueuelen "$TXQUEUELEN"
ip link set "$IFACE" up
ip -details -brief link show "$IFACE"
