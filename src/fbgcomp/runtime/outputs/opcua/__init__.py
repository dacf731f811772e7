"""OPC UA server facing the CNC / PLC (asyncua), in its own process.

Modules: :mod:`.address_space` (namespace, node names, descriptions, units: plain data),
:mod:`.nodes` (building them in asyncua), :mod:`.security` (the server certificate, who may
write, which model files may be loaded), :mod:`.access` (session users and permissions),
:mod:`.channel` (configuration, snapshot and messages the two processes share), :mod:`.bridge`
(the service's handle, :class:`OpcUaServer`) and :mod:`.worker` (the server process). Only
:mod:`.nodes`, :mod:`.access` and :mod:`.worker` import asyncua, and only the server process
imports them. Users and passwords are :mod:`fbgcomp.runtime.auth`'s.

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

# the users store moved to fbgcomp.runtime.auth; re-exported for the documented
# ``from fbgcomp.runtime.outputs.opcua import hash_password``
from fbgcomp.runtime.auth import PBKDF2_ITERATIONS, hash_password, load_users, verify_password
from fbgcomp.runtime.outputs.opcua.address_space import (
    APPLICATION_URI,
    AXES,
    DEFAULT_EU_RANGES,
    DESCRIPTIONS,
    NAMESPACE,
    UNECE_NAMESPACE_URI,
    UNITS,
    unece_unit_id,
)
from fbgcomp.runtime.outputs.opcua.bridge import OpcUaServer
from fbgcomp.runtime.outputs.opcua.channel import OpcUaConfig, Snapshot, send_control
from fbgcomp.runtime.outputs.opcua.security import (
    ModelPathRefused,
    ensure_certificate,
    model_in_folder,
    writer_warning,
)

__all__ = [
    "APPLICATION_URI",
    "AXES",
    "DEFAULT_EU_RANGES",
    "DESCRIPTIONS",
    "NAMESPACE",
    "PBKDF2_ITERATIONS",
    "UNECE_NAMESPACE_URI",
    "UNITS",
    "ModelPathRefused",
    "OpcUaConfig",
    "OpcUaServer",
    "Snapshot",
    "ensure_certificate",
    "hash_password",
    "load_users",
    "model_in_folder",
    "send_control",
    "unece_unit_id",
    "verify_password",
    "writer_warning",
]
