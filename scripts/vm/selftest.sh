#!/usr/bin/env bash
# Self-test of scripts/vmrun (about 3 boots, ~8 s with UML): AF_CAN on vcan0 within one
# process and between two processes, --rw persistence, overlay writes vanishing, exit
# status, pipes (not ttys) for stdout, the timeout, and a guest kernel panic.
#
#   scripts/vm/selftest.sh          (VMRUN_BACKEND=qemu to test the fallback)
set -euo pipefail

HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
VMRUN=$HERE/../vmrun
PY=/usr/bin/python3   # Debian's, not a pyenv shim: shims fork a lot, slow in a guest
T=$(mktemp -d /tmp/vmrun-selftest.XXXXXX)
trap 'rm -rf "$T"' EXIT
fails=0
check() {   # check NAME COMMAND...: run COMMAND, report
    if "${@:2}"; then echo "ok:   $1"; else echo "FAIL: $1"; fails=$((fails + 1)); fi
}

cat >"$T/can.py" <<'EOF'
import socket, struct, sys
FMT = "=IB3x8s"
def sock(filt=None):
    s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    s.bind(("vcan0",)); s.settimeout(5)
    if filt: s.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, struct.pack("=II", *filt))
    return s
def frame(i, d): return struct.pack(FMT, i, len(d), d.ljust(8, b"\0"))
def unframe(b): i, n, d = struct.unpack(FMT, b); return i, d[:n]
mode = sys.argv[1]
if mode == "pair":      # two sockets, one process
    tx, rx = sock(), sock()
    tx.send(frame(0x123, b"\xde\xad"))
    assert unframe(rx.recv(16)) == (0x123, b"\xde\xad")
elif mode == "server":  # answers 0x20x with 0x30x until 0x20f
    s = sock((0x200, 0x7f0)); open(sys.argv[2], "w").write("ready")
    while True:
        i, d = unframe(s.recv(16))
        if i == 0x20f: break
        s.send(frame(0x300 | (i & 0xf), d))
elif mode == "client":
    s = sock((0x300, 0x7f0))
    for k in range(5):
        s.send(frame(0x200 + k, bytes([k])))
        assert unframe(s.recv(16)) == (0x300 + k, bytes([k]))
    s.send(frame(0x20f, b""))
print(mode, "ok")
EOF
cat >"$T/guest.sh" <<EOF
set -e
$PY $T/can.py pair
rm -f /tmp/selftest-ready
$PY $T/can.py server /tmp/selftest-ready &
while [ ! -s /tmp/selftest-ready ]; do sleep 0.01; done
$PY $T/can.py client
wait \$!
echo persisted >$T/rw/file
echo gone >$HERE/../../selftest-overlay-file
[ -p /dev/stdout ] && ! [ -t 1 ] && echo stdout-is-a-pipe
exit 7
EOF

mkdir -p "$T/rw"
rc=0
"$VMRUN" --rw "$T/rw" bash "$T/guest.sh" >"$T/out" 2>"$T/err" || rc=$?
check "exit status passed through (7, got $rc)" [ "$rc" = 7 ]
check "AF_CAN pair on vcan0" grep -qx "pair ok" "$T/out"
check "AF_CAN between two processes" grep -qx "client ok" "$T/out"
check "background server process" grep -qx "server ok" "$T/out"
check "--rw dir persists" grep -qx persisted "$T/rw/file"
check "overlay writes vanish" [ ! -e "$HERE/../../selftest-overlay-file" ]
check "stdout is a pipe" grep -qx stdout-is-a-pipe "$T/out"
[ "$fails" = 0 ] || { echo "--- guest stdout:"; cat "$T/out"; echo "--- guest stderr:"; cat "$T/err"; }

rc=0
VMRUN_TIMEOUT=3 "$VMRUN" sleep 60 2>/dev/null || rc=$?
check "timeout kills the guest (124, got $rc)" [ "$rc" = 124 ]
rc=0
"$VMRUN" sh -c 'echo c >/proc/sysrq-trigger' 2>/dev/null || rc=$?
check "guest panic returns 125 (got $rc)" [ "$rc" = 125 ]

if [ "$fails" = 0 ]; then echo "vmrun selftest: all passed"; else echo "vmrun selftest: $fails failed"; exit 1; fi
