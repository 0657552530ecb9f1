"""N asyncua clients subscribed to a cncgw OPC UA server, for examples/opcua_cost.rs.

    opcua_clients.py URL N SECONDS MACHINE_NAME

Each client (its own session, anonymous, policy None: the example's server allows it on
loopback) makes a subscription at 100 ms publishing with the machine state, every axis'
commanded and actual position and following error, the spindle's speeds and load, the
program's line and progress, and the alarm events; prints "subscribed" once all are, then
after SECONDS the notifications each received, as JSON, and leaves.
"""

import asyncio
import json
import sys

from asyncua import Client, ua

URL, N, SECONDS, MACHINE = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
NS = "urn:cncgw:machine-tool"


class Count:
    def __init__(self):
        self.n = 0

    def datachange_notification(self, node, val, data):
        self.n += 1

    def event_notification(self, event):
        self.n += 1


async def one(k):
    c = Client(URL, timeout=10)
    await c.connect()
    ns = await c.get_namespace_index(NS)
    m = await c.nodes.objects.get_child([f"{ns}:Machines", f"{ns}:{MACHINE}"])
    nodes = [await m.get_child([f"{ns}:Monitoring", f"{ns}:MachineTool", f"{ns}:MachineState"])]
    for v in ("RotationSpeed", "CommandedSpeed", "Load"):
        nodes.append(await m.get_child([f"{ns}:Monitoring", f"{ns}:Spindle1", f"{ns}:{v}"]))
    for v in ("Line", "Progress"):
        nodes.append(await m.get_child([f"{ns}:Production", f"{ns}:ActiveProgram", f"{ns}:{v}"]))
    for ax in await (await m.get_child(f"{ns}:Axes")).get_children():
        for v in ("CommandedPosition", "ActualPosition", "FollowingError"):
            nodes.append(await ax.get_child(f"{ns}:{v}"))
    h = Count()
    sub = await c.create_subscription(100, h)
    await sub.subscribe_data_change(nodes)
    await sub.subscribe_events(c.nodes.server)
    return c, h, len(nodes)


async def main():
    clients = await asyncio.gather(*(one(k) for k in range(N)))
    print("subscribed", flush=True)
    await asyncio.sleep(SECONDS)
    out = {"clients": N, "items_each": clients[0][2], "notifications": [h.n for _, h, _ in clients]}
    for c, _, _ in clients:
        try:
            await c.disconnect()
        except Exception:  # noqa: BLE001
            pass
    print(json.dumps(out), flush=True)


asyncio.run(main())
