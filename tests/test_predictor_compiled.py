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
