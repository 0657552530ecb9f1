#!/usr/bin/env python3
"""A Modbus master we did not write: pymodbus reads and writes the registers of
`sim-drives --modbus-tcp HOST:PORT` (the default drives, units 1, 2, 3; CiA 402 map of
cncgw-bus' Cia402Map::default()) and checks the exception codes of bad requests.

    modbus_peer.py HOST PORT      → prints "all checks passed", exit 0; else exit 1
"""
import inspect
import socket
import struct
import sys
import time

from pymodbus.client import ModbusTcpClient
from pymodbus.pdu import ExceptionResponse

CONTROLWORD, TARGET_POSITION, MODE = 0, 1, 5
STATUSWORD, MODE_DISPLAY, POSITION_ACTUAL, ERROR_CODE = 10, 11, 12, 16
INTERPOLATION_MS = 20

failures = []


def check(cond, what):
    print(("ok   " if cond else "FAIL ") + what)
    if not cond:
        failures.append(what)


def state(sw):
    """CiA 402 state from a statusword (CiA 402-2 table 30), the states used here."""
    if sw & 0x4F == 0x40:
        return "switch on disabled"
    if sw & 0x6F == 0x21:
        return "ready to switch on"
    if sw & 0x6F == 0x23:
        return "switched on"
    if sw & 0x6F == 0x27:
        return "operation enabled"
    if sw & 0x4F == 0x08:
        return "fault"
    return "other %#06x" % sw


def raw_read_exception(host, port, unit, addr, count):
    """Send FC03 as a hand-built Modbus TCP frame; the exception code of the answer, or None."""
    pdu = struct.pack(">BHH", 3, addr, count)
    frame = struct.pack(">HHHB", 0x4242, 0, len(pdu) + 1, unit) + pdu
    with socket.create_connection((host, port), timeout=2) as s:
        s.sendall(frame)
        resp = b""
        while len(resp) < 9:
            chunk = s.recv(260)
            if not chunk:
                break
            resp += chunk
    if len(resp) >= 9 and resp[0:2] == b"\x42\x42" and resp[7] == 0x83:
        return resp[8]
    return None


def main():
    host, port = sys.argv[1], int(sys.argv[2])
    c = ModbusTcpClient(host, port=port, timeout=2, retries=0)
    check(c.connect(), "connect to %s:%d" % (host, port))
    # pymodbus 3.10 renamed the unit keyword from slave= to device_id=.
    unit_kw = "device_id" if "device_id" in inspect.signature(c.read_holding_registers).parameters else "slave"

    def u(n):
        return {unit_kw: n}

    def exc(r):
        return r.exception_code if isinstance(r, ExceptionResponse) else None

    time.sleep(0.02)  # boot-up of the drives
    for unit in (1, 2, 3):
        r = c.read_holding_registers(STATUSWORD, count=7, **u(unit))
        check(not r.isError() and len(r.registers) == 7, "unit %d: FC03 statusword … error code" % unit)
        if not r.isError():
            check(state(r.registers[0]) == "switch on disabled", "unit %d: %s" % (unit, state(r.registers[0])))
            check(r.registers[6] == 0, "unit %d: error code 0" % unit)

    # FC06 controlword, FC04 reads the same map.
    check(not c.write_register(CONTROLWORD, 0x0006, **u(1)).isError(), "FC06 controlword = 6")
    r = c.read_input_registers(STATUSWORD, count=1, **u(1))
    check(not r.isError() and state(r.registers[0]) == "ready to switch on", "FC04 statusword: ready to switch on")
    # FC16: mode 8 and the interpolation period; the mode display follows.
    check(not c.write_registers(MODE, [8], **u(1)).isError(), "FC16 mode = 8")
    check(not c.write_register(INTERPOLATION_MS, 4, **u(1)).isError(), "FC06 interpolation period = 4 ms")
    r = c.read_holding_registers(MODE_DISPLAY, count=1, **u(1))
    check(not r.isError() and r.registers[0] == 8, "mode display 8")
    # FC23: enable (controlword 0x0F + the present position as target) and read back.
    r = c.read_holding_registers(POSITION_ACTUAL, count=2, **u(1))
    hi, lo = r.registers
    r = c.readwrite_registers(read_address=STATUSWORD, read_count=7, write_address=CONTROLWORD, values=[0x000F, hi, lo], **u(1))
    check(not r.isError() and state(r.registers[0]) == "operation enabled", "FC23 enable: %s" % (state(r.registers[0]) if not r.isError() else r))
    # 32-bit target, high word first: 1000 counts on.
    pos = ((hi << 16) | lo) + 1000
    pos &= 0xFFFFFFFF
    check(not c.write_registers(TARGET_POSITION, [pos >> 16, pos & 0xFFFF], **u(1)).isError(), "FC16 target position +1000")
    for _ in range(5):  # keep streaming it, as a CSP master does
        c.write_registers(CONTROLWORD, [0x000F, pos >> 16, pos & 0xFFFF], **u(1))
        time.sleep(0.004)
    time.sleep(0.3)
    r = c.read_holding_registers(POSITION_ACTUAL, count=2, **u(1))
    act = (r.registers[0] << 16) | r.registers[1]
    d = (act - pos + 0x80000000) % 0x100000000 - 0x80000000
    check(abs(d) <= 10, "position actual within 10 counts of the target (off by %d)" % d)

    # Exceptions.
    check(exc(c.read_holding_registers(6, count=1, **u(1))) == 2, "read of an unmapped register → 0x02")
    check(exc(c.read_holding_registers(0, count=24, **u(1))) == 2, "read across a gap of the map → 0x02")
    check(exc(c.write_register(STATUSWORD, 0, **u(1))) == 2, "write to the read-only statusword → 0x02")
    check(exc(c.write_register(MODE, 3, **u(1))) == 3, "mode 3 → 0x03")
    check(exc(c.write_register(INTERPOLATION_MS, 1000, **u(1))) == 3, "interpolation period 1000 ms → 0x03")
    # pymodbus will not send a read of 126 registers: the raw frame over a second connection.
    check(raw_read_exception(host, port, 1, 0, 126) == 3, "FC03 of 126 registers (raw frame) → 0x03")
    check(raw_read_exception(host, port, 1, 0, 0) == 3, "FC03 of 0 registers (raw frame) → 0x03")
    check(exc(c.read_coils(0, count=1, **u(1))) == 1, "FC01 read coils → 0x01")
    check(exc(c.read_holding_registers(STATUSWORD, count=1, **u(9))) == 0x0B, "unit 9 → 0x0B")
    r = c.read_holding_registers(ERROR_CODE, count=1, **u(1))
    check(not r.isError() and r.registers[0] == 0, "still no fault after the refused requests")
    c.close()
    if failures:
        print("%d checks failed" % len(failures))
        return 1
    print("all checks passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
