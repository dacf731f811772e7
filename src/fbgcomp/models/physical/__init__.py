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
Where the campaigns carry the spindle's measured power (heat.csv, ``<source>_W``), the housing
calibration also takes its change since the zero state low-passed at ``HEAT_TAUS_S`` (the housing
probe sees a power step minutes late, the power at once), and the model reads it after its probes.
Either way the inputs are clipped to the envelope they were learned on (``SHRUNK``), what the
sensors' noise alone makes of the part is not applied (firm shrinkage) and each axis is clamped
to the range it was validated on (``CLAMPED``).

Every prediction therefore carries its applicability flags (``last_flags`` after each call,
bits of :mod:`fbgcomp.models.policy`), which the runtime publishes with the correction.

**Interval** (95 %, per axis). The thermal part's error variance grows with the probes'
excursion and the housing's transient, fitted on the load-free training campaigns' errors and
scaled to cover 95 % of them (:meth:`PhysicalModel._fit_interval`). Two terms speak for what
those campaigns cannot: the twin map's members' disagreement (where the gratings cannot tell
one heat source from another) and the part of the correction made from feature directions no
training campaign moved along (a face warmer than its opposite one, see
:func:`~fbgcomp.models.physical.thermal.unseen_basis`), at ``unseen_relative_error`` of itself,
since only the twin and the description vouch for it. A third, added after the scaling, speaks
for what the training's own trajectory of heat cannot show at all: the whole thermal
correction at ``thermal_relative_error`` (0.5 %) of itself, about what the twin driven by a ram's
true inputs is off (ram5: 0.2-0.7 % of dz); a heat taking another path than in training leaves
that much (ram5's thermal_c: 0.45 µm of dz for six hours on 54 µm, inside +-0.3 µm before).
While a load is applied, the force estimate's noise and the signature's relative error are
added through the compliance.

The package: :mod:`~fbgcomp.models.physical.thermal` (thermal regressors and the twin-learned
map), :mod:`~fbgcomp.models.physical.predictor` (load tracking, thermal part and policy of one
sensor set), :mod:`~fbgcomp.models.physical.shapes` (the model file's shape checks) and
:mod:`~fbgcomp.models.physical.model` (the estimator and its file).
"""

from fbgcomp.models.physical.model import PhysicalModel
from fbgcomp.models.physical.predictor import (
    FORCE_AXES,
    LOAD_FALSE_STARTS_PER_H,
    LOAD_FAST_S,
    LOAD_HOLD_S,
    STEADY_BACKOFF,
    STEADY_WINDOW,
    PhysicalPredictor,
    excursion2,
    gls_operator,
)
from fbgcomp.models.physical.thermal import (
    CAL_LEADS_S,
    MAP_LEADS_S,
    PROBE_SMOOTHING_S,
    housing_leads,
    housing_mean,
    map_features,
    ridge_from_moments,
    thermal_regressors,
    twin_thermal_population,
    weighted_lstsq,
)

__all__ = [
    "CAL_LEADS_S",
    "FORCE_AXES",
    "LOAD_FALSE_STARTS_PER_H",
    "LOAD_FAST_S",
    "LOAD_HOLD_S",
    "MAP_LEADS_S",
    "PROBE_SMOOTHING_S",
    "STEADY_BACKOFF",
    "STEADY_WINDOW",
    "PhysicalModel",
    "PhysicalPredictor",
    "excursion2",
    "gls_operator",
    "housing_leads",
    "housing_mean",
    "map_features",
    "ridge_from_moments",
    "thermal_regressors",
    "twin_thermal_population",
    "weighted_lstsq",
]
