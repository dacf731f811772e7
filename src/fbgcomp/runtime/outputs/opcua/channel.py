"""What the service and the OPC UA server process share: configuration, snapshot, messages.

The two processes talk over a Unix ``SOCK_SEQPACKET`` socket pair, one pickled
``(kind, payload)`` tuple per packet (at most :data:`MESSAGE_BYTES`):

* service -> server: ``init`` (first, the server's configuration), ``snap`` (a
  :class:`Snapshot`; dropped when the server lags), ``model_id``, ``set_enabled``,
  ``reload_result`` and ``stop``;
* server -> service: ``ready`` or ``error`` (after ``init``), ``enabled`` (written by a
  client) and ``reload`` (a ``ReloadModel`` call).

Snapshots may be dropped, control messages may not: they go through :func:`send_control`.
"""

from __future__ import annotations

import logging
import pickle
import select
import socket
import time
from dataclasses import dataclass, field

from fbgcomp.runtime import trust

log = logging.getLogger("fbgcomp.runtime")
MESSAGE_BYTES = 1 << 16  # the largest message either side reads


@dataclass
class OpcUaConfig:
    """The ``[opcua]`` section of serve's configuration (docs/runtime.md)."""

    endpoint: str = "opc.tcp://127.0.0.1:4840/fbgcomp/"
    rate_hz: float = 100.0  # address-space updates per second; 0 = every batch
    allow_anonymous: bool = False
    users_file: str | None = None
    # certificates: $XDG_STATE_HOME/fbgcomp (~/.local/state/fbgcomp), never the working folder
    state_dir: str = field(default_factory=lambda: str(trust.default_state_dir()))
    # the client certificates trusted; unset or "": <state_dir>/opcua/trusted (fbgcomp trust add)
    trusted_clients_dir: str | None = None
    models_dir: str | None = None  # ReloadModel loads only files in this folder


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
    output_flags: tuple = (0, 0, 0)  # health.FLAG_* per axis: model policy | limits
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
                log.error("control message %r not delivered: the other process is not reading", message[0])
                return False
            select.select([], [sock], [], remaining)
        except OSError:
            return False
