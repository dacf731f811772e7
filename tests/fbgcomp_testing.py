"""Shared test helpers (imported by the tests; pytest puts this folder on sys.path)."""

from __future__ import annotations

import importlib
import os
import shutil

import pytest


def require_all() -> bool:
    """True in CI: every optional component must be present, no silent skips."""
    return os.environ.get("FBGCOMP_REQUIRE_ALL", "") not in ("", "0")


def require(module: str):
    """Import an optional module, skipping the test locally when it is missing (failing in CI)."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        if require_all():
            pytest.fail(f"optional component {module!r} is required in CI: {exc}")
        pytest.skip(f"{module} not installed")


def require_program(name: str) -> str:
    """Path of an external program, skipping locally when missing (failing in CI)."""
    path = shutil.which(name)
    if path is None:
        if require_all():
            pytest.fail(f"program {name!r} is required in CI but not on PATH")
        pytest.skip(f"{name} not on PATH")
    return path
