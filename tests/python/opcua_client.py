"""The OPC UA peer we did not write: python asyncua against `cncgw run`'s server.

    opcua_client.py URL PKI_DIR WORK_DIR USER PASSWORD MACHINE_NAME
    opcua_client.py --user-certs WORK_DIR     (before the run: the X.509 users' certificates)

Run by tests/cli/opcua_server.rs while `cncgw run --realtime` runs a program on the embedded
machine whose X drive faults. In order:
  1. an unsigned (None) connection is refused (no such endpoint);
  2. Basic256Sha256 Sign&Encrypt with a fresh client certificate is refused until the
     certificate is moved from PKI_DIR/rejected to PKI_DIR/trusted (the administrator's step);
  3. a wrong password is refused; an X.509 user certificate that is not configured is
     refused, the configured one (WORK_DIR/cell_user.der, user "cell") signs in;
  4. with the right one: browse the machine, read identification, subscribe to the Z axis'
     actual position, the machine state and the alarm events (as a generic client takes them,
     BaseEventType, and filtered on our condition type CncAlarmConditionType), until the alarm;
  5. a second client, connecting after the alarm, calls ConditionRefresh and receives the
     condition (still active, unacknowledged); acknowledging it is refused (read-only); it
     browses to the condition's node (Notification/Messages, and HasCondition from the
     machine) and reads its ActiveState and AlarmNumber.
Prints one JSON object on stdout with what it saw.
"""

import asyncio
import json
import math
import shutil
import socket
import sys
import time
from pathlib import Path

from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID

APP_URI = "urn:cncgw-test:opcua-client"
NS = "urn:cncgw:machine-tool"


def log(*a):
    print(*a, file=sys.stderr, flush=True)


def wait_for_port(url, seconds=60):
    host, port = url.split("//", 1)[1].rstrip("/").rsplit(":", 1)
    end = time.time() + seconds
    while time.time() < end:
        try:
            socket.create_connection((host, int(port)), timeout=0.5).close()
            return
        except OSError:
            time.sleep(0.05)
    raise SystemExit(f"nothing listens on {url}")


async def make_cert():
    key, cert = Path(WORK) / "client_key.pem", Path(WORK) / "client_cert.der"
    await setup_self_signed_certificate(key, cert, APP_URI, socket.gethostname(), [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "cncgw-test-client"})
    return cert, key


async def make_user_certs(work):
    """The X.509 user identities: "cell" (configured in the test's [[opcua.users]]) and
    "stranger" (not), each a self-signed certificate with its key (asyncua's generator)."""
    for who in ("cell", "stranger"):
        await setup_self_signed_certificate(Path(work) / f"{who}_user_key.pem", Path(work) / f"{who}_user.der", f"urn:cncgw-test:user:{who}",
                                            socket.gethostname(), [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": f"cncgw-test-user-{who}"})


async def cert_user_client(cert, key, who):
    """Sign&Encrypt with the application certificate, and as identity the user certificate
    WORK/<who>_user.der, the token signed with its key."""
    c = Client(URL, timeout=5)
    c.application_uri = APP_URI
    await c.set_security(SecurityPolicyBasic256Sha256, str(cert), str(key), mode=ua.MessageSecurityMode.SignAndEncrypt)
    await c.load_client_certificate(str(Path(WORK) / f"{who}_user.der"))
    await c.load_private_key(Path(WORK) / f"{who}_user_key.pem")
    return c


async def secure_client(cert, key, user, password):
    c = Client(URL, timeout=5)
    c.application_uri = APP_URI
    await c.set_security(SecurityPolicyBasic256Sha256, str(cert), str(key), mode=ua.MessageSecurityMode.SignAndEncrypt)
    c.set_user(user)
    c.set_password(password)
    return c


async def refused(client):
    """The error connecting, or None if it connected (then disconnected)."""
    try:
        await client.connect()
    except Exception as e:  # noqa: BLE001 - any refusal counts, its name is reported
        return f"{type(e).__name__}: {e}"
    await client.disconnect()
    return None


class Handler:
    def __init__(self):
        self.t0 = time.time()
        self.changes = []
        self.events = []

    def datachange_notification(self, node, val, data):
        if isinstance(val, float) and math.isnan(val):
            val = None  # (Spindle1/Load before the drive's first answer; JSON has no NaN)
        self.changes.append({"node": node.nodeid.to_string(), "value": val, "t": round(time.time() - self.t0, 3)})

    def event_notification(self, event):
        f = event.get_event_props_as_fields_dict()
        self.events.append({k: text_or_value(v.Value) for k, v in f.items() if k in FIELDS})


# The event fields the test looks at (asyncua names nested ones "ActiveState/Id").
FIELDS = ("Message", "Severity", "AlarmNumber", "SourceName", "EventType", "ActiveState", "ActiveState/Id", "AckedState/Id", "Retain",
          "ConditionName", "EventId", "NodeId")


def text_or_value(v):
    if isinstance(v, ua.LocalizedText):
        return v.Text
    if isinstance(v, ua.NodeId):
        return v.to_string()
    if isinstance(v, bytes):
        return v.hex()
    return v


def condition_filter(of_type, ns):
    """An event filter for alarm conditions: the fields by browse path (BaseEventType as type,
    as the standard allows) and OfType as where clause. (asyncua's own filter for a type does
    not work against async-opcua 0.19: its where clause, InList on EventType, compares NodeIds,
    which async-opcua's content filter cannot; and its core namespace returns inverse
    HasSubtype references twice, on which asyncua's walk up the type tree gives up.)"""
    f = ua.EventFilter()
    for path in ("EventId", "EventType", "SourceName", "Message", "Severity", "Time", "ConditionName", "Retain", "ActiveState",
                 "ActiveState/Id", "AckedState/Id", f"{ns}:AlarmNumber"):
        op = ua.SimpleAttributeOperand()
        op.TypeDefinitionId = ua.NodeId(ua.ObjectIds.BaseEventType)
        op.AttributeId = ua.AttributeIds.Value
        op.BrowsePath = [ua.QualifiedName.from_string(p) for p in path.split("/")]
        f.SelectClauses.append(op)
    cid = ua.SimpleAttributeOperand()
    cid.TypeDefinitionId = ua.NodeId(ua.ObjectIds.ConditionType)
    cid.AttributeId = ua.AttributeIds.NodeId
    f.SelectClauses.append(cid)
    el = ua.ContentFilterElement()
    el.FilterOperator = ua.FilterOperator.OfType
    el.FilterOperands.append(ua.LiteralOperand(Value=ua.Variant(of_type)))
    f.WhereClause.Elements.append(el)
    return f


async def late_client(cert, key, ns):
    """5. Connect after the alarm: ConditionRefresh brings the retained condition."""
    out = {}
    client = await secure_client(cert, key, USER, PASSWORD)
    await client.connect()
    try:
        h = Handler()
        sub = await client.create_subscription(100, h)
        # A generic alarms & conditions client: AlarmConditionType, default queue size (the
        # server spaces the refresh's events one per publishing interval).
        await sub.subscribe_events(client.nodes.server, evfilter=condition_filter(ua.NodeId(ua.ObjectIds.AlarmConditionType), ns))
        await asyncio.sleep(0.3)
        out["before_refresh"] = list(h.events)
        cond_type = client.get_node(ua.NodeId(ua.ObjectIds.ConditionType))
        await cond_type.call_method(ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh), ua.Variant(sub.subscription_id, ua.VariantType.UInt32))
        end = time.time() + 5
        while time.time() < end and not h.events:
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.3)
        out["refreshed"] = h.events
        try:
            await cond_type.call_method(ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh), ua.Variant(987654, ua.VariantType.UInt32))
            out["refresh_bad_subscription"] = None
        except Exception as e:  # noqa: BLE001
            out["refresh_bad_subscription"] = f"{type(e).__name__}: {e}"
        out["condition_node"] = await condition_node(client, ns)
        if h.events:
            ev = h.events[0]
            cond = client.get_node(ua.NodeId.from_string(ev["NodeId"]))
            try:
                await cond.call_method(ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge),
                                       ua.Variant(bytes.fromhex(ev["EventId"]), ua.VariantType.ByteString), ua.LocalizedText("seen"))
                out["ack_refused"] = None
            except Exception as e:  # noqa: BLE001
                out["ack_refused"] = f"{type(e).__name__}: {e}"
    finally:
        try:
            await client.disconnect()
        except Exception:  # noqa: BLE001
            pass
    return out


async def condition_node(client, ns):
    """The alarm's condition as a node: in Notification/Messages, and HasCondition from the
    machine; its type, ActiveState (and Id), AlarmNumber, Retain."""
    machine = await client.nodes.objects.get_child([f"{ns}:Machines", f"{ns}:{MACHINE}"])
    messages = await machine.get_child([f"{ns}:Notification", f"{ns}:Messages"])
    found = await messages.get_children()
    out = {"in_messages": [n.nodeid.to_string() for n in found]}
    refs = await machine.get_referenced_nodes(refs=ua.ObjectIds.HasCondition, direction=ua.BrowseDirection.Forward)
    out["has_condition"] = [n.nodeid.to_string() for n in refs]
    if found:
        cond = found[0]
        out["browse_name"] = (await cond.read_browse_name()).to_string()
        out["type"] = (await cond.read_type_definition()).to_string()
        active = await cond.get_child("0:ActiveState")
        out["ActiveState"] = (await active.read_value()).Text
        out["ActiveState/Id"] = await (await active.get_child("0:Id")).read_value()
        out["AlarmNumber"] = await (await cond.get_child(f"{ns}:AlarmNumber")).read_value()
        out["Retain"] = await (await cond.get_child("0:Retain")).read_value()
        out["Message"] = (await (await cond.get_child("0:Message")).read_value()).Text
    return out


async def main():
    out = {}
    wait_for_port(URL)
    # 1. No None endpoint: an unsigned connection is refused.
    c = Client(URL, timeout=5)
    c.set_user(USER)
    c.set_password(PASSWORD)
    out["none_refused"] = await refused(c)
    cert, key = await make_cert()
    # 2. An unknown client certificate is refused, and lands in rejected/.
    out["untrusted_refused"] = await refused(await secure_client(cert, key, USER, PASSWORD))
    rejected = list((Path(PKI) / "rejected").glob("*.der"))
    out["rejected_files"] = len(rejected)
    (Path(PKI) / "trusted").mkdir(parents=True, exist_ok=True)
    for f in rejected:
        shutil.move(str(f), str(Path(PKI) / "trusted" / f.name))
    # 3. Trusted now, but a wrong password.
    out["wrong_password_refused"] = await refused(await secure_client(cert, key, USER, PASSWORD + "x"))
    # 3b. X.509 user identities: an unknown certificate is refused, the configured one is in.
    out["unknown_user_cert_refused"] = await refused(await cert_user_client(cert, key, "stranger"))
    try:
        c = await cert_user_client(cert, key, "cell")
        await c.connect()
        ns = await c.get_namespace_index(NS)
        out["cert_user_state"] = await c.get_node(ua.NodeId("Monitoring.MachineTool.MachineState", ns)).read_value()
        await c.disconnect()
    except Exception as e:  # noqa: BLE001 - reported, the test says what it expected
        out["cert_user_state"] = None
        out["cert_user_error"] = f"{type(e).__name__}: {e}"
    # 4. The right one.
    client = await secure_client(cert, key, USER, PASSWORD)
    await client.connect()
    ns = await client.get_namespace_index(NS)
    machine = await client.nodes.objects.get_child([f"{ns}:Machines", f"{ns}:{MACHINE}"])
    out["machine_children"] = sorted([(await n.read_browse_name()).Name for n in await machine.get_children()])
    out["axes"] = sorted([(await n.read_browse_name()).Name for n in await (await machine.get_child(f"{ns}:Axes")).get_children()])
    ident = await machine.get_child(f"{ns}:Identification")
    out["identification"] = {(await n.read_browse_name()).Name: await n.read_value() for n in await ident.get_children()}
    state = await machine.get_child([f"{ns}:Monitoring", f"{ns}:MachineTool", f"{ns}:MachineState"])
    z = await machine.get_child([f"{ns}:Axes", f"{ns}:Z", f"{ns}:ActualPosition"])
    load = await machine.get_child([f"{ns}:Monitoring", f"{ns}:Spindle1", f"{ns}:Load"])
    program = await machine.get_child([f"{ns}:Production", f"{ns}:ActiveProgram", f"{ns}:Name"])
    out["program"] = await program.read_value()
    out["state_at_connect"] = await state.read_value()
    try:
        await z.write_value(ua.DataValue(ua.Variant(1.0, ua.VariantType.Double)))
        out["write_refused"] = None
    except Exception as e:  # noqa: BLE001
        out["write_refused"] = f"{type(e).__name__}: {e}"
    h = Handler()
    sub = await client.create_subscription(100, h)
    await sub.subscribe_data_change([z, state, load])
    cnc_alarm = client.get_node(ua.NodeId("CncAlarmConditionType", ns))
    # The events as a generic client takes them (BaseEventType on the Server object) and
    # filtered by our condition type (CncAlarmConditionType: AlarmConditionType's fields and
    # AlarmNumber), on the machine object.
    await sub.subscribe_events(client.nodes.server)
    h2 = Handler()
    sub2 = await client.create_subscription(100, h2)
    await sub2.subscribe_events(machine, evfilter=condition_filter(cnc_alarm.nodeid, ns), queuesize=10)
    # Until the server goes away after the run (linger), at most 60 s.
    end = time.time() + 60
    try:
        while time.time() < end:
            await asyncio.sleep(0.2)
            try:
                await client.check_connection()
            except Exception:  # noqa: BLE001 - the server closed: the run is over
                break
            if h.events and h2.events and any(c["value"] in ("Alarm", "EStop") for c in h.changes):
                await asyncio.sleep(0.5)
                break
    finally:
        try:
            await client.disconnect()
        except Exception:  # noqa: BLE001
            pass
    out["changes"] = h.changes
    out["events"] = h.events
    out["typed_events"] = h2.events
    if h.events:
        out["late"] = await late_client(cert, key, ns)
    print(json.dumps(out, default=str), flush=True)


if sys.argv[1] == "--user-certs":
    asyncio.run(make_user_certs(sys.argv[2]))
else:
    URL, PKI, WORK, USER, PASSWORD, MACHINE = sys.argv[1:7]
    asyncio.run(main())
