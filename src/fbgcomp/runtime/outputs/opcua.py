"""OPC UA server facing the CNC / PLC (asyncua), in its own process.

The compensation loop hands over the latest values with :meth:`OpcUaServer.publish`, which
never blocks: the server process writes them into the address space at most ``rate_hz`` times a
second (latest value wins), so clients connecting, disconnecting or reading slowly - and the
RSA work of their secure-channel handshakes, and the encryption of every notification - never
stall the loop, nor compete with it for the interpreter lock.

Security: only ``Basic256Sha256`` Sign & Encrypt endpoints, with a self-signed application
certificate generated on first start under ``<state_dir>/opcua/``. Only clients whose
certificate is in the trust list (``<state_dir>/opcua/trusted/`` or ``trusted_clients_dir``,
filled with ``fbgcomp trust add``; see :mod:`fbgcomp.runtime.trust`) may open a session.
Anonymous sessions are refused unless ``allow_anonymous``; even then they may only browse, read
and subscribe. Writing ``Enabled`` and calling ``ReloadModel`` need a user name and password
(users from the configured users file or the ``FBGCOMP_OPCUA_USER`` / ``FBGCOMP_OPCUA_PASSWORD``
environment). ``ReloadModel`` loads only files inside ``models_dir``. Every write and method
call, refused or not, and every client certificate accepted or refused is logged with its user
on the ``fbgcomp.audit`` logger and in ``<state_dir>/opcua/audit.log``.

Address space (namespace ``urn:fbgcomp:runtime``, string node ids ``FbgComp.<name>``) is
documented in docs/runtime.md; how it maps onto OPC 40501-1 (Machine Tools) in docs/opcua-cnc.md.
Every length, wavelength and duration is an ``AnalogItemType`` variable with its
``EngineeringUnits`` (UNECE Rec. 20 code, OPC 10000-8 section 5.6.3) and ``EURange``; every
node carries a Description, and ``ReloadModel``'s arguments are named and described.
"""

from __future__ import annotations

import asyncio
import base64
import contextvars
import dataclasses
import datetime as dt
import hashlib
import hmac
import ipaddress
import logging
import os
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Awaitable, Callable

from fbgcomp.errors import InputError
from fbgcomp.runtime import trust

log = logging.getLogger("fbgcomp.runtime")
audit = logging.getLogger("fbgcomp.audit")
AUDIT_LOG_BYTES = 1 << 20          # audit.log rotates at 1 MiB, 5 old files kept
NAMESPACE = "urn:fbgcomp:runtime"
APPLICATION_URI = "urn:fbgcomp:runtime:server"
AXES = ("X", "Y", "Z")
PBKDF2_ITERATIONS = 100_000


# --------------------------------------------------------------------------- units
UNECE_NAMESPACE_URI = "http://www.opcfoundation.org/UA/units/un/cefact"
# unit in our names (``_um``...) -> UNECE Rec. 20 common code, display name, description
UNITS = {
    "um": ("4H", "\u00b5m", "micrometre (micron)"),
    "nm": ("C45", "nm", "nanometre"),
    "ms": ("C26", "ms", "millisecond"),
    "mm": ("MMT", "mm", "millimetre"),
    # Rec. 20 has no micrometre per metre; "59" (part per million, 10^-6) is the same ratio
    # (1 µm of correction per m of travel), shown as µm/m (docs/opcua-cnc.md)
    "um_per_m": ("59", "\u00b5m/m", "micrometre per metre (part per million, 1e-6)"),
}


def unece_unit_id(common_code: str) -> int:
    """OPC UA ``EUInformation.UnitId`` of a UNECE Rec. 20 common code (OPC 10000-8, 5.6.3).

    The code's (at most three) ASCII characters, most significant first:
    ``"4H"`` (micrometre) -> ``0x3448`` = 13384, ``"C45"`` (nanometre) -> ``0x433435``.
    """
    if not 1 <= len(common_code) <= 3 or not common_code.isascii():
        raise ValueError(f"not a UNECE common code: {common_code!r}")
    unit_id = 0
    for c in common_code:
        unit_id = (unit_id << 8) | ord(c)
    return unit_id


def eu_information(unit: str):
    """``ua.EUInformation`` of one of :data:`UNITS` (``"um"``, ``"nm"``, ``"ms"``)."""
    from asyncua import ua
    code, display, description = UNITS[unit]
    return ua.EUInformation(NamespaceUri=UNECE_NAMESPACE_URI, UnitId=unece_unit_id(code),
                            DisplayName=ua.LocalizedText(display),
                            Description=ua.LocalizedText(description))


# EURange (OPC 10000-8: the range "likely to be obtained in normal operation", e.g. to scale a
# bar graph) of the analog variables; OpcUaServer(eu_ranges=...) overrides any of them
DEFAULT_EU_RANGES = {
    "Correction": (-1000.0, 1000.0),          # µm: serve's default --max-correction-um
    "PredictedDeviation": (-1000.0, 1000.0),  # µm
    "IntervalHalfWidth": (0.0, 1000.0),       # µm
    "ExpectedError": (0.0, 1000.0),           # µm
    "Latency_ms": (0.0, 1000.0),              # ms
    "Wavelength_nm": (1460.0, 1640.0),        # nm: S, C and L bands of FBG interrogators
    "Offset": (-1000.0, 1000.0),              # µm: the offset + Z slope form (cnc_form)
    "Slope": (-1000.0, 1000.0),               # µm/m
    "ZRef_mm": (-10000.0, 10000.0),           # mm
}

# Description attribute of every node (what a PLC programmer or an integrator browsing the
# server reads); the per-axis ones take the axis letter
DESCRIPTIONS = {
    "FbgComp": "Thermal compensation of the machine tool from fibre-Bragg-grating strain sensors "
               "(fbgcomp). OPC 40501-1: a <MonitoredElement> of MachineTool/Monitoring "
               "(ElementMonitoringType concept); vendor-specific, see docs/opcua-cnc.md.",
    "ThermalCompensationType": "fbgcomp's thermal compensation of a machine tool. Corresponds to "
                               "OPC 40501-1 ElementMonitoringType (a <MonitoredElement> of the "
                               "machine tool's Monitoring); not derived from it, since the server "
                               "does not load the Machine Tools nodeset.",
    "Name": "Name of the monitored element (as ElementMonitoringType.Name in OPC 40501-1).",
    "Correction": "Correction to apply on axis {a}: minus the predicted tool-tip deviation, "
                  "after the do-no-harm limits; 0 while ZEROING or not Enabled, held and ramped "
                  "to 0 in ALARM.",
    "PredictedDeviation": "Model prediction of the tool-tip (TTP) thermal deviation on axis {a} "
                          "(NaN without a model).",
    "IntervalHalfWidth": "Half-width of the 95 % prediction interval of the deviation on axis {a}.",
    "ExpectedError": "Residual standard deviation of the model in use (full or fallback) on "
                     "axis {a}.",
    "OutputFlags": "Why the published correction on axis {a} is held back, one bit each: "
                   "{flags}; 0 = not held back.",
    "SampleTime": "Instrument time stamp of the published sample; written last, so a client "
                  "watching it sees a complete sample.",
    "Latency_ms": "Frame time stamp to publication (updated at most 10 times a second).",
    "ModelId": "model_id of the model file in use.",
    "Health": "ZEROING, OK, DEGRADED or ALARM; apply the correction only in OK or DEGRADED.",
    "Alarm": "True: compensator fault (health ALARM); ramp the applied correction to zero.",
    "FallbackInUse": "Sensors excluded by the fallback model in use, e.g. S3; empty for the "
                     "full model.",
    "Limited": "True: the published correction is held back on some axis (a flag is set).",
    "OutputFlagsText": "The output flags as text, e.g. Y:RATE_LIMITED Z:SHRUNK; empty when "
                       "nothing is held back.",
    "SourceStatus": "Wavelength source: connected, reconnecting (...), replaying or finished.",
    "FramesProcessed": "Frames processed since start (updated at most 10 times a second).",
    "Heartbeat": "Incremented at least every 0.2 s, data or not: the CNC's watchdog.",
    "Enabled": "Switch of the correction output (false: the published correction is 0). "
               "Writable by an authenticated user.",
    "Sensors": "The fibre-Bragg-grating strain sensors (vendor-specific).",
    "Sensor": "Strain sensor {s}: a grating bonded to the machine structure.",
    "Sensors.Status": "Sensor status, one of {statuses} (docs/runtime.md).",
    "Sensors.Wavelength_nm": "Last Bragg wavelength of the sensor in its window (updated at "
                             "most 10 times a second).",
    "Offset": "Offset of the correction on axis {a} at the reference position ZRef_mm, the "
              "form a CNC's thermal compensation takes from the PLC (offset + slope x (Z - "
              "ZRef_mm), docs/cnc-integration.md): the correction rate- and magnitude-limited "
              "as the Modbus output's offset; ramps to 0 when the output is off or in ALARM.",
    "Slope": "Slope of the correction on axis {a} with the Z position at ZRef_mm, micrometres "
             "of correction per metre of Z travel (rate- and magnitude-limited as the Modbus "
             "output's); 0 for a model without a Z term or when not applied.",
    "ZRef_mm": "Reference Z position of OffsetX/Y/Z_um and SlopeX/Y/Z_um_per_m: the live Z "
               "the model was evaluated at, else the model's own; 0 for a model without a Z "
               "term (its slope is 0).",
    "ReloadModel": "Load a model file of the models folder (opcua.models_dir), or reload the "
                   "current one. Needs an authenticated user; the new model must expect the "
                   "same sensors and probes.",
    "ReloadModel.ModelFile": "Model file name relative to the models folder (no absolute path, "
                             "no '..'); empty: reload the model serve was started with.",
    "ReloadModel.Result": "What was loaded: 'loaded <model_id>'.",
}


def reload_model_arguments():
    """``ReloadModel``'s input and output arguments (``ua.Argument``), named and described."""
    from asyncua import ua

    def arg(name):
        return ua.Argument(Name=name, DataType=ua.NodeId(ua.ObjectIds.String),
                           ValueRank=ua.ValueRank.Scalar, ArrayDimensions=[],
                           Description=ua.LocalizedText(DESCRIPTIONS[f"ReloadModel.{name}"]))
    return [arg("ModelFile")], [arg("Result")]


def writer_warning(users: dict, allow_anonymous: bool) -> str | None:
    """The start-up warning when no OPC UA user may write, else None.

    Only password users may write ``Enabled`` and call ``ReloadModel``; without any, no client
    can switch the compensation or reload its model (and without ``allow_anonymous`` no client
    can even open a session).
    """
    if users:
        return None
    who = ("anonymous sessions may only read" if allow_anonymous else
           "and without --allow-anonymous every session is refused (BadIdentityTokenRejected)")
    return ("no OPC UA user may write: no client can switch the compensation (Enabled) or "
            f"reload the model (ReloadModel), {who}. Add a user: --users FILE (lines "
            "name:pbkdf2_sha256$..., docs/security.md) or FBGCOMP_OPCUA_USER and "
            "FBGCOMP_OPCUA_PASSWORD in serve's environment")


# --------------------------------------------------------------------------- certificate
def ensure_certificate(state_dir: str | Path, application_uri: str = APPLICATION_URI,
                       days: int = 3650) -> tuple[Path, Path]:
    """Self-signed server certificate (DER) and key (PEM) under ``state_dir/opcua``.

    Generated once with ``cryptography`` and reused; both files are written atomically and the
    key is readable by the owner only.
    """
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import rsa
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    folder = Path(state_dir) / "opcua"
    folder.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = folder / "server_cert.der", folder / "server_key.pem"
    if cert_path.is_file() and key_path.is_file():
        try:
            cert = x509.load_der_x509_certificate(cert_path.read_bytes())
            uris = cert.extensions.get_extension_for_class(
                x509.SubjectAlternativeName).value.get_values_for_type(
                x509.UniformResourceIdentifier)
            if application_uri in uris and cert.not_valid_after_utc > dt.datetime.now(dt.timezone.utc):
                return cert_path, key_path
        except Exception:  # unreadable or foreign certificate: make a new one
            pass
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "fbgcomp runtime"),
                      x509.NameAttribute(NameOID.ORGANIZATION_NAME, "fbgcomp")])
    now = dt.datetime.now(dt.timezone.utc)
    host = socket.gethostname()
    san = [x509.UniformResourceIdentifier(application_uri), x509.DNSName("localhost"),
           x509.DNSName(host), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.SubjectAlternativeName(san), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=True,
                                         key_encipherment=True, data_encipherment=True,
                                         key_agreement=False, key_cert_sign=False,
                                         crl_sign=False, encipher_only=False,
                                         decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                           critical=False)
            .sign(key, hashes.SHA256()))
    key_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                serialization.NoEncryption())
    _atomic_write(key_path, key_pem, mode=0o600)
    _atomic_write(cert_path, cert.public_bytes(serialization.Encoding.DER))
    return cert_path, key_path


def _atomic_write(path: Path, data: bytes, mode: int = 0o644) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


# --------------------------------------------------------------------------- users
def hash_password(password: str, salt: bytes | None = None,
                  iterations: int = PBKDF2_ITERATIONS) -> str:
    """``pbkdf2_sha256$<iterations>$<salt b64>$<hash b64>`` for the users file."""
    salt = salt or os.urandom(16)
    digest = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
    return (f"pbkdf2_sha256${iterations}${base64.b64encode(salt).decode()}$"
            f"{base64.b64encode(digest).decode()}")


def verify_password(password: str, stored: str) -> bool:
    try:
        algo, iters, salt, digest = stored.split("$")
        if algo != "pbkdf2_sha256":
            return False
        got = hashlib.pbkdf2_hmac("sha256", password.encode(), base64.b64decode(salt), int(iters))
        return hmac.compare_digest(got, base64.b64decode(digest))
    except (ValueError, TypeError):
        return False


def load_users(users_file: str | Path | None, environ=os.environ, *, service="OPC UA",
               env_prefix="FBGCOMP_OPCUA", doc="docs/runtime.md", iterations=1000) -> dict[str, str]:
    """User -> password hash, from ``users_file`` (lines ``name:pbkdf2_sha256$...``) and the
    environment (``<env_prefix>_USER`` / ``<env_prefix>_PASSWORD``, hashed in memory only).

    Shared by every password-protected surface (OPC UA writes, the dashboard's control).
    """
    users: dict[str, str] = {}
    if users_file:
        path = Path(users_file)
        if not path.is_file():
            raise InputError(f"{service} users file not found", file=path)
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            name, sep, stored = line.partition(":")
            if not sep or not stored.startswith("pbkdf2_sha256$"):
                raise InputError(f"expected name:pbkdf2_sha256$... (see {doc})",
                                 file=path, column=f"line {i}")
            users[name.strip()] = stored.strip()
    user, pwd = environ.get(f"{env_prefix}_USER"), environ.get(f"{env_prefix}_PASSWORD")
    if user and pwd:
        users[user] = hash_password(pwd, iterations=iterations)
    return users


def make_user_manager(users: dict[str, str], allow_anonymous: bool):
    from asyncua.crypto.permission_rules import User, UserRole

    class FbgUserManager:
        """Password users get the User role (read, write, call); anonymous only reads."""

        def __init__(self):
            self._ok_cache: dict[tuple[str, bytes], bool] = {}

        def get_user(self, iserver, username=None, password=None, certificate=None):
            if username is None:
                return User(role=UserRole.Anonymous) if allow_anonymous else None
            stored = users.get(username)
            if stored is None or password is None:
                return None
            key = (username, hashlib.sha256(password.encode()).digest())
            if key not in self._ok_cache:
                self._ok_cache[key] = verify_password(password, stored)
            return User(role=UserRole.User, name=username) if self._ok_cache[key] else None

    return FbgUserManager()


# The user of the request being served. asyncua hands the user to the permission ruleset but
# not to method callbacks; a connection's requests are served one at a time in one task, so
# the ruleset records it here and ReloadModel reads it back for the audit log.
_request_user: contextvars.ContextVar[str] = contextvars.ContextVar("opcua_user",
                                                                     default="unknown")


def user_label(user) -> str:
    """How a session's user appears in the audit log: the user name, or ``anonymous``."""
    name = getattr(user, "name", None)
    return name if name else "anonymous"


def make_ruleset():
    from asyncua import ua
    from asyncua.crypto.permission_rules import SimpleRoleRuleset, UserRole

    write = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)
    call = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)

    class ReadOnlyAnonymousRuleset(SimpleRoleRuleset):
        """Anonymous sessions may browse, read and subscribe, never write or call."""

        def __init__(self):
            super().__init__()
            denied = {write, call,
                      ua.NodeId(ua.ObjectIds.HistoryReadRequest_Encoding_DefaultBinary)}
            self._permission_dict[UserRole.Anonymous] = (
                self._permission_dict[UserRole.User] - denied)

        def check_validity(self, user, action_type_id, body):
            _request_user.set(user_label(user))
            allowed = super().check_validity(user, action_type_id, body)
            if not allowed and action_type_id in (write, call):
                audit.warning("OPC UA %s by %s refused: access denied",
                              "write" if action_type_id == write else "method call",
                              user_label(user))
            return allowed

    return ReadOnlyAnonymousRuleset()


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
        raise ModelPathRefused("no models folder is configured (opcua.models_dir, --models-dir)",
                               "BadNotSupported")
    if "\x00" in name or len(name) > 4096:
        raise ModelPathRefused("not a file name")
    rel = Path(name)
    if rel.is_absolute() or ".." in rel.parts:
        raise ModelPathRefused(f"{name!r} is not a file name inside the models folder "
                               "(absolute paths and '..' are refused)")
    folder = Path(models_dir).resolve()
    target = (folder / rel).resolve()
    if not target.is_relative_to(folder):
        raise ModelPathRefused(f"{name!r} leads out of the models folder")
    if not target.is_file():
        raise ModelPathRefused(f"no model {name!r} in the models folder", "BadNotFound")
    return str(target)


# --------------------------------------------------------------------------- server
@dataclass
class OpcUaConfig:
    endpoint: str = "opc.tcp://127.0.0.1:4840/fbgcomp/"
    rate_hz: float = 100.0            # address-space updates per second; 0 = every batch
    allow_anonymous: bool = False
    users_file: str | None = None
    # certificates: $XDG_STATE_HOME/fbgcomp (~/.local/state/fbgcomp), never the working folder
    state_dir: str = field(default_factory=lambda: str(trust.default_state_dir()))
    # the client certificates trusted; unset or "": <state_dir>/opcua/trusted (fbgcomp trust add)
    trusted_clients_dir: str | None = None
    models_dir: str | None = None     # ReloadModel loads only files in this folder


@dataclass
class Snapshot:
    """Values of one published sample (the last frame of a batch)."""

    sample_time_s: float
    correction_um: tuple
    deviation_um: tuple
    half_width_um: tuple
    expected_rms_um: tuple
    health: str
    fallback: str
    alarm: bool
    sensor_status: list
    sensor_wavelength_nm: list
    source_status: str = ""
    frames: int = 0
    model_id: str = ""
    received_s: float = 0.0
    output_flags: tuple = (0, 0, 0)   # health.FLAG_* per axis: model policy | limits
    # the offset + Z slope form (runtime.cnc_form), rate- and magnitude-limited; None: not
    # computed for this sample (the OPC UA variables keep their value)
    cnc_offset_um: tuple | None = None
    cnc_slope_um_per_m: tuple | None = None
    cnc_z_ref_mm: float | None = None


def send_control(sock, message, timeout_s: float = 2.0) -> bool:
    """Send a control message (Enabled, model id, reload) over the process socket pair.

    Snapshots may be dropped when the other side lags (the newest wins anyway); a control
    message may not: an operator's "disable" that silently vanished would leave corrections on.
    So wait, up to ``timeout_s``, for room in the socket buffer; False (logged) if there is none.
    """
    import pickle
    import select

    if sock is None:
        return False
    data = pickle.dumps(message)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            sock.send(data, socket.MSG_DONTWAIT)
            return True
        except (BlockingIOError, InterruptedError):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                log.error("control message %r not delivered: the other process is not reading",
                          message[0])
                return False
            select.select([], [sock], [], remaining)
        except OSError:
            return False


class OpcUaServer:
    """The OPC UA server, run in a child process; this is the service-side handle.

    Running asyncua in its own process (not a thread) keeps its work - encryption of every
    notification, secure-channel handshakes, clients coming and going - off the compensation
    loop's interpreter: no GIL hand-over on every update. The two sides talk over a Unix
    ``SOCK_SEQPACKET`` socket pair: ``publish`` sends the newest snapshot without ever blocking
    (when the server process lags, snapshots are dropped: the newest wins anyway); the server
    sends back changes of ``Enabled`` and ``ReloadModel`` calls, which a small reader thread
    hands to ``on_reload`` on ``main_loop``. The server process exits when the service dies
    (the socket closes).
    """

    def __init__(self, config: OpcUaConfig, sensor_names: list[str], model_id: str,
                 on_reload: Callable[[str], Awaitable[str]] | None = None,
                 main_loop: asyncio.AbstractEventLoop | None = None,
                 eu_ranges: dict[str, tuple[float, float]] | None = None):
        self.config = config
        # EURange overrides, by kind (keys of DEFAULT_EU_RANGES) or Wavelength_nm.<sensor>
        self.eu_ranges = dict(eu_ranges or {})
        self.sensor_names = list(sensor_names)
        self._model_id = model_id
        self.on_reload = on_reload
        self.main_loop = main_loop
        self.enabled = True
        self.users = load_users(config.users_file)
        self.dropped = 0
        self.cert_path, self.key_path = ensure_certificate(config.state_dir)
        self._sock: socket.socket | None = None
        self._proc = None
        self._reader: threading.Thread | None = None

    @property
    def model_id(self) -> str:
        return self._model_id

    @model_id.setter
    def model_id(self, value: str) -> None:
        self._model_id = value
        send_control(self._sock, ("model_id", value))

    def start(self, timeout_s: float = 60.0) -> None:
        import pickle
        import subprocess
        import sys
        parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "fbgcomp.runtime.outputs.opcua", "--worker-fd", str(child.fileno())],
            pass_fds=[child.fileno()])
        child.close()
        init = {"config": self.config.__dict__, "sensor_names": self.sensor_names,
                "model_id": self._model_id, "users": self.users,
                "cert": str(self.cert_path), "key": str(self.key_path),
                "enabled": self.enabled, "eu_ranges": self.eu_ranges,
                "log_level": logging.getLogger("fbgcomp").getEffectiveLevel()}
        parent.sendall(pickle.dumps(("init", init)))
        parent.settimeout(timeout_s)
        try:
            kind, payload = pickle.loads(parent.recv(1 << 16))
        except (socket.timeout, EOFError, OSError, pickle.UnpicklingError):
            self._proc.kill()
            raise InputError(f"OPC UA server at {self.config.endpoint} did not start",
                             column="opcua.endpoint")
        if kind != "ready":
            self._proc.wait(5)
            raise InputError(f"cannot start OPC UA server at {self.config.endpoint}: {payload}",
                             column="opcua.endpoint")
        parent.settimeout(None)
        self._sock = parent
        self._reader = threading.Thread(target=self._read_messages, name="fbgcomp-opcua-rx",
                                        daemon=True)
        self._reader.start()
        warning = writer_warning(self.users, self.config.allow_anonymous)
        if warning:
            # loud: the README's serve command has no users, and nothing else would say why
            # the PLC's or the operator's switch is refused
            log.warning(warning)
            print(f"WARNING: {warning}", flush=True)

    def _send(self, message) -> bool:
        import pickle
        sock = self._sock
        if sock is None:
            return False
        try:
            sock.send(pickle.dumps(message), socket.MSG_DONTWAIT)
            return True
        except (BlockingIOError, InterruptedError):
            self.dropped += 1          # the server process lags: never wait for it
        except OSError:
            pass
        return False

    def publish(self, snapshot: Snapshot, enabled: bool | None = None, slope_um_per_m=None,
                z_ref_mm: float | None = None, cnc_limits=None) -> None:
        """Send the newest sample; with ``slope_um_per_m`` (runtime.cnc_form.newest_slope) also
        its offset + Z slope form, limited by ``cnc_limits``: a ModbusOutput that has just
        published this sample (its limited values are taken as they are, so a PLC reads the
        same numbers over OPC UA and Modbus) or a ModbusConfig (its limits, applied here)."""
        if slope_um_per_m is not None:
            offset, slope = self._cnc_form(snapshot, bool(enabled), slope_um_per_m, cnc_limits)
            snapshot = dataclasses.replace(
                snapshot, cnc_offset_um=tuple(float(v) for v in offset),
                cnc_slope_um_per_m=tuple(float(v) for v in slope),
                cnc_z_ref_mm=0.0 if z_ref_mm is None else float(z_ref_mm))
        self._send(("snap", snapshot))

    def _cnc_form(self, snapshot: Snapshot, enabled: bool, slope_um_per_m, limits):
        """Limited (offset µm, slope µm/m) per axis: the Modbus output's when it published this
        sample, else the same limiter (cnc_form.limit_toward, the Modbus output's apply rule)
        with ``limits``' rates and maxima (none: no limit)."""
        import numpy as np

        from fbgcomp.runtime.outputs.cnc_form import limit_toward
        from fbgcomp.runtime.pipeline import per_axis

        if hasattr(limits, "offset_um") and hasattr(limits, "slope_um_per_m"):
            return np.asarray(limits.offset_um, float), np.asarray(limits.slope_um_per_m, float)
        now = time.monotonic()
        state = getattr(self, "_cnc_state", None)
        dt = 0.0 if state is None else now - state[0]
        offset, slope = (np.zeros(3), np.zeros(3)) if state is None else state[1:]

        def lim(name):
            return per_axis(getattr(limits, name, float("inf")))
        apply = enabled and snapshot.health in ("OK", "DEGRADED")
        target = np.asarray(slope_um_per_m, float) if apply else np.zeros(3)
        offset = limit_toward(offset, np.asarray(snapshot.correction_um, float), dt,
                              lim("offset_rate_um_per_s"), lim("max_offset_um"))[0]
        slope = limit_toward(slope, target, dt, lim("slope_rate_um_per_m_per_s"),
                             lim("max_slope_um_per_m"))[0]
        self._cnc_state = (now, offset, slope)
        return offset, slope

    def set_enabled(self, value: bool) -> None:
        """Write ``Enabled`` from the service side (e.g. the dashboard): one shared state."""
        self.enabled = bool(value)
        send_control(self._sock, ("set_enabled", self.enabled))

    def _read_messages(self) -> None:
        import pickle
        sock = self._sock
        while True:
            try:
                data = sock.recv(1 << 16)
            except OSError:
                return
            if not data:
                return
            kind, payload = pickle.loads(data)
            if kind == "enabled":
                self.enabled = bool(payload)
            elif kind == "reload":
                request_id, path = payload
                self._reload(request_id, path)

    def _reload(self, request_id: int, path: str) -> None:
        if self.on_reload is None or self.main_loop is None:
            send_control(self._sock, ("reload_result", (request_id, False, "reload not supported")))
            return
        fut = asyncio.run_coroutine_threadsafe(self.on_reload(path), self.main_loop)

        def done(f):
            try:
                send_control(self._sock, ("reload_result", (request_id, True, f.result())))
            except Exception as exc:
                log.warning("model reload refused: %s", exc)
                send_control(self._sock, ("reload_result", (request_id, False, str(exc))))

        fut.add_done_callback(done)

    def stop(self, timeout_s: float = 5.0) -> None:
        if self._sock is not None:
            try:
                self._sock.send(__import__("pickle").dumps(("stop", None)))
            except OSError:
                pass
        if self._proc is not None:
            try:
                self._proc.wait(timeout_s)
            except Exception:
                self._proc.kill()
                self._proc.wait(5)
        if self._sock is not None:
            self._sock.close()
            self._sock = None


class _ServerCore:
    """The asyncua server itself (in the worker process)."""

    def __init__(self, sock: socket.socket, init: dict):
        self.sock = sock
        self.config = OpcUaConfig(**init["config"])
        self.sensor_names = init["sensor_names"]
        self.model_id = init["model_id"]
        self.users = init["users"]
        self.cert_path, self.key_path = init["cert"], init["key"]
        self.enabled = bool(init["enabled"])
        self.eu_ranges = init.get("eu_ranges", {})
        self.published = 0
        self._latest: Snapshot | None = None
        self._reloads: dict[int, asyncio.Future] = {}
        self._next_reload = 0

    def send(self, message) -> None:
        """Control messages to the service (Enabled written by a client, reload requests)."""
        send_control(self.sock, message, timeout_s=1.0)

    def _on_readable(self) -> None:
        import pickle
        while True:
            try:
                data = self.sock.recv(1 << 16, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                data = b""
            if not data:             # the service is gone: stop serving
                self._stop.set()
                break
            kind, payload = pickle.loads(data)
            if kind == "snap":
                self._latest = payload
                self._wake.set()
            elif kind == "model_id":
                self.model_id = payload
            elif kind == "set_enabled":
                asyncio.ensure_future(self._set_enabled(bool(payload)))
            elif kind == "reload_result":
                request_id, ok, message = payload
                fut = self._reloads.pop(request_id, None)
                if fut is not None and not fut.done():
                    fut.set_result((ok, message))
            elif kind == "stop":
                self._stop.set()

    async def main(self) -> None:
        from asyncua import Server, ua

        loop = asyncio.get_running_loop()
        self._wake, self._stop = asyncio.Event(), asyncio.Event()
        cfg = self.config
        server = Server(user_manager=make_user_manager(self.users, cfg.allow_anonymous))
        await server.init()
        server.set_endpoint(cfg.endpoint)
        server.set_server_name("fbgcomp runtime")
        await server.set_application_uri(APPLICATION_URI)
        await server.load_certificate(str(self.cert_path))
        await server.load_private_key(str(self.key_path))
        server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt],
                                   permission_ruleset=make_ruleset())
        tokens = [ua.UserNameIdentityToken]
        if cfg.allow_anonymous:
            tokens.append(ua.AnonymousIdentityToken)
        server.set_identity_tokens(tokens)
        # unknown client certificates are refused, always (an empty trust list trusts nobody)
        server.set_certificate_validator(trust.TrustListValidator(
            trust.trusted_dir(cfg.state_dir, cfg.trusted_clients_dir),
            trust.rejected_dir(cfg.state_dir)))
        from asyncua.common.callback import CallbackType
        server.subscribe_server_callback(CallbackType.PostWrite, self._audit_write)
        idx = await server.register_namespace(NAMESPACE)
        self._nodes = await self._build(server, idx)
        self._server = server
        async with server:
            logging.getLogger("asyncua").setLevel(logging.WARNING)
            # the standard address space is tens of thousands of long-lived objects: keep them
            # out of the cyclic collector, whose full passes would stall updates for ~10 ms
            import gc
            gc.collect()
            gc.freeze()
            self.send(("ready", cfg.endpoint))
            loop.add_reader(self.sock.fileno(), self._on_readable)
            try:
                await self._publish_loop()
            finally:
                loop.remove_reader(self.sock.fileno())

    async def _build(self, server, idx) -> dict:
        from asyncua import ua

        from fbgcomp.runtime.health import FLAG_NAMES, STATUS_NAMES

        def nid(name):
            return ua.NodeId(f"FbgComp.{name}", idx)

        def text(key, **fields):
            return ua.LocalizedText(DESCRIPTIONS[key].format(**fields))

        # our own ObjectType, so a client can recognise the compensator; it stands for
        # OPC 40501-1's ElementMonitoringType (docs/opcua-cnc.md)
        ctype = await server.nodes.base_object_type.add_object_type(
            ua.NodeId("ThermalCompensationType", idx),
            ua.QualifiedName("ThermalCompensationType", idx))
        await ctype.write_attribute(ua.AttributeIds.Description,
                                    ua.DataValue(ua.Variant(text("ThermalCompensationType"))))
        root = await server.nodes.objects.add_object(ua.NodeId("FbgComp", idx),
                                                     ua.QualifiedName("FbgComp", idx),
                                                     objecttype=ctype.nodeid)
        await root.write_attribute(ua.AttributeIds.Description,
                                   ua.DataValue(ua.Variant(text("FbgComp"))))
        await self._add_variable(root, nid("Name"), ua.QualifiedName("Name", idx),
                                 ua.Variant("fbgcomp thermal compensation", ua.VariantType.String),
                                 text("Name"), prop=True)
        nodes = {}

        async def var(parent, path, name, value, vtype, description, unit=None, eu_range=None):
            node = await self._add_variable(parent, nid(path), ua.QualifiedName(name, idx),
                                            ua.Variant(value, vtype), description, unit=unit,
                                            eu_range=eu_range)
            nodes[path] = node
            return node

        D, S, B, T = (ua.VariantType.Double, ua.VariantType.String, ua.VariantType.Boolean,
                      ua.VariantType.DateTime)
        for prefix in ("Correction", "PredictedDeviation", "IntervalHalfWidth",
                       "ExpectedError"):
            for a in AXES:
                await var(root, f"{prefix}{a}_um", f"{prefix}{a}_um", 0.0, D,
                          text(prefix, a=a), "um", self._eu_range(prefix))
        # the offset + Z slope form a CNC's thermal compensation takes (docs/cnc-integration.md)
        for a in AXES:
            await var(root, f"Offset{a}_um", f"Offset{a}_um", 0.0, D, text("Offset", a=a), "um",
                      self._eu_range("Offset"))
            await var(root, f"Slope{a}_um_per_m", f"Slope{a}_um_per_m", 0.0, D,
                      text("Slope", a=a), "um_per_m", self._eu_range("Slope"))
        await var(root, "ZRef_mm", "ZRef_mm", 0.0, D, text("ZRef_mm"), "mm",
                  self._eu_range("ZRef_mm"))
        await var(root, "SampleTime", "SampleTime", dt.datetime.now(dt.timezone.utc), T,
                  text("SampleTime"))
        await var(root, "Latency_ms", "Latency_ms", 0.0, D, text("Latency_ms"), "ms",
                  self._eu_range("Latency_ms"))
        await var(root, "ModelId", "ModelId", self.model_id, S, text("ModelId"))
        await var(root, "Health", "Health", "STARTING", S, text("Health"))
        await var(root, "Alarm", "Alarm", False, B, text("Alarm"))
        await var(root, "FallbackInUse", "FallbackInUse", "", S, text("FallbackInUse"))
        flags = ", ".join(f"{bit} {name}" for bit, name in FLAG_NAMES.items())
        for a in AXES:
            await var(root, f"OutputFlags{a}", f"OutputFlags{a}", 0, ua.VariantType.Byte,
                      text("OutputFlags", a=a, flags=flags))
        await var(root, "Limited", "Limited", False, B, text("Limited"))
        await var(root, "OutputFlags", "OutputFlags", "", S, text("OutputFlagsText"))
        await var(root, "SourceStatus", "SourceStatus", "", S, text("SourceStatus"))
        await var(root, "FramesProcessed", "FramesProcessed", 0, ua.VariantType.UInt64,
                  text("FramesProcessed"))
        await var(root, "Heartbeat", "Heartbeat", 0, ua.VariantType.UInt32, text("Heartbeat"))
        enabled = await var(root, "Enabled", "Enabled", bool(self.enabled), B, text("Enabled"))
        await enabled.set_writable(True)
        sensors = await root.add_folder(nid("Sensors"), ua.QualifiedName("Sensors", idx))
        await sensors.write_attribute(ua.AttributeIds.Description,
                                      ua.DataValue(ua.Variant(text("Sensors"))))
        statuses = ", ".join(STATUS_NAMES)
        for s in self.sensor_names:
            obj = await sensors.add_object(nid(f"Sensors.{s}"), ua.QualifiedName(s, idx))
            await obj.write_attribute(ua.AttributeIds.Description,
                                      ua.DataValue(ua.Variant(text("Sensor", s=s))))
            await var(obj, f"Sensors.{s}.Status", "Status", "UNKNOWN", S,
                      text("Sensors.Status", statuses=statuses))
            await var(obj, f"Sensors.{s}.Wavelength_nm", "Wavelength_nm", float("nan"), D,
                      text("Sensors.Wavelength_nm"), "nm", self._eu_range("Wavelength_nm", s))
        inputs, outputs = reload_model_arguments()
        method = await root.add_method(nid("ReloadModel"), ua.QualifiedName("ReloadModel", idx),
                                       self._reload, inputs, outputs)
        await method.write_attribute(ua.AttributeIds.Description,
                                     ua.DataValue(ua.Variant(text("ReloadModel"))))
        self._last_text: dict[str, object] = {}
        return nodes

    def _eu_range(self, kind: str, sensor: str | None = None) -> tuple[float, float]:
        """EURange of a kind of analog variable: ``eu_ranges`` given to the server (by kind,
        or ``Wavelength_nm.<sensor>`` for one sensor), else :data:`DEFAULT_EU_RANGES`."""
        ranges = self.eu_ranges
        if sensor is not None and f"{kind}.{sensor}" in ranges:
            return tuple(ranges[f"{kind}.{sensor}"])
        return tuple(ranges.get(kind, DEFAULT_EU_RANGES[kind]))

    @staticmethod
    async def _add_variable(parent, nodeid, qname, variant, description, unit=None,
                            eu_range=None, prop=False):
        """A read-only scalar variable with its Description; with ``unit`` (a key of
        :data:`UNITS`) an ``AnalogItemType`` with ``EngineeringUnits`` and ``EURange``.

        asyncua's ``add_variable`` always types a variable ``BaseDataVariableType``, so the
        node is added with the same AddNodes service call it makes, naming the type.
        """
        from asyncua import ua
        from asyncua.common.node_factory import make_node

        item = ua.AddNodesItem()
        item.RequestedNewNodeId = nodeid
        item.BrowseName = qname
        item.NodeClass = ua.NodeClass.Variable
        item.ParentNodeId = parent.nodeid
        if prop:
            item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasProperty)
            item.TypeDefinition = ua.NodeId(ua.ObjectIds.PropertyType)
        else:
            item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasComponent)
            item.TypeDefinition = ua.NodeId(ua.ObjectIds.AnalogItemType if unit
                                            else ua.ObjectIds.BaseDataVariableType)
        attrs = ua.VariableAttributes()
        attrs.DisplayName = ua.LocalizedText(qname.Name)
        attrs.Description = description
        attrs.DataType = ua.NodeId(getattr(ua.ObjectIds, variant.VariantType.name))
        attrs.Value = variant
        attrs.ValueRank = ua.ValueRank.Scalar
        attrs.ArrayDimensions = None
        attrs.WriteMask = attrs.UserWriteMask = 0
        attrs.Historizing = False
        attrs.AccessLevel = attrs.UserAccessLevel = ua.AccessLevel.CurrentRead.mask
        item.NodeAttributes = attrs
        result = (await parent.session.add_nodes([item]))[0]
        result.StatusCode.check()
        node = make_node(parent.session, result.AddedNodeId)
        if unit:
            base = nodeid.Identifier
            await node.add_property(ua.NodeId(f"{base}.EngineeringUnits", nodeid.NamespaceIndex),
                                    ua.QualifiedName("EngineeringUnits", 0), eu_information(unit),
                                    datatype=ua.ObjectIds.EUInformation)
            low, high = eu_range
            await node.add_property(ua.NodeId(f"{base}.EURange", nodeid.NamespaceIndex),
                                    ua.QualifiedName("EURange", 0),
                                    ua.Range(Low=float(low), High=float(high)),
                                    datatype=ua.ObjectIds.Range)
        return node

    def _audit_write(self, event, _dispatcher) -> None:
        """PostWrite: every client write, with its user, value and result."""
        if not event.is_external:
            return
        results = event.response_params or []
        for i, item in enumerate(event.request_params.NodesToWrite):
            status = results[i].name if i < len(results) else "?"
            value = item.Value.Value.Value if item.Value and item.Value.Value else None
            audit.info("OPC UA write %s = %r by %s: %s", item.NodeId.to_string(), value,
                       user_label(event.user), status)

    async def _reload(self, parent, path_variant):
        """ReloadModel: ask the service to load a model file of the models folder."""
        from asyncua import ua
        name = path_variant.Value if hasattr(path_variant, "Value") else str(path_variant)
        user = _request_user.get()
        try:
            path = model_in_folder(str(name), self.config.models_dir)
        except ModelPathRefused as exc:
            audit.warning("OPC UA call ReloadModel(%r) by %s refused: %s", name, user, exc)
            return ua.StatusCode(getattr(ua.StatusCodes, exc.status))
        self._next_reload += 1
        fut = asyncio.get_running_loop().create_future()
        self._reloads[self._next_reload] = fut
        self.send(("reload", (self._next_reload, path)))
        try:
            ok, message = await asyncio.wait_for(fut, 30.0)
        except asyncio.TimeoutError:
            audit.warning("OPC UA call ReloadModel(%r) by %s: no answer", name, user)
            return ua.StatusCode(ua.StatusCodes.BadTimeout)
        audit.log(logging.INFO if ok else logging.WARNING,
                  "OPC UA call ReloadModel(%r) by %s: %s", name, user,
                  message if ok else f"failed: {message}")
        if not ok:
            return ua.StatusCode(ua.StatusCodes.BadInvalidArgument)
        return [ua.Variant(message, ua.VariantType.String)]

    async def _publish_loop(self) -> None:
        period = 1.0 / self.config.rate_hz if self.config.rate_hz > 0 else 0.0
        last = 0.0
        stop_task = asyncio.ensure_future(self._stop.wait())
        try:
            while not self._stop.is_set():
                if not self._wake.is_set():
                    wake_task = asyncio.ensure_future(self._wake.wait())
                    await asyncio.wait({wake_task, stop_task}, timeout=0.2,
                                       return_when=asyncio.FIRST_COMPLETED)
                    wake_task.cancel()
                self._wake.clear()
                await self._read_enabled()
                await self._heartbeat()
                wait = last + period - time.monotonic()
                if wait > 0:
                    await asyncio.sleep(wait)  # rate limit: the newest snapshot wins
                snap, self._latest = self._latest, None
                if snap is not None:
                    last = time.monotonic()
                    await self._write(snap)
        finally:
            stop_task.cancel()

    async def _heartbeat(self) -> None:
        """Counter bumped at least every 0.2 s, data or not: a watchdog for the CNC side."""
        from asyncua import ua
        now = time.monotonic()
        if now - getattr(self, "_beat_at", 0.0) < 0.2:
            return
        self._beat_at = now
        self._beats = (getattr(self, "_beats", 0) + 1) % (1 << 32)
        await self._server.write_attribute_value(
            self._nodes["Heartbeat"].nodeid,
            ua.DataValue(ua.Variant(self._beats, ua.VariantType.UInt32)))

    async def _set_enabled(self, value: bool) -> None:
        from asyncua import ua
        self.enabled = value
        await self._server.write_attribute_value(
            self._nodes["Enabled"].nodeid, ua.DataValue(ua.Variant(value, ua.VariantType.Boolean)))

    async def _read_enabled(self) -> None:
        from asyncua import ua
        # straight from the address space: no request round trip on every update
        dv = self._server.iserver.aspace.read_attribute_value(self._nodes["Enabled"].nodeid,
                                                              ua.AttributeIds.Value)
        if dv.Value is not None and bool(dv.Value.Value) != self.enabled:
            self.enabled = bool(dv.Value.Value)
            self.send(("enabled", self.enabled))

    async def _write(self, s: Snapshot) -> None:
        from asyncua import ua
        server = self._server
        now = dt.datetime.now(dt.timezone.utc)
        src = dt.datetime.fromtimestamp(s.sample_time_s, dt.timezone.utc)

        async def put(path, value, vtype, always=True):
            if not always and self._last_text.get(path) == value:
                return
            self._last_text[path] = value
            await server.write_attribute_value(
                self._nodes[path].nodeid,
                ua.DataValue(ua.Variant(value, vtype), SourceTimestamp=src, ServerTimestamp=now))

        D = ua.VariantType.Double
        for prefix, values in (("Correction", s.correction_um),
                               ("PredictedDeviation", s.deviation_um),
                               ("IntervalHalfWidth", s.half_width_um),
                               ("ExpectedError", s.expected_rms_um)):
            for a, v in zip(AXES, values):
                await put(f"{prefix}{a}_um", float(v), D, always=prefix == "Correction")
        if s.cnc_offset_um is not None:
            for a, o, k in zip(AXES, s.cnc_offset_um, s.cnc_slope_um_per_m):
                await put(f"Offset{a}_um", float(o), D)
                await put(f"Slope{a}_um_per_m", float(k), D)
            await put("ZRef_mm", float(s.cnc_z_ref_mm), D, False)
        S = ua.VariantType.String
        await put("Health", s.health, S, False)
        await put("Alarm", bool(s.alarm), ua.VariantType.Boolean, False)
        await put("FallbackInUse", s.fallback, S, False)
        from fbgcomp.runtime.health import describe_flags
        flags = tuple(int(v) for v in s.output_flags)
        for a, v in zip(AXES, flags):
            await put(f"OutputFlags{a}", v, ua.VariantType.Byte, False)
        await put("Limited", any(flags), ua.VariantType.Boolean, False)
        await put("OutputFlags", describe_flags(flags), S, False)
        await put("SourceStatus", s.source_status, S, False)
        await put("ModelId", self.model_id, S, False)
        for name, st in zip(self.sensor_names, s.sensor_status):
            await put(f"Sensors.{name}.Status", st, S, False)
        mono = time.monotonic()
        if mono - getattr(self, "_diag_at", 0.0) >= 0.1:
            # diagnostics at <= 10 Hz: they must not slow down the correction updates
            self._diag_at = mono
            await put("FramesProcessed", int(s.frames), ua.VariantType.UInt64)
            for name, wl in zip(self.sensor_names, s.sensor_wavelength_nm):
                await put(f"Sensors.{name}.Wavelength_nm", float(wl), D)
            await put("Latency_ms", (time.time() - s.sample_time_s) * 1e3, D)
        # SampleTime last: a client watching it sees a complete, consistent sample
        await put("SampleTime", src, ua.VariantType.DateTime)
        self.published += 1


def _setup_logging(init: dict) -> None:
    """The server process logs to stderr at serve's level, and its audit records (always) to
    ``<state_dir>/opcua/audit.log``, rotated at :data:`AUDIT_LOG_BYTES`."""
    from logging.handlers import RotatingFileHandler

    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    stderr = logging.StreamHandler()
    stderr.setFormatter(fmt)
    stderr.setLevel(int(init.get("log_level", logging.WARNING)))
    root = logging.getLogger()
    root.handlers[:] = [stderr]
    root.setLevel(stderr.level)
    audit.setLevel(logging.INFO)
    folder = Path(init["config"]["state_dir"]) / "opcua"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        handler = RotatingFileHandler(folder / "audit.log", maxBytes=AUDIT_LOG_BYTES,
                                      backupCount=5, encoding="utf-8")
    except OSError as exc:
        log.error("no OPC UA audit file in %s (%s): audit records go to stderr only", folder,
                  exc.strerror)
        return
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    audit.addHandler(handler)


def _worker(fd: int) -> None:
    """Entry point of the server process: ``python -m fbgcomp.runtime.outputs.opcua --worker-fd N``."""
    import pickle
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # the service decides when to stop
    sock = socket.socket(fileno=fd)
    kind, init = pickle.loads(sock.recv(1 << 16))
    _setup_logging(init)
    # start-up failures (busy port...) reach the user as serve's one-line error, not as
    # asyncua tracebacks
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    core = _ServerCore(sock, init)
    try:
        asyncio.run(core.main())
    except Exception as exc:
        core.send(("error", f"{type(exc).__name__}: {exc}"))
        raise SystemExit(1)


if __name__ == "__main__":
    import sys
    logging.basicConfig(level=logging.WARNING)
    if len(sys.argv) == 3 and sys.argv[1] == "--worker-fd":
        _worker(int(sys.argv[2]))
    else:
        raise SystemExit("usage: python -m fbgcomp.runtime.outputs.opcua --worker-fd FD (started by serve)")
