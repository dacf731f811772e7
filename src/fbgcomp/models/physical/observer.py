"""A thermal state observer on the machine's FE twin: a Kalman filter over its reduced thermal model.

Issue 12 names this route beside the default's twin-learned map (:mod:`.thermal`). The twin's
reduced thermal model (:class:`fbgcomp.structure.thermal.ReducedThermal`) is a set of decoupled
first-order modes q driven by the inputs u = [ambient ΔT, heat source 1, ...]:

    q' = -λ q + Φᵀ B u,      y = O Φ q + D u

(y: the gratings' elongations, the TTP, the gratings' mean gauge temperatures and the point probes;
D the static correction of the truncated modes). The heat sources are unknown: each is a state
that walks at random (``heat_walk``), the ambient is measured and enters as a known input. Both
the probes and the gratings are measurements: on CFRP a grating's uncompensated reading is mostly
a thermometer of its gauge, ``elongation + ΔT_gauge · L · ((α_f + ξ)/(1 − p_e) − α_f)`` (paper eq.
2-4 with ΔT = 0, :func:`fbgcomp.optics.elongation_um`). The TTP is then read off the estimated
state, with its standard deviation from the filter's covariance.

Pure numpy; the step is fixed (``step_s``) and inputs are held over it (zero-order hold). A
missing measurement (NaN: a lost grating, a probe row not there) is left out of that step's update.
Measured on ram2 in ``benchmarks/bench_observer.py`` and docs/accuracy.md; in the physical model with
``fbgcomp fit --observer`` (:meth:`ThermalObserver.stream`), not by default.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np

from fbgcomp.optics import elongation_um, wavelength_nm
from fbgcomp.threads import one_blas_thread


@dataclass(frozen=True)
class ObserverResult:
    """What :meth:`ThermalObserver.run` estimates, one row per step.

    ttp_um : (n, 3) TTP displacement (dx, dy, dz) change from the first step, µm
    ttp_sd_um : (n, 3) its standard deviation from the filter's covariance, µm
    heat : (n, m) the heat inputs' estimates, in the order of ``input_names`` (W or W/m²)
    """

    time_s: np.ndarray
    ttp_um: np.ndarray
    ttp_sd_um: np.ndarray
    heat: np.ndarray
    input_names: tuple[str, ...]


def discretised(lam_per_s, phi_b, step_s):
    """The augmented model over one step of ``step_s`` (zero-order hold): z = [q, w] with q the
    modes (N,) and w the unknown heat inputs (m - 1,) as random walks.

    Returns A (N + m - 1, N + m - 1) and the ambient's input column b (N + m - 1,):
    z[k+1] = A z[k] + b · ambient[k]."""
    lam = np.asarray(lam_per_s, float)
    phi_b = np.asarray(phi_b, float)
    n, m = phi_b.shape
    e = np.exp(-lam * step_s)
    g = -np.expm1(-lam * step_s) / lam  # ∫₀ʰ e^(-λs) ds
    a = np.zeros((n + m - 1, n + m - 1))
    a[:n, :n] = np.diag(e)
    a[:n, n:] = g[:, None] * phi_b[:, 1:]
    a[n:, n:] = np.eye(m - 1)
    b = np.concatenate([g * phi_b[:, 0], np.zeros(m - 1)])
    return a, b


def grating_thermal_um_per_K(gauge_length_mm, photoelastic, thermo_optic_per_K, fibre_cte_per_K):
    """µm of uncompensated elongation per K of a grating's gauge: the optics' forward model
    (paper eq. 2-4) of 1 K on a strain-free path, read back with ΔT = 0."""
    pe, xi, af = (np.asarray(v, float) for v in (photoelastic, thermo_optic_per_K, fibre_cte_per_K))
    shifted = wavelength_nm(
        0.0, 1.0, gauge_length_mm, 1.0, photoelastic=pe, thermo_optic_per_K=xi, fibre_cte_per_K=af
    )
    return elongation_um(shifted, 1.0, gauge_length_mm, 0.0, photoelastic=pe)


class ThermalObserver:
    """Kalman filter of the twin's thermal state from probes and gratings.

    Parameters
    ----------
    twin : fbgcomp.structure.Twin
        The machine's twin (usually of :func:`fbgcomp.structure.scenarios.generic_heat_machine`,
        so that a heat source the description does not declare has a whole-face source to go to).
    sensors : sequence
        The campaign's gratings (``name``, ``gauge_length_mm``, ``photoelastic``,
        ``thermo_optic_per_K``, ``fibre_cte_per_K``), each a grating of the twin.
    probes : sequence of str
        Point probes of the twin read by the campaign, in the order of the measurements.
    step_s : float
        Filter step, s.
    heat_walk_W : float
        Random-walk intensity of each volume heat source, W per √s.
    flux_walk_W_per_m2 : float
        Random-walk intensity of each radiant source, W/m² per √s.
    probe_sd_K : float
        Probe noise and model error, K (one SD).
    grating_sd_um : float
        Grating noise and model error over a step, µm of uncompensated elongation (one SD).
    nonnegative : bool
        Hold every heat input at or above zero after each update (a projection). On ram2 with a
        wrong description it halves the worst errors and harms still (docs/accuracy.md).
    measured_inputs : sequence of str
        Heat inputs (of ``input_names``) that are measured, e.g. the spindle's power from the CNC:
        each is one more measurement, after the gratings in :meth:`run`'s ``gratings_um``
        columns, in the input's unit (W or W/m²); NaN where not read.
    measured_sd : float
        SD of such a reading as the heat the twin's source gives (W or W/m²).
    probe_bias_K : float or (P,) array
        SD of each probe's zero-state error, K: a constant state per probe the filter estimates
        (0: none). A zero read from one quantised sample is 0.1 K off, which the filter would
        otherwise explain with a heat input held for the whole run.
    """

    def __init__(
        self,
        twin,
        sensors,
        probes,
        step_s=10.0,
        heat_walk_W=5.0,
        flux_walk_W_per_m2=0.5,
        probe_sd_K=0.15,
        grating_sd_um=0.1,
        nonnegative=False,
        probe_bias_K=0.0,
        measured_inputs=(),
        measured_sd=5.0,
    ):
        red = twin.reduced
        s_all = list(twin.sensor_names)
        point = twin.machine.point_probe_names
        S, P = len(s_all), len(point)
        el = [s_all.index(s.name) for s in sensors]
        ts = [S + 3 + i for i in el]
        # a point probe's row, or a strain-free reference grating's (<sensor>_ref): its gauge's
        # mean temperature
        pr = [
            2 * S + 3 + point.index(p) if p in point else S + 3 + s_all.index(p[: -len("_ref")])
            for p in probes
        ]
        ttp = [S, S + 1, S + 2]
        assert red.OPhi.shape[0] == 2 * S + 3 + P
        c_t = grating_thermal_um_per_K(
            [s.gauge_length_mm for s in sensors],
            [s.photoelastic for s in sensors],
            [s.thermo_optic_per_K for s in sensors],
            [s.fibre_cte_per_K for s in sensors],
        )

        def rows(o, d):  # measurement rows on z = [q, w] and the ambient's column
            return np.hstack([o, d[:, 1:]]), d[:, 0]

        o_phi, dd = red.OPhi, red.D
        cp, dp = rows(o_phi[pr], dd[pr])
        cg, dg = rows(o_phi[el] + c_t[:, None] * o_phi[ts], dd[el] + c_t[:, None] * dd[ts])
        names = tuple(twin.input_names[1:])
        walk = [heat_walk_W if name.endswith("_W") else flux_walk_W_per_m2 for name in names]
        # a heat input read directly (a CNC's spindle power): a row on its own state
        cm = np.zeros((len(measured_inputs), cp.shape[1]))
        cm[
            np.arange(len(measured_inputs)),
            red.lam_per_s.size + np.array([names.index(h) for h in measured_inputs], int),
        ] = 1.0
        self._setup(
            red.lam_per_s,
            red.PhiB,
            np.vstack([cp, cg, cm]),
            np.concatenate([dp, dg, np.zeros(len(measured_inputs))]),
            *rows(o_phi[ttp], dd[ttp]),
            walk,
            np.concatenate(
                [
                    np.full(len(probes), probe_sd_K**2),
                    np.full(len(sensors), grating_sd_um**2),
                    np.full(len(measured_inputs), float(measured_sd) ** 2),
                ]
            ),
            step_s,
            names,
            [h.nominal for h in twin.machine.thermal.sources],
            nonnegative,
            len(probes),
            probe_bias_K,
        )

    def _setup(
        self,
        lam,
        phi_b,
        C,
        d,
        C_ttp,
        d_ttp,
        walk,
        R,
        step_s,
        names,
        nominal,
        nonnegative,
        n_probes=0,
        probe_bias_K=0.0,
    ):
        self.lam_per_s, self.phi_b = np.asarray(lam, float), np.asarray(phi_b, float)
        self.C_rows, self.d = np.asarray(C, float), np.asarray(d, float)
        self.C_ttp_rows, self.d_ttp = np.asarray(C_ttp, float), np.asarray(d_ttp, float)
        self.n_probes = int(n_probes)
        self.probe_bias_K = np.broadcast_to(np.asarray(probe_bias_K, float), (self.n_probes,)).copy()
        self.walk = np.asarray(walk, float)
        self.R = np.asarray(R, float)
        self.step_s = float(step_s)
        self.input_names = tuple(names)
        self.nominal = np.asarray(nominal, float)
        self.nonnegative = bool(nonnegative)
        a, b = discretised(self.lam_per_s, self.phi_b, self.step_s)
        n = self.lam_per_s.size
        # each probe's zero-state error as a constant state (a quantised probe's zero is one
        # reading: 0.1 K off reads as a heat input for as long as the run lasts)
        nb = self.n_probes if (self.probe_bias_K > 0).any() else 0
        k = a.shape[0]
        self.A = np.eye(k + nb)
        self.A[:k, :k] = a
        self.b = np.concatenate([b, np.zeros(nb)])
        self.C = np.hstack([self.C_rows, np.zeros((self.C_rows.shape[0], nb))])
        self.C[np.arange(nb), k + np.arange(nb)] = 1.0
        self.C_ttp = np.hstack([self.C_ttp_rows, np.zeros((3, nb))])
        self.Q = np.diag(np.concatenate([np.zeros(n), np.square(self.walk) * self.step_s, np.zeros(nb)]))
        self.n_modes = n
        self.n_heat = k - n
        # A = [[diag(e), G], [0, I]] (modes decay, the heat walks and probe zeros hold):
        # :meth:`_step` propagates the covariance block-wise, O(n² (k - n)) not O(k³)
        self._e = np.diag(self.A)[:n].copy()
        self._g = self.A[:n, n:].copy()
        self._q = np.diag(self.Q).copy()
        # the start: the heat inputs as uncertain as one step's walk, each probe's zero by its bias
        self.P0 = self.Q + np.diag(np.concatenate([np.zeros(k), np.square(self.probe_bias_K[:nb])]))

    def to_dict(self) -> dict:
        """The observer as a model file holds it (the reduced model's modes and the measured
        rows, not the discretised matrices: :func:`discretised` rebuilds them)."""
        return {
            "step_s": self.step_s,
            "lam_per_s": self.lam_per_s.tolist(),
            "phi_b": self.phi_b.tolist(),
            "C": self.C_rows.tolist(),
            "d": self.d.tolist(),
            "C_ttp": self.C_ttp_rows.tolist(),
            "d_ttp": self.d_ttp.tolist(),
            "walk": self.walk.tolist(),
            "R": self.R.tolist(),
            "input_names": list(self.input_names),
            "nominal": self.nominal.tolist(),
            "nonnegative": self.nonnegative,
            "n_probes": self.n_probes,
            "probe_bias_K": self.probe_bias_K.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> ThermalObserver:
        """The observer of :meth:`to_dict`'s dict."""
        obs = cls.__new__(cls)
        obs._setup(
            d["lam_per_s"],
            d["phi_b"],
            d["C"],
            d["d"],
            d["C_ttp"],
            d["d_ttp"],
            d["walk"],
            d["R"],
            d["step_s"],
            d["input_names"],
            d["nominal"],
            d.get("nonnegative", False),
            d.get("n_probes", 0),
            d.get("probe_bias_K", 0.0),
        )
        return obs

    def _start(self):
        return np.zeros(self.A.shape[0]), self.P0.copy()

    def _step(self, z, cov, meas, amb_prev, amb, first, extra_var=0.0):
        """One step of the filter: propagate from the last step (ambient ``amb_prev``) unless
        ``first``, then take the step's measurements ``meas`` (NaN: missing) at ambient ``amb``,
        their variance the noise's ``R`` plus ``extra_var``."""
        if not first:
            n, e, g = self.n_modes, self._e, self._g
            z = np.concatenate([e * z[:n] + g @ z[n:], z[n:]]) + self.b * amb_prev
            # A cov Aᵀ by blocks (modes | the rest): the rest's rows and columns stay, the
            # modes' block is E P11 E + E P12 Gᵀ + G P21 E + G P22 Gᵀ
            p12 = e[:, None] * cov[:n, n:] + g @ cov[n:, n:]
            p11 = (e[:, None] * cov[:n, :n] + g @ cov[n:, :n]) * e[None, :] + p12 @ g.T
            cov = cov.copy()
            cov[:n, :n] = p11
            cov[:n, n:] = p12
            cov[n:, :n] = p12.T
            cov.flat[:: cov.shape[0] + 1] += self._q
        ok = np.isfinite(meas)
        if ok.any():
            c = self.C[ok]
            r = (self.R + extra_var)[ok]
            m = c @ cov  # (p, k)
            s = m @ c.T + np.diag(r)
            gain = np.linalg.solve(s, m).T
            z = z + gain @ (meas[ok] - c @ z - self.d[ok] * amb)
            # Joseph form (I - K C) P (I - K C)ᵀ + K R Kᵀ, expanded so that it costs O(k² p):
            # P - K M - Mᵀ Kᵀ + K S Kᵀ with M = C P
            km = gain @ m
            cov = cov - km
            cov -= km.T
            cov += (gain @ s) @ gain.T
            cov += cov.T
            cov *= 0.5
        if self.nonnegative:
            z = z.copy()
            z[self.n_modes : self.n_modes + self.n_heat] = np.maximum(
                z[self.n_modes : self.n_modes + self.n_heat], 0.0
            )
        return z, cov

    def run(self, ambient_K, probes_K, gratings_um):
        """Filter a campaign on the observer's clock (one row per ``step_s``, from the zero state).

        ambient_K : (n,) ambient temperature change from the zero state, K
        probes_K : (n, P) point-probe changes, K (NaN: missing)
        gratings_um : (n, S) uncompensated elongation changes net of any applied load, µm (NaN: missing),
            then a column per ``measured_inputs`` (W or W/m²)
        """
        amb = np.asarray(ambient_K, float)
        meas = np.hstack([np.atleast_2d(probes_K), np.atleast_2d(gratings_um)])
        n = amb.size
        z, cov = self._start()
        out = np.empty((n, 3))
        sd = np.empty((n, 3))
        heat = np.empty((n, self.n_heat))
        with one_blas_thread():
            for i in range(n):
                z, cov = self._step(z, cov, meas[i], amb[i - 1] if i else 0.0, amb[i], i == 0)
                out[i] = self.C_ttp @ z + self.d_ttp * amb[i]
                sd[i] = np.sqrt(np.clip(((self.C_ttp @ cov) * self.C_ttp).sum(axis=1), 0.0, None))
                heat[i] = z[self.n_modes : self.n_modes + self.n_heat]
        t = np.arange(n) * self.step_s
        return ObserverResult(t, out - out[:1], sd, heat, self.input_names)

    def stream(self, state, time_s, ambient_K, probes_K, gratings_um, gate_k=3.0, gratings_var_um2=None):
        """The filter on the interrogator's own frames, carried between calls (the runtime's
        form of :meth:`run`): frames in (end - step_s, end] make one step, whose gratings are
        their mean and whose probes and ambient are its last frame's; a step ends at the first
        frame past it, and a step with no frame updates nothing (a gap in the feed).

        time_s (n,) s; ambient_K (n,) K; probes_K (n, P) K; gratings_um (n, S) µm of
        uncompensated elongation net of the applied load (NaN: missing), all as changes from the
        zero state. ``gratings_var_um2`` (n, S) µm²: each reading's error beyond the noise (the
        applied load's share, known to its signature's relative error), the step's largest added
        to the gratings' ``R``. ``state``: None for a new run, else the last call's.

        Returns the TTP (n, 3) µm each frame sees (the last finished step's estimate, as a change
        from the first step's; 0 before it), whether every heat estimate has stayed within
        ``gate_k`` times its nominal value so far (n,) bool (:func:`plausible`, latched), and
        the new state."""
        t = np.asarray(time_s, float).ravel()
        amb = np.asarray(ambient_K, float).ravel()
        pr = np.atleast_2d(np.asarray(probes_K, float))
        gr = np.atleast_2d(np.asarray(gratings_um, float))
        n = t.size
        if state is None and not n:  # an empty batch before the first frame: nothing to start
            return np.zeros((0, 3)), np.ones(0, bool), None
        if state is None:
            z, cov = self._start()
            state = {
                "z": z,
                "cov": cov,
                "end": float(t[0]) + self.step_s,
                "sum": np.zeros(gr.shape[1]),
                "count": np.zeros(gr.shape[1]),
                "var": np.zeros(gr.shape[1]),
                "last": None,  # the step's last frame: (probes, ambient)
                "amb_prev": 0.0,
                "steps": 0,
                "out": np.zeros(3),
                "zero": None,
                "ok": True,
            }
        else:
            state = dict(state)
        out = np.empty((n, 3))
        ok = np.empty(n, bool)
        # single-threaded BLAS only when a step closes in this batch (entering costs ~30 µs)
        with one_blas_thread() if n and t[-1] > state["end"] else contextlib.nullcontext():
            self._frames(state, t, amb, pr, gr, gate_k, gratings_var_um2, out, ok)
        return out, ok, state

    def _frames(self, state, t, amb, pr, gr, gate_k, gratings_var_um2, out, ok):
        """:meth:`stream`'s pass over the batch's frames, updating ``state``, ``out`` and ``ok``."""
        n = t.size
        i = 0
        while i < n:
            if t[i] > state["end"]:  # close the step before this frame
                cnt = state["count"]
                with np.errstate(invalid="ignore", divide="ignore"):
                    g = np.where(cnt > 0, state["sum"] / np.where(cnt > 0, cnt, 1.0), np.nan)
                if state["last"] is None:
                    meas, a = np.full(self.C.shape[0], np.nan), state["amb_prev"]
                else:
                    meas, a = np.concatenate([state["last"][0], g]), state["last"][1]
                extra = np.concatenate([np.zeros(self.C.shape[0] - cnt.size), state["var"]])
                state["z"], state["cov"] = self._step(
                    state["z"], state["cov"], meas, state["amb_prev"], a, state["steps"] == 0, extra
                )
                y = self.C_ttp @ state["z"] + self.d_ttp * a
                if state["zero"] is None:
                    state["zero"] = y
                state["out"] = y - state["zero"]
                heat = state["z"][self.n_modes : self.n_modes + self.n_heat]
                state["ok"] = state["ok"] and bool(plausible(heat, self.nominal, gate_k)[0])
                state.update(
                    amb_prev=a,
                    steps=state["steps"] + 1,
                    end=state["end"] + self.step_s,
                    sum=np.zeros_like(state["sum"]),
                    count=np.zeros_like(state["count"]),
                    var=np.zeros_like(state["var"]),
                    last=None,
                )
                continue
            j = int(np.searchsorted(t, state["end"], side="right"))  # frames i..j-1 in this step
            out[i:j] = state["out"]
            ok[i:j] = state["ok"]
            seg = gr[i:j]
            fin = np.isfinite(seg)
            state["sum"] = state["sum"] + np.where(fin, seg, 0.0).sum(axis=0)
            state["count"] = state["count"] + fin.sum(axis=0)
            if gratings_var_um2 is not None:
                state["var"] = np.maximum(state["var"], np.asarray(gratings_var_um2, float)[i:j].max(axis=0))
            state["last"] = (pr[j - 1], float(amb[j - 1]))
            i = j


def campaign_inputs(
    campaign,
    sensors,
    probes,
    ambient,
    step_s=10.0,
    zero_s=60.0,
    force_N=None,
    force_time_s=None,
    sensor_per_force_um_per_N=None,
):
    """A campaign's measurements on the observer's clock: step k covers (t0 + k h, t0 + (k+1) h]
    of the interrogator's clock and is stamped at its end (causal).

    Gratings: the mean uncompensated elongation change over each step (µm; the zero state is the
    mean of the first ``zero_s``), less ``sensor_per_force_um_per_N @ force_N`` where an applied
    force per interrogator frame is given. Probes and the ambient: the last reading up to the step's
    end, as changes from their mean over the first ``zero_s`` (K). Returns (end times (n,), ambient
    (n,), probes (n, P), gratings (n, S)); a step without a frame is NaN (left out of the update)."""
    fbg, temps = campaign.fbg, campaign.temperatures
    tf = fbg["time_s"].to_numpy(float)
    t0 = tf[0]
    n = int(np.floor((min(tf[-1], temps["time_s"].iloc[-1]) - t0) / step_s))
    ends = t0 + step_s * np.arange(1, n + 1)
    wl = fbg[[f"{s.name}_nm" for s in sensors]].to_numpy(float)
    first = tf <= t0 + zero_s
    el = elongation_um(
        wl,
        wl[first].mean(axis=0),
        np.array([s.gauge_length_mm for s in sensors]),
        0.0,
        photoelastic=np.array([s.photoelastic for s in sensors]),
    )
    if force_N is not None:
        f = np.column_stack([np.interp(tf, force_time_s, np.asarray(force_N)[:, j]) for j in range(3)])
        el = el - f @ np.asarray(sensor_per_force_um_per_N, float).T
    k = np.clip(np.ceil((tf - t0) / step_s).astype(int) - 1, 0, None)  # the step each frame falls in
    keep = k < n
    total = np.zeros((n, el.shape[1]))
    count = np.bincount(k[keep], minlength=n).astype(float)
    np.add.at(total, k[keep], el[keep])
    with np.errstate(invalid="ignore", divide="ignore"):
        gratings = total / count[:, None]
    tt = temps["time_s"].to_numpy(float)
    at = np.searchsorted(tt, ends, side="right") - 1
    zero = tt <= tt[0] + zero_s

    def read(names):
        v = temps[[f"{p}_C" for p in names]].to_numpy(float)
        out = v[np.clip(at, 0, None)] - v[zero].mean(axis=0)
        out[at < 0] = np.nan
        return out

    amb = read(ambient).mean(axis=1) if len(ambient) else np.zeros(n)
    return ends, np.nan_to_num(amb), read(probes), gratings


def plausible(heat, nominal, k=3.0):
    """Per step (n,), whether every heat input estimated so far has stayed within ``k`` times
    its source's nominal value (a source without one is not judged): once the filter needs an
    implausible input to explain the readings, the twin's dynamics disagree with the machine
    (a heat source declared wrongly or not at all, films off) and it stays untrusted.

    On ram2 with its data sheet's description the spindle estimate peaks at 230 W (150 W true,
    120 W nominal); with the radiant source undeclared it reaches 7 800 W, with the films
    doubled 3 200 W (benchmarks/bench_observer.py)."""
    heat = np.atleast_2d(np.asarray(heat, float))
    nominal = np.asarray(nominal, float)
    judged = nominal > 0
    bad = (np.abs(heat[:, judged]) > k * nominal[judged]).any(axis=1)
    return ~np.maximum.accumulate(bad)
