"""Live inputs read from an OPC UA server by subscription (:class:`OpcUaReader`)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os

from fbgcomp.errors import InputError
from fbgcomp.runtime.live_inputs.config import Latest, OpcUaInputConfig

log = logging.getLogger("fbgcomp.runtime.inputs")


class OpcUaReader:
    """One asyncua client, subscribed to ``nodes`` (name -> node id) of one endpoint."""

    kind = "opcua"

    def __init__(
        self,
        endpoint: str,
        nodes: dict,
        config: OpcUaInputConfig | None = None,
        where: str = "temperatures.opcua",
    ):
        self.endpoint = endpoint
        self.config = config or OpcUaInputConfig(endpoint=endpoint)
        self.where = where
        self.nodes = dict(nodes)
        self.values = {n: Latest() for n in self.nodes}
        self.scale = dict.fromkeys(self.nodes, 1.0)
        self.status = "connecting"
        self._client = None
        if not endpoint.startswith("opc.tcp://"):
            raise InputError(
                f"expected opc.tcp://HOST:PORT, got {endpoint!r}", column=f"field {where}.endpoint"
            )
        if self.config.security not in ("None", "Basic256Sha256"):
            raise InputError(
                f"expected None or Basic256Sha256, got {self.config.security!r}",
                column=f"field {where}.security",
            )
        if self.config.security == "Basic256Sha256":
            if self.config.mode not in ("SignAndEncrypt", "Sign"):
                raise InputError(
                    f"expected SignAndEncrypt or Sign, got {self.config.mode!r}", column=f"field {where}.mode"
                )
            if not self.config.certificate or not self.config.private_key:
                raise InputError(
                    "Basic256Sha256 needs certificate and private_key paths",
                    column=f"field {where}.certificate",
                )
            have = [os.path.exists(self.config.certificate), os.path.exists(self.config.private_key)]
            if have[0] != have[1]:
                # a pair is created only when neither file exists: creating one would overwrite
                # the certificate (or key) the user has, which a server may already trust
                missing = "private_key" if have[0] else "certificate"
                raise InputError(
                    f"{getattr(self.config, missing)} does not exist but its "
                    f"{'certificate' if have[0] else 'private key'} does: give both, or neither "
                    "(a new pair is then created)",
                    column=f"field {where}.{missing}",
                )
        from asyncua import ua  # noqa: PLC0415 - optional extra: asyncua (imported only when used)

        for name, nid in self.nodes.items():
            try:
                ua.NodeId.from_string(str(nid))
            except Exception as exc:
                raise InputError(
                    f"not an OPC UA node id: {nid!r} (e.g. ns=2;s=Probes.T_bulk)",
                    column=f"field {where}.nodes.{name}",
                ) from exc

    def add(self, name: str, node: str, scale: float = 1.0) -> None:
        """Read input ``name`` from node id ``node``, multiplied by ``scale``."""
        self.nodes[name] = node
        self.values[name] = Latest()
        self.scale[name] = float(scale)

    async def _connect(self):
        from asyncua import Client, ua  # noqa: PLC0415 - optional extra: asyncua (imported only when used)

        cfg = self.config
        client = Client(
            self.endpoint,
            timeout=cfg.timeout_s,
            watchdog_intervall=1.0,
            auto_reconnect=True,
            reconnect_max_delay=5.0,
        )
        client.application_uri = "urn:fbgcomp:serve:inputs"
        client.session_timeout = 600_000  # ms: what asyncua servers grant at most
        if cfg.security == "Basic256Sha256":
            from asyncua.crypto import uacrypto  # noqa: PLC0415 - optional extra: asyncua (imported only when used)
            from asyncua.crypto.security_policies import (  # noqa: PLC0415 - optional extra: asyncua (imported only when used)
                SecurityPolicyBasic256Sha256,
            )

            if not (os.path.exists(cfg.certificate) and os.path.exists(cfg.private_key)):
                await client.setup_self_signed_certificate(cfg.private_key, cfg.certificate)
                os.chmod(cfg.private_key, 0o600)  # the key is a secret, as serve's own server key

            # each file loaded as what it holds, not as its name says: asyncua writes the
            # certificate it creates as DER and the key as PEM whatever the names end with
            def props(path: str) -> uacrypto.CertProperties:
                with open(path, "rb") as fh:
                    fmt = "pem" if b"-----BEGIN" in fh.read() else "der"
                return uacrypto.CertProperties(path, fmt)

            cert = props(cfg.certificate)
            # the session's application URI is the certificate's (OPC UA Part 4: servers refuse
            # a session whose URI the certificate does not name - BadCertificateUriInvalid), so a
            # certificate issued elsewhere works; one created here names client.application_uri
            uri = certificate_uri(await uacrypto.load_certificate(cert.path_or_content, cert.extension))
            if uri:
                client.application_uri = uri
            await client.set_security(
                SecurityPolicyBasic256Sha256,
                cert,
                props(cfg.private_key),
                server_certificate=props(cfg.server_certificate) if cfg.server_certificate else None,
                mode=getattr(ua.MessageSecurityMode, cfg.mode),
            )
        if cfg.user:
            client.set_user(cfg.user)
            client.set_password(os.environ.get("FBGCOMP_INPUT_PASSWORD", ""))
        reader = self

        async def lost(exc):
            reader.status = f"reconnecting ({type(exc).__name__})"

        client.connection_lost_callback = lost
        await client.connect()

        class Handler:
            def datachange_notification(self, node, val, data):
                name = names.get(node.nodeid)
                if name is None:
                    return
                reader.status = "connected"
                dv = data.monitored_item.Value
                good = dv is None or dv.StatusCode is None or dv.StatusCode.is_good()
                reader.values[name].set(val * reader.scale[name] if good and val is not None else math.nan)

            def status_change_notification(self, status):
                reader.status = f"subscription status {status}"

        names = {client.get_node(nid).nodeid: name for name, nid in self.nodes.items()}
        sub = await client.create_subscription(100, Handler())
        # StatusValueTimestamp: a rewritten steady value (new timestamp) is fresh, not stale
        flt = ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValueTimestamp)
        handles = await sub._subscribe(
            [client.get_node(nid) for nid in self.nodes.values()],
            mfilter=flt,
            queuesize=1,
            sampling_interval=float(cfg.sampling_ms),
        )
        for (name, nid), h in zip(self.nodes.items(), handles):
            if isinstance(h, ua.StatusCode):
                log.warning("OPC UA input %s: cannot subscribe to %s (%s)", name, nid, h)
        return client

    async def run(self) -> None:
        """Connect (retrying with capped back-off) and keep the subscription until cancelled."""
        delay = 0.2
        while True:
            try:
                self._client = await self._connect()
                self.status = "connected"
                log.info("OPC UA inputs: %s on %s", ", ".join(self.nodes), self.endpoint)
                # asyncua's supervisor now watches the link, reconnects and re-creates the
                # subscription; until then the values simply stop arriving (and go stale)
                await asyncio.Event().wait()
            except asyncio.CancelledError:
                raise
            except InputError:
                raise
            except Exception as exc:  # refused, timed out, bad certificate: retry
                self.status = f"connecting ({type(exc).__name__})"
                # the type too: a timeout (e.g. a server that cannot decrypt what a wrongly
                # pinned server_certificate encrypted) has no message of its own
                why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                log.warning("OPC UA inputs: %s: %s; retry in %.1f s", self.endpoint, why, delay)
                await self._disconnect()
                await asyncio.sleep(delay)
                delay = min(delay * 2.0, 5.0)

    async def _disconnect(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(client.disconnect(), 2.0)

    async def close(self) -> None:
        """Unsubscribe and disconnect."""
        await self._disconnect()


def certificate_uri(cert) -> str:
    """The application URI a certificate names (its first SubjectAltName URI), or ""."""
    from cryptography import x509  # noqa: PLC0415 - optional extra: cryptography (with asyncua)

    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return ""
    uris = san.get_values_for_type(x509.UniformResourceIdentifier)
    return uris[0] if uris else ""
