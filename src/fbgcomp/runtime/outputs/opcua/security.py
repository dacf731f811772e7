"""The OPC UA server's own certificate, and what a client may do or load.

Security: only ``Basic256Sha256`` Sign & Encrypt endpoints, with a self-signed application
certificate generated on first start under ``<state_dir>/opcua/`` (:func:`ensure_certificate`).
Only password users may write ``Enabled`` and call ``ReloadModel`` (:func:`writer_warning` says
when there is none; the session rules are :mod:`.access`'s), and ``ReloadModel`` loads only
files inside ``models_dir`` (:func:`model_in_folder`). Plain Python: the service side imports
it (``cryptography``, of the runtime extra, only when a certificate is made).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import socket
from pathlib import Path

from fbgcomp.atomic import write_bytes
from fbgcomp.runtime.outputs.opcua.address_space import APPLICATION_URI


def ensure_certificate(
    state_dir: str | Path, application_uri: str = APPLICATION_URI, days: int = 3650
) -> tuple[Path, Path]:
    """Self-signed server certificate (DER) and key (PEM) under ``state_dir/opcua``.

    Generated once with ``cryptography`` and reused; both files are written atomically and the
    key is readable by the owner only.
    """
    # optional extra (cryptography, of the runtime extra): imported only when a certificate is needed
    from cryptography import x509  # noqa: PLC0415 - optional extra: cryptography
    from cryptography.hazmat.primitives import hashes, serialization  # noqa: PLC0415 - optional extra
    from cryptography.hazmat.primitives.asymmetric import rsa  # noqa: PLC0415 - optional extra
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID  # noqa: PLC0415 - optional extra

    folder = Path(state_dir) / "opcua"
    folder.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = folder / "server_cert.der", folder / "server_key.pem"
    if cert_path.is_file() and key_path.is_file():
        try:
            cert = x509.load_der_x509_certificate(cert_path.read_bytes())
            uris = cert.extensions.get_extension_for_class(
                x509.SubjectAlternativeName
            ).value.get_values_for_type(x509.UniformResourceIdentifier)
            if application_uri in uris and cert.not_valid_after_utc > dt.datetime.now(dt.UTC):
                return cert_path, key_path
        except Exception:  # unreadable or foreign certificate: make a new one
            pass
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    name = x509.Name(
        [
            x509.NameAttribute(NameOID.COMMON_NAME, "fbgcomp runtime"),
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "fbgcomp"),
        ]
    )
    now = dt.datetime.now(dt.UTC)
    host = socket.gethostname()
    san = [
        x509.UniformResourceIdentifier(application_uri),
        x509.DNSName("localhost"),
        x509.DNSName(host),
        x509.IPAddress(ipaddress.ip_address("127.0.0.1")),
    ]
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.SubjectAlternativeName(san), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=True,
                key_encipherment=True,
                data_encipherment=True,
                key_agreement=False,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    key_pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    write_bytes(key_path, key_pem, mode=0o600)
    write_bytes(cert_path, cert.public_bytes(serialization.Encoding.DER), mode=0o644)
    return cert_path, key_path


def writer_warning(users: dict, allow_anonymous: bool) -> str | None:
    """The start-up warning when no OPC UA user may write, else None.

    Only password users may write ``Enabled`` and call ``ReloadModel``; without any, no client
    can switch the compensation or reload its model (and without ``allow_anonymous`` no client
    can even open a session).
    """
    if users:
        return None
    who = (
        "anonymous sessions may only read"
        if allow_anonymous
        else "and without --allow-anonymous every session is refused (BadIdentityTokenRejected)"
    )
    return (
        "no OPC UA user may write: no client can switch the compensation (Enabled) or "
        f"reload the model (ReloadModel), {who}. Add a user: --users FILE (lines "
        "name:pbkdf2_sha256$..., docs/security.md) or FBGCOMP_OPCUA_USER and "
        "FBGCOMP_OPCUA_PASSWORD in serve's environment"
    )


class ModelPathRefused(ValueError):
    """A ReloadModel argument that names no file of the models folder; ``status`` is the
    OPC UA status code name the call answers."""

    def __init__(self, message: str, status: str = "BadInvalidArgument"):
        super().__init__(message)
        self.status = status


def model_in_folder(name: str, models_dir: str | Path | None) -> str:
    """The model file ``ReloadModel(name)`` may load: ``name`` relative to ``models_dir``.

    ``""`` reloads the model ``serve`` was started with. Absolute paths, ``..`` and symbolic
    links that lead out of the folder are refused (``BadInvalidArgument``), as is any name when
    no folder is configured (``BadNotSupported``); a missing file is ``BadNotFound``.
    """
    if not name:
        return ""
    if not models_dir:
        raise ModelPathRefused(
            "no models folder is configured (opcua.models_dir, --models-dir)", "BadNotSupported"
        )
    if "\x00" in name or len(name) > 4096:
        raise ModelPathRefused("not a file name")
    rel = Path(name)
    if rel.is_absolute() or ".." in rel.parts:
        raise ModelPathRefused(
            f"{name!r} is not a file name inside the models folder (absolute paths and '..' are refused)"
        )
    folder = Path(models_dir).resolve()
    target = (folder / rel).resolve()
    if not target.is_relative_to(folder):
        raise ModelPathRefused(f"{name!r} leads out of the models folder")
    if not target.is_file():
        raise ModelPathRefused(f"no model {name!r} in the models folder", "BadNotFound")
    return str(target)
