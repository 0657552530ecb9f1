"""An independent CANopen master (python `canopen` over python-can's `socketcand`
interface) against `sim-drives --socketcand`. Run by sim-drives/tests/python_peer.rs:

    build/venv/bin/python tests/python/canopen_peer.py HOST PORT

Checks: the raw `< frame >` format of a zero-length SYNC; identity 0x1018 and 0x1000 by
SDO; RPDO1/TPDO1 configured by SDO the CiA 301 way (python canopen's PdoMap.save); node 1
to Operation Enabled in CSP with BaseNode402; targets streamed with SYNC and the actual
position following them; the fault objects 0x2100 (a raised fault shows in 0x603F and
the statusword, a fault reset clears it). Exits non-zero with a message on any failure.
"""

import os
import re
import socket
import sys
import time

import can
import canopen
from can.interfaces.socketcand.socketcand import convert_ascii_message_to_can_message

HOST, PORT = sys.argv[1], int(sys.argv[2])
NODE = 1
EDS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "sim_drive.eds")
SYNC_S = 0.010


def check(cond, what):
    if not cond:
        print(f"FAIL: {what}", file=sys.stderr)
        sys.exit(1)
    print(f"ok: {what}")


def raw_handshake():
    s = socket.create_connection((HOST, PORT), timeout=3)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    check(s.recv(256) == b"< hi >", "server greets with '< hi >' alone")
    s.sendall(b"< open can0 >")
    check(s.recv(256) == b"< ok >", "'< open can0 >' answered by '< ok >' alone")
    s.sendall(b"< rawmode >")
    check(s.recv(256) == b"< ok >", "'< rawmode >' answered by '< ok >' alone")
    return s


def sync_wire_format():
    """A SYNC sent by one python-can client arrives at a raw socket in socketcand's format."""
    listener = raw_handshake()
    time.sleep(0.05)
    bus = can.Bus(interface="socketcand", host=HOST, port=PORT, channel="can0")
    time.sleep(0.05)
    bus.send(can.Message(arbitration_id=0x80, data=[], is_extended_id=False))
    text = b""
    deadline = time.monotonic() + 3
    while b">" not in text and time.monotonic() < deadline:
        text += listener.recv(256)
    msg = text.split(b">")[0].decode() + ">"
    check(re.fullmatch(r"< frame 080 \d{10,}\.\d{6}  >", msg) is not None, f"zero-length SYNC on the wire as {msg!r}")
    m = convert_ascii_message_to_can_message(msg)
    check(m is not None and m.arbitration_id == 0x80 and m.dlc == 0 and not m.is_extended_id,
          "python-can parses it as a standard-id SYNC with no data")
    bus.shutdown()
    listener.close()


def main():
    sync_wire_format()

    net = canopen.Network()
    # tcp_tune: TCP_NODELAY on the client side too, else its SYNCs leave in 40 ms bursts.
    net.connect(interface="socketcand", host=HOST, port=PORT, channel="can0", tcp_tune=True)
    try:
        run(net)
    finally:
        net.sync.stop()
        net.disconnect()


def block_transfer(node):
    """SDO block download and upload (CRC on) of the 4096-byte DOMAIN 0x2200, read back both
    ways; the throughput of each upload mode over socketcand is printed."""
    data = bytes((i * 7 + i // 251) & 0xFF for i in range(4096))
    with node.sdo.open(0x2200, 0, "wb", size=len(data), block_transfer=True) as f:
        f.write(data)
    t = time.perf_counter()
    with node.sdo.open(0x2200, 0, "rb", block_transfer=True) as f:
        back = f.read()
    t_block = time.perf_counter() - t
    check(back == data, f"0x2200: 4096 bytes block download, block upload reads them back (CRC on)")
    t = time.perf_counter()
    seg = node.sdo.upload(0x2200, 0)
    t_seg = time.perf_counter() - t
    check(seg == data, "the segmented upload agrees")
    print(f"figure: socketcand SDO upload of 4096 bytes: block {len(data) / t_block:.0f} B/s, "
          f"segmented {len(data) / t_seg:.0f} B/s")
    with node.sdo.open(0x2200, 0, "wb", size=5, block_transfer=True) as f:
        f.write(b"hello")
    with node.sdo.open(0x2200, 0, "rb", block_transfer=True) as f:
        check(f.read() == b"hello", "a 5-byte block transfer (one short segment)")
    try:
        with node.sdo.open(0x2200, 0, "wb", size=5000, block_transfer=True) as f:
            f.write(bytes(5000))
        check(False, "5000 bytes into the 4096-byte 0x2200 must abort")
    except canopen.SdoAbortedError as e:
        check(e.code == 0x06070012, f"5000 bytes into 0x2200 abort with 0x{e.code:08X} (too long)")


def run(net):
    node = canopen.BaseNode402(NODE, EDS)
    # BaseNode402's timeouts (0.2–0.8 s) assume a quiet machine; CI shares its cores.
    node.TIMEOUT_SWITCH_STATE_FINAL = 5.0
    node.TIMEOUT_SWITCH_STATE_SINGLE = 2.0
    node.TIMEOUT_SWITCH_OP_MODE = 2.0
    node.TIMEOUT_CHECK_TPDO = 1.0
    net.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 1.0

    node.nmt.state = "PRE-OPERATIONAL"
    time.sleep(0.05)
    check(node.sdo[0x1000].raw == 0x00020192, "0x1000 device type = 0x00020192 (CiA 402 servo)")
    vendor, product = node.sdo[0x1018][1].raw, node.sdo[0x1018][2].raw
    serial = node.sdo[0x1018][4].raw
    check(vendor == 0x00000CA7 and product == 0x04020001 and serial == 0x51000000 + NODE,
          f"0x1018 identity vendor 0x{vendor:08X} product 0x{product:08X} serial 0x{serial:08X}")
    try:
        node.sdo.upload(0x1018, 9)
        check(False, "0x1018:9 must abort")
    except canopen.SdoAbortedError as e:
        check(e.code == 0x06090011, f"0x1018:9 aborts with 0x{e.code:08X} (sub-index does not exist)")

    block_transfer(node)

    # RPDO1 = controlword + target position, TPDO1 = statusword + position actual, on SYNC.
    node.rpdo.read()
    node.tpdo.read()
    rp, tp = node.rpdo[1], node.tpdo[1]
    rp.clear()
    rp.add_variable(0x6040)
    rp.add_variable(0x607A)
    rp.trans_type = 1
    rp.enabled = True
    rp.save()
    tp.clear()
    tp.add_variable(0x6041)
    tp.add_variable(0x6064)
    tp.trans_type = 1
    tp.enabled = True
    tp.save()
    # Read the configuration back from the drive (what BaseNode402 relies on).
    node.setup_402_state_machine(read_pdos=True)
    check(len(node.tpdo[1]) == 2 and node.tpdo[1][0].index == 0x6041 and node.tpdo[1][1].index == 0x6064
          and node.tpdo[1].cob_id == 0x180 + NODE, "TPDO1 read back: 0x6041 + 0x6064 on 0x181")
    check(len(node.rpdo[1]) == 2 and node.rpdo[1][1].index == 0x607A and node.rpdo[1].trans_type == 1,
          "RPDO1 read back: 0x6040 + 0x607A, synchronous")
    node.sdo[0x60C2][1].raw = int(SYNC_S * 1000)
    node.sdo[0x60C2][2].raw = -3

    node.nmt.state = "OPERATIONAL"
    net.sync.start(SYNC_S)
    # A synchronous RPDO is the application's job to send every cycle (python canopen
    # then only updates its data): start it before the state machine needs it.
    start = node.sdo[0x6064].raw
    node.rpdo[1][0].raw = 0
    node.rpdo[1][1].raw = start  # hold where it is when the power stage comes on
    rp.start(SYNC_S)
    time.sleep(0.1)
    node.op_mode = "CYCLIC SYNCHRONOUS POSITION"
    check(node.sdo[0x6061].raw == 8 and node.op_mode == "CYCLIC SYNCHRONOUS POSITION", "0x6061 shows CSP (8)")

    node.state = "SWITCH ON DISABLED"
    node.state = "OPERATION ENABLED"
    check(node.state == "OPERATION ENABLED", "BaseNode402 reaches OPERATION ENABLED")

    # Stream a ramp: a new target after each SYNC's TPDO (the periodic RPDO carries it).
    step = 200  # counts per 10 ms = 20000 counts/s
    sent = []
    worst = 0
    cycles = 100
    for k in range(1, cycles + 30):
        tp.wait_for_reception(timeout=0.5)
        actual = node.tpdo_values[0x6064]
        target = start + step * min(k, cycles)
        node.rpdo[1][1].raw = target
        sent.append(target)
        if k > 5 and k <= cycles:
            # The RPDO is not aligned with the SYNC (python's own timer): the feedback of
            # this SYNC belongs to a target set 2–3 cycles before.
            worst = max(worst, abs(sent[-3] - actual))
    final_target = start + step * cycles
    time.sleep(0.3)
    actual = node.tpdo_values[0x6064]
    check(actual - start > step * cycles * 0.99, f"the axis moved {actual - start} counts of {step * cycles}")
    check(abs(actual - final_target) <= 20, f"settled at {actual}, target {final_target}")
    # Loose on purpose (python's own timer sends the RPDO; a stall of this process delays
    # targets): an axis that does not follow lags by up to the whole ramp.
    check(worst <= 10 * step, f"lag while moving ≤ 10 cycles of travel (worst {worst} counts)")
    check(node.statusword & 0x1000 != 0, "statusword bit 12 (following the command) set")
    check(node.sdo[0x6041].raw & 0x0400 != 0, "statusword bit 10 (target reached) set at rest")

    # Fault injection by SDO: the manufacturer object 0x2100.
    node.sdo[0x2100][1].raw = 0x2310
    time.sleep(0.1)
    check(node.sdo[0x603F].raw == 0x2310, "0x2100:1 = 0x2310 raises overcurrent (0x603F)")
    check(node.state == "FAULT", "the drive is in FAULT")
    node.rpdo[1][0].raw = 0x0080
    time.sleep(0.1)
    check(node.sdo[0x603F].raw == 0 and node.state == "SWITCH ON DISABLED", "fault reset clears it")
    print("all checks passed")


if __name__ == "__main__":
    main()
