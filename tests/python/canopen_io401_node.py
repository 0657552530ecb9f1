"""A CiA 401 digital I/O module we did not write in Rust: a python `canopen` LocalNode (SDO
server and object dictionary from tests/python/io401.eds) over python-can's `socketcand`
interface, for cncgw's own master to drive (`[io.devices.*] canopen_node`). Run by
tests/realtime/io_python.rs:

    build/venv/bin/python tests/python/canopen_io401_node.py HOST PORT NODE

NMT slave (boot-up after a reset, the communication objects back to the EDS defaults),
0x6000 inputs and 0x6200 outputs (8 bits per sub-index) read and written by SDO and PDO:
RPDO1 (0x200 + node) sets the outputs, TPDO1 (0x180 + node) sends the inputs on SYNC
(transmission type 1–240) or on change (254/255), as mapped in 0x1600 / 0x1A00 by the
master; heartbeat producer 0x1017. The wiring: inputs 0 and 1 on (E-stop chain, door),
input 2 following output 1 after 150 ms (the chuck's switch after its valve).

Prints "ready" once on the bus; on SIGTERM/SIGINT prints one JSON line (the distinct output
values the module took, in order; NMT resets; SYNCs seen; TPDOs sent; 0x1000 reads) and exits.
"""

import json
import os
import signal
import struct
import sys
import threading
import time

import canopen

HOST, PORT, NID = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
EDS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "io401.eds")
PREOP, OP, STOPPED = 0x7F, 0x05, 0x04
FOLLOW_S = 0.150


class Module:
    def __init__(self, net):
        self.net = net
        self.lock = threading.RLock()
        self.node = canopen.LocalNode(NID, EDS)
        net.add_node(self.node)
        # Our own NMT (boot-up after a reset, comm objects to their defaults).
        net.unsubscribe(0, self.node.nmt.on_command)
        self.node.nmt.stop_heartbeat()
        self.node._write_callbacks.remove(self.node.nmt.on_write)
        net.subscribe(0, self.on_nmt)
        net.subscribe(0x80, self.on_sync)
        net.subscribe(0x200 + NID, self.on_rpdo)
        self.node.add_read_callback(self.on_read)
        self.node.add_write_callback(self.on_write)
        self.outputs, self.out_changed = 0, 0.0
        self.seen = [0]
        self.resets = self.syncs = self.tpdos = self.type_reads = 0
        self.last_sent = None
        self.hb_next = None
        self.boot()

    def get(self, ix, sub, fmt):
        return struct.unpack(fmt, self.node.get_data(ix, sub))[0]

    def send(self, cob, data):
        self.net.send_message(cob, bytes(data))

    def boot(self):
        for ix in [k for k in self.node.data_store if 0x1000 <= k <= 0x1FFF]:
            del self.node.data_store[ix]
        self.nmt, self.last_sent, self.hb_next = PREOP, None, None
        self.send(0x700 + NID, [0])

    def inputs(self):
        v = 0b011
        clamp = self.outputs >> 1 & 1
        if time.monotonic() - self.out_changed < FOLLOW_S:
            clamp ^= 1  # the switch has not followed the valve yet
        return v | clamp << 2

    def set_outputs(self, v):
        if (v ^ self.outputs) & 0b10:
            self.out_changed = time.monotonic()
        self.outputs = v
        if v != self.seen[-1]:
            self.seen.append(v)

    def on_read(self, index, subindex, od):
        with self.lock:
            if index == 0x1000:
                self.type_reads += 1
            if index in (0x6000, 0x6200) and 1 <= subindex <= 4:
                v = self.inputs() if index == 0x6000 else self.outputs
                return v >> 8 * (subindex - 1) & 0xFF
        return None

    def on_write(self, index, subindex, od, data):
        with self.lock:
            if index == 0x6200 and 1 <= subindex <= 4:
                sh = 8 * (subindex - 1)
                self.set_outputs(self.outputs & ~(0xFF << sh) | data[0] << sh)
            elif index == 0x1017:
                self.hb_next = time.monotonic() if struct.unpack("<H", data[:2])[0] else None

    def on_nmt(self, can_id, data, ts):
        if len(data) != 2 or data[1] not in (0, NID):
            return
        with self.lock:
            cmd = data[0]
            if cmd == 1:
                self.nmt = OP
            elif cmd == 2:
                self.nmt = STOPPED
            elif cmd == 0x80:
                self.nmt = PREOP
            elif cmd in (0x81, 0x82):
                self.resets += 1
                self.boot()

    def send_inputs(self):
        cob = self.get(0x1800, 1, "<I")
        if self.nmt != OP or cob & 0x80000000:
            return
        out = b""
        for k in range(1, self.get(0x1A00, 0, "<B") + 1):
            e = self.get(0x1A00, k, "<I")
            out += self.node.get_data(e >> 16, (e >> 8) & 0xFF)[: (e & 0xFF) // 8]
        self.send(cob & 0x7FF, out[:8])
        self.tpdos += 1
        self.last_sent = out

    def on_sync(self, can_id, data, ts):
        with self.lock:
            self.syncs += 1
            if 1 <= self.get(0x1800, 2, "<B") <= 240:
                self.send_inputs()

    def on_rpdo(self, can_id, data, ts):
        with self.lock:
            if self.nmt != OP or self.get(0x1400, 1, "<I") & 0x80000000:
                return
            n = self.get(0x1600, 0, "<B")
            if len(data) < n:
                return
            b = bytes(data[:n]) + bytes(4 - n)
            self.set_outputs(struct.unpack("<I", b[:4])[0])

    def tick(self):
        with self.lock:
            now = time.monotonic()
            if self.hb_next is not None and now >= self.hb_next:
                self.send(0x700 + NID, [self.nmt])
                self.hb_next = now + self.get(0x1017, 0, "<H") / 1000.0
            if self.get(0x1800, 2, "<B") >= 254 and self.nmt == OP:
                n = self.get(0x1A00, 0, "<B")
                if self.last_sent != bytes([self.inputs() >> 8 * k & 0xFF for k in range(n)]):
                    self.send_inputs()


def main():
    net = canopen.Network()
    net.connect(interface="socketcand", host=HOST, port=PORT, channel="can0", tcp_tune=True)
    time.sleep(0.05)
    m = Module(net)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    print("ready", flush=True)
    while not stop.is_set():
        m.tick()
        time.sleep(0.001)
    with m.lock:
        print(json.dumps({"outputs_seen": m.seen, "resets": m.resets, "syncs": m.syncs, "tpdos": m.tpdos, "type_reads": m.type_reads}), flush=True)
    net.disconnect()


if __name__ == "__main__":
    main()
