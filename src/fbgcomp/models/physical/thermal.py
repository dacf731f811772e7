"""The physical model's thermal part: regressors, the twin-learned thermal map and probe roles.

Pure, vectorised pieces of :class:`~fbgcomp.models.physical.PhysicalModel`'s thermal part: the
housing and ambient regressors fitted on measured load-free campaigns (:func:`thermal_regressors`),
the features of the ridge map learned on the machine's FE twin (:func:`map_features`,
:func:`twin_thermal_population`, :func:`ridge_from_moments`), the housing leads its transient is
calibrated on, the gratings' uncompensated feature map and which probes sit on the housing or in
the air.

Over 600 lines as one unit: every function here reads or writes the map's feature columns (the
gratings, the probes, the housing leads in ``MAP_LEADS_S`` order), and the population's moments
are right only while they are formed by the same :func:`map_features` the predictor streams.
Splitting it into the features and the population (about 300 lines each) is the next step.
"""

from __future__ import annotations

import numpy as np

from fbgcomp.models.features import FeatureMap
from fbgcomp.models.filters import first_order_filter, first_order_step
from fbgcomp.optics import wavelength_nm
from fbgcomp.structure.elastic import CTE_PARTS
from fbgcomp.structure.scenarios import GENERIC_PREFIX, generic_heat_machine, thermal_scenarios

#: Low-pass of the probe temperatures before the thermal regressors, s.
PROBE_SMOOTHING_S = 60.0


def weighted_lstsq(X, Y, w):
    """Weighted least squares ``min sum w (Y - X B)^2``; returns B and the weighted residuals'
    covariance (columns of Y), with the weights normalised to the number of rows."""
    sw = np.sqrt(w)[:, None]
    B, *_ = np.linalg.lstsq(X * sw, Y * sw, rcond=None)
    R = Y - X @ B
    wn = w / w.sum()
    cov = (R * wn[:, None]).T @ R
    return B, cov


def thermal_regressors(
    delta_T_K, housing_idx, ambient_idx, lead_tau_s, time_s=None, state=None, nominal_dt_s=1.0
):
    """Thermal regressors (n, 1 + nh): [1, ΔT of each housing probe, ΔT of each ambient probe,
    lead of the mean housing ΔT (``T - lowpass(T, lead_tau_s)``, K)] and the filter state.

    ``delta_T_K`` (n, P) are probe temperature changes from the zero state."""
    dT = np.atleast_2d(np.asarray(delta_T_K, dtype=float))
    n = dT.shape[0]
    state = state or {}
    # Probes are quantised (0.1 K is typical) and sampled slowly: a 60 s low-pass keeps their
    # steps out of the correction (thermal drift is far slower), then the lead term is formed.
    used = list(housing_idx) + list(ambient_idx)
    smooth, state_in = first_order_filter(
        dT[:, used], time_s, PROBE_SMOOTHING_S, state.get("in"), nominal_dt_s
    )
    cols = [np.ones((n, 1)), smooth]
    new_state = {"in": state_in}
    if len(housing_idx):
        housing = smooth[:, : len(housing_idx)].mean(axis=1, keepdims=True)
        slow, new_state["lead"] = first_order_filter(
            housing, time_s, lead_tau_s, state.get("lead"), nominal_dt_s
        )
        cols.append(housing - slow)
    return np.hstack(cols), new_state


#: Time constants of the housing lead terms of the twin-learned thermal map, s.
MAP_LEADS_S = (300.0, 1800.0)


def map_features(e_um, delta_T_K, housing_idx, time_s=None, state=None, nominal_dt_s=1.0):
    """Features of the twin-learned thermal map (n, S + P + 2) and the filter state:
    [uncompensated grating elongations e (µm), every probe's ΔT low-passed over
    ``PROBE_SMOOTHING_S`` (K), the mean housing ΔT's lead ``T - lowpass(T, tau)`` for each tau
    of ``MAP_LEADS_S`` (K)]. On CFRP the gratings are thermometers of their gauges (~5 µm of
    uncompensated elongation per K over 600 mm), which is why they carry the face gradients.

    The elongations are low-passed over ``PROBE_SMOOTHING_S`` too, starting from 0 (the zero
    state): as thermometers they change over minutes, and each raw frame carries the
    interrogator's noise (0.3-0.4 µm per frame on the twin, four times what the twin
    population assumes), which the map turned into ±2 µm spikes of dz on a static campaign."""
    e = np.atleast_2d(np.asarray(e_um, float))
    dT = np.atleast_2d(np.asarray(delta_T_K, float))
    if e.shape[0] == 1 and time_s is not None and state and state["in"][1] is not None:
        return _map_features_one(e[0].tolist(), dT[0].tolist(), housing_idx, time_s, state)
    state = state or {}
    s_in, s_e = state.get("in"), state.get("e")
    if s_in is not None and s_e is not None and s_in[1] == s_e[1]:
        # a running state: probes and gratings through one filter call (the same low-pass and
        # clock, column by column: the same numbers as two calls)
        P = dT.shape[1]
        both, (y, t_end) = first_order_filter(
            np.hstack([dT, e]),
            time_s,
            PROBE_SMOOTHING_S,
            (np.concatenate([s_in[0], s_e[0]]), s_in[1]),
            nominal_dt_s,
        )
        smooth, e = both[:, :P], both[:, P:]
        new = {"in": (y[:P], t_end), "e": (y[P:], t_end)}
    else:
        smooth, s_in = first_order_filter(dT, time_s, PROBE_SMOOTHING_S, s_in, nominal_dt_s)
        e, s_e = first_order_filter(
            e, time_s, PROBE_SMOOTHING_S, s_e or (np.zeros(e.shape[1]), None), nominal_dt_s
        )
        new = {"in": s_in, "e": s_e}
    leads = housing_leads(housing_mean(smooth, housing_idx), MAP_LEADS_S, time_s, state, new, nominal_dt_s)
    return np.hstack([e, smooth, leads]), new


def _map_features_one(e, dT, housing_idx, time_s, state):
    """:func:`map_features` of one frame (a runtime batch of 1) from a running state, on Python
    floats: each filter's single step (:func:`~fbgcomp.models.filters.first_order_step`), where
    numpy's per-call cost on a dozen numbers was the time."""
    t1 = float(np.ravel(time_s)[0])

    def step(x, key, tau_s):
        y_prev, t_prev = state[key]
        y = first_order_step(max(t1 - t_prev, 0.0) / tau_s, x, y_prev.tolist())
        new[key] = (np.array(y), t1)
        return y

    new: dict = {}
    smooth = step(dT, "in", PROBE_SMOOTHING_S)
    e_s = step(e, "e", PROBE_SMOOTHING_S)
    h = [smooth[i] for i in housing_idx]
    housing = [sum(h) / len(h) if h else 0.0]
    leads = [housing[0] - step(housing, f"lead{tau:g}", tau)[0] for tau in MAP_LEADS_S]
    return np.array([e_s + smooth + leads]), new


#: Time constants of the housing leads on which the twin map's housing transient is calibrated
#: against the measured load-free campaigns, s.
CAL_LEADS_S = (300.0, 900.0)

#: Time constant of the ambient's low-pass on which the twin map's uniform warming is calibrated
#: against the measured load-free campaigns, s: about a CFRP wall's own (ram2: rho c t / h =
#: 1580 x 950 x 0.015 / 7 = 3200 s). The air follows no heat source, so the term cannot take a
#: radiant load or the spindle for a change of the hall's temperature.
CAL_AMBIENT_TAU_S = 3600.0

#: Time constants of the measured heat inputs' low-passes (heat.csv: a spindle's power as the
#: CNC reads it) on which the housing calibration takes them, s: the bearings' own zone (about a
#: minute) and the steel housing (about ten). The housing's probe sees a power step minutes late,
#: the power itself at once; what is slower the probes see in time. Measured (the bearings' heat
#: of ram2's and ram3's truth files read at 1 s with 5 W of noise, fitted on thermal_a +
#: static_xyz, 2026-11-28): thermal_b dz 4.62 -> 1.84 µm (ram2) and 7.40 -> 2.96 (ram3). Four
#: (30-1800 s) fitted one campaign's duty history too closely: ram3's thermal_c dy, unloaded,
#: 0.53 -> 2.15 µm of median error (1.35 with these two); one (300 s) left ram3's thermal_b dy
#: at 4.67 µm against 4.41.
HEAT_TAUS_S = (60.0, 600.0)

#: The housing's rest level for the calibrated leads: the mean of its probes over the first
#: ``HOUSING_REST_S`` seconds, s. One fastest lead's time constant: 30 samples of a probe read
#: every 10 s put the level within 0.1 K / sqrt(30) = 0.018 K, 3 sigma of which make 0.6 µm
#: of dz through the 11 µm/K lead; a spindle started in the window moves the housing probe
#: 0.01-0.02 K by its end (ram2). 120 s (0.029 K) still left 0.61 µm on the worst of 17
#: simulated static campaigns and moved ram2's thermal_c dz coverage to 0.8998; 60 s left 1.05.
HOUSING_REST_S = 300.0


def housing_rest(raw_K, housing_K, time_s, state, new_state, rest_s=HOUSING_REST_S, nominal_dt_s=1.0):
    """The housing ΔT relative to its rest level (n, 1) K and the frames past the rest window (n,).

    The zero state is the mean of the first 10 s, one sample of a probe read every 10 s, so it
    carries the probe's whole noise (0.1 K); a leads' transient detector with 11 µm of dz per K
    read that as a spindle start: 1.4-4 µm of dz on 3 of 7 simulated static campaigns of ram2,
    where nothing moves (0.2 µm). The rest level is the mean of the raw housing ΔT ``raw_K``
    (n,) or (n, 1) over the first ``rest_s`` seconds; within them the leads are not formed (zeros),
    after them ``housing_K`` (n, 1), the low-passed mean housing ΔT, is taken relative to it.
    ``state`` holds the first frame's time, the running sum and count, and the level once fixed.
    """
    raw = np.asarray(raw_K, float).ravel()
    n = raw.size
    t0, total, count = state.get("t0"), float(state.get("sum", 0.0)), float(state.get("n", 0.0))
    level = state.get("level")
    if time_s is None:
        done = float(state.get("frames", 0))
        t = (done + np.arange(n)) * nominal_dt_s
        new_state["frames"] = done + n
    else:
        t = np.asarray(time_s, float).ravel()
    if t0 is None and n:
        t0 = float(t[0])
    past = (t - t0 > rest_s) if n else np.zeros(0, bool)
    if level is None:
        inside = ~past
        total += float(raw[inside].sum())
        count += float(inside.sum())
        if past.any():
            level = total / max(count, 1.0)
    new_state.update({"t0": t0, "sum": total, "n": count, "level": level})
    rel = np.zeros((n, 1))
    if level is not None:
        rel[past] = np.asarray(housing_K, float).reshape(n, -1)[past, :1] - level
    return rel, past


def calibration_probe_columns(cal: dict) -> int:
    """Columns of a housing calibration (the model file's ``twin_map.calibration``) before its
    measured heat inputs' low-passes: the housing's ΔT, its leads and the ambient's low-pass."""
    return 1 + len(cal["leads_s"]) + (cal.get("ambient_tau_s") is not None)


def housing_mean(smooth_K, housing_idx):
    """Mean ΔT (n, 1) K of the housing probes among probe ΔTs already low-passed over
    ``PROBE_SMOOTHING_S`` (zeros without a housing probe)."""
    smooth = np.atleast_2d(smooth_K)
    return (
        smooth[:, list(housing_idx)].mean(axis=1, keepdims=True)
        if len(housing_idx)
        else np.zeros((smooth.shape[0], 1))
    )


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
    feature columns ``keep`` (others get 0), features standardised by ``scale``, penalty ``lam``.
    A column that is zero in every scenario (``scale`` 0: the housing leads of a machine without a
    housing probe) carries nothing and gets 0 as well."""
    scale = np.asarray(scale, float)
    keep = np.asarray([k for k in keep if scale[k] > 0], int)
    sc = scale[keep]
    g = np.asarray(gram, float)[np.ix_(keep, keep)] / np.outer(sc, sc)
    b = np.asarray(xty, float)[keep] / sc[:, None]
    coef = np.zeros((len(scale), np.asarray(xty).shape[1]))
    coef[keep] = np.linalg.solve(g + lam * np.eye(len(keep)), b) / sc[:, None]
    return coef


def map_members(tm, cols, lam):
    """Coefficients (m, k, 3) of the twin map's members on the feature columns ``cols``: the
    map of the whole population first, then one map per undeclared source, fitted on the same
    scenarios with that source taken out (``tm["without"]``), then the map of an expansion
    coefficient the training asked for (``tm["cte_members"]``).

    A member speaks only for the axes its source moves: on an axis where the source's own TTP
    response (RMS over the population) is within the full map's error there, the member's
    coefficients are the full map's. Taking a source out leaves feature directions no scenario
    excites, and the member's answer on an axis the source hardly moves is that conditioning,
    not physics (the built-in twin: the face pulses move dz by 0.04-0.08 µm RMS against the
    map's 0.48 µm, and their members were 1.3-1.6 µm further off on dz). The expansion
    coefficient's member speaks for the axes whose training residual it fits better
    (``axes``, :meth:`~fbgcomp.models.physical.PhysicalModel._calibrate_cte`)."""
    full = ridge_from_moments(tm["gram"], tm["xty"], tm["scale"], cols, lam)
    err2 = population_mse(tm, full)

    def member(w, speaks):
        """A member's map from its moments, the full map's on the axes it does not speak for."""
        g = np.asarray(w["gram"], float)
        c = ridge_from_moments(g, w["xty"], np.sqrt(np.clip(np.diag(g), 0, None)), cols, lam)
        c[:, ~speaks] = full[:, ~speaks]
        return c

    every = np.ones(3, bool)
    out = [full]
    for w in tm.get("without", []):
        moved = err2 is not None and "ttp_ms_um2" in w
        out.append(member(w, ~(np.asarray(w["ttp_ms_um2"], float) <= err2) if moved else every))
    # the map of the expansion coefficient the training asked for, where it contradicted the
    # description's (PhysicalModel._calibrate_cte): only what both answer is applied
    # (on the axes whose training it fits better, ``axes``; every axis in files before it)
    for w in tm.get("cte_members", []):
        out.append(member(w, np.asarray(w.get("axes", every), bool)))
    return np.stack(out)


def population_mse(tm, coef):
    """Mean square error (3,) µm² of the map coefficients ``coef`` (k, 3) over the twin's
    population, from its second moments: ``E[y²] - 2 c·E[x y] + c' E[x x'] c`` per axis; None
    without the population's TTP moments (``ttp_ms_um2``)."""
    ms = tm.get("ttp_ms_um2")
    if ms is None:
        return None
    g, b = np.asarray(tm["gram"], float), np.asarray(tm["xty"], float)
    return np.asarray(ms, float) - 2 * np.sum(coef * b, axis=0) + np.einsum("ka,kl,la->a", coef, g, coef)


def lost_information_sd(tm, cols, coef, lam):
    """SD (3,) µm of the error the twin map ``coef`` on the feature columns ``cols`` (the first
    of :func:`map_members`) makes beyond the full map's, over the twin's population (0 for the
    full set or without the population's TTP moments): what the left-out gratings told the
    full map. Without S4 the built-in twin's map errs by 0.77 µm more on dy, and ram2's by
    6.1 µm on dx."""
    k = len(tm["scale"])
    part = population_mse(tm, coef)
    if part is None or len(cols) == k:
        return np.zeros(3)
    full = population_mse(tm, ridge_from_moments(tm["gram"], tm["xty"], tm["scale"], list(range(k)), lam))
    return np.sqrt(np.clip(part - full, 0.0, None))


#: A direction of the map's standardised features is unseen by the training when the load-free
#: training campaigns move along it by less than this share of the variance of their most
#: excited direction (1e-3: 3 % in SD). ram2's thermal_a leaves 7 of 12 unseen: every face
#: warmer than its opposite one, which no training campaign without a gradient shows.
UNSEEN_VARIANCE_RATIO = 1e-3


def unseen_basis(features, weights, scale, ratio=UNSEEN_VARIANCE_RATIO):
    """Orthonormal basis (k, r) of the standardised feature directions the training left unseen.

    ``features`` (n, k) are the twin map's features on the load-free training frames,
    ``weights`` (n,) the frames' weights (campaigns weighted equally), ``scale`` (k,) the
    map's standardisation. The second moments are taken about zero, as the map is (every
    campaign starts at its zero state). A direction whose weighted mean square is below
    ``ratio`` times the largest is unseen; columns the twin never moves (scale 0) carry
    nothing and are left out of both."""
    sc = np.asarray(scale, float)
    live = sc > 0
    if not live.any():
        return np.zeros((sc.size, 0))
    Z = np.asarray(features, float)[:, live] / sc[live]
    w = np.asarray(weights, float)
    lam, V = np.linalg.eigh((Z * (w / w.sum())[:, None]).T @ Z)
    unseen = lam < ratio * lam.max()
    out = np.zeros((sc.size, int(unseen.sum())))
    out[live] = V[:, unseen]
    return out


def unseen_operator(basis, scale, coef):
    """The map's prediction from its features' unseen part: the matrix (k, 3) that takes
    features (n, k) to the correction (n, 3) µm the map makes of the part of them along the
    standardised ``basis`` (:func:`unseen_basis`), ``coef`` (k, 3) the map's coefficients.

    That part of a correction rests on the twin's physics alone: no measured campaign ever
    checked it."""
    sc = np.asarray(scale, float)
    inv = np.where(sc > 0, 1.0 / np.where(sc > 0, sc, 1.0), 0.0)
    U = np.asarray(basis, float)
    return inv[:, None] * (U @ (U.T @ (sc[:, None] * np.asarray(coef, float))))


def consensus(members_um):
    """Per frame and axis, the correction every member agrees on (m, n, 3) -> (n, 3): the
    smallest in magnitude when all have the same sign, else 0.

    The gratings cannot always tell an undeclared heat source from a declared one (a face with
    one grating reads the same whether the whole face or a zone of it warms), and the TTP
    moves differently for each: the twin map then answers with its scenarios' prior, which a
    real shop need not share. What every prior without one of those sources agrees on is what
    the sensors, not the prior, say."""
    return agreed(*member_bounds(np.asarray(members_um, float)))


def member_bounds(members_um):
    """Smallest and largest member per frame and axis, (m, n, 3) -> two (n, 3) arrays.

    One elementwise pass per member: numpy's reduction across the members of an (n, m, 3)
    product (the predictor's layout, a strided short axis) took 3.5x as long on ram2's 5 members
    and 130 000 frames."""
    lo = np.array(members_um[0], float)
    hi = lo.copy()
    for member in members_um[1:]:
        np.minimum(lo, member, out=lo)
        np.maximum(hi, member, out=hi)
    return lo, hi


def agreed(lo_um, hi_um):
    """:func:`consensus` from the members' bounds (:func:`member_bounds`)."""
    return np.where(lo_um > 0.0, lo_um, np.where(hi_um < 0.0, hi_um, 0.0))


def twin_thermal_population(
    machine,
    sensors,
    probe_names,
    housing_probes,
    n_scenarios=40,
    seed=0,
    grating_noise_um=0.1,
    probe_noise_K=0.1,
    nominal_W=None,
    twin=None,
    per_material=True,
):
    """Second moments of (map features, TTP) over the twin's generic thermal scenarios
    (:mod:`fbgcomp.structure.scenarios`), or None when the machine description lacks one of
    the campaign's gratings or probes. Measurement noise is added as the instruments have it
    (seeded), so the map does not lean on differences finer than the sensors resolve.
    ``nominal_W`` ({volume source: W}) sets the scenarios' bearing power in place of the
    description's (:func:`fbgcomp.structure.scenarios.thermal_scenarios`). ``twin``: the twin of
    :func:`~fbgcomp.structure.scenarios.generic_heat_machine` of ``machine``, when the caller
    has it (else it is built). ``per_material``: also the moments per material expansion
    coefficient (``"cte"``, for :func:`population_at`); without them the population takes a
    fraction of the time (ram2, 2026-11-29: 2.4 s against 5.6).

    The result is kept in the twin cache (:func:`fbgcomp.structure.cache.cached_json`) under
    the twin's key and every argument: a second fit of the same machine on campaigns with the
    same gratings, probes and heat prior reads it (ram2: 6 s of a 15 s fit) instead of
    simulating the scenarios again."""
    names = [s.name for s in machine.sensors]
    mprobes = [p.name for p in machine.probes]
    # a strain-free reference grating (<sensor>_ref) reads the temperature of its sensor's gauge
    ref_of = {f"{n}_ref": n for n in names}
    if any(s.name not in names for s in sensors) or any(
        p not in mprobes and p not in ref_of for p in probe_names
    ):
        return None
    from fbgcomp.structure import Twin  # noqa: PLC0415 - optional extra: scikit-fem (the FE twin)
    from fbgcomp.structure.cache import cached_json  # noqa: PLC0415 - with the twin

    twin = Twin(generic_heat_machine(machine)) if twin is None else twin
    ident = {
        "twin": twin.cache_key,
        "sensors": [s.model_dump(mode="json") for s in sensors],
        "probes": list(probe_names),
        "housing": list(housing_probes),
        "n_scenarios": int(n_scenarios),
        "seed": int(seed),
        "grating_noise_um": float(grating_noise_um),
        "probe_noise_K": float(probe_noise_K),
        "nominal_W": None if nominal_W is None else {str(k): float(v) for k, v in nominal_W.items()},
        "per_material": bool(per_material),
    }
    args = (sensors, probe_names, housing_probes, n_scenarios, seed, grating_noise_um, probe_noise_K)
    return cached_json(
        "thermal-population",
        ident,
        lambda: _population(twin, *args, nominal_W, per_material, mprobes, ref_of),
    )


def _population(
    twin,
    sensors,
    probe_names,
    housing_probes,
    n_scenarios,
    seed,
    grating_noise_um,
    probe_noise_K,
    nominal_W,
    per_material,
    mprobes,
    ref_of,
):
    """:func:`twin_thermal_population`'s moments, computed (its arguments; ``mprobes`` the
    machine's probe names, ``ref_of`` {reference grating: its sensor})."""
    idx = [twin.sensor_names.index(s.name) for s in sensors]
    # each thermometer's column in the twin's response: a probe's, or its gauge's temperature
    sources = [
        ("probe_C", twin.probe_names.index(p))
        if p in mprobes
        else ("sensor_temperature_C", twin.sensor_names.index(ref_of[p]))
        for p in probe_names
    ]

    def thermometers(r):
        return (
            np.column_stack([getattr(r, field)[:, i] for field, i in sources])
            if sources
            else np.zeros((r.time_s.size, 0))
        )

    h_idx = [list(probe_names).index(p) for p in housing_probes]
    fmap = grating_map(sensors, probe_names)
    lam0 = np.array([s.lambda0_nm for s in sensors])

    def features(r, el, dT):
        """The map's features of the scenario ``r`` from the elongations ``el`` and thermometers ``dT``."""
        wl = grating_wavelengths_nm(sensors, el, r.sensor_temperature_C[:, idx])
        return map_features(fmap.base(wl, dT, lam0, np.zeros(len(sources))), dT, h_idx, r.time_s)[0]

    n_parts = len(twin.cte_per_K)
    n_twin_sensors = len(twin.sensor_names)

    def cte_blocks(r, parts, el_noise, dT):
        """The scenario's features as (1 + P, n, k) blocks, the gratings' noise alone and then
        each material's part per 1/K of its expansion coefficient, and its TTP per part
        (P, n, 3): the features are affine in the elongations, so with coefficients alpha they
        are ``Z[0] + sum_j alpha_j Z[1 + j]`` and the TTP ``sum_j alpha_j Y[j]``."""
        zero = features(r, np.zeros_like(el_noise), dT)
        Z = [features(r, el_noise, dT)] + [
            features(r, parts[:, j, :n_twin_sensors][:, idx], dT) - zero for j in range(n_parts)
        ]
        return np.stack(Z), parts[:, :, n_twin_sensors:].transpose(1, 0, 2)

    def add_blocks(acc, Z, Y):
        # as matrix products of the blocks stacked along their columns (BLAS: einsum's own
        # loops took 4.4 of a ram2 fit's 25 s)
        nz, ny = Z.shape[0], Y.shape[0]
        Zf = Z.transpose(0, 2, 1).reshape(nz * Z.shape[2], -1)
        Yf = Y.transpose(0, 2, 1).reshape(ny * Y.shape[2], -1)
        acc["zz"] += (Zf @ Zf.T).reshape(nz, Z.shape[2], nz, Z.shape[2]).transpose(0, 2, 1, 3)
        acc["zy"] += (Zf @ Yf.T).reshape(nz, Z.shape[2], ny, Y.shape[2]).transpose(0, 2, 1, 3)
        acc["yy"] += np.einsum("ina,jna->ija", Y, Y)

    rng = np.random.default_rng(seed)
    k = len(sensors) + len(probe_names) + len(MAP_LEADS_S)

    def new_blocks():
        return {
            "zz": np.zeros((1 + n_parts, 1 + n_parts, k, k)),
            "zy": np.zeros((1 + n_parts, n_parts, k, 3)),
            "yy": np.zeros((n_parts, n_parts, 3)),
            "alone_yy": np.zeros((n_parts, n_parts, 3)),  # a member's source's own TTP
        }

    blocks = new_blocks()
    gram, xty, noise, n = np.zeros((k, k)), np.zeros((k, 3)), np.zeros((k, k)), 0
    lo, hi = np.full(k, np.inf), np.full(k, -np.inf)
    ylo, yhi = np.full(3, np.inf), np.full(3, -np.inf)
    # The moments of the same scenarios with each undeclared (generic) source taken out: the twin
    # is linear, so a scenario without it is the scenario minus that source's response alone
    # (same inputs otherwise, same noise), and the members differ by that source only.
    Tref = twin.machine.reference_temperature_C
    generic = [h.name for h in twin.machine.thermal.sources if h.name.startswith(GENERIC_PREFIX)]
    without = {g: [np.zeros((k, k)), np.zeros((k, 3)), np.zeros(3), new_blocks()] for g in generic}
    yy = np.zeros(3)
    for inputs, out in thermal_scenarios(twin, n_scenarios, seed, nominal_W=nominal_W, parts=per_material):
        r, parts = out if per_material else (out, None)
        r = r.change_from_start()
        if parts is not None:
            parts = parts - parts[:1]
        t = r.time_s
        el0 = r.sensor_elongation_um[:, idx]
        el_noise = rng.normal(0, grating_noise_um, (t.size, len(idx)))
        el = el0 + el_noise
        # probe noise, and the error of a zero state read from a single slow probe sample
        dT0 = thermometers(r)
        dT_noise = rng.normal(0, probe_noise_K, (t.size, len(sources))) + rng.normal(
            0, probe_noise_K, len(sources)
        )
        dT = dT0 + dT_noise
        X = features(r, el, dT)
        N = X - features(r, el0, dT0)
        noise += N.T @ N
        Y = r.ttp_um
        if parts is not None:
            add_blocks(blocks, *cte_blocks(r, parts, el_noise, dT))
        XtX, XtY = X.T @ X, X.T @ Y
        gram += XtX
        xty += XtY
        yy += (Y**2).sum(axis=0)
        n += t.size
        for g, acc in without.items():
            if not np.any(inputs["heat"][g]):
                acc[0] += XtX
                acc[1] += XtY
                if parts is not None:
                    add_blocks(acc[3], *cte_blocks(r, parts, el_noise, dT))
                continue
            heat = {g: inputs["heat"][g]}
            if parts is not None:
                alone, alone_parts = twin.thermal_parts(t, Tref, heat=heat, initial_C=Tref)
            else:
                alone = twin.thermal(t, Tref, heat=heat, initial_C=Tref)
            alone = alone.change_from_start()
            rest = r - alone
            dT_rest = thermometers(rest) + dT_noise
            Xg = features(rest, rest.sensor_elongation_um[:, idx] + el_noise, dT_rest)
            acc[0] += Xg.T @ Xg
            acc[1] += Xg.T @ rest.ttp_um
            acc[2] += (alone.ttp_um**2).sum(axis=0)
            if parts is None:
                continue
            alone_parts = alone_parts - alone_parts[:1]
            add_blocks(acc[3], *cte_blocks(rest, parts - alone_parts, el_noise, dT_rest))
            Ya = alone_parts[:, :, n_twin_sensors:]
            acc[3]["alone_yy"] += np.einsum("nia,nja->ija", Ya, Ya)
        lo, hi = np.minimum(lo, X.min(axis=0)), np.maximum(hi, X.max(axis=0))
        ylo, yhi = np.minimum(ylo, Y.min(axis=0)), np.maximum(yhi, Y.max(axis=0))
    gram, xty, noise = gram / n, xty / n, noise / n
    # the moments per material expansion part (:func:`population_at`): kept in memory for the
    # fit's calibration of the coefficients, not written to a model file
    cte = {}
    if per_material:
        for b in [blocks] + [a[3] for a in without.values()]:
            for key in b:
                b[key] /= n
        cte["cte"] = {
            "parts": list(CTE_PARTS),
            "nominal_per_K": twin.cte_per_K.tolist(),
            "blocks": blocks,
            "without": [a[3] for a in without.values()],
        }
    return {
        **cte,
        "gram": gram.tolist(),
        "xty": xty.tolist(),
        "scale": np.sqrt(np.diag(gram)).tolist(),
        "ttp_ms_um2": (yy / n).tolist(),
        "without": [
            {
                "source": g,
                "gram": (a[0] / n).tolist(),
                "xty": (a[1] / n).tolist(),
                "ttp_ms_um2": (a[2] / n).tolist(),
            }
            for g, a in without.items()
        ],
        "noise_gram": noise.tolist(),
        "n_samples": n,
        "n_scenarios": n_scenarios,
        "seed": seed,
        "envelope_low": lo.tolist(),
        "envelope_high": hi.tolist(),
        "ttp_low_um": ylo.tolist(),
        "ttp_high_um": yhi.tolist(),
        "features": [f"e_{s.name}" for s in sensors]
        + [f"dT_{p}" for p in probe_names]
        + [f"lead{tau:g}s_housing" for tau in MAP_LEADS_S],
    }


def population_at(tm, cte_per_K) -> dict:
    """The twin map's population moments (``gram``, ``xty``, ``ttp_ms_um2`` and each member's
    in ``without``) for a ram whose materials expand by ``cte_per_K`` (P,) in
    ``tm["cte"]["parts"]`` order instead of the description's, from the per-part moments
    :func:`twin_thermal_population` keeps: the temperatures do not depend on the coefficients,
    the elongations and the TTP are linear in them."""
    alpha = np.asarray(cte_per_K, float)
    a = np.concatenate([[1.0], alpha])

    def at(b, ms="yy"):
        gram = np.einsum("i,j,ijKL->KL", a, a, b["zz"])
        return {
            "gram": gram,
            "xty": np.einsum("i,j,ijKa->Ka", a, alpha, b["zy"]),
            "ttp_ms_um2": np.clip(np.einsum("i,j,ija->a", alpha, alpha, b[ms]), 0.0, None),
            "scale": np.sqrt(np.clip(np.diag(gram), 0.0, None)),
        }

    cte = tm["cte"]
    out = at(cte["blocks"])
    out["without"] = [at(b, "alone_yy") for b in cte["without"]]
    return out


def grating_wavelengths_nm(sensors, elongation_um, gauge_delta_t_K=0.0):
    """Bragg wavelengths (n, S) nm of the campaign's gratings ``sensors`` (SensorSpec) whose
    paths elongate by ``elongation_um`` (n, S) with their gauges ``gauge_delta_t_K`` (n, S) warmer
    than at the zero state (paper eq. 2-4, :func:`fbgcomp.optics.wavelength_nm`)."""
    return wavelength_nm(
        elongation_um,
        np.array([s.lambda0_nm for s in sensors], float),
        np.array([s.gauge_length_mm for s in sensors], float),
        gauge_delta_t_K,
        photoelastic=np.array([s.photoelastic for s in sensors], float),
        thermo_optic_per_K=np.array([s.thermo_optic_per_K for s in sensors], float),
        fibre_cte_per_K=np.array([s.fibre_cte_per_K for s in sensors], float),
    )


def grating_map(sensors, probe_names):
    """Feature map of the gratings' *uncompensated* elongations (paper eq. 2-4 with dT = 0).

    The load part never compensates a grating with a probe on another face: a 0.1 K step of a
    quantised remote probe is ~0.5 µm of false elongation on a 600 mm CFRP gauge, hundreds of N
    of false load. The gratings' own thermal reading is modelled instead (``B``, ``Sigma``)."""
    bare = [s.model_copy(update={"temperature_probe": None}) for s in sensors]
    return FeatureMap(bare, probe_names, False)


def housing_probe_names(probe_names, machine=None):
    """Probes on the spindle housing (the machine description's point probes in or on it, nearest
    its centre first: :meth:`~fbgcomp.structure.Machine.housing_probe_names`; without one, names
    containing 'flange', 'housing' or 'spindle')."""
    if machine is not None:
        found = [n for n in machine.housing_probe_names() if n in probe_names]
        if found:
            return found
    keys = ("flange", "housing", "spindle")
    return [p for p in probe_names if any(k in p.lower() for k in keys)]


def ambient_probe_names(probe_names, machine=None):
    """Probes in the air (the machine description's ambient probes, else names containing 'amb')."""
    if machine is not None:
        found = [p.name for p in machine.probes if p.kind == "ambient" and p.name in probe_names]
        if found:
            return found
    return [p for p in probe_names if "amb" in p.lower()]
