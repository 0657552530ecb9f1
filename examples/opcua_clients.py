"""N asyncua clients subscribed to a cncgw OPC UA server, for examples/opcua_cost.rs.

    opcua_clients.py URL N SECONDS MACHINE_NAME [PKI_DIR]

Each client (its own session, anonymous; policy None, which the example's server allows on
loopback, or with PKI_DIR Basic256Sha256 Sign&Encrypt: one client certificate, made here,
refused once and moved from PKI_DIR/rejected to PKI_DIR/trusted, for all) makes a subscription at 100 ms publishing with the machine state, every axis'
commanded and actual position and following error, the spindle's speeds and load, the
program's line and progress, and the alarm events; prints "subscribed" once all are, then
after SECONDS the notifications each received, as JSON, and leaves.
"""

import asyncio
import json
import shutil
import socket
import sys
import tempfile
from pathlib import Path

from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID

URL, N, SECONDS, MACHINE = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
PKI = sys.argv[5] if len(sys.argv) > 5 else None
NS = "urn:cncgw:machine-tool"
APP_URI = "urn:cncgw-example:opcua-clients"


async def trusted_cert(work):
    """A client certificate the server trusts (copied into PKI/trusted: the administrator's step)."""
    key, cert = Path(work) / "key.pem", Path(work) / "cert.der"
    await setup_self_signed_certificate(key, cert, APP_URI, socket.gethostname(), [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "cncgw-cost-client"})
    # As an administrator does: the first attempt is refused and leaves the certificate in
    # PKI/rejected; move it to PKI/trusted (tests/python/opcua_client.py does the same).
    try:
        await (await one_client(cert, key)).connect()
    except Exception:  # noqa: BLE001 - refused, as expected
        pass
    (Path(PKI) / "trusted").mkdir(parents=True, exist_ok=True)
    for f in (Path(PKI) / "rejected").glob("*.der"):
        shutil.move(str(f), str(Path(PKI) / "trusted" / f.name))
    return cert, key


async def one_client(cert, key):
    c = Client(URL, timeout=10)
    c.application_uri = APP_URI
    await c.set_security(SecurityPolicyBasic256Sha256, str(cert), str(key), mode=ua.MessageSecurityMode.SignAndEncrypt)
    return c


class Count:
    def __init__(self):
        self.n = 0

    def datachange_notification(self, node, val, data):
        self.n += 1

    def event_notification(self, event):
        self.n += 1


async def one(k, secure):
    c = await one_client(*secure) if secure else Client(URL, timeout=10)
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
    work = tempfile.mkdtemp(prefix="cncgw_opcua_clients_")
    secure = await trusted_cert(work) if PKI else None
    clients = await asyncio.gather(*(one(k, secure) for k in range(N)))
    shutil.rmtree(work, ignore_errors=True)
    print("subscribed", flush=True)
    await asyncio.sleep(SECONDS)
    out = {"clients": N, "policy": "Basic256Sha256 SignAndEncrypt" if PKI else "None", "items_each": clients[0][2], "notifications": [h.n for _, h, _ in clients]}
    for c, _, _ in clients:
        try:
            await c.disconnect()
        except Exception:  # noqa: BLE001
            pass
    print(json.dumps(out), flush=True)


asyncio.run(main())
