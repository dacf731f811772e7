"""OPC UA server with a real asyncua client over TCP, Basic256Sha256 Sign & Encrypt."""

import asyncio
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from test_runtime_support import free_port, secure_client


async def trusted_client(url, state, trust_dir, user=None, password=None):
    """A secure client whose certificate was first put in the server's trust list."""
    from fbgcomp.runtime.trust import add_certificate

    client = await secure_client(url, state, user, password)
    add_certificate(state / "client_cert.der", trust_dir)
    return client


@pytest.fixture()
def server_factory(tmp_path, monkeypatch):
    import fbgcomp_testing

    fbgcomp_testing.require("asyncua")
    from fbgcomp.runtime.outputs.opcua import OpcUaConfig, OpcUaServer

    started = []

    def make(allow_anonymous=False, on_reload=None, main_loop=None, models_dir=None, eu_ranges=None):
        monkeypatch.setenv("FBGCOMP_OPCUA_USER", "operator")
        monkeypatch.setenv("FBGCOMP_OPCUA_PASSWORD", "s3cret-for-test")
        port = free_port()
        cfg = OpcUaConfig(
            endpoint=f"opc.tcp://127.0.0.1:{port}/fbgcomp/",
            rate_hz=0,
            allow_anonymous=allow_anonymous,
            state_dir=str(tmp_path / "state"),
            models_dir=None if models_dir is None else str(models_dir),
        )
        srv = OpcUaServer(
            cfg, ["S1", "S2"], "model-abc", on_reload=on_reload, main_loop=main_loop, eu_ranges=eu_ranges
        )
        srv.start()
        started.append(srv)
        return srv, cfg.endpoint

    yield make
    for s in started:
        s.stop()


def TRUSTED(tmp_path):
    """The trust list of the fixture's server (the default under its state folder)."""
    return tmp_path / "state" / "opcua" / "trusted"


def _snapshot(i, t):
    from fbgcomp.runtime.outputs.opcua import Snapshot

    return Snapshot(
        sample_time_s=t,
        correction_um=(-1.0 * i, 2.0 * i, 0.5),
        deviation_um=(i, -2.0 * i, -0.5),
        half_width_um=(0.1, 0.2, 0.3),
        expected_rms_um=(0.05, 0.05, 0.05),
        health="OK",
        fallback="",
        alarm=False,
        sensor_status=["OK", "MISSING"],
        sensor_wavelength_nm=[1530.0, float("nan")],
        source_status="connected",
        frames=i,
    )


def _node(client, name):
    from asyncua import ua

    return client.get_node(ua.NodeId(f"FbgComp.{name}", 2))


def test_subscribed_client_receives_published_values(server_factory, tmp_path):
    srv, url = server_factory()
    assert (tmp_path / "state" / "opcua" / "server_cert.der").is_file()

    async def main():
        client = await trusted_client(
            url, tmp_path / "client", TRUSTED(tmp_path), "operator", "s3cret-for-test"
        )
        received = []

        class Handler:
            def datachange_notification(self, node, val, data):
                received.append((node.nodeid.Identifier, val))

        async with client:
            ns = await client.get_namespace_index("urn:fbgcomp:runtime")
            assert ns == 2
            assert client.security_policy.Mode.name == "SignAndEncrypt"
            sub = await client.create_subscription(0, Handler())
            await sub.subscribe_data_change([_node(client, "CorrectionX_um"), _node(client, "SampleTime")])
            await asyncio.sleep(0.3)
            for i in range(1, 6):
                srv.publish(_snapshot(i, time.time()))
                await asyncio.sleep(0.05)
            end = time.monotonic() + 5
            while time.monotonic() < end and not any(
                v == -5.0 for n, v in received if n == "FbgComp.CorrectionX_um"
            ):
                await asyncio.sleep(0.05)
            assert await _node(client, "Sensors.S2.Status").read_value() == "MISSING"
            assert await _node(client, "ModelId").read_value() == "model-abc"
            assert await _node(client, "CorrectionY_um").read_value() == 10.0
            assert await _node(client, "IntervalHalfWidthZ_um").read_value() == 0.3
            assert await _node(client, "Health").read_value() == "OK"
        return received

    received = asyncio.run(main())
    xs = [v for n, v in received if n == "FbgComp.CorrectionX_um"]
    assert -5.0 in xs and xs == sorted(xs, reverse=True)
    assert any(n == "FbgComp.SampleTime" for n, _ in received)


def test_anonymous_refused_unless_configured_and_wrong_password_refused(server_factory, tmp_path):
    from asyncua import ua

    _srv, url = server_factory(allow_anonymous=False)

    async def main():
        # trusted machines: what refuses them here is the user, not the certificate
        anon = await trusted_client(url, tmp_path / "c1", TRUSTED(tmp_path))
        with pytest.raises(ua.UaError, match=r"BadIdentityToken|BadUserAccessDenied"):
            async with anon:
                pass
        bad = await trusted_client(url, tmp_path / "c2", TRUSTED(tmp_path), "operator", "wrong")
        with pytest.raises(ua.UaError, match=r"BadIdentityToken|BadUserAccessDenied"):
            async with bad:
                pass

    asyncio.run(main())


def test_no_unencrypted_endpoint(server_factory, tmp_path):
    from asyncua import Client, ua

    _srv, url = server_factory(allow_anonymous=True)

    async def main():
        client = Client(url, timeout=5)  # SecurityPolicy None
        endpoints = await client.connect_and_get_server_endpoints()
        assert {e.SecurityPolicyUri.rsplit("#", 1)[-1] for e in endpoints} == {"Basic256Sha256"}
        assert {e.SecurityMode.name for e in endpoints} == {"SignAndEncrypt"}
        # the client finds no endpoint without security and refuses before sending anything
        with pytest.raises(ua.UaError, match="No matching endpoints"):
            async with client:
                await _node(client, "CorrectionX_um").read_value()

    asyncio.run(main())


def test_unauthenticated_writes_and_calls_are_refused(server_factory, tmp_path):
    from asyncua import ua

    reloads = []
    models = tmp_path / "models"
    models.mkdir()
    (models / "new.json").write_text("{}")

    async def main():
        loop = asyncio.get_running_loop()

        async def on_reload(path):
            reloads.append(path)
            return f"loaded {os.path.basename(path)}"

        srv, url = server_factory(
            allow_anonymous=True, on_reload=on_reload, main_loop=loop, models_dir=models
        )
        anon = await trusted_client(url, tmp_path / "anon", TRUSTED(tmp_path))
        async with anon:
            assert await _node(anon, "Enabled").read_value() is True  # reading is fine
            with pytest.raises(ua.UaStatusCodeError) as e:
                await _node(anon, "Enabled").write_value(False)
            assert "BadUserAccessDenied" in type(e.value).__name__ + str(e.value)
            root = anon.get_node(ua.NodeId("FbgComp", 2))
            with pytest.raises(ua.UaStatusCodeError):
                await root.call_method(ua.NodeId("FbgComp.ReloadModel", 2), "x.json")
        assert srv.enabled is True and reloads == []

        op = await trusted_client(url, tmp_path / "op", TRUSTED(tmp_path), "operator", "s3cret-for-test")
        async with op:
            with pytest.raises(ua.UaStatusCodeError):  # read-only value, even for a user
                await _node(op, "CorrectionX_um").write_value(1.0)
            await _node(op, "Enabled").write_value(False)
            root = op.get_node(ua.NodeId("FbgComp", 2))
            answer = await root.call_method(ua.NodeId("FbgComp.ReloadModel", 2), "new.json")
            assert answer == "loaded new.json"
            srv.publish(_snapshot(1, time.time()))  # wakes the server's loop
            end = time.monotonic() + 3
            while srv.enabled and time.monotonic() < end:
                await asyncio.sleep(0.05)
        assert srv.enabled is False and reloads == [str((models / "new.json").resolve())]

    asyncio.run(main())


def test_control_messages_are_not_dropped_when_snapshots_are():
    """A lagging OPC UA process may lose snapshots (the newest wins) but never an Enabled switch."""
    import pickle
    import socket
    import threading
    import time

    from fbgcomp.runtime.outputs.opcua import send_control

    parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        filled = 0
        while True:  # the buffer is full: a snapshot would now be dropped
            try:
                parent.send(pickle.dumps(("snap", filled)), socket.MSG_DONTWAIT)
                filled += 1
            except BlockingIOError:
                break
        assert filled > 0
        assert send_control(parent, ("set_enabled", False), timeout_s=0.2) is False  # reported

        received = []

        def drain_slowly():
            time.sleep(0.3)
            while True:
                kind, payload = pickle.loads(child.recv(1 << 16))
                received.append((kind, payload))
                if kind == "set_enabled":
                    return

        reader = threading.Thread(target=drain_slowly)
        reader.start()
        assert send_control(parent, ("set_enabled", False), timeout_s=5.0) is True
        reader.join(5.0)
        assert received[-1] == ("set_enabled", False)
        assert len(received) == filled + 1
    finally:
        parent.close()
        child.close()


# --------------------------------------------------------------------------- issue 13, finding 6
def _fbgcomp(*args):
    """The real command line, in a process of its own: (exit code, stdout, stderr)."""
    p = subprocess.run(
        [sys.executable, "-m", "fbgcomp", *map(str, args)], capture_output=True, text=True, timeout=120
    )
    return p.returncode, p.stdout, p.stderr


def test_unknown_client_certificate_is_refused_until_trust_add(server_factory, tmp_path):
    """Before: with no trusted_clients_dir every certificate was accepted, so a right password
    from any machine was enough. Now the machine must be in the trust list too."""
    from asyncua import ua

    _srv, url = server_factory()
    state = tmp_path / "state"

    async def connect(folder):
        client = await secure_client(url, folder, "operator", "s3cret-for-test")
        async with client:
            return await _node(client, "ModelId").read_value()

    async def refused(folder):
        with pytest.raises(ua.UaError, match="BadCertificateUntrusted"):
            await connect(folder)

    asyncio.run(refused(tmp_path / "stranger"))
    # the refused certificate is kept for the administrator, who trusts it with the CLI
    kept = sorted((state / "opcua" / "rejected").glob("*.der"))
    assert len(kept) == 1
    assert kept[0].read_bytes() == (tmp_path / "stranger" / "client_cert.der").read_bytes()
    code, out, err = _fbgcomp("trust", "list", "--state-dir", state)
    assert code == 0 and "(0 certificate(s))" in out
    code, out, err = _fbgcomp("trust", "add", kept[0], "--state-dir", state)
    assert code == 0, err
    assert out.startswith("trusted: ") and "urn:fbgcomp:test:client" in out
    # the running server reads the changed trust list at the next connection: no restart
    assert asyncio.run(connect(tmp_path / "stranger")) == "model-abc"
    code, out, _ = _fbgcomp("trust", "list", "--state-dir", state)
    assert "(1 certificate(s))" in out and "urn:fbgcomp:test:client" in out
    # another machine with the same user name and password is still refused
    asyncio.run(refused(tmp_path / "other"))
    audit_log = (state / "opcua" / "audit.log").read_text()
    assert audit_log.count("OPC UA client refused (BadCertificateUntrusted)") == 2
    assert audit_log.count("OPC UA client accepted") == 1


def test_an_unreadable_trust_list_trusts_nobody(server_factory, tmp_path):
    from asyncua import ua

    _srv, url = server_factory()

    async def main():
        client = await trusted_client(url, tmp_path / "c", TRUSTED(tmp_path), "operator", "s3cret-for-test")
        (TRUSTED(tmp_path) / "broken.der").write_bytes(b"not a certificate")
        with pytest.raises(ua.UaError, match="BadCertificateUntrusted"):
            async with client:
                pass

    asyncio.run(main())
    code, out, err = _fbgcomp("trust", "list", "--dir", TRUSTED(tmp_path))
    assert code == 2 and "broken.der: not a readable certificate" in out
    assert err.startswith("error: ") and len(err.strip().splitlines()) == 1


def test_reload_model_loads_only_from_the_models_folder(server_factory, tmp_path):
    """Before: ReloadModel handed any path to the service, e.g. /etc/passwd or ../x.json."""
    from asyncua import ua

    models = tmp_path / "models"
    (models / "sub").mkdir(parents=True)
    (models / "good.json").write_text("{}")
    (models / "sub" / "other.json").write_text("{}")
    (tmp_path / "x.json").write_text("{}")
    (models / "escape.json").symlink_to(tmp_path / "x.json")
    reloads = []

    async def main():
        loop = asyncio.get_running_loop()

        async def on_reload(path):
            reloads.append(path)
            return f"loaded {os.path.basename(path)}"

        _srv, url = server_factory(on_reload=on_reload, main_loop=loop, models_dir=models)
        client = await trusted_client(url, tmp_path / "op", TRUSTED(tmp_path), "operator", "s3cret-for-test")
        answers = {}
        async with client:
            root = client.get_node(ua.NodeId("FbgComp", 2))
            for name in (
                "../x.json",
                "/etc/passwd",
                "sub/../../x.json",
                "escape.json",
                "missing.json",
                "good.json",
                "sub/other.json",
            ):
                try:
                    answers[name] = await root.call_method(ua.NodeId("FbgComp.ReloadModel", 2), name)
                except ua.UaStatusCodeError as exc:
                    answers[name] = type(exc).__name__
        return answers

    answers = asyncio.run(main())
    assert answers == {
        "../x.json": "BadInvalidArgument",
        "/etc/passwd": "BadInvalidArgument",
        "sub/../../x.json": "BadInvalidArgument",
        "escape.json": "BadInvalidArgument",
        "missing.json": "BadNotFound",
        "good.json": "loaded good.json",
        "sub/other.json": "loaded other.json",
    }
    assert reloads == [str((models / "good.json").resolve()), str((models / "sub" / "other.json").resolve())]


def test_reload_model_by_name_needs_a_models_folder(server_factory, tmp_path):
    from asyncua import ua

    reloads = []

    async def main():
        loop = asyncio.get_running_loop()

        async def on_reload(path):
            reloads.append(path)
            return "reloaded"

        _srv, url = server_factory(on_reload=on_reload, main_loop=loop)
        client = await trusted_client(url, tmp_path / "op", TRUSTED(tmp_path), "operator", "s3cret-for-test")
        async with client:
            root = client.get_node(ua.NodeId("FbgComp", 2))
            with pytest.raises(ua.UaStatusCodeError, match="BadNotSupported"):
                await root.call_method(ua.NodeId("FbgComp.ReloadModel", 2), "model.json")
            # an empty name reloads the model serve was started with
            return await root.call_method(ua.NodeId("FbgComp.ReloadModel", 2), "")

    assert asyncio.run(main()) == "reloaded" and reloads == [""]


def test_writes_and_calls_are_logged_with_their_user(server_factory, tmp_path, capfd):
    from asyncua import ua

    models = tmp_path / "models"
    models.mkdir()
    (models / "m.json").write_text("{}")
    # serve -v: the server process logs at INFO on stderr, as the service does
    fbg = logging.getLogger("fbgcomp")
    level = fbg.level
    fbg.setLevel(logging.INFO)

    async def main():
        loop = asyncio.get_running_loop()

        async def on_reload(path):
            return "loaded"

        try:
            srv, url = server_factory(
                allow_anonymous=True, on_reload=on_reload, main_loop=loop, models_dir=models
            )
        finally:
            fbg.setLevel(level)
        op = await trusted_client(url, tmp_path / "op", TRUSTED(tmp_path), "operator", "s3cret-for-test")
        async with op:
            await _node(op, "Enabled").write_value(False)
            root = op.get_node(ua.NodeId("FbgComp", 2))
            await root.call_method(ua.NodeId("FbgComp.ReloadModel", 2), "m.json")
            with pytest.raises(ua.UaStatusCodeError):
                await root.call_method(ua.NodeId("FbgComp.ReloadModel", 2), "/etc/passwd")
        anon = await trusted_client(url, tmp_path / "anon", TRUSTED(tmp_path))
        async with anon:
            with pytest.raises(ua.UaStatusCodeError):
                await _node(anon, "Enabled").write_value(True)
        srv.stop()

    asyncio.run(main())
    expected = [
        "OPC UA write ns=2;s=FbgComp.Enabled = False by operator: Good",
        "OPC UA call ReloadModel('m.json') by operator: loaded",
        "OPC UA call ReloadModel('/etc/passwd') by operator refused",
        "OPC UA write by anonymous refused: access denied",
    ]
    audit_log = (tmp_path / "state" / "opcua" / "audit.log").read_text()
    stderr = capfd.readouterr().err
    for line in expected:
        assert line in audit_log
        assert line in stderr  # python logging of the server process


# --------------------------------------------------------------------------- issue 15, item 6
# UnitIds as published in the OPC Foundation's UNECE_to_OPCUA.csv (UNECE Rec. 20 common code ->
# OPC 10000-8 5.6.3 UnitId); HUR is the hour, not the hertz (HTZ)
PUBLISHED_UNIT_IDS = {
    "4H": 13384,
    "C45": 4404277,
    "C26": 4403766,
    "CEL": 4408652,
    "HTZ": 4740186,
    "HUR": 4740434,
    "SEC": 5457219,
    "MMT": 5066068,
}
# "59" (part per million, our µm/m) by part 8's rule alone: "5" = 0x35, "9" = 0x39
RULE_UNIT_IDS = {**PUBLISHED_UNIT_IDS, "59": 0x3539}
ANALOG = {
    **{
        f"{p}{a}_um": "um"
        for p in ("Correction", "PredictedDeviation", "IntervalHalfWidth", "ExpectedError")
        for a in "XYZ"
    },
    "Latency_ms": "ms",
    "Sensors.S1.Wavelength_nm": "nm",
    "Sensors.S2.Wavelength_nm": "nm",
    # the offset + Z slope form a CNC takes (issue 15, item 5; docs/cnc-integration.md)
    **{f"Offset{a}_um": "um" for a in "XYZ"},
    **{f"Slope{a}_um_per_m": "um_per_m" for a in "XYZ"},
    "ZRef_mm": "mm",
}


def test_unece_unit_ids_follow_part_8():
    from fbgcomp.runtime.outputs.opcua import unece_unit_id

    assert {code: unece_unit_id(code) for code in PUBLISHED_UNIT_IDS} == PUBLISHED_UNIT_IDS
    for bad in ("", "ABCD", "µm"):
        with pytest.raises(ValueError):
            unece_unit_id(bad)


def test_analog_items_units_ranges_descriptions_and_method_arguments(server_factory, tmp_path):
    """What an integrator's client (UaExpert, a PLC's OPC UA client) browses: every length,
    wavelength and duration an AnalogItemType with its UNECE unit and EURange, every node
    described, every method argument named, typed and described."""
    from asyncua import ua

    _srv, url = server_factory(
        eu_ranges={
            "Correction": (-200.0, 200.0),
            "Correction.Z": (-50.0, 50.0),
            "Wavelength_nm.S2": (1545.0, 1555.0),
        }
    )

    async def main():
        client = await trusted_client(url, tmp_path / "c", TRUSTED(tmp_path), "operator", "s3cret-for-test")
        async with client:
            root = client.get_node(ua.NodeId("FbgComp", 2))
            ctype = await root.read_type_definition()
            ctype_node = client.get_node(ctype)
            found = {
                "type": (await ctype_node.read_browse_name()).Name,
                "type_description": (await ctype_node.read_description()).Text,
                "description": (await root.read_description()).Text,
                "name": await (await root.get_child(["2:Name"])).read_value(),
            }
            variables, methods = {}, []
            sensors = await root.get_child(["2:Sensors"])
            children = await root.get_children()
            for sensor in await sensors.get_children():
                children += await sensor.get_children()
            for node in children:
                klass = await node.read_node_class()
                if klass == ua.NodeClass.Method:
                    methods.append(node)
                elif klass == ua.NodeClass.Variable:
                    variables[node.nodeid.Identifier[len("FbgComp.") :]] = node
            analog, descriptions = {}, {}
            for name, node in variables.items():
                descriptions[name] = (await node.read_description()).Text
                if await node.read_type_definition() != ua.NodeId(ua.ObjectIds.AnalogItemType):
                    continue
                eu = await (await node.get_child(["0:EngineeringUnits"])).read_value()
                rng = await (await node.get_child(["0:EURange"])).read_value()
                analog[name] = (eu, rng, await node.read_data_type_as_variant_type())
            arguments = {}
            for m in methods:
                name = (await m.read_browse_name()).Name
                descriptions[name] = (await m.read_description()).Text
                arguments[name] = [
                    await (await m.get_child([f"0:{k}"])).read_value()
                    for k in ("InputArguments", "OutputArguments")
                ]
            return found, variables, analog, descriptions, arguments

    found, variables, analog, descriptions, arguments = asyncio.run(main())
    assert found["type"] == "ThermalCompensationType"
    assert "OPC 40501-1" in found["type_description"]
    assert "ElementMonitoringType" in found["type_description"]
    assert "ElementMonitoringType" in found["description"]
    assert found["name"] == "fbgcomp thermal compensation"

    assert set(analog) == set(ANALOG)
    assert {"Health", "Heartbeat", "Enabled", "SampleTime"} <= set(variables) - set(analog)
    units = {
        "um": ("4H", "µm"),
        "nm": ("C45", "nm"),
        "ms": ("C26", "ms"),
        "mm": ("MMT", "mm"),
        "um_per_m": ("59", "µm/m"),
    }
    for name, (eu, rng, vtype) in analog.items():
        code, display = units[ANALOG[name]]
        assert isinstance(eu, ua.EUInformation) and isinstance(rng, ua.Range), name
        assert eu.NamespaceUri == "http://www.opcfoundation.org/UA/units/un/cefact"
        assert (eu.UnitId, eu.DisplayName.Text) == (RULE_UNIT_IDS[code], display), name
        assert vtype == ua.VariantType.Double
        assert rng.Low < rng.High
    assert {n: (r.Low, r.High) for n, (_, r, _) in analog.items() if n.startswith("Correction")} == {
        "CorrectionX_um": (-200.0, 200.0),
        "CorrectionY_um": (-200.0, 200.0),
        "CorrectionZ_um": (-50.0, 50.0),
    }  # configured: by kind, and for one axis
    assert (analog["PredictedDeviationY_um"][1].Low, analog["PredictedDeviationY_um"][1].High) == (
        -1000.0,
        1000.0,
    )  # default
    assert (analog["Sensors.S2.Wavelength_nm"][1].Low, analog["Sensors.S2.Wavelength_nm"][1].High) == (
        1545.0,
        1555.0,
    )
    assert (analog["Sensors.S1.Wavelength_nm"][1].Low, analog["Sensors.S1.Wavelength_nm"][1].High) == (
        1460.0,
        1640.0,
    )

    # every node says what it is (asyncua's default description is the browse name)
    for name, text in descriptions.items():
        assert text and text != name.rsplit(".", 1)[-1] and len(text) > 20, (name, text)
    assert "axis Z" in descriptions["CorrectionZ_um"]
    assert "axis Y" in descriptions["SlopeY_um_per_m"] and "ZRef_mm" in descriptions["OffsetX_um"]
    assert "8 RATE_LIMITED" in descriptions["OutputFlagsY"]

    assert set(arguments) == {"ReloadModel"}  # every method the server exposes
    for inputs, outputs in arguments.values():
        for arg in inputs + outputs:
            assert arg.Name and arg.Description.Text and len(arg.Description.Text) > 20
            assert arg.DataType == ua.NodeId(ua.ObjectIds.String)
            assert arg.ValueRank == ua.ValueRank.Scalar
    (model_file,), (result,) = arguments["ReloadModel"]
    assert model_file.Name == "ModelFile" and "models folder" in model_file.Description.Text
    assert result.Name == "Result"


def test_values_still_update_on_analog_items(server_factory, tmp_path):
    """The AnalogItemType variables keep their node ids and take the published values."""
    srv, url = server_factory()

    async def main():
        client = await trusted_client(url, tmp_path / "c", TRUSTED(tmp_path), "operator", "s3cret-for-test")
        async with client:
            srv.publish(_snapshot(3, time.time()))
            end = time.monotonic() + 5
            while time.monotonic() < end:
                if await _node(client, "CorrectionX_um").read_value() == -3.0:
                    break
                await asyncio.sleep(0.05)
            return [
                await _node(client, n).read_value()
                for n in ("CorrectionX_um", "PredictedDeviationY_um", "Sensors.S1.Wavelength_nm")
            ]

    assert asyncio.run(main()) == [-3.0, -6.0, 1530.0]


def test_writer_warning_wording():
    from fbgcomp.runtime.outputs.opcua import writer_warning

    assert writer_warning({"operator": "pbkdf2_sha256$1$x$y"}, False) is None
    closed, read_only = writer_warning({}, False), writer_warning({}, True)
    for text in (closed, read_only):
        assert "no client can switch the compensation (Enabled)" in text
        assert "--users FILE" in text and "FBGCOMP_OPCUA_USER" in text
        assert "\n" not in text
    assert "BadIdentityTokenRejected" in closed and "may only read" in read_only


@pytest.mark.parametrize("writer", [False, True])
def test_serve_warns_loudly_when_no_user_may_write(tmp_path, runtime_model_and_campaign, writer):
    """The README's serve has no users: before, every client was refused and nothing said so.
    Now a real ``fbgcomp serve`` says it on stdout and in its log (stderr) - and only then."""
    import fbgcomp_testing

    fbgcomp_testing.require("asyncua")
    from test_runtime_support import fbgcomp_process

    model, campaign = runtime_model_and_campaign
    env = (
        {"FBGCOMP_OPCUA_USER": "operator", "FBGCOMP_OPCUA_PASSWORD": "pw-for-test-1"}
        if writer
        else {"FBGCOMP_OPCUA_USER": "", "FBGCOMP_OPCUA_PASSWORD": ""}
    )
    proc = fbgcomp_process(
        "serve",
        "--model",
        model,
        "--source",
        f"sim://{campaign}?rate=50",
        "--opcua",
        f"opc.tcp://127.0.0.1:{free_port()}/fbgcomp/",
        "--state-dir",
        tmp_path / "state",
        "--duration",
        2,
        env=env,
    )
    try:
        out, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    out, err = out.decode(), err.decode()
    assert proc.returncode == 0, err[-3000:]
    assert "processed" in err  # it did run
    warned = [line for line in out.splitlines() if "no OPC UA user may write" in line]
    logged = [line for line in err.splitlines() if "no OPC UA user may write" in line]
    if writer:
        assert warned == [] and logged == [], (out, err)
    else:
        assert len(warned) == 1 and warned[0].startswith("WARNING: "), out
        assert "BadIdentityTokenRejected" in warned[0] and "--users FILE" in warned[0]
        assert len(logged) == 1 and " WARNING fbgcomp.runtime: " in logged[0], err
    # the one-line start-up summary, without -v: what runs, and who may change it
    summary = [line for line in err.splitlines() if line.startswith("serving model ")]
    assert len(summary) == 1, err
    meta = json.loads(Path(model).read_text())
    s = summary[0]
    assert f"serving model {meta['model_id']} ({meta['model_type']}, {model})" in s, s
    assert f"| inputs: gratings sim://{campaign}?rate=50 |" in s, s
    assert "| outputs: OPC UA opc.tcp://127.0.0.1:" in s and "run log" not in s, s
    assert "| policy: output filter on, max correction " in s and " µm/s" in s, s
    assert s.endswith("| may write: OPC UA: operator" if writer else "| may write: OPC UA: nobody"), s


def test_the_correction_eurange_is_the_cap_in_force():
    """serve gives the OPC UA server each axis's correction cap as its EURange (a client
    scaling a bar graph sees the range the correction can take); no cap, the default."""
    from fbgcomp.runtime.service import correction_eu_ranges

    assert correction_eu_ranges((42.0, 1000.0, float("inf"))) == {
        "Correction.X": (-42.0, 42.0),
        "Correction.Y": (-1000.0, 1000.0),
    }
