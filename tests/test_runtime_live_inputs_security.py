"""Input-side OPC UA security of ``fbgcomp serve`` (``[temperatures.opcua] security =
"Basic256Sha256"``): probe temperatures read from a real asyncua server on loopback whose only
endpoint is Basic256Sha256 (server certificate made in the test's folder), by the real reader
(:class:`fbgcomp.runtime.live_inputs.LiveInputs`, as serve builds it) and by a real ``fbgcomp
serve`` process. What is checked: a secure reader gets the values and their changes; a reader
without security, or pinning another server's certificate, gets nothing and says its probes are
stale without stopping; a server with a trust list refuses the reader's certificate until it is
trusted; a certificate issued elsewhere (own application URI, PEM under any name) works."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import shutil
import socket
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import fbgcomp_testing
from test_runtime_live_inputs import OpcUaTestServer, assert_serve_refuses, serve_and_sim, wait_log

SERVER_URI = "urn:fbgcomp:test:secure-plc"
READER_URI = "urn:fbgcomp:serve:inputs"  # what the reader names in the certificates it creates
BASIC256SHA256 = "http://opcfoundation.org/UA/SecurityPolicy#Basic256Sha256"
PROBES = {"T_bulk": 21.25, "T_surf": 22.5}
NODES = {p: f"ns=2;s={p}" for p in PROBES}


def make_certificate(key: Path, cert: Path, uri: str, server: bool = False) -> None:
    """A self-signed application certificate (DER) and key (PEM), asyncua's own generator."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    use = [ExtendedKeyUsageOID.CLIENT_AUTH] + ([ExtendedKeyUsageOID.SERVER_AUTH] if server else [])
    for folder in (key.parent, cert.parent):
        folder.mkdir(parents=True, exist_ok=True)
    asyncio.run(setup_self_signed_certificate(key, cert, uri, socket.gethostname(), use, {}))


class SecureOpcUaTestServer(OpcUaTestServer):
    """:class:`OpcUaTestServer` (``ns=2;s=<probe>`` Doubles, rewritten every 0.2 s) whose only
    endpoint is Basic256Sha256 in ``mode``, with a self-signed server certificate made in
    ``folder``. ``validation`` (asyncua ``CertificateValidatorOptions``): the checks the server
    makes of a client's certificate; with ``trusted`` (a folder), against that trust list."""

    def __init__(self, values: dict, folder: Path, mode="SignAndEncrypt", validation=None, trusted=None):
        super().__init__(values)
        self.cert, self.key = folder / "server_cert.der", folder / "server_key.pem"
        make_certificate(self.key, self.cert, SERVER_URI, server=True)
        self.mode, self.validation, self.trusted = mode, validation, trusted
        self.trust_store = None

    async def secure(self, server):
        from asyncua import ua
        from asyncua.crypto.truststore import TrustStore
        from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions

        await server.set_application_uri(SERVER_URI)
        await server.load_certificate(str(self.cert))
        await server.load_private_key(str(self.key))
        server.set_security_policy([getattr(ua.SecurityPolicyType, f"Basic256Sha256_{self.mode}")])
        if self.validation is not None:
            if self.trusted is not None:
                self.trust_store = TrustStore([self.trusted], [])
                await self.trust_store.load()
            server.set_certificate_validator(
                CertificateValidator(
                    self.validation | CertificateValidatorOptions.PEER_CLIENT, self.trust_store
                )
            )

    def reload_trust(self) -> None:
        """Read the trust list folder again (on the server's loop)."""
        assert self.trust_store is not None
        asyncio.run_coroutine_threadsafe(self.trust_store.load(), self._loop).result(10)


def endpoints(url: str) -> set:
    """(security policy URI, mode name) of every endpoint a real client is offered."""

    async def main():
        from asyncua import Client

        return await Client(url, timeout=5).connect_and_get_server_endpoints()

    return {(e.SecurityPolicyUri, e.SecurityMode.name) for e in asyncio.run(main())}


def input_config(endpoint: str, **kw):
    from fbgcomp.runtime.live_inputs import OpcUaInputConfig

    return OpcUaInputConfig(endpoint=endpoint, nodes=dict(NODES), stale_s=1.0, timeout_s=2.0, **kw)


def with_live_inputs(config, body):
    """Run ``await body(live, reader)`` with serve's live inputs built from ``config`` (the
    [temperatures.opcua] section) and started; closed afterwards."""
    from fbgcomp.runtime.live_inputs import LiveInputs, PositionConfig, TemperaturesConfig

    async def main():
        live = LiveInputs(TemperaturesConfig(opcua=config), PositionConfig(), list(PROBES))
        (reader,) = live.readers
        live.start()
        try:
            return await body(live, reader)
        finally:
            await live.close()

    return asyncio.run(main())


async def until(predicate, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        await asyncio.sleep(0.05)
    return predicate()


def fresh(live, values: dict) -> bool:
    return live.temperatures_C() == values


def secure_reader_files(folder: Path) -> dict:
    return {"certificate": str(folder / "inputs_cert.der"), "private_key": str(folder / "inputs_key.pem")}


# ------------------------------------------------------------------ a secure reader
@pytest.mark.parametrize(
    "mode,pinned", [("SignAndEncrypt", False), ("SignAndEncrypt", True), ("Sign", False)]
)
def test_a_basic256sha256_reader_gets_the_probes_and_their_changes_from_a_secure_only_server(
    tmp_path, mode, pinned
):
    fbgcomp_testing.require("asyncua")
    from cryptography import x509

    with SecureOpcUaTestServer(PROBES, tmp_path / "server", mode=mode) as opc:
        # the server really is secure-only: one endpoint, Basic256Sha256 in that mode
        assert endpoints(opc.endpoint) == {(BASIC256SHA256, mode)}
        files = secure_reader_files(tmp_path / "client")
        config = input_config(
            opc.endpoint,
            security="Basic256Sha256",
            mode=mode,
            server_certificate=str(opc.cert) if pinned else "",
            **files,
        )

        async def body(live, reader):
            got = await until(lambda: fresh(live, PROBES), 10)
            first = (live.temperatures_C(), live.check(live.temperatures_C(), None), reader.status)
            assert got, (reader.status, live.temperatures_C())
            opc.values["T_bulk"] = 23.75  # the PLC's value changes
            got = await until(lambda: fresh(live, {**PROBES, "T_bulk": 23.75}), 5)
            return first, got, live.temperatures_C()

        first, changed, after = with_live_inputs(config, body)
    values, status, reader_status = first
    assert values == PROBES and status == "inputs OK" and reader_status == "connected"
    assert changed, after
    # the reader made its certificate (absent before): DER, naming the reader's URI, and its key
    cert = x509.load_der_x509_certificate(Path(files["certificate"]).read_bytes())
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.UniformResourceIdentifier) == [READER_URI]
    assert Path(files["private_key"]).read_bytes().startswith(b"-----BEGIN PRIVATE KEY-----")


# ------------------------------------------------------------------ readers that cannot connect
@pytest.mark.parametrize("case", ["security None", "another server's certificate pinned"])
def test_a_reader_that_cannot_talk_to_the_secure_server_reports_stale_probes_and_keeps_trying(
    tmp_path, caplog, case
):
    fbgcomp_testing.require("asyncua")
    caplog.set_level(logging.WARNING, logger="fbgcomp.runtime.inputs")
    with SecureOpcUaTestServer(PROBES, tmp_path / "server") as opc:
        if case == "security None":
            config = input_config(opc.endpoint)  # the default: security "None"
            # asyncua's client finds no endpoint it may use
            reason = "UaError: No matching endpoints: 1, http://opcfoundation.org/UA/SecurityPolicy#None"
        else:
            other = tmp_path / "other"
            make_certificate(other / "key.pem", other / "cert.der", "urn:someone:else", server=True)
            files = secure_reader_files(tmp_path / "client")
            config = input_config(opc.endpoint, security="Basic256Sha256", **files)
            config.server_certificate = str(other / "cert.der")
            config.timeout_s = 0.5
            # the server cannot decrypt what was encrypted for another: no answer
            reason = ": TimeoutError; retry in"

        async def body(live, reader):
            # several connection attempts (back-off 0.2, 0.4, 0.8 s ...), none gets a value
            await asyncio.sleep(2.5)
            values = live.temperatures_C()
            return values, live.check(values, None), reader.status

        values, status, reader_status = with_live_inputs(config, body)
    assert all(math.isnan(v) for v in values.values()), values
    # what serve publishes (SourceStatus, the log): the probes never had a value, by name
    assert status == "stale: T_bulk (opcua, never), T_surf (opcua, never)"
    # the reader did not stop (a stopped reader says "stopped (error)"): it is retrying
    assert reader_status in ("connecting (UaError)", "connecting (TimeoutError)"), reader_status
    retries = [r.getMessage() for r in caplog.records if r.getMessage().startswith("OPC UA inputs: ")]
    assert len(retries) >= 2, retries
    assert all(m.startswith(f"OPC UA inputs: {opc.endpoint}: ") and reason in m for m in retries), retries


# ------------------------------------------------------------------ the server's trust list
def test_a_server_trust_list_refuses_the_readers_certificate_until_it_is_trusted(tmp_path):
    fbgcomp_testing.require("asyncua")
    from asyncua.crypto.validator import CertificateValidatorOptions

    trusted = tmp_path / "trusted"
    # the trust list knows another client only
    make_certificate(tmp_path / "other" / "key.pem", trusted / "other_client.der", "urn:someone:else")
    with SecureOpcUaTestServer(
        PROBES,
        tmp_path / "server",
        validation=CertificateValidatorOptions.TRUSTED_VALIDATION,
        trusted=trusted,
    ) as opc:
        files = secure_reader_files(tmp_path / "client")
        config = input_config(opc.endpoint, security="Basic256Sha256", **files)

        async def body(live, reader):
            refused = await until(lambda: reader.status == "connecting (BadCertificateUntrusted)", 10)
            values = live.temperatures_C()
            before = (refused, reader.status, values, live.check(values, None))
            # the operator trusts the reader's certificate (made by the reader at its first
            # attempt); the reader's next attempt gets a session, without a restart
            shutil.copy(files["certificate"], trusted / "fbgcomp_inputs.der")
            opc.reload_trust()
            got = await until(lambda: fresh(live, PROBES), 10)
            return before, got, reader.status, live.temperatures_C()

        before, got, reader_status, after = with_live_inputs(config, body)
    refused, refused_status, values, status = before
    assert refused, refused_status
    assert all(math.isnan(v) for v in values.values()), values
    assert status == "stale: T_bulk (opcua, never), T_surf (opcua, never)"
    assert got and reader_status == "connected", (reader_status, after)


# ------------------------------------------------------------------ certificates from elsewhere
@pytest.mark.parametrize("case", ["issued elsewhere", "created under other names"])
def test_a_certificate_is_read_as_what_it_holds_and_names_the_session(tmp_path, case):
    """Regression: the reader loaded each file by its name's extension (a PEM certificate named
    .crt, or the DER certificate it created itself at a path ending in .pem, never loaded:
    ValueError at every attempt) and always named its session urn:fbgcomp:serve:inputs (a
    certificate with another application URI: BadCertificateUriInvalid from any server that
    checks the URI, as OPC UA requires)."""
    fbgcomp_testing.require("asyncua")
    from asyncua.crypto.validator import CertificateValidatorOptions
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    client = tmp_path / "client"
    if case == "issued elsewhere":
        # the plant's certificate for this machine: its own URI, PEM, the usual .crt / .key names
        make_certificate(client / "key.pem", client / "cert.der", "urn:plant:line3:fbgcomp")
        pem = x509.load_der_x509_certificate((client / "cert.der").read_bytes()).public_bytes(Encoding.PEM)
        (client / "line3.crt").write_bytes(pem)
        (client / "key.pem").rename(client / "line3.key")
        files = {"certificate": str(client / "line3.crt"), "private_key": str(client / "line3.key")}
    else:
        # absent: the reader creates them (asyncua writes a DER certificate and a PEM key)
        files = {"certificate": str(client / "cert.pem"), "private_key": str(client / "key.der")}
    # the server checks every client certificate's application URI, key usage and validity
    with SecureOpcUaTestServer(
        PROBES, tmp_path / "server", validation=CertificateValidatorOptions.EXT_VALIDATION
    ) as opc:
        config = input_config(opc.endpoint, security="Basic256Sha256", **files)

        async def body(live, reader):
            got = await until(lambda: fresh(live, PROBES), 10)
            return got, reader.status

        got, reader_status = with_live_inputs(config, body)
    assert got and reader_status == "connected", reader_status
    if case == "created under other names":  # the created key is a secret: owner only
        assert Path(files["private_key"]).stat().st_mode & 0o077 == 0, oct(
            Path(files["private_key"]).stat().st_mode
        )


# ------------------------------------------------------------------ serve
@pytest.mark.slow
def test_serve_reads_probe_temperatures_from_a_secure_only_server(tmp_path, runtime_model_and_campaign):
    """A real ``fbgcomp serve`` configured from its TOML with Basic256Sha256 SignAndEncrypt:
    the run log's temperatures are the server's values, before and after a change."""
    fbgcomp_testing.require("asyncua")
    from fbgcomp.models.registry import load_model

    model_path, campaign = runtime_model_and_campaign
    probes = load_model(model_path).probe_names
    camp_t = pd.read_csv(campaign / "temperatures.csv").iloc[0]
    values = {p: float(camp_t[f"{p}_C"]) for p in probes}
    with SecureOpcUaTestServer(values, tmp_path / "server") as opc:
        assert endpoints(opc.endpoint) == {(BASIC256SHA256, "SignAndEncrypt")}
        nodes = ", ".join(f'{p} = "ns=2;s={p}"' for p in probes)
        toml = f"""
[temperatures.opcua]
endpoint = "{opc.endpoint}"
security = "Basic256Sha256"
mode = "SignAndEncrypt"
certificate = "{tmp_path / "inputs" / "cert.der"}"
private_key = "{tmp_path / "inputs" / "key.pem"}"
server_certificate = "{opc.cert}"
nodes = {{ {nodes} }}
stale_s = 2
"""
        with serve_and_sim(
            tmp_path, toml, model_path, campaign, ("--duration", "60"), ("--rate", "200", "--speed", "5")
        ) as (serve, _sim):
            wait_log(tmp_path / "log", "OK", 40)
            opc.values["T_bulk"] += 0.5
            t_step = time.monotonic()
            while time.monotonic() - t_step < 15:  # until a frame with the new value is logged
                with contextlib.suppress(OSError, ValueError, KeyError):
                    df = pd.read_parquet(tmp_path / "log" / "data")
                    if (df["health"].astype(str).eq("OK") & (df["T_bulk_C"] == values["T_bulk"] + 0.5)).any():
                        break
                time.sleep(0.3)
            serve.terminate()
            serve.wait(20)
    err = (tmp_path / "serve.err").read_text()
    df = pd.read_parquet(tmp_path / "log" / "data")
    ok = df[df["health"].astype(str) == "OK"]
    assert len(ok) > 100, err[-3000:]
    for p in probes:
        expected = {values[p]} | ({values[p] + 0.5} if p == "T_bulk" else set())
        assert set(ok[f"{p}_C"].to_numpy()) == expected, (p, err[-3000:])
    assert np.isfinite(ok[["dev_dx_um", "dev_dy_um", "dev_dz_um"]].to_numpy()).all()
    # connected at the first attempt (a failed one logs "OPC UA inputs: <endpoint>: <why>; retry")
    assert "OPC UA inputs: " not in err and "live inputs fresh again" in err, err[-3000:]


@pytest.mark.parametrize(
    "extra,message",
    [
        (
            'security = "Basic256Sha256"\nmode = "Encrypt"\ncertificate = "{tmp}/c.der"\nprivate_key = "{tmp}/k.pem"\n',
            "mode: expected SignAndEncrypt or Sign, got 'Encrypt'",
        ),
        ('security = "Basic256Sha256"\n', "Basic256Sha256 needs certificate and private_key paths"),
        ('security = "Basic128Rsa15"\n', "expected None or Basic256Sha256, got 'Basic128Rsa15'"),
        (
            # the user's certificate is there, its key path is wrong: creating a new pair would
            # overwrite the certificate a server may already trust
            'security = "Basic256Sha256"\ncertificate = "{tmp}/have.der"\nprivate_key = "{tmp}/typo.pem"\n',
            "typo.pem does not exist but its certificate does",
        ),
    ],
    ids=["mode", "no certificate", "policy", "key missing"],
)
def test_a_bad_security_configuration_stops_serve_with_one_line(
    tmp_path, runtime_model_and_campaign, extra, message
):
    fbgcomp_testing.require("asyncua")
    from fbgcomp.models.registry import load_model

    model_path, _campaign = runtime_model_and_campaign
    (tmp_path / "have.der").write_bytes(b"the user's certificate")
    nodes = ", ".join(f'{p} = "ns=2;s={p}"' for p in load_model(model_path).probe_names)
    (tmp_path / "serve.toml").write_text(
        # paths in the test's folder: a reader that starts anyway creates them there, not in the cwd
        f'[temperatures.opcua]\nendpoint = "opc.tcp://127.0.0.1:9"\n{extra.format(tmp=tmp_path)}'
        f"nodes = {{ {nodes} }}\n"
    )
    lines = assert_serve_refuses(tmp_path / "serve.toml", model_path, message)
    assert "temperatures.opcua" in lines[-1], lines
    assert (tmp_path / "have.der").read_bytes() == b"the user's certificate"
