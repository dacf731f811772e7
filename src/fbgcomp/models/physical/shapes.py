"""The physical model file's shape checks: every array as its sensors and probes imply."""

from __future__ import annotations

import numpy as np

from fbgcomp.errors import InputError
from fbgcomp.models.physical.thermal import MAP_LEADS_S


def check_shapes(d: dict, source) -> None:
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
        need(
            isinstance(node, list) and all(isinstance(x, str) for x in node), field, "must be a list of names"
        )
        need(len(set(node)) == len(node), field, "names must be distinct")
        return node

    need(
        isinstance(d.get("sensors"), list)
        and d["sensors"]
        and all(isinstance(x, dict) for x in d["sensors"]),
        "sensors",
        "must be a non-empty list of sensors",
    )
    sensor_names = names([x.get("name") for x in d["sensors"]], "sensors")
    probes = names(d.get("probes"), "probes")
    for key in ("housing_probes", "ambient_probes"):
        got = names(d.get(key), key)
        need(all(p in probes for p in got), key, "names a probe the model does not read")
    heat = names(d.get("heat_inputs", []), "heat_inputs")
    need(not set(heat) & set(probes), "heat_inputs", "names a probe")
    S, P = len(sensor_names), len(probes)
    nh = 1 + len(d["housing_probes"]) + len(d["ambient_probes"]) + (1 if d["housing_probes"] else 0)
    need(
        isinstance(d.get("nominal_dt_s"), (int, float))
        and not isinstance(d["nominal_dt_s"], bool)
        and d["nominal_dt_s"] > 0,
        "nominal_dt_s",
        "must be a positive number",
    )
    if d.get("trained_z_axis_mm") is not None:  # absent from files before it
        node = d["trained_z_axis_mm"]
        need(isinstance(node, list) and len(node) >= 1, "trained_z_axis_mm", "must be a list of positions")
        z = array(node, "trained_z_axis_mm", (len(node),))
        need(np.all(np.isfinite(z)), "trained_z_axis_mm", "must be finite")
    th = d.get("thermal")
    if not isinstance(th, dict):
        raise InputError("must be a mapping", file=source, column="field thermal")
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
        for key, shape in (
            ("G_um_per_N", (S, 3)),
            ("C_um_per_N", (3, 3)),
            ("grating_thermal_coef", (nh, S)),
            ("thermal_sigma_unit_um2", (S, S)),
            ("thermal_scale", (P,)),
            ("noise_var_um2", (S,)),
            ("active_forces", (3,)),
        ):
            array(L.get(key), f"load.{key}", shape)
        for key in ("max_force_N", "drift_N_per_s"):
            if key in L:
                array(L[key], f"load.{key}", (3,))
        if "interval_scale" in L:
            need(
                np.all(array(L["interval_scale"], "load.interval_scale", (3,)) > 0),
                "load.interval_scale",
                "must be > 0",
            )
        if "interval_trained" in L:
            t = L["interval_trained"]
            need(
                isinstance(t, list) and len(t) == 3 and all(isinstance(v, bool) for v in t),
                "load.interval_trained",
                "must be a list of 3 booleans",
            )
        need(np.all(np.asarray(L["noise_var_um2"], float) >= 0), "load.noise_var_um2", "must be >= 0")

    def interval(iv, at):
        need(isinstance(iv, dict), at, "must be a mapping or null")
        # vs_um2 and vc_um2 are absent from files written before those terms
        for key in (
            "v0_um2",
            "v1_um2",
            "v2_um2",
            *(k for k in ("vs_um2", "vc_um2", "resid_sd_um") if k in iv),
        ):
            need(np.all(array(iv.get(key), f"{at}.{key}", (3,)) >= 0), f"{at}.{key}", "must be >= 0")
        need(
            np.all(array(iv.get("dT_scale_K"), f"{at}.dT_scale_K", (P,)) > 0),
            f"{at}.dT_scale_K",
            "must be > 0",
        )
        if "deadband_K" in iv:
            array(iv["deadband_K"], f"{at}.deadband_K", (P,))
        a = iv.get("activity_scale_K")
        need(
            isinstance(a, (int, float)) and not isinstance(a, bool) and a > 0,
            f"{at}.activity_scale_K",
            "must be a positive number",
        )

    iv = d.get("interval")
    if iv is not None:
        interval(iv, "interval")
        # each probe's fallback's own interval (absent from files written before them)
        own = iv.get("without_probe", {})
        need(isinstance(own, dict), "interval.without_probe", "must be a mapping")
        for q, sub in own.items():
            need(q in probes, f"interval.without_probe.{q}", "names a probe the model does not read")
            interval(sub, f"interval.without_probe.{q}")
            need("resid_sd_um" in sub, f"interval.without_probe.{q}.resid_sd_um", "is missing")
        # each pair of probes' (absent from files written before them)
        pairs = iv.get("without_probes", [])
        need(isinstance(pairs, list), "interval.without_probes", "must be a list")
        for i, sub in enumerate(pairs):
            at = f"interval.without_probes[{i}]"
            need(isinstance(sub, dict), at, "must be a mapping")
            two = sub.get("probes")
            need(
                isinstance(two, list) and len(two) == 2 and len(set(map(str, two))) == 2,
                f"{at}.probes",
                "must name two probes",
            )
            need(all(q in probes for q in two), f"{at}.probes", "names a probe the model does not read")
            interval(sub, at)
            need("resid_sd_um" in sub, f"{at}.resid_sd_um", "is missing")
    tm = d.get("twin_map")
    if tm is not None:
        need(isinstance(tm, dict), "twin_map", "must be a mapping or null")
        k = S + P + len(MAP_LEADS_S)
        for key, shape in (
            ("coef", (k, 3)),
            ("gram", (k, k)),
            ("xty", (k, 3)),
            ("scale", (k,)),
            ("noise_gram", (k, k)),
            ("envelope_low", (k,)),
            ("envelope_high", (k,)),
        ):
            array(tm.get(key), f"twin_map.{key}", shape)
        need(np.all(np.asarray(tm["scale"], float) >= 0), "twin_map.scale", "must be >= 0")
        if "unseen_basis" in tm:
            ub = tm["unseen_basis"]
            r = len(ub[0]) if isinstance(ub, list) and ub and isinstance(ub[0], list) else -1
            need(0 <= r <= k, "twin_map.unseen_basis", f"must be a list of {k} rows of at most {k} numbers")
            array(ub, "twin_map.unseen_basis", (k, r))
        # the consensus members: one per undeclared source, and an estimated expansion's
        for field in ("without", "cte_members"):
            members = tm.get(field, [])
            need(isinstance(members, list), f"twin_map.{field}", "must be a list")
            for i, w in enumerate(members):
                need(isinstance(w, dict), f"twin_map.{field}[{i}]", "must be a mapping")
                array(w.get("gram"), f"twin_map.{field}[{i}].gram", (k, k))
                array(w.get("xty"), f"twin_map.{field}[{i}].xty", (k, 3))
                if "ttp_ms_um2" in w:
                    need(
                        np.all(array(w["ttp_ms_um2"], f"twin_map.{field}[{i}].ttp_ms_um2", (3,)) >= 0),
                        f"twin_map.{field}[{i}].ttp_ms_um2",
                        "must be >= 0",
                    )
                if "axes" in w:
                    axes = w["axes"]
                    need(
                        isinstance(axes, list) and len(axes) == 3 and all(isinstance(a, bool) for a in axes),
                        f"twin_map.{field}[{i}].axes",
                        "must be a list of 3 booleans (dx, dy, dz)",
                    )
        if "ttp_ms_um2" in tm:
            need(
                np.all(array(tm["ttp_ms_um2"], "twin_map.ttp_ms_um2", (3,)) >= 0),
                "twin_map.ttp_ms_um2",
                "must be >= 0",
            )
        cal = tm.get("calibration")
        if cal is not None:
            need(isinstance(cal, dict), "twin_map.calibration", "must be a mapping or null")
            leads = array(
                cal.get("leads_s"), "twin_map.calibration.leads_s", (len(cal.get("leads_s") or []),)
            )
            need(
                leads.size > 0 and np.all(leads > 0),
                "twin_map.calibration.leads_s",
                "must be positive time constants",
            )
            k = 1 + leads.size
            if "ambient_tau_s" in cal:
                tau = array([cal["ambient_tau_s"]], "twin_map.calibration.ambient_tau_s", (1,))
                need(tau[0] > 0, "twin_map.calibration.ambient_tau_s", "must be a positive time constant")
                k += 1
            taus = cal.get("heat_taus_s") or []
            need(
                isinstance(taus, list) and (len(taus) > 0) == (len(heat) > 0),
                "twin_map.calibration.heat_taus_s",
                "must be a list of time constants exactly when the model has heat_inputs",
            )
            if taus:
                taus = array(taus, "twin_map.calibration.heat_taus_s", (len(taus),))
                need(np.all(taus > 0), "twin_map.calibration.heat_taus_s", "must be positive time constants")
                k += taus.size * len(heat)
            array(cal.get("coef"), "twin_map.calibration.coef", (k, 3))
            for key in ("envelope_low", "envelope_high"):
                array(cal.get(key), f"twin_map.calibration.{key}", (k,))
            for key in ("noise_sd_um", "floor_sd_um", "floor_k", "zero_sd_um"):
                if key in cal:
                    need(
                        np.all(array(cal[key], f"twin_map.calibration.{key}", (3,)) >= 0),
                        f"twin_map.calibration.{key}",
                        "must be >= 0",
                    )
    ob = d.get("observer")
    if ob is not None:
        need(isinstance(ob, dict), "observer", "must be a mapping or null")
        obs_p = names(ob.get("probes"), "observer.probes")
        need(all(q in probes for q in obs_p), "observer.probes", "names a probe the model does not read")
        amb = names(ob.get("ambient"), "observer.ambient")
        need(all(q in probes for q in amb), "observer.ambient", "names a probe the model does not read")
        step = ob.get("step_s")
        need(
            isinstance(step, (int, float)) and not isinstance(step, bool) and step > 0,
            "observer.step_s",
            "must be a positive number",
        )
        lam = np.asarray(ob.get("lam_per_s"), dtype=object)
        need(lam.ndim == 1 and lam.size > 0, "observer.lam_per_s", "must be a non-empty list of rates")
        n = lam.size
        inputs = names(ob.get("input_names"), "observer.input_names")
        m = len(inputs) + 1
        k = n + m - 1
        need(
            np.all(array(ob["lam_per_s"], "observer.lam_per_s", (n,)) > 0),
            "observer.lam_per_s",
            "must be > 0",
        )
        array(ob.get("phi_b"), "observer.phi_b", (n, m))
        # the measured heat inputs it reads (absent from files written before them)
        measured = names(ob.get("measured", []), "observer.measured")
        need(
            all(h in heat for h in measured),
            "observer.measured",
            "names a heat input the model does not read",
        )
        rows = len(obs_p) + S + len(measured)
        array(ob.get("C"), "observer.C", (rows, k))
        array(ob.get("d"), "observer.d", (rows,))
        array(ob.get("C_ttp"), "observer.C_ttp", (3, k))
        array(ob.get("d_ttp"), "observer.d_ttp", (3,))
        need(np.all(array(ob.get("walk"), "observer.walk", (m - 1,)) >= 0), "observer.walk", "must be >= 0")
        need(np.all(array(ob.get("R"), "observer.R", (rows,)) > 0), "observer.R", "must be > 0")
        array(ob.get("nominal"), "observer.nominal", (m - 1,))
        if "n_probes" in ob:
            need(
                ob["n_probes"] == len(obs_p),
                "observer.n_probes",
                f"must be {len(obs_p)}, the probes it reads",
            )
            bias = array(ob.get("probe_bias_K"), "observer.probe_bias_K", (len(obs_p),))
            need(np.all(bias >= 0), "observer.probe_bias_K", "must be >= 0")
