#!/usr/bin/env python3
"""A Modbus TCP drive built by someone else from docs/MODBUS_MAPS.md, with only some of the
cia402 map's registers: pymodbus' simulator device (its own register store and exception
answers, not ours), for `cncgw config check --bus` to find the ones missing.

Usage: modbus_drive.py PORT UNITS [MISSING...]
  UNITS   unit ids, comma-separated ("1,2,3")
  MISSING names of cia402 map registers the drive does not have (answered 0x02)
"""
import asyncio
import sys

from pymodbus.server import StartAsyncTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

# The default cia402 map of docs/MODBUS_MAPS.md: name -> (address, registers).
CIA402 = {
    "controlword": (0, 1),
    "target_position": (1, 2),
    "target_velocity": (3, 2),
    "mode": (5, 1),
    "statusword": (10, 1),
    "mode_display": (11, 1),
    "position_actual": (12, 2),
    "velocity_actual": (14, 2),
    "error_code": (16, 1),
    "interpolation_ms": (20, 1),
    "following_error_window": (21, 2),
    "comm_timeout_ms": (23, 1),
    "homing_method": (24, 1),
    "home_offset": (25, 2),
    "homing_switch_speed": (27, 2),
    "homing_zero_speed": (29, 2),
    "homing_accel": (31, 2),
    "digital_inputs": (33, 2),
}


async def main() -> None:
    port = int(sys.argv[1])
    units = [int(u) for u in sys.argv[2].split(",")]
    missing = set(sys.argv[3:])
    unknown = missing - CIA402.keys()
    if unknown:
        sys.exit(f"unknown register names: {sorted(unknown)}")
    data = [
        SimData(address=a, count=n, values=0, datatype=DataType.REGISTERS)
        for name, (a, n) in sorted(CIA402.items(), key=lambda kv: kv[1][0])
        if name not in missing
    ]
    devices = [SimDevice(id=u, simdata=data) for u in units]
    print(f"listening on 127.0.0.1:{port}, units {units}, missing {sorted(missing)}", flush=True)
    await StartAsyncTcpServer(devices, address=("127.0.0.1", port))


asyncio.run(main())
