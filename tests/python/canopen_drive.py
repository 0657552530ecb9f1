"""CiA 402 drives we did not write in Rust: python `canopen` LocalNodes (SDO server and
object dictionary from tests/python/sim_drive.eds) over python-can's `socketcand` interface,
with a CiA 402 state machine, SYNC/PDO handling, heartbeat producer and consumer, and the
shapes of commercial drives that trouble a master at start-up (issue 27). A second opinion
to sim-drives' [drive.shape]; run by tests/cli/python_drives.rs:

    build/venv/bin/python tests/python/canopen_drive.py HOST PORT SHAPE

SHAPE: plain | pp_boot | user_units | sync_producer | no_1016 | no_6502 | ip_only |
fixed_pdo | ext_sync | tap_sN (N: the spindle's time constant in ms, e.g. tap_s15, tap_s40).
fixed_pdo (issue 21): PDO mappings that cannot be changed. The drives' own sets are in their
EDS (edited at start: DefaultValue of 0x1600/0x1601/0x1A00/0x1A01) and at power-on, not in the
master's order: RPDO1 = 0x607A + controlword, TPDO1 = 0x6064 + statusword + 0x6061. A write
of a mapping object's own value is taken, any other refused as vendors do, one per node: RPDO
/ TPDO abort 0x06040041 / 0x08000022 (node 1), 0x06040043 / 0x06040041 (2), 0x08000022 /
0x06040043 (3). COB-IDs and transmission types stay writable.
user_units: 0x6092:1 = a tenth of the increments per revolution (1 µm, 0.01°); the machine
configuration must declare the axes in those units (counts_per_unit, travel_per_rev).
ext_sync (issue 21, bus.sync = "external"): node 1 produces SYNC (0x1005 = 0x40000080, 0x1006
= 5000 µs at power-on; the master sets 0x1006 to its cycle); the others consume it. The
interpreter's own SYNC reaches all three drives (notify), as a frame on the bus would.
The final JSON line per node also gives position_actual (0x6064, in the drive's units) and
the SYNCs the node produced and heard.
ip_only (issue 21): interpolated position (7) and no CSP — 0x6060 = 8 aborts 0x06090030,
0x6502 lists PP, HM, IP; 0x60C0/0x60C1/0x60C4 added to the EDS; in IP the position follows
0x60C1:1 at each SYNC while controlword bit 4 is set, and statusword bit 12 says so.
Nodes 1 (X), 2 (Z) linear (100000 increments per motor revolution), 3 (S1) spindle
(360000), all with the same shape. The position follows the CSP target at each SYNC (an
ideal drive: no dynamics). Prints "ready" once on the bus; on SIGTERM/SIGINT prints one JSON
line per node (modes it was enabled in, position in increments, NMT resets) and exits.

tap_sN (issue 17, the rigid tap on drives we did not write): the spindle (3) and Z (2) are not
ideal. Each follows its CSP set-point through dynamics of our own choosing, not sim-drives'
(no kv/ff position loop, no inertia or friction model): a critically damped second-order
response with velocity feed-forward, τ²·ÿ + 2τ·ẏ + y = r + 2τ·ff·ṙ, the set-point r
interpolated linearly over the interpolation period 0x60C2 and integrated in 20 steps per
SYNC, behind `delay` extra SYNCs of transport delay. Spindle: τ = N ms, ff 1.0 (no lag at
steady speed, a·τ² while accelerating), one extra cycle of delay. Z: τ 6 ms, ff 0.97 (a lag of
0.06·τ·v at steady speed), no extra delay. The following-error window 0x6065 is checked
against the delayed set-point (fault 0x8611, as a commercial drive does). The drives run on
the SYNCs they receive (a late SYNC is not bridged: late_sync_extrapolation = 0 in cncgw's
configuration); a SYNC that finds no new RPDO continues the last set-point step.
"""

import json
import os
import re
import signal
import struct
import sys
import tempfile
import threading
import time

import canopen
from canopen.sdo import SdoAbortedError

HOST, PORT, SHAPE = sys.argv[1], int(sys.argv[2]), sys.argv[3]
EDS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "sim_drive.eds")

SOD, RTSO, SO, OE, FAULT = 0x40, 0x21, 0x23, 0x27, 0x08
PREOP, OP, STOPPED = 0x7F, 0x05, 0x04

SHAPES = {
    "plain": {},
    "pp_boot": {"boot_mode": 1, "switch_s": 0.3, "switch_syncs": 50},
    "user_units": {"feed_div": 10},  # 0x6092 = increments / 10 per revolution: 1 µm
    "sync_producer": {"sync_producer": True},
    "no_1016": {"drop": ["1016"]},
    "no_6502": {"drop": ["6502"]},
    "ip_only": {"modes": (0, 1, 6, 7), "ip": True},
    # node: (abort on a remapping of RPDO1/2, of TPDO1/2): each drive answers as one vendor does.
    "fixed_pdo": {"fixed": {1: (0x06040041, 0x08000022), 2: (0x06040043, 0x06040041), 3: (0x08000022, 0x06040043)}},
    "ext_sync": {"sync_nodes": (1,), "sync_us": 5000},
}
# fixed_pdo: the drives' own PDO sets (mapping entries), in their EDS and at power-on; not the
# master's order (target before controlword; mode display after position and statusword).
FIXED_MAPS = {
    0x1600: [0x607A0020, 0x60400010],
    0x1601: [0x60400010, 0x60FF0020],
    0x1A00: [0x60640020, 0x60410010, 0x60610008],
    0x1A01: [0x60410010, 0x606C0020],
}
_tap = re.fullmatch(r"tap_s(\d+)", SHAPE)
if _tap:
    # node: (τ s, velocity feed-forward, extra SYNCs of transport delay)
    SHAPES[SHAPE] = {"dyn": {3: (int(_tap.group(1)) / 1000.0, 1.0, 1), 2: (0.006, 0.97, 0)}}

IP_EDS = """
[60C0]
ParameterName=Interpolation sub mode select
ObjectType=0x7
DataType=0x0003
AccessType=rw
DefaultValue=0
PDOMapping=0

[60C1]
ParameterName=Interpolation data record
ObjectType=0x9
SubNumber=2

[60C1sub0]
ParameterName=Highest sub-index supported
ObjectType=0x7
DataType=0x0005
AccessType=ro
DefaultValue=1
PDOMapping=0

[60C1sub1]
ParameterName=Position set-point
ObjectType=0x7
DataType=0x0004
AccessType=rw
DefaultValue=0
PDOMapping=1

[60C4]
ParameterName=Interpolation data configuration
ObjectType=0x9
SubNumber=7
""" + "".join(
    "\n[60C4sub%d]\nParameterName=Sub %d\nObjectType=0x7\nDataType=0x%04X\nAccessType=%s\nDefaultValue=%d\nPDOMapping=0\n" % (k, k, t, a, v)
    for k, t, a, v in [(0, 5, "ro", 6), (1, 7, "ro", 1), (2, 7, "ro", 1), (3, 5, "rw", 0), (4, 6, "rw", 0), (5, 5, "wo", 4), (6, 5, "wo", 1)]
)
shape = SHAPES[SHAPE]


def shaped_eds():
    """sim_drive.eds without the objects this shape lacks."""
    text = open(EDS).read()
    # Every shape lacks max torque 0x6072: this drive models no torque (0x6077 stays 0), and a
    # limit would only have the master read that zero every other cycle.
    for ix in ["6072"] + shape.get("drop", []):
        text = re.sub(r"\[%s(sub[0-9A-Fa-f]+)?\]\n(?:[^\[]*\n)*?\n" % ix, "", text)
    if shape.get("ip"):
        text = text.replace("DefaultValue=0x000001A1", "DefaultValue=0x00000061") + "\n" + IP_EDS
    if shape.get("fixed"):
        # The fixed sets as the EDS's defaults (AccessType stays rw, as in many vendors' EDS
        # files: the drive takes its own value back and refuses any other at run time).
        for ix, entries in FIXED_MAPS.items():
            for sub, v in enumerate([len(entries)] + entries):
                text = re.sub(r"(\[%Xsub%d\]\n(?:[^\[\n]*\n)*?DefaultValue=)[^\n]*" % (ix, sub), lambda m: m.group(1) + "0x%X" % v, text, count=1)
    f = tempfile.NamedTemporaryFile("w", suffix=".eds", delete=False)
    f.write(text)
    f.close()
    return f.name


class Drive:
    def __init__(self, net, nid, axis, counts_per_rev, eds, send_lock):
        self.net, self.nid, self.axis, self.cpr = net, nid, axis, counts_per_rev
        self.lock = threading.RLock()
        self.send_lock = send_lock
        self.producer = shape.get("sync_producer", False) or nid in shape.get("sync_nodes", ())
        self.node = canopen.LocalNode(nid, eds)
        net.add_node(self.node)
        # Our own NMT (boot-up after a reset, comm objects to their defaults).
        net.unsubscribe(0, self.node.nmt.on_command)
        self.node.nmt.stop_heartbeat()
        self.node._write_callbacks.remove(self.node.nmt.on_write)
        net.subscribe(0, self.on_nmt)
        net.subscribe(0x80, self.on_sync)
        net.subscribe(0x77F, self.on_master_heartbeat)
        net.subscribe(0x200 + nid, self.on_rpdo)
        self.node.add_read_callback(self.on_read)
        self.node.add_write_callback(self.on_write)
        self.state, self.cw, self.mode = SOD, 0, shape.get("boot_mode", 0)
        self.pending = None  # (mode, due time, syncs left)
        self.pos_inc = 0.0
        self.target = 0
        self.error = 0
        self.enabled_modes = set()
        self.resets = 0
        self.syncs_sent = self.syncs_heard = 0
        self.rpdo = None
        self.master_hb = None
        self.dyn = shape.get("dyn", {}).get(nid)
        self.cmds = []  # set-points in increments, newest last (transport delay)
        self.vel = 0.0  # increments/s (dynamics)
        self.ferr_max = 0.0
        self.due = None
        self.late, self.step = 0, 0
        self.app_defaults()
        self.boot()

    # ---- object dictionary -----------------------------------------------------------

    def put(self, ix, sub, fmt, v):
        self.node.data_store.setdefault(ix, {})[sub] = struct.pack(fmt, v)

    def get(self, ix, sub, fmt):
        return struct.unpack(fmt, self.node.get_data(ix, sub))[0]

    def comm_defaults(self):
        """0x1000–0x1FFF as at power-on (NMT reset communication)."""
        for ix in [k for k in self.node.data_store if 0x1000 <= k <= 0x1FFF]:
            del self.node.data_store[ix]
        n = self.nid
        self.put(0x1005, 0, "<I", 0x40000080 if self.producer else 0x80)
        self.put(0x1006, 0, "<I", shape.get("sync_us", 2000) if self.producer else 0)
        self.put(0x1017, 0, "<H", 0)
        for sub, v in [(1, 0x00000CA8), (2, 0x04020100 + n), (3, 0x00020001), (4, 0x7A000000 + n)]:
            self.put(0x1018, sub, "<I", v)
        self.put(0x1400, 1, "<I", 0x200 + n)
        self.put(0x1400, 2, "<B", 1)
        self.put(0x1600, 0, "<B", 2)
        self.put(0x1600, 1, "<I", 0x60400010)
        self.put(0x1600, 2, "<I", 0x607A0020)
        self.put(0x1800, 1, "<I", 0x180 + n)
        self.put(0x1800, 2, "<B", 1)
        self.put(0x1A00, 0, "<B", 2)
        self.put(0x1A00, 1, "<I", 0x60410010)
        self.put(0x1A00, 2, "<I", 0x60640020)
        if shape.get("fixed"):
            for ix in (0x1600, 0x1A00):
                self.put(ix, 0, "<B", len(FIXED_MAPS[ix]))
                for k, e in enumerate(FIXED_MAPS[ix]):
                    self.put(ix, k + 1, "<I", e)
        if "1016" not in shape.get("drop", []):
            self.put(0x1016, 1, "<I", 0)
        self.hb_period, self.hb_next = 0.0, None
        self.sync_next = None

    def app_defaults(self):
        self.put(0x6060, 0, "<b", self.mode)
        self.put(0x608F, 1, "<I", self.cpr)
        self.put(0x608F, 2, "<I", 1)
        self.put(0x6091, 1, "<I", 1)
        self.put(0x6091, 2, "<I", 1)
        self.put(0x6092, 1, "<I", self.cpr // shape.get("feed_div", 1))
        self.put(0x6092, 2, "<I", 1)
        self.put(0x607E, 0, "<B", 0)

    def inc_per_unit(self):
        inc = self.get(0x608F, 1, "<I") / self.get(0x608F, 2, "<I")
        gear = self.get(0x6091, 1, "<I") / self.get(0x6091, 2, "<I")
        feed = self.get(0x6092, 1, "<I") / self.get(0x6092, 2, "<I")
        return inc * gear / feed

    def statusword(self):
        s = self.state | 0x0200
        if self.state != FAULT:
            s |= 0x10
        if self.state == OE:
            s |= 0x0400
            if self.mode in (8, 9) or (self.mode == 7 and self.cw & 0x10):
                s |= 0x1000  # following the command value; in IP: ip mode active
        return s

    def on_read(self, index, subindex, od):
        with self.lock:
            if index == 0x6041:
                return self.statusword()
            if index == 0x6061:
                return self.mode
            if index == 0x6064:
                return int(round(self.pos_inc / self.inc_per_unit()))
            if index == 0x6063:
                return int(round(self.pos_inc))
            if index == 0x603F:
                return self.error
            if index == 0x1008:
                return "PYCANOPEN-402 %s" % self.axis.upper()
        return None

    def on_write(self, index, subindex, od, data):
        v = int.from_bytes(data, "little", signed=od.data_type in (2, 3, 4)) if len(data) <= 4 else 0
        with self.lock:
            if index == 0x6060:
                if v not in shape.get("modes", (0, 1, 6, 8, 9)):
                    raise SdoAbortedError(0x06090030)
                self.request_mode(v)
            elif index in FIXED_MAPS and shape.get("fixed") and bytes(data) != self.node.get_data(index, subindex):
                # A fixed mapping: its own value is taken back, any other refused.
                raise SdoAbortedError(shape["fixed"][self.nid][0 if index < 0x1A00 else 1])
            elif index == 0x1005 and v & 0x40000000 and not self.producer:
                raise SdoAbortedError(0x06090030)
            elif index == 0x1017:
                self.hb_period = v / 1000.0
                self.hb_next = time.monotonic() + self.hb_period if v else None
            elif index == 0x1016 and subindex == 1:
                self.master_hb = None  # armed by the next heartbeat
            elif index == 0x6040:
                self.controlword(v)
            elif index == 0x1005 or index == 0x1006:
                self.sync_next = None

    # ---- NMT, heartbeat, SYNC ----------------------------------------------------------

    def send(self, cob, data):
        with self.send_lock:
            self.net.send_message(cob, bytes(data))

    def boot(self):
        self.comm_defaults()
        self.nmt = PREOP
        self.send(0x700 + self.nid, [0])

    def on_nmt(self, can_id, data, ts):
        if len(data) != 2 or data[1] not in (0, self.nid):
            return
        cmd = data[0]
        with self.lock:
            if cmd == 1:
                self.nmt = OP
            elif cmd == 2:
                self.nmt = STOPPED
            elif cmd == 0x80:
                self.nmt = PREOP
            elif cmd in (0x81, 0x82):
                self.resets += 1
                if cmd == 0x81:
                    self.mode, self.state, self.pending = shape.get("boot_mode", 0), SOD, None
                    for ix in [k for k in self.node.data_store if k >= 0x2000]:
                        del self.node.data_store[ix]
                    self.app_defaults()
                self.boot()

    def request_mode(self, m):
        if "switch_s" in shape and m != self.mode:
            self.pending = (m, time.monotonic() + shape["switch_s"], shape["switch_syncs"])
        else:
            self.pending = None
            self.mode = m

    def step_pending(self, sync):
        if self.pending:
            m, due, left = self.pending
            left = max(0, left - (1 if sync else 0))
            self.pending = (m, due, left)
            if left == 0 and time.monotonic() >= due:
                self.mode, self.pending = m, None

    def on_master_heartbeat(self, can_id, data, ts):
        with self.lock:
            self.master_hb = time.monotonic()

    def fault(self, code):
        self.state, self.error = FAULT, code
        self.send(0x80 + self.nid, list(struct.pack("<HB5x", code, 0x11)))

    def tick(self):
        """Timers, every millisecond: heartbeat, SYNC production, mode switch, consumer."""
        now = time.monotonic()
        fire = False
        with self.lock:
            if self.hb_next is not None and now >= self.hb_next and self.nmt != 0:
                self.send(0x700 + self.nid, [self.nmt])
                self.hb_next += self.hb_period
            c = self.get(0x1005, 0, "<I")
            period = self.get(0x1006, 0, "<I") / 1e6
            if c & 0x40000000 and period > 0 and self.nmt in (PREOP, OP):
                if self.sync_next is None:
                    self.sync_next = now + period
                elif now >= self.sync_next:
                    # After a stall of this interpreter: on the period again, no burst of
                    # SYNCs to catch up (a producer's timer does not queue them).
                    self.sync_next = max(self.sync_next + period, now + period / 2)
                    fire = True
            self.step_pending(False)
            consumer = self.get(0x1016, 1, "<I") if "1016" not in shape.get("drop", []) else 0
            timeout = (consumer & 0xFFFF) / 1000.0
            if timeout and self.master_hb is not None and now - self.master_hb > timeout:
                self.master_hb = None
                if self.nmt == OP or self.state == OE:
                    self.fault(0x8130)
        if fire:
            # Our own frames do not come back to us: every drive of this interpreter (this one
            # too) gets the SYNC as if received, outside this drive's lock.
            self.send(0x80, [])
            self.syncs_sent += 1
            self.net.notify(0x80, b"", time.time())

    def on_sync(self, can_id, data, ts):
        with self.lock:
            self.syncs_heard += 1
            self.sync()

    def sync(self):
        self.step_pending(True)
        if self.nmt != OP:
            return
        cob = self.get(0x1800, 1, "<I")
        if not cob & 0x80000000:
            out = b""
            for k in range(1, self.get(0x1A00, 0, "<B") + 1):
                e = self.get(0x1A00, k, "<I")
                out += self.node.get_data(e >> 16, (e >> 8) & 0xFF)[: (e & 0xFF) // 8]
            self.send(cob & 0x7FF, out[:8])
        before = self.target
        if self.rpdo is None and self.dyn and self.state == OE and self.mode == 8 and self.late < 10:
            # No set-point for this SYNC (the RPDO is late): continue the last step, as drives
            # that bridge a late SYNC do (axes.NAME.late_sync_extrapolation = 10 of the lathe).
            self.late += 1
            self.target += self.step
        if self.rpdo is not None:
            self.late = 0
            data, self.rpdo = self.rpdo, None
            pos = 0
            for k in range(1, self.get(0x1600, 0, "<B") + 1):
                e = self.get(0x1600, k, "<I")
                n = (e & 0xFF) // 8
                chunk = data[pos: pos + n]
                pos += n
                if e >> 16 == 0x6040:
                    self.controlword(int.from_bytes(chunk, "little"))
                elif e >> 16 in (0x607A, 0x60C1):
                    self.target = int.from_bytes(chunk, "little", signed=True)
        self.step = self.target - before
        if self.state == OE:
            self.enabled_modes.add(self.mode)
            if self.mode == 8 or (self.mode == 7 and self.cw & 0x10):
                if self.dyn:
                    self.due = self.target * self.inc_per_unit()  # after every drive's TPDO: after_sync
                else:
                    self.pos_inc = self.target * self.inc_per_unit()

    def after_sync(self, can_id, data, ts):
        """The dynamics' step, once every drive on this interpreter has sent its TPDO (python
        runs the drives one after another: a step computed first would delay the others)."""
        with self.lock:
            if self.due is not None:
                r, self.due = self.due, None
                self.follow(r)

    def period(self):
        """The interpolation period 0x60C2 in s (the master sets it to its cycle)."""
        v, ix = self.get(0x60C2, 1, "<B"), self.get(0x60C2, 2, "<b")
        return v * 10.0**ix if v else 0.002

    def follow(self, r):
        """One SYNC of the dynamics towards set-point r (increments), behind the delay."""
        tau, ff, delay = self.dyn
        self.cmds.append(r)
        if len(self.cmds) > delay + 2:
            del self.cmds[0]
        c1 = self.cmds[max(0, len(self.cmds) - 1 - delay)]
        c0 = self.cmds[max(0, len(self.cmds) - 2 - delay)]
        dt = self.period()
        n = 20
        h, rv = dt / n, (c1 - c0) / dt
        y, v = self.pos_inc, self.vel
        for k in range(1, n + 1):
            rk = c0 + (c1 - c0) * k / n
            a = (rk + 2 * tau * ff * rv - y - 2 * tau * v) / (tau * tau)
            v += a * h
            y += v * h
        self.pos_inc, self.vel = y, v
        self.ferr_max = max(self.ferr_max, abs(c1 - y))
        window = self.get(0x6065, 0, "<I") if 0x6065 in self.node.data_store else 0
        if window and abs(c1 - y) > window and self.state == OE:
            self.fault(0x8611)

    def on_rpdo(self, can_id, data, ts):
        with self.lock:
            need = sum((self.get(0x1600, k, "<I") & 0xFF) // 8 for k in range(1, self.get(0x1600, 0, "<B") + 1))
            if self.nmt == OP and not self.get(0x1400, 1, "<I") & 0x80000000 and len(data) >= need:
                self.rpdo = bytes(data)

    def controlword(self, cw):
        prev, self.cw, s = self.cw, cw, self.state
        if s == FAULT:
            if cw & 0x80 and not prev & 0x80:
                self.state, self.error = SOD, 0
                self.send(0x80 + self.nid, [0] * 8)
        elif cw & 0x82 == 0 or cw & 0x86 == 0x02:
            self.state = SOD
        elif cw & 0x87 == 0x06:
            self.state = RTSO
        elif cw & 0x8F == 0x07 and s in (RTSO, OE):
            self.state = SO
        elif cw & 0x8F == 0x0F and s in (RTSO, SO):
            self.state = OE
            # Hold where it is: the next target is relative to this position.
            self.target = int(round(self.pos_inc / self.inc_per_unit()))
            self.cmds, self.vel, self.step = [], 0.0, 0


def main():
    eds = shaped_eds()
    net = canopen.Network()
    net.connect(interface="socketcand", host=HOST, port=PORT, channel="can0", tcp_tune=True)
    send_lock = threading.Lock()
    time.sleep(0.05)
    drives = [Drive(net, n, a, cpr, eds, send_lock) for n, a, cpr in [(1, "x", 100000), (2, "z", 100000), (3, "s1", 360000)]]
    for d in drives:
        net.subscribe(0x80, d.after_sync)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    print("ready", flush=True)
    while not stop.is_set():
        for d in drives:
            d.tick()
        time.sleep(0.001)
    for d in drives:
        print(json.dumps({"node": d.nid, "enabled_modes": sorted(d.enabled_modes), "position": round(d.pos_inc), "position_actual": d.get(0x6064, 0, "<i"), "resets": d.resets, "syncs_sent": d.syncs_sent, "syncs_heard": d.syncs_heard, "mode": d.mode, "state": d.state, "ferr_max": round(d.ferr_max), "error": d.error}), flush=True)
    net.disconnect()
    os.unlink(eds)


if __name__ == "__main__":
    main()
