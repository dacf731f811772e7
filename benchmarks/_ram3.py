"""The project's own independent rams (tests/data/README.md), as the benchmarks read them: an
archive unpacked into a folder of the caller's, and the description from its data sheet.

ram3 (both rails on -X, five gratings), ram4 (rails on two adjacent faces, seven gratings and
two strain-free reference gratings, two heat sources in a cast-iron housing) and ram5 (rails on
two opposite faces, the -Y one floating along its normal, five gratings, five probes) and ram6
(rails on two adjacent faces, the +Y one floating along its normal, a CFRP that shortens when
warmed, six gratings, a heat source at the top of the box) and ram7 (a long box on two opposite
faces, both rails locating at three carriage stations, an aluminium housing, five gratings) and
ram8 (a box whose +X wall, which carries both rails, is thicker than the others: a wall per face
in its description; six gratings, a radiant load on the thin -X wall)."""

from __future__ import annotations

import tarfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RAM3_ARCHIVE = REPO / "tests" / "data" / "ram3.tar.xz"
RAM3_MACHINE = REPO / "examples" / "machines" / "ram3.yaml"
RAM4_ARCHIVE = REPO / "tests" / "data" / "ram4.tar.xz"
RAM4_MACHINE = REPO / "examples" / "machines" / "ram4.yaml"
RAM5_ARCHIVE = REPO / "tests" / "data" / "ram5.tar.xz"
RAM5_MACHINE = REPO / "examples" / "machines" / "ram5.yaml"
RAM6_ARCHIVE = REPO / "tests" / "data" / "ram6.tar.xz"
RAM6_MACHINE = REPO / "examples" / "machines" / "ram6.yaml"
RAM7_ARCHIVE = REPO / "tests" / "data" / "ram7.tar.xz"
RAM7_MACHINE = REPO / "examples" / "machines" / "ram7.yaml"
RAM8_ARCHIVE = REPO / "tests" / "data" / "ram8.tar.xz"
RAM8_MACHINE = REPO / "examples" / "machines" / "ram8.yaml"


def unpack(archive: Path, dest: Path) -> Path:
    """An archived ram's folder (README.md, results.json, data/, truth/) unpacked into ``dest``."""
    with tarfile.open(archive) as tar:
        tar.extractall(dest, filter="data")
    return Path(dest)


def unpack_ram3(dest: Path) -> Path:
    """ram3's folder unpacked into ``dest``."""
    return unpack(RAM3_ARCHIVE, dest)


#: each independent ram's held-out campaigns (thermal_b, thermal_c, the static one in static_x's role)
HELD_OUT = {
    "ram2": ("thermal_b", "thermal_c", "static_x"),
    "ram3": ("thermal_b", "thermal_c", "static_y"),
    "ram4": ("thermal_b", "thermal_c", "static_y"),
    "ram5": ("thermal_b", "thermal_c", "static_x"),
    "ram6": ("thermal_b", "thermal_c", "static_x"),
    "ram7": ("thermal_b", "thermal_c", "static_x"),
    "ram8": ("thermal_b", "thermal_c", "static_x"),
}
#: the project's own rams: archive and description
OWN_RAMS = {
    "ram3": (RAM3_ARCHIVE, RAM3_MACHINE),
    "ram4": (RAM4_ARCHIVE, RAM4_MACHINE),
    "ram5": (RAM5_ARCHIVE, RAM5_MACHINE),
    "ram6": (RAM6_ARCHIVE, RAM6_MACHINE),
    "ram7": (RAM7_ARCHIVE, RAM7_MACHINE),
    "ram8": (RAM8_ARCHIVE, RAM8_MACHINE),
}


def add_ram_arguments(ap, default: str) -> None:
    """The ``--ram2 PATH`` and ``--rams a,b`` options of the benchmarks that judge several rams."""
    ap.add_argument(
        "--ram2", help="the ram2 data set (default: $FBGCOMP_RAM2, else ../shared/reference/ram2)"
    )
    ap.add_argument(
        "--rams", default=default, help="comma-separated subset of ram2,ram3,ram4,ram5,ram6,ram7,ram8"
    )


def ram_folder(ram: str, dest: Path, ram2=None):
    """(``data`` folder, description) of ``ram``: ram2 where ``--ram2``/$FBGCOMP_RAM2 or the
    shared reference puts it, the project's own rams unpacked into ``dest``/ram. ValueError with
    the one line to print where the ram is unknown or ram2 is not found."""
    if ram == "ram2":
        from fbgcomp.cli.demo import RAM2_MACHINE, find_ram2

        data, looked = find_ram2(ram2)
        if data is None:
            raise ValueError(f"ram2 not found at {looked}")
        return data, RAM2_MACHINE
    if ram not in OWN_RAMS:
        raise ValueError(f"--rams: unknown ram {ram!r} (ram2, ram3, ram4, ram5, ram6, ram7, ram8)")
    archive, machine = OWN_RAMS[ram]
    return unpack(archive, Path(dest) / ram) / "data", machine


def default_fit(data: Path, machine):
    """The default fit of a ram: the physical model with its description ``machine``, fitted on
    the campaigns thermal_a and static_xyz of its ``data`` folder."""
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.physical import PhysicalModel

    return PhysicalModel(machine=machine).fit([read_campaign(data / n) for n in ("thermal_a", "static_xyz")])
