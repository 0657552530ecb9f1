"""An independent CANopen master (python `canopen` over python-can's `socketcand`
interface) against the CiA 401 I/O module `sim-drives --socketcand --config M` emulates
(sim-drives/src/io401.rs). Run by tests/realtime/io_python.rs:

    build/venv/bin/python tests/python/canopen_io401.py HOST PORT NODE

The module's wiring (the machine config's [io.devices.*.emulate]) is expected to be:
inputs 0 and 1 on from the start (E-stop chain, door), input 2 following output 1 after
200 ms (chuck clamped follows the clamp valve).

Checks: boot-up after NMT reset communication; 0x1000 = profile 401, the CiA 301 mandatory
error register 0x1001 and identity 0x1018 by SDO (the module's EDS, tests/python/io401.eds);
0x6000 / 0x6200 by SDO, an output written and read back and the input wired to it following;
read-only and missing objects aborted with the CiA 301 codes; the PDO configuration read
back the CiA 301 way (PdoMap.read); after NMT start the inputs by TPDO1 (on change: 255),
an output set by RPDO1 and the input following it in the next TPDO; TPDO1 remapped to
synchronous (1) with PdoMap.save and sent on every SYNC; the heartbeat producer 0x1017
showing the NMT state; in Stopped no SDO answer and no output taken. Exits non-zero with a
message on any failure; the last line is the module's final state as JSON.
"""

import json
import os
import sys
import time

import canopen

HOST, PORT, NODE = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
EDS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "io401.eds")
# Input 2 follows output 1 after 200 ms; wait well past it on a loaded machine.
FOLLOW_S = 0.6


def check(cond, what):
    if not cond:
        print(f"FAIL: {what}", file=sys.stderr)
        sys.exit(1)
    print(f"ok: {what}")


def aborts(fn, code, what):
    try:
        fn()
    except canopen.SdoAbortedError as e:
        check(e.code == code, f"{what}: aborted with 0x{e.code:08X} (expected 0x{code:08X})")
        return
    check(False, f"{what}: must abort with 0x{code:08X}")


def main():
    net = canopen.Network()
    net.connect(interface="socketcand", host=HOST, port=PORT, channel="can0", tcp_tune=True)
    try:
        run(net)
    finally:
        net.sync.stop()
        net.disconnect()


def sdo_checks(node):
    dt = node.sdo[0x1000].raw
    check(dt & 0xFFFF == 401, f"0x1000 device type 0x{dt:08X}: profile 401 in the low word")
    check(dt >> 16 == 0x000F, f"0x1000 additional information 0x{dt >> 16:04X}: digital inputs and outputs (bits 0, 1), 8-bit access")
    check(node.sdo[0x1001].raw == 0, "0x1001 error register 0")
    ident = [node.sdo[0x1018][s].raw for s in range(1, 5)]
    check(node.sdo[0x1018][0].raw == 4 and ident[0] == 0x00000CA7 and ident[1] == 0x04010001,
          f"0x1018 identity vendor 0x{ident[0]:08X} product 0x{ident[1]:08X}")
    check(node.sdo[0x6000][0].raw == 4 and node.sdo[0x6200][0].raw == 4, "0x6000 / 0x6200 have 4 sub-indices (32 bits each)")
    check(node.sdo[0x6000][1].raw == 0b011, f"0x6000:1 = 0b{node.sdo[0x6000][1].raw:08b}: inputs 0 and 1 wired on")
    check(node.sdo[0x6000][2].raw == 0, "0x6000:2 = 0")
    check(node.sdo[0x6200][1].raw == 0, "0x6200:1 = 0: outputs off after the reset")

    # Output 1 on (the clamp valve): read back, and input 2 follows it.
    node.sdo[0x6200][1].raw = 0b10
    check(node.sdo[0x6200][1].raw == 0b10, "0x6200:1 written 0b10 reads back 0b10")
    node.sdo[0x6200][3].raw = 0xA5
    check(node.sdo[0x6200][3].raw == 0xA5 and node.sdo[0x6200][1].raw == 0b10,
          "0x6200:3 written 0xA5 reads back, 0x6200:1 unchanged (one byte per sub-index)")
    node.sdo[0x6200][3].raw = 0
    time.sleep(FOLLOW_S)
    check(node.sdo[0x6000][1].raw == 0b111, f"0x6000:1 = 0b{node.sdo[0x6000][1].raw:08b}: input 2 followed output 1")
    node.sdo[0x6200][1].raw = 0
    time.sleep(FOLLOW_S)
    check(node.sdo[0x6000][1].raw == 0b011, "input 2 went off with output 1")

    aborts(lambda: node.sdo.download(0x6000, 1, b"\x01"), 0x06010002, "writing the input 0x6000:1")
    aborts(lambda: node.sdo.download(0x1000, 0, b"\x00\x00\x00\x00"), 0x06010002, "writing the device type 0x1000")
    aborts(lambda: node.sdo.upload(0x6401, 1), 0x06020000, "reading the analogue input 0x6401 it has not")


def pdo_checks(net, node):
    node.tpdo.read()
    node.rpdo.read()
    tp, rp = node.tpdo[1], node.rpdo[1]
    check(tp.enabled and tp.cob_id == 0x180 + NODE and tp.trans_type == 255 and len(tp) == 1
          and (tp[0].index, tp[0].subindex, tp[0].length) == (0x6000, 1, 8),
          f"TPDO1 read back: 0x6000:1 (8 bits) on 0x{tp.cob_id:03X}, transmission type {tp.trans_type}")
    check(rp.enabled and rp.cob_id == 0x200 + NODE and len(rp) == 1 and (rp[0].index, rp[0].subindex) == (0x6200, 1),
          f"RPDO1 read back: 0x6200:1 on 0x{rp.cob_id:03X}")

    node.nmt.state = "OPERATIONAL"
    tp.wait_for_reception(timeout=2.0)
    check(tp[0].raw == 0b011, f"after NMT start TPDO1 carries the inputs 0b{tp[0].raw:08b}")

    # Output 1 by RPDO1; input 2 follows and the module sends it (transmission type 255).
    rp[0].raw = 0b10
    rp.transmit()
    deadline = time.monotonic() + 3.0
    while tp[0].raw != 0b111 and time.monotonic() < deadline:
        tp.wait_for_reception(timeout=0.5)
    check(tp[0].raw == 0b111, f"RPDO1 set output 1; the next TPDO1 carries input 2 on: 0b{tp[0].raw:08b}")
    check(node.sdo[0x6200][1].raw == 0b10, "0x6200:1 by SDO shows the output the RPDO set")

    # Synchronous TPDO1: configured in pre-operational with PdoMap.save, one per SYNC.
    node.nmt.state = "PRE-OPERATIONAL"
    time.sleep(0.05)
    tp.trans_type = 1
    tp.save()
    tp.read()
    check(tp.trans_type == 1 and tp.enabled and len(tp) == 1, "TPDO1 saved synchronous (1) and read back")
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.05)
    got = 0
    for _ in range(10):
        t0 = tp.timestamp
        net.sync.transmit()
        tp.wait_for_reception(timeout=1.0)
        got += tp.timestamp != t0
    check(got == 10, f"a TPDO1 for each of 10 SYNCs (got {got})")
    check(tp[0].raw == 0b111, "still input 2 on")

    # Heartbeat producer: the NMT state every 50 ms.
    node.sdo[0x1017].raw = 50
    st = node.nmt.wait_for_heartbeat(timeout=1.0)
    check(st == "OPERATIONAL", f"heartbeat 0x1017 = 50 ms shows {st}")

    # Stopped: no SDO, no output taken from an RPDO; the heartbeat says STOPPED.
    node.nmt.state = "STOPPED"
    time.sleep(0.1)
    check(node.nmt.wait_for_heartbeat(timeout=1.0) == "STOPPED", "heartbeat shows STOPPED")
    rp[0].raw = 0
    rp.transmit()
    node.sdo.RESPONSE_TIMEOUT = 0.3
    try:
        node.sdo[0x6200][1].raw
        check(False, "an SDO answer in Stopped")
    except canopen.SdoCommunicationError:
        check(True, "no SDO answer in Stopped")
    node.sdo.RESPONSE_TIMEOUT = 1.0
    node.nmt.state = "PRE-OPERATIONAL"
    time.sleep(0.05)
    check(node.sdo[0x6200][1].raw == 0b10, "the RPDO sent in Stopped was not taken: output 1 still on")


def run(net):
    node = canopen.RemoteNode(NODE, EDS)
    net.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 1.0

    # Reset communication: the module answers with its boot-up and is pre-operational.
    node.nmt.send_command(0x82)
    node.nmt.wait_for_bootup(timeout=2.0)
    check(True, "boot-up after NMT reset communication")
    sdo_checks(node)
    pdo_checks(net, node)
    state = {"inputs": node.sdo[0x6000][1].raw, "outputs": node.sdo[0x6200][1].raw}
    print("all checks passed")
    print(json.dumps(state))


if __name__ == "__main__":
    main()
