"""The physical model type (``model_type`` "physical", the default of ``fbgcomp fit``): :class:`PhysicalModel`.

Over 600 lines as one unit: the fits of the default model's parts (load signature, thermal map,
housing calibration, drift allowance, interval) share one set of training arrays and end in one
model file.

Fitting (load signature and compliance, the thermal part, the twin map's housing calibration,
the load tracker's drift allowance and the interval), the runtime contract and the model file.
The design is described in :mod:`fbgcomp.models.physical`.
"""

from __future__ import annotations

import copy
import logging
from itertools import combinations

import numpy as np

from fbgcomp.errors import InputError
from fbgcomp.io.campaign import HEAT_FILE, HEAT_SUFFIX, SensorSpec
from fbgcomp.io.campaign.align import diff_noise_sd, zero_state
from fbgcomp.models.base import (
    EstimatorParams,
    ModelFile,
    as_campaign_list,
    campaign_z_axis_mm,
    check_compatible,
)
from fbgcomp.models.distributions import chi2_ppf, norm_ppf
from fbgcomp.models.filters import first_order_filter
from fbgcomp.models.physical.observer import ThermalObserver, campaign_inputs
from fbgcomp.models.physical.predictor import FORCE_AXES, PhysicalPredictor, excursion2
from fbgcomp.models.physical.shapes import check_shapes
from fbgcomp.models.physical.thermal import (
    CAL_AMBIENT_TAU_S,
    CAL_LEADS_S,
    HEAT_TAUS_S,
    HOUSING_REST_S,
    ambient_probe_names,
    calibration_probe_columns,
    grating_map,
    grating_wavelengths_nm,
    housing_probe_names,
    population_at,
    ridge_from_moments,
    thermal_regressors,
    twin_thermal_population,
    unseen_basis,
    weighted_lstsq,
)
from fbgcomp.structure.machine import Machine, load_machine
from fbgcomp.structure.scenarios import ScenarioDesign, generic_heat_machine
from fbgcomp.threads import one_blas_thread
from fbgcomp.units import AXES

log = logging.getLogger(__name__)

#: The expansion calibration (:meth:`PhysicalModel._calibrate_cte`) moves a coefficient by at
#: most this many of its prior SDs from the description's value,
CTE_PRIOR_BOUND = 3.0
#: and only where the estimate is further than this many prior SDs from it (a data sheet's
#: tolerance: 0.5e-6 /K on a CFRP's axial expansion with the default prior).
CTE_TOLERANCE_SD = 0.5

#: High-pass of a combined campaign's signals before its load signature is read, s: heat moves
#: the gratings by minutes to hours, a load step within seconds.
SIGNATURE_HIGHPASS_S = 60.0

#: A force component the gratings cannot read counts as applied beyond this |force|, N (below
#: it: a load cell's noise on a component no one loads).
UNREAD_FORCE_N = 50.0

#: A combined campaign with known forces is thermal training where no force acts: its samples
#: without a component beyond UNREAD_FORCE_N, this long (s) before and after any that has one
#: (the load tracker's transition settles in a few offset_tau_s).
THERMAL_LOAD_MARGIN_S = 120.0


def load_free_samples(loads_N, time_s, margin_s=THERMAL_LOAD_MARGIN_S) -> np.ndarray:
    """(n,) bool: the samples of a campaign with known forces ``loads_N`` (n, 3) N at
    ``time_s`` (n,) s that lie more than ``margin_s`` from any sample with a force component
    beyond :data:`UNREAD_FORCE_N` or unknown (NaN: the load cell's gap may hold a load)."""
    t = np.asarray(time_s, float)
    on = ~(np.abs(np.asarray(loads_N, float)) <= UNREAD_FORCE_N).all(axis=1)
    if not on.any():
        return np.ones(t.size, bool)
    t_on = t[on]
    # the nearest loaded sample's time on either side of each sample
    k = np.searchsorted(t_on, t)
    before = np.where(k > 0, t - t_on[np.maximum(k - 1, 0)], np.inf)
    after = np.where(k < t_on.size, t_on[np.minimum(k, t_on.size - 1)] - t, np.inf)
    return (np.minimum(before, after) > margin_s) & ~on


def _free(row, a):
    """A training campaign's per-sample array ``a`` at its thermal training samples (the row's
    ``free`` mask; all of them where it is None)."""
    return a if row["free"] is None else a[row["free"]]


def effective_samples(x) -> float:
    """Effective number of independent samples in the series ``x``: n / tau, with tau the
    integrated autocorrelation time 1 + 2 sum rho_k, summed while rho_k stays positive (Geyer's
    initial positive sequence, simplified); between 1 and n."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)] - np.nanmean(x) if x.size else x
    n = x.size
    if n < 3 or not np.any(x):
        return float(max(n, 1))
    f = np.fft.rfft(x, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n]
    rho = acf / acf[0]
    neg = np.nonzero(rho[1:] <= 0.0)[0]
    stop = neg[0] + 1 if neg.size else n
    tau = 1.0 + 2.0 * rho[1:stop].sum()
    return float(np.clip(n / tau, 1.0, n))


def probe_noise_sd_K(campaigns, probe_names) -> np.ndarray:
    """White noise of each probe (K), from the successive differences of its own samples on its
    own clock, over all ``campaigns``: RMS / sqrt(2). Differences of the frames would not do: a
    probe read every 10 s and held over 1 s frames has 9 differences of 10 at zero, and a
    quantised one (0.1 K steps) most of the rest, so a robust MAD of them reads 0 K (on the
    twin, where the probes scatter by 0.1 K, the thermal part's noise came out 0.02 µm against
    0.2 µm, and the noise of a zero state went into the correction). Heat moves a probe far
    less than its noise between two samples, so no trend is removed. A probe no campaign reads
    from temperatures.csv (a reference grating) gets 0."""
    sums = np.zeros(len(probe_names))
    counts = np.zeros(len(probe_names))
    for c in campaigns:
        for names, (_t, values) in c.thermometers().items():
            d = np.diff(values, axis=0)
            if len(d) == 0:
                continue
            for k, name in enumerate(names):
                if name in probe_names:
                    j = probe_names.index(name)
                    ok = np.isfinite(d[:, k])
                    sums[j] += float(np.sum(d[ok, k] ** 2))
                    counts[j] += int(ok.sum())
    return np.sqrt(np.where(counts > 0, sums / np.maximum(counts, 1) / 2.0, 0.0))


#: Frames of instrument noise the thermal part's noise floor is measured on, past the housing's
#: rest window (:meth:`PhysicalModel._noise_floor`), s: its slow parts (the ambient's hour
#: low-pass, the housing's leads) hold few independent samples in two hours, and ram2's floor
#: drawn with five seeds spread 1.22x over 7200 s, 1.04x over 24 h (0.4 s of a fit).
NOISE_FLOOR_S = 86400.0


def trained_z_axis_mm(campaigns, machine=None) -> list[float]:
    """The Z-axis positions (mm) the training campaigns were measured at, sorted: each one's
    ``z_axis_mm``, or for a campaign that records none the description's ``supports.z_axis_mm``
    (0 without a description), the position its twin is built at too."""
    default = float(machine.supports.z_axis_mm) if machine is not None else 0.0
    zs = (campaign_z_axis_mm(c) for c in campaigns)
    return sorted({default if z is None else z for z in zs})


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
    unseen_relative_error : float
        Relative error (one SD) of the part of the twin map's correction that rests on feature
        directions no load-free training campaign moved along (:func:`unseen_basis`): how far
        the twin's response to such a state is trusted, which is as far as the machine's
        description is right. It widens the interval only, never the correction.
    thermal_relative_error : float
        Relative error (one SD) of the whole thermal correction, however well the training
        campaigns' residuals say it is known: a housing warming another way than in training
        (another duty cycle, walls at another temperature) leaves an error of a fraction of a
        percent of the correction that no training residual shows (ram5's thermal_c: dz 0.45
        µm off for six hours on 54 µm, inside an interval of +-0.3 µm). It widens the interval
        only, never the correction. 0 in model files from before it.
    observer : bool
        Average the map's thermal correction with a thermal state observer's (a Kalman filter
        on the twin's reduced thermal model, :mod:`.observer`) while the observer's heat
        estimates stay within 3x their sources' nominal values, the two's disagreement widening
        the interval (``fbgcomp fit --observer``). Off by default: on ram2 it takes thermal_b's
        dz from 4.62 to 3.88 µm and thermal_c's from 5.22 to 3.93, but on a second independent
        ram it takes the loaded thermal campaign's dy from 8.27 to 9.17 (docs/accuracy.md).
    heat_prior : {"training", "declared"}
        The power the twin's scenarios run each volume heat source at (the map's prior on how
        hard the bearings work). "training": the mean the thermal observer infers on the
        load-free training campaigns, divided by the scenarios' mean duty level, within 1/4-4x
        the declared ``nominal_W`` (the declared value where the campaigns show the source
        idle); "declared": the description's ``nominal_W``.
    heat_inputs : bool
        Take the measured heat inputs of the campaigns (``heat.csv``: a spindle's power as the
        CNC reads it) into the housing calibration, low-passed at ``HEAT_TAUS_S``, when every
        thermal or combined training campaign carries them (:meth:`_calibrate_housing`). The
        model then reads them after its probes (``probe_names``: ``<source>_W``; the runtime
        feeds them as it feeds probes), and every campaign it judges but a static one must carry
        them. The housing probe sees a power step minutes late, the power itself at once: ram2's
        thermal_b dz 4.62 -> 1.84 µm with its bearings' heat read (docs/accuracy.md).
    calibrate_cte : bool
        Test the description's expansion coefficients against the measured load-free campaigns
        and, where they contradict it, put the map of the coefficients they ask for beside the
        description's as a consensus member (:meth:`_calibrate_cte`): the face-gradient
        response no training campaign checks turns on them.
    cte_prior_sd_per_K : (3,) floats
        The prior's SDs of those coefficients (per K), in the order CFRP along the fibres, CFRP
        across, housing; 0 keeps one as described. The default estimates the CFRP's axial
        coefficient alone, the near-zero number data sheets give loosely: with the other two
        free as well, ram2's training took its transverse coefficient from 26e-6 to 12e-6 /K
        and its thermal_b dx from 2.3 to 29 µm.
    cte_test_p : float
        False-alarm probability of the test that the training contradicts the description
        (likelihood ratio, chi-square with one degree per estimated coefficient).
    z_tolerance_mm : float
        How far (mm) the Z-axis position a frame is predicted at may lie from every position
        the training was measured at (``trained_z_axis_mm_``) before its lateral correction is
        held back (dx and dy, flag ``SHRUNK``; the interval takes in the correction held back).
        The ram slides through its carriages: its overhang, and with it the TTP's compliance
        and the lateral thermal drift, change with Z (on the built-in twin, trained at Z = 0,
        static-xyz at Z = 300 mm came out dx 564 µm off on 467 uncompensated,
        ``benchmarks/bench_z_position.py``). dz is kept: the ball-screw nut travels with the
        ram, and neither the axial compliance nor the housing's and box's growth depends on Z.
        10 mm: about 3 % of a load's deflection on a 1 m overhang (compliance ~ overhang^3).
    link_loss_tau_s : float
        When every grating is lost (the interrogator or its link down) the set without gratings
        corrects from the probes, which see no gradient between the faces. It goes on from the
        last thermal correction the gratings gave, the difference fading with this time
        constant (s): what they read of a gradient persists while the walls keep their
        temperatures. 3600 s, the hour ram2's walls take to follow the hall (the calibration's
        ambient time constant); 0 corrects from the probes alone. The load read from the
        gratings is not carried (no force can be read without them), and nothing is carried
        when the link is lost under a held force: the gratings' thermal reading is then net of
        a load read with its signature's relative error (``benchmarks/bench_link_loss.py``).
    """

    model_type = "physical"
    #: what a fit's served predictions share, during the fit only (:meth:`fit`)
    _served_memo: dict | None = None

    def __init__(
        self,
        machine=None,
        zero_window_s=10.0,
        lead_tau_s=300.0,
        envelope_margin=0.1,
        load_k_sigma=3.0,
        contradiction_p=1e-3,
        thermal_error_inflation=4.0,
        load_relative_error=0.03,
        twin_scenarios=40,
        map_ridge=1e-3,
        separability_cos=0.95,
        offset_tau_s=20.0,
        calibrate_housing=True,
        unseen_relative_error=0.2,
        thermal_relative_error=0.005,
        observer=False,
        heat_prior="training",
        heat_inputs=True,
        calibrate_cte=True,
        cte_prior_sd_per_K=(1.0e-6, 0.0, 0.0),
        cte_test_p=1e-2,
        z_tolerance_mm=10.0,
        link_loss_tau_s=3600.0,
    ):
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
        self.unseen_relative_error = unseen_relative_error
        self.thermal_relative_error = thermal_relative_error
        self.observer = observer
        self.heat_prior = heat_prior
        self.heat_inputs = heat_inputs
        self.calibrate_cte = calibrate_cte
        self.cte_prior_sd_per_K = cte_prior_sd_per_K
        self.cte_test_p = cte_test_p
        self.z_tolerance_mm = z_tolerance_mm
        self.link_loss_tau_s = link_loss_tau_s

    # -- fitting -----------------------------------------------------------------------------
    def _machine(self):
        if self.machine is None:
            return None
        return self.machine if isinstance(self.machine, Machine) else load_machine(self.machine)

    def fit(self, X, y=None, *, progress=None):
        """Fit on campaigns (``X`` a campaign, a path or a list of them; ``y`` must be None)."""
        # A fit serves each load-free training campaign ~20 times (ram2: the intervals of every
        # probe's and pair's fallback, the held-out halves). What those share is taken once and
        # dropped with the fit: each campaign's frames (_served) and the load tracker's results
        # from rest (PhysicalPredictor._track_load_from_rest).
        self._served_memo = {"frames": {}, "load": {}}
        try:
            return self._fit_campaigns(X, y, progress)
        finally:
            self._served_memo = None

    def _fit_campaigns(self, X, y, progress):
        if y is not None:
            raise ValueError("PhysicalModel fits on campaigns (y must be None)")
        campaigns = as_campaign_list(X)
        if not campaigns:
            raise ValueError("fit needs at least one campaign")
        machine = self._machine()
        first = campaigns[0]
        self.sensors_ = list(first.meta.sensors)
        common = [p for p in first.meta.probe_names if all(p in c.meta.probe_names for c in campaigns[1:])]
        self.housing_probes_ = housing_probe_names(common, machine)
        self.ambient_probes_ = ambient_probe_names(common, machine)
        sensor_probes = [s.temperature_probe for s in self.sensors_ if s.temperature_probe]
        # a strain-free reference grating reads its gauge's own temperature: a thermometer
        # the twin map takes beside the probes even where the sensor names a probe to
        # compensate it (that choice is the paper's eq. 4, not the map's)
        references = [s.reference_probe for s in self.sensors_ if s.reference_probe in common]
        self.probe_names_ = list(
            dict.fromkeys(sensor_probes + references + self.housing_probes_ + self.ambient_probes_)
        )
        self.heat_inputs_ = self._heat_input_names(campaigns, machine)
        self.trained_z_axis_mm_ = trained_z_axis_mm(campaigns, machine)
        for c in campaigns:
            check_compatible(self, c)
        if machine is not None:
            self._check_described(machine, first)
        aligned = [c.aligned(zero_window_s=self.zero_window_s) for c in campaigns]
        dts = [np.median(np.diff(a.time_s)) for a in aligned if len(a.time_s) > 1]
        self.nominal_dt_s_ = float(np.median(dts)) if dts else 1.0
        fmap = grating_map(self.sensors_, self.probe_names_)

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
            H, _ = thermal_regressors(
                t - t0,
                [self.probe_names_.index(p) for p in self.housing_probes_],
                [self.probe_names_.index(p) for p in self.ambient_probes_],
                self.lead_tau_s,
                a.time_s,
            )
            F = a.loads_N
            # A static or combined campaign without loads.csv was loaded by forces nobody
            # recorded: its deviations are no thermal drift, so it is kept out of everything
            # thermal (and, without forces, out of the load regression). Taken as load-free,
            # ram2's static_xyz without its loads.csv made thermal_b dy 348 µm off on 18.
            forces_unknown = F is None and c.meta.kind in ("static", "combined")
            loaded = forces_unknown or (
                F is not None and np.nanmax(np.abs(np.nan_to_num(F))) > UNREAD_FORCE_N
            )
            # the samples that are thermal training: every one of a load-free campaign (None);
            # those where no force acts of a combined campaign with known forces (ram2's
            # thermal_c, -2500 N from 3 h to 7 h of 12, with static_xyz as the only other
            # training: no thermal part at all, every axis uncompensated on thermal_b and an
            # interval of 0.1 µm that covered 0.012 of dz); none of a static campaign
            free = None
            if loaded:
                free = np.zeros(len(a.time_s), bool)
                if c.meta.kind == "combined" and not forces_unknown:
                    free = load_free_samples(F, a.time_s)
                    if free.sum() < 10:
                        free[:] = False
            rows.append(
                {
                    "name": c.meta.name,
                    "e": e,
                    "H": H,
                    "dT": t - t0,
                    "t": a.time_s,
                    "y": a.reference_um,
                    "zero": (w0, t0),  # the zero state's wavelengths and temperatures
                    "F": None if F is None else np.nan_to_num(F),
                    "loaded": loaded,
                    "free": free,
                    "thermal": free is None or bool(free.any()),
                    "forces_unknown": forces_unknown,
                    "heated": c.meta.kind == "combined",
                }
            )
        thermal_rows = [r for r in rows if r["thermal"]]
        loaded_rows = [r for r in rows if r["loaded"] and not r["forces_unknown"]]
        nh = rows[0]["H"].shape[1]
        S = len(self.sensor_names)

        # Gratings' thermal reading vs the thermal regressors, on load-free campaigns: their
        # thermal samples' regressors Hs, each campaign weighted equally (ws); the TTP's thermal
        # part below is fitted on the same
        if thermal_rows:
            H_rows = [_free(r, r["H"]) for r in thermal_rows]
            Hs = np.vstack(H_rows)
            ws = np.concatenate([np.full(len(h), 1.0 / len(h)) for h in H_rows])
            Es = np.vstack([_free(r, r["e"]) for r in thermal_rows])
            B, _ = weighted_lstsq(Hs, Es, ws)
            dTs = np.vstack([_free(r, r["dT"]) for r in thermal_rows])
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
        # the gratings' frame noise, read on every training campaign, loaded or not: a training
        # set without loads left it NaN and the step test fell back to 0.05 µm, a sixth of the
        # twin's frame noise, so noise started loads on every held-out frame (the twin's
        # thermal-36h-b fitted on thermal-36h alone: dx 1123 µm against 3.1 uncompensated)
        noise_var, frame_dt = self._frame_noise_var(campaigns, aligned, rows, fmap)
        if loaded_rows:
            Xs, Es_, Ys, ws_ = [], [], [], []
            k = len(loaded_rows)
            F_raw = []
            for i, r in enumerate(loaded_rows):
                n = len(r["e"])
                onehot = np.zeros((n, k))
                onehot[:, i] = 1.0
                F, E, Y, H = r["F"], r["e"], r["y"], r["H"][:, 1:]
                if r["heated"]:
                    # A combined campaign heats while it loads: the gratings' thermal reading that
                    # no probe sees (a face warmer than its opposite) moves with the hours a load is
                    # held and went into the signature (ram2 thermal_c as the only loaded training:
                    # Fx read 0.2-0.3 µm/kN on S3 and S4, which see none, and thermal_c's own dy
                    # came out 5.8 µm off on 3.7). Its signature is read from the load changes
                    # alone: every signal less its SIGNATURE_HIGHPASS_S low-pass, which heat
                    # hardly moves and a load step does at once.
                    F, E, Y, H = (
                        v - first_order_filter(v, r["t"], SIGNATURE_HIGHPASS_S)[0] for v in (F, E, Y, H)
                    )
                    onehot[:] = 0.0
                F_raw.append(r["F"])
                Xs.append(np.hstack([onehot, F, H]))
                Es_.append(E)
                Ys.append(Y)
                ws_.append(np.full(n, 1.0 / n))
            X = np.vstack(Xs)
            w_all = np.concatenate(ws_)
            Fall = np.vstack(F_raw)
            active = np.sqrt(np.average(Fall**2, axis=0, weights=w_all)) > 100.0
            cols = list(range(k)) + [k + j for j in range(3) if active[j]] + list(range(k + 3, X.shape[1]))
            Bg, _ = weighted_lstsq(X[:, cols], np.vstack(Es_), w_all)
            By, _ = weighted_lstsq(X[:, cols], np.vstack(Ys), w_all)
            G = np.zeros((S, 3))
            C = np.zeros((3, 3))
            G[:, active] = Bg[k : k + active.sum()].T
            C[:, active] = By[k : k + active.sum()].T
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
            u = np.linalg.svd(np.vstack([_free(r, r["e"]) for r in thermal_rows]), full_matrices=False)[2][0]
            norm = np.linalg.norm(G, axis=0)
            cos = np.abs(u @ G) / np.where(norm > 0, norm, 1.0)
            separable = cos < self.separability_cos
            active = active & separable
        if G is not None and active.any():
            self.load_ = {
                "G_um_per_N": G.tolist(),
                "C_um_per_N": C.tolist(),
                "active_forces": active.tolist(),
                "grating_thermal_coef": B.tolist(),
                "thermal_sigma_unit_um2": (self.thermal_error_inflation * cov_unit).tolist(),
                "thermal_scale": scale.tolist(),
                "noise_var_um2": noise_var.tolist(),
                "noise_frame_dt_s": float(frame_dt),
                "max_force_N": np.where(max_force > 0, max_force, 5000.0).tolist(),
                "source": source,
                "not_separable": [f for f, ok in zip(FORCE_AXES, separable) if not ok],
            }
        # Thermal part of the TTP: y minus the (policy-applied) load part, on load-free campaigns.
        self.thermal_coef_ = np.zeros((nh, 3))
        self.thermal_envelope_ = (np.zeros(nh - 1), np.zeros(nh - 1))
        self.thermal_range_um_ = (np.zeros(3), np.zeros(3))
        self.thermal_resid_sd_um_ = np.full(3, 0.1)
        self.thermal_noise_sd_um_ = np.zeros(3)
        if thermal_rows:
            Ys = np.vstack([_free(r, r["y"]) for r in thermal_rows])
            # through the origin: every campaign is zeroed at its start (dT = 0, y = 0), so a
            # fitted intercept is a bias applied to every frame of every campaign (on the twin
            # -0.33 µm of dz, more than a static campaign's whole dz: a correction that harms)
            A1, cov_y = weighted_lstsq(Hs[:, 1:], Ys, ws)
            A = np.vstack([np.zeros((1, Ys.shape[1])), A1])
            self.thermal_coef_ = A
            self.thermal_envelope_ = (Hs[:, 1:].min(axis=0), Hs[:, 1:].max(axis=0))
            fitted = Hs @ A
            span = np.abs(Ys).max(axis=0)
            self.thermal_range_um_ = (
                np.minimum(fitted.min(axis=0), Ys.min(axis=0)) - 0.1 * span,
                np.maximum(fitted.max(axis=0), Ys.max(axis=0)) + 0.1 * span,
            )
            self.thermal_resid_sd_um_ = np.sqrt(np.diag(cov_y))
            # the part's response to probe noise (the zero state itself is one noisy reading of
            # a slow probe): each regressor's probe noise through its coefficient
            sd_p = probe_noise_sd_K(campaigns, self.probe_names_)
            used = [self.probe_names_.index(q) for q in self.housing_probes_ + self.ambient_probes_]
            sd_h = np.concatenate([sd_p[used], sd_p[used[:1]] if self.housing_probes_ else []])
            self.thermal_noise_sd_um_ = np.sqrt(((A[1:] * np.asarray(sd_h)[:, None]) ** 2).sum(axis=0))
        # Thermal part learned from the twin's thermal physics, when the machine describes
        # every grating and probe of the campaigns (the face-gradient coefficients no measured
        # campaign without a gradient can teach).
        self.twin_map_ = None
        self.observer_ = None
        self._cte_moments = None
        heat_twin = None  # the twin of generic_heat_machine: the map's, the prior's, the observer's
        if machine is not None and self.twin_scenarios > 0:
            from fbgcomp.structure import Twin  # noqa: PLC0415 - optional extra: scikit-fem (the FE twin)

            heat_twin = Twin(generic_heat_machine(machine))
            prior = (
                self._heat_prior(machine, campaigns, rows, heat_twin) if self.heat_prior == "training" else {}
            )
            pop = twin_thermal_population(
                machine,
                self.sensors_,
                self.probe_names_,
                self.housing_probes_,
                n_scenarios=self.twin_scenarios,
                seed=0,
                nominal_W=prior,
                twin=heat_twin,
                per_material=bool(self.calibrate_cte),
            )
            if pop is not None:
                pop["heat_prior_W"] = prior
                # the per-material moments serve the expansion calibration below, not the file
                self._cte_moments = pop.pop("cte", None)
                pop["coef"] = ridge_from_moments(
                    pop["gram"], pop["xty"], pop["scale"], range(len(pop["scale"])), self.map_ridge
                ).tolist()
                self.twin_map_ = pop
        # Load-part uncertainty calibrated on loaded campaigns: the load part's residual.
        self.training_ = {
            "campaigns": [
                {"name": r["name"], "loaded": bool(r["loaded"]), "n_samples": len(r["y"])}
                | ({"forces_unknown": True} if r["forces_unknown"] else {})
                | ({"thermal_samples": int(r["free"].sum())} if r["loaded"] and r["thermal"] else {})
                for r in rows
            ],
            "n_samples": int(sum(len(r["y"]) for r in rows)),
        }
        self._predictors = {}
        if self.load_ is not None:
            self._calibrate_drift(rows)
        # the housing calibration: of the housing probe's leads, or of the measured heat inputs
        # alone where no probe is on the housing (its columns are then zeros)
        calibrating = (
            self.twin_map_ is not None
            and bool(thermal_rows)
            and self._sees_housing
            and self.calibrate_housing
        )
        if self.heat_inputs_ and not calibrating:
            # only the housing calibration takes the heat inputs
            log.warning(
                "heat.csv (%s) not used: the housing calibration takes it, and it runs only with a "
                "machine description, a load-free training campaign and calibrate_housing on",
                ", ".join(self.heat_inputs_),
            )
            self.heat_inputs_ = []
        if calibrating:
            self.twin_map_["calibration"] = self._calibrate_housing(rows, campaigns)
            if self.calibrate_cte and self._cte_moments is not None:
                self.twin_map_["cte"] = self._calibrate_cte(rows)
                self._predictors = {}
            noise, heat_noise, k, zero = self._noise_floor(campaigns)
            self.twin_map_["calibration"]["floor_sd_um"] = noise.tolist()
            self.twin_map_["calibration"]["zero_sd_um"] = zero.tolist()
            self.twin_map_["calibration"]["floor_k"] = k.tolist()
            if self.heat_inputs_:
                self.twin_map_["calibration"]["heat_noise_sd_um"] = heat_noise.tolist()
            self._predictors = {}
        if self.twin_map_ is not None and thermal_rows:
            # the map's error on the measured load-free campaigns (only the housing transient is
            # fitted there) sets its interval and widens the validated range to what the twin
            # covers; the features they move along leave the rest unseen (:func:`unseen_basis`,
            # every frame of each campaign weighted equally)
            res, X, w = [], [], []
            for r, c in zip(rows, campaigns):
                if not r["thermal"]:
                    continue
                pred, _, p, at = self._served(c, policy=False)
                res.append(_free(r, pred - r["y"]))
                if r["free"] is None:
                    X.append(p.last_map_features)
                else:  # the frames of the load-free reference times
                    X.append(p.last_map_features[np.unique(at[r["free"]])])
                w.append(np.full(len(X[-1]), 1.0 / len(X[-1])))
            basis = unseen_basis(np.vstack(X), np.concatenate(w), self.twin_map_["scale"])
            self.twin_map_["unseen_basis"] = basis.tolist()
            self._predictors = {}
            res = np.vstack(res)
            self.thermal_resid_sd_um_ = np.sqrt(np.mean(res**2, axis=0))
            lo, hi = np.asarray(self.twin_map_["ttp_low_um"]), np.asarray(self.twin_map_["ttp_high_um"])
            span = hi - lo
            self.thermal_range_um_ = (
                np.minimum(self.thermal_range_um_[0], lo - 0.1 * span),
                np.maximum(self.thermal_range_um_[1], hi + 0.1 * span),
            )
        self.interval_ = self._fit_interval(rows, campaigns) if thermal_rows else None
        self._predictors = {}
        if self.load_ is not None and self.interval_ is not None:
            scale, trained = self._fit_load_interval(rows, campaigns)
            self.load_["interval_scale"] = scale.tolist()
            self.load_["interval_trained"] = trained.tolist()
            self._predictors = {}
        if self.interval_ is not None and self.twin_map_ is not None and not self.observer:
            # each probe's fallback (fallback_sets) errs by more than the full model: without the
            # housing probe it loses the housing calibration as well, which the twin population's
            # lost information does not count (ram2 thermal_c served from the start without
            # T_flange: dz covered 0.85, without T_amb 0.47). Its own interval, fitted as the
            # full model's on its own training errors, speaks for it
            self.interval_["without_probe"] = {
                q: self._fit_interval(rows, campaigns, exclude=frozenset({q})) for q in self.probe_names_
            }
            # and each pair's (two probes on one lost input module, or a fibre past both of
            # ram4's reference gratings), for the same reason
            self.interval_["without_probes"] = [
                {"probes": list(pair)} | self._fit_interval(rows, campaigns, exclude=frozenset(pair))
                for pair in combinations(sorted(self.probe_names_), 2)
            ]
            self._predictors = {}
        # the thermal state observer, the map's partner (PhysicalPredictor._with_observer): the
        # intervals above are the map's own, calibrated before it joins; the two members'
        # disagreement widens them
        self.observer_ = (
            self._observer(machine, campaigns, heat_twin)
            if self.twin_map_ is not None and self.observer
            else None
        )
        self._predictors = {}
        self._cal_rows = self._map_rows = self._cte_moments = None
        return self

    def _calibrate_cte(self, rows) -> dict:
        """The test of the description's expansion coefficients against the measured load-free
        campaigns (returned for the model file), and, where they contradict it, the map of the
        coefficients they ask for as one more consensus member (``twin_map["cte_members"]``).

        The twin's face-gradient response, which no training campaign checks, turns on the
        expansion coefficients: on a CFRP ram its sign follows the fibres' own, a number near
        zero that data sheets give loosely (ram4 with the CFRP's axial coefficient as 0 /K
        instead of its 1.0e-6: thermal_b dx 17.2 µm against 10.3 uncompensated). The response
        the training does check, the uniform warming and the housing's, turns on the same
        coefficients. So they are estimated, maximum a posteriori with the description's values
        as the prior's mean (``cte_prior_sd_per_K`` its SD) and, per axis, the profile
        likelihood ``n_eff/2 log J(alpha)`` of the training residual left once the housing
        calibration has taken its part (``J``, the mean square; ``n_eff`` the residual's
        effective sample count, :func:`effective_samples`); and put beside the description's
        map only where the training contradicts the description (``cte_test_p``) by more than
        a data sheet's tolerance (``CTE_TOLERANCE_SD``). The map is linear in the
        coefficients' moments (:func:`population_at`), so each trial costs one ridge solve."""
        tm, cte = self.twin_map_, self._cte_moments
        tm["cte"] = cte  # population_at reads it here
        A = np.vstack(self._cal_rows[0])
        Q = np.linalg.qr(A)[0] if A.shape[1] else np.zeros((A.shape[0], 0))
        X = np.vstack([r[0] for r in self._map_rows])
        Y = np.vstack([r[1] for r in self._map_rows])
        alpha0 = np.asarray(cte["nominal_per_K"], float)
        sd = np.asarray(self.cte_prior_sd_per_K, float)
        k = X.shape[1]

        def residual(alpha):
            pa = population_at(tm, alpha)
            R = Y - X @ ridge_from_moments(pa["gram"], pa["xty"], pa["scale"], range(k), self.map_ridge)
            return R - Q @ (Q.T @ R)

        # the residual's effective sample count per axis, at the described coefficients, summed
        # over the campaigns (each weighted equally in J)
        R0 = residual(alpha0)
        n_eff, start = np.zeros(3), 0
        for r in self._map_rows:
            n = len(r[0])
            n_eff += [effective_samples(R0[start : start + n, j]) for j in range(3)]
            start += n
        floor = 1e-12 + 1e-9 * np.sum(Y**2, axis=0)

        def objective(u):
            J = np.sum(residual(alpha0 + sd * u) ** 2, axis=0) + floor
            return 0.5 * float(np.sum(n_eff * np.log(J))) + 0.5 * float(u @ u)

        from scipy import optimize  # noqa: PLC0415 - start-up: fit-time only

        free = np.flatnonzero(sd > 0)
        u = np.zeros(len(alpha0))
        if free.size == 1:
            j = free[0]

            def along(v):
                u[j] = v
                return objective(u)

            res = optimize.minimize_scalar(
                along, bounds=(-CTE_PRIOR_BOUND, CTE_PRIOR_BOUND), method="bounded", options={"xatol": 1e-3}
            )
            u[j] = res.x
        elif free.size:

            def some(v):
                u[free] = v
                return objective(u)

            res = optimize.minimize(
                some, np.zeros(free.size), method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-4}
            )
            u[free] = np.clip(res.x, -CTE_PRIOR_BOUND, CTE_PRIOR_BOUND)
        # the description stands unless the training contradicts it: a likelihood-ratio test of
        # the described coefficients against the estimate at cte_test_p. On ram2 as published
        # the residual's small gains (0.8 % of its dx mean square, taken from another part of
        # the twin's error) moved the CFRP's coefficient by 0.3e-6 /K (D 0.3), and taken as the
        # map that took thermal_b dx from 2.3 to 9.1 µm; a description off by 1e-6 /K is
        # contradicted (ram4 with handbook materials: D = 22; with sources, films and materials
        # all from a handbook D = 10.1, which a test at 1e-3, 10.8, let through to dx 17.1 µm
        # on 10.3 uncompensated)
        J0 = np.sum(R0**2, axis=0) + floor
        J1 = np.sum(residual(alpha0 + sd * u) ** 2, axis=0) + floor
        D_axis = n_eff * np.log(J0 / J1)
        D = float(np.sum(D_axis))
        threshold = float(chi2_ppf(1.0 - self.cte_test_p, max(free.size, 1)))
        # and only by more than a data sheet's tolerance: on the built-in twin, whose residual is
        # its instruments' white noise (n_eff ~1200), a shift of 0.16e-6 /K passed the test
        # alone (D = 39) and took 0.5 µm of dy from what a lost S4 is known to cost
        material = bool(np.any(np.abs(u) > CTE_TOLERANCE_SD))
        # and only where no axis contradicts the estimate in turn: a coefficient is one number
        # for every axis, so an estimate that fits one axis's training residual worse by as
        # much as the test asks of the description (its own deviance below -threshold) is not
        # a coefficient the training asks for, but another misfit the coefficient absorbs on
        # the other axes. ram2 described without its radiant source: D 7.5 from dx +9.8 and dz
        # +9.6 against dy -11.9 (its dy training RMS 0.13 -> 0.36 µm at the estimate);
        # thermal_b dx 30.56 µm on 30.6 uncompensated with the estimate's map in the consensus
        coherent = bool(np.all(D_axis >= -threshold))
        contradicted = bool(free.size) and threshold < D and material and coherent
        # Where it is contradicted, the map of the estimate joins the map's consensus members
        # (thermal.map_members): only what the description's and the estimate's maps both
        # answer is applied, and their disagreement widens the interval. Replacing the map by the
        # estimate's was tried: ram4 with handbook materials thermal_b dx 17.2 -> 4.5 µm, but
        # ram2 described without its radiant source (D 7.5 at 1e-2, estimate -1.0e-6 /K
        # against its 0.4e-6) 11.7 -> 47.7 µm on 30.6 uncompensated: another slip of the
        # description can pull the estimate the wrong way, and the test cannot tell which.
        tm.pop("cte_members", None)
        if contradicted:
            pe = population_at(tm, alpha0 + sd * u)
            tm["cte_members"] = [
                {key: np.asarray(pe[key]).tolist() for key in ("gram", "xty", "ttp_ms_um2")}
                # it speaks for the axes whose training residual it fits better; on the others
                # the training prefers the description (thermal.map_members). ram2 without S2
                # and S4: dz's deviance -2.4, and its member had taken thermal_b dz 4.6 -> 6.8 µm
                | {"axes": (D_axis > 0).tolist()}
            ]
        return {
            "parts": list(cte["parts"]),
            "described_per_K": alpha0.tolist(),
            "estimated_per_K": (alpha0 + sd * u).tolist(),
            "contradicted": contradicted,
            "deviance": D,
            "deviance_per_axis": D_axis.tolist(),
            "tolerance_per_K": (CTE_TOLERANCE_SD * sd).tolist(),
            "threshold": threshold,
            "prior_sd_per_K": sd.tolist(),
            "n_eff": n_eff.tolist(),
            "training_rms_described_um": np.sqrt(J0).tolist(),
            "training_rms_estimated_um": np.sqrt(J1).tolist(),
        }

    def _fit_load_interval(self, rows, campaigns):
        """Scale (3,) of the load terms of the interval (:meth:`PhysicalPredictor.load_variance`),
        per axis, from the loaded training campaigns with known forces: as the thermal part's
        (:meth:`_fit_interval`), the smallest scale under which the 95 % interval covers the
        conformal share of their loaded samples (the weighted 95th percentile, with the
        finite-sample correction for the effective number of independent errors, at most the
        97.5th), within [1e-3, 1e3]; 1 on an axis no load moved or without such a campaign.
        Then the force components (3,) bool those campaigns applied beyond
        :data:`UNREAD_FORCE_N`: the scale speaks for their terms only. A component the training
        never applied keeps its prior (1): on a steel ram trained under Fy alone (our twin), dx's
        scale came out 1e-3 from the few tenths of a µm Fy moves it, and under Fx the interval
        was +-0.3 µm around errors of up to 2 µm on the plateaus (0.56 covered).

        The load terms are priors: a frame's force noise at the training's thermal extreme and
        a 3 % signature error. A load held is read as the mean of many frames, and ram2's
        signature, read on its static campaign, is right to 0.05 % of a plateau, so on static_x
        they made an interval of +-18.7 µm of dx at 2 kN around errors of 0.3 µm: the band was
        met only by the samples on load ramps."""
        z2 = norm_ppf(0.975) ** 2
        need, w, n_eff = [[], [], []], [[], [], []], np.zeros(3)
        trained = np.zeros(3, bool)
        for r, c in zip(rows, campaigns):
            if not r["loaded"] or r["forces_unknown"]:
                continue
            trained |= (np.abs(r["F"]) > UNREAD_FORCE_N).any(axis=0)
            pred, half, p, at = self._served(c)
            force, moving, s2 = p.last_force_N[at], p.last_moving[at], p.last_s2[at]
            _, ld = p.load_variance(force, moving, s2)
            rest = (half**2) / z2 - p.load_variance(force, moving, s2, scaled=True)[1]
            e2 = (pred - r["y"]) ** 2
            # a force the gratings cannot read (a nuisance: Fz on ram2) moves the TTP unseen;
            # the load terms are not what it is, so its samples do not scale them
            unread = (
                (np.abs(r["F"][:, ~p.active]) > UNREAD_FORCE_N).any(axis=1)
                if p.has_load
                else np.zeros(len(e2), bool)
            )
            for j in range(3):
                on = (ld[:, j] > 0) & ~unread
                if on.sum() < 2:
                    continue
                need[j].append(
                    np.where(e2[on, j] / z2 <= rest[on, j], 0.0, (e2[on, j] / z2 - rest[on, j]) / ld[on, j])
                )
                w[j].append(np.full(int(on.sum()), 1.0 / on.sum()))
                n_eff[j] += effective_samples(pred[on, j] - r["y"][on, j])
        scale = np.ones(3)
        for j in range(3):
            if not need[j]:
                continue
            nj, wj = np.concatenate(need[j]), np.concatenate(w[j])
            level = min(np.ceil((n_eff[j] + 1.0) * 0.95) / max(n_eff[j], 1.0), 0.975)
            order = np.argsort(nj)
            at = np.searchsorted(np.cumsum(wj[order]) / wj.sum(), level - 1e-12)
            # the priors are the widest the load terms get: a scale above 1 would be the
            # training's in-sample errors speaking for loads it never held
            scale[j] = np.clip(nj[order][min(at, len(order) - 1)], 1e-3, 1.0)
        return scale, trained

    def _noise_floor(self, campaigns, duration_s=NOISE_FLOOR_S):
        """SD (3,) µm of the thermal part (twin map and housing calibration, unclipped), SD (3,)
        of its measured heat inputs' part alone, and the universal threshold (3,) in SDs of that
        noise over ``duration_s``: what the instruments' white noise alone
        makes, nothing moving, with the zero state's own error: each probe at its own noise
        (:func:`probe_noise_sd_K`) on its own sampling interval, held on the frame clock as a live
        feed is, each grating at its frame noise, ``duration_s`` of frames past the housing's
        rest window (seeded: the same model file for the same data).

        The twin population's noise (``noise_gram``) knows the map alone. The housing
        calibration's leads amplify a quantised probe's scatter as well, and by the most where
        the map leaves the housing transient to them: on ram2 described with its bearing heat
        centred in the housing, the calibration's 300 s lead took 18.7 µm/K of dz against 11.5,
        the map's noise estimate fell from 0.61 to 0.29 µm, and 1.7 µm of probe noise passed
        the policy onto static_x's dz, which moves 0.2 µm (harm)."""
        rng = np.random.default_rng(0)
        # on the interrogator's own clock in thermal operation: the load-free training
        # campaigns' frame interval (the reference's, 15.5 s on ram2, made each grating's noise
        # pass the 60 s low-pass at 4x its SD and its zero look like one frame's)
        frames = [
            float(np.median(np.diff(c.fbg["time_s"].to_numpy(dtype=float))))
            for c in campaigns
            if c.meta.kind != "static" and len(c.fbg) > 1
        ]
        dt = max(frames) if frames else float(self.nominal_dt_s_)
        t = np.arange(0.0, HOUSING_REST_S + duration_s, dt)
        P, S = len(self.probe_names_), len(self.sensors_)
        sd = probe_noise_sd_K(campaigns, self.probe_names_)
        every = np.full(P, dt)
        for c in campaigns:
            for names, (tt, _v) in c.thermometers().items():
                if len(tt) > 1:
                    for name in names:
                        if name in self.probe_names_:
                            every[self.probe_names_.index(name)] = float(np.median(np.diff(tt)))
        temps = np.zeros((t.size, P))
        for j in range(P):
            held = np.floor(t / max(every[j], dt)).astype(int)
            temps[:, j] = rng.normal(0.0, sd[j], held.max() + 1)[held]
        # the measured heat inputs at their own white noise (from successive differences,
        # the largest any campaign shows) on their own sampling interval
        H = len(self.heat_inputs_)
        heat = np.zeros((t.size, H))
        for j, h in enumerate(self.heat_inputs_):
            sd_h, every_h = 0.0, dt
            for c in campaigns:
                if h in c.heat_names:
                    ht, hv = c.heat_inputs()
                    if len(ht) > 11:
                        sd_h = max(sd_h, float(diff_noise_sd(hv[:, c.heat_names.index(h)])))
                        every_h = float(np.median(np.diff(ht)))
            held = np.floor(t / max(every_h, dt)).astype(int)
            heat[:, j] = rng.normal(0.0, sd_h, held.max() + 1)[held]
        temps = np.hstack([temps, heat])
        lam0 = np.array([s.lambda0_nm for s in self.sensors_])
        el_sd = (
            np.sqrt(np.asarray(self.load_["noise_var_um2"], float)) if self.load_ is not None else np.zeros(S)
        )
        el = rng.normal(0.0, 1.0, (t.size, S)) * el_sd
        wl = grating_wavelengths_nm(self.sensors_, el)
        p = PhysicalPredictor(self)
        out, _ = p.predict(wl, temps, lam0, np.zeros(P + H), time_s=t, thermal_policy=False)
        thermal = out - p.last_force_N @ p.C.T if p.has_load else out
        past = t > HOUSING_REST_S
        cal = self.twin_map_["calibration"]
        k0 = calibration_probe_columns(cal)
        heat_part = p.last_cal_features[past, k0:] @ np.asarray(cal["coef"], float)[k0:]
        # The zero state is a mean of each signal's first zero_window_s on its own clock, off by
        # its noise over the samples there (one or two of a probe read every 10 s): a constant
        # for the whole run, which the map's level terms turn into a constant correction (the
        # housing's and the ambient's calibrated terms start from their own rest levels, and a
        # lead of a constant is 0)
        window = float(self.zero_window_s)
        coef = np.asarray(self.twin_map_["coef"], float)
        zero_sd = np.concatenate(
            [
                el_sd / np.sqrt(np.floor(window / dt) + 1.0),
                sd / np.sqrt(np.floor(window / np.maximum(every, dt)) + 1.0),
            ]
        )
        offset2 = ((coef[: S + P] * zero_sd[:, None]) ** 2).sum(axis=0)
        jitter2 = np.mean(thermal[past] ** 2, axis=0)
        # the universal threshold (Donoho & Johnstone) of a day of frames: the largest excursion
        # the noise alone is expected to reach over as many independent samples as it holds
        n_eff = np.array([effective_samples(thermal[past, j]) for j in range(3)])
        k = np.maximum(np.sqrt(2.0 * np.log(np.maximum(n_eff, 2.0))), float(self.load_k_sigma))
        return np.sqrt(jitter2 + offset2), np.sqrt(np.mean(heat_part**2, axis=0)), k, np.sqrt(offset2)

    def _calibrate_housing(self, rows, campaigns):
        """Least squares (no intercept, campaigns weighted equally) of the twin map's error on
        the measured load-free campaigns against the housing's mean ΔT (K), its leads at
        ``CAL_LEADS_S`` (K) and, with an ambient probe, the ambient's mean ΔT low-passed over
        ``CAL_AMBIENT_TAU_S`` (K): the uniform warming, which a training campaign's day cycle
        excites and a description can get wrong (ram2 with both rails described as locating:
        thermal_b dx 10.85 µm, 5.01 with the term).

        How late the housing probe sees the bearings' heat depends on where the bearings and
        the probe sit in the steel, which a data sheet rarely gives to the millimetre; every
        spindle duty cycle excites it, so the measured campaigns can teach it. The face-gradient
        coefficients stay the twin's (no campaign without a gradient can teach them)."""
        amb = {"ambient_tau_s": CAL_AMBIENT_TAU_S} if self.ambient_probes_ else {}
        heat = {"heat_taus_s": list(HEAT_TAUS_S)} if self.heat_inputs_ else {}
        k = 1 + len(CAL_LEADS_S) + len(amb) + len(HEAT_TAUS_S) * len(self.heat_inputs_)
        # the map as it stands, with the leads computed alongside (zero coefficients)
        self.twin_map_["calibration"] = {
            "leads_s": list(CAL_LEADS_S),
            **amb,
            **heat,
            "coef": np.zeros((k, 3)).tolist(),
            "envelope_low": [-1e9] * k,
            "envelope_high": [1e9] * k,
        }
        self._predictors = {}
        A_rows, b_rows, feats, map_rows = [], [], [], []
        for r, c in zip(rows, campaigns):
            if not r["thermal"]:
                continue
            pred, _, p, at = self._served(c, policy=False)
            L = _free(r, p.last_cal_features[at])
            w = np.sqrt(1.0 / len(L))
            A_rows.append(L * w)
            b_rows.append(_free(r, r["y"] - pred) * w)
            feats.append(L)
            map_rows.append((_free(r, p.last_map_features[at]) * w, _free(r, r["y"]) * w))
        self._map_rows = map_rows
        # kept for the interval's held-out errors (:meth:`_held_out_served`)
        self._cal_rows = (A_rows, b_rows)
        A, b = np.vstack(A_rows), np.vstack(b_rows)
        coef = np.linalg.lstsq(A, b, rcond=None)[0]
        L = np.vstack(feats)
        return {
            "leads_s": list(CAL_LEADS_S),
            **amb,
            **heat,
            "coef": coef.tolist(),
            "source": "measured load-free campaigns",
            "envelope_low": L.min(axis=0).tolist(),
            "envelope_high": L.max(axis=0).tolist(),
        }

    def _fit_interval(self, rows, campaigns, exclude=frozenset()):
        """Thermal part's error variance as v0 + vs s + v1 s² + v2 a² (+ vc for a model blind to
        the spindle housing), s² the squared probe
        excursion (:func:`excursion2`) and a the housing's fastest lead (a transient) over its
        training maximum, per axis; of the sensor set without ``exclude`` (a probe's fallback:
        that probe held at its zero, as from a loss at the start; with its training errors'
        RMS, ``resid_sd_um``).

        v0 is the reference instrument's own noise, measured on the training campaigns (robust
        SD of successive differences, the quietest campaign): a machine at rest and zeroed has
        no thermal error, so its interval is the interferometer's. vs, v1 and v2 come from
        non-negative least squares of the applied prediction's squared error beyond v0 on each
        load-free training campaign (campaigns weighted equally): what grows with the thermal
        state and its transients. With a housing calibration, that error is 1/3 in-sample and 2/3
        of each half of the campaign predicted by a calibration fitted without it
        (:meth:`_held_out_served`): what a fit on all of the data errs by on data it did not see."""
        dTs = [_free(r, r["dT"]) for r in rows if r["thermal"]]
        z2 = norm_ppf(0.975) ** 2
        scale = np.maximum(np.abs(np.vstack(dTs)).max(axis=0), 0.5)
        sd_ref = []
        for r in rows:
            if len(r["y"]) > 11:
                sd_ref.append(diff_noise_sd(r["y"]))
        v0 = np.min(sd_ref, axis=0) ** 2 if sd_ref else np.zeros(3)
        # dT is a reading minus the zero reading: a change within twice the SD of such a
        # difference of two readings (sqrt 2 x each probe's white noise) is none
        deadband = 2.0 * np.sqrt(2.0) * probe_noise_sd_K(campaigns, self.probe_names_)
        e2, S, act, w, n_eff, spread2 = [], [], [], [], [], []
        rho = float(self.unseen_relative_error)
        held_out = self._held_out_served(rows, campaigns, exclude)
        lost = [self.probe_names_.index(q) for q in exclude if q in self.probe_names_]
        for i, (r, c) in enumerate(zip(rows, campaigns)):
            if not r["thermal"]:
                continue
            pred, _, p, at = self._served(c, exclude)
            err2 = (pred - r["y"]) ** 2
            m = r["free"]
            if m is not None:  # a combined campaign: its load-free samples
                r = {**r, "y": r["y"][m], "dT": r["dT"][m]}
                pred, err2, at = pred[m], err2[m], at[m]
            if i in held_out:
                # what a model fitted on all of the data errs by on data it did not see: least
                # squares' in-sample errors are low by about p/n, those of a half predicted by a
                # fit without it high by about 2p/n, so 1/3 of the one and 2/3 of the other
                pred = held_out[i] if m is None else held_out[i][m]
                err2 = err2 / 3.0 + 2.0 * (pred - r["y"]) ** 2 / 3.0
            e2.append(err2)
            n_eff.append([effective_samples(pred[:, j] - r["y"][:, j]) for j in range(3)])
            dT = r["dT"].copy()
            dT[:, lost] = 0.0  # a lost probe's reading is held (PhysicalPredictor.predict)
            S.append(excursion2(dT, scale, deadband))
            act.append(p.last_activity[at])
            # the members' disagreement as a 95 % half-width; the unseen part's error and the
            # zero state's (at the share of the correction the threshold passes) as SDs
            spread2.append(
                p.last_spread[at] ** 2
                + z2 * ((rho * p.last_unseen[at]) ** 2 + (p.zero_sd_um * p.last_passed[at]) ** 2)
            )
            w.append(np.full(len(pred), 1.0 / len(pred)))  # campaigns weighted equally
        e2, s2, act, w = np.vstack(e2), np.concatenate(S), np.concatenate(act), np.concatenate(w)
        # the members' disagreement is a variance of its own (PhysicalPredictor._variance): what
        # is left for the state terms is the error beyond it and the instrument's noise
        base = v0[None, :] + np.vstack(spread2) / z2
        a_scale = max(float(np.abs(act).max()), 1e-3)
        # A model that sees nothing of the spindle housing (no probe in or on it, no measured
        # heat input) cannot tell a spindle start from rest: the TTP moves while no state it
        # reads does. Its interval carries a constant term; without it the few samples of each
        # start decided the state terms' scale alone (ram2 without T_flange: 1000x, a median
        # dz half-width of 400 µm on thermal_b around errors under 16 µm, and 0.80 coverage
        # on thermal_c all the same).
        from scipy.optimize import nnls  # noqa: PLC0415 - start-up: fit-time only

        blind = not self._sees_housing_without(exclude)
        A = np.column_stack([np.sqrt(s2), s2, (act / a_scale) ** 2, np.full_like(s2, float(blind))])
        sw = np.sqrt(w)[:, None]
        v = np.array(
            [nnls(A * sw, (e2[:, j] - base[:, j]) * sw[:, 0])[0] for j in range(3)]
        )  # (axes, [vs, v1, v2, vc])
        # The errors are not Gaussian (heavy tails from the transients): scale the state terms
        # so that the 95 % interval covers 95 % of the training samples (campaigns weighted
        # equally), v0 staying the instrument's. A sample is covered for every scale from
        # (e² / z² - v0) / (its state variance) up: the scale is the weighted 95th percentile of
        # that, within [1e-3, 1e3]. The percentile carries the split-conformal finite-sample
        # correction, ceil((n + 1) 0.95) / n, with n the training's *effective* number of
        # independent errors (:func:`effective_samples`): thermal errors stay correlated for
        # hours, so a 36 h campaign holds a few dozen of them, not 130 000, and the plain 95th
        # percentile covered 88 % on ram2's unseen thermal_b (dy).
        shape = A @ v.T  # (n, 3) state variance
        n_ind = np.sum(n_eff, axis=0)
        level = np.minimum(np.ceil((n_ind + 1.0) * 0.95) / np.maximum(n_ind, 1.0), 0.975)
        for j in range(3):
            if not np.any(shape[:, j] > 0):
                continue
            with np.errstate(divide="ignore", invalid="ignore"):
                need = np.where(e2[:, j] / z2 <= base[:, j], 0.0, (e2[:, j] / z2 - base[:, j]) / shape[:, j])
            order = np.argsort(need)
            # (a share of exactly 0.95 counts as reached: the cumulative sum's rounding must not
            # push the level to the next sample)
            at = np.searchsorted(np.cumsum(w[order]) / w.sum(), level[j] - 1e-12)
            v[j] *= np.clip(need[order][min(at, len(order) - 1)], 1e-3, 1e3)
        return {
            "v0_um2": v0.tolist(),
            "vs_um2": v[:, 0].tolist(),
            "v1_um2": v[:, 1].tolist(),
            "v2_um2": v[:, 2].tolist(),
            "vc_um2": v[:, 3].tolist(),
            "dT_scale_K": scale.tolist(),
            "deadband_K": deadband.tolist(),
            "activity_scale_K": a_scale,
        } | ({"resid_sd_um": np.sqrt(np.average(e2, axis=0, weights=w)).tolist()} if exclude else {})

    def _held_out_served(self, rows, campaigns, exclude=frozenset()) -> dict:
        """{row index: applied prediction (m, 3)} of each load-free training campaign, each
        half of it (in time) predicted by a housing calibration fitted without that half ({}
        without a housing calibration).

        The calibration is fitted on the very campaigns the interval is scaled on, and its
        in-sample errors understate what a new campaign shows. With measured heat inputs, whose
        low-passes add one coefficient per input and ``HEAT_TAUS_S`` entry: ram2, its bearings'
        heat read, thermal_a's dz RMS 0.17 µm in-sample against thermal_c's 0.38 held out,
        whose dz interval covered 0.89; ram3's thermal_c dy 0.68. Without them as well: on
        2026-12-06, scaled on in-sample errors alone, ram7's held-out dz covered 0.883 and 0.763,
        ram6's thermal_c dy and dz 0.887 and 0.851, ram4's thermal_b dx 0.843
        (:meth:`_fit_interval` takes 1/3 of the in-sample errors and 2/3 of these)."""
        cal = (self.twin_map_ or {}).get("calibration") or {}
        if getattr(self, "_cal_rows", None) is None or PhysicalPredictor(self, exclude).cal is None:
            return {}  # the set runs without the calibration (a housing or ambient probe lost)
        A_rows, b_rows = self._cal_rows
        keep = cal["coef"]
        free = [i for i, r in enumerate(rows) if r["thermal"]]
        out = {}
        try:
            for j, i in enumerate(free):
                # halves in time of the whole campaign; a combined campaign's calibration rows
                # are its load-free samples (``free``)
                m, n = rows[i]["free"], len(rows[i]["y"])
                pred = np.empty((n, 3))
                for half in (np.arange(n) < n // 2, np.arange(n) >= n // 2):
                    hm = half if m is None else half[m]
                    A = np.vstack([a if k != j else a[~hm] for k, a in enumerate(A_rows)])
                    b = np.vstack([v if k != j else v[~hm] for k, v in enumerate(b_rows)])
                    cal["coef"] = np.linalg.lstsq(A, b, rcond=None)[0].tolist()
                    self._predictors = {}
                    p_half, _, _, _ = self._served(campaigns[i], exclude)
                    pred[half] = p_half[half]
                out[i] = pred
        finally:
            cal["coef"] = keep
            self._predictors = {}
        return out

    def _frame_noise_var(self, campaigns, aligned, rows, fmap):
        """White noise of each grating's frame: its variance (µm²), the largest any training
        campaign shows, loaded or not, and the fastest frame interval of those campaigns (s).

        From successive differences of the interrogator's own frames (robust: MAD, so load
        steps and ramps do not count), the frames the runtime sees (:meth:`frame_arrays`), not
        the aligned ones: aligning a campaign onto its reference's clock interpolates between
        frames, which halves their noise (on the twin, 0.135 µm on static-y's aligned frames
        against 0.30 µm on its own), and the step test then took the thermal campaigns' noise
        for loads. The step test takes a frame slower than the fastest one as carrying this
        variance (an interrogator's sweep has its noise whatever the rate; the twin's frames at
        0.1 s and 1 s agree) and a faster one as the same density (variance x interval, the
        safe side for an interrogator that averages sweeps into its exported frames). InputError
        when no training campaign has 10 frames to read it from."""
        out = np.zeros(len(self.sensor_names))
        fastest = np.inf
        for c, a, r in zip(campaigns, aligned, rows):
            ft, w, t = self.frame_arrays(c, a)
            t = t[:, : len(self.probe_names_)]  # the probes (the heat inputs follow them)
            if ft.size < 10:
                continue
            out = np.maximum(out, diff_noise_sd(fmap.base(w, t, *r["zero"])) ** 2)
            fastest = min(fastest, float(np.median(np.diff(ft))))
        if not np.isfinite(fastest):
            # zero noise would make the step test take every frame's noise for a load
            first = campaigns[0]
            raise InputError(
                "the physical model reads each grating's noise from at least 10 interrogator "
                f"frames, and no training campaign has 10 ({len(campaigns)} given)",
                file=first.path / "fbg.csv" if first.path is not None else first.name,
            )
        return out, fastest

    def _calibrate_drift(self, rows):
        """How far heat (and noise) move the force reading the step test sees, on the load-free
        training campaigns: the 99th percentile of its magnitude with the tracker listening
        (no step taken), per component, stored as a rate over the offset's tracking time
        (``drift_N_per_s`` x max(``offset_tau_s``, frame interval) is the allowance; floor
        0.1 N/s). A step must stand ``load_k_sigma`` times clear of it. (Frame-to-frame rates,
        as before, measured the noise: 622 N/s on the twin, and no load was ever applied.)

        The step test judges the sensors' noise on its own (``k_start`` x the low-passed
        noise), so the gratings are listened to with their noise averaged out first: a centred
        moving mean over ``3 offset_tau_s`` (the tracker's memory), which leaves the lag of the
        tracker behind heat as it is. Listening to the raw frames counted the noise twice: on the
        twin (1 s frames, 56 N of Fy noise per frame) the allowance came out 277 N, of which
        heat was 30 N, and a 1000 N step stood 1.1 allowances clear: the first 0 -> 1000 N step
        was missed, the offset took it in, and the tracker stayed one level behind (+188 µm
        at 0 N)."""
        from scipy.ndimage import uniform_filter1d  # noqa: PLC0415 - start-up: fit-time only

        p = self.predictor()
        seen = [np.zeros((0, 3))]
        for r in rows:
            if r["loaded"] or len(r["t"]) < 3:
                continue
            dt = float(np.median(np.diff(r["t"])))
            width = max(1, round(3.0 * self.offset_tau_s / dt)) if dt > 0 else 1
            e = uniform_filter1d(r["e"][:, p._keep], size=min(width, len(r["t"])), axis=0, mode="nearest")
            F, _, _ = p._track_load(e, r["t"], None, {}, listen=True)
            seen.append(np.abs(F))
        seen = np.vstack(seen)
        q = np.quantile(seen, 0.99, axis=0) if len(seen) else np.full(3, 20.0)
        span = max(float(self.offset_tau_s), float(self.nominal_dt_s_))
        self.load_["drift_N_per_s"] = np.maximum(q / span, 0.1).tolist()
        self._predictors = {}

    def _check_described(self, machine, campaign):
        """InputError unless the machine description declares every grating and probe the model
        reads, by the campaign's names: the twin's load signature and thermal map are built for
        the description's names, and a data sheet's "FBG1" for the campaign's "S1" silently left
        the fit without either (ram2 thermal_b dx 30.3 µm on 30.6: no compensation at all)."""
        sensors = [s.name for s in machine.sensors]
        probes = [p.name for p in machine.probes] + [f"{n}_ref" for n in sensors]
        missing = [s.name for s in self.sensors_ if s.name not in sensors]
        field, have = "sensors", sensors
        if not missing:
            missing = [p for p in self.probe_names_ if p not in probes]
            field, have = "probes", [p.name for p in machine.probes]
        where = self.machine if not isinstance(self.machine, Machine) else "<machine>"
        if missing:
            raise InputError(
                f"the campaign {campaign.meta.name}'s {'gratings' if field == 'sensors' else 'probes'} "
                f"{', '.join(missing)} are not in the machine description (it has "
                f"{', '.join(have) or 'none'}); name them as the campaign files do",
                file=where,
                column=f"field {field}",
            )
        # where campaign.yaml also says where a grating is bonded, it must be where the
        # description puts it: the twin's signature of a grating on the wrong face is another
        # grating's
        for spec in self.sensors_:
            i = sensors.index(spec.name)
            ms = machine.sensors[i]
            for key, said, here in (
                ("face", spec.face, ms.face),
                ("z_start_mm", spec.z_start_mm, ms.z_start_mm),
                ("z_end_mm", spec.z_end_mm, ms.z_end_mm),
                ("depth_mm", spec.depth_mm, ms.depth_mm),
                ("gauge_length_mm", spec.gauge_length_mm, ms.gauge_length),
            ):
                if said is None:
                    continue
                if key == "face":
                    if said == here:
                        continue
                    what = f"is on face {here} here but on {said}"
                elif abs(said - here) <= 1.0:
                    continue
                else:
                    what = f"has {key} {here:g} here but {said:g}"
                raise InputError(
                    f"grating {spec.name} {what} in the campaign {campaign.meta.name}'s "
                    "campaign.yaml; describe the grating where it is bonded",
                    file=where,
                    column=f"field sensors[{i}].{key}",
                )

    def _observer(self, machine, campaigns, twin):
        """The thermal observer of the campaigns' gratings and thermometers on the twin the map
        learned from (:class:`~fbgcomp.models.physical.observer.ThermalObserver`), as the model
        file holds it; its measurements are the point probes and strain-free reference gratings
        the description places, its known input the ambient probes' mean. ``twin``: the twin
        of :func:`generic_heat_machine` of ``machine``."""
        refs = {f"{s.name}_ref" for s in machine.sensors}
        # the measured heat inputs (heat.csv) of the twin's own volume sources are measurements
        # of those inputs' states: the spindle's power read, its heat need not be inferred
        sources = {h.name: h.input_name for h in twin.machine.thermal.sources if h.kind == "volume"}
        measured = [h for h in self.heat_inputs_ if h in sources]
        obs, probes = self._thermal_observer(machine, campaigns, twin, refs, [sources[h] for h in measured])
        return obs.to_dict() | {"probes": probes, "ambient": list(self.ambient_probes_), "measured": measured}

    def _thermal_observer(self, machine, campaigns, twin, references=frozenset(), measured_inputs=()):
        """(:class:`ThermalObserver`, its thermometers) on ``twin``, the one the map learns from
        (of :func:`generic_heat_machine`): the campaigns' point probes the description places,
        and those of ``references`` (strain-free reference gratings, ``<sensor>_ref``) the
        campaigns carry; ``measured_inputs``: the twin's input channels (``<source>_W``) whose heat
        the campaigns read (heat.csv)."""
        point = set(machine.point_probe_names)
        probes = [q for q in self.probe_names_ if q in point or q in references]
        # each probe's zero is its readings' mean over the zero window: off by about one
        # reading's noise, which the filter estimates as a constant
        bias = probe_noise_sd_K(campaigns, self.probe_names_)[[self.probe_names_.index(q) for q in probes]]
        obs = ThermalObserver(twin, self.sensors_, probes, probe_bias_K=bias, measured_inputs=measured_inputs)
        return obs, probes

    def _heat_prior(self, machine, campaigns, rows, twin) -> dict:
        """{volume source: W} the twin's scenarios run each volume heat source at, from the load-free
        training campaigns: the mean heat the thermal observer infers there over the scenarios'
        mean duty level (``ScenarioDesign.mean_duty_fraction``), within 1/4-4x the declared
        nominal. A source whose inferred mean is under a tenth of its declared duty mean (idle in
        training), a source in the housing when no probe of the campaigns is in or on the
        housing, and every source when no load-free campaign or no point probe is there, keeps
        its declared nominal (``benchmarks/bench_heat_prior.py``: ram2 74.0 W inferred against
        70.6, ram3 80.1 against 80.1; without its housing probe ram2's estimate is 20.8 W, the
        bearings' heat taken for the other inputs', and neither the inputs' separability nor
        the filter's innovations tell that case apart: docs/accuracy.md)."""
        in_housing = set(machine.housing_probe_names()) & set(self.probe_names_)
        volume = [
            h for h in machine.thermal.sources if h.kind == "volume" and (in_housing or not h.in_housing)
        ]
        point = set(machine.point_probe_names)
        free = [c for c, r in zip(campaigns, rows, strict=True) if not r["loaded"]]
        if not volume or not any(q in point for q in self.probe_names_) or not free:
            return {}
        from fbgcomp.structure.cache import array_digest, cached_json  # noqa: PLC0415 - with the twin

        obs, probes = self._thermal_observer(machine, campaigns, twin)
        # the filter's run is kept in the twin cache under the observer's and the data's identity:
        # a second fit on the same campaigns reads it (ram2 thermal_a: 12 960 Kalman steps, ~3 s)
        ident = {
            "twin": twin.cache_key,
            "sensors": [s.model_dump(mode="json") for s in self.sensors_],
            "probes": probes,
            "probe_bias_K": np.asarray(obs.probe_bias_K, float).tolist(),
        }
        total, steps = np.zeros(obs.n_heat), 0
        for c in free:
            _, amb, pr, gr = campaign_inputs(
                c, self.sensors_, probes, list(self.ambient_probes_), obs.step_s, zero_s=60.0
            )
            if len(amb) == 0:
                continue
            run = cached_json(
                "observer-heat-sum",
                {**ident, "inputs": array_digest(amb, pr, gr)},
                lambda a=amb, p=pr, g=gr: {"sum": obs.run(a, p, g).heat.sum(axis=0), "steps": len(a)},
            )
            total += run["sum"]
            steps += run["steps"]
        if steps == 0:
            return {}
        mean_level = ScenarioDesign().mean_duty_fraction
        prior = {}
        for h in volume:
            declared = h.nominal_W or 100.0
            inferred = total[list(obs.input_names).index(h.input_name)] / steps
            if inferred >= 0.1 * mean_level * declared:
                prior[h.name] = float(np.clip(inferred / mean_level, declared / 4, 4 * declared))
        return prior

    def _twin_signature(self, machine):
        """(G, C) from the FE twin, or None without a machine description (``fit`` has checked
        that the description names every grating: :meth:`_check_described`)."""
        if machine is None:
            return None
        names = [s.name for s in machine.sensors]
        from fbgcomp.structure import Twin  # noqa: PLC0415 - optional extra: scikit-fem (the FE twin)

        twin = Twin(machine)
        inf = twin.influence
        idx = [names.index(s) for s in self.sensor_names]
        return np.asarray(inf.sensor_per_force_um_per_N)[idx], np.asarray(inf.ttp_per_force_um_per_N)

    # -- prediction --------------------------------------------------------------------------
    @property
    def fallback_sets(self) -> list:
        """Every sensor set without one or more gratings (the load part needs none of them),
        then, on a model with a twin map, the full set and each set without one or two
        gratings, without one probe as well (a probe lost at runtime: the map without its
        columns; not with the thermal observer, whose states are the probes' own), and each set
        without one grating at most, without two probes (a lost input module, or a fibre past
        two reference gratings). A fibre break takes a reference grating with its sensor and the
        gratings past it: ram2's default stores 193 sets (151 without the pairs, 91 with one
        grating per fibre break) and loads in 0.52 s (0.25, 0.11)."""
        names = self.sensor_names
        out = []
        for k in range(1, len(names) + 1):
            out += [frozenset(c) for c in combinations(names, k)]
        if getattr(self, "twin_map_", None) is not None and getattr(self, "observer_", None) is None:
            singles = [frozenset(), *out[: len(names)]]
            pairs = [frozenset(c) for c in combinations(self.probe_names_, 2)]
            out += [s | {q} for q in self.probe_names_ for s in [frozenset(), *out] if len(s) <= 2]
            out += [s | pair for pair in pairs for s in singles]
        return out

    def predictor(self, exclude=frozenset()) -> PhysicalPredictor:
        """The predictor of the sensor set without ``exclude`` (one per set, kept)."""
        exclude = frozenset(exclude)
        if exclude not in self._predictors:
            self._predictors[exclude] = PhysicalPredictor(self, exclude)
        return self._predictors[exclude]

    def predict_interval(self, X, exclude=frozenset(), raw=False, policy=True):
        """Deviation (n, 3) µm and 95 % half-width on a campaign's reference clock, as the runtime
        would publish them (``raw``: without the policy; ``policy=False``: thermal part unclipped);
        the policy flags of each sample in ``last_flags_``."""
        (campaign,) = as_campaign_list(X)
        check_compatible(self, campaign)
        mean, half, p, at = self._served(campaign, exclude, raw, policy)
        self.last_flags_ = p.last_flags[at]
        return mean, half

    def _served(self, campaign, exclude=frozenset(), raw=False, policy=True):
        """Deviation and half-width at each reference time as the runtime publishes them (the
        last frame's output, carried forward: the reference clock is offset from the
        interrogator's, e.g. +0.3 s), the predictor that ran, and the frame index of each
        reference time."""
        memo = self._served_memo  # a fit's (fit)
        key = (id(campaign), self.zero_window_s, tuple(self.sensor_names), tuple(self.probe_names))
        if memo is not None and key in memo["frames"]:
            _, aligned, w0, t0, frame_t, w, t = memo["frames"][key]
        else:
            aligned = campaign.aligned(zero_window_s=self.zero_window_s)
            _, _, w0, t0 = self.instrument_arrays(aligned)
            frame_t, w, t = self.frame_arrays(campaign, aligned)
            t0 = np.concatenate([t0, self._heat_zero_W(campaign)])
            if memo is not None:  # (the campaign kept with them: its id is not reused)
                for a in (w0, t0, frame_t, w, t):
                    a.flags.writeable = False  # shared by every call: none may change them
                memo["frames"][key] = (campaign, aligned, w0, t0, frame_t, w, t)
        p = PhysicalPredictor(self, exclude)  # fresh filter state per campaign
        p.load_memo = None if memo is None else memo["load"]
        # BLAS on one thread: the products here are (frames x ~12) by (~12 x 15), too thin for
        # threads to pay. ram2's default fit (22 campaigns' worth of frames) spent 12.2 CPU-s
        # with them threaded against 7.4 on one thread, in the same wall time and to the same
        # model (benchmarks/bench_fit_threads.py)
        with one_blas_thread():
            mean, half = p.predict(
                w,
                t,
                w0,
                t0,
                time_s=frame_t,
                z_axis_mm=campaign_z_axis_mm(campaign),
                raw=raw,
                thermal_policy=policy,
            )
        at = np.clip(np.searchsorted(frame_t, aligned.time_s, side="right") - 1, 0, frame_t.size - 1)
        return mean[at], half[at], p, at

    def frame_arrays(self, campaign, aligned):
        """The campaign as the runtime sees it: every interrogator frame inside the aligned
        overlap, with each probe's last reading at that frame (held, as a live feed is).

        Returns frame times (s), wavelengths (n, sensors) nm and temperatures (n, probes) degC
        in the model's order, then its measured heat inputs (W, :meth:`_heat_frames`). The load
        tracker runs on this clock (its filters are set in
        seconds), so validation sees the correction the runtime would publish, not one computed
        from gratings averaged over each reference interval.
        """
        ft, w, temps = campaign.frames(aligned, self.sensor_names, self.probe_names_)
        return ft, w, np.hstack([temps, self._heat_frames(campaign, ft)])

    # -- measured heat inputs (heat.csv) -----------------------------------------------------
    @property
    def probe_names(self) -> list:
        """The slow inputs the model reads, in its order: its probes (°C), then its measured
        heat inputs as ``<source>_W`` (W); the runtime feeds them as it feeds probes."""
        return list(self.probe_names_) + self.heat_channels

    @property
    def _sees_housing(self) -> bool:
        """Whether an instrument reads the spindle housing's heat: a probe in or on the housing,
        or a measured heat input (what the housing calibration needs, and what a spindle start
        shows in)."""
        return self._sees_housing_without()

    def unread_forces(self, loads_N=None) -> dict:
        """The force components the gratings cannot read on this machine (their signature is
        the gratings' own warming pattern, ``load_["not_separable"]``: Fz on a CFRP ram), each
        with the largest |force| N of ``loads_N`` (n, 3) (only those it applies beyond
        :data:`UNREAD_FORCE_N`; without it: the training's largest) and the TTP µm per axis that
        force moves through the load signature. Neither the correction nor its interval holds
        that displacement: the model cannot see the force. {} when every component is read, or
        the model has no load part."""
        L = self.load_
        if L is None or not L.get("not_separable"):
            return {}
        C = np.abs(np.asarray(L["C_um_per_N"], float))
        out = {}
        for f in L["not_separable"]:
            j = FORCE_AXES.index(f)
            if loads_N is None:
                big = float(L["max_force_N"][j])
            else:
                big = float(np.nanmax(np.abs(np.asarray(loads_N, float)[:, j]), initial=0.0))
                if big <= UNREAD_FORCE_N:
                    continue
            out[f] = {"max_abs_N": big, "ttp_um": dict(zip(AXES, (C[:, j] * big).tolist()))}
        return out

    def _sees_housing_without(self, exclude=frozenset()) -> bool:
        """:attr:`_sees_housing` of the sensor set without the probes of ``exclude``."""
        return bool(set(self.housing_probes_) - set(exclude) or self.heat_inputs_)

    @property
    def heat_channels(self) -> list[str]:
        """The runtime's names of the measured heat inputs (``<source>_W``, W), in model order."""
        return [f"{h}{HEAT_SUFFIX}" for h in getattr(self, "heat_inputs_", [])]

    def _heat_input_names(self, campaigns, machine) -> list:
        """The heat inputs every thermal or combined training campaign carries (heat.csv), in
        the first one's order; [] when one carries none, or ``heat_inputs`` is off. A static
        campaign is one at rest: the spindle stopped, with or without heat.csv."""
        moving = [c for c in campaigns if c.meta.kind != "static"]
        if not self.heat_inputs or not moving:
            return []
        names = [h for h in moving[0].heat_names if all(h in c.heat_names for c in moving[1:])]
        clash = [q for q in self.probe_names_ if q.endswith(HEAT_SUFFIX)]
        if names and clash:
            c = moving[0]
            raise InputError(
                f"probe {clash[0]} ends in {HEAT_SUFFIX}, the runtime's mark of a heat input; rename "
                "the probe or fit with heat_inputs off",
                file=(c.path / "temperatures.csv") if c.path is not None else c.name,
                column=f"{clash[0]}_C",
            )
        unknown = [
            h for h in names if machine is not None and h not in {src.name for src in machine.thermal.sources}
        ]
        if unknown:
            log.warning(
                "heat.csv input(s) %s name no heat source of the machine description; taken as measured "
                "inputs all the same",
                ", ".join(unknown),
            )
        return names

    def _heat_table(self, campaign):
        """The model's heat inputs in ``campaign``: ``(time_s (n,), values (n, H) W)`` on
        heat.csv's clock in model order, or None for a static campaign without them (at rest);
        InputError for any other campaign that lacks one."""
        missing = [h for h in self.heat_inputs_ if h not in campaign.heat_names]
        if missing and (campaign.heat is not None or campaign.meta.kind != "static"):
            where = campaign.path / HEAT_FILE if campaign.path is not None else campaign.name
            raise InputError(
                f"the model was fitted with the measured heat input {missing[0]} and the campaign "
                f"does not carry it (a {campaign.meta.kind} campaign must, as a column "
                f"{missing[0]}{HEAT_SUFFIX} of {HEAT_FILE})",
                file=where,
                column=f"{missing[0]}{HEAT_SUFFIX}",
            )
        if missing or not self.heat_inputs_:
            return None
        ht, hv = campaign.heat_inputs()
        return ht, hv[:, [campaign.heat_names.index(h) for h in self.heat_inputs_]]

    def _heat_frames(self, campaign, frame_t) -> np.ndarray:
        """The model's heat inputs (W) at each frame, each its last reading (held, as a live
        feed is); zeros for a static campaign without heat.csv (at rest)."""
        table = self._heat_table(campaign)
        if table is None:
            return np.zeros((np.size(frame_t), len(self.heat_inputs_)))
        ht, hv = table
        return hv[np.clip(np.searchsorted(ht, frame_t, side="right") - 1, 0, ht.size - 1)]

    def _heat_zero_W(self, campaign) -> np.ndarray:
        """The heat inputs' zero state (W): their mean over the zero window, as the probes'."""
        table = self._heat_table(campaign)
        if table is None:
            return np.zeros(len(self.heat_inputs_))
        ht, hv = table
        return zero_state(ht, hv, self.zero_window_s)

    # -- reporting and persistence -----------------------------------------------------------
    def summary(self) -> str:
        """The thermal part's coefficients or twin map, its validated range and the load signature."""
        names = (
            ["const"]
            + [f"dT_{p}" for p in self.housing_probes_]
            + [f"dT_{p}" for p in self.ambient_probes_]
            + ([f"lead{self.lead_tau_s:g}s_housing"] if self.housing_probes_ else [])
        )
        out = [
            f"physical model (default): load signature + housing thermal, do-no-harm policy; "
            f"{self.training_['n_samples']} samples from "
            f"{', '.join(c['name'] for c in self.training_['campaigns'])}",
            f"housing probes: {', '.join(self.housing_probes_) or 'none'}; ambient: "
            f"{', '.join(self.ambient_probes_) or 'none'}",
        ]
        tz = getattr(self, "trained_z_axis_mm_", None)
        if tz:
            out.append(
                f"trained at Z = {', '.join(f'{z:g}' for z in tz)} mm: dx and dy are held back at a Z "
                f"more than {self.z_tolerance_mm:g} mm from it"
                + (" (the load part is those positions' compromise)" if len(tz) > 1 else "")
            )
        out += [
            f"{c['name']}: static or combined without loads.csv, so its forces are unknown: "
            "kept out of the thermal calibration and the force regression"
            for c in self.training_["campaigns"]
            if c.get("forces_unknown")
        ]
        out += [
            f"{c['name']}: combined, its thermal training the {c['thermal_samples']} of its "
            f"{c['n_samples']} samples at least {THERMAL_LOAD_MARGIN_S:g} s from any applied force"
            for c in self.training_["campaigns"]
            if c.get("thermal_samples")
        ]
        out.append("")
        tm = self.twin_map_
        if tm is None:
            out += [
                "thermal part (µm per K; lead in µm per K of T - lowpass(T))",
                f"{'term':<22}" + "".join(f"{a:>11}" for a in AXES),
            ]
            for name, row in zip(names, np.asarray(self.thermal_coef_)):
                out.append(f"{name:<22}" + "".join(f"{v:>11.4g}" for v in row))
        else:
            out.append(
                f"thermal part: ridge map learned on {tm['n_scenarios']} thermal scenarios of the "
                f"machine's FE twin ({len(tm['features'])} features: {', '.join(tm['features'])})"
            )
            prior = tm.get("heat_prior_W") or {}
            out.append(
                "scenarios' volume heat sources at "
                + (
                    ", ".join(f"{k} {v:.1f} W" for k, v in prior.items())
                    + " nominal (the thermal observer's mean on the load-free training campaigns over "
                    + f"the scenarios' mean duty level, {ScenarioDesign().mean_duty_fraction:.2f})"
                    if prior
                    else "their declared nominal power"
                )
            )
            cal = tm.get("calibration")
            if cal is not None:
                out += [
                    f"housing transient calibrated on the {cal.get('source', 'measured campaigns')} "
                    "(µm per K"
                    + (
                        f"; measured heat inputs {', '.join(self.heat_inputs_)} low-passed, µm per W)"
                        if cal.get("heat_taus_s")
                        else ")"
                    ),
                    f"{'term':<22}" + "".join(f"{a:>11}" for a in AXES),
                ]
                names = ["dT_housing"] + [f"lead{t:g}s_housing" for t in cal["leads_s"]]
                if "ambient_tau_s" in cal:
                    names.append(f"ambient{cal['ambient_tau_s']:g}s")
                names += [f"{h}_lp{t:g}s" for t in cal.get("heat_taus_s") or () for h in self.heat_inputs_]
                for name, row in zip(names, np.asarray(cal["coef"]), strict=True):
                    out.append(f"{name:<22}" + "".join(f"{v:>11.4g}" for v in row))
            cte = tm.get("cte")
            if cte is not None:
                free = [i for i, v in enumerate(cte["prior_sd_per_K"]) if v > 0]
                said = ", ".join(
                    f"{cte['parts'][i]} {cte['described_per_K'][i]:.3g} described, "
                    f"{cte['estimated_per_K'][i]:.3g} estimated"
                    for i in free
                )
                per_axis = cte.get("deviance_per_axis")
                against = [a for a, v in zip(AXES, per_axis or []) if v < -cte["threshold"]]
                speaks = [a for a, v in zip(AXES, per_axis or []) if v > 0]
                if cte["contradicted"]:
                    verdict = "contradicted: the estimate's map joins the consensus"
                    if per_axis and len(speaks) < len(AXES):
                        verdict += " on " + ", ".join(speaks)
                elif against and cte["deviance"] > cte["threshold"]:
                    verdict = f"not contradicted: {', '.join(against)} contradicts the estimate in turn"
                else:
                    verdict = "not contradicted"
                each = (
                    " (" + ", ".join(f"{a} {v:.3g}" for a, v in zip(AXES, per_axis)) + ")" if per_axis else ""
                )
                out.append(
                    f"expansion coefficients (1/K) tested on the training: {said}; "
                    f"deviance {cte['deviance']:.3g}{each} against {cte['threshold']:.3g}, {verdict}"
                )
            basis = np.asarray(tm.get("unseen_basis", []), float)
            if basis.ndim == 2 and basis.shape[1]:
                out.append(
                    f"unseen by the training: {basis.shape[1]} of {basis.shape[0]} feature directions; "
                    f"the correction made from them enters the interval at "
                    f"{100 * float(self.unseen_relative_error):g} % of itself (1 SD)"
                )
            zero = (cal or {}).get("zero_sd_um")
            if zero is not None:
                out.append(
                    "the zero state's error (each probe and grating zeroed on the zero window's samples) "
                    "enters the interval once the correction passes the noise threshold: "
                    + ", ".join(f"{a} {v:.3g}" for a, v in zip(AXES, zero))
                    + " µm (1 SD)"
                )
            if float(self.thermal_relative_error):
                out.append(
                    f"the whole thermal correction enters the interval at "
                    f"{100 * float(self.thermal_relative_error):g} % of itself (1 SD)"
                )
            ob = getattr(self, "observer_", None)
            if ob is not None:
                out.append(
                    f"thermal observer (--observer): Kalman filter on {len(ob['lam_per_s'])} thermal modes of "
                    f"the twin, heat inputs {', '.join(ob['input_names'])}; measured by "
                    f"{', '.join(ob['probes']) or 'no probe'} and the gratings; averaged with the map "
                    "while every heat estimate stays within 3x its nominal value"
                )
        out.append(f"{'residual SD µm':<22}" + "".join(f"{v:>11.3g}" for v in self.thermal_resid_sd_um_))
        lo, hi = self.thermal_range_um_
        out.append(
            f"{'validated range µm':<22}"
            + ", ".join(f"{ax} {a:.3g}..{b:.3g}" for ax, a, b in zip(AXES, lo, hi))
        )
        if self.load_ is None:
            out.append("\nload part: none (no training campaign with loads and no machine description)")
        else:
            L = self.load_
            out.append(
                f"\nload part ({L['source']}); forces estimated: "
                + ", ".join(f for f, on in zip(FORCE_AXES, L["active_forces"]) if on)
            )
            for f, u in self.unread_forces().items():
                moves = ", ".join(f"{a} {v:.3g}" for a, v in u["ttp_um"].items())
                out.append(
                    f"{f} is not read: its signature is the gratings' warming pattern; at the "
                    f"training's {u['max_abs_N']:.4g} N it moves the TTP {moves} µm, which neither "
                    "the correction nor its interval holds"
                )
            out.append(f"{'':<8}" + "".join(f"{f + ' µm/kN':>13}" for f in FORCE_AXES))
            for s, row in zip(self.sensor_names, np.asarray(L["G_um_per_N"])):
                out.append(f"{s:<8}" + "".join(f"{1e3 * v:>13.4g}" for v in row))
            for a, row in zip(AXES, np.asarray(L["C_um_per_N"])):
                out.append(f"{a:<8}" + "".join(f"{1e3 * v:>13.4g}" for v in row))
            p = self.predictor()
            at_rest, warm = p.F_sds
            out.append(
                "force 1-sigma N at rest / at the training's thermal extreme: "
                + ", ".join(f"{f} {a:.3g}/{b:.3g}" for f, a, b in zip(FORCE_AXES, at_rest, warm))
                + f"; applied from {self.load_k_sigma:g} sigma, in full beyond {2 * self.load_k_sigma:g}"
            )
        return "\n".join(out)

    def to_dict(self) -> dict:
        """The model file's content (hyper-parameters but the machine, learned state)."""
        d = self._header()
        d.update(
            {
                "params": {k: v for k, v in self.get_params().items() if k != "machine"},
                "zero_state": {"method": "mean_of_first_window", "window_s": self.zero_window_s},
                "sensors": [s.model_dump(mode="json") for s in self.sensors_],
                "probes": list(self.probe_names_),
                "heat_inputs": list(self.heat_inputs_),
                "housing_probes": list(self.housing_probes_),
                "ambient_probes": list(self.ambient_probes_),
                "nominal_dt_s": self.nominal_dt_s_,
                "thermal": {
                    "coef": np.asarray(self.thermal_coef_).tolist(),
                    "envelope_low": np.asarray(self.thermal_envelope_[0]).tolist(),
                    "envelope_high": np.asarray(self.thermal_envelope_[1]).tolist(),
                    "range_low_um": np.asarray(self.thermal_range_um_[0]).tolist(),
                    "range_high_um": np.asarray(self.thermal_range_um_[1]).tolist(),
                    "resid_sd_um": np.asarray(self.thermal_resid_sd_um_).tolist(),
                    "noise_sd_um": np.asarray(self.thermal_noise_sd_um_).tolist(),
                },
                "twin_map": copy.deepcopy(self.twin_map_),
                "observer": copy.deepcopy(getattr(self, "observer_", None)),
                "interval": copy.deepcopy(getattr(self, "interval_", None)),
                "load": copy.deepcopy(self.load_),
                "training": copy.deepcopy(self.training_),
                "uncertainty": {
                    "level": 0.95,
                    "method": (
                        "thermal error v0 (reference noise) + vs excursion + v1 excursion^2 + v2 lead^2,"
                        " calibrated to 95 % training coverage, + applied load's GLS and relative error"
                    ),
                },
                "z_axis_mm": None,
                "trained_z_axis_mm": self.trained_z_axis_mm_,
            }
        )
        return d

    @classmethod
    def from_dict(cls, d: dict, source="<dict>") -> PhysicalModel:
        """The model of a model file's dict; InputError unless its shapes agree and every sensor
        set predicts finite numbers."""
        check_shapes(d, source)
        # (files from before the thermal part's relative error: none)
        m = cls(**({"thermal_relative_error": 0.0} | d.get("params", {})))
        m.sensors_ = [SensorSpec(**s) for s in d["sensors"]]
        m.probe_names_ = list(d["probes"])
        m.heat_inputs_ = list(d.get("heat_inputs") or [])
        m.housing_probes_ = list(d["housing_probes"])
        m.ambient_probes_ = list(d["ambient_probes"])
        m.nominal_dt_s_ = float(d["nominal_dt_s"])
        tz = d.get("trained_z_axis_mm")  # absent from files before it: no Z check
        m.trained_z_axis_mm_ = None if tz is None else [float(z) for z in tz]
        th = d["thermal"]
        m.thermal_coef_ = np.asarray(th["coef"], float)
        m.thermal_envelope_ = (np.asarray(th["envelope_low"], float), np.asarray(th["envelope_high"], float))
        m.thermal_range_um_ = (np.asarray(th["range_low_um"], float), np.asarray(th["range_high_um"], float))
        m.thermal_resid_sd_um_ = np.asarray(th["resid_sd_um"], float)
        m.thermal_noise_sd_um_ = np.asarray(th.get("noise_sd_um", [0.0] * 3), float)
        m.twin_map_ = d.get("twin_map")
        m.observer_ = d.get("observer")
        m.interval_ = d.get("interval")
        m.load_ = d.get("load")
        m.training_ = d.get("training", {"campaigns": [], "n_samples": 0})
        m._predictors = {}
        # what loaded must predict finite numbers with every sensor set the runtime may use
        w0 = np.array([s.lambda0_nm for s in m.sensors_])
        t0 = np.full(len(m.probe_names), 20.0)
        for exclude in [frozenset(), *m.fallback_sets]:
            dev, half = PhysicalPredictor(m, exclude).predict(w0[None, :] + 0.01, t0[None, :] + 0.5, w0, t0)
            if not (np.isfinite(dev).all() and np.isfinite(half).all()):
                raise InputError(
                    "model cannot predict finite numbers"
                    + (f" without {', '.join(sorted(exclude))}" if exclude else ""),
                    file=source,
                    column="field thermal/load/twin_map",
                )
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
