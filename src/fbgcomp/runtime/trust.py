"""The OPC UA server's trust list: which client certificates may open a session.

The trust list is a folder of certificates, ``<state_dir>/opcua/trusted/`` unless
``opcua.trusted_clients_dir`` names another. A client is accepted only when its certificate is
in that folder, or was issued by a CA certificate in it, is within its validity period, names
the client's application URI and allows client use: asyncua's ``TrustStore`` and
``CertificateValidator`` with ``TRUSTED_VALIDATION``. An empty or missing folder trusts nobody.

``fbgcomp trust add CERT`` checks that CERT is one X.509 certificate (DER or PEM) and writes it,
as DER, into the folder atomically; ``fbgcomp trust list`` shows what is trusted. The running
server notices a changed folder at the next connection attempt: no restart is needed.

A refused certificate is copied to ``<state_dir>/opcua/rejected/`` (at most
:data:`MAX_REJECTED` files, so a hostile client cannot fill the disk) and the log says how to
trust it: the usual OPC UA way of admitting a new client after checking it is the expected one.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

from fbgcomp.atomic import write_bytes
from fbgcomp.errors import InputError

log = logging.getLogger("fbgcomp.runtime")
audit = logging.getLogger("fbgcomp.audit")

MAX_CERT_BYTES = 64 * 1024  # a certificate is a few kB; anything larger is not one
MAX_REJECTED = 64


def default_state_dir() -> Path:
    """``$XDG_STATE_HOME/fbgcomp`` (``~/.local/state/fbgcomp``), never the working folder."""
    return Path(os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state") / "fbgcomp"


def trusted_dir(state_dir: str | Path | None = None, configured: str | Path | None = None) -> Path:
    """The trust-list folder: ``configured`` if set, else ``<state_dir>/opcua/trusted``."""
    if configured:
        return Path(configured)
    return Path(state_dir or default_state_dir()) / "opcua" / "trusted"


def rejected_dir(state_dir: str | Path | None = None) -> Path:
    """Where refused client certificates are kept: ``<state_dir>/opcua/rejected``."""
    return Path(state_dir or default_state_dir()) / "opcua" / "rejected"


# --------------------------------------------------------------------------- certificates
@dataclass
class CertificateInfo:
    """What identifies a certificate to a person deciding whether to trust it."""

    path: Path
    subject: str = ""
    application_uri: str = ""
    sha256: str = ""
    not_after: str = ""
    error: str = ""  # set when the file is not a readable certificate

    def describe(self) -> str:
        """One line: file name, subject, application URI, expiry and SHA-256 (or the error)."""
        if self.error:
            return f"{self.path.name}: {self.error}"
        return (
            f"{self.path.name}: {self.subject or '(no subject)'}, "
            f"uri {self.application_uri or '(none)'}, valid until {self.not_after}, "
            f"sha256 {self.sha256}"
        )


def _info(cert, path: Path) -> CertificateInfo:
    from cryptography import x509  # noqa: PLC0415 - optional extra: cryptography (the runtime extra)
    from cryptography.hazmat.primitives import serialization  # noqa: PLC0415 - optional extra: cryptography (the runtime extra)

    der = cert.public_bytes(serialization.Encoding.DER)
    try:
        uris = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value.get_values_for_type(
            x509.UniformResourceIdentifier
        )
    except x509.ExtensionNotFound:
        uris = []
    return CertificateInfo(
        path,
        cert.subject.rfc4514_string(),
        ", ".join(uris),
        hashlib.sha256(der).hexdigest(),
        cert.not_valid_after_utc.strftime("%Y-%m-%d"),
    )


def parse_certificate(data: bytes):
    """One X.509 certificate from DER or PEM bytes; ValueError with the reason otherwise."""
    from cryptography import x509  # noqa: PLC0415 - optional extra: cryptography (the runtime extra)

    if b"-----BEGIN" in data:
        blocks = re.findall(rb"-----BEGIN CERTIFICATE-----.+?-----END CERTIFICATE-----", data, re.S)
        if len(blocks) != 1:
            raise ValueError(f"PEM file holds {len(blocks)} certificates, expected one")
        return x509.load_pem_x509_certificate(blocks[0])
    return x509.load_der_x509_certificate(data)


def read_certificate(path: str | Path):
    """The certificate in ``path`` (DER or PEM), or InputError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError("certificate file not found", file=path)
    with open(path, "rb") as fh:
        data = fh.read(MAX_CERT_BYTES + 1)
    if len(data) > MAX_CERT_BYTES:
        raise InputError(f"larger than {MAX_CERT_BYTES // 1024} kB: not a certificate", file=path)
    try:
        cert = parse_certificate(data)
    except ValueError as exc:
        reason = str(exc) if "expected one" in str(exc) else "not an X.509 certificate (DER or PEM)"
        raise InputError(reason, file=path) from exc
    if cert.not_valid_after_utc < dt.datetime.now(dt.UTC):
        raise InputError(f"certificate expired on {cert.not_valid_after_utc:%Y-%m-%d}", file=path)
    return cert


def add_certificate(path: str | Path, directory: str | Path) -> tuple[CertificateInfo, bool]:
    """Copy the certificate in ``path`` into the trust list ``directory`` (as DER, atomically).

    Returns its description and whether it was new (False: already trusted, nothing written).
    """
    from cryptography.hazmat.primitives import serialization  # noqa: PLC0415 - optional extra: cryptography (the runtime extra)

    cert = read_certificate(path)
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise InputError("trust list is not a folder", file=directory)
    info = _info(cert, Path(path))
    for known in list_certificates(directory):
        if known.sha256 == info.sha256:
            return known, False
    cn = cert.subject.rfc4514_string().partition("CN=")[2].split(",")[0] or "client"
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", cn)[:40].strip("._") or "client"
    target = directory / f"{name}-{info.sha256[:16]}.der"
    directory.mkdir(parents=True, exist_ok=True)
    # world-readable like any certificate; the temporary name ".incoming-<hex>.tmp" holds
    # neither "der" nor "pem", so a server reloading the folder meanwhile never reads a half
    write_bytes(target, cert.public_bytes(serialization.Encoding.DER), mode=0o644, prefix=".incoming-")
    info.path = target
    audit.info("trust list %s: added %s", directory, info.describe())
    return info, True


def list_certificates(directory: str | Path) -> list[CertificateInfo]:
    """Every certificate file in ``directory`` (unreadable ones with their ``error``)."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    out = []
    for path in sorted(directory.iterdir()):
        # the files asyncua's TrustStore reads: a name with a dot that holds "der" or "pem"
        name = path.name.lower()
        if "." not in name or not re.match(".*(der|pem)", name) or not path.is_file():
            continue
        try:
            if path.stat().st_size > MAX_CERT_BYTES:
                raise ValueError("too large")
            out.append(_info(parse_certificate(path.read_bytes()), path))
        except (ValueError, OSError):
            out.append(CertificateInfo(path, error="not a readable certificate"))
    return out


# --------------------------------------------------------------------------- server side
class TrustListValidator:
    """asyncua certificate validator (``Server.set_certificate_validator``) over a trust folder.

    Every session's client certificate goes through asyncua's ``CertificateValidator`` with
    ``TRUSTED_VALIDATION | PEER_CLIENT`` and a ``TrustStore`` of ``directory``, reloaded when
    the folder changed since the last check. Accepted and refused clients are logged on
    ``fbgcomp.audit``; refused certificates are kept in ``rejected`` for ``fbgcomp trust add``.
    """

    def __init__(self, directory: str | Path, rejected: str | Path | None = None):
        self.directory = Path(directory)
        self.rejected = Path(rejected) if rejected else None
        self._signature = None
        self._store = None
        # asyncua's trust store logs a traceback for every refused certificate; we log one line
        logging.getLogger("asyncuagds.validate").setLevel(logging.CRITICAL)

    def _folder_signature(self):
        try:
            return tuple(
                sorted((e.name, e.stat().st_mtime_ns, e.stat().st_size) for e in os.scandir(self.directory))
            )
        except OSError:
            return None

    async def _current_store(self):
        from asyncua.crypto.truststore import TrustStore  # noqa: PLC0415 - optional extra: asyncua (the runtime extra)

        signature = self._folder_signature()
        if signature != self._signature:
            self._signature = signature
            self._store = None
            if signature:
                store = TrustStore([self.directory], [])
                try:
                    await store.load()
                    self._store = store
                except ValueError:  # no certificate in the folder
                    pass
                except Exception as exc:  # a foreign file: trust nobody rather than guess
                    log.error(
                        "OPC UA trust list %s unreadable (%s): every client is refused; "
                        "see fbgcomp trust list",
                        self.directory,
                        type(exc).__name__,
                    )
            log.info("OPC UA trust list %s: %d certificate file(s)", self.directory, len(signature or ()))
        return self._store

    async def __call__(self, cert, app_description) -> None:
        """Accept (return) or refuse (asyncua ``ServiceError``) a session's client certificate."""
        from asyncua import ua  # noqa: PLC0415 - optional extra: asyncua (the runtime extra)
        from asyncua.common.utils import ServiceError  # noqa: PLC0415 - optional extra: asyncua (the runtime extra)
        from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions  # noqa: PLC0415 - optional extra: asyncua (the runtime extra)

        info = _info(cert, Path("client"))
        store = await self._current_store()
        try:
            if store is None:
                raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)
            await CertificateValidator(
                CertificateValidatorOptions.TRUSTED_VALIDATION | CertificateValidatorOptions.PEER_CLIENT,
                store,
            ).validate(cert, app_description)
        except ServiceError as exc:
            # asyncua annotates the value as its UInt32 (an int subclass); the int code is what it takes
            reason = ua.StatusCode(exc.code).name  # type: ignore[arg-type]
            kept = self._keep_rejected(cert, info)
            hint = f"; to trust it: fbgcomp trust add {kept}" if kept else ""
            audit.warning(
                "OPC UA client refused (%s): %s, uri %s, sha256 %s%s",
                reason,
                info.subject,
                app_description.ApplicationUri,
                info.sha256,
                hint,
            )
            raise
        audit.info(
            "OPC UA client accepted: %s, uri %s, sha256 %s",
            info.subject,
            app_description.ApplicationUri,
            info.sha256,
        )

    def _keep_rejected(self, cert, info: CertificateInfo) -> Path | None:
        from cryptography.hazmat.primitives import serialization  # noqa: PLC0415 - optional extra: cryptography (the runtime extra)

        if self.rejected is None:
            return None
        target = self.rejected / f"{info.sha256[:16]}.der"
        try:
            if target.exists():
                return target
            if self.rejected.is_dir() and sum(1 for _ in self.rejected.glob("*.der")) >= MAX_REJECTED:
                return None
            write_bytes(target, cert.public_bytes(serialization.Encoding.DER))
            return target
        except OSError:
            return None
