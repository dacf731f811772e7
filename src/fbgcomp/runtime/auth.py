"""Password users: the users file and the PBKDF2 hashes every password-protected surface checks.

One store for the OPC UA server (writes and method calls) and the dashboard (its control
switch): a users file of lines ``name:pbkdf2_sha256$<iterations>$<salt b64>$<hash b64>``
(made with :func:`hash_password`, docs/security.md), plus one user from the environment
(``<PREFIX>_USER`` / ``<PREFIX>_PASSWORD``, hashed in memory only). Client certificates, the
other half of who may connect to the OPC UA server, are :mod:`fbgcomp.runtime.trust`'s.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
from pathlib import Path

from fbgcomp.errors import InputError

PBKDF2_ITERATIONS = 100_000


def hash_password(password: str, salt: bytes | None = None, iterations: int = PBKDF2_ITERATIONS) -> str:
    """``pbkdf2_sha256$<iterations>$<salt b64>$<hash b64>`` for the users file."""
    salt = salt or os.urandom(16)
    digest = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
    return f"pbkdf2_sha256${iterations}${base64.b64encode(salt).decode()}${base64.b64encode(digest).decode()}"


def verify_password(password: str, stored: str) -> bool:
    """Whether ``password`` matches ``stored`` (a :func:`hash_password` string), in constant
    time; False for a malformed or foreign hash."""
    try:
        algo, iters, salt, digest = stored.split("$")
        if algo != "pbkdf2_sha256":
            return False
        got = hashlib.pbkdf2_hmac("sha256", password.encode(), base64.b64decode(salt), int(iters))
        return hmac.compare_digest(got, base64.b64decode(digest))
    except (ValueError, TypeError):
        return False


def load_users(
    users_file: str | Path | None,
    environ=os.environ,
    *,
    service="OPC UA",
    env_prefix="FBGCOMP_OPCUA",
    doc="docs/runtime.md",
    iterations=1000,
) -> dict[str, str]:
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
                raise InputError(
                    f"expected name:pbkdf2_sha256$... (see {doc})", file=path, column=f"line {i}"
                )
            users[name.strip()] = stored.strip()
    user, pwd = environ.get(f"{env_prefix}_USER"), environ.get(f"{env_prefix}_PASSWORD")
    if user and pwd:
        users[user] = hash_password(pwd, iterations=iterations)
    return users
