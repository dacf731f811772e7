"""The default model: load from the gratings' load signature, heat from the housing, do no harm.

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
At run time each frame's force is the generalised least-squares estimate

    F = (G' W G)^-1 G' W (e - e_thermal),    W = (Sigma_thermal + Sigma_noise)^-1

where ``e_thermal`` is the gratings' thermal reading predicted from the probes (fitted on the
load-free campaigns) and ``Sigma_thermal`` the covariance of that prediction's error: a reading
pattern the probes explain badly (common-mode warming) carries little weight, a differential
pattern (bending) a lot. Frames whose residual contradicts every load the structure can carry
(chi-square test) drop the load part (``LOAD_REFUSED``); each force component is shrunk to zero
unless it stands clear of its uncertainty and of the other components' cross-talk (firm
shrinkage), so sensor noise and thermal
mismatch are never published as a correction on an axis that does not move.

**Thermal part**: per axis a least-squares fit, on the load-free training campaigns, of the
TTP deviation on the temperature changes of the housing probe(s) and the ambient, and on the
housing probe's thermal lead ``T - lowpass(T, tau)`` (~ tau dT/dt): the spindle housing is
steel (11.5e-6 /K against 0.4e-6 /K for the CFRP), so the TTP's axial drift follows the housing's
mean temperature, which a probe on the housing's far face sees late; the lead term recovers it
(on ram2, fit on thermal_a: held-out dz RMS 2.9 -> 1.0 µm). The regressors are clipped to the
training envelope (``SHRUNK``) and each axis to the range of thermal deviations it was validated
on (``CLAMPED``): a heat source absent from training can move the correction no further than
what was seen.

Every prediction therefore carries its applicability flags (``last_flags`` after each call,
bits of :mod:`fbgcomp.policy`), which the runtime publishes with the correction.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np
from scipy import stats

from .errors import InputError
from .features import FeatureMap
from .models import AXES, EstimatorParams, ModelFile, _as_campaign_list, check_compatible, register_model_type
from . import policy as P
from .model_types import first_order_filter

_FORCE_AXES = ("fx", "fy", "fz")
#: Low-pass of the probe temperatures before the thermal regressors, s.
PROBE_SMOOTHING_S = 60.0


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
        self.thermal_resid_var = np.asarray(m.thermal_resid_sd_um_) ** 2
        keep = [i for i, s in enumerate(self.sensor_names) if s not in self.exclude]
        self._keep = keep
        self.has_load = m.load_ is not None and len(keep) >= 1
        if self.has_load:
            L = m.load_
            G = np.asarray(L["G_um_per_N"])[keep]
            self.C = np.asarray(L["C_um_per_N"])                          # (3 axes, 3 forces)
            self.B = np.asarray(L["grating_thermal_coef"])[:, keep]       # (1 + nh, S)
            noise = np.diag(np.asarray(L["noise_var_um2"], float)[keep])
            unit = np.asarray(L["thermal_sigma_unit_um2"], float)[np.ix_(keep, keep)]
            self.active = np.asarray(L["active_forces"], bool)
            self.thermal_scale = np.asarray(L["thermal_scale"], float)
            Ga = G[:, self.active]
            # GLS operators on a grid of thermal excursions s² (0 = isothermal): the gratings'
            # thermal reading is only uncertain in proportion to how far the machine is from its
            # zero state, so a static load at rest is read with the sensors' noise alone.
            self.s2_grid = np.concatenate([[0.0], np.logspace(-4, 4, 49)])
            nS = len(keep)
            self.ops = np.zeros((self.s2_grid.size, 3, nS))
            self.Ws = np.zeros((self.s2_grid.size, nS, nS))
            self.F_sds = np.zeros((self.s2_grid.size, 3))
            for i, s2 in enumerate(self.s2_grid):
                op, cov, W = gls_operator(Ga, noise + s2 * unit)
                self.ops[i][self.active] = op
                self.Ws[i] = W
                self.F_sds[i][self.active] = np.sqrt(np.clip(np.diag(cov), 0, None))
            self.F_sd = self.F_sds[0]
            self.G = G
            self.dof = len(keep) - int(self.active.sum())
            self.k_sigma = float(m.load_k_sigma)
            self.p_contra = float(m.contradiction_p)
            self.chi2_inflation = float(L.get("chi2_inflation", 1.0))
            self.s2_limit = float(L.get("s2_limit", np.inf))
            self.relative_error = float(m.load_relative_error)
            # no load beyond 1.5x the largest the signature was calibrated with is believed
            self.max_force_N = 1.5 * np.asarray(L.get("max_force_N", [np.inf] * 3), float)
        var = self.thermal_resid_var.copy()
        if self.has_load:
            var = var + (self.C ** 2 @ self.F_sds[self.s2_grid.searchsorted(1.0)] ** 2)
        self.expected_rms_error_um = np.sqrt(var)
        self._t = stats.norm.ppf(0.975)
        self.state = None
        self.last_flags = np.zeros((0, 3), np.uint8)
        self.last_force_N = np.zeros((0, 3))

    def reset(self):
        self.state = None

    def thermal_regressors(self, temperature_C, temperature_zero_C, time_s=None):
        """[1, ΔT_housing..., ΔT_ambient..., lead of mean ΔT_housing] (n, 1 + nh)."""
        dT = np.atleast_2d(np.asarray(temperature_C, float)) - np.asarray(temperature_zero_C, float)
        H, self.state = thermal_regressors(dT, self._h_idx, self._a_idx, self.lead_tau_s, time_s,
                                           self.state, self.nominal_dt_s)
        return H

    def thermal_excursion(self, delta_T_K):
        """s² per frame (n,): every probe's temperature change in units of its largest change in
        training, squared and summed (0 at the zero state; ~1 at the training's extremes)."""
        return np.sum((np.atleast_2d(delta_T_K) / self.thermal_scale) ** 2, axis=1)

    def estimate_force(self, e_mech, delta_T_K):
        """GLS force (n, 3) N, chi-square of the residual (n,) and force SD (n, 3) N."""
        s2 = self.thermal_excursion(delta_T_K)
        k = np.minimum(self.s2_grid.searchsorted(s2), self.s2_grid.size - 1)
        force = np.empty((len(k), 3))
        chi2 = np.empty(len(k))
        for i in np.unique(k):
            rows = k == i
            f = e_mech[rows] @ self.ops[i].T
            r = e_mech[rows] - f[:, self.active] @ self.G[:, self.active].T
            force[rows] = f
            chi2[rows] = np.einsum("ns,st,nt->n", r, self.Ws[i], r)
        return force, chi2, self.F_sds[k]

    def predict(self, wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C, *,
                time_s=None, z_axis_mm=None, raw=False):
        """Applied TTP deviation (n, 3) µm and 95 % half-width (n, 3) µm; ``raw=True`` skips
        the policy (envelope clipping, axis clamp, load gating) for diagnosis."""
        wl = np.atleast_2d(np.asarray(wavelength_nm, dtype=float))
        n = wl.shape[0]
        flags = np.zeros((n, 3), np.uint8)
        H = self.thermal_regressors(temperature_C, temperature_zero_C, time_s)
        if raw:
            thermal = H @ self.A
        else:
            Hc, outside = P.clip_to_envelope(H[:, 1:], self.h_low, self.h_high, self.margin)
            Hc = np.hstack([H[:, :1], Hc])
            thermal, clamped = P.clamp_axes(Hc @ self.A, self.t_low, self.t_high)
            flags[outside] |= P.SHRUNK
            flags[clamped] |= P.CLAMPED
        load = np.zeros((n, 3))
        force = np.zeros((n, 3))
        if self.has_load:
            w = wl.copy()
            w0 = np.asarray(wavelength_zero_nm, float)
            cols = [i for i, s in enumerate(self.sensor_names) if s in self.exclude]
            w[:, cols] = w0[cols]
            e = self._fmap.base(w, temperature_C, w0, temperature_zero_C)[:, self._keep]
            e_mech = e - H @ self.B
            dT = np.atleast_2d(np.asarray(temperature_C, float)) - np.asarray(temperature_zero_C, float)
            force, chi2, F_sd = self.estimate_force(e_mech, dT)
            if not raw:
                # The gratings' thermal reading is only modelled inside the thermal states the
                # training saw: beyond them, or when the gratings contradict every load the
                # structure can carry, no load is read from them.
                s2 = self.thermal_excursion(dT)
                refused = (s2 > self.s2_limit) | P.contradiction(chi2, self.dof, self.p_contra,
                                                                 self.chi2_inflation)
                # A component is read only beyond its noise and beyond the cross-talk the other
                # components' signature error can leak into it (relative_error of their size).
                other = np.sqrt(np.maximum((force ** 2).sum(axis=1, keepdims=True) - force ** 2, 0.0))
                floor = np.maximum(F_sd, self.relative_error * other / self.k_sigma)
                force = P.firm(force, floor, self.k_sigma, 2 * self.k_sigma)
                force[refused] = 0.0
                flags[refused] |= P.LOAD_REFUSED
                big = np.abs(force) > self.max_force_N
                force = np.clip(force, -self.max_force_N, self.max_force_N)
                flags[big.any(axis=1)] |= P.CLAMPED
            load = force @ self.C.T
        self.last_flags = flags
        self.last_force_N = force
        deviation = thermal + load
        var = self.expected_rms_error_um[None, :] ** 2 + np.zeros((n, 3))
        return deviation, self._t * np.sqrt(var)


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
    """

    model_type = "physical"

    def __init__(self, machine=None, zero_window_s=10.0, lead_tau_s=300.0, envelope_margin=0.1,
                 load_k_sigma=3.0, contradiction_p=1e-3, thermal_error_inflation=4.0,
                 load_relative_error=0.03):
        self.machine = machine
        self.zero_window_s = zero_window_s
        self.lead_tau_s = lead_tau_s
        self.envelope_margin = envelope_margin
        self.load_k_sigma = load_k_sigma
        self.contradiction_p = contradiction_p
        self.thermal_error_inflation = thermal_error_inflation
        self.load_relative_error = load_relative_error

    # -- fitting -----------------------------------------------------------------------------
    def _machine(self):
        if self.machine is None:
            return None
        from .structure import Machine, load_machine

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
            max_force = np.abs(Fall).max(axis=0)
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
        if G is not None and active.any():
            if np.isnan(noise_var).any():
                noise_var = np.full(S, 0.05 ** 2)
            self.load_ = {"G_um_per_N": G.tolist(), "C_um_per_N": C.tolist(),
                          "active_forces": active.tolist(), "grating_thermal_coef": B.tolist(),
                          "thermal_sigma_unit_um2": (self.thermal_error_inflation * cov_unit).tolist(),
                          "thermal_scale": scale.tolist(), "noise_var_um2": noise_var.tolist(),
                          "max_force_N": np.where(max_force > 0, max_force, 5000.0).tolist(),
                          "source": source, "chi2_inflation": 1.0}
        # Thermal part of the TTP: y minus the (policy-applied) load part, on load-free campaigns.
        self.thermal_coef_ = np.zeros((nh, 3))
        self.thermal_envelope_ = (np.zeros(nh - 1), np.zeros(nh - 1))
        self.thermal_range_um_ = (np.zeros(3), np.zeros(3))
        self.thermal_resid_sd_um_ = np.full(3, 0.1)
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
        # Load-part uncertainty calibrated on loaded campaigns: the load part's residual.
        self.training_ = {"campaigns": [{"name": r["name"], "loaded": bool(r["loaded"]),
                                         "n_samples": int(len(r["y"]))} for r in rows],
                          "n_samples": int(sum(len(r["y"]) for r in rows))}
        self._predictors = {}
        if self.load_ is not None:
            self._calibrate_applicability(rows)
        return self

    def _calibrate_applicability(self, rows):
        """Thresholds of the load part's applicability, from the training campaigns: the largest
        thermal excursion s² they reached (x 1.2), and a chi-square inflation such that their
        frames (conditions the model was validated on) are not refused (0.99 quantile x 1.5)."""
        p = self.predictor()
        s2_max, worst = 0.0, 0.0
        for r in rows:
            s2_max = max(s2_max, float(np.max(p.thermal_excursion(r["dT"]))) if len(r["dT"]) else 0.0)
            e_mech = r["e"][:, p._keep] - r["H"] @ p.B
            _, chi2, _ = p.estimate_force(e_mech, r["dT"])
            if p.dof >= 1 and chi2.size:
                worst = max(worst, float(np.quantile(chi2, 0.99)))
        self.load_["s2_limit"] = max(s2_max, 1.0)
        if p.dof >= 1:
            base = stats.chi2.ppf(1 - self.contradiction_p, p.dof)
            self.load_["chi2_inflation"] = max(1.0, 1.5 * worst / base)
        self._predictors = {}

    def _twin_signature(self, machine):
        """(G, C) from the FE twin, or None without a machine description or a matching sensor set."""
        if machine is None:
            return None
        names = [s.name for s in machine.sensors]
        if any(s not in names for s in self.sensor_names):
            return None
        from .structure import Twin

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

    def predict_interval(self, X, exclude=frozenset(), raw=False):
        (campaign,) = _as_campaign_list(X)
        check_compatible(self, campaign)
        aligned = campaign.aligned(zero_window_s=self.zero_window_s)
        p = PhysicalPredictor(self, exclude)       # fresh filter state per campaign
        w, t, w0, t0 = self.instrument_arrays(aligned)
        out = p.predict(w, t, w0, t0, time_s=aligned.time_s, raw=raw)
        self.last_flags_ = p.last_flags
        return out

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
               "", "thermal part (µm per K; lead in µm per K of T - lowpass(T))",
               f"{'term':<22}" + "".join(f"{a:>11}" for a in AXES)]
        for name, row in zip(names, np.asarray(self.thermal_coef_)):
            out.append(f"{name:<22}" + "".join(f"{v:>11.4g}" for v in row))
        out.append(f"{'residual SD µm':<22}" + "".join(f"{v:>11.3g}" for v in self.thermal_resid_sd_um_))
        lo, hi = self.thermal_range_um_
        out.append(f"{'validated range µm':<22}" + "".join(f"{f'{a:.3g}..{b:.3g}':>11}" for a, b in zip(lo, hi)))
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
            at_rest, warm = p.F_sds[0], p.F_sds[p.s2_grid.searchsorted(1.0)]
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
                        "resid_sd_um": np.asarray(self.thermal_resid_sd_um_).tolist()},
            "load": self.load_,
            "training": self.training_,
            "uncertainty": {"level": 0.95, "method": "thermal residual + load GLS covariance"},
            "z_axis_mm": None,
        })
        return d

    @classmethod
    def from_dict(cls, d: dict, source="<dict>") -> "PhysicalModel":
        from .campaign import SensorSpec

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
        m.load_ = d.get("load")
        m.training_ = d.get("training", {"campaigns": [], "n_samples": 0})
        m._predictors = {}
        arrays = [m.thermal_coef_, *m.thermal_envelope_, *m.thermal_range_um_, m.thermal_resid_sd_um_]
        if m.load_ is not None:
            arrays += [np.asarray(m.load_[k], float) for k in
                       ("G_um_per_N", "C_um_per_N", "grating_thermal_coef", "thermal_sigma_unit_um2",
                        "noise_var_um2", "thermal_scale")]
        if not all(np.all(np.isfinite(a)) for a in arrays):
            raise InputError("model holds a non-finite coefficient", file=source, column="field thermal/load")
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
