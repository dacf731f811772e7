"""fbgcomp report: real campaigns (a static load campaign and a thermal one), a real fitted model,
the real HTML file opened in Debian's chromium. Screenshots go to test-artifacts/report/."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import fbgcomp_testing
from fbgcomp import optics
from fbgcomp.bench import synthetic
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import Campaign, CampaignMeta, read_campaign, write_campaign
from fbgcomp.models import MRAModel, load_model
from fbgcomp.models.features import TEMPERATURE_FEATURES, design_matrix
from fbgcomp.models.metrics import validation_metrics

ARTIFACTS = Path(__file__).resolve().parent.parent / "test-artifacts" / "report"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
SENSITIVITY_UM_PER_N = np.array([0.004, -0.003, 0.006, -0.005, 0.001])


def static_campaign(name="static_y", seed=5, hold_s=40.0, dt_s=1.0) -> Campaign:
    """Forces of 0-4000 N in steps on the TTP (paper sec. 3.1): elongations proportional to F_y,
    wavelengths from the bonded-FBG forward model, the TTP deviation from the synthetic truth."""
    rng = np.random.default_rng(seed)
    meta = CampaignMeta(**synthetic.default_meta(name=name, kind="static"))
    levels = np.array([0.0, 1000.0, 2000.0, 3000.0, 4000.0, 0.0])
    t = np.arange(0.0, hold_s * levels.size, dt_s)
    fy = levels[np.minimum((t // hold_s).astype(int), levels.size - 1)]
    dl = fy[:, None] * SENSITIVITY_UM_PER_N + 0.02 * rng.standard_normal((t.size, 5))
    lam0 = np.array([s.lambda0_nm for s in meta.sensors])
    gauge = np.array([s.gauge_length_mm for s in meta.sensors])
    lam = optics.wavelength_nm(dl, lam0, gauge, 0.0)
    temps = 30.0 + 0.01 * rng.standard_normal((t.size, len(synthetic.PROBES)))
    coef = synthetic.default_coefficients()
    names = [f"dL_{s}" for s in synthetic.SENSORS] + list(TEMPERATURE_FEATURES)
    design = design_matrix(np.hstack([dl, np.zeros((t.size, 3))]), names, names)
    beta = np.array([[coef[a].get(n, 0.0) for a in synthetic.AXES] for n in ["const", *names]])
    ref = design @ beta + 0.05 * rng.standard_normal((t.size, 3))

    def frame(values, columns):
        df = pd.DataFrame(values, columns=columns)
        df.insert(0, "time_s", t)
        return df

    return Campaign.from_arrays(
        meta,
        fbg=frame(lam, [f"{s}_nm" for s in synthetic.SENSORS]),
        temperatures=frame(temps, [f"{p}_C" for p in synthetic.PROBES]),
        reference=frame(ref, ["dx_um", "dy_um", "dz_um"]),
        loads=frame(np.column_stack([0 * fy, fy, 0 * fy]), ["fx_N", "fy_N", "fz_N"]),
    )


@pytest.fixture(scope="session")
def setup(tmp_path_factory):
    fbgcomp_testing.require("matplotlib")
    base = tmp_path_factory.mktemp("report")
    thermal, _ = synthetic.linear_truth_campaign(
        "thermal_a", seed=3, duration_s=2 * 3600, wavelength_noise_nm=0.0005
    )
    static = static_campaign()
    model = MRAModel(features="eq13", stepwise=True).fit([thermal, static])
    model_path = model.save(base / "model.json")
    return {
        "base": base,
        "model": model_path,
        "thermal": write_campaign(thermal, base / "thermal_a"),
        "static": write_campaign(static, base / "static_y"),
    }


def _cli(*args) -> subprocess.CompletedProcess:
    """``fbgcomp ARGS`` through the console entry point."""
    return subprocess.run(
        [sys.executable, "-m", "fbgcomp", *map(str, args)], capture_output=True, text=True, timeout=120
    )


def _launch(playwright):
    chromium = fbgcomp_testing.require_program("chromium")
    return playwright.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)


@pytest.mark.slow
def test_report_cli_writes_one_self_contained_file_with_the_figures_that_apply(setup):
    out = setup["base"] / "out"
    result = _cli("report", setup["static"], setup["thermal"], "--model", setup["model"], "-o", out)
    assert result.returncode == 0, result.stderr
    assert "report written to" in result.stdout and str(out / "report.html") in result.stdout
    text = (out / "report.html").read_text(encoding="utf-8")
    # figures by campaign kind: loads -> 6 and 7, time history -> 8 and 9, else "not applicable"
    assert sorted(p.name for p in out.glob("*.png")) == [
        "static_y_fig6.png",
        "static_y_fig7.png",
        "thermal_a_fig8.png",
        "thermal_a_fig9.png",
    ]
    assert len(re.findall(r'<img src="data:image/png;base64,', text)) == 4
    assert re.search(r'data-not-applicable="fig6">Fig. 6 not applicable: no loads.csv', text)
    assert 'data-not-applicable="fig8"' in text and 'data-not-applicable="fig9"' in text
    # nothing outside the file: no external script, stylesheet, font or image
    assert not re.search(r'(src|href)="(?!data:|#)', text)
    # no staging folder left behind
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".out.")]

    # Table 1 per axis: every term with value, standard error, t and p from the model file
    model = load_model(setup["model"])
    for axis in ("dx", "dy", "dz"):
        fit = model.axes_[axis]
        block = text.split(f'id="table1-{axis}"')[1].split("</table>")[0]
        for term, p, se, t in zip(fit.terms, fit.params, fit.bse, fit.tvalues):
            row = re.search(
                rf"<code>{re.escape(term)}</code></td><td>([^<]+)</td><td>([^<]+)"
                rf"</td><td[^>]*>[^<]*</td><td>([^<]+)</td>",
                block,
            )
            assert row, (axis, term)
            assert float(row.group(1)) == pytest.approx(p, rel=1e-4, abs=1e-12)
            assert float(row.group(2)) == pytest.approx(se, rel=1e-3)
            assert float(row.group(3)) == pytest.approx(t, abs=0.006)
        assert f"Stepwise history, axis {axis}" in text
    # the validation metrics are the library's
    c = read_campaign(setup["thermal"])
    pred, half = model.predict_interval(c)
    m = validation_metrics(c.aligned(zero_window_s=model.zero_window_s).reference_um, pred, half)
    assert f"{m['axes']['dz']['rms_error_um']:.4g}" in text


@pytest.mark.slow
def test_rewrite_replaces_a_report_but_never_another_folder(setup, tmp_path):
    from fbgcomp.report.html import write_report

    model = load_model(setup["model"])
    static = read_campaign(setup["static"])
    target = tmp_path / "rep"
    first = write_report([static], model, target)
    (target / "stale.png").write_bytes(b"old")
    write_report([static], model, target)
    assert first.is_file() and not (target / "stale.png").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rep"]

    other = tmp_path / "photos"
    other.mkdir()
    (other / "holiday.jpg").write_bytes(b"x")
    with pytest.raises(InputError, match="not a report folder"):
        write_report([static], model, other)
    assert sorted(p.name for p in other.iterdir()) == ["holiday.jpg"]


def test_sensor_health_flags_the_faulty_channel_and_only_it():
    from fbgcomp.report.html import probe_health, sensor_health

    rng = np.random.default_rng(0)
    t = np.arange(0.0, 700.0, 0.1)
    lam0 = 1530.0 + 5.0 * np.arange(5)
    slow = 0.02 * np.sin(2 * np.pi * t / 300.0)
    wl = lam0 + slow[:, None] + 0.0005 * rng.standard_normal((t.size, 5))
    wl[:, 1] += 0.008 * rng.standard_normal(t.size)  # S2: 8 pm noise
    wl[3000:, 2] += 0.5  # S3: a 0.5 nm jump
    wl[1000:1100, 3] = wl[1000, 3]  # S4: stuck for 10 s
    h = {r["sensor"]: r for r in sensor_health(t, wl, lam0, ["S1", "S2", "S3", "S4", "S5"])}
    assert h["S1"]["status"] == h["S5"]["status"] == "OK"
    assert h["S1"]["noise_pm"] == pytest.approx(0.5, rel=0.15)
    assert h["S2"]["status"] == "CHECK" and h["S2"]["noise_pm"] == pytest.approx(8.0, rel=0.15)
    assert h["S3"]["jumps"] == 1 and h["S3"]["status"] == "CHECK"
    assert h["S4"]["longest_constant_s"] == pytest.approx(9.9, abs=0.01)
    assert h["S4"]["status"] == "CHECK"
    assert all(r["out_of_band_fraction"] == 0 for r in h.values())
    assert h["S3"]["band_margin_nm"] == pytest.approx(5.0 - np.max(np.abs(wl[:, 2] - lam0[2])))

    temps = 30.0 + 0.001 * rng.standard_normal((t.size, 2))
    temps[:, 1] = 25.0  # a dead probe: constant > 10 min
    p = {r["probe"]: r for r in probe_health(t, temps, ["T_bulk", "T_surf"])}
    assert p["T_bulk"]["status"] == "OK" and p["T_surf"]["status"] == "CHECK"


@pytest.mark.slow
def test_report_in_chromium_shows_every_figure_and_table(setup):
    sync_api = fbgcomp_testing.require("playwright.sync_api")
    out = setup["base"] / "browser"
    result = _cli("report", setup["static"], setup["thermal"], "--model", setup["model"], "-o", out)
    assert result.returncode == 0, result.stderr
    assert (out / "report.html").is_file()
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    with sync_api.sync_playwright() as p:
        browser = _launch(p)
        try:
            page = browser.new_page(viewport={"width": 1200, "height": 900})
            requested = []
            page.on("request", lambda r: requested.append(r.url))
            page.goto((out / "report.html").as_uri())
            page.wait_for_load_state("load")
            figures = page.eval_on_selector_all(
                "figure img",
                "imgs => imgs.map(i => [i.closest('figure').id, i.complete, "
                "i.naturalWidth, i.naturalHeight, i.getBoundingClientRect().width])",
            )
            assert [f[0] for f in figures] == [
                "static_y-fig6",
                "static_y-fig7",
                "thermal_a-fig8",
                "thermal_a-fig9",
            ]
            for fid, complete, w, h, shown in figures:
                assert complete and w >= 1000 and h >= 500, fid  # decoded, print resolution
                assert shown > 600, fid  # and laid out readably
            # the four pictures are different pictures
            sources = page.eval_on_selector_all("figure img", "imgs => imgs.map(i => i.src)")
            assert len(set(sources)) == 4
            # only the file itself and its embedded data were loaded
            assert all(u.startswith(("file://", "data:")) for u in requested), requested
            na = page.locator("[data-not-applicable]").all_inner_texts()
            assert len(na) == 4 and all("not applicable" in t for t in na)
            headers = page.locator("#table1-dy + table th").all_inner_texts()
            assert headers[3:5] == ["value", "standard error"] and "P>|t|" in headers
            page.screenshot(path=str(ARTIFACTS / "report-full.png"), full_page=True)
            page.locator("#static_y-fig7").screenshot(path=str(ARTIFACTS / "report-fig7.png"))
            page.locator("#table1-dy + table").screenshot(path=str(ARTIFACTS / "report-table1.png"))
        finally:
            browser.close()
