"""ram3, the project's second independent ram (tests/data/README.md), as the benchmarks read it:
the archive unpacked into a folder of the caller's, and its description from its data sheet."""

from __future__ import annotations

import tarfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RAM3_ARCHIVE = REPO / "tests" / "data" / "ram3.tar.xz"
RAM3_MACHINE = REPO / "examples" / "machines" / "ram3.yaml"


def unpack_ram3(dest: Path) -> Path:
    """ram3's folder (README.md, results.json, data/, truth/) unpacked into ``dest``."""
    with tarfile.open(RAM3_ARCHIVE) as tar:
        tar.extractall(dest, filter="data")
    return Path(dest)
