"""The default model: loads read as steps of the gratings' load signature, heat from the twin, do no harm.

Why not the paper's regression (eq. 11-13) as the default: on a CFRP ram with near-zero axial
CTE a bonded grating is mostly a thermometer of its own gauge (~10.5 pm/K against ~2 pm per µm
of elongation over 600 mm). Compensated with a probe on another face, it reads ~5 µm of false
elongation per kelvin of mismatch, and the static load gain (14-26 µm of TTP per µm of
differential elongation) turns that into hundreds of µm of lateral "correction" as soon as a
heat source the training never saw warms one face. This model splits the TTP deviation into
two physically separate parts and guards each one:

**Load part** (paper eq. 11 read through the structure's load signature). The gratings'
elongations respond to a TTP force F as ``e = G F`` (G: µm per N, S x 3) and the TTP moves by
``C F`` (C: the compliance, µm per N). G and C are measured on the training campaigns that carry
a loads.csv (static tests), or taken from the FE twin of the machine description when none does.
The gratings' thermal reading drifts by thousands of N of load-equivalent over a day and no
probe predicts it, but a load arrives in seconds and heat in minutes to hours: the applied force
changes only by steps that the generalised least-squares estimate ``(G' W G)^-1 G' W x`` of the
unexplained reading ``x`` shows clear of the gratings' noise, of heat's drift within the
tracking time and of the other components' cross-talk; everything else is tracked as the
gratings' thermal offset, loaded or not (:meth:`PhysicalPredictor._track_load`). A step that no
load explains (one grating jumps alone) is refused (``LOAD_REFUSED``); a force whose signature
is the gratings' warming pattern is a nuisance, never a load.

**Thermal part**. With a machine description: a ridge map from [the gratings' uncompensated
elongations (thermometers of their gauges), the probes' smoothed ΔT, the housing's leads
``T - lowpass(T, tau)``] to the TTP, learned on generic thermal scenarios of the machine's FE
twin (:func:`twin_thermal_population`), so the face-gradient coefficients that no measured
campaign without a gradient can teach come from physics; only the housing's transient (how
late its probe sees the bearings' heat, which every spindle duty cycle excites) is calibrated
on the measured load-free campaigns (:meth:`PhysicalModel._calibrate_housing`). Without one: per axis a least-squares
fit, on the load-free training campaigns, of the TTP on the housing and ambient probes and the
housing's lead (the steel housing's mean temperature, which a probe on its far face sees late).
Either way the inputs are clipped to the envelope they were learned on (``SHRUNK``), what the
sensors' noise alone makes of the part is not applied (firm shrinkage) and each axis is clamped
to the range it was validated on (``CLAMPED``).

Every prediction therefore carries its applicability flags (``last_flags`` after each call,
bits of :mod:`fbgcomp.models.policy`), which the runtime publishes with the correction.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np
from scipy import stats

from fbgcomp.errors import InputError
from fbgcomp.models.features import FeatureMap
from fbgcomp.models.base import AXES, EstimatorParams, ModelFile, _as_campaign_list, check_compatible, register_model_type
from fbgcomp.models import policy as P
from fbgcomp.models.model_types import first_order_filter, first_order_recursion as _first_order

_FORCE_AXES = ("fx", "fy", "fz")
#: Low-pass of the probe temperatures before the thermal regressors, s.
PROBE_SMOOTHING_S = 60.0
# Low-pass of the gratings' load reading, s: a step is judged on it (so frame rate and batching
# do not matter) and a load transition follows it.
LOAD_FAST_S = 0.5
# Slower low-pass, s: a transition ends when the fast reading agrees with it, at its value.
LOAD_HOLD_S = 3.0
#: Expected false load starts per hour of load-free running: a step test is one look per frame
#: (at most one per 2 LOAD_FAST_S, the low-pass's memory), so its threshold in sigma grows with
#: the number of looks an hour holds (5.1 sigma at 1 look/s) instead of a fixed 3 sigma that
#: noise alone crosses a few times a day at 1 Hz.
LOAD_FALSE_STARTS_PER_H = 1e-3
# Frames of a stretch without load transition run vectorised at a time, and frames the per-frame
# recursion takes after a stretch stopped at once (PhysicalPredictor._steady_run).
STEADY_WINDOW = 4096
STEADY_BACKOFF = 64


# ---------------------------------------------------------------------------------------------
# Pure pieces
# ---------------------------------------------------------------------------------------------
def gls_operator(G, Sigma):
    """GLS force estimator ``(G' W G)^-1 G' W`` (3 x S), its covariance (3 x 3) and W (S x S)
    for elongation covariance ``Sigma`` (µm²); G in µm per N."""
    W = np.linalg.pinv(Sigma)
    info = G.T @ W @ G
    cov = np.linalg.pinv(info)
    return cov @ G.T @ W, cov, W


def weighted_lstsq(X, Y, w):
    """Weighted least squares ``min sum w (Y - X B)^2``; returns B and the weighted residuals'
    covariance (columns of Y), with the weights normalised to the number of rows."""
    sw = np.sqrt(w)[:, None]
    B, *_ = np.linalg.lstsq(X * sw, Y * sw, rcond=None)
    R = Y - X @ B
    wn = w / w.sum()
    cov = (R * wn[:, None]).T @ R
    return B, cov


def thermal_regressors(delta_T_K, housing_idx, ambient_idx, lead_tau_s, time_s=None, state=None,
                       nominal_dt_s=1.0):
    """Thermal regressors (n, 1 + nh): [1, ΔT of each housing probe, ΔT of each ambient probe,
    lead of the mean housing ΔT (``T - lowpass(T, lead_tau_s)``, K)] and the filter state.

    ``delta_T_K`` (n, P) are probe temperature changes from the zero state."""
    dT = np.atleast_2d(np.asarray(delta_T_K, dtype=float))
    n = dT.shape[0]
    state = state or {}
    # Probes are quantised (0.1 K is typical) and sampled slowly: a 60 s low-pass keeps their
    # steps out of the correction (thermal drift is far slower), then the lead term is formed.
    used = list(housing_idx) + list(ambient_idx)
    smooth, state_in = first_order_filter(dT[:, used], time_s, PROBE_SMOOTHING_S, state.get("in"), nominal_dt_s)
    cols = [np.ones((n, 1)), smooth]
    new_state = {"in": state_in}
    if len(housing_idx):
        housing = smooth[:, :len(housing_idx)].mean(axis=1, keepdims=True)
        slow, new_state["lead"] = first_order_filter(housing, time_s, lead_tau_s, state.get("lead"), nominal_dt_s)
        cols.append(housing - slow)
    return np.hstack(cols), new_state


#: Time constants of the housing lead terms of the twin-learned thermal map, s.
MAP_LEADS_S = (300.0, 1800.0)


def map_features(e_um, delta_T_K, housing_idx, time_s=None, state=None, nominal_dt_s=1.0):
    """Features of the twin-learned thermal map (n, S + P + 2) and the filter state:
    [uncompensated grating elongations e (µm), every probe's ΔT low-passed over
    ``PROBE_SMOOTHING_S`` (K), the mean housing ΔT's lead ``T - lowpass(T, tau)`` for each tau
    of ``MAP_LEADS_S`` (K)]. On CFRP the gratings are thermometers of their gauges (~5 µm of
    uncompensated elongation per K over 600 mm), which is why they carry the face gradients."""
    e = np.atleast_2d(np.asarray(e_um, float))
    dT = np.atleast_2d(np.asarray(delta_T_K, float))
    state = state or {}
    smooth, s_in = first_order_filter(dT, time_s, PROBE_SMOOTHING_S, state.get("in"), nominal_dt_s)
    new = {"in": s_in}
    leads = housing_leads(housing_mean(smooth, housing_idx), MAP_LEADS_S, time_s, state, new, nominal_dt_s)
    return np.hstack([e, smooth, leads]), new


#: Time constants of the housing leads on which the twin map's housing transient is calibrated
#: against the measured load-free campaigns, s.
CAL_LEADS_S = (300.0, 900.0)


def housing_mean(smooth_K, housing_idx):
    """Mean ΔT (n, 1) K of the housing probes among probe ΔTs already low-passed over
    ``PROBE_SMOOTHING_S`` (zeros without a housing probe)."""
    smooth = np.atleast_2d(smooth_K)
    return (smooth[:, list(housing_idx)].mean(axis=1, keepdims=True) if len(housing_idx)
            else np.zeros((smooth.shape[0], 1)))


def housing_leads(housing_K, taus_s, time_s, state, new_state, nominal_dt_s=1.0):
    """The housing ΔT's leads ``T - lowpass(T, tau)`` (n, len(taus_s)) K, from its mean ΔT
    (:func:`housing_mean`); each filter's state is read from ``state`` and written to
    ``new_state`` under ``lead<tau>``."""
    cols = []
    for tau in taus_s:
        key = f"lead{tau:g}"
        slow, new_state[key] = first_order_filter(housing_K, time_s, tau, state.get(key), nominal_dt_s)
        cols.append(housing_K - slow)
    return np.hstack(cols)


def ridge_from_moments(gram, xty, scale, keep, lam):
    """Ridge coefficients (k, 3) from second moments ``gram = X'X/n`` and ``xty = X'Y/n`` on the
    feature columns ``keep`` (others get 0), features standardised by ``scale``, penalty ``lam``."""
    keep = np.asarray(keep, int)
    sc = np.asarray(scale, float)[keep]
    g = np.asarray(gram, float)[np.ix_(keep, keep)] / np.outer(sc, sc)
    b = np.asarray(xty, float)[keep] / sc[:, None]
    coef = np.zeros((len(scale), np.asarray(xty).shape[1]))
    coef[keep] = np.linalg.solve(g + lam * np.eye(len(keep)), b) / sc[:, None]
    return coef


def twin_thermal_population(machine, sensors, probe_names, housing_probes, n_scenarios=40, seed=0,
                            grating_noise_um=0.1, probe_noise_K=0.1):
    """Second moments of (map features, TTP) over the twin's generic thermal scenarios
    (:mod:`fbgcomp.structure.scenarios`), or None when the machine description lacks one of
    the campaign's gratings or probes. Measurement noise is added as the instruments have it
    (seeded), so the map does not lean on differences finer than the sensors resolve."""
    names = [s.name for s in machine.sensors]
    mprobes = [p.name for p in machine.probes]
    # a strain-free reference grating (<sensor>_ref) reads the temperature of its sensor's gauge
    ref_of = {f"{n}_ref": n for n in names}
    if any(s.name not in names for s in sensors) or \
            any(p not in mprobes and p not in ref_of for p in probe_names):
        return None
    from fbgcomp.optics import wavelength_nm
    from fbgcomp.structure import Twin
    from fbgcomp.structure.scenarios import generic_heat_machine, thermal_scenarios

    twin = Twin(generic_heat_machine(machine))
    idx = [twin.sensor_names.index(s.name) for s in sensors]
    # each thermometer's column in the twin's response: a probe's, or its gauge's temperature
    sources = [("probe_C", twin.probe_names.index(p)) if p in mprobes
               else ("sensor_temperature_C", twin.sensor_names.index(ref_of[p])) for p in probe_names]

    def thermometers(r):
        return np.column_stack([getattr(r, field)[:, i] for field, i in sources]) if sources \
            else np.zeros((r.time_s.size, 0))

    h_idx = [list(probe_names).index(p) for p in housing_probes]
    fmap = _grating_map(sensors, probe_names)
    rng = np.random.default_rng(seed)
    lam0 = np.array([s.lambda0_nm for s in sensors])
    k = len(sensors) + len(probe_names) + len(MAP_LEADS_S)
    gram, xty, noise, n = np.zeros((k, k)), np.zeros((k, 3)), np.zeros((k, k)), 0
    lo, hi = np.full(k, np.inf), np.full(k, -np.inf)
    ylo, yhi = np.full(3, np.inf), np.full(3, -np.inf)
    for inputs, r in thermal_scenarios(twin, n_scenarios, seed):
        r = r.change_from_start()
        t = r.time_s
        el0 = r.sensor_elongation_um[:, idx]
        el = el0 + rng.normal(0, grating_noise_um, (t.size, len(idx)))

        def features(el, dT):
            wl = np.column_stack([
                wavelength_nm(el[:, j], s.lambda0_nm, s.gauge_length_mm, r.sensor_temperature_C[:, i],
                              photoelastic=s.photoelastic, thermo_optic_per_K=s.thermo_optic_per_K,
                              fibre_cte_per_K=s.fibre_cte_per_K)
                for j, (i, s) in enumerate(zip(idx, sensors))])
            return map_features(fmap.base(wl, dT, lam0, np.zeros(len(sources))), dT, h_idx, t)[0]

        # probe noise, and the error of a zero state read from a single slow probe sample
        dT0 = thermometers(r)
        dT = (dT0 + rng.normal(0, probe_noise_K, (t.size, len(sources)))
              + rng.normal(0, probe_noise_K, len(sources)))
        X = features(el, dT)
        N = X - features(el0, dT0)
        noise += N.T @ N
        Y = r.ttp_um
        gram += X.T @ X
        xty += X.T @ Y
        n += t.size
        lo, hi = np.minimum(lo, X.min(axis=0)), np.maximum(hi, X.max(axis=0))
        ylo, yhi = np.minimum(ylo, Y.min(axis=0)), np.maximum(yhi, Y.max(axis=0))
    gram, xty, noise = gram / n, xty / n, noise / n
    return {"gram": gram.tolist(), "xty": xty.tolist(), "scale": np.sqrt(np.diag(gram)).tolist(),
            "noise_gram": noise.tolist(),
            "n_samples": n, "n_scenarios": n_scenarios, "seed": seed,
            "envelope_low": lo.tolist(), "envelope_high": hi.tolist(),
            "ttp_low_um": ylo.tolist(), "ttp_high_um": yhi.tolist(),
            "features": [f"e_{s.name}" for s in sensors] + [f"dT_{p}" for p in probe_names]
            + [f"lead{tau:g}s_housing" for tau in MAP_LEADS_S]}


def _grating_map(sensors, probe_names):
    """Feature map of the gratings' *uncompensated* elongations (paper eq. 2-4 with dT = 0).

    The load part never compensates a grating with a probe on another face: a 0.1 K step of a
    quantised remote probe is ~0.5 µm of false elongation on a 600 mm CFRP gauge, hundreds of N
    of false load. The gratings' own thermal reading is modelled instead (``B``, ``Sigma``)."""
    bare = [s.model_copy(update={"temperature_probe": None}) for s in sensors]
    return FeatureMap(bare, probe_names, False)


def _housing_probe_names(probe_names, machine=None):
    """Probes on the spindle housing (the machine description's point probes below z = 0, else
    names containing 'flange', 'housing' or 'spindle')."""
    if machine is not None:
        found = [p.name for p in machine.probes
                 if p.kind == "point" and p.z_mm is not None and p.z_mm < 0 and p.name in probe_names]
        if found:
            return found
    keys = ("flange", "housing", "spindle")
    return [p for p in probe_names if any(k in p.lower() for k in keys)]


def _ambient_probe_names(probe_names, machine=None):
    if machine is not None:
        found = [p.name for p in machine.probes if p.kind == "ambient" and p.name in probe_names]
        if found:
            return found
    return [p for p in probe_names if "amb" in p.lower()]


# ---------------------------------------------------------------------------------------------
# Predictor (one sensor set; runtime and offline share it)
# ---------------------------------------------------------------------------------------------
def excursion2(dT, scale_K, deadband_K=0.0):
    """Squared thermal excursion of each frame: sum over probes of (dT / scale)^2, where
    ``scale_K`` is each probe's largest |dT| in training (so 1 ~ the training's extreme) and
    a change within a probe's ``deadband_K`` (its noise) counts as none."""
    dT = np.atleast_2d(np.asarray(dT, float))
    dT = np.sign(dT) * np.maximum(np.abs(dT) - np.asarray(deadband_K, float), 0.0)
    return np.sum((dT / np.asarray(scale_K, float)) ** 2, axis=1)


class PhysicalPredictor:
    """Vectorised, stateful predictor of one sensor set (full, or without excluded gratings).

    ``predict`` returns the deviation it judges safe to apply (n, 3) µm and the half-width of its
    95 % interval; ``last_flags`` (n, 3) uint8 holds the policy flags of the last call.
    """

    def __init__(self, model, exclude=frozenset()):
        m = model
        self.exclude = frozenset(exclude)
        self.sensor_names = list(m.sensor_names)
        self.probe_names = list(m.probe_names_)
        self._fmap = _grating_map(m.sensors_, m.probe_names_)
        self._h_idx = [self.probe_names.index(p) for p in m.housing_probes_]
        self._a_idx = [self.probe_names.index(p) for p in m.ambient_probes_]
        self.lead_tau_s = float(m.lead_tau_s)
        self.nominal_dt_s = float(m.nominal_dt_s_)
        self.A = np.asarray(m.thermal_coef_)                  # (1 + nh, 3)
        self.h_low, self.h_high = np.asarray(m.thermal_envelope_[0]), np.asarray(m.thermal_envelope_[1])
        self.t_low, self.t_high = np.asarray(m.thermal_range_um_[0]), np.asarray(m.thermal_range_um_[1])
        self.margin = float(m.envelope_margin)
        self.k_sigma = float(m.load_k_sigma)       # also the thermal part's noise shrinkage
        self.thermal_resid_var = np.asarray(m.thermal_resid_sd_um_) ** 2
        # interval of the thermal part: variance = v0 + vs s + v1 s^2 + v2 a^2 (s the thermal
        # excursion, a the housing's lead), fitted on the load-free training campaigns
        # (``PhysicalModel._fit_interval``); a constant without it
        iv = getattr(m, "interval_", None)
        self.interval = None if iv is None else {
            "v0": np.asarray(iv["v0_um2"], float), "v1": np.asarray(iv["v1_um2"], float),
            "scale": np.asarray(iv["dT_scale_K"], float), "v2": np.asarray(iv["v2_um2"], float),
            "activity_scale": float(iv["activity_scale_K"]),
            "vs": np.asarray(iv.get("vs_um2", np.zeros(3)), float),
            "deadband": np.asarray(iv.get("deadband_K", 0.0), float)}
        self.thermal_noise_sd_um = np.asarray(getattr(m, "thermal_noise_sd_um_", np.zeros(3)), float)
        keep = [i for i, s in enumerate(self.sensor_names) if s not in self.exclude]
        self._keep = keep
        self.has_load = m.load_ is not None and len(keep) >= 1
        if self.has_load:
            L = m.load_
            G = np.asarray(L["G_um_per_N"])[keep]
            self.C = np.asarray(L["C_um_per_N"])                          # (3 axes, 3 forces)
            self.noise_var = np.asarray(L["noise_var_um2"], float)[keep]
            noise = np.diag(self.noise_var)
            unit = np.asarray(L["thermal_sigma_unit_um2"], float)[np.ix_(keep, keep)]
            self.active = np.asarray(L["active_forces"], bool)
            Ga = G[:, self.active]
            # forces the gratings cannot tell from a warming (not separable) stay unknown
            # nuisances: their signature is absorbed, never read as a load or a contradiction
            nuis = (~self.active) & (np.abs(G).sum(axis=0) > 0)
            Gn = G[:, nuis]
            max_f = np.asarray(L.get("max_force_N", [5000.0] * 3), float)[nuis]
            nuisance_cov = Gn @ np.diag((1.5 * max_f) ** 2) @ Gn.T if nuis.any() else 0.0
            # GLS operators at rest (steps are read against the sensors' noise) and at the
            # training's thermal extreme, s² = 1 (the load part's share of the interval): the
            # gratings' thermal-reading error grows in proportion to the thermal excursion.
            self.step_cov = noise + nuisance_cov
            self.ops = np.zeros((2, 3, len(keep)))
            self.F_sds = np.zeros((2, 3))
            for i, s2 in enumerate((0.0, 1.0)):
                op, cov, _ = gls_operator(Ga, self.step_cov + s2 * unit)
                self.ops[i][self.active] = op
                self.F_sds[i][self.active] = np.sqrt(np.clip(np.diag(cov), 0, None))
            self.F_sd = self.F_sds[0]
            self.G = G
            self.dof = len(keep) - int(self.active.sum())
            self.k_sigma = float(m.load_k_sigma)
            self.p_contra = float(m.contradiction_p)
            self.relative_error = float(m.load_relative_error)
            # no load beyond 1.5x the largest the signature was calibrated with is believed
            self.max_force_N = 1.5 * np.asarray(L.get("max_force_N", [np.inf] * 3), float)
            self.offset_tau_s = float(m.offset_tau_s)
            # a transition ends this long after the load stops, at the mean reading since then
            self.settle_s = float(m.offset_tau_s)
            self.drift_N_per_s = np.asarray(L.get("drift_N_per_s", [0.0] * 3), float)
            self.noise_cov = noise
            self.nuisance_cov = nuisance_cov + np.zeros_like(noise)
        self.map = None
        self.cal = None
        self.last_cal_features = None
        if getattr(m, "twin_map_", None) is not None:
            tm = m.twin_map_
            S = len(self.sensor_names)
            k = len(tm["scale"])
            cols = [i for i in range(k) if i >= S or i in keep]
            coef = (np.asarray(tm["coef"], float) if len(cols) == k else
                    ridge_from_moments(tm["gram"], tm["xty"], tm["scale"], cols, float(m.map_ridge)))
            lo, hi = np.asarray(tm["envelope_low"], float), np.asarray(tm["envelope_high"], float)
            nz = np.asarray(tm.get("noise_gram", np.zeros((k, k))), float)
            self.map_noise_sd_um = np.sqrt(np.clip(np.einsum("ka,kl,la->a", coef, nz, coef), 0, None))
            self.map = {"coef": coef, "low": lo, "high": hi,
                        "G": (np.asarray(m.load_["G_um_per_N"], float) if m.load_ is not None
                              else np.zeros((S, 3)))}
            cal = tm.get("calibration")
            self.cal = None if cal is None else {
                "leads_s": tuple(float(x) for x in cal["leads_s"]), "coef": np.asarray(cal["coef"], float),
                "low": np.asarray(cal["envelope_low"], float), "high": np.asarray(cal["envelope_high"], float)}
        var = self.thermal_resid_var.copy()
        if self.has_load:
            var = var + (self.C ** 2 @ self.F_sds[1] ** 2)
        self.expected_rms_error_um = np.sqrt(var)
        self._t = stats.norm.ppf(0.975)
        self.state = None
        self.last_flags = np.zeros((0, 3), np.uint8)
        self.last_force_N = np.zeros((0, 3))

    def reset(self):
        self.state = None

    def _one_grating(self, y, cov) -> bool:
        """Whether the misfit of the reading ``y`` (S,) is one grating's alone: with some single
        grating left out, the loads re-estimated from the others explain them. That is a fault
        (a fibre slips in its bond, a connector is re-seated) and the step is refused. A misfit
        spread over several gratings is a load or heat the signature does not hold; refusing
        it would leave a stale load applied (on the twin, +1475 N held while -2500 N was on),
        so the step is taken."""
        S = y.size
        Ga = self.G[:, self.active]
        dof = S - 1 - Ga.shape[1]
        if dof < 1:
            return True
        limit = stats.chi2.ppf(1 - self.p_contra, dof)
        for j in range(S):
            keep = np.arange(S) != j
            op, _, _ = gls_operator(Ga[keep], cov[np.ix_(keep, keep)])
            r = y[keep] - Ga[keep] @ (op @ y[keep])
            if r @ np.linalg.lstsq(cov[np.ix_(keep, keep)], r, rcond=None)[0] <= limit:
                return True
        return False

    def _quantile(self, kind, q, dof=None):
        """scipy.stats quantiles the load tracker asks for on every batch, each computed once
        (``chi2``: the ``q`` quantile with ``dof``; ``isf``: the normal's upper ``q``)."""
        cache = self.__dict__.setdefault("_quantiles", {})
        key = (kind, float(q), dof)
        if key not in cache:
            cache[key] = float(stats.chi2.ppf(q, dof) if kind == "chi2" else stats.norm.isf(q))
        return cache[key]

    #: Run stretches without a load transition vectorised (:meth:`_steady_run`); False runs
    #: every frame through the per-frame recursion (the reference the fast path is tested on).
    steady_fast_path = True

    def _steady_run(self, e, dt, applied, offset, xs, f_hold, recent, k_fast, k_start, lag):
        """Frames of :meth:`_track_load` while no load transition is under way, vectorised.

        With the applied force fixed the recursion is linear: the low-passed gratings
        ``y = xs + offset`` follow ``e`` (``LOAD_FAST_S``), the thermal offset follows
        ``e - G applied`` (``offset_tau_s``), the slow force estimate follows the fast one
        (``LOAD_HOLD_S``) and ``recent`` sums the offset's shifts with a ``LOAD_HOLD_S``
        memory. They are formed for every frame, the step test is evaluated on all of them,
        and the frames before the first one whose test fires are accepted. Returns the number
        of frames accepted and the state after them (offset, xs, f_hold, recent)."""
        e = np.asarray(e, float)
        y = _first_order(dt / LOAD_FAST_S, e, xs + offset)
        off = _first_order(dt / self.offset_tau_s, e - self.G @ applied, offset)
        off_prev = np.vstack([offset[None, :], off[:-1]])
        f_fast = (y - off_prev) @ self.ops[0].T
        k = self.k_sigma
        sd_fast = self.F_sd[None, :] * np.sqrt(k_fast)[:, None]
        sq = f_fast ** 2
        cross = self.relative_error * np.sqrt(np.maximum(sq.sum(axis=1, keepdims=True) - sq, 0.0)) / k
        limit = np.maximum(np.hypot(k_start[:, None] * sd_fast, k * lag), k * cross)
        fires = (np.abs(f_fast - applied[None, :]) > limit).any(axis=1)
        m = int(np.argmax(fires)) if fires.any() else len(e)
        if m == 0:
            return 0, offset, xs, f_hold, recent
        hold = _first_order(dt[:m] / LOAD_HOLD_S, f_fast[:m], f_hold)
        shift = off[:m] - off_prev[:m]
        rec = _first_order(dt[:m] / LOAD_HOLD_S, shift, recent, gain=False)
        return m, off[m - 1].copy(), y[m - 1] - off[m - 1], hold[m - 1].copy(), rec[m - 1].copy()

    def _track_load(self, e, time_s, state, new_state, raw=False, listen=False):
        """Applied force per frame (n, 3) N, and the frames where a force was clamped (n,) and
        where a step was refused (n,). ``listen=True`` returns instead the low-passed force
        reading beyond the tracked offset that the step test sees, and takes no step (how
        far heat and noise move it on load-free data calibrates ``drift_N_per_s``).

        On CFRP the gratings are thermometers first: their thermal reading drifts by thousands
        of N of load-equivalent over a day, and no probe predicts it (a radiant load on one face
        is invisible to a probe on another). What tells a load from heat is time: a load arrives
        in seconds, a thermal change takes minutes to hours. So the applied force changes only
        by steps. The gratings beyond their tracked thermal offset are low-passed
        (``LOAD_FAST_S``); a component whose force estimate stands ``load_k_sigma`` clear of the
        applied one, of the drift heat can cause within the offset's tracking time
        (``drift_N_per_s`` x max(``offset_tau_s``, frame interval)) and of the other components'
        cross-talk starts a load transition. Through the transition the component follows the
        low-passed estimate, the offset is frozen, and it ends ``3 offset_tau_s`` after the load
        stopped moving (fast and slow, ``LOAD_HOLD_S``, estimates agree) at the slow estimate.
        Everything the applied force does not explain is tracked as the gratings' thermal offset
        (first order, ``offset_tau_s``). All decisions are on time constants in seconds and on
        the noise the low-pass leaves at the actual frame interval (the training noise taken
        as a density, variance x interval), so the same signal gives the same correction at any
        frame rate and in batches of any size."""
        n, S = e.shape
        state = state or {}
        offset = np.array(state.get("offset", np.zeros(S)), float)
        applied = np.array(state.get("force", np.zeros(3)), float)
        xs = state.get("fast")                           # low-passed e - offset (S,)
        f_hold = state.get("hold")                       # slow estimate of the force (3,)
        mean_sum = np.array(state.get("mean_sum", np.zeros(3)), float)   # since the load stopped
        mean_w = np.array(state.get("mean_w", np.zeros(3)), float)
        # what the offset took in over the last ~LOAD_HOLD_S: a load's first moments, before its
        # step is taken, are given back when it is (else each step leaves ~1 % in the offset)
        recent = np.array(state.get("recent", np.zeros(S)), float)
        t_last = state.get("t")
        t = (np.arange(1, n + 1) * self.nominal_dt_s + (t_last or 0.0) if time_s is None
             else np.asarray(time_s, float).ravel())
        dt = np.diff(np.concatenate([[t[0] if t_last is None else t_last], t]))
        dt = np.clip(dt, 0.0, None)
        first = xs is None
        xs = np.zeros(S) if first else np.array(xs, float)
        f_hold = np.zeros(3) if f_hold is None else np.array(f_hold, float)
        alpha = 1.0 - np.exp(-dt / self.offset_tau_s)
        forget = np.exp(-dt / LOAD_HOLD_S)
        b_fast = 1.0 - np.exp(-dt / LOAD_FAST_S)
        b_hold = 1.0 - np.exp(-dt / LOAD_HOLD_S)
        # variance left by a first-order low-pass of white noise, per unit of the training
        # frame's variance: (nominal / dt) b / (2 - b); 1 for a frame without history
        rate = self.nominal_dt_s / np.where(dt > 0, dt, self.nominal_dt_s)
        k_fast = np.where(dt > 0, rate * b_fast / (2.0 - b_fast), 1.0)
        k_hold = np.where(dt > 0, rate * b_hold / (2.0 - b_hold), 1.0)
        lag = self.drift_N_per_s[None, :] * np.maximum(dt, self.offset_tau_s)[:, None]
        op = self.ops[0]
        Ga = self.G
        force = np.zeros((n, 3))
        clamped = np.zeros(n, bool)
        settle = np.array(state.get("settle", np.zeros(3)), float)   # s left of a load transition
        refused = np.zeros(n, bool)
        act = self.active
        chi2_limit = self._quantile("chi2", 1 - self.p_contra, max(self.dof, 1))
        k = self.k_sigma
        look_s, at = np.unique(np.maximum(dt, 2.0 * LOAD_FAST_S), return_inverse=True)
        k_start = np.maximum(k, np.array([self._quantile("isf", 0.5 * LOAD_FALSE_STARTS_PER_H * s / 3600.0)
                                          for s in look_s])[at.ravel()] if n else np.zeros(0))
        i, slow_until = -1, 0
        while i + 1 < n:
            i += 1
            if (self.steady_fast_path and i >= slow_until and not (raw or listen or (first and i == 0))
                    and not (settle > 0).any()):
                # No transition under way: the recursion is linear until the first frame whose
                # step test fires, so run it vectorised up to that frame, at most STEADY_WINDOW
                # frames at a time (equal to the per-frame recursion to rounding, not bit for
                # bit: tests/test_physical.py). Where a test fires at once (a refused step
                # repeating), the next STEADY_BACKOFF frames go through the recursion.
                w = slice(i, min(i + STEADY_WINDOW, n))
                m, offset, xs, f_hold, recent = self._steady_run(
                    e[w], dt[w], applied, offset, xs, f_hold, recent, k_fast[w], k_start[w], lag[w])
                force[i:i + m] = applied
                if m == 0:
                    slow_until = i + STEADY_BACKOFF
                i += m
                if i >= n:
                    break
                if m == w.stop - w.start:       # the window ran out before any test fired
                    i -= 1
                    continue
            x_now = e[i] - offset
            if raw:
                force[i] = op @ x_now
                continue
            if first and i == 0:
                xs = x_now.copy()
                f_hold = op @ xs
            else:
                xs += b_fast[i] * (x_now - xs)
            f_fast = op @ xs
            f_hold += b_hold[i] * (f_fast - f_hold)
            if listen:
                force[i] = f_fast - applied
                shift = alpha[i] * (e[i] - Ga @ applied - offset)
                offset += shift
                xs -= shift
                continue
            sd_fast = self.F_sd * np.sqrt(k_fast[i])
            other = np.sqrt(np.maximum((f_fast ** 2).sum() - f_fast ** 2, 0.0))
            cross = self.relative_error * other / k
            moving = settle > 0
            step = f_fast - applied
            # noise is judged at the false-start rate; the drift allowance (already a 99th
            # percentile of what heat did in training) and cross-talk at k sigma
            limit = np.maximum(np.hypot(k_start[i] * sd_fast, k * lag[i]), k * cross)
            take = (~moving) & (np.abs(step) > limit)
            if take.any() and self.dof >= 1:
                # a step no load explains (one grating jumps: a fibre slips, a connector is
                # re-seated) is refused, and the offset absorbs it
                new = np.where(take | moving, f_fast, applied)   # moving ones follow too
                r = xs - Ga @ new
                g = self.relative_error * (Ga[:, act] @ (new - applied)[act])
                cov = self.noise_cov * k_fast[i] + self.nuisance_cov + np.outer(g, g)
                if r @ np.linalg.lstsq(cov, r, rcond=None)[0] > chi2_limit and self._one_grating(xs, cov):
                    refused[i] = True
                    take[:] = False
            if take.any():
                if not (settle > 0).any():
                    offset -= recent
                    xs += recent
                    f_fast = op @ xs
                    recent[:] = 0.0
                settle = np.where(take, self.settle_s, settle)
                f_hold = np.where(take, f_fast, f_hold)
            moving = settle > 0
            if moving.any():
                # in a transition: follow the low-passed force; still moving while the fast and
                # slow estimates disagree beyond their noise
                sd_hold = self.F_sd * np.sqrt(k_hold[i])
                still = moving & (np.abs(f_fast - f_hold)
                                  > k * np.maximum(np.hypot(sd_fast, sd_hold), cross))
                settle = np.where(still, self.settle_s, settle)
                mean_sum = np.where(still, 0.0, mean_sum + dt[i] * f_fast)
                mean_w = np.where(still, 0.0, mean_w + dt[i])
                applied = np.where(moving, f_fast, applied)
                settle = np.maximum(settle - dt[i], 0.0)
                ended = moving & (settle <= 0) & (mean_w > 0)
                applied = np.where(ended, mean_sum / np.where(mean_w > 0, mean_w, 1.0), applied)
                mean_sum = np.where(moving & ~(settle > 0), 0.0, mean_sum)
                mean_w = np.where(moving & ~(settle > 0), 0.0, mean_w)
            big = np.abs(applied) > self.max_force_N
            if big.any():
                clamped[i] = True
                applied = np.clip(applied, -self.max_force_N, self.max_force_N)
            if not (settle > 0).any():
                shift = alpha[i] * (e[i] - Ga @ applied - offset)
                offset += shift
                xs -= shift                        # xs is relative to the offset
                recent = recent * forget[i] + shift
            force[i] = applied
        new_state["load"] = {"offset": offset, "force": applied, "settle": settle, "fast": xs,
                             "hold": f_hold, "mean_sum": mean_sum, "mean_w": mean_w, "recent": recent,
                             "t": float(t[-1]) if n else t_last}
        return force, clamped, refused

    def predict(self, wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C, *,
                time_s=None, z_axis_mm=None, raw=False, thermal_policy=True):
        """Applied TTP deviation (n, 3) µm and 95 % half-width (n, 3) µm; ``raw=True`` skips
        the policy (envelope clipping, axis clamp, load gating) for diagnosis."""
        wl = np.atleast_2d(np.asarray(wavelength_nm, dtype=float))
        n = wl.shape[0]
        flags = np.zeros((n, 3), np.uint8)
        state = self.state or {}
        new_state = {}
        dT = np.atleast_2d(np.asarray(temperature_C, float)) - np.asarray(temperature_zero_C, float)
        w = wl.copy()
        w0 = np.asarray(wavelength_zero_nm, float)
        lost = [i for i, s in enumerate(self.sensor_names) if s in self.exclude]
        w[:, lost] = w0[lost]
        e_all = self._fmap.base(w, temperature_C, w0, temperature_zero_C)
        load = np.zeros((n, 3))
        force = np.zeros((n, 3))
        if self.has_load:
            force, clamped, refused = self._track_load(e_all[:, self._keep], time_s, state.get("load"),
                                                       new_state, raw)
            flags[clamped] |= P.CLAMPED
            flags[refused] |= P.LOAD_REFUSED
            load = force @ self.C.T
        if self.map is not None:
            # the gratings minus the load read from them are thermometers of their gauges
            e_th = e_all - force @ self.map["G"].T
            e_th[:, lost] = 0.0
            X, new_state["map"] = map_features(e_th, dT, self._h_idx, time_s, state.get("map"),
                                               self.nominal_dt_s)
            activity = X[:, -len(MAP_LEADS_S)]          # the housing's fastest lead, K
            L = None
            if self.cal is not None:
                S = len(self.sensor_names)
                smooth = X[:, S:S + len(self.probe_names)]
                new_state["cal"] = {}
                housing = housing_mean(smooth, self._h_idx)
                L = np.hstack([housing, housing_leads(housing, self.cal["leads_s"], time_s, state.get("cal", {}),
                                                      new_state["cal"], self.nominal_dt_s)])
            self.last_cal_features = L
            if raw or not thermal_policy:
                thermal = X @ self.map["coef"]
                if L is not None:
                    thermal = thermal + L @ self.cal["coef"]
            else:
                Xc, outside = P.clip_to_envelope(X, self.map["low"], self.map["high"], self.margin)
                thermal = Xc @ self.map["coef"]
                if L is not None:
                    Lc, out_l = P.clip_to_envelope(L, self.cal["low"], self.cal["high"], self.margin)
                    thermal = thermal + Lc @ self.cal["coef"]
                    outside = outside | out_l
                # what the sensors' noise alone would make of the map is not applied
                thermal = P.firm(thermal, self.map_noise_sd_um, self.k_sigma, 2 * self.k_sigma)
                thermal, clamped = P.clamp_axes(thermal, self.t_low, self.t_high)
                flags[outside] |= P.SHRUNK
                flags[clamped] |= P.CLAMPED
        else:
            # no twin: the housing fit on the measured load-free campaigns
            H, new_state["h"] = thermal_regressors(dT, self._h_idx, self._a_idx, self.lead_tau_s, time_s,
                                                   state.get("h"), self.nominal_dt_s)
            activity = H[:, -1] if self._h_idx else np.zeros(n)
            if raw or not thermal_policy:
                thermal = H @ self.A
            else:
                Hc, outside = P.clip_to_envelope(H[:, 1:], self.h_low, self.h_high, self.margin)
                Hc = np.hstack([H[:, :1], Hc])
                thermal = P.firm(Hc @ self.A, self.thermal_noise_sd_um, self.k_sigma, 2 * self.k_sigma)
                thermal, clamped = P.clamp_axes(thermal, self.t_low, self.t_high)
                flags[outside] |= P.SHRUNK
                flags[clamped] |= P.CLAMPED
        self.state = new_state
        self.last_flags = flags
        self.last_force_N = force
        deviation = thermal + load
        self.last_activity = activity
        return deviation, self._t * np.sqrt(self._variance(dT, activity, force))

    def _variance(self, dT, activity, force):
        """Predictive variance (n, 3) µm²: the thermal part's error at the current thermal
        excursion, plus, while a load is applied, the force estimate's noise and the signature's
        relative error through the compliance."""
        n = dT.shape[0]
        if self.interval is None:
            return self.expected_rms_error_um[None, :] ** 2 + np.zeros((n, 3))
        iv = self.interval
        s2 = excursion2(dT, iv["scale"], iv["deadband"])
        a2 = (np.asarray(activity, float) / iv["activity_scale"]) ** 2
        var = (iv["v0"][None, :] + iv["vs"][None, :] * np.sqrt(s2)[:, None] + iv["v1"][None, :] * s2[:, None]
               + iv["v2"][None, :] * a2[:, None])
        if self.has_load:
            on = (force != 0.0).astype(float)                       # components applied
            var = var + (on * self.F_sds[1] ** 2) @ (self.C ** 2).T + (self.relative_error * force @ self.C.T) ** 2
        return var


# ---------------------------------------------------------------------------------------------
# Model file shapes
# ---------------------------------------------------------------------------------------------
def _check_shapes(d: dict, source) -> None:
    """Every array of a physical model file has the shape its sensors and probes imply, and the
    sensor and probe names are distinct strings; InputError naming the first field that does not."""
    def need(cond, field, what):
        if not cond:
            raise InputError(what, file=source, column=f"field {field}")

    def array(node, field, shape):
        try:
            a = np.asarray(node, dtype=float)
        except (TypeError, ValueError):
            raise InputError("not an array of numbers", file=source, column=f"field {field}") from None
        need(a.shape == tuple(shape), field, f"shape {a.shape} where {tuple(shape)} is expected")
        return a

    def names(node, field):
        need(isinstance(node, list) and all(isinstance(x, str) for x in node), field, "must be a list of names")
        need(len(set(node)) == len(node), field, "names must be distinct")
        return node

    need(isinstance(d.get("sensors"), list) and d["sensors"]
         and all(isinstance(x, dict) for x in d["sensors"]), "sensors", "must be a non-empty list of sensors")
    sensor_names = names([x.get("name") for x in d["sensors"]], "sensors")
    probes = names(d.get("probes"), "probes")
    for key in ("housing_probes", "ambient_probes"):
        got = names(d.get(key), key)
        need(all(p in probes for p in got), key, "names a probe the model does not read")
    S, P = len(sensor_names), len(probes)
    nh = 1 + len(d["housing_probes"]) + len(d["ambient_probes"]) + (1 if d["housing_probes"] else 0)
    need(isinstance(d.get("nominal_dt_s"), (int, float)) and not isinstance(d["nominal_dt_s"], bool)
         and d["nominal_dt_s"] > 0, "nominal_dt_s", "must be a positive number")
    th = d.get("thermal")
    need(isinstance(th, dict), "thermal", "must be a mapping")
    array(th.get("coef"), "thermal.coef", (nh, 3))
    for key in ("envelope_low", "envelope_high"):
        array(th.get(key), f"thermal.{key}", (nh - 1,))
    for key in ("range_low_um", "range_high_um", "resid_sd_um"):
        array(th.get(key), f"thermal.{key}", (3,))
    need(np.all(np.asarray(th["resid_sd_um"], float) >= 0), "thermal.resid_sd_um", "must be >= 0")
    if "noise_sd_um" in th:
        array(th["noise_sd_um"], "thermal.noise_sd_um", (3,))
    L = d.get("load")
    if L is not None:
        need(isinstance(L, dict), "load", "must be a mapping or null")
        for key, shape in (("G_um_per_N", (S, 3)), ("C_um_per_N", (3, 3)), ("grating_thermal_coef", (nh, S)),
                           ("thermal_sigma_unit_um2", (S, S)), ("thermal_scale", (P,)),
                           ("noise_var_um2", (S,)), ("active_forces", (3,))):
            array(L.get(key), f"load.{key}", shape)
        for key in ("max_force_N", "drift_N_per_s"):
            if key in L:
                array(L[key], f"load.{key}", (3,))
        need(np.all(np.asarray(L["noise_var_um2"], float) >= 0), "load.noise_var_um2", "must be >= 0")
    iv = d.get("interval")
    if iv is not None:
        need(isinstance(iv, dict), "interval", "must be a mapping or null")
        # vs_um2 is absent from files written before the interval's linear term
        for key in ("v0_um2", "v1_um2", "v2_um2") + (("vs_um2",) if "vs_um2" in iv else ()):
            need(np.all(array(iv.get(key), f"interval.{key}", (3,)) >= 0), f"interval.{key}", "must be >= 0")
        need(np.all(array(iv.get("dT_scale_K"), "interval.dT_scale_K", (P,)) > 0), "interval.dT_scale_K",
             "must be > 0")
        if "deadband_K" in iv:
            array(iv["deadband_K"], "interval.deadband_K", (P,))
        a = iv.get("activity_scale_K")
        need(isinstance(a, (int, float)) and not isinstance(a, bool) and a > 0, "interval.activity_scale_K",
             "must be a positive number")
    tm = d.get("twin_map")
    if tm is not None:
        need(isinstance(tm, dict), "twin_map", "must be a mapping or null")
        k = S + P + len(MAP_LEADS_S)
        for key, shape in (("coef", (k, 3)), ("gram", (k, k)), ("xty", (k, 3)), ("scale", (k,)),
                           ("noise_gram", (k, k)), ("envelope_low", (k,)), ("envelope_high", (k,))):
            array(tm.get(key), f"twin_map.{key}", shape)
        need(np.all(np.asarray(tm["scale"], float) > 0), "twin_map.scale", "must be > 0")
        cal = tm.get("calibration")
        if cal is not None:
            need(isinstance(cal, dict), "twin_map.calibration", "must be a mapping or null")
            leads = array(cal.get("leads_s"), "twin_map.calibration.leads_s", (len(cal.get("leads_s") or []),))
            need(leads.size > 0 and np.all(leads > 0), "twin_map.calibration.leads_s",
                 "must be positive time constants")
            array(cal.get("coef"), "twin_map.calibration.coef", (1 + leads.size, 3))
            for key in ("envelope_low", "envelope_high"):
                array(cal.get(key), f"twin_map.calibration.{key}", (1 + leads.size,))


# ---------------------------------------------------------------------------------------------
# Estimator
# ---------------------------------------------------------------------------------------------
class PhysicalModel(EstimatorParams, ModelFile):
    """Load-signature + housing-thermal model with a do-no-harm policy (the default model).

    Parameters
    ----------
    machine : Machine, path or None
        Machine description; used to find the housing and ambient probes and, when no training
        campaign carries loads, for the FE twin's load signature.
    zero_window_s : float
        Zero state = mean of each signal's first ``zero_window_s`` seconds.
    lead_tau_s : float
        Time constant of the housing probe's thermal lead term, s.
    envelope_margin : float
        Fraction of the training span by which thermal regressors may leave the training
        envelope before they are clipped.
    load_k_sigma : float
        A force component is applied only when it stands ``load_k_sigma`` standard deviations
        clear of zero (firm shrinkage: zero below, a linear ramp up to twice that, unbiased beyond).
    contradiction_p : float
        Per-frame false-alarm probability of the gratings' consistency test.
    load_relative_error : float
        Relative error of the load signature: a force component smaller than this share of the
        others (x k_sigma) may be their cross-talk and is not applied.
    thermal_error_inflation : float
        Factor on the variance of the gratings' thermal-reading error seen in training (what a
        held-out campaign adds to the in-sample residual).
    twin_scenarios : int
        Generic thermal scenarios of the machine's FE twin the thermal map learns from (0: fit
        the thermal part on the measured load-free campaigns instead, as without a machine).
    map_ridge : float
        Ridge penalty of the twin-learned thermal map (standardised features).
    offset_tau_s : float
        Time constant with which the gratings' unexplained thermal reading is tracked while no
        load is applied, s.
    calibrate_housing : bool
        Calibrate the twin map's housing transient (its leads at ``CAL_LEADS_S``) on the
        measured load-free campaigns (:meth:`_calibrate_housing`).
    separability_cos : float
        A force whose grating signature has |cos| above this with the gratings' warming pattern
        is not read from the gratings.
    """

    model_type = "physical"

    def __init__(self, machine=None, zero_window_s=10.0, lead_tau_s=300.0, envelope_margin=0.1,
                 load_k_sigma=3.0, contradiction_p=1e-3, thermal_error_inflation=4.0,
                 load_relative_error=0.03, twin_scenarios=40, map_ridge=1e-3, separability_cos=0.95,
                 offset_tau_s=20.0, calibrate_housing=True):
        self.machine = machine
        self.zero_window_s = zero_window_s
        self.lead_tau_s = lead_tau_s
        self.envelope_margin = envelope_margin
        self.load_k_sigma = load_k_sigma
        self.contradiction_p = contradiction_p
        self.thermal_error_inflation = thermal_error_inflation
        self.load_relative_error = load_relative_error
        self.twin_scenarios = twin_scenarios
        self.map_ridge = map_ridge
        self.separability_cos = separability_cos
        self.offset_tau_s = offset_tau_s
        self.calibrate_housing = calibrate_housing

    # -- fitting -----------------------------------------------------------------------------
    def _machine(self):
        if self.machine is None:
            return None
        from fbgcomp.structure import Machine, load_machine

        return self.machine if isinstance(self.machine, Machine) else load_machine(self.machine)

    def fit(self, X, y=None, *, progress=None):
        if y is not None:
            raise ValueError("PhysicalModel fits on campaigns (y must be None)")
        campaigns = _as_campaign_list(X)
        if not campaigns:
            raise ValueError("fit needs at least one campaign")
        machine = self._machine()
        first = campaigns[0]
        self.sensors_ = list(first.meta.sensors)
        common = [p for p in first.meta.probe_names
                  if all(p in c.meta.probe_names for c in campaigns[1:])]
        self.housing_probes_ = _housing_probe_names(common, machine)
        self.ambient_probes_ = _ambient_probe_names(common, machine)
        sensor_probes = [s.temperature_probe for s in self.sensors_ if s.temperature_probe]
        self.probe_names_ = list(dict.fromkeys(sensor_probes + self.housing_probes_ + self.ambient_probes_))
        for c in campaigns:
            check_compatible(self, c)
        aligned = [c.aligned(zero_window_s=self.zero_window_s) for c in campaigns]
        dts = [np.median(np.diff(a.time_s)) for a in aligned if len(a.time_s) > 1]
        self.nominal_dt_s_ = float(np.median(dts)) if dts else 1.0
        fmap = _grating_map(self.sensors_, self.probe_names_)

        # Per campaign: instrument arrays in model order, elongations, thermal regressors.
        self.load_ = None
        self.interval_ = None
        self.thermal_coef_ = np.zeros((1, 3))
        self.thermal_envelope_ = (np.zeros(0), np.zeros(0))
        self.thermal_range_um_ = (np.zeros(3), np.zeros(3))
        self.thermal_resid_sd_um_ = np.zeros(3)
        rows = []
        for c, a in zip(campaigns, aligned):
            w, t, w0, t0 = self.instrument_arrays(a)
            e = fmap.base(w, t, w0, t0)
            H, _ = thermal_regressors(t - t0, [self.probe_names_.index(p) for p in self.housing_probes_],
                                      [self.probe_names_.index(p) for p in self.ambient_probes_],
                                      self.lead_tau_s, a.time_s)
            F = a.loads_N
            loaded = F is not None and np.nanmax(np.abs(np.nan_to_num(F))) > 50.0
            rows.append({"name": c.meta.name, "e": e, "H": H, "dT": t - t0, "t": a.time_s, "y": a.reference_um,
                         "F": None if F is None else np.nan_to_num(F), "loaded": loaded})
        thermal_rows = [r for r in rows if not r["loaded"]]
        loaded_rows = [r for r in rows if r["loaded"]]
        nh = rows[0]["H"].shape[1]
        S = len(self.sensor_names)

        # Gratings' thermal reading vs the thermal regressors, on load-free campaigns.
        if thermal_rows:
            Hs = np.vstack([r["H"] for r in thermal_rows])
            Es = np.vstack([r["e"] for r in thermal_rows])
            ws = np.concatenate([np.full(len(r["H"]), 1.0 / len(r["H"])) for r in thermal_rows])
            B, _ = weighted_lstsq(Hs, Es, ws)
            dTs = np.vstack([r["dT"] for r in thermal_rows])
            scale = np.maximum(np.abs(dTs).max(axis=0), 0.5)
            s2 = np.sum((dTs / scale) ** 2, axis=1)
            R = Es - Hs @ B
            # error covariance per unit of s²: weighted regression through the origin of the
            # residual products on s², so the uncertainty grows with the thermal excursion
            wn = ws * s2 / np.sum(ws * s2 * s2)
            cov_unit = (R * wn[:, None]).T @ R
        else:
            B, cov_unit = np.zeros((nh, S)), np.zeros((S, S))
            scale = np.ones(len(self.probe_names_))

        # Load signature G and compliance C from loaded campaigns (per-campaign intercepts).
        G = C = None
        max_force = np.full(3, 5000.0)
        active = np.zeros(3, bool)
        noise_var = np.full(S, np.nan)
        if loaded_rows:
            Xs, Es_, Ys, ws_ = [], [], [], []
            k = len(loaded_rows)
            for i, r in enumerate(loaded_rows):
                n = len(r["e"])
                onehot = np.zeros((n, k))
                onehot[:, i] = 1.0
                Xs.append(np.hstack([onehot, r["F"], r["H"][:, 1:]]))
                Es_.append(r["e"])
                Ys.append(r["y"])
                ws_.append(np.full(n, 1.0 / n))
            X = np.vstack(Xs)
            w_all = np.concatenate(ws_)
            Fall = X[:, k:k + 3]
            active = np.sqrt(np.average(Fall ** 2, axis=0, weights=w_all)) > 100.0
            cols = list(range(k)) + [k + j for j in range(3) if active[j]] + list(range(k + 3, X.shape[1]))
            Bg, _ = weighted_lstsq(X[:, cols], np.vstack(Es_), w_all)
            By, _ = weighted_lstsq(X[:, cols], np.vstack(Ys), w_all)
            G = np.zeros((S, 3))
            C = np.zeros((3, 3))
            G[:, active] = Bg[k:k + active.sum()].T
            C[:, active] = By[k:k + active.sum()].T
            # white noise of each grating from successive differences (robust: MAD), so load
            # steps and ramps do not count as noise
            diffs = np.vstack([np.diff(r["e"], axis=0) for r in loaded_rows])
            mad = np.median(np.abs(diffs - np.median(diffs, axis=0)), axis=0)
            noise_var = (1.4826 * mad) ** 2 / 2.0
            # a component the training never excited (its column is load-cell noise) is
            # believed over the range of those it did: its signature comes from the twin
            max_force = np.abs(Fall).max(axis=0)
            max_force = np.where(active, max_force, max_force[active].max() if active.any() else 5000.0)
            source = "training campaigns with loads"
        if G is None or not active.all():
            twin_GC = self._twin_signature(machine)
            if twin_GC is not None:
                Gt, Ct = twin_GC
                if G is None:
                    G, C = Gt, Ct
                    source = "FE twin of the machine description"
                else:
                    G[:, ~active], C[:, ~active] = Gt[:, ~active], Ct[:, ~active]
                    source += " (unexcited components from the FE twin)"
                active = np.ones(3, bool)
        separable = np.ones(3, bool)
        if G is not None and thermal_rows:
            # A force whose signature is (nearly) the gratings' own warming pattern cannot be
            # told from a temperature change (on CFRP rams: Fz, a uniform compression, against
            # a uniform warming); it is not read from the gratings at all.
            u = np.linalg.svd(np.vstack([r["e"] for r in thermal_rows]), full_matrices=False)[2][0]
            norm = np.linalg.norm(G, axis=0)
            cos = np.abs(u @ G) / np.where(norm > 0, norm, 1.0)
            separable = cos < self.separability_cos
            active = active & separable
        if G is not None and active.any():
            if np.isnan(noise_var).any():
                noise_var = np.full(S, 0.05 ** 2)
            self.load_ = {"G_um_per_N": G.tolist(), "C_um_per_N": C.tolist(),
                          "active_forces": active.tolist(), "grating_thermal_coef": B.tolist(),
                          "thermal_sigma_unit_um2": (self.thermal_error_inflation * cov_unit).tolist(),
                          "thermal_scale": scale.tolist(), "noise_var_um2": noise_var.tolist(),
                          "max_force_N": np.where(max_force > 0, max_force, 5000.0).tolist(),
                          "source": source,
                          "not_separable": [f for f, ok in zip(_FORCE_AXES, separable) if not ok]}
        # Thermal part of the TTP: y minus the (policy-applied) load part, on load-free campaigns.
        self.thermal_coef_ = np.zeros((nh, 3))
        self.thermal_envelope_ = (np.zeros(nh - 1), np.zeros(nh - 1))
        self.thermal_range_um_ = (np.zeros(3), np.zeros(3))
        self.thermal_resid_sd_um_ = np.full(3, 0.1)
        self.thermal_noise_sd_um_ = np.zeros(3)
        if thermal_rows:
            Hs = np.vstack([r["H"] for r in thermal_rows])
            Ys = np.vstack([r["y"] for r in thermal_rows])
            ws = np.concatenate([np.full(len(r["H"]), 1.0 / len(r["H"])) for r in thermal_rows])
            A, cov_y = weighted_lstsq(Hs, Ys, ws)
            self.thermal_coef_ = A
            self.thermal_envelope_ = (Hs[:, 1:].min(axis=0), Hs[:, 1:].max(axis=0))
            fitted = Hs @ A
            span = np.abs(Ys).max(axis=0)
            self.thermal_range_um_ = (np.minimum(fitted.min(axis=0), Ys.min(axis=0)) - 0.1 * span,
                                      np.maximum(fitted.max(axis=0), Ys.max(axis=0)) + 0.1 * span)
            self.thermal_resid_sd_um_ = np.sqrt(np.diag(cov_y))
            # the part's response to probe noise (the zero state itself is one noisy reading of
            # a slow probe): each regressor's probe noise (robust, from successive differences)
            # through its coefficient
            d = np.vstack([np.diff(r["dT"], axis=0) for r in rows if len(r["dT"]) > 1])
            sd_p = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(2)
            used = [self.probe_names_.index(q) for q in self.housing_probes_ + self.ambient_probes_]
            sd_h = np.concatenate([sd_p[used], sd_p[used[:1]] if self.housing_probes_ else []])
            self.thermal_noise_sd_um_ = np.sqrt(((A[1:] * np.asarray(sd_h)[:, None]) ** 2).sum(axis=0))
        # Thermal part learned from the twin's thermal physics, when the machine describes
        # every grating and probe of the campaigns (the face-gradient coefficients no measured
        # campaign without a gradient can teach).
        self.twin_map_ = None
        if machine is not None and self.twin_scenarios > 0:
            pop = twin_thermal_population(machine, self.sensors_, self.probe_names_, self.housing_probes_,
                                          n_scenarios=self.twin_scenarios, seed=0)
            if pop is not None:
                pop["coef"] = ridge_from_moments(pop["gram"], pop["xty"], pop["scale"],
                                                 range(len(pop["scale"])), self.map_ridge).tolist()
                self.twin_map_ = pop
        # Load-part uncertainty calibrated on loaded campaigns: the load part's residual.
        self.training_ = {"campaigns": [{"name": r["name"], "loaded": bool(r["loaded"]),
                                         "n_samples": int(len(r["y"]))} for r in rows],
                          "n_samples": int(sum(len(r["y"]) for r in rows))}
        self._predictors = {}
        if self.load_ is not None:
            self._calibrate_drift(rows)
        if self.twin_map_ is not None and thermal_rows and self.housing_probes_ and self.calibrate_housing:
            self.twin_map_["calibration"] = self._calibrate_housing(rows, campaigns)
            self._predictors = {}
        if self.twin_map_ is not None and thermal_rows:
            # the map's error on the measured load-free campaigns (only the housing transient is
            # fitted there)
            # sets its interval and widens the validated range to what the twin covers
            res = []
            for r, c in zip(rows, campaigns):
                if r["loaded"]:
                    continue
                pred, _ = self.predict_interval(c, policy=False)
                res.append(pred - r["y"])
            res = np.vstack(res)
            self.thermal_resid_sd_um_ = np.sqrt(np.mean(res ** 2, axis=0))
            lo, hi = np.asarray(self.twin_map_["ttp_low_um"]), np.asarray(self.twin_map_["ttp_high_um"])
            span = hi - lo
            self.thermal_range_um_ = (np.minimum(self.thermal_range_um_[0], lo - 0.1 * span),
                                      np.maximum(self.thermal_range_um_[1], hi + 0.1 * span))
        self.interval_ = self._fit_interval(rows, campaigns) if thermal_rows else None
        self._predictors = {}
        return self

    def _calibrate_housing(self, rows, campaigns):
        """Least squares (no intercept, campaigns weighted equally) of the twin map's error on
        the measured load-free campaigns against the housing's mean ΔT (K) and its leads at
        ``CAL_LEADS_S`` (K).

        How late the housing probe sees the bearings' heat depends on where the bearings and
        the probe sit in the steel, which a data sheet rarely gives to the millimetre; every
        spindle duty cycle excites it, so the measured campaigns can teach it. The face-gradient
        coefficients stay the twin's (no campaign without a gradient can teach them)."""
        k = 1 + len(CAL_LEADS_S)
        # the map as it stands, with the leads computed alongside (zero coefficients)
        self.twin_map_["calibration"] = {"leads_s": list(CAL_LEADS_S), "coef": np.zeros((k, 3)).tolist(),
                                         "envelope_low": [-1e9] * k, "envelope_high": [1e9] * k}
        self._predictors = {}
        A_rows, b_rows, feats = [], [], []
        for r, c in zip(rows, campaigns):
            if r["loaded"]:
                continue
            pred, _, p, at = self._served(c, policy=False)
            L = p.last_cal_features[at]
            w = np.sqrt(1.0 / len(L))
            A_rows.append(L * w)
            b_rows.append((r["y"] - pred) * w)
            feats.append(L)
        A, b = np.vstack(A_rows), np.vstack(b_rows)
        coef = np.linalg.lstsq(A, b, rcond=None)[0]
        L = np.vstack(feats)
        return {"leads_s": list(CAL_LEADS_S), "coef": coef.tolist(), "source": "measured load-free campaigns",
                "envelope_low": L.min(axis=0).tolist(), "envelope_high": L.max(axis=0).tolist()}

    def _fit_interval(self, rows, campaigns):
        """Thermal part's error variance as v0 + vs s + v1 s² + v2 a², s² the squared probe
        excursion (:func:`excursion2`) and a the housing's fastest lead (a transient) over its
        training maximum, per axis.

        v0 is the reference instrument's own noise, measured on the training campaigns (robust
        SD of successive differences, the quietest campaign): a machine at rest and zeroed has
        no thermal error, so its interval is the interferometer's. vs, v1 and v2 come from
        non-negative least squares of the applied prediction's squared error beyond v0 on each
        load-free training campaign (campaigns weighted equally): what grows with the thermal
        state and its transients."""
        from scipy.optimize import nnls

        dTs = [r["dT"] for r in rows if not r["loaded"]]
        scale = np.maximum(np.abs(np.vstack(dTs)).max(axis=0), 0.5)
        sd_ref = []
        for r in rows:
            d = np.diff(r["y"], axis=0)
            if len(d) > 10:
                sd_ref.append(1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(2))
        v0 = np.min(sd_ref, axis=0) ** 2 if sd_ref else np.zeros(3)
        # dT is a reading minus the zero reading: a change within twice the SD of such a
        # difference (the SD of successive readings' differences; quantised probes make a
        # robust MAD of them read low) is none
        d = np.vstack([np.diff(r["dT"], axis=0) for r in rows if len(r["dT"]) > 1])
        deadband = 2.0 * d.std(axis=0)
        e2, S, act, w = [], [], [], []
        for r, c in zip(rows, campaigns):
            if r["loaded"]:
                continue
            pred, _, p, at = self._served(c)
            e2.append((pred - r["y"]) ** 2)
            S.append(excursion2(r["dT"], scale, deadband))
            act.append(p.last_activity[at])
            w.append(np.full(len(pred), 1.0 / len(pred)))          # campaigns weighted equally
        e2, s2, act, w = np.vstack(e2), np.concatenate(S), np.concatenate(act), np.concatenate(w)
        a_scale = max(float(np.abs(act).max()), 1e-3)
        A = np.column_stack([np.sqrt(s2), s2, (act / a_scale) ** 2])
        sw = np.sqrt(w)[:, None]
        v = np.array([nnls(A * sw, (e2[:, j] - v0[j]) * sw[:, 0])[0] for j in range(3)])   # (axes, [vs, v1, v2])
        # The errors are not Gaussian (heavy tails from the transients): scale the state terms
        # so that the 95 % interval covers 95 % of the training samples (campaigns weighted
        # equally), v0 staying the instrument's. A sample is covered for every scale from
        # (e² / z² - v0) / (its state variance) up: the scale is the weighted 95th percentile of
        # that, within [1e-3, 1e3].
        z2 = stats.norm.ppf(0.975) ** 2
        shape = A @ v.T                                                  # (n, 3) state variance
        for j in range(3):
            if not np.any(shape[:, j] > 0):
                continue
            with np.errstate(divide="ignore", invalid="ignore"):
                need = np.where(e2[:, j] / z2 <= v0[j], 0.0, (e2[:, j] / z2 - v0[j]) / shape[:, j])
            order = np.argsort(need)
            # (a share of exactly 0.95 counts as reached: the cumulative sum's rounding must not
            # push the level to the next sample)
            at = np.searchsorted(np.cumsum(w[order]) / w.sum(), 0.95 - 1e-12)
            v[j] *= np.clip(need[order][min(at, len(order) - 1)], 1e-3, 1e3)
        return {"v0_um2": v0.tolist(), "vs_um2": v[:, 0].tolist(), "v1_um2": v[:, 1].tolist(),
                "v2_um2": v[:, 2].tolist(), "dT_scale_K": scale.tolist(), "deadband_K": deadband.tolist(),
                "activity_scale_K": a_scale}

    def _calibrate_drift(self, rows):
        """How far heat (and noise) move the force reading the step test sees, on the load-free
        training campaigns: the 99th percentile of its magnitude with the tracker listening
        (no step taken), per component, stored as a rate over the offset's tracking time
        (``drift_N_per_s`` x max(``offset_tau_s``, frame interval) is the allowance; floor
        0.1 N/s). A step must stand ``load_k_sigma`` times clear of it. (Frame-to-frame rates,
        as before, measured the noise: 622 N/s on the twin, and no load was ever applied.)"""
        p = self.predictor()
        seen = [np.zeros((0, 3))]
        for r in rows:
            if r["loaded"] or len(r["t"]) < 3:
                continue
            F, _, _ = p._track_load(r["e"][:, p._keep], r["t"], None, {}, listen=True)
            seen.append(np.abs(F))
        seen = np.vstack(seen)
        q = np.quantile(seen, 0.99, axis=0) if len(seen) else np.full(3, 20.0)
        span = max(float(self.offset_tau_s), float(self.nominal_dt_s_))
        self.load_["drift_N_per_s"] = np.maximum(q / span, 0.1).tolist()
        self._predictors = {}

    def _twin_signature(self, machine):
        """(G, C) from the FE twin, or None without a machine description or a matching sensor set."""
        if machine is None:
            return None
        names = [s.name for s in machine.sensors]
        if any(s not in names for s in self.sensor_names):
            return None
        from fbgcomp.structure import Twin

        twin = Twin(machine)
        inf = twin.influence
        idx = [names.index(s) for s in self.sensor_names]
        return np.asarray(inf.sensor_per_force_um_per_N)[idx], np.asarray(inf.ttp_per_force_um_per_N)

    # -- prediction --------------------------------------------------------------------------
    @property
    def fallback_sets(self) -> list:
        names = self.sensor_names
        out = []
        for k in range(1, len(names) + 1):
            out += [frozenset(c) for c in combinations(names, k)]
        return out

    def predictor(self, exclude=frozenset()) -> PhysicalPredictor:
        exclude = frozenset(exclude)
        if exclude not in self._predictors:
            self._predictors[exclude] = PhysicalPredictor(self, exclude)
        return self._predictors[exclude]

    def predict_interval(self, X, exclude=frozenset(), raw=False, policy=True):
        (campaign,) = _as_campaign_list(X)
        check_compatible(self, campaign)
        mean, half, p, at = self._served(campaign, exclude, raw, policy)
        self.last_flags_ = p.last_flags[at]
        return mean, half

    def _served(self, campaign, exclude=frozenset(), raw=False, policy=True):
        """Deviation and half-width at each reference time as the runtime publishes them (the
        last frame's output, carried forward: the reference clock is offset from the
        interrogator's, e.g. +0.3 s), the predictor that ran, and the frame index of each
        reference time."""
        aligned = campaign.aligned(zero_window_s=self.zero_window_s)
        p = PhysicalPredictor(self, exclude)       # fresh filter state per campaign
        _, _, w0, t0 = self.instrument_arrays(aligned)
        frame_t, w, t = self.frame_arrays(campaign, aligned)
        mean, half = p.predict(w, t, w0, t0, time_s=frame_t, raw=raw, thermal_policy=policy)
        at = np.clip(np.searchsorted(frame_t, aligned.time_s, side="right") - 1, 0, frame_t.size - 1)
        return mean[at], half[at], p, at

    def frame_arrays(self, campaign, aligned):
        """The campaign as the runtime sees it: every interrogator frame inside the aligned
        overlap, with each probe's last reading at that frame (held, as a live feed is).

        Returns frame times (s), wavelengths (n, sensors) nm and temperatures (n, probes) degC
        in the model's order. The load tracker runs on this clock (its filters are set in
        seconds), so validation sees the correction the runtime would publish, not one computed
        from gratings averaged over each reference interval.
        """
        ft = campaign.fbg["time_s"].to_numpy(dtype=float)
        t_lo, t_hi = aligned.dropped["overlap_s"]
        keep = (ft >= t_lo - 1e-9) & (ft <= t_hi + 1e-9)
        if not keep.any():
            keep[:] = True
        ft = ft[keep]
        w = campaign.fbg[[f"{s}_nm" for s in self.sensor_names]].to_numpy(dtype=float)[keep]
        temps = np.empty((ft.size, len(self.probe_names_)))
        for names, (tt, tv) in campaign.thermometers().items():
            held = np.clip(np.searchsorted(tt, ft, side="right") - 1, 0, tt.size - 1)
            for j, p in enumerate(names):
                if p in self.probe_names_:
                    temps[:, self.probe_names_.index(p)] = tv[held, j]
        return ft, w, temps

    # -- reporting and persistence -----------------------------------------------------------
    def summary(self) -> str:
        names = ["const"] + [f"dT_{p}" for p in self.housing_probes_] + \
            [f"dT_{p}" for p in self.ambient_probes_] + \
            ([f"lead{self.lead_tau_s:g}s_housing"] if self.housing_probes_ else [])
        out = [f"physical model (default): load signature + housing thermal, do-no-harm policy; "
               f"{self.training_['n_samples']} samples from "
               f"{', '.join(c['name'] for c in self.training_['campaigns'])}",
               f"housing probes: {', '.join(self.housing_probes_) or 'none'}; ambient: "
               f"{', '.join(self.ambient_probes_) or 'none'}",
               ""]
        tm = self.twin_map_
        if tm is None:
            out += ["thermal part (µm per K; lead in µm per K of T - lowpass(T))",
                    f"{'term':<22}" + "".join(f"{a:>11}" for a in AXES)]
            for name, row in zip(names, np.asarray(self.thermal_coef_)):
                out.append(f"{name:<22}" + "".join(f"{v:>11.4g}" for v in row))
        else:
            out.append(f"thermal part: ridge map learned on {tm['n_scenarios']} thermal scenarios of the "
                       f"machine's FE twin ({len(tm['features'])} features: {', '.join(tm['features'])})")
            cal = tm.get("calibration")
            if cal is not None:
                out += [f"housing transient calibrated on the {cal.get('source', 'measured campaigns')} "
                        "(µm per K)", f"{'term':<22}" + "".join(f"{a:>11}" for a in AXES)]
                for name, row in zip(["dT_housing"] + [f"lead{t:g}s_housing" for t in cal["leads_s"]],
                                     np.asarray(cal["coef"])):
                    out.append(f"{name:<22}" + "".join(f"{v:>11.4g}" for v in row))
        out.append(f"{'residual SD µm':<22}" + "".join(f"{v:>11.3g}" for v in self.thermal_resid_sd_um_))
        lo, hi = self.thermal_range_um_
        out.append(f"{'validated range µm':<22}" + ", ".join(f"{ax} {a:.3g}..{b:.3g}" for ax, a, b in zip(AXES, lo, hi)))
        if self.load_ is None:
            out.append("\nload part: none (no training campaign with loads and no machine description)")
        else:
            L = self.load_
            out.append(f"\nload part ({L['source']}); forces estimated: "
                       + ", ".join(f for f, on in zip(_FORCE_AXES, L["active_forces"]) if on))
            out.append(f"{'':<8}" + "".join(f"{f + ' µm/kN':>13}" for f in _FORCE_AXES))
            for s, row in zip(self.sensor_names, np.asarray(L["G_um_per_N"])):
                out.append(f"{s:<8}" + "".join(f"{1e3 * v:>13.4g}" for v in row))
            for a, row in zip(AXES, np.asarray(L["C_um_per_N"])):
                out.append(f"{a:<8}" + "".join(f"{1e3 * v:>13.4g}" for v in row))
            p = self.predictor()
            at_rest, warm = p.F_sds
            out.append("force 1-sigma N at rest / at the training's thermal extreme: "
                       + ", ".join(f"{f} {a:.3g}/{b:.3g}" for f, a, b in zip(_FORCE_AXES, at_rest, warm))
                       + f"; applied from {self.load_k_sigma:g} sigma, in full beyond {2 * self.load_k_sigma:g}")
        return "\n".join(out)

    def to_dict(self) -> dict:
        d = self._header()
        d.update({
            "params": {k: v for k, v in self.get_params().items() if k != "machine"},
            "zero_state": {"method": "mean_of_first_window", "window_s": self.zero_window_s},
            "sensors": [s.model_dump(mode="json") for s in self.sensors_],
            "probes": list(self.probe_names_),
            "housing_probes": list(self.housing_probes_),
            "ambient_probes": list(self.ambient_probes_),
            "nominal_dt_s": self.nominal_dt_s_,
            "thermal": {"coef": np.asarray(self.thermal_coef_).tolist(),
                        "envelope_low": np.asarray(self.thermal_envelope_[0]).tolist(),
                        "envelope_high": np.asarray(self.thermal_envelope_[1]).tolist(),
                        "range_low_um": np.asarray(self.thermal_range_um_[0]).tolist(),
                        "range_high_um": np.asarray(self.thermal_range_um_[1]).tolist(),
                        "resid_sd_um": np.asarray(self.thermal_resid_sd_um_).tolist(),
                        "noise_sd_um": np.asarray(self.thermal_noise_sd_um_).tolist()},
            "twin_map": self.twin_map_,
            "interval": getattr(self, "interval_", None),
            "load": self.load_,
            "training": self.training_,
            "uncertainty": {"level": 0.95, "method": "thermal error v0 (reference noise) + vs excursion + v1 excursion^2 + v2 lead^2, calibrated to 95 % training coverage, + applied load's GLS and relative error"},
            "z_axis_mm": None,
        })
        return d

    @classmethod
    def from_dict(cls, d: dict, source="<dict>") -> "PhysicalModel":
        from fbgcomp.io.campaign import SensorSpec

        _check_shapes(d, source)
        m = cls(**d.get("params", {}))
        m.sensors_ = [SensorSpec(**s) for s in d["sensors"]]
        m.probe_names_ = list(d["probes"])
        m.housing_probes_ = list(d["housing_probes"])
        m.ambient_probes_ = list(d["ambient_probes"])
        m.nominal_dt_s_ = float(d["nominal_dt_s"])
        th = d["thermal"]
        m.thermal_coef_ = np.asarray(th["coef"], float)
        m.thermal_envelope_ = (np.asarray(th["envelope_low"], float), np.asarray(th["envelope_high"], float))
        m.thermal_range_um_ = (np.asarray(th["range_low_um"], float), np.asarray(th["range_high_um"], float))
        m.thermal_resid_sd_um_ = np.asarray(th["resid_sd_um"], float)
        m.thermal_noise_sd_um_ = np.asarray(th.get("noise_sd_um", [0.0] * 3), float)
        m.twin_map_ = d.get("twin_map")
        m.interval_ = d.get("interval")
        m.load_ = d.get("load")
        m.training_ = d.get("training", {"campaigns": [], "n_samples": 0})
        m._predictors = {}
        # what loaded must predict finite numbers with every sensor set the runtime may use
        w0 = np.array([s.lambda0_nm for s in m.sensors_])
        t0 = np.full(len(m.probe_names_), 20.0)
        for exclude in [frozenset()] + m.fallback_sets:
            dev, half = PhysicalPredictor(m, exclude).predict(w0[None, :] + 0.01, t0[None, :] + 0.5, w0, t0)
            if not (np.isfinite(dev).all() and np.isfinite(half).all()):
                raise InputError("model cannot predict finite numbers"
                                 + (f" without {', '.join(sorted(exclude))}" if exclude else ""),
                                 file=source, column="field thermal/load/twin_map")
        m._predictors = {}
        return m

    @property
    def max_correction_um(self):
        """Largest |correction| per axis this model was validated for (thermal range plus the
        largest load the training carried, with a margin), µm."""
        lo, hi = self.thermal_range_um_
        bound = np.maximum(np.abs(lo), np.abs(hi))
        if self.load_ is not None:
            bound = bound + 1.5 * np.abs(np.asarray(self.load_["C_um_per_N"])).sum(axis=1) * 5000.0
        return [float(b) for b in bound]

register_model_type("physical", PhysicalModel)
