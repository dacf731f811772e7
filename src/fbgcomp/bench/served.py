"""A recorded campaign served through the runtime core, as the machine would have received it.

``fbgcomp validate`` judges a model's own prediction; what a CNC receives is that prediction
through the runtime's output policy (output filter, per-axis maximum and rate limit) and its
fault handling (a grating lost switches to a fallback). :func:`served` feeds a campaign's own
interrogator frames to a :class:`~fbgcomp.runtime.pipeline.Pipeline` in batches, on the
interrogator's clock, optionally with one grating lost from some point of the run on, and
returns the published correction at the reference instrument's samples (the last frame's, as
``validate`` compares); inside a gap of the campaign's fbg.csv, the runtime's lost link
(:func:`link_loss_frames`). ``benchmarks/bench_lost_grating.py`` and the runtime tests on ram2 judge
the runtime this way.
"""

from __future__ import annotations

import numpy as np

from fbgcomp.io.campaign.folder import FBG_FILE
from fbgcomp.runtime.pipeline import Pipeline, PipelineConfig

#: The batch results :func:`process_in_batches` concatenates (``BatchResult`` fields).
BATCH_FIELDS = (
    "deviation_um",
    "half_width_um",
    "correction_um",
    "health",
    "sensor_status",
    "model_set",
    "expected_rms_um",
    "output_flags",
)


def process_in_batches(pipe, time_s, wavelength_nm, temperature_C, sizes=(100,), counts=None) -> dict:
    """Feed frames to ``pipe.process`` in batches whose sizes cycle through ``sizes`` (one peak
    per grating unless ``counts`` (n, S)); returns :data:`BATCH_FIELDS`, concatenated."""
    out, i, k = [], 0, 0
    counts = np.ones(wavelength_nm.shape, np.int8) if counts is None else counts
    while i < time_s.size:
        j = min(time_s.size, i + sizes[k % len(sizes)])
        out.append(
            pipe.process(
                time_s[i:j], wavelength_nm[i:j], counts[i:j], np.zeros_like(counts[i:j]), temperature_C[i:j]
            )
        )
        i, k = j, k + 1
    return {n: np.concatenate([getattr(r, n) for r in out]) for n in BATCH_FIELDS}


def link_loss_frames(model, campaign, time_s, wavelength_nm, temperature_C, counts):
    """The frames with, inside each gap of the campaign's fbg.csv (:meth:`Campaign.gaps`: the
    interrogator stopped), one frame every median frame interval without any grating, the probes
    and heat inputs at their last reading: what ``serve`` runs while its link is lost and the
    probes arrive live (``probes_on_link_loss``; a model without a set for it holds and ramps its
    correction to zero on them). Returns the four arrays, in time order."""
    gaps = campaign.gaps().get(FBG_FILE, [])
    if not gaps or time_s.size < 2:
        return time_s, wavelength_nm, temperature_C, counts
    dt = float(np.median(np.diff(time_s)))
    ticks = np.concatenate([np.arange(a + dt, b - 0.5 * dt, dt) for a, b in gaps])
    ticks = ticks[(ticks > time_s[0]) & (ticks < time_s[-1])]
    if not ticks.size:
        return time_s, wavelength_nm, temperature_C, counts
    slow = campaign.slow_inputs()  # probes (<probe>_C) and heat inputs (<source>_W)
    held = np.clip(np.searchsorted(slow["time_s"].to_numpy(), ticks, side="right") - 1, 0, len(slow) - 1)
    # (a strain-free reference grating is read through the interrogator: lost with it, NaN)
    tick_temp = np.full((ticks.size, len(model.probe_names)), np.nan)
    for j, name in enumerate(model.probe_names):
        col = name if name in slow.columns else f"{name}_C"
        if col in slow.columns:
            tick_temp[:, j] = slow[col].to_numpy(np.float64)[held]
    order = np.argsort(np.concatenate([time_s, ticks]), kind="stable")
    S = wavelength_nm.shape[1]
    return (
        np.concatenate([time_s, ticks])[order],
        np.vstack([wavelength_nm, np.full((ticks.size, S), np.nan)])[order],
        np.vstack([temperature_C, tick_temp])[order],
        np.vstack([counts, np.zeros((ticks.size, S), counts.dtype)])[order],
    )


def served(model, campaign, pipe=None, lost=None, lost_from=0.4, sizes=(100,), lost_until=None):
    """``campaign`` served through ``pipe`` (default: a fresh ``Pipeline`` of ``model`` with
    the default configuration), grating or probe ``lost`` (a name, or several lost together)
    gone (no peak; no reading) from the fraction ``lost_from`` of the run on, up to the
    fraction ``lost_until`` (None: to the end).
    Returns the published correction (m, 3) µm at the reference samples, the reference (m, 3)
    µm (the aligned campaign's) and the batch results (:func:`process_in_batches`), with ``at``:
    the frame index of each reference sample."""
    al = campaign.aligned(zero_window_s=model.zero_window_s)
    if hasattr(model, "frame_arrays"):  # the physical model: its measured heat inputs too
        ft, w, temp = model.frame_arrays(campaign, al)
    else:
        ft, w, temp = campaign.frames(al, model.sensor_names, model.probe_names)
    counts = np.ones(w.shape, np.int8)
    if lost is not None:
        span = ft[-1] - ft[0]
        gone = ft >= ft[0] + lost_from * span
        if lost_until is not None:
            gone &= ft < ft[0] + lost_until * span
        w, temp = w.copy(), temp.copy()
        for name in [lost] if isinstance(lost, str) else lost:  # one name, or several at once
            if name in model.sensor_names:
                j = model.sensor_names.index(name)
                w[gone, j] = np.nan
                counts[gone, j] = 0
            else:
                temp[gone, list(model.probe_names).index(name)] = np.nan
    ft, w, temp, counts = link_loss_frames(model, campaign, ft, w, temp, counts)
    out = process_in_batches(pipe or Pipeline(model, PipelineConfig()), ft, w, temp, sizes, counts)
    at = np.clip(np.searchsorted(ft, al.time_s, side="right") - 1, 0, ft.size - 1)
    out["at"] = at
    return out["correction_um"][at], al.reference_um, out


def published(model, campaign):
    """What the runtime publishes on ``campaign``, as a model's prediction is judged: the
    deviation (m, 3) µm the published correction undoes, its 95 % half-width (m, 3) µm and the
    reference (m, 3) µm, at the reference samples (:func:`served` with the default pipeline).

    The runtime's half-width is the model's, about the model's own deviation; where the output
    policy holds the correction elsewhere (the filter at rest, a limit, a hold), the correction's
    interval is that half-width plus the departure: the model's 95 % interval, moved by as much
    as the policy moved its centre. Without it, a quiet axis the filter holds still covered 0.28
    on ram4's static_y (dx, a cross-talk of 3 µm the filter confirms late)."""
    correction, reference, out = served(model, campaign)
    deviation = -correction
    model_deviation = out["deviation_um"][out["at"]]
    half = out["half_width_um"][out["at"]] + np.abs(deviation - model_deviation)
    return deviation, half, reference
