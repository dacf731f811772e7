import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from fbgcomp.campaign import write_campaign
from fbgcomp.cli import main
from fbgcomp.synthetic import linear_truth_campaign

FBGCOMP = [sys.executable, "-m", "fbgcomp"]


@pytest.fixture(scope="module")
def campaigns(tmp_path_factory):
    root = tmp_path_factory.mktemp("campaigns")
    train, _ = linear_truth_campaign("train", seed=1, duration_s=3600, temperature_dt_s=10,
                                     reference_offset_s=0.3)
    test, _ = linear_truth_campaign("test", seed=2, duration_s=3600, temperature_dt_s=10)
    return write_campaign(train, root / "train"), write_campaign(test, root / "test")


def run(*args, cwd=None):
    return subprocess.run([*FBGCOMP, *map(str, args)], capture_output=True, text=True, cwd=cwd,
                          timeout=300, env={**os.environ, "PYTHONWARNINGS": "ignore"})


def test_fit_then_validate_through_the_console(campaigns, tmp_path):
    train, test = campaigns
    model = tmp_path / "model.json"
    r = run("fit", train, "--features", "eq13", "--stepwise", "-o", model)
    assert r.returncode == 0, r.stderr
    assert "== dx (µm) ==" in r.stdout and "std err" in r.stdout and "stepwise history" in r.stdout
    assert json.loads(model.read_text())["model_type"] == "mra"

    metrics = tmp_path / "metrics.json"
    r = run("validate", model, test, "--json", metrics)
    assert r.returncode == 0, r.stderr
    m = json.loads(metrics.read_text())
    assert m["n_samples"] > 3000
    for axis in ("dx", "dy", "dz"):
        a = m["axes"][axis]
        assert set(a) >= {"peak_um", "max_abs_error_um", "rms_error_um", "error_pct_of_peak",
                          "compensation_ratio"}
        assert a["rms_error_um"] < 0.15 and a["compensation_ratio"] > 0.98
    assert "campaign test" in r.stdout and "comp. ratio" in r.stdout


def test_fit_chooses_the_regression_inference(campaigns, tmp_path):
    """--cov-type nonrobust gives the paper's i.i.d. tables; the default is Newey-West with the
    bandwidth --hac-maxlags fixes; a bad value is a one-line error naming the option."""
    train, _ = campaigns
    naive, hac = tmp_path / "naive.json", tmp_path / "hac.json"
    r = run("fit", train, "--features", "eq13", "--cov-type", "nonrobust", "-o", naive)
    assert r.returncode == 0, r.stderr
    r = run("fit", train, "--features", "eq13", "--hac-maxlags", "32", "-o", hac)
    assert r.returncode == 0, r.stderr
    a, b = json.loads(naive.read_text()), json.loads(hac.read_text())
    assert a["inference"]["cov_type"] == "nonrobust"
    assert b["inference"] == {"cov_type": "HAC", "hac_maxlags": 32}
    assert r.stdout.count("HAC (Newey-West, Bartlett, 32 lags)") == 3
    for bad, option in ((["--cov-type", "robust"], "--cov-type"), (["--hac-maxlags", "-3"], "--hac-maxlags")):
        r = run("fit", train, "--features", "eq13", *bad, "-o", tmp_path / "x.json")
        assert r.returncode != 0 and "Traceback" not in r.stderr
        assert option in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not (tmp_path / "x.json").exists()


def test_inspect(campaigns):
    r = run("inspect", campaigns[0])
    assert r.returncode == 0, r.stderr
    assert "fbg.csv: 3601 rows" in r.stdout and "every 10 s" in r.stdout and "overlap" in r.stdout
    r = run("inspect", campaigns[0], "--json")
    assert json.loads(r.stdout)


def _broken_copy(src, dst, file, transform):
    shutil.copytree(src, dst)
    p = dst / file
    p.write_text(transform(p.read_text()))
    return dst


def _replace_cell(row, column_index, value):
    def f(text):
        lines = text.splitlines()
        cells = lines[row].split(",")
        cells[column_index] = value
        lines[row] = ",".join(cells)
        return "\n".join(lines) + "\n"
    return f


BAD = {
    "non-numeric": ("fbg.csv", _replace_cell(5, 2, "abc"), ["fbg.csv", "row 5 (line 6)", "S2_nm", "abc"]),
    "nan": ("fbg.csv", _replace_cell(7, 3, "nan"), ["fbg.csv", "row 7 (line 8)", "S3_nm"]),
    "out-of-band": ("fbg.csv", _replace_cell(9, 1, "1600.0"), ["fbg.csv", "row 9 (line 10)", "S1_nm", "1600"]),
    "time-not-increasing": ("reference.csv", _replace_cell(4, 0, "0.0"), ["reference.csv", "row 4 (line 5)", "time_s"]),
    "semicolons": ("temperatures.csv", lambda t: t.replace(",", ";"), ["temperatures.csv", "';'"]),
    "header-only": ("reference.csv", lambda t: t.splitlines()[0] + "\n", ["reference.csv"]),
    "empty": ("fbg.csv", lambda t: "", ["fbg.csv", "empty"]),
    "missing-column": ("reference.csv", lambda t: "\n".join(",".join(l.split(",")[:3]) for l in t.splitlines()) + "\n",
                       ["reference.csv", "dz_um"]),
    "unknown-sensor": ("fbg.csv", lambda t: "\n".join(l + (",S9_nm" if i == 0 else ",1560.0")
                                                    for i, l in enumerate(t.splitlines())) + "\n", ["fbg.csv", "S9"]),
    "unknown-probe": ("campaign.yaml", lambda t: t.replace("temperature_probe: T_surf", "temperature_probe: T_nowhere", 1),
                      ["campaign.yaml", "T_nowhere"]),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_is_one_line_exit_2_no_traceback(campaigns, tmp_path, capsys, case):
    file, transform, must_name = BAD[case]
    broken = _broken_copy(campaigns[0], tmp_path / "broken", file, transform)
    code = main(["fit", str(broken), "-o", str(tmp_path / "m.json")])
    err = capsys.readouterr().err
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for fragment in must_name:
        assert fragment in lines[0], (fragment, lines[0])
    assert not (tmp_path / "m.json").exists()


def test_console_script_bad_input_and_missing_folder(campaigns, tmp_path):
    broken = _broken_copy(campaigns[0], tmp_path / "broken", "fbg.csv", _replace_cell(5, 2, "abc"))
    r = run("validate", tmp_path / "nope.json", broken)
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "nope.json" in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = run("inspect", tmp_path / "no-such-campaign")
    assert r.returncode == 2 and "no-such-campaign" in r.stderr and "Traceback" not in r.stderr


def test_existing_model_file_survives_a_failed_fit(campaigns, tmp_path, capsys):
    model = tmp_path / "model.json"
    assert main(["fit", str(campaigns[0]), "-o", str(model)]) == 0
    before = model.read_bytes()
    broken = _broken_copy(campaigns[0], tmp_path / "broken", "fbg.csv", _replace_cell(5, 2, "x"))
    assert main(["fit", str(broken), "-o", str(model)]) == 2
    assert model.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".model")] == []
