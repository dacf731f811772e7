"""The physical model's predictor: load tracking by steps of the load signature, thermal part, policy.

:class:`PhysicalPredictor` is the vectorised, stateful prediction of one sensor set (the runtime
and the offline validation share it). Its load tracking (:meth:`PhysicalPredictor._track_load`
with its vectorised steady stretches, :meth:`PhysicalPredictor._steady_run`) and its thermal part
and interval are one state machine over the same frames, so they stay one class: over 600 lines
as one unit for that reason (the step test, its live noise estimate and the transitions share
the per-frame state).
"""

from __future__ import annotations

import copy
import math

import numpy as np

import fbgcomp.models.policy as P
from fbgcomp.models.distributions import chi2_ppf, norm_isf, norm_ppf
from fbgcomp.models.filters import first_order_filter, first_order_recursion, first_order_step
from fbgcomp.models.physical.observer import ThermalObserver
from fbgcomp.models.physical.thermal import (
    MAP_LEADS_S,
    agreed,
    calibration_probe_columns,
    grating_map,
    housing_leads,
    housing_mean,
    housing_rest,
    lost_information_sd,
    map_features,
    map_members,
    member_bounds,
    thermal_regressors,
    unseen_operator,
)

#: Names of the TTP force components, in the order of every force array.
FORCE_AXES = ("fx", "fy", "fz")
#: 95 % half-width at a Z the training never saw, per µm of lateral correction held back: the
#: deflection left is about that correction, give or take how far the compliance moved with Z
#: (about (1 + dL / L)^3 for an overhang L lengthened by dL: 1.5x for 15 % of it)
UNTRAINED_Z_HALF = 1.5
# Low-pass of the gratings' load reading, s: a step is judged on it (so frame rate and batching
# do not matter) and a load transition follows it.
LOAD_FAST_S = 0.5
# Slower low-pass, s: a transition ends when the fast reading agrees with it, at its value.
LOAD_HOLD_S = 3.0
#: Low-pass, s, of the reading a transition follows while the load still moves (the fast and
#: hold readings disagree): a first-order low-pass lags a ramp by its time constant, and at the
#: interrogator's 10 Hz the fast reading's 0.5 s held ram2's static_x 97 N (13.6 µm of dx) behind
#: its 200 N/s ramps. 0.1 s passes a 1 s frame whole and a 10 Hz one at 0.63; once the load has
#: stopped the transition follows the fast reading again, which is then as settled as it is.
LOAD_FOLLOW_S = 0.1
#: Frames a load transition's line (:func:`ramp_line`) needs before it is published: with 2 it
#: passes through both, no better than the last frame.
RAMP_LINE_MIN = 3
#: Shortest frame interval, s, at which a transition publishes its line: ``LOAD_FAST_S``. What
#: ends the line at a ramp's end is a frame that leaves it by k sigma. At frames of the fast
#: low-pass or longer that is the first frame after the end; at 10 Hz one frame's step off the
#: line is a tenth of a ramp's second, under its noise, and the line ran on past each end of
#: ram2's static_xyz ramps (in-sample samples 2-4 µm further off, the load interval's dx scale
#: 0.136 -> 0.216 and the test of static_x's ramps failed; docs/accuracy.md).
RAMP_LINE_DT_S = LOAD_FAST_S
#: Memory of the load reading's thermal lag, s: between transitions the thermal offset follows
#: the gratings' drift ``offset_tau_s`` behind, so the reading stands ``r offset_tau_s`` off
#: the applied force for a drift of r N/s, and through a transition (offset frozen) it drifts
#: on by r per second. Both are taken off the level a transition ends at. Long against the
#: frame noise (1.4 N of lag at 1 s frames on ram2), short against the heat's hours. It learns
#: only ``3 offset_tau_s`` after a transition: until then the reading still carries the offset
#: taking in what the last level left (a signature's cross-talk) and the lag building up again,
#: neither of which is the drift.
LOAD_TREND_S = 120.0
#: Expected false load starts per hour of load-free running: a step test is one look per frame
#: (at most one per 2 LOAD_FAST_S, the low-pass's memory), so its threshold in sigma grows with
#: the number of looks an hour holds (5.1 sigma at 1 look/s) instead of a fixed 3 sigma that
#: noise alone crosses a few times a day at 1 Hz.
LOAD_FALSE_STARTS_PER_H = 1e-3
# Frames of a stretch without load transition run vectorised at a time, and frames the per-frame
# recursion takes after a stretch stopped at once (PhysicalPredictor._steady_run).
STEADY_WINDOW = 4096
STEADY_BACKOFF = 64
#: How many SDs of a fallback's lost information (thermal.lost_information_sd) its policy holds
#: back, where the noise counts at ``k_sigma`` (3): the noise is white over ~1e5 frames a campaign,
#: the map's error a slow, systematic one with a few independent values, for which 2 SDs is the
#: usual significance. Measured on the runtime's fallbacks (bench_lost_grating): at 3, ram2's
#: thermal_b lost S2 and S4 at dx 13.9 µm (5.8 and 5.7 without the term); at 0, the built-in
#: twin's thermal-36h-b without S4 had dy 0.87 µm on a drift of 0.19 (harm).
LOST_K_SIGMA = 2.0
#: The thermal observer's applicability gate: it is trusted while every heat input it estimates
#: stays within this many times its source's nominal value (latched; observer.plausible).
OBSERVER_GATE_K = 3.0

#: Memory of the live noise estimate, s, and the weight, s, of its prior (the training noise):
#: the step test learns how far the stream's own low-passed noise exceeds the training's
#: (an interrogator averaging differently, noise correlated over many frames) and never
#: judges noise smaller than the training's (PhysicalPredictor._noise_excess).
NOISE_LEARN_S = 120.0
NOISE_PRIOR_S = 10.0


def fast_hold_noise(dt, rate, b_fast, b_hold):
    """Variance of the fast minus the hold reading (``LOAD_FAST_S`` low-pass, then its
    ``LOAD_HOLD_S`` low-pass) per unit of the training frame's noise variance, for white noise of
    ``rate`` times that variance per frame at frame interval ``dt`` (n,): the stationary
    covariance of the two cascaded first-order filters, solved in closed form. 1 where dt = 0."""
    a, g = 1.0 - b_fast, 1.0 - b_hold
    c = b_hold * a
    ok = dt > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        p00 = rate * b_fast**2 / (1.0 - a**2)
        p01 = (a * c * p00 + rate * b_hold * b_fast**2) / (1.0 - a * g)
        p11 = (c**2 * p00 + 2.0 * c * g * p01 + rate * (b_hold * b_fast) ** 2) / (1.0 - g**2)
        out = p00 + p11 - 2.0 * p01
    return np.where(ok, out, 1.0)


def ramp_line(line, on, t, y, sd, k):
    """One frame of the least-squares line through a moving load's quick reading.

    ``line`` (3, 6) holds per force component the frame count, the line's time origin (s) and the
    sums of tau, tau², y and tau y (tau = t - origin); ``on`` (3,) marks the components still
    moving. Components not moving start anew (count 0). A frame whose reading ``y`` (3,) N
    leaves the line by more than ``k`` times its prediction's SD (``sd`` (3,) N, the reading's
    noise) starts it anew from that frame: the ramp ended, or turned. Returns the line's value
    at ``t`` where it holds ``RAMP_LINE_MIN`` frames (NaN elsewhere) and the updated sums.

    On a ramp the frames lie on a line, so its value at the last one carries less noise than
    that frame: (4n - 2) / (n (n + 1)) of its variance for n frames, 0.35 at ten. At 1 s frames
    the tracker had followed each frame's reading alone, and one frame's noise (3 sigma, 200 N
    of ram5's 2200 N) landed on the sample that ended the ramp (benchmarks/bench_latency_floor.py
    and docs/accuracy.md)."""
    est, new = ramp_line_floats(
        np.asarray(line, float).tolist(),
        [bool(v) for v in on],
        float(t),
        np.asarray(y, float).tolist(),
        np.asarray(sd, float).tolist(),
        k,
    )
    return np.array(est), np.array(new)


def ramp_line_floats(line, on, t, y, sd, k):
    """:func:`ramp_line` on Python floats (lists: ``line`` 3 x 6, ``on``, ``y``, ``sd`` 3), the
    load tracker's per-frame form; the same arithmetic. Returns the estimates (NaN where the
    line is not yet published) and the new sums, as lists."""
    est = [math.nan] * 3
    out = []
    for a in range(3):
        if not on[a]:
            out.append([0.0] * 6)
            continue
        n, t0, St, Stt, Sy, Sty = line[a]
        if n == 0:
            t0 = t
        tau = t - t0
        if n >= RAMP_LINE_MIN:
            sxx = Stt - St * St / n
            if sxx > 0:
                b = (Sty - St * Sy / n) / sxx
                c = (Sy - b * St) / n
                v = sd[a] ** 2 * (1.0 + 1.0 / n + (tau - St / n) ** 2 / sxx)
                if abs(y[a] - (c + b * tau)) > k * math.sqrt(v):
                    n, t0, St, Stt, Sy, Sty, tau = 0.0, t, 0.0, 0.0, 0.0, 0.0, 0.0
        n, St, Stt, Sy, Sty = n + 1, St + tau, Stt + tau * tau, Sy + y[a], Sty + tau * y[a]
        out.append([n, t0, St, Stt, Sy, Sty])
        if n >= RAMP_LINE_MIN:
            sxx = Stt - St * St / n
            b = (Sty - St * Sy / n) / sxx if sxx > 0 else 0.0
            est[a] = (Sy - b * St) / n + b * tau
    return est, out


def quick_fast_noise(b_quick, b_fast):
    """Variance of the quick minus the fast reading (two first-order low-passes of the same
    white noise, gains ``b_quick`` and ``b_fast`` per frame) per unit of the frame's noise
    variance: their stationary variances less twice their covariance."""
    with np.errstate(divide="ignore", invalid="ignore"):
        cov = np.where(b_fast > 0, b_quick * b_fast / (1.0 - (1.0 - b_quick) * (1.0 - b_fast)), 0.0)
    return b_quick / (2.0 - b_quick) + b_fast / (2.0 - b_fast) - 2.0 * cov


def _row_products(rows, v) -> list[float]:
    """A matrix (its rows as lists) times a vector, on Python floats: the load tracker's GLS
    and signature products of one frame."""
    return [sum(r * x for r, x in zip(row, v)) for row in rows]


def _floats(v):
    """A state vector as a list of Python floats (the one-frame path's form; the array path
    reads either)."""
    return v.tolist() if isinstance(v, np.ndarray) else v


def gls_operator(G, Sigma):
    """GLS force estimator ``(G' W G)^-1 G' W`` (3 x S), its covariance (3 x 3) and W (S x S)
    for elongation covariance ``Sigma`` (µm²); G in µm per N."""
    W = np.linalg.pinv(Sigma)
    info = G.T @ W @ G
    cov = np.linalg.pinv(info)
    return cov @ G.T @ W, cov, W


def excursion2(dT, scale_K, deadband_K=0.0):
    """Squared thermal excursion of each frame: sum over probes of (dT / scale)^2, where
    ``scale_K`` is each probe's largest |dT| in training (so 1 ~ the training's extreme) and
    a change within a probe's ``deadband_K`` (its noise) counts as none."""
    dT = np.atleast_2d(np.asarray(dT, float))
    dT = np.sign(dT) * np.maximum(np.abs(dT) - np.asarray(deadband_K, float), 0.0)
    return np.sum((dT / np.asarray(scale_K, float)) ** 2, axis=1)


def _held_force(state) -> np.ndarray:
    """The applied force (3,) N the load tracker's part of a predictor's ``state`` holds (0
    before it has run)."""
    return np.asarray((state.get("load") or {}).get("force", np.zeros(3)), float)


def _interval_terms(iv) -> dict:
    """The thermal interval's terms (:meth:`PhysicalModel._fit_interval`) as arrays."""
    return {
        "v0": np.asarray(iv["v0_um2"], float),
        "v1": np.asarray(iv["v1_um2"], float),
        "scale": np.asarray(iv["dT_scale_K"], float),
        "v2": np.asarray(iv["v2_um2"], float),
        "activity_scale": float(iv["activity_scale_K"]),
        "vs": np.asarray(iv.get("vs_um2", np.zeros(3)), float),
        "deadband": np.asarray(iv.get("deadband_K", 0.0), float),
        # the constant term of a model blind to the housing (absent from older files)
        "vc": np.asarray(iv.get("vc_um2", np.zeros(3)), float),
    }


def _state_variance(iv, dT, activity, lost_sd_um):
    """The thermal part's error variance (n, 3) µm² of interval terms ``iv`` at probe changes
    ``dT`` (n, P) K and housing lead ``activity`` (n,) K, plus ``lost_sd_um`` (3,) squared; and
    the squared excursion s² (n,)."""
    s2 = excursion2(dT, iv["scale"], iv["deadband"])
    a2 = (np.asarray(activity, float) / iv["activity_scale"]) ** 2
    var = (
        iv["v0"][None, :]
        + iv["vs"][None, :] * np.sqrt(s2)[:, None]
        + iv["v1"][None, :] * s2[:, None]
        + iv["v2"][None, :] * a2[:, None]
        + iv["vc"][None, :]
        + np.asarray(lost_sd_um, float)[None, :] ** 2
    )
    return var, s2


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
        # measured heat inputs (W), read after the probes in the slow inputs' columns
        self.heat_names = list(getattr(m, "heat_inputs_", None) or [])
        self._fmap = grating_map(m.sensors_, m.probe_names_)
        self._h_idx = [self.probe_names.index(p) for p in m.housing_probes_]
        self._a_idx = [self.probe_names.index(p) for p in m.ambient_probes_]
        self.lead_tau_s = float(m.lead_tau_s)
        self.nominal_dt_s = float(m.nominal_dt_s_)
        self.A = np.asarray(m.thermal_coef_)  # (1 + nh, 3)
        self.h_low, self.h_high = np.asarray(m.thermal_envelope_[0]), np.asarray(m.thermal_envelope_[1])
        self.t_low, self.t_high = np.asarray(m.thermal_range_um_[0]), np.asarray(m.thermal_range_um_[1])
        self.margin = float(m.envelope_margin)
        self.k_sigma = float(m.load_k_sigma)  # also the thermal part's noise shrinkage
        self.thermal_resid_var = np.asarray(m.thermal_resid_sd_um_) ** 2
        # interval of the thermal part: variance = v0 + vs s + v1 s^2 + v2 a^2 + vc (s the thermal
        # excursion, a the housing's lead), fitted on the load-free training campaigns
        # (``PhysicalModel._fit_interval``); a constant without it
        # probes this set goes without (one lost at runtime): the map leaves out their columns
        # (and the housing's leads and calibration with a housing probe, the calibration with
        # an ambient one it reads); their reading is held at its last value for the filters
        self._lost_p = [j for j, q in enumerate(self.probe_names) if q in self.exclude]
        iv = getattr(m, "interval_", None)
        self.interval = None if iv is None else _interval_terms(iv)
        # a probe's fallback also has its own, fitted on its own training errors (absent from
        # files before it): it answers for the housing calibration the fallback goes without,
        # the full model's (with the map's lost information) for what the training never moved
        own = None
        lost_names = sorted(self.probe_names[j] for j in self._lost_p)
        if len(lost_names) == 1:
            own = ((iv or {}).get("without_probe") or {}).get(lost_names[0])
        elif len(lost_names) == 2:  # a pair's (absent from files written before them)
            pairs = (iv or {}).get("without_probes") or ()
            own = next((e for e in pairs if sorted(e["probes"]) == lost_names), None)
        self._own_interval = None if own is None else _interval_terms(own)
        self.thermal_noise_sd_um = np.asarray(getattr(m, "thermal_noise_sd_um_", np.zeros(3)), float)
        keep = [i for i, s in enumerate(self.sensor_names) if s not in self.exclude]
        self._keep = keep
        lost_housing = any(j in self._h_idx for j in self._lost_p)
        lost_ambient = any(j in self._a_idx for j in self._lost_p)
        self.has_load = m.load_ is not None and len(keep) >= 1
        self.C = (
            np.zeros((3, 3)) if m.load_ is None else np.asarray(m.load_["C_um_per_N"])
        )  # (3 axes, 3 forces)
        # the axes each force moves: at least a tenth of its largest compliance (last_follow, and
        # the axes a set without gratings holds back under a force it can no longer read)
        mag = np.abs(self.C)
        self._moves = (mag >= 0.1 * mag.max(axis=0, keepdims=True)) & (mag > 0)
        if self.has_load:
            L = m.load_
            G = np.asarray(L["G_um_per_N"])[keep]
            self.noise_var = np.asarray(L["noise_var_um2"], float)[keep]
            # (model files before the frame noise was measured: the nominal interval)
            self.noise_frame_dt_s = float(L.get("noise_frame_dt_s", m.nominal_dt_s_))
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
            # the thermal lag is learnt only this long after a transition (LOAD_TREND_S)
            self.trend_after_s = 3.0 * self.offset_tau_s
            self.drift_N_per_s = np.asarray(L.get("drift_N_per_s", [0.0] * 3), float)
            # the load terms' share of the interval, per axis, as the loaded training campaigns
            # showed it (PhysicalModel._fit_load_interval; 1 in files without it)
            self.load_interval_scale = np.asarray(L.get("interval_scale", [1.0] * 3), float)
            # ... which speaks for the terms of the force components the training applied; the
            # others keep their prior (all of them in files without it)
            self.load_interval_trained = np.asarray(L.get("interval_trained", [True] * 3), bool)
            self.noise_cov = noise
            self.nuisance_cov = nuisance_cov + np.zeros_like(noise)
            # the one-frame path's operands as Python floats (_steady_frame)
            self._G_rows = G.tolist()
            self._op_rows = self.ops[0].tolist()
            self._F_sd = self.F_sd.tolist()
            self._sd2 = [v * v if v > 0 else math.inf for v in self._F_sd]
        self.map = None
        self.cal = None
        self.last_cal_features = None
        self.last_map_features = None
        self.map_lost_sd_um = np.zeros(3)
        # the share of it a probe's fallback adds to its own interval: its lost gratings'
        self._interval_lost_sd_um = np.zeros(3)
        self._floor_scale = np.ones(3)
        # the zero state's error through the map (PhysicalModel._noise_floor), (3,) µm
        self.zero_sd_um = np.zeros(3)
        if getattr(m, "twin_map_", None) is not None:
            tm = m.twin_map_
            S = len(self.sensor_names)
            k = len(tm["scale"])
            drop = {S + j for j in self._lost_p}
            if lost_housing:
                drop |= set(range(k - len(MAP_LEADS_S), k))
            cols = [i for i in range(k) if (i >= S or i in keep) and i not in drop]
            members = map_members(tm, cols, float(m.map_ridge))
            if len(cols) == k:
                members[0] = np.asarray(tm["coef"], float)
            coef = members[0]
            lo, hi = np.asarray(tm["envelope_low"], float), np.asarray(tm["envelope_high"], float)
            nz = np.asarray(tm.get("noise_gram", np.zeros((k, k))), float)
            self.map_noise_sd_um = np.sqrt(np.clip(np.einsum("ka,kl,la->a", coef, nz, coef), 0, None))
            self.map = {
                "coef": coef,
                # (k, 3 m): every member's coefficients side by side, one product per batch
                "members": np.concatenate(list(members), axis=1),
                "n_members": len(members),
                "low": lo,
                "high": hi,
                "G": (np.asarray(m.load_["G_um_per_N"], float) if m.load_ is not None else np.zeros((S, 3))),
                # the map's weights on the gratings at their sizes: what a load signature's error
                # on each grating can make of the thermal part (its threshold during a load)
                "leak_weights": np.abs(coef[:S]),
            }
            self._map_box = (lo, hi, self.margin)
            basis = tm.get("unseen_basis")
            if basis is not None and np.asarray(basis, float).size:
                # the part of the correction only the twin's physics vouches for, and what the
                # gratings' and probes' noise alone makes of it
                W = unseen_operator(basis, tm["scale"], coef)
                self.map["unseen"] = W
                self.map["unseen_noise_sd"] = np.sqrt(np.clip(np.einsum("ka,kl,la->a", W, nz, W), 0, None))
            cal = tm.get("calibration")
            if cal is not None and "zero_sd_um" in cal:
                self.zero_sd_um = np.asarray(cal["zero_sd_um"], float)
            if cal is not None and "floor_sd_um" in cal and len(cols) == k and not self.heat_names:
                # the whole thermal part's noise at the instruments' own rates, the housing
                # calibration's leads and the zero state's error included
                # (PhysicalModel._noise_floor): the policy holds back what noise alone makes.
                # The twin population's noise is its scenarios' (a probe's noise every 60 s, low-
                # passed over 60 s: 2.4 times a probe's read every 10 s, 7.5 times a grating's
                # at 1 Hz) and stands for the map of a fallback set, which the simulation does
                # not run (ram3: 1.0 µm of dy and dz against 0.44 simulated)
                self.map_noise_sd_um = np.asarray(cal["floor_sd_um"], float)
                # held back up to the largest excursion a day of that noise reaches (firm's
                # k_sigma is the load step test's, for a noise judged frame by frame)
                self._floor_scale = np.asarray(cal.get("floor_k", [self.k_sigma] * 3), float) / self.k_sigma
            elif cal is not None and ("floor_sd_um" in cal or "noise_sd_um" in cal):
                # a fallback set, a file written before the zero state's error entered the floor,
                # or a model reading measured heat inputs: its calibration leaves the probes far
                # less to do (ram2's dz floor 0.25 µm), and with the threshold that low its
                # interval, scaled on halves of one training campaign, covered 0.62 of ram2's
                # thermal_c dz and 0.80 of ram3's thermal_b dy (docs/accuracy.md)
                floor = cal.get("floor_sd_um", cal.get("noise_sd_um"))
                self.map_noise_sd_um = np.maximum(self.map_noise_sd_um, np.asarray(floor, float))
            self.map_lost_sd_um = lost_information_sd(tm, cols, coef, float(m.map_ridge))
            if own is not None:
                # the probe's own interval holds what losing the probe costs; the gratings lost
                # with it add what they told the map beyond it
                probe_cols = [i for i in range(k) if i not in drop]
                alone = lost_information_sd(
                    tm, probe_cols, map_members(tm, probe_cols, float(m.map_ridge))[0], float(m.map_ridge)
                )
                self._interval_lost_sd_um = np.sqrt(np.clip(self.map_lost_sd_um**2 - alone**2, 0.0, None))
            # a fallback's map errs by what the lost gratings told the full one: the policy
            # holds back what that error alone could make, as it does the noise's, at
            # LOST_K_SIGMA of it where the noise counts at k_sigma
            self.map_noise_sd_um = np.hypot(
                self.map_noise_sd_um, LOST_K_SIGMA / float(m.load_k_sigma) * self.map_lost_sd_um
            )
            # without a probe it reads, the housing calibration is left out (its features then
            # pass through this set's state unchanged: take_state)
            cal_lost = cal is not None and (
                lost_housing or (lost_ambient and cal.get("ambient_tau_s") is not None)
            )
            self.cal = (
                None
                if cal is None or cal_lost
                else {
                    "leads_s": tuple(float(x) for x in cal["leads_s"]),
                    "ambient_tau_s": cal.get("ambient_tau_s"),
                    "heat_taus_s": tuple(float(x) for x in cal.get("heat_taus_s") or ()),
                    # the columns before the heat inputs' (housing, its leads, the ambient)
                    "k_probes": calibration_probe_columns(cal),
                    "heat_noise_sd": np.asarray(cal.get("heat_noise_sd_um", [0.0] * 3), float),
                    "coef": np.asarray(cal["coef"], float),
                    "low": np.asarray(cal["envelope_low"], float),
                    "high": np.asarray(cal["envelope_high"], float),
                }
            )
        # the thermal state observer (a Kalman filter on the twin's reduced thermal model), the
        # map's partner while its heat estimates stay plausible
        ob = getattr(m, "observer_", None)
        self.obs = None
        if ob is not None and self.map is not None and not self._lost_p:
            self.obs = ThermalObserver.from_dict(ob)
            self._obs_p = [self.probe_names.index(q) for q in ob["probes"]]
            self._obs_a = [self.probe_names.index(q) for q in ob["ambient"]]
            # the measured heat inputs the filter reads, columns of the heat inputs
            self._obs_h = [self.heat_names.index(h) for h in ob.get("measured", [])]
        self.last_observer_ok = np.ones(0, bool)
        var = self.thermal_resid_var + self.map_lost_sd_um**2
        if own is not None:
            # a probe's fallback: its own training errors, and its lost gratings' share
            var = np.maximum(var, np.asarray(own["resid_sd_um"], float) ** 2 + self._interval_lost_sd_um**2)
        if self.has_load:
            var = var + (self.C**2 @ self.F_sds[1] ** 2)
        self.expected_rms_error_um = np.sqrt(var)
        self._t = norm_ppf(0.975)
        # the Z positions the training was measured at (files before them: no check)
        tz = getattr(m, "trained_z_axis_mm_", None)
        self.trained_z_mm = None if tz is None else np.asarray(tz, float)
        self.z_tolerance_mm = float(m.z_tolerance_mm)
        self.link_loss_tau_s = float(getattr(m, "link_loss_tau_s", 0.0))
        self.unseen_relative_error = float(getattr(m, "unseen_relative_error", 0.0))
        self.thermal_relative_error = float(getattr(m, "thermal_relative_error", 0.0))
        self.last_thermal = np.zeros((0, 3))
        self.last_unseen = np.zeros((0, 3))
        self.last_passed = np.zeros((0, 3))
        self.state = None
        self._handed_over = False  # take_state left readings to take from the next frame
        self.last_flags = np.zeros((0, 3), np.uint8)
        self.last_force_N = np.zeros((0, 3))

    def reset(self):
        """Forget the filter and load-tracking state (a new zero state, a new campaign)."""
        self.state = None
        self._handed_over = False

    def take_state(self, other: PhysicalPredictor) -> None:
        """Go on from ``other``'s state: a predictor of the same model on another sensor set,
        which ran up to the frame before this one's next (the runtime's switch to a fallback
        when a grating is lost, and back when it returns).

        A fallback started from a fresh state in the middle of a run reads the gratings'
        thermal drift since the zero state as a load step and restarts every low-pass from
        zero: on ram2's thermal_b, a grating lost after 14 h left dx 38-158 µm off on a drift
        of 30.6. What both sets read carries over: the probes' and the housing's filters,
        the applied force and the step test's state, and each grating's low-passed reading and
        thermal offset. A grating this set leaves out reads zero, as it always does here; one
        it takes that ``other`` left out (a re-admission) starts from its first frame, its
        thermal offset then being all the reading the applied force does not explain.

        A probe ``other`` went without (held at its last reading) that this set reads is taken
        back on this set's first frame (:meth:`_rebase_probes`)."""
        st = copy.deepcopy(other.state) if other.state else None
        if not st:
            self.reset()
            return
        back = [j for j, q in enumerate(self.probe_names) if q in other.exclude and q not in self.exclude]
        if back:
            st["probe_rebase"] = back
        names = self.sensor_names
        mine = [s not in self.exclude for s in names]
        theirs = [s not in other.exclude for s in names]
        m = st.get("map")
        if m is not None and m.get("e") is not None:
            y, t = m["e"]
            y = np.array(y, float)
            for i, (a, b) in enumerate(zip(mine, theirs)):
                y[i] = 0.0 if not a else (np.nan if not b else y[i])
            m["e"] = (y, t)
        if self.has_load:
            # the load tracker's state as the last set that ran it left it: a set without any
            # grating passes it on untouched (predict), so that the gratings back after a lost
            # link read a load held through the loss against the offsets it had; started
            # afresh, they took its whole reading into their thermal offsets and the load was
            # gone for good (ram2's thermal_c, the link lost for 1 h under 2500 N of Fx: dx
            # 340 µm off on every later plateau)
            old = st.get("load")
            where = {n: j for j, n in enumerate(old["names"])} if old else {}
            L = dict(old or {})
            L["names"] = [names[i] for i in self._keep]
            for key, fill in (("offset", np.nan), ("fast", 0.0), ("quick", 0.0), ("recent", 0.0)):
                v = L.get(key)
                if v is None:
                    if key == "offset":
                        L[key] = np.full(len(self._keep), np.nan)
                    continue
                v = np.asarray(v, float)
                L[key] = np.array([v[where[names[i]]] if names[i] in where else fill for i in self._keep])
            st["load"] = L
        self.state = st
        self._handed_over = True

    def _rebase_probes(self, state, dT0):
        """``state`` with the probes :meth:`take_state` marked as back taken at their reading
        ``dT0`` (P,) K on the first frame: the set that went without them ran its filters on
        their last reading, held; each filter state they enter is moved by the probe's change
        over the gap, so the gap reads as a slow change the filters had followed, not as a
        step (a housing probe back after an hour of warming would otherwise be a lead of that
        hour's warming: ~10 µm of dz per K on ram2). States the set without them passed on
        unchanged (the housing calibration's) are time-stamped: their filters step over the
        gap by themselves."""
        back = state.get("probe_rebase")
        if not back:
            return state
        state = {k: v for k, v in state.items() if k != "probe_rebase"}
        held = np.asarray(state.get("probe_last", np.zeros(len(self.probe_names))), float)
        jump = np.zeros(len(self.probe_names))
        jump[back] = np.nan_to_num(np.asarray(dT0, float)[back] - held[back])
        m = state.get("map")
        if m is not None:
            m = dict(m)
            dh = float(housing_mean(jump[None, :], self._h_idx)[0, 0])
            for key, by in [("in", jump)] + [(f"lead{tau:g}", dh) for tau in MAP_LEADS_S]:
                if m.get(key) is not None and m[key][1] is not None:
                    y, t = m[key]
                    m[key] = (np.asarray(y, float) + by, t)
            state["map"] = m
        return state

    def _resume(self, state, e_keep0, e_all0):
        """``state`` with what :meth:`take_state` left pending (NaN) taken from the first frame:
        ``e_keep0`` (the kept gratings' elongations), ``e_all0`` (every grating's) µm."""
        L = state.get("load")
        if L is not None and np.isnan(np.asarray(L["offset"], float)).any():
            L = dict(L)
            applied = np.asarray(L.get("force", np.zeros(3)), float)
            off = np.array(L["offset"], float)
            todo = np.isnan(off)
            read = self.G @ applied  # a held load's share of each reading
            off[todo] = (e_keep0 - read)[todo]
            L["offset"] = off
            for key in ("fast", "quick"):
                if L.get(key) is not None:
                    v = np.array(L[key], float)
                    v[todo] = read[todo]
                    L[key] = v
            if L.get("recent") is not None:
                L["recent"] = np.where(todo, 0.0, np.asarray(L["recent"], float))
            state = {**state, "load": L}
        m = state.get("map")
        if m is not None and m.get("e") is not None and np.isnan(np.asarray(m["e"][0], float)).any():
            y, t = m["e"]
            force = _held_force(state)
            now = e_all0 - (self.map["G"] @ force if self.has_load else 0.0)
            y = np.where(np.isnan(y), now, y)
            state = {**state, "map": {**m, "e": (y, t)}}
        return state

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
        limit = chi2_ppf(1 - self.p_contra, dof)
        for j in range(S):
            keep = np.arange(S) != j
            op, _, _ = gls_operator(Ga[keep], cov[np.ix_(keep, keep)])
            r = y[keep] - Ga[keep] @ (op @ y[keep])
            if r @ np.linalg.lstsq(cov[np.ix_(keep, keep)], r, rcond=None)[0] <= limit:
                return True
        return False

    def _quantile(self, kind, q, dof=None):
        """Quantiles the load tracker asks for on every batch, each computed once
        (``chi2``: the ``q`` quantile with ``dof``; ``isf``: the normal's upper ``q``)."""
        cache = self.__dict__.setdefault("_quantiles", {})
        key = (kind, float(q), dof)
        if key not in cache:
            cache[key] = float(chi2_ppf(q, dof) if kind == "chi2" else norm_isf(q))
        return cache[key]

    def _frame_terms(self, dt):
        """The load tracker's per-frame constants at frame intervals ``dt`` (n,) s: the offset's
        gain, the recent-shift memory, the fast and hold gains, the noise each low-pass leaves
        (fast, hold, their difference: :func:`fast_hold_noise`), the drift allowance (n, 3) N,
        the step test's threshold in sigma, and the thermal lag's gain (``LOAD_TREND_S``) and
        the noise its low-pass leaves (0 where dt = 0: nothing learnt)."""
        alpha = 1.0 - np.exp(-dt / self.offset_tau_s)
        forget = np.exp(-dt / LOAD_HOLD_S)
        b_fast = 1.0 - np.exp(-dt / LOAD_FAST_S)
        b_hold = 1.0 - np.exp(-dt / LOAD_HOLD_S)
        # variance left by a first-order low-pass of white noise, per unit of the training
        # frame's variance: (frame / dt) b / (2 - b); 1 for a frame without history. A frame
        # slower than the training's fastest (``noise_frame_dt_s``) carries the training
        # frame's variance, a faster one its density (PhysicalModel._frame_noise_var).
        fdt = self.noise_frame_dt_s
        rate = np.maximum(fdt / np.where(dt > 0, dt, fdt), 1.0)
        k_fast = np.where(dt > 0, rate * b_fast / (2.0 - b_fast), 1.0)
        k_hold = np.where(dt > 0, rate * b_hold / (2.0 - b_hold), 1.0)
        kd = fast_hold_noise(dt, rate, b_fast, b_hold)
        b_trend = 1.0 - np.exp(-dt / LOAD_TREND_S)
        k_trend = rate * b_trend / (2.0 - b_trend)
        b_follow = 1.0 - np.exp(-dt / LOAD_FOLLOW_S)
        k_follow = np.where(dt > 0, rate * quick_fast_noise(b_follow, b_fast), 1.0)
        lag = self.drift_N_per_s[None, :] * np.maximum(dt, self.offset_tau_s)[:, None]
        look = np.maximum(dt, 2.0 * LOAD_FAST_S)
        if len(dt) and look.min() == look.max():  # frames faster than the low-pass: one look each
            look_s, at = look[:1], np.zeros(len(dt), int)
        else:
            look_s, at = np.unique(look, return_inverse=True)
        k_start = np.maximum(
            self.k_sigma,
            np.array([self._quantile("isf", 0.5 * LOAD_FALSE_STARTS_PER_H * s / 3600.0) for s in look_s])[
                at.ravel()
            ]
            if len(dt)
            else np.zeros(0),
        )
        return (
            alpha,
            forget,
            b_fast,
            b_hold,
            k_fast,
            k_hold,
            kd,
            lag,
            k_start,
            b_trend,
            k_trend,
            b_follow,
            k_follow,
        )

    def _one_frame_terms(self, dt):
        """:meth:`_frame_terms` of one frame interval as Python floats (k_fast, kd, lag (3,),
        k_start), computed once per distinct interval: an interrogator's frames come at a
        handful of intervals (a float clock's rounding included), and each is the vectorised
        arithmetic's own result."""
        cache = self.__dict__.setdefault("_terms_1", {})
        hit = cache.get(dt)
        if hit is None:
            if len(cache) >= 256:  # a jittered clock: forget, do not grow
                cache.clear()
            _, _, _, _, k_fast, _, kd, lag, k_start, _, _, _, _ = self._frame_terms(np.array([dt]))
            hit = cache[dt] = (float(k_fast[0]), float(kd[0]), lag[0].tolist(), float(k_start[0]))
        return hit

    #: Run stretches without a load transition vectorised (:meth:`_steady_run`); False runs
    #: every frame through the per-frame recursion (the reference the fast path is tested on).
    steady_fast_path = True

    def _linear_run(self, e, dt, applied, offset, xs, f_hold):
        """The load tracker's filters over frames ``e`` (n, S) at intervals ``dt`` (n,) while the
        applied force stays ``applied`` (3,), vectorised: the low-passed gratings
        ``y = xs + offset`` (``LOAD_FAST_S``), the thermal offset following ``e - G applied``
        (``offset_tau_s``) and the one before each frame, the fast force estimate (n, 3) and its
        slow estimate (``LOAD_HOLD_S``). Linear, so equal to the per-frame recursion to rounding."""
        e = np.asarray(e, float)
        y = first_order_recursion(dt / LOAD_FAST_S, e, xs + offset)
        off = first_order_recursion(dt / self.offset_tau_s, e - self.G @ applied, offset)
        off_prev = np.vstack([offset[None, :], off[:-1]])
        f_fast = (y - off_prev) @ self.ops[0].T
        return y, off, off_prev, f_fast, first_order_recursion(dt / LOAD_HOLD_S, f_fast, f_hold)

    def _steady_run(
        self, e, dt, applied, offset, xs, f_hold, recent, trend, quiet, k_fast, k_start, lag, kd, noise
    ):
        """Frames of :meth:`_track_load` while no load transition is under way, vectorised.

        With the applied force fixed the recursion is linear: the low-passed gratings
        ``y = xs + offset`` follow ``e`` (``LOAD_FAST_S``), the thermal offset follows
        ``e - G applied`` (``offset_tau_s``), the slow force estimate follows the fast one
        (``LOAD_HOLD_S``), ``recent`` sums the offset's shifts with a ``LOAD_HOLD_S``
        memory and ``trend`` low-passes the reading's lag behind the applied force
        (``LOAD_TREND_S``) from ``3 offset_tau_s`` after the last transition (``quiet``, s since
        it); the live noise estimate (:meth:`_noise_excess`) learns from every
        frame. They are formed for every frame, the step test is evaluated on all of them, and
        the frames before the first one whose test fires are accepted. Returns the number of
        frames accepted and the state after them (offset, xs, f_hold, recent, trend, quiet, noise)."""
        y, off, off_prev, f_fast, hold = self._linear_run(e, dt, applied, offset, xs, f_hold)
        learnt = self._noise_excess(f_fast - hold, dt, kd, noise)
        excess = self._excess(np.vstack([noise[None, :], learnt[:-1]]))
        k = self.k_sigma
        sd_fast = self.F_sd[None, :] * np.sqrt(k_fast[:, None] * excess)
        sq = f_fast**2
        cross = self.relative_error * np.sqrt(np.maximum(sq.sum(axis=1, keepdims=True) - sq, 0.0)) / k
        limit = np.maximum(np.hypot(k_start[:, None] * sd_fast, k * lag), k * cross)
        fires = (np.abs(f_fast - applied[None, :]) > limit).any(axis=1)
        m = int(np.argmax(fires)) if fires.any() else len(e)
        if m == 0:
            return 0, offset, xs, f_hold, recent, trend, quiet, noise
        shift = off[:m] - off_prev[:m]
        rec = first_order_recursion(dt[:m] / LOAD_HOLD_S, shift, recent, gain=False)
        q = quiet + np.cumsum(dt[:m])
        learn = np.where(q >= self.trend_after_s, dt[:m] / LOAD_TREND_S, 0.0)
        tr = first_order_recursion(learn, f_fast[:m] - applied[None, :], trend)
        return (
            m,
            off[m - 1].copy(),
            y[m - 1] - off[m - 1],
            hold[m - 1].copy(),
            rec[m - 1].copy(),
            tr[m - 1].copy(),
            float(q[-1]),
            learnt[m - 1].copy(),
        )

    def _steady_frame(self, e, time_s, state, new_state):
        """One frame of :meth:`_track_load` (a runtime batch of 1) while no load transition is
        under way: :meth:`_steady_run`'s arithmetic for n = 1 on Python floats, where numpy's
        per-call cost on 3 to 8 numbers was the time. Returns what :meth:`_track_load` does, or
        None where it does not apply (no state yet, a transition under way) or where the frame's
        step test fires: the general path takes that frame, as it would have."""
        st = state or {}
        t_last = st.get("t")
        if st.get("fast") is None or t_last is None or any(v > 0 for v in _floats(st["settle"])):
            return None
        t1 = self.nominal_dt_s + t_last if time_s is None else float(np.ravel(time_s)[0])
        dt = max(t1 - t_last, 0.0)
        k_fast, kd, lag, k_start = self._one_frame_terms(dt)
        e = e[0].tolist()
        offset, xs, applied = _floats(st["offset"]), _floats(st["fast"]), _floats(st["force"])
        f_hold, recent, noise = _floats(st["hold"]), _floats(st["recent"]), _floats(st["noise"])
        S = len(offset)
        quiet = float(st.get("quiet", 0.0)) + dt
        y = first_order_step(dt / LOAD_FAST_S, e, [xs[j] + offset[j] for j in range(S)])
        Ga = _row_products(self._G_rows, applied)
        u = [e[j] - Ga[j] for j in range(S)]
        off = first_order_step(dt / self.offset_tau_s, u, offset)
        x = [y[j] - offset[j] for j in range(S)]
        f_fast = _row_products(self._op_rows, x)
        hold = first_order_step(dt / LOAD_HOLD_S, f_fast, f_hold)
        learnt = self._noise_step(f_fast, hold, dt, kd, noise)
        k = self.k_sigma
        sq = [f * f for f in f_fast]
        total = sq[0] + sq[1] + sq[2]
        for a in range(3):
            excess = max(noise[a] / max(noise[3], 1e-12), 1.0)
            sd_fast = self._F_sd[a] * math.sqrt(k_fast * excess)
            cross = self.relative_error * math.sqrt(max(total - sq[a], 0.0)) / k
            if abs(f_fast[a] - applied[a]) > max(math.hypot(k_start * sd_fast, k * lag[a]), k * cross):
                return None
        new_state["load"] = {
            **st,
            "offset": off,
            "fast": [y[j] - off[j] for j in range(S)],
            "hold": hold,
            "trend": first_order_step(
                dt / LOAD_TREND_S if quiet >= self.trend_after_s else 0.0,
                [f_fast[a] - applied[a] for a in range(3)],
                _floats(st.get("trend", [0.0, 0.0, 0.0])),
            ),
            "quiet": quiet,
            "recent": first_order_step(
                dt / LOAD_HOLD_S, [off[j] - offset[j] for j in range(S)], recent, gain=False
            ),
            "noise": learnt,
            "t": t1,
        }
        self.last_transition = np.zeros((1, 3), bool)
        return np.array([applied]), np.zeros(1, bool), np.zeros(1, bool)

    def _noise_step(self, f_fast, f_hold, dt, kd, noise):
        """:meth:`_noise_excess` of one frame on Python floats: the running sums (4,) after a
        frame of fast and hold readings ``f_fast``, ``f_hold`` (3,) N at interval ``dt`` s and
        difference noise ``kd``."""
        sd2 = self._sd2
        # as _noise_excess: a frame after a gap longer than the filters' memory counts as 1
        q = [
            min((f_fast[a] - f_hold[a]) ** 2 / (sd2[a] * kd), 100.0) if sd2[a] * kd > 0 else 1.0
            for a in range(3)
        ]
        return first_order_step(dt / NOISE_LEARN_S, [dt * q[0], dt * q[1], dt * q[2], dt], noise, gain=False)

    def _noise_excess(self, d, dt, kd, noise):
        """Running sums (n, 4) of the live noise estimate after each frame, from ``noise``
        (4,: the three components' weighted squares, then their shared weight, s): the fast
        minus the hold reading ``d`` (n, 3) N is noise while no load moves
        (heat moves it by its drift over ``LOAD_HOLD_S``, a little); its square over what the
        training noise would give at that frame interval (``kd``, :func:`fast_hold_noise`) is
        averaged, weighted by frame time, over ``NOISE_LEARN_S``. A stream noisier than the
        training (a served campaign interpolated to a faster rate, an interrogator that averages
        less) has its steps judged against its own noise instead of starting false loads;
        a quieter one keeps the training's threshold (:meth:`_excess`)."""
        sd2 = np.where(self.F_sd > 0, self.F_sd**2, np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            # (inf x 0, a component not read after such a gap, is NaN: no noise, as below)
            den = sd2[None, :] * kd[:, None]
            # (10 sigma: a spike no more). A frame after a gap longer than both filters' memory
            # (kd = 0: the fast and hold readings are the same frame) tells nothing of the
            # noise and counts as the training's; its 0/0 made the estimate NaN for good
            q = np.where(den > 0, np.minimum(d**2 / den, 100.0), 1.0)
        return first_order_recursion(
            dt / NOISE_LEARN_S, dt[:, None] * np.hstack([q, np.ones((len(dt), 1))]), noise, gain=False
        )

    @staticmethod
    def _excess(noise):
        """Factor (…, 3) on the training's noise variance the step test uses, from running sums
        (…, 4): the live estimate's ratio, never below 1."""
        return np.maximum(noise[..., :3] / np.maximum(noise[..., 3:], 1e-12), 1.0)

    #: a fit's memo of load-tracker results from rest (:meth:`_track_load_from_rest`), or None
    load_memo: dict | None = None

    #: what the load tracker reads of the predictor besides its input (a memo's key)
    _LOAD_ATTRS = (
        "G", "ops", "F_sd", "active", "dof", "k_sigma", "p_contra", "relative_error", "max_force_N",
        "noise_cov", "nuisance_cov", "nominal_dt_s", "noise_frame_dt_s", "offset_tau_s", "settle_s",
        "trend_after_s", "drift_N_per_s", "steady_fast_path",
    )  # fmt: skip

    def _track_load_from_rest(self, e, time_s, state, new_state, raw=False):
        """:meth:`_track_load`, or its result on the same inputs from a fit's memo (``load_memo``).

        The load tracker reads the gratings alone, uncompensated (:func:`grating_map`). A fit
        serves each load-free training campaign once per probe set and calibration (the
        intervals of every probe's and pair's fallback, the held-out halves): ~20 times on
        ram2, where the probes and the housing calibration change what follows and not the
        tracker's input. From rest (no state), the same elongations, clock and load parameters
        give the same result: it is taken once per fit and set of gratings."""
        memo = self.load_memo
        if memo is None or state:
            return self._track_load(e, time_s, state, new_state, raw)
        from fbgcomp.structure.cache import array_digest  # noqa: PLC0415 - fit-time only

        clock = () if time_s is None else (np.asarray(time_s, float),)
        params = (getattr(self, name) for name in self._LOAD_ATTRS)
        key = (array_digest(np.asarray(e, float), *clock, *params), bool(raw))
        if key not in memo:
            out = self._track_load(e, time_s, state, new_state, raw)
            memo[key] = (out, new_state["load"], self.last_transition)
        (force, clamped, refused), load_state, transition = memo[key]
        new_state["load"] = copy.deepcopy(load_state)
        self.last_transition = transition.copy()
        return force.copy(), clamped.copy(), refused.copy()

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
        if n == 1 and self.steady_fast_path and not (raw or listen):
            one = self._steady_frame(e, time_s, state, new_state)
            if one is not None:
                return one
        state = state or {}
        offset = np.array(state.get("offset", np.zeros(S)), float)
        applied = np.array(state.get("force", np.zeros(3)), float)
        xs = state.get("fast")  # low-passed e - offset (S,)
        # e - offset low-passed over LOAD_FOLLOW_S, kept only through a transition (S,) or None
        xq = state.get("quick")
        xq = None if xq is None else np.array(xq, float)
        f_hold = state.get("hold")  # slow estimate of the force (3,)
        mean_sum = np.array(state.get("mean_sum", np.zeros(3)), float)  # since the load stopped
        mean_w = np.array(state.get("mean_w", np.zeros(3)), float)
        level_from = np.array(state.get("from", np.zeros(3)), float)  # when the transition began
        # the reading's thermal lag behind the applied force (LOAD_TREND_S), the seconds since
        # the offset froze for a transition (one clock: it freezes for every component while
        # any moves), and their time-weighted sum over each component's mean window
        trend = np.array(state.get("trend", np.zeros(3)), float)
        quiet = float(state.get("quiet", 0.0))  # s since the last transition
        since = float(state.get("since", 0.0))
        mean_tsum = np.array(state.get("mean_tsum", np.zeros(3)), float)
        # the line through each moving component's quick reading (ramp_line)
        line = np.array(state.get("line", np.zeros((3, 6))), float)
        # what the offset took in over the last ~LOAD_HOLD_S: a load's first moments, before its
        # step is taken, are given back when it is (else each step leaves ~1 % in the offset)
        recent = np.array(state.get("recent", np.zeros(S)), float)
        # the live noise estimate's running sums (weighted squares, weights), from the prior
        noise = np.array(state.get("noise", np.full(4, NOISE_PRIOR_S)), float)
        t_last = state.get("t")
        t = (
            np.arange(1, n + 1) * self.nominal_dt_s + (t_last or 0.0)
            if time_s is None
            else np.asarray(time_s, float).ravel()
        )
        dt = np.diff(np.concatenate([[t[0] if t_last is None else t_last], t]))
        dt = np.clip(dt, 0.0, None)
        first = xs is None
        xs = np.zeros(S) if first else np.array(xs, float)
        f_hold = np.zeros(3) if f_hold is None else np.array(f_hold, float)
        (
            alpha,
            forget,
            b_fast,
            b_hold,
            k_fast,
            k_hold,
            kd,
            lag,
            k_start,
            b_trend,
            k_trend,
            b_follow,
            k_follow,
        ) = self._frame_terms(dt)
        op = self.ops[0]
        Ga = self.G
        force = np.zeros((n, 3))
        transition = np.zeros((n, 3), bool)  # components following the reading, per frame
        clamped = np.zeros(n, bool)
        settle = np.array(state.get("settle", np.zeros(3)), float)  # s left of a load transition
        refused = np.zeros(n, bool)
        if raw:  # the GLS reading beyond the tracked offset, which stays as it was
            force[:] = (e - offset) @ op.T
        elif listen and n:  # no step is taken: the filters alone, vectorised
            y, off, _, f_fast, hold = self._linear_run(e, dt, applied, offset, xs, f_hold)
            force[:] = f_fast - applied
            offset, xs, f_hold, xq = off[-1], y[-1] - off[-1], hold[-1], None
        act = self.active
        chi2_limit = self._quantile("chi2", 1 - self.p_contra, max(self.dof, 1))
        k = self.k_sigma
        # Frame by frame the state is held in Python floats, one list per vector (3 force
        # components, S gratings): numpy's per-call cost on a few numbers was the time of a load
        # transition's frame (ram2's static_xyz at 100 Hz, 85 % of its frames in a transition:
        # 198 µs a frame on arrays, 38 on floats; benchmarks/bench_load_tracker.py). The
        # arithmetic is numpy's, operation for operation; only the sums of the GLS and signature
        # products run in another order (tests/test_physical.py compares the vectorised steady
        # stretches with it to 1e-8).
        rel, F, max_f = self.relative_error, self._F_sd, self.max_force_N.tolist()
        op_rows, G_rows, settle_s = self._op_rows, self._G_rows, self.settle_s
        A, J = range(3), range(S)
        offset, applied, xs, f_hold = offset.tolist(), applied.tolist(), xs.tolist(), f_hold.tolist()
        xq = None if xq is None else xq.tolist()
        mean_sum, mean_w, mean_tsum = mean_sum.tolist(), mean_w.tolist(), mean_tsum.tolist()
        level_from, trend, line = level_from.tolist(), trend.tolist(), line.tolist()
        recent, noise, settle = recent.tolist(), noise.tolist(), settle.tolist()
        i, slow_until = -1, 0
        while i + 1 < (0 if raw or listen else n):
            i += 1
            if (
                self.steady_fast_path
                and i >= slow_until
                and not (first and i == 0)
                and not any(s > 0 for s in settle)
            ):
                # No transition under way: the recursion is linear until the first frame whose
                # step test fires, so run it vectorised up to that frame, at most STEADY_WINDOW
                # frames at a time (equal to the per-frame recursion to rounding, not bit for
                # bit: tests/test_physical.py). Where a test fires at once (a refused step
                # repeating), the next STEADY_BACKOFF frames go through the recursion.
                w = slice(i, min(i + STEADY_WINDOW, n))
                m, *run = self._steady_run(
                    e[w],
                    dt[w],
                    np.array(applied),
                    np.array(offset),
                    np.array(xs),
                    np.array(f_hold),
                    np.array(recent),
                    np.array(trend),
                    quiet,
                    k_fast[w],
                    k_start[w],
                    lag[w],
                    kd[w],
                    np.array(noise),
                )
                offset, xs, f_hold, recent, trend = (v.tolist() for v in run[:5])
                quiet, noise = run[5], run[6].tolist()
                force[i : i + m] = applied
                if m == 0:
                    slow_until = i + STEADY_BACKOFF
                i += m
                if i >= n:
                    break
                if m == w.stop - w.start:  # the window ran out before any test fired
                    i -= 1
                    continue
            dti = float(dt[i])
            ei = e[i].tolist()
            x_now = [ei[j] - offset[j] for j in J]
            # the low-pass starts at the zero state (no load, by its definition), not at the
            # first frame: one raw frame carries the whole frame noise, which the step test,
            # judging low-passed noise, took for a load (a twin static campaign of ram2's
            # description, seed 16: -40 N of Fy at 2 s, held as dy -8.5 to +4 µm throughout)
            base = xs if xq is None else xq
            bq, bf, bh = float(b_follow[i]), float(b_fast[i]), float(b_hold[i])
            xq = [base[j] + bq * (x_now[j] - base[j]) for j in J]
            xs = [xs[j] + bf * (x_now[j] - xs[j]) for j in J]
            f_fast = _row_products(op_rows, xs)
            f_hold = [f_hold[a] + bh * (f_fast[a] - f_hold[a]) for a in A]
            excess = [max(noise[a] / max(noise[3], 1e-12), 1.0) for a in A]
            kf = float(k_fast[i])
            sd_fast = [F[a] * math.sqrt(kf * excess[a]) for a in A]
            sq = [f * f for f in f_fast]
            total = sq[0] + sq[1] + sq[2]
            cross = [rel * math.sqrt(max(total - sq[a], 0.0)) / k for a in A]
            moving = [s > 0 for s in settle]
            # noise is judged at the false-start rate; the drift allowance (already a 99th
            # percentile of what heat did in training) and cross-talk at k sigma
            ks, lg = float(k_start[i]), lag[i].tolist()
            limit = [max(math.hypot(ks * sd_fast[a], k * lg[a]), k * cross[a]) for a in A]
            take = [not moving[a] and abs(f_fast[a] - applied[a]) > limit[a] for a in A]
            if not (any(take) or any(moving)):  # a steady frame: the noise estimate learns
                noise = self._noise_step(f_fast, f_hold, dti, float(kd[i]), noise)
                quiet += dti
                if quiet >= self.trend_after_s:
                    bt = float(b_trend[i])
                    trend = [trend[a] + bt * (f_fast[a] - applied[a] - trend[a]) for a in A]
            else:
                quiet = 0.0
            if any(take) and self.dof >= 1:
                # a step no load explains (one grating jumps: a fibre slips, a connector is
                # re-seated) is refused, and the offset absorbs it
                new = np.array(
                    [f_fast[a] if take[a] or moving[a] else applied[a] for a in A]
                )  # moving ones follow too
                y = np.array(xs)
                r = y - Ga @ new
                g = rel * (Ga[:, act] @ (new - np.array(applied))[act])
                cov = self.noise_cov * kf * max(excess) + self.nuisance_cov + np.outer(g, g)
                if r @ np.linalg.lstsq(cov, r, rcond=None)[0] > chi2_limit and self._one_grating(y, cov):
                    refused[i] = True
                    take = [False, False, False]
            if any(take):
                if not any(s > 0 for s in settle):  # the offset freezes from this frame on
                    offset = [offset[j] - recent[j] for j in J]
                    xs = [xs[j] + recent[j] for j in J]
                    xq = [xq[j] + recent[j] for j in J]
                    f_fast = _row_products(op_rows, xs)
                    recent = [0.0] * S
                    since = 0.0
                fresh = [take[a] and not settle[a] > 0 for a in A]
                level_from = [applied[a] if fresh[a] else level_from[a] for a in A]
                line = [[0.0] * 6 if fresh[a] else line[a] for a in A]
                settle = [settle_s if take[a] else settle[a] for a in A]
                # the slow estimate runs on from before the step: while it lags the fast one the
                # load is still moving, so a ramp does not enter the level's mean (it was set to
                # the fast reading here, and a 300 N step taken mid-ramp ended at 281 N)
            moving = [s > 0 for s in settle]
            transition[i] = moving
            if any(moving):
                # in a transition: follow the low-passed force; still moving while the fast and
                # slow estimates disagree beyond their noise
                kh = float(k_hold[i])
                sd_hold = [F[a] * math.sqrt(kh * excess[a]) for a in A]
                still = [
                    moving[a]
                    and abs(f_fast[a] - f_hold[a]) > k * max(math.hypot(sd_fast[a], sd_hold[a]), cross[a])
                    for a in A
                ]
                settle = [settle_s if still[a] else settle[a] for a in A]
                since += dti
                mean_sum = [0.0 if still[a] else mean_sum[a] + dti * f_fast[a] for a in A]
                mean_tsum = [0.0 if still[a] else mean_tsum[a] + dti * since for a in A]
                mean_w = [0.0 if still[a] else mean_w[a] + dti for a in A]
                # while the load ramps (the quick reading stands clear of the fast one beyond
                # their difference's noise) the quick reading; else the fast one
                f_quick = _row_products(op_rows, xq)
                kq = float(k_follow[i])
                ramping = [
                    still[a] and abs(f_quick[a] - f_fast[a]) > k * (F[a] * math.sqrt(kq * excess[a]))
                    for a in A
                ]
                settle = [max(settle[a] - dti, 0.0) for a in A]
                ended = [moving[a] and settle[a] <= 0 and mean_w[a] > 0 for a in A]
                # the level is the mean reading less the thermal lag it carried into the
                # transition (trend = r offset_tau_s) and the drift since the offset froze
                # (r x the window's mean time since then): under thermal_b's radiant drift
                # (-1 N/s of Fx) a 300 N step ended 35 N low, 5 µm of dx held for its duration
                # (the lag's own noise is not applied: firm shrinkage at k sigma of the noise
                # the LOAD_TREND_S low-pass leaves; on ram2's thermal_c, 2.6 N at rest)
                kt = float(k_trend[i])
                # while the load moves, the reading (the quick one while it ramps); once it has
                # stopped, the level it will end at, as far as the frames since then tell it,
                # and zero where that is a release to a level the step test cannot tell from
                # zero (as at the end, below). The fast reading alone carried a frame's noise
                # through the whole settling time: at 1 frame/s on the twin's combined campaign
                # (165 N of Fy a frame) its 2000 N release wandered 27-68 µm of dy for 15 s after
                # the load was off; the running mean alone, correlated noise, 17-32 µm.
                chosen = []
                for a in A:
                    lagged = P.firm1(trend[a], F[a] * math.sqrt(kt * excess[a]), k, 2 * k)
                    mw = mean_w[a] if mean_w[a] > 0 else 1.0
                    level = mean_sum[a] / mw - lagged * (1.0 + mean_tsum[a] / mw / self.offset_tau_s)
                    settling = moving[a] and not still[a] and mean_w[a] > 0
                    if ramping[a]:
                        chosen.append(f_quick[a])
                    elif still[a]:
                        chosen.append(f_fast[a])
                    elif settling and abs(level) <= limit[a] and abs(level) < abs(level_from[a]):
                        chosen.append(0.0)
                    elif settling:
                        chosen.append(level)
                    else:
                        chosen.append(f_fast[a] if moving[a] else applied[a])
                # while it still moves, at frames of RAMP_LINE_DT_S or longer, the line through
                # the quick reading since the transition began, once it holds RAMP_LINE_MIN
                # frames (ramp_line); its noise is the quick low-pass's (b / (2 - b) of a
                # frame's variance) where k_fast holds the fast one's
                k_q = kf * (bq / (2.0 - bq)) / (bf / (2.0 - bf)) if bf > 0 else 1.0
                drawn, line = ramp_line_floats(
                    line,
                    [still[a] and dti >= RAMP_LINE_DT_S for a in A],
                    float(t[i]),
                    f_quick,
                    [F[a] * math.sqrt(k_q * excess[a]) for a in A],
                    k,
                )
                applied = [drawn[a] if still[a] and math.isfinite(drawn[a]) else chosen[a] for a in A]
                # a release that ends at a level the step test could not tell from zero ends at
                # zero: that level would not have started a load from rest, and held it stays
                # for good (the offset takes in what it leaves). On the twin's combined campaign
                # a 2000 N release settled at 117 N of correlated noise and held 24.6 µm of dy
                # for the remaining six hours. Only a release: a small load just taken stays
                # (zeroed, the offset would take it in and its removal start a false load).
                for a in A:
                    if ended[a] and abs(applied[a]) <= limit[a] and abs(applied[a]) < abs(level_from[a]):
                        applied[a] = 0.0
                    if moving[a] and not settle[a] > 0:
                        mean_sum[a] = mean_tsum[a] = mean_w[a] = 0.0
            if any(abs(applied[a]) > max_f[a] for a in A):
                clamped[i] = True
                applied = [min(max(applied[a], -max_f[a]), max_f[a]) for a in A]
            if not any(s > 0 for s in settle):
                al, fg = float(alpha[i]), float(forget[i])
                Ga_applied = _row_products(G_rows, applied)
                shift = [al * (ei[j] - Ga_applied[j] - offset[j]) for j in J]
                offset = [offset[j] + shift[j] for j in J]
                xs = [xs[j] - shift[j] for j in J]  # xs is relative to the offset
                recent = [recent[j] * fg + shift[j] for j in J]
                xq = None  # no transition: the quick reading starts anew from xs at the next
            force[i] = applied
        new_state["load"] = {
            # the gratings the per-grating arrays are of (take_state maps them by name)
            "names": [self.sensor_names[i] for i in self._keep],
            "offset": np.array(offset),
            "force": np.array(applied),
            "settle": np.array(settle),
            "fast": np.array(xs),
            "quick": None if xq is None else np.array(xq),
            "hold": np.array(f_hold),
            "mean_sum": np.array(mean_sum),
            "mean_w": np.array(mean_w),
            "from": np.array(level_from),
            "recent": np.array(recent),
            "trend": np.array(trend),
            "quiet": quiet,
            "since": since,
            "mean_tsum": np.array(mean_tsum),
            "line": np.array(line),
            "noise": np.array(noise),
            "t": float(t[-1]) if len(t) else t_last,
        }
        self.last_transition = transition
        return force, clamped, refused

    def predict(
        self,
        wavelength_nm,
        temperature_C,
        wavelength_zero_nm,
        temperature_zero_C,
        *,
        time_s=None,
        z_axis_mm=None,
        raw=False,
        thermal_policy=True,
    ):
        """Applied TTP deviation (n, 3) µm and 95 % half-width (n, 3) µm; ``raw=True`` skips
        the policy (envelope clipping, axis clamp, load gating) for diagnosis.

        ``temperature_C`` holds the probes (°C) and, after them, the measured heat inputs (W)
        of a model fitted with them (``heat_names``); ``temperature_zero_C`` likewise."""
        wl = np.atleast_2d(np.asarray(wavelength_nm, dtype=float))
        n = wl.shape[0]
        P_ = len(self.probe_names)
        heat_W = np.atleast_2d(np.asarray(temperature_C, float))[:, P_:]
        heat_zero_W = np.asarray(temperature_zero_C, float)[P_:]
        temperature_C = np.atleast_2d(np.asarray(temperature_C, float))[:, :P_]
        temperature_zero_C = np.asarray(temperature_zero_C, float)[:P_]
        flags = np.zeros((n, 3), np.uint8)
        spread = np.zeros((n, 3))
        unseen = np.zeros((n, 3))
        passed = np.ones((n, 3))  # without the policy's threshold the whole correction passes
        state = self.state or {}
        new_state = {}
        lost_p = self._lost_p
        if lost_p:  # a lost probe reads its last change (0 before it had one), held
            held = np.asarray(state.get("probe_last", np.zeros(P_)), float)[lost_p]
            zero = np.nan_to_num(temperature_zero_C[lost_p])
            temperature_zero_C = temperature_zero_C.copy()
            temperature_zero_C[lost_p] = zero
            temperature_C = temperature_C.copy()
            temperature_C[:, lost_p] = zero + held
        dT = np.atleast_2d(np.asarray(temperature_C, float)) - np.asarray(temperature_zero_C, float)
        new_state["probe_last"] = dT[-1].copy() if n else state.get("probe_last")
        w = wl.copy()
        w0 = np.asarray(wavelength_zero_nm, float)
        lost = [i for i, s in enumerate(self.sensor_names) if s in self.exclude]
        w[:, lost] = w0[lost]
        e_all = self._fmap.base(w, temperature_C, w0, temperature_zero_C)
        took_over = self._handed_over and n
        if took_over:
            state = self._resume(state, e_all[0, self._keep], e_all[0])
            state = self._rebase_probes(state, dT[0])
            self._handed_over = False
        load = np.zeros((n, 3))
        force = np.zeros((n, 3))
        moving = np.zeros((n, 3), bool)
        if self.has_load:
            force, clamped, refused = self._track_load_from_rest(
                e_all[:, self._keep], time_s, state.get("load"), new_state, raw
            )
            flags[clamped] |= P.CLAMPED
            flags[refused] |= P.LOAD_REFUSED
            load = force @ self.C.T
            moving = self.last_transition
        if self.map is not None:
            # the gratings minus the load read from them are thermometers of their gauges
            e_th = e_all - force @ self.map["G"].T
            e_th[:, lost] = 0.0
            X, new_state["map"] = map_features(
                e_th, dT, self._h_idx, time_s, state.get("map"), self.nominal_dt_s
            )
            if n and new_state["map"].get("in") is not None:
                # a probe lost after this frame is held at its low-passed reading, not at its
                # last sample: the filters that go on without it then see no step at the loss.
                # Held at a sample 0.25 K below its level (its noise and 0.1 K quantisation),
                # ram6's housing probe put that step into the housing's leads for the 116 s it
                # was lost, and dz was 1.84 µm off on a static campaign that moves 0.16 µm.
                new_state["probe_last"] = np.asarray(new_state["map"]["in"][0], float).copy()
            activity = X[:, -len(MAP_LEADS_S)]  # the housing's fastest lead, K
            L = None
            if self.cal is not None:
                S = len(self.sensor_names)
                smooth = X[:, S : S + len(self.probe_names)]
                new_state["cal"], new_state["rest"] = {}, {}
                housing, past = housing_rest(
                    housing_mean(dT, self._h_idx),
                    housing_mean(smooth, self._h_idx),
                    time_s,
                    state.get("rest", {}),
                    new_state["rest"],
                    nominal_dt_s=self.nominal_dt_s,
                )
                tau_a = self.cal["ambient_tau_s"]
                k_h = 1 + len(self.cal["leads_s"])
                L = np.zeros((n, k_h + (tau_a is not None)))
                rest_a = state.get("rest_amb", {})
                if tau_a is not None and n == 1 and time_s is not None and rest_a.get("level") is not None:
                    # one frame past the rest window (a runtime batch of 1): the same step on
                    # Python floats, where numpy's per-call cost on one number was the time
                    sm = smooth[0]
                    air = sum(float(sm[i]) for i in self._a_idx) / len(self._a_idx) - rest_a["level"]
                    y_prev, t_prev = state["amb"]
                    t1 = float(np.ravel(time_s)[0])
                    (y,) = first_order_step(max(t1 - t_prev, 0.0) / float(tau_a), (air,), (float(y_prev[0]),))
                    new_state["rest_amb"], new_state["amb"] = rest_a, (np.array([y]), t1)
                    L[0, k_h] = y
                elif tau_a is not None:
                    # the ambient relative to its own rest level, low-passed as the ram's walls
                    # follow it: the calibrated uniform warming
                    new_state["rest_amb"] = {}
                    air, past_a = housing_rest(
                        housing_mean(dT, self._a_idx),
                        housing_mean(smooth, self._a_idx),
                        time_s,
                        state.get("rest_amb", {}),
                        new_state["rest_amb"],
                        nominal_dt_s=self.nominal_dt_s,
                    )
                    if past_a.any():
                        ta = None if time_s is None else np.asarray(time_s, float).ravel()[past_a]
                        slow, new_state["amb"] = first_order_filter(
                            air[past_a],
                            ta,
                            float(tau_a),
                            state.get("amb") or (np.zeros(1), None),  # the walls at rest: from 0
                            self.nominal_dt_s,
                        )
                        L[past_a, k_h:] = slow
                    elif "amb" in state:
                        new_state["amb"] = state["amb"]
                if past.any():  # the leads start at the first frame past the rest window
                    tp = None if time_s is None else np.asarray(time_s, float).ravel()[past]
                    L[past, :k_h] = np.hstack(
                        [
                            housing[past],
                            housing_leads(
                                housing[past],
                                self.cal["leads_s"],
                                tp,
                                state.get("cal", {}),
                                new_state["cal"],
                                self.nominal_dt_s,
                            ),
                        ]
                    )
                else:
                    new_state["cal"] = dict(state.get("cal", {}))
                if self.cal["heat_taus_s"]:
                    L = np.hstack([L, self._heat_features(heat_W - heat_zero_W, time_s, state, new_state)])
            self.last_cal_features = L
            self.last_map_features = X
            policy = not (raw or not thermal_policy)
            # the features the policy clips, as the consensus sees them
            Xc, outside = P.clip_to_envelope(X, *self._map_box) if policy else (X, None)
            if self.map["n_members"] > 1:
                each = (Xc @ self.map["members"]).reshape(n, self.map["n_members"], 3)
                lo, hi = member_bounds(each.transpose(1, 0, 2))
                spread = hi - lo
            if "unseen" in self.map:
                unseen = P.firm(
                    Xc @ self.map["unseen"], self.map["unseen_noise_sd"], self.k_sigma, 2 * self.k_sigma
                )
            if not policy:
                thermal = X @ self.map["coef"]
                if L is not None:
                    thermal = thermal + L @ self.cal["coef"]
            else:
                multi = self.map["n_members"] > 1
                thermal = agreed(lo, hi) if multi else Xc @ self.map["coef"]
                heat_part = 0.0
                if L is not None:
                    Lc, out_l = P.clip_to_envelope(L, self.cal["low"], self.cal["high"], self.margin)
                    k0 = self.cal["k_probes"]
                    thermal = thermal + Lc[:, :k0] @ self.cal["coef"][:k0]
                    outside = outside | out_l
                    if k0 < L.shape[1]:
                        # the measured heat inputs' part: what their own noise alone makes
                        # of it is held back, not what the probes' and gratings' noise makes
                        # of the rest (a spindle start the power shows at once would otherwise
                        # wait behind the map's threshold)
                        heat_part = P.firm(
                            Lc[:, k0:] @ self.cal["coef"][k0:],
                            self.cal["heat_noise_sd"],
                            self.k_sigma,
                            2 * self.k_sigma,
                        )
                # what the sensors' noise alone would make of the map is not applied, nor what
                # the load signature's error makes of the gratings net of the load read (each
                # grating off by relative_error of its load response, the map's weights at their
                # sizes): on ram2's static_xyz, a combined load at rest, 0.55 µm of dx passed a
                # threshold that knew the noise alone
                sd = self.map_noise_sd_um
                if self.has_load and np.any(force):
                    leak = self.relative_error * np.abs(force @ self.map["G"].T) @ self.map["leak_weights"]
                    sd = np.hypot(sd, leak)
                sd = sd * self._floor_scale
                before = thermal
                thermal = P.firm(thermal, sd, self.k_sigma, 2 * self.k_sigma)
                # the share of the map's correction the threshold lets through: the zero
                # state's error passes with it (_variance)
                with np.errstate(divide="ignore", invalid="ignore"):
                    passed = np.where(before != 0.0, np.abs(thermal) / np.abs(before), 0.0)
                thermal = thermal + heat_part
                thermal, clamped = P.clamp_axes(thermal, self.t_low, self.t_high)
                flags[outside] |= P.SHRUNK
                flags[clamped] |= P.CLAMPED
            if self.obs is not None:
                thermal, spread, closed = self._with_observer(
                    thermal,
                    spread,
                    e_th,
                    force,
                    moving,
                    dT,
                    time_s,
                    lost,
                    state,
                    new_state,
                    policy,
                    (heat_W - heat_zero_W)[:, self._obs_h],
                )
                flags[closed] |= P.SHRUNK
        else:
            # no twin: the housing fit on the measured load-free campaigns
            H, new_state["h"] = thermal_regressors(
                dT, self._h_idx, self._a_idx, self.lead_tau_s, time_s, state.get("h"), self.nominal_dt_s
            )
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
        unread = 0.0
        if not (raw or not thermal_policy):
            thermal = self._carry_over(thermal, time_s, state, new_state, took_over)
            thermal, unread, unheld = self._hold_loaded_axes(thermal, state)
            flags[:, unheld] |= P.SHRUNK
        if lost_p:
            # what this set does not run (the housing calibration without its probe) passes on
            # as it was, for the set that reads the probe again (take_state)
            for key, v in state.items():
                if key not in ("probe_rebase", "carry"):
                    new_state.setdefault(key, v)
        elif not self.has_load and state.get("load") is not None:
            new_state["load"] = state["load"]  # ... and the load tracker's, without any grating
        self.state = new_state
        self.last_flags = flags
        self.last_force_N = force
        self.last_moving = moving
        # per axis, the frames whose correction follows a load transition the step test
        # confirmed (a component moving that moves this axis): the runtime's output filter
        # publishes them as they are instead of confirming the motion once more
        self.last_follow = (
            (moving.astype(np.uint8) @ self._moves.T.astype(np.uint8)) > 0
            if self.has_load and moving.any()
            else np.zeros((n, 3), bool)
        )
        self.last_activity = activity
        self.last_spread = spread
        self.last_unseen = unseen
        self.last_passed = passed
        self.last_thermal = thermal
        var = self._variance(dT, activity, force, spread, unseen, moving, thermal, passed)
        var = var + (unread / self._t) ** 2
        deviation = thermal + load
        off_z = None if raw else self._untrained_z(z_axis_mm, n)
        if off_z is not None:
            # a Z the training never saw: the overhang below the carriages is another one, and
            # so are the lateral compliance and thermal drift (the load's mismatch also reads
            # as a thermal state), so dx and dy are held back and what they would have
            # corrected is the error; dz (the nut travels with the ram) is kept
            held = deviation[off_z, :2]
            deviation[off_z, :2] = 0.0  # both arrays are this call's own
            var[off_z, :2] += (UNTRAINED_Z_HALF * held / self._t) ** 2
            flags[np.ix_(off_z, [0, 1])] |= P.SHRUNK
        return deviation, self._t * np.sqrt(var)

    def _carry_over(self, thermal, time_s, state, new_state, took_over):
        """``thermal`` (n, 3) µm, carried over from the gratings when this set reads none.

        A set without any grating (every grating lost: the interrogator's link down) reads the
        probes alone, which see no gradient between the faces; what the gratings read of it at
        the loss persists while the walls keep their temperatures and fades as they follow their
        heat inputs. Such a set taking over from one with gratings (``took_over``) goes on from
        that set's last thermal correction (``thermal_last`` in its state): its own plus the
        difference on its first frame, fading with ``link_loss_tau_s``. On ram2's thermal_b, an
        hour without the interrogator from 13 h: dx 18.5 -> 10.2 µm, dy 9.7 -> 4.3 (probes
        alone -> carried over; docs/runtime.md). A set with gratings never carries one over:
        it reads the gradient itself."""
        n = thermal.shape[0]
        keep = state.get("carry")
        if self._keep or time_s is None or self.link_loss_tau_s <= 0:
            keep = None
        elif took_over:
            # under a force the gratings' thermal reading is net of a load read with its
            # signature's relative error: carried, that error stays while the force is no
            # longer read (ram5's thermal_c, the link lost under 2200 N of Fy: dy 2.5 µm further
            # than the probes alone, both beyond uncompensated). The probes alone then.
            held = _held_force(state)
            last = state.get("thermal_last")
            keep = None
            if last is not None and state.get("thermal_by_gratings") and not held.any():
                keep = (np.asarray(last, float) - thermal[0], float(np.ravel(time_s)[0]))
        if keep is not None and n:
            offset, t0 = keep
            t = np.asarray(time_s, float).ravel()
            fade = np.exp(-np.clip(t - t0, 0.0, None) / self.link_loss_tau_s)
            thermal = thermal + fade[:, None] * np.asarray(offset, float)[None, :]
            thermal, _ = P.clamp_axes(thermal, self.t_low, self.t_high)
        if keep is not None:
            new_state["carry"] = keep
        new_state["thermal_last"] = thermal[-1].copy() if n else state.get("thermal_last")
        new_state["thermal_by_gratings"] = bool(self._keep) or keep is not None
        return thermal

    def _hold_loaded_axes(self, thermal, state):
        """``thermal`` (n, 3) µm with the axes a held force moves set to 0, what the interval
        adds there (n, 3) µm (0 on the others), and those axes (3,) bool.

        A set without any grating (the interrogator's link down) cannot read the force: the
        one held when the link went down (the load tracker's state, passed on untouched) may
        stay or go. Its correction is not published (0: the force may be gone), and on the axes
        it moves the thermal correction is held back too: there an unread load dominates, and a
        thermal correction of the opposite sign to it lengthens the error instead of shortening
        it (ram5's thermal_c, the link lost for an hour under 2200 N of Fy: dy 196.9 µm against
        191.8 uncompensated). Those axes read as uncompensated, their interval as wide as the
        held load and the held-back correction; the other axes (dz, where a lateral force barely
        reaches) keep theirs."""
        held = np.zeros(3) if self._keep else _held_force(state)  # a set with gratings reads it
        axes = self._moves[:, held != 0].any(axis=1)
        if not axes.any():
            return thermal, np.zeros_like(thermal), axes
        unread = np.where(axes, np.abs(self.C @ held) + np.abs(thermal), 0.0)
        thermal = thermal.copy()
        thermal[:, axes] = 0.0
        return thermal, unread, axes

    def _untrained_z(self, z_axis_mm, n):
        """The frames (n,) bool whose Z position (mm, scalar or (n,)) is more than
        ``z_tolerance_mm`` from every trained position or unknown (NaN: a live Z gone stale),
        or None when none is (no Z given at all: the trained position assumed, as before Z was
        checked; a model file without its trained positions)."""
        if z_axis_mm is None or self.trained_z_mm is None:
            return None
        z = np.broadcast_to(np.asarray(z_axis_mm, float), (n,))
        gap = np.abs(z[:, None] - self.trained_z_mm[None, :]).min(axis=1)
        off = ~(gap <= self.z_tolerance_mm)  # NaN: held
        return off if off.any() else None

    def _heat_features(self, dP_W, time_s, state, new_state):
        """The measured heat inputs' changes since the zero state (W) low-passed at each of the
        calibration's ``heat_taus_s``: (n, taus x inputs), tau-major. The filters start at 0
        (the machine at rest in its zero state) and run from the first frame."""
        n, H = dP_W.shape
        if len(self.heat_names) != H:
            raise ValueError(
                f"expected {len(self.heat_names)} heat input column(s) after the probes, got {H}"
            )
        prev = state.get("heat", {})
        new_state["heat"] = {}
        out = np.zeros((n, H * len(self.cal["heat_taus_s"])))
        for k, tau in enumerate(self.cal["heat_taus_s"]):
            out[:, k * H : (k + 1) * H], new_state["heat"][tau] = first_order_filter(
                dP_W, time_s, tau, prev.get(tau) or (np.zeros(H), None), self.nominal_dt_s
            )
        return out

    def _with_observer(
        self, thermal, spread, e_th, force, moving, dT, time_s, lost, state, new_state, policy, dP_W
    ):
        """The map's thermal correction (n, 3) µm averaged with the observer's while the
        observer's heat estimates stay plausible (:data:`OBSERVER_GATE_K`; always without the
        policy), and their disagreement added to the members' ``spread`` (n, 3) µm: two
        estimates of one drift from different physics (a regression over the twin's scenarios,
        a filter of its thermal state), each wrong in its own way. Returns the thermal part,
        the spread and the frames (n,) where the gate has closed and the map alone is applied.
        ``dP_W`` (n, H): the measured heat inputs the filter reads, as changes since the zero
        state."""
        n = thermal.shape[0]
        if time_s is None:
            done = state.get("obs_frames", 0)
            t = (done + np.arange(n)) * self.nominal_dt_s
            new_state["obs_frames"] = done + n
        else:
            t = np.asarray(time_s, float).ravel()
        g = np.array(e_th, float)
        g[:, lost] = np.nan  # a lost grating is left out of the filter's update
        # so are the gratings while a load is in transition: the force read lags the reading
        g[np.asarray(moving, bool).reshape(n, -1).any(axis=1)] = np.nan
        amb = dT[:, self._obs_a].mean(axis=1) if self._obs_a else np.zeros(n)
        # a reading net of the applied load errs by the load signature's relative error
        var = (self.relative_error * force @ self.map["G"].T) ** 2 if self.has_load else None
        if dP_W.shape[1]:
            g = np.hstack([g, dP_W])
            var = None if var is None else np.hstack([var, np.zeros_like(dP_W)])
        obs, ok, new_state["obs"] = self.obs.stream(
            state.get("obs"), t, amb, dT[:, self._obs_p], g, OBSERVER_GATE_K, var
        )
        if policy:
            obs = P.clamp_axes(obs, self.t_low, self.t_high)[0]
        else:
            ok = np.ones(n, bool)
        self.last_observer_ok = ok
        both = ok[:, None]
        blended = np.where(both, 0.5 * (thermal + obs), thermal)
        spread = np.where(both, np.hypot(spread, np.abs(thermal - obs)), spread)
        return blended, spread, ~ok

    def _variance(self, dT, activity, force, spread=0.0, unseen=0.0, moving=False, thermal=0.0, passed=0.0):
        """Predictive variance (n, 3) µm²: the thermal part's error at the current thermal
        excursion, plus, while a load is applied, the force estimate's noise and the signature's
        relative error through the compliance.

        Plus the twin map's members' disagreement ``spread`` (n, 3) µm (max - min, see
        :func:`~fbgcomp.models.physical.thermal.consensus`) as a half-width of its own: where
        the gratings cannot tell one heat source from another, the truth may lie anywhere the
        members do, whatever the training campaigns' residuals say (they never saw that
        ambiguity: on ram2 without S5 and S6, the radiant load of thermal_b, 0.90 -> 0.99 on dx).

        Plus the part ``unseen`` (n, 3) µm of the map's correction that comes from feature
        directions no training campaign moved along (a face warmer than its opposite one, see
        :func:`~fbgcomp.models.physical.thermal.unseen_operator`) as an SD of
        ``unseen_relative_error`` times itself: the training residuals cannot speak for a
        response they never exercised, and it is only as good as the machine's description.

        Plus the thermal correction ``thermal`` (n, 3) µm itself at ``thermal_relative_error``
        of it (one SD): a heat taking another path than in training leaves a fraction of a
        percent of it, which no training residual shows.

        Plus the zero state's error (``zero_sd_um``: each probe and grating zeroed on the few
        samples of the zero window, through the map's coefficients;
        :meth:`~fbgcomp.models.physical.PhysicalModel._noise_floor`) at the share ``passed``
        (n, 3) of the map's correction the policy's threshold lets through: a constant error
        for the whole run once the correction passes, which the instrument's noise ``v0`` does
        not hold and one training campaign's residuals sample only once (0.26 µm SD on ram5's
        dz, 0.16 on ram2's)."""
        n = dT.shape[0]
        ambiguity = (np.asarray(spread, float) / self._t) ** 2 + (
            (self.unseen_relative_error * np.asarray(unseen, float)) ** 2
            + (self.thermal_relative_error * np.asarray(thermal, float)) ** 2
            + (self.zero_sd_um * np.asarray(passed, float)) ** 2
        ) * np.ones((n, 3))
        if self.interval is None:
            self.last_s2 = None
            return self.expected_rms_error_um[None, :] ** 2 + ambiguity
        # (a fallback's lost gratings: 0 for the full set)
        var, s2 = _state_variance(self.interval, dT, activity, self.map_lost_sd_um)
        if self._own_interval is not None:
            # a probe's fallback: the wider of the full model's and its own
            var = np.maximum(
                var, _state_variance(self._own_interval, dT, activity, self._interval_lost_sd_um)[0]
            )
        var = var + ambiguity
        self.last_s2 = s2
        if self.has_load:
            heat, own = self.load_variance(force, moving, s2, scaled=True)
            var = var + heat + own
        return var

    def load_variance(self, force, moving=False, s2=None, scaled=False):
        """The load terms of the predictive variance while a component is applied, through the
        compliance, in two parts (n, 3) µm² each:

        - what heat adds to the force estimate's error: its GLS variance at the training's
          thermal extreme less that at rest, in proportion to the thermal excursion ``s2`` (n,)
          up to that extreme (None: at it);
        - the load part's own error, before its calibrated scale (``load_interval_scale``,
          :meth:`PhysicalModel._fit_load_interval`): the estimate's noise at rest and the
          signature's relative error. A component following the reading (``moving`` (n, 3): a
          load transition) carries a frame's noise; one held at its level, the mean of the
          ``settle_s`` of readings it ended on, which hold ``settle_s / (2 LOAD_FAST_S)``
          independent ones. ``scaled``: times its calibrated scale, per axis for the terms of
          the force components the training applied (``load_interval_trained``), 1 for the
          others."""
        on = np.asarray(force) != 0.0
        C2 = (self.C**2).T
        s = np.ones(on.shape[0]) if s2 is None else np.minimum(np.asarray(s2, float), 1.0)
        heat = (on * s[:, None] * np.clip(self.F_sds[1] ** 2 - self.F_sds[0] ** 2, 0.0, None)) @ C2
        held = 2.0 * LOAD_FAST_S / max(self.settle_s, 2.0 * LOAD_FAST_S)
        share = np.where(np.asarray(moving, bool), 1.0, held) * on
        if not scaled or self.load_interval_trained.all():
            own = (share * self.F_sds[0] ** 2) @ C2 + (self.relative_error * force @ self.C.T) ** 2
            return heat, own * self.load_interval_scale[None, :] if scaled else own
        # S[k, j]: axis j's scale on force component k's terms
        S = np.where(self.load_interval_trained[:, None], self.load_interval_scale[None, :], 1.0)
        own = (share * self.F_sds[0] ** 2) @ (C2 * S) + (
            self.relative_error * force @ (self.C.T * np.sqrt(S))
        ) ** 2
        return heat, own
