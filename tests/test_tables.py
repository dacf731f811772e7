"""Console tables (issue 15, item 2): aligned columns, units in the headers, rounding-level
numbers as 0, no negative zero, missing values as a dash - the shared formatter and the tables
``fbgcomp validate`` and ``compare`` print with it."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from fbgcomp.tables import MISSING, Column, format_number, format_table, text
from fbgcomp_testing import cli


@pytest.mark.parametrize(
    "value, decimals, expected",
    [
        (25.7104, 2, "25.71"),
        (2.07e-145, 3, "0"),
        (1.169e-31, 3, "0"),
        (-1.169e-31, 3, "0"),
        (-0.0, 3, "0"),
        (-0.0004, 3, "0"),
        (0.0004999, 3, "0"),
        (-0.0005, 3, "-0.001"),
        (0.0006, 3, "0.001"),
        (-0.004, 2, "0"),
        (-0.006, 2, "-0.01"),
        (844.874, 3, "844.874"),
        (-1.5, 0, "-2"),
        (0.4, 0, "0"),
        (float("nan"), 3, MISSING),
        (None, 3, MISSING),
        (np.float64("nan"), 2, MISSING),
        (float("inf"), 3, "inf"),
        (-math.inf, 3, "-inf"),
        (7, 3, "7"),
        (np.float32(0.1), 1, "0.1"),
    ],
)
def test_format_number(value, decimals, expected):
    assert format_number(value, decimals) == expected


def test_no_rounding_level_number_keeps_a_sign_or_an_exponent():
    rng = np.random.default_rng(0)
    for x in np.concatenate(
        [rng.normal(scale=1e-3, size=2000), 10.0 ** -rng.uniform(3, 300, 500) * rng.choice([-1, 1], 500)]
    ):
        s = format_number(x, 3)
        assert "e" not in s and s not in ("-0", "-0.000", "0.000")
        # the figure is unchanged: the text is the number rounded to 3 decimals
        assert float(s) == pytest.approx(round(float(x), 3), abs=1e-12)


def test_table_columns_align_headers_carry_units():
    cols = [
        text("axis"),
        Column("max|err|", "µm"),
        Column("load", "N", 1),
        Column("ΔT", "K", 2),
        Column("share", "%", 2),
    ]
    rows = [
        ["dx", 25.712, 1500.0, -0.001, 2.07e-145],
        ["dy", -1.169e-31, 12.25, float("nan"), 99.999, "WORSE than uncompensated"],
        ["dz", 1234567.891, None, 3.0, -0.004],
    ]
    out = format_table(cols, rows, indent="  ").splitlines()
    assert out[0].split() == ["axis", "max|err|", "(µm)", "load", "(N)", "ΔT", "(K)", "share", "(%)"]
    body = [line[: len(out[0])] for line in out]
    # every column ends at the same place in every line (right-aligned numbers)
    ends = [m.end() for m in re.finditer(r"\S+(?: \(\S+\))?", out[0])]
    for line in body[1:]:
        for end in ends[1:]:
            assert line[end - 1] != " ", (line, end)
            assert end == len(line) or line[end] == " ", (line, end)
    assert out[1].split() == ["dx", "25.712", "1500.0", "0", "0"]
    assert out[2].split()[:5] == ["dy", "0", "12.2", MISSING, "100.00"]
    assert out[2].endswith("  WORSE than uncompensated")
    assert out[3].split() == ["dz", "1234567.891", MISSING, "3.00", "0"]
    assert all(line.startswith("  ") for line in out)
    # two columns never run together, however wide a number
    assert "25.7121500" not in "\n".join(out)
    with pytest.raises(ValueError):
        format_table(cols, [["dx", 1.0]])


def _run(*args, cwd):
    return cli(*args, cwd=cwd)


def _assert_aligned(block: str):
    """The lines of a table: each column's right edge (numbers right-aligned) at the same
    position in every row, cells separated by at least two spaces."""
    lines = block.splitlines()
    header = lines[0]
    edges = [m.end() for m in re.finditer(r"\S+(?: \S+)*", header)][1:]
    assert len(edges) >= 3, header
    for line in lines[1:]:
        for e in edges:
            assert line[e - 1] != " " and (e == len(line) or line[e : e + 2] == "  "), (header, line)


@pytest.fixture(scope="session")
def campaigns(tmp_path_factory):
    work = tmp_path_factory.mktemp("tables")
    for scenario, seed, name in (("thermal-36h", 1, "thermal_a"), ("static-y", 2, "static_y")):
        r = _run("simulate", "--scenario", scenario, "--seed", seed, "-o", name, cwd=work)
        assert r.returncode == 0, r.stderr
        assert (work / name / "campaign.yaml").is_file()
    r = _run("fit", "thermal_a", "static_y", "--features", "eq11", "-o", "m.json", cwd=work)
    assert r.returncode == 0, r.stderr
    assert json.loads((work / "m.json").read_text())["model_type"] == "mra"
    return work


@pytest.mark.slow
def test_validate_prints_aligned_tables_with_units(campaigns):
    r = _run("validate", "m.json", "thermal_a", "static_y", cwd=campaigns)
    assert r.returncode == 0, r.stderr
    blocks = re.findall(r"^(axis .*\n(?:d[xyz] .*\n?){3})", r.stdout, re.M)
    assert len(blocks) == 4  # two campaigns, static plateaus, pooled
    for block in blocks:
        _assert_aligned(block)
        assert "(µm)" in block.splitlines()[0]
    assert "comp. ratio" in r.stdout and "max err (% of peak)" in r.stdout
    assert "-0.000" not in r.stdout and "e-" not in r.stdout
