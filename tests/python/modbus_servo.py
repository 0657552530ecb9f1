#!/usr/bin/env python3
"""Three CiA 402 servos on Modbus TCP built by someone else from docs/MODBUS_MAPS.md (the
`cia402` map, its defaults), on pymodbus' simulator device: register store, framing and
exception answers are pymodbus', the drive behind them is this file's, not sim-drives'.

- The CiA 402 state machine on the controlword, 20 ms per transition (switch-on delays).
- Mode 8 (cyclic synchronous position): each target written is reached linearly over the
  interpolation period (register 20, ms) from its receipt; a late target holds the last
  one. The motor follows the demand with a first-order lag (15 ms feed axes, 60 ms
  spindle); |demand - actual| above the window (register 21) faults with 0x8611.
- Mode 9 (cyclic synchronous velocity): the motor follows the target velocity (register 3,
  counts/s) with the same lag; no following-error watch (a speed mode has none).
- Every mode written and every fault is printed, one line each, for the test to read.

Usage: modbus_servo.py PORT
"""
import asyncio
import functools
import sys
import time

from pymodbus.server import StartAsyncTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

CW, TPOS, TVEL, MODE, SW, MODE_DISP, PACT, VACT, ERR, IPO, WINDOW, WD = 0, 1, 3, 5, 10, 11, 12, 14, 16, 20, 21, 23
SIZE = 24
TAU = {1: 0.015, 2: 0.015, 3: 0.060}
STEP = 0.0005


def i32(hi, lo):
    v = (hi << 16) | lo
    return v - (1 << 32) if v & 0x8000_0000 else v


def split(v):
    v = int(round(v)) & 0xFFFF_FFFF
    return [v >> 16, v & 0xFFFF]


class Servo:
    def __init__(self, unit):
        self.unit = unit
        self.state = "disabled"
        self.pending = None  # (state, when)
        self.mode = 0
        self.t = time.monotonic()
        self.pos = 0.0
        self.vel = 0.0
        self.seg = None  # (from, to, t0, period)
        self.error = 0
        self.statusword = 0x0040

    def step_to(self, now, regs):
        while self.t + STEP <= now:
            self.t += STEP
            self.physics(regs)
        if self.pending and now >= self.pending[1]:
            self.state, self.pending = self.pending[0], None

    def demand(self):
        if not self.seg:
            return self.pos
        a, b, t0, period = self.seg
        u = min(max((self.t - t0) / period, 0.0), 1.0)
        return a + (b - a) * u

    def physics(self, regs):
        tau = TAU[self.unit]
        if self.state != "enabled":
            self.vel += (0.0 - self.vel) * STEP / tau
        elif self.mode == 9:
            self.vel += (i32(regs[TVEL], regs[TVEL + 1]) - self.vel) * STEP / tau
        elif self.mode == 8:
            d = self.demand()
            # A position loop with velocity feed-forward: the lag of a first-order system.
            ff = 0.0
            if self.seg:
                a, b, _, period = self.seg
                ff = (b - a) / period if self.t < self.seg[2] + period else 0.0
            self.vel += (ff + (d - self.pos) / tau - self.vel) * STEP / (tau / 4)
            window = i32(regs[WINDOW], regs[WINDOW + 1])
            if window > 0 and abs(d - self.pos) > window:
                print(f"unit {self.unit}: fault 0x8611 following error {d - self.pos:.0f} > {window}", flush=True)
                self.state, self.error = "fault", 0x8611
        self.pos += self.vel * STEP

    def controlword(self, cw, now):
        nxt = None
        if self.state == "fault":
            if cw & 0x80:
                self.state, self.error = "disabled", 0
            return
        if cw & 0x02 == 0:
            self.state, self.pending = "disabled", None
            return
        if cw & 0x04 == 0:
            nxt = "quickstop" if self.state == "enabled" else "disabled"
        elif cw & 0x0F == 0x06:
            nxt = "ready"
        elif cw & 0x0F == 0x07:
            nxt = "switched_on" if self.state in ("ready", "switched_on", "enabled") else None
        elif cw & 0x0F == 0x0F:
            nxt = "enabled" if self.state in ("switched_on", "enabled") else None
        if nxt and nxt != self.state and not (self.pending and self.pending[0] == nxt):
            if nxt == "enabled":
                self.seg = None
            self.pending = (nxt, now + 0.020)

    def sw(self):
        return {
            "disabled": 0x0040,
            "ready": 0x0021,
            "switched_on": 0x0023,
            "enabled": 0x1427,
            "quickstop": 0x0007,
            "fault": 0x0008,
        }[self.state]


SERVOS = {u: Servo(u) for u in (1, 2, 3)}


async def action(unit, function_code, start_address, address, count, regs, values):
    s = SERVOS[unit]
    now = time.monotonic()
    s.step_to(now, regs)
    if values:
        for k, v in enumerate(values):
            regs[address - start_address + k] = v
        written = range(address, address + count)
        if MODE in written and regs[MODE] != s.mode:
            s.mode = regs[MODE]
            s.seg = None
            print(f"unit {unit}: mode {s.mode}", flush=True)
        if TPOS + 1 in written and s.mode == 8 and s.state == "enabled":
            period = max(regs[IPO], 1) * 1e-3
            s.seg = (s.demand(), i32(regs[TPOS], regs[TPOS + 1]), now, period)
        if CW in written:
            s.controlword(regs[CW], now)
    regs[SW] = s.sw()
    regs[MODE_DISP] = s.mode
    regs[PACT : PACT + 2] = split(s.pos)
    regs[VACT : VACT + 2] = split(s.vel)
    regs[ERR] = s.error
    return None


async def main() -> None:
    port = int(sys.argv[1])
    data = [SimData(address=0, count=SIZE, values=0, datatype=DataType.REGISTERS)]
    devices = [SimDevice(id=u, simdata=data, action=functools.partial(action, u)) for u in SERVOS]
    print(f"listening on 127.0.0.1:{port}", flush=True)
    await StartAsyncTcpServer(devices, address=("127.0.0.1", port))


asyncio.run(main())
