"""Who may do what in an OPC UA session: password users write and call, anonymous only reads.

The asyncua user manager and permission ruleset of the server process (imported only there, by
:mod:`.worker`). Users come from :func:`fbgcomp.runtime.auth.load_users`; a refused write or
method call is logged with its user on the ``fbgcomp.audit`` logger.
"""

from __future__ import annotations

import contextvars
import hashlib
import logging

from asyncua import ua
from asyncua.crypto.permission_rules import SimpleRoleRuleset, User, UserRole
from asyncua.server.user_managers import UserManager

from fbgcomp.runtime.auth import verify_password

audit = logging.getLogger("fbgcomp.audit")

# The user of the request being served. asyncua hands the user to the permission ruleset but
# not to method callbacks; a connection's requests are served one at a time in one task, so
# the ruleset records it here and ReloadModel reads it back for the audit log.
request_user: contextvars.ContextVar[str] = contextvars.ContextVar("opcua_user", default="unknown")

_WRITE = ua.NodeId(ua.Int32(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary))
_CALL = ua.NodeId(ua.Int32(ua.ObjectIds.CallRequest_Encoding_DefaultBinary))


def user_label(user) -> str:
    """How a session's user appears in the audit log: the user name, or ``anonymous``."""
    name = getattr(user, "name", None)
    return name if name else "anonymous"


class FbgUserManager(UserManager):
    """Password users get the User role (read, write, call); anonymous only reads.

    ``users``: user -> password hash (:func:`fbgcomp.runtime.auth.load_users`). A checked
    password is remembered (by its SHA-256), so reconnecting clients do not pay PBKDF2 again.
    """

    def __init__(self, users: dict[str, str], allow_anonymous: bool):
        self.users = users
        self.allow_anonymous = allow_anonymous
        self._ok_cache: dict[tuple[str, bytes], bool] = {}

    def get_user(self, iserver, username=None, password=None, certificate=None):
        """The session's ``User`` (asyncua's user manager interface), or None to refuse it."""
        if username is None:
            return User(role=UserRole.Anonymous) if self.allow_anonymous else None
        stored = self.users.get(username)
        if stored is None or password is None:
            return None
        key = (username, hashlib.sha256(password.encode()).digest())
        if key not in self._ok_cache:
            self._ok_cache[key] = verify_password(password, stored)
        return User(role=UserRole.User, name=username) if self._ok_cache[key] else None


def make_user_manager(users: dict[str, str], allow_anonymous: bool) -> FbgUserManager:
    """The server's user manager (``Server(user_manager=...)``) over ``users``."""
    return FbgUserManager(users, allow_anonymous)


class ReadOnlyAnonymousRuleset(SimpleRoleRuleset):
    """Anonymous sessions may browse, read and subscribe, never write or call."""

    def __init__(self):
        super().__init__()
        denied = {_WRITE, _CALL, ua.NodeId(ua.ObjectIds.HistoryReadRequest_Encoding_DefaultBinary)}
        self._permission_dict[UserRole.Anonymous] = self._permission_dict[UserRole.User] - denied

    def check_validity(self, user, action_type_id, body):
        """Whether ``user`` may make this request; records the user for :data:`request_user`
        and audits a refused write or call."""
        request_user.set(user_label(user))
        allowed = super().check_validity(user, action_type_id, body)
        if not allowed and action_type_id in (_WRITE, _CALL):
            audit.warning(
                "OPC UA %s by %s refused: access denied",
                "write" if action_type_id == _WRITE else "method call",
                user_label(user),
            )
        return allowed


def make_ruleset() -> ReadOnlyAnonymousRuleset:
    """The server's permission ruleset (``set_security_policy(permission_ruleset=...)``)."""
    return ReadOnlyAnonymousRuleset()
