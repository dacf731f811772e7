"""Dashboard drift windows: a 36 h run log written by the real RunLog (1 frame/s, with a day
cycle of the ambient, a rate-limited hour, a max-limited stretch, a lost grating, an alarm and the
output switched off), served by the real Dashboard on loopback, read over HTTP and shown in
Debian's chromium. Screenshots go to test-artifacts/dashboard/ (drift-36h.png is the one in
docs/img/dashboard-drift-36h.png)."""

from __future__ import annotations

import json
import time
import types
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

import fbgcomp_testing

ARTIFACTS = Path(__file__).resolve().parent.parent / "test-artifacts" / "dashboard"
HOUR = 3600.0
SPAN_S = 36 * HOUR
SENSORS = ["S1", "S2", "S3"]
PROBES = ["T_bulk", "T_amb"]

# the module fixture writes a 36 h run log through the real RunLog (10-15 s under load)
pytestmark = pytest.mark.slow


def _scenario(t_rel):
    """Per-frame logged values of the 36 h scenario (t_rel: s since the start)."""
    from fbgcomp.runtime import health as H
    from fbgcomp.runtime.pipeline import HEALTH_ALARM, HEALTH_DEGRADED

    n = t_rel.size
    h = t_rel / HOUR
    t_amb = 20.0 + 1.5 * np.sin(2 * np.pi * (h - 8.0) / 24.0)
    t_bulk = 20.0 + 1.0 * np.sin(2 * np.pi * (h - 11.0) / 24.0)
    dev = np.column_stack([4.0 * (t_bulk - 20.0), -6.0 * (t_amb - 20.0), 2.0 * (t_bulk - 20.0)])
    corr = -dev.copy()
    flags = np.zeros((n, 3), np.uint8)
    health = np.zeros(n, np.uint8)
    status = np.zeros((n, len(SENSORS)), np.uint8)
    enabled = np.ones(n, bool)
    rate = (h >= 6.0) & (h < 7.0)  # dx rate limited for one hour
    corr[rate, 0] *= 0.5
    flags[rate, 0] |= H.FLAG_RATE_LIMITED
    cap = (h >= 14.0) & (h < 16.0) & (np.abs(corr[:, 1]) > 5.0)  # dy held at its maximum
    corr[cap, 1] = np.sign(corr[cap, 1]) * 5.0
    flags[cap, 1] |= H.FLAG_MAX_LIMITED
    lost = (h >= 24.0) & (h < 26.0)  # S2 lost: fallback, DEGRADED
    status[lost, 1] = H.MISSING
    health[lost] = HEALTH_DEGRADED
    alarm = (h >= 26.0) & (h < 26.25)  # then no usable model for 15 min
    health[alarm] = HEALTH_ALARM
    dev[alarm] = np.nan
    corr[alarm] = 0.0
    off = (h >= 30.0) & (h < 30.5)  # output switched off for 30 min
    enabled[off] = False
    corr[off] = 0.0
    return {
        "T": np.column_stack([t_bulk, t_amb]),
        "dev": dev,
        "corr": corr,
        "flags": flags,
        "health": health,
        "status": status,
        "enabled": enabled,
        "masks": {"rate": rate, "cap": cap, "lost": lost, "alarm": alarm, "off": off},
    }


def write_36h_log(folder: Path, end_s: float) -> dict:
    """The scenario through the real RunLog, one hour of frames per batch; returns it."""
    from fbgcomp.runtime import health as H
    from fbgcomp.runtime.log import RunLog
    from fbgcomp.runtime.pipeline import HEALTH_NAMES, BatchResult
    from fbgcomp.runtime.windows import SensorBatch

    meta = {
        "format": "fbgcomp-runlog",
        "version": 1,
        "model_id": "drift-test",
        "sensor_names": SENSORS,
        "probe_names": PROBES,
        "temperature_probes": [
            {"name": "T_bulk", "location": "ram, bulk"},
            {"name": "T_amb", "location": "air beside the machine"},
        ],
        "health_names": list(HEALTH_NAMES),
        "status_names": list(H.STATUS_NAMES),
        "flag_names": {str(k): v for k, v in H.FLAG_NAMES.items()},
    }
    t_rel = np.arange(int(SPAN_S), dtype=float)  # 1 frame/s
    sc = _scenario(t_rel)
    t = end_s - SPAN_S + t_rel
    log = RunLog(folder, meta, flush_s=0.05)
    S = len(SENSORS)
    n = 1800  # half an hour per batch
    for k in range(int(SPAN_S) // n):
        sl = slice(k * n, (k + 1) * n)
        wl = 1530.0 + 10.0 * np.arange(S) + 1e-3 * sc["T"][sl, :1]
        wl[sc["status"][sl] == H.MISSING] = np.nan
        b = SensorBatch(t[sl], wl, np.ones((n, S), np.int8), np.zeros((n, S), np.int8), float(t[sl][-1]))
        r = BatchResult(
            t[sl],
            sc["dev"][sl],
            np.full((n, 3), 0.8),
            sc["corr"][sl],
            np.full((n, 3), 0.4),
            sc["health"][sl],
            sc["status"][sl],
            np.zeros(n, np.int16),
            sc["T"][sl],
            output_flags=sc["flags"][sl],
        )
        log.submit(b, r, bool(sc["enabled"][sl][0]))  # the switch acts per batch
        end = time.monotonic() + 10
        while log.files <= k and time.monotonic() < end:  # one part per half hour, as a
            time.sleep(0.005)  # long log has many parts
    log.close(30)
    assert log.written_rows == t.size and log.dropped_rows == 0
    return {"t": t, **sc}


def _get(url):
    with urllib.request.urlopen(url, timeout=30) as r:
        return json.loads(r.read())


def _until_complete(ask, parts=72):
    """Ask again while the answer is not complete, as the page does: a cold cache is filled
    within a time budget per request (newest part first, at least one part per request), so on
    a loaded host the first answer may cover only the newest hours. Each request reads at
    least one more part, so ``parts`` requests always suffice."""
    for _ in range(parts):
        d = ask()
        if d["complete"]:
            return d
    raise AssertionError(f"still not complete after {parts} requests: {d.get('covered_from_s')}")


@pytest.fixture(scope="module")
def drift(tmp_path_factory):
    fbgcomp_testing.require("pyarrow")
    from fbgcomp.dashboard import Dashboard, DashboardConfig
    from fbgcomp.runtime.outputs.opcua import Snapshot

    folder = tmp_path_factory.mktemp("drift") / "log"
    end_s = time.time()
    scenario = write_36h_log(folder, end_s)
    dash = Dashboard(DashboardConfig(listen="127.0.0.1:0"), SENSORS, PROBES, "drift-test", log_dir=folder)
    dash.start()
    last = -1
    snap = Snapshot(
        sample_time_s=float(scenario["t"][last]),
        correction_um=tuple(scenario["corr"][last]),
        deviation_um=tuple(scenario["dev"][last]),
        half_width_um=(0.8,) * 3,
        expected_rms_um=(0.4,) * 3,
        health="OK",
        fallback="",
        alarm=False,
        sensor_status=["OK"] * 3,
        sensor_wavelength_nm=[1530.02, 1540.02, 1550.02],
        source_status="connected",
        frames=int(scenario["t"].size),
        model_id="drift-test",
    )
    pipeline = types.SimpleNamespace(model=None, wavelength_zero_nm=None, temperature_zero_C=None)
    dash.publish(snap, scenario["T"][last], pipeline)
    yield {"base": dash.url.rstrip("/"), "folder": folder, "scenario": scenario, "dash": dash}
    dash.stop()


def test_history_of_36_hours_is_bucketed_from_the_log(drift):
    """The server's 36 h answer against the log read independently with pandas."""
    import pandas as pd

    d = _until_complete(lambda: _get(drift["base"] + f"/api/history?window_s={SPAN_S:g}&points=600"))
    assert d["bucket_s"] == pytest.approx(SPAN_S / 600)
    assert 590 <= len(d["t"]) <= 600
    span = d["t"][-1] + d["bucket_s"] - d["t"][0]
    assert span > 35.9 * HOUR, span
    assert d["ambient"] == ["T_amb"]  # named by its location
    df = pd.read_parquet(drift["folder"] / "data")
    inside = df[df["time_s"] >= d["t"][0]]
    assert d["frames"] == len(inside) > 0.99 * SPAN_S
    # every frame of a bucket counted, min/max/mean as pandas finds them
    ids = np.floor(inside["time_s"].to_numpy() / d["bucket_s"]).astype(np.int64)
    grouped = inside.assign(b=ids).groupby("b")
    np.testing.assert_array_equal(d["n"], grouped.size().to_numpy())
    np.testing.assert_allclose(d["series"]["corr_dy_um"]["max"], grouped["corr_dy_um"].max(), atol=1e-4)
    np.testing.assert_allclose(d["series"]["T_amb_C"]["mean"], grouped["T_amb_C"].mean(), atol=1e-4)
    # why held back: every flagged frame is counted in its bucket
    flagged = (inside["flags_dx"].to_numpy() & 8) != 0
    assert sum(d["counts"]["flag:RATE_LIMITED"]) == flagged.sum() == 3600
    assert sum(d["counts"]["health:DEGRADED"]) == (inside["health"] == "DEGRADED").sum() == 7200
    assert sum(d["counts"]["sensor:S2"]) == 7200 and sum(d["counts"]["sensor:S1"]) == 0
    # no prediction while in ALARM: those buckets' means come from the other frames only
    assert sum(d["counts"]["health:ALARM"]) == 900


def test_short_windows_come_from_the_frames_and_bad_requests_are_refused(drift):
    d = _get(drift["base"] + "/api/history?window_s=60&points=600")
    assert d["bucket_s"] == pytest.approx(0.1) and d["frames"] == 60 and len(d["t"]) == 60
    assert d["t_end"] == pytest.approx(drift["scenario"]["t"][-1])
    d = _get(drift["base"] + "/api/history?window_s=3600&points=600")
    assert d["bucket_s"] == 6.0 and 3590 <= d["frames"] <= 3600
    for query in ("window_s=10", "window_s=200000", "window_s=abc", "points=5"):
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(drift["base"] + "/api/history?" + query, timeout=10)
        assert err.value.code == 400


def test_a_cold_cache_fills_newest_first_and_ends_equal(drift):
    from fbgcomp.dashboard.history import LogHistory
    from fbgcomp.runtime.log import log_parts

    assert len(log_parts(drift["folder"])) == 72
    h = LogHistory(drift["folder"])
    first = h.window(SPAN_S, 600, budget_s=0.0)  # one part, then "ask again"
    assert h.parts_read == 1 and not first["complete"]
    # the newest half hour only: 30 min / 216 s buckets, ending at the newest frame
    assert first["covered_from_s"] >= drift["scenario"]["t"][-1] - 1800 - 216
    answers = [first]
    while not answers[-1]["complete"]:
        answers.append(h.window(SPAN_S, 600, budget_s=0.0))
        assert len(answers) <= 72
    assert len(answers) == 72
    fresh = LogHistory(drift["folder"])
    full = _until_complete(lambda: fresh.window(SPAN_S, 600))
    assert answers[-1]["series"] == full["series"] and answers[-1]["n"] == full["n"]
    again = h.parts_read
    h.window(SPAN_S, 600)
    assert h.parts_read == again  # nothing read twice


def test_page_shows_a_36_hour_window_in_chromium(drift):
    sync_api = fbgcomp_testing.require("playwright.sync_api")
    chromium = fbgcomp_testing.require_program("chromium")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    from test_dashboard import CHROMIUM_ARGS

    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1900})
            page.goto(drift["base"] + "/")
            page.wait_for_selector("#drift:not([hidden])")
            page.wait_for_function(
                "() => fbgcomp.drift && fbgcomp.drift.window_s === 3600 && fbgcomp.drift.drawn > 0",
                timeout=30000,
            )
            one_hour = page.evaluate("fbgcomp.drift")
            assert one_hour["bucket_s"] == 6.0 and one_hour["span_s"] <= 3600
            pixels = page.evaluate("document.getElementById('drift-dy').toDataURL()")
            page.click("#windows button[data-window-s='129600']")
            page.wait_for_function(
                "() => fbgcomp.drift.window_s === 129600 && "
                "fbgcomp.drift.complete && fbgcomp.drift.drawn > 0",
                timeout=30000,
            )
            d = page.evaluate("fbgcomp.drift")
            # a 36 h window drawn from ~600 buckets of 216 s
            assert d["bucket_s"] == pytest.approx(216.0)
            assert 590 <= d["points"] <= 600
            assert 35.9 * HOUR < d["span_s"] <= SPAN_S
            assert d["frames"] > 0.99 * SPAN_S
            # the reasons the correction was held back, each over about as many buckets as it
            # lasted (a bucket boundary may split an event: +1)
            lanes = d["lanes"]
            assert 16 <= lanes["RATE_LIMITED"] <= 18  # 1 h / 216 s = 16.7
            assert 1 <= lanes["MAX_LIMITED"] <= 35  # part of 2 h
            assert 33 <= lanes["DEGRADED"] <= 35 and 33 <= lanes["S2 not OK"] <= 35
            assert 4 <= lanes["ALARM"] <= 6  # 15 min
            assert 8 <= lanes["output disabled"] <= 10  # 30 min
            assert lanes["CLAMPED"] == lanes["SHRUNK"] == lanes["LOAD_REFUSED"] == 0
            assert "S1 not OK" not in lanes
            assert d["temperatures"] == ["T_amb"]
            assert "T_amb" in page.inner_text("#drift-temperature-caption")
            assert page.get_attribute("#windows button[data-window-s='129600']", "aria-pressed") == "true"
            assert page.inner_text("#drift-note").startswith("36 h window")
            assert page.evaluate("document.getElementById('drift-dy').toDataURL()") != pixels
            page.screenshot(path=str(ARTIFACTS / "drift-36h.png"), full_page=True)
        finally:
            browser.close()
