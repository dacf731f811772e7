"""The regression predictor's compiled form (term indices, stacked covariance roots) gives the
design matrix of ``features.design_matrix`` to the bit and the interval of the per-axis einsum
it replaced to round-off, for the runtime's test model and a dynamic model."""

import numpy as np

from fbgcomp.io.campaign import read_campaign
from fbgcomp.models.dynamic import DynamicModel
from fbgcomp.models.features import design_matrix
from fbgcomp.models.registry import load_model


def _einsum_interval(p, d):
    spread = np.einsum("nk,akm->anm", d, p._cov_sqrt)
    var = p._resid_var[None, :] + np.einsum("anm,anm->na", spread, spread)
    return p._t[None, :] * np.sqrt(var)


def test_compiled_design_and_interval_equal_the_reference(runtime_model_and_campaign):
    model_path, campaign_path = runtime_model_and_campaign
    model = load_model(model_path)
    campaign = read_campaign(campaign_path)
    aligned = campaign.aligned(zero_window_s=model.zero_window_s)
    w, t, w0, t0 = model.instrument_arrays(aligned)
    dynamic = DynamicModel().fit([campaign])
    for p in (model.predictor(), model.predictor(frozenset({"S3"})), dynamic.predictor()):
        assert p._factors is not None and len(p.terms) > 3
        dynamic_state = hasattr(p, "reset")  # its design carries the filters' state
        if dynamic_state:
            p.reset()
            dev, half = p.predict(w, t, w0, t0, time_s=aligned.time_s)
            p.reset()
            d = p.design(w, t, w0, t0, aligned.time_s)
            base = p.last_base
        else:
            dev, half = p.predict(w, t, w0, t0)
            base = p.feature_map.base(w, t, w0, t0)
            d = p.design(w, t, w0, t0)
        np.testing.assert_array_equal(d, design_matrix(base, p.feature_map.base_names, p.terms))
        np.testing.assert_array_equal(dev, d @ p.coef)
        np.testing.assert_allclose(half, _einsum_interval(p, d), rtol=1e-12, atol=0)
        assert np.isfinite(half).all() and (half > 0).all()


def test_feature_map_base_is_the_optics_arithmetic_to_the_bit():
    """``FeatureMap.base`` writes eq. 2-4 and the eq. 13 temperature features in place (the
    runtime's per-frame cost): it must give optics' eq. 2-4 and eq. 13's values exactly, with a grating
    and a probe missing, uncompensated sensors, one frame and many, with and without probes."""
    from types import SimpleNamespace

    from fbgcomp import optics
    from fbgcomp.models.features import FeatureMap, TemperatureRoles

    rng = np.random.default_rng(0)
    probes = ["T_bulk", "T_surf", "T_flange", "T_x"]
    sensors = [
        SimpleNamespace(
            name=f"S{i}",
            gauge_length_mm=500.0 + i,
            photoelastic=0.22,
            thermo_optic_per_K=6.67e-6 + i * 1e-8,
            fibre_cte_per_K=0.55e-6,
            temperature_probe=[None, *probes][i % 5],
        )
        for i in range(7)
    ]
    for probe_names, temperature_features in ((probes, False), (probes, True), ([], False)):
        bare = (
            sensors
            if probe_names
            else [SimpleNamespace(**{**vars(s), "temperature_probe": None}) for s in sensors]
        )
        fm = FeatureMap(bare, probe_names, temperature_features, TemperatureRoles())
        for n in (1, 9):
            w0 = 1530.0 + 20.0 * rng.random(7)
            t0 = 20.0 + rng.random(len(probe_names))
            w = w0 + rng.normal(0.0, 0.01, (n, 7))
            t = t0 + rng.normal(0.0, 1.0, (n, len(probe_names)))
            w[-1, 2] = np.nan
            if probe_names:
                t[0, 1] = np.nan
            delta = t - t0
            sensor_dt = (
                np.where(fm._compensated, delta[:, np.maximum(fm._sensor_probe, 0)], 0.0)
                if probe_names
                else np.zeros_like(w)
            )
            expected = optics.elongation_um(
                w,
                w0,
                fm._gauge_mm,
                sensor_dt,
                photoelastic=fm._pe,
                thermo_optic_per_K=fm._xi,
                fibre_cte_per_K=fm._af,
            )
            if temperature_features:
                b, s, f = (delta[:, i] for i in fm._roles)  # eq. 13
                expected = np.hstack([expected, np.column_stack([b, b - s, f - b])])
            got = fm.base(w[0] if n == 1 else w, t[0] if n == 1 else t, w0, t0)
            np.testing.assert_array_equal(got, expected)
            assert np.isnan(got).any() and np.isfinite(got).sum() > got.size // 2
