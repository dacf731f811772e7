"""OPC UA server with a real asyncua client over TCP, Basic256Sha256 Sign & Encrypt."""

import asyncio
import time

import pytest

from test_runtime_support import free_port, secure_client



@pytest.fixture()
def server_factory(tmp_path, monkeypatch):
    import fbgcomp_testing
    fbgcomp_testing.require("asyncua")
    from fbgcomp.runtime.opcua import OpcUaConfig, OpcUaServer

    started = []

    def make(allow_anonymous=False, on_reload=None, main_loop=None):
        monkeypatch.setenv("FBGCOMP_OPCUA_USER", "operator")
        monkeypatch.setenv("FBGCOMP_OPCUA_PASSWORD", "s3cret-for-test")
        port = free_port()
        cfg = OpcUaConfig(endpoint=f"opc.tcp://127.0.0.1:{port}/fbgcomp/", rate_hz=0,
                          allow_anonymous=allow_anonymous, state_dir=str(tmp_path / "state"))
        srv = OpcUaServer(cfg, ["S1", "S2"], "model-abc", on_reload=on_reload,
                          main_loop=main_loop)
        srv.start()
        started.append(srv)
        return srv, cfg.endpoint

    yield make
    for s in started:
        s.stop()


def _snapshot(i, t):
    from fbgcomp.runtime.opcua import Snapshot
    return Snapshot(sample_time_s=t, correction_um=(-1.0 * i, 2.0 * i, 0.5), deviation_um=(i, -2.0 * i, -0.5),
                    half_width_um=(0.1, 0.2, 0.3), expected_rms_um=(0.05, 0.05, 0.05),
                    health="OK", fallback="", alarm=False, sensor_status=["OK", "MISSING"],
                    sensor_wavelength_nm=[1530.0, float("nan")], source_status="connected",
                    frames=i)


def _node(client, name):
    from asyncua import ua
    return client.get_node(ua.NodeId(f"FbgComp.{name}", 2))


def test_subscribed_client_receives_published_values(server_factory, tmp_path):
    srv, url = server_factory()
    assert (tmp_path / "state" / "opcua" / "server_cert.der").is_file()

    async def main():
        client = await secure_client(url, tmp_path / "client", "operator", "s3cret-for-test")
        received = []

        class Handler:
            def datachange_notification(self, node, val, data):
                received.append((node.nodeid.Identifier, val))

        async with client:
            ns = await client.get_namespace_index("urn:fbgcomp:runtime")
            assert ns == 2
            assert client.security_policy.Mode.name == "SignAndEncrypt"
            sub = await client.create_subscription(0, Handler())
            await sub.subscribe_data_change([_node(client, "CorrectionX_um"),
                                             _node(client, "SampleTime")])
            await asyncio.sleep(0.3)
            for i in range(1, 6):
                srv.publish(_snapshot(i, time.time()))
                await asyncio.sleep(0.05)
            end = time.monotonic() + 5
            while time.monotonic() < end and not any(
                    v == -5.0 for n, v in received if n == "FbgComp.CorrectionX_um"):
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
    srv, url = server_factory(allow_anonymous=False)

    async def main():
        anon = await secure_client(url, tmp_path / "c1")
        with pytest.raises(Exception):
            async with anon:
                pass
        bad = await secure_client(url, tmp_path / "c2", "operator", "wrong")
        with pytest.raises(Exception):
            async with bad:
                pass

    asyncio.run(main())


def test_no_unencrypted_endpoint(server_factory, tmp_path):
    from asyncua import Client
    srv, url = server_factory(allow_anonymous=True)

    async def main():
        client = Client(url, timeout=5)   # SecurityPolicy None
        endpoints = await client.connect_and_get_server_endpoints()
        assert {e.SecurityPolicyUri.rsplit("#", 1)[-1] for e in endpoints} == {"Basic256Sha256"}
        assert {e.SecurityMode.name for e in endpoints} == {"SignAndEncrypt"}
        with pytest.raises(Exception):
            async with client:
                await _node(client, "CorrectionX_um").read_value()

    asyncio.run(main())


def test_unauthenticated_writes_and_calls_are_refused(server_factory, tmp_path):
    from asyncua import ua
    reloads = []

    async def main():
        loop = asyncio.get_running_loop()

        async def on_reload(path):
            reloads.append(path)
            return f"loaded {path}"

        srv, url = server_factory(allow_anonymous=True, on_reload=on_reload, main_loop=loop)
        anon = await secure_client(url, tmp_path / "anon")
        async with anon:
            assert await _node(anon, "Enabled").read_value() is True       # reading is fine
            with pytest.raises(ua.UaStatusCodeError) as e:
                await _node(anon, "Enabled").write_value(False)
            assert "BadUserAccessDenied" in type(e.value).__name__ + str(e.value)
            root = anon.get_node(ua.NodeId("FbgComp", 2))
            with pytest.raises(ua.UaStatusCodeError):
                await root.call_method(ua.NodeId("FbgComp.ReloadModel", 2), "x.json")
        assert srv.enabled is True and reloads == []

        op = await secure_client(url, tmp_path / "op", "operator", "s3cret-for-test")
        async with op:
            with pytest.raises(ua.UaStatusCodeError):   # read-only value, even for a user
                await _node(op, "CorrectionX_um").write_value(1.0)
            await _node(op, "Enabled").write_value(False)
            root = op.get_node(ua.NodeId("FbgComp", 2))
            answer = await root.call_method(ua.NodeId("FbgComp.ReloadModel", 2), "new.json")
            assert answer == "loaded new.json"
            srv.publish(_snapshot(1, time.time()))          # wakes the server's loop
            end = time.monotonic() + 3
            while srv.enabled and time.monotonic() < end:
                await asyncio.sleep(0.05)
        assert srv.enabled is False and reloads == ["new.json"]

    asyncio.run(main())


def test_control_messages_are_not_dropped_when_snapshots_are():
    """A lagging OPC UA process may lose snapshots (the newest wins) but never an Enabled switch."""
    import pickle
    import socket
    import threading
    import time

    from fbgcomp.runtime.opcua import send_control

    parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        filled = 0
        while True:                       # the buffer is full: a snapshot would now be dropped
            try:
                parent.send(pickle.dumps(("snap", filled)), socket.MSG_DONTWAIT)
                filled += 1
            except BlockingIOError:
                break
        assert filled > 0
        assert send_control(parent, ("set_enabled", False), timeout_s=0.2) is False   # reported

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
