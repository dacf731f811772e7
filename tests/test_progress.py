"""Progress of long commands (issue 15, item 2): named stages on stderr when forced with
FBGCOMP_PROGRESS=1 (or on a terminal), nothing with FBGCOMP_PROGRESS=0 or --quiet, and stdout
the same either way - through the CLI (run in the test's process: fbgcomp_testing.cli; its stderr,
like a pipe's, is not a terminal)."""

from __future__ import annotations

import pytest

from fbgcomp_testing import cli

# both tests run the real CLI several times (3-30 s under load)
pytestmark = pytest.mark.slow


def _run(args, cwd, progress=None):
    return cli(*args, cwd=cwd, env={"FBGCOMP_PROGRESS": progress})


def test_stages_on_stderr_only_and_stdout_unchanged(tmp_path):
    runs = {}
    for progress in ("1", "0", None):
        work = tmp_path / f"p{progress}"
        work.mkdir()
        sim = _run(["simulate", "--scenario", "static-y", "--seed", 2, "-o", "static_y"], work, progress)
        fit = _run(["fit", "static_y", "--model", "hybrid", "-o", "m.json"], work, progress)
        assert sim.returncode == 0 and fit.returncode == 0, (sim.stderr, fit.stderr)
        val = _run(["validate", "m.json", "static_y", "--json", "metrics.json"], work, progress)
        assert val.returncode == 0, val.stderr
        runs[progress] = (sim, fit, val, work)
    forced, off, default = runs["1"], runs["0"], runs[None]
    sim, fit, val, _ = forced
    assert sim.stderr.splitlines() == [
        "simulate: reading the machine and scenario",
        "simulate: running the scenario on the FE twin (built or loaded from its cache)",
        "simulate: writing static_y",
    ]
    assert fit.stderr.splitlines() == [
        "fit: reading campaigns",
        "  reading campaigns: campaign 1/1",
        "fit: fitting the hybrid model",
        "fit: writing m.json",
    ]
    assert "validating: campaign 1/1" in val.stderr
    rep = _run(["report", "static_y", "--model", "m.json", "-o", "rep"], forced[3], "1")
    assert rep.returncode == 0, rep.stderr
    assert rep.stderr.splitlines() == [
        "report: reading the model and campaigns",
        "report: analysing static-y",  # the campaign's name (campaign.yaml), not its folder
        "report: written to rep",
    ]
    assert (forced[3] / "rep" / "report.html").is_file()
    # not a terminal and not forced: nothing, as with FBGCOMP_PROGRESS=0
    for quiet in (off, default):
        assert all(r.stderr == "" for r in quiet[:3]), [r.stderr for r in quiet[:3]]
    # stdout identical (the model id differs with nothing: same data, same fit)
    for i in range(3):
        assert forced[i].stdout == off[i].stdout == default[i].stdout
    assert (forced[3] / "metrics.json").read_text() == (off[3] / "metrics.json").read_text()


def test_quiet_option_wins_over_forcing(tmp_path):
    r = _run(["--quiet", "simulate", "--scenario", "static-y", "--seed", 2, "-o", "s"], tmp_path, "1")
    assert r.returncode == 0 and r.stderr == "" and "written to s" in r.stdout
    assert (tmp_path / "s" / "campaign.yaml").is_file() and (tmp_path / "s" / "fbg.csv").is_file()
