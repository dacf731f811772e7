"""A campaign folder as a whole: the :class:`Campaign` object (construction, alignment,
inspection), :func:`read_campaign` and the atomic :func:`write_campaign`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from fbgcomp import optics
from fbgcomp.atomic import staged_dir
from fbgcomp.errors import InputError
from fbgcomp.io.campaign.align import (
    AlignedCampaign,
    check_window,
    interp_columns,
    moving_in_window,
    onto_reference,
    zero_state,
)
from fbgcomp.io.campaign.layout import (
    FBG_FILE,
    HEAT_FILE,
    HEAT_SUFFIX,
    LOAD_COLUMNS,
    LOADS_FILE,
    META_FILE,
    REFERENCE_COLUMNS,
    REFERENCE_FILE,
    TEMPERATURES_FILE,
    TIME_COLUMN,
)
from fbgcomp.io.campaign.meta import CampaignMeta, meta_yaml, read_meta, validate_meta
from fbgcomp.io.campaign.tables import read_table, table_from_input, write_csv

__all__ = ["GAP_FACTOR", "Campaign", "read_campaign", "write_campaign"]

#: Sampling gaps longer than this many median intervals are reported by ``summary()``.
GAP_FACTOR = 5.0


def _sampling_gaps(t: np.ndarray) -> list[tuple[float, float]]:
    """The gaps of time stamps ``t`` (s) longer than ``GAP_FACTOR`` x their median interval, each
    as (last sample before, first sample after)."""
    step = np.diff(t)
    if not step.size or not np.median(step) > 0:
        return []
    return [(float(t[i]), float(t[i + 1])) for i in np.flatnonzero(step > GAP_FACTOR * np.median(step))]


@dataclass(eq=False)
class Campaign:
    """A campaign folder in memory: metadata and one DataFrame per instrument, each on its own
    clock, validated and with canonical column order (see the module docstring)."""

    path: Path | None
    meta: CampaignMeta
    fbg: pd.DataFrame
    temperatures: pd.DataFrame
    reference: pd.DataFrame
    loads: pd.DataFrame | None = None
    heat: pd.DataFrame | None = None

    # -- names -------------------------------------------------------------------------------
    @property
    def name(self) -> str:
        """The campaign's name (campaign.yaml ``name``)."""
        return self.meta.name

    @property
    def sensor_names(self) -> list[str]:
        """Sensor names in campaign.yaml order."""
        return self.meta.sensor_names

    @property
    def probe_names(self) -> list[str]:
        """Declared probes, then temperature columns found in the data but not declared."""
        return self.meta.probe_names + self.undeclared_probes

    @property
    def undeclared_probes(self) -> list[str]:
        """Probes of temperatures.csv columns that campaign.yaml does not declare, in file order."""
        declared = {p.column for p in self.meta.temperature_probes}
        return [c[:-2] for c in self.temperatures.columns if c != TIME_COLUMN and c not in declared]

    @property
    def heat_names(self) -> list[str]:
        """Measured heat inputs (heat.csv's ``<source>_W`` columns, file order); [] without heat.csv."""
        if self.heat is None:
            return []
        return [c[: -len(HEAT_SUFFIX)] for c in self.heat.columns if c != TIME_COLUMN]

    def heat_inputs(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The measured heat inputs on heat.csv's clock: ``(time_s (n,), values (n, k) W)`` in
        :attr:`heat_names` order, or None without heat.csv."""
        if self.heat is None:
            return None
        cols = [f"{h}{HEAT_SUFFIX}" for h in self.heat_names]
        return self.heat[TIME_COLUMN].to_numpy(), self.heat[cols].to_numpy(dtype=np.float64)

    def __repr__(self) -> str:
        loads = "none" if self.loads is None else f"{len(self.loads)} rows"
        return (
            f"Campaign(name={self.name!r}, kind={self.meta.kind!r}, path={self.path}, "
            f"fbg={len(self.fbg)} rows x {len(self.sensor_names)} sensors, "
            f"temperatures={len(self.temperatures)} rows x {len(self.probe_names)} probes, "
            f"reference={len(self.reference)} rows, loads={loads}"
            + ("" if self.heat is None else f", heat={len(self.heat)} rows x {len(self.heat_names)} inputs")
            + ")"
        )

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_arrays(
        cls,
        meta: CampaignMeta | Mapping,
        *,
        fbg,
        temperatures,
        reference,
        loads=None,
        heat=None,
        path: str | Path | None = None,
    ) -> Campaign:
        """Build a validated campaign from DataFrames or mappings ``{column: 1-D array}``.

        The same checks as :func:`read_campaign` apply (columns, finite numbers, strictly
        increasing ``time_s``, wavelengths within the grating band); errors name the file the
        table would be written to.
        """
        meta = validate_meta(meta, META_FILE)
        return cls(
            path=None if path is None else Path(path),
            meta=meta,
            fbg=table_from_input(FBG_FILE, fbg, meta, FBG_FILE),
            temperatures=table_from_input(TEMPERATURES_FILE, temperatures, meta, TEMPERATURES_FILE),
            reference=table_from_input(REFERENCE_FILE, reference, meta, REFERENCE_FILE),
            loads=None if loads is None else table_from_input(LOADS_FILE, loads, meta, LOADS_FILE),
            heat=None if heat is None else table_from_input(HEAT_FILE, heat, meta, HEAT_FILE),
        )

    def validate(self) -> Campaign:
        """Re-run every check on the in-memory tables (after editing them); returns a campaign
        with canonical column order."""
        return self.replaced()

    def replaced(
        self, *, meta=None, fbg=None, temperatures=None, reference=None, loads=None, heat=None
    ) -> Campaign:
        """A validated campaign with the parts given replaced and the others as they are: the
        same measurements under another campaign.yaml (``meta``, a CampaignMeta or mapping), or
        the same campaign with one table edited. ``loads`` and ``heat`` cannot be removed this way."""
        return Campaign.from_arrays(
            self.meta if meta is None else meta,
            fbg=self.fbg if fbg is None else fbg,
            temperatures=self.temperatures if temperatures is None else temperatures,
            reference=self.reference if reference is None else reference,
            loads=self.loads if loads is None else loads,
            heat=self.heat if heat is None else heat,
            path=self.path,
        )

    # -- alignment ---------------------------------------------------------------------------
    def _spans(self) -> dict[str, tuple[float, float]]:
        spans = {}
        for role, frame in (
            (FBG_FILE, self.fbg),
            (TEMPERATURES_FILE, self.temperatures),
            (REFERENCE_FILE, self.reference),
        ):
            t = frame[TIME_COLUMN].to_numpy()
            spans[role] = (float(t[0]), float(t[-1]))
        return spans

    def _where(self):
        return self.path if self.path is not None else self.name

    def aligned(self, zero_window_s: float = 10.0, average: bool = True) -> AlignedCampaign:
        """All instruments on the reference clock inside their common time range.

        The overlap is [latest first sample, earliest last sample] over fbg, temperatures and
        reference; reference samples outside it are dropped (and counted), the other signals are
        interpolated linearly, never extrapolated. With ``average`` (default), an instrument
        that samples at least three times per reference interval (e.g. a 10 Hz interrogator
        against a 1 Hz interferometer) is first averaged over that interval — a local
        least-squares line centred on each reference time, exact for linear signals — so its
        noise drops by the square root of the samples averaged instead of aliasing. Loads do not
        restrict the overlap: they are interpolated inside their own time range and NaN outside
        it. Zero states are the mean of the first ``zero_window_s`` seconds of each signal on its
        own clock.
        """
        window = check_window(zero_window_s)
        spans = self._spans()
        t0 = max(span[0] for span in spans.values())
        t1 = min(span[1] for span in spans.values())
        if t0 > t1:
            ranges = "; ".join(f"{role} {a:g} to {b:g} s" for role, (a, b) in spans.items())
            raise InputError(f"the instruments' records do not overlap in time: {ranges}", file=self._where())
        ref_t = self.reference[TIME_COLUMN].to_numpy()
        first = int(np.searchsorted(ref_t, t0, side="left"))
        stop = int(np.searchsorted(ref_t, t1, side="right"))
        if stop <= first:
            raise InputError(
                f"no reference sample falls inside the overlap {t0:g} to {t1:g} s "
                "of fbg.csv, temperatures.csv and reference.csv",
                file=self._where(),
            )
        time_s = ref_t[first:stop].copy()
        ref_dt = float(np.median(np.diff(ref_t))) if ref_t.size > 1 else 0.0

        fbg_t = self.fbg[TIME_COLUMN].to_numpy()
        fbg_v = self.fbg[[s.column for s in self.meta.sensors]].to_numpy(dtype=np.float64)
        # each thermometer on its own clock: probes on temperatures.csv's, reference gratings
        # on the interrogator's
        temperature_C = np.empty((time_s.size, len(self.probe_names)))
        temperature_zero_C = np.empty(len(self.probe_names))
        for names, (src_t, src_v) in self.thermometers().items():
            idx = [self.probe_names.index(p) for p in names]
            temperature_C[:, idx] = onto_reference(time_s, src_t, src_v, ref_dt, average)
            temperature_zero_C[idx] = zero_state(src_t, src_v, window)
        ref_v = self.reference[list(REFERENCE_COLUMNS)].to_numpy(dtype=np.float64)
        reference_zero_um = zero_state(ref_t, ref_v, window)

        loads_N = None
        loads_outside = None
        if self.loads is not None:
            loads_t = self.loads[TIME_COLUMN].to_numpy()
            loads_v = self.loads[list(LOAD_COLUMNS)].to_numpy(dtype=np.float64)
            moving = moving_in_window(loads_t, loads_v, window)
            if moving is not None:
                row, col, change = moving
                where = LOADS_FILE if self.path is None else Path(self.path) / LOADS_FILE
                raise InputError(
                    f"the load changes by {change:+.0f} N within the zero window (the first "
                    f"{window:g} s): the zero state must be taken at rest; start the campaign "
                    "before the load is applied, or drop the rows recorded while it moved",
                    file=where,
                    row=row + 1,
                    column=LOAD_COLUMNS[col],
                )
            loads_N = interp_columns(time_s, loads_t, loads_v, outside=np.nan)
            loads_outside = int(np.isnan(loads_N[:, 0]).sum())

        return AlignedCampaign(
            name=self.name,
            meta=self.meta,
            time_s=time_s,
            wavelength_nm=onto_reference(time_s, fbg_t, fbg_v, ref_dt, average),
            wavelength_zero_nm=zero_state(fbg_t, fbg_v, window),
            temperature_C=temperature_C,
            temperature_zero_C=temperature_zero_C,
            reference_um=ref_v[first:stop] - reference_zero_um,
            reference_zero_um=reference_zero_um,
            loads_N=loads_N,
            dropped={
                "before": first,
                "after": int(ref_t.size - stop),
                "overlap_s": (t0, t1),
                "loads_outside": loads_outside,
            },
            sensor_names=list(self.sensor_names),
            probe_names=list(self.probe_names),
            zero_window_s=window,
        )

    def frames(self, aligned, sensor_names, probe_names):
        """The campaign as a runtime sees it: every interrogator frame inside ``aligned``'s
        overlap (:meth:`aligned`), with each probe's last reading at that frame (held, as a live
        feed is). Frame times (n,) s, wavelengths (n, sensors) nm and temperatures (n, probes)
        degC in the order of ``sensor_names`` and ``probe_names``; a probe this campaign does not
        carry is NaN (no reading)."""
        ft = self.fbg[TIME_COLUMN].to_numpy(dtype=float)
        t_lo, t_hi = aligned.dropped["overlap_s"]
        keep = (ft >= t_lo - 1e-9) & (ft <= t_hi + 1e-9)
        if not keep.any():
            keep[:] = True
        ft = ft[keep]
        w = self.fbg[[f"{s}_nm" for s in sensor_names]].to_numpy(dtype=float)[keep]
        temps = np.full((ft.size, len(probe_names)), np.nan)
        for names, (tt, tv) in self.thermometers().items():
            held = np.clip(np.searchsorted(tt, ft, side="right") - 1, 0, tt.size - 1)
            for j, name in enumerate(names):
                if name in probe_names:
                    temps[:, list(probe_names).index(name)] = tv[held, j]
        return ft, w, temps

    def thermometers(self) -> dict[tuple, tuple[np.ndarray, np.ndarray]]:
        """Every temperature reading on its own clock: ``{probe names: (time_s (n,), values
        (n, k) degC)}``. Probes come from temperatures.csv; a strain-free reference grating
        (``<sensor>_ref``) is read from fbg.csv as the temperature change of the sensor's gauge
        since the first sample (eq. 3 inverted, :func:`fbgcomp.optics.grating_temperature_change_K`)."""
        refs = set(self.meta.reference_probe_names)
        probes = tuple(p for p in self.probe_names if p not in refs)
        out = {
            probes: (
                self.temperatures[TIME_COLUMN].to_numpy(),
                self.temperatures[[f"{p}_C" for p in probes]].to_numpy(dtype=np.float64),
            )
        }
        with_ref = [s for s in self.meta.sensors if s.reference_column is not None]
        if with_ref:
            lam = self.fbg[[s.reference_column for s in with_ref]].to_numpy(dtype=np.float64)
            dT = optics.grating_temperature_change_K(
                lam,
                lam[0],
                thermo_optic_per_K=np.array([s.thermo_optic_per_K for s in with_ref]),
                fibre_cte_per_K=np.array([s.fibre_cte_per_K for s in with_ref]),
            )
            # a sensor with a reference grating always has its reference probe (SensorSpec)
            probes = tuple(s.reference_probe for s in with_ref if s.reference_probe is not None)
            out[probes] = (self.fbg[TIME_COLUMN].to_numpy(), dT)
        return out

    def slow_inputs(self) -> pd.DataFrame:
        """temperatures.csv and heat.csv on one clock, as a runtime replays them: ``time_s``,
        the ``<probe>_C`` columns, then the ``<source>_W`` ones; each column holds its own
        file's last reading at every time stamp of either file (NaN before its first)."""
        if self.heat is None:
            return self.temperatures
        parts = [self.temperatures, self.heat]
        t = np.union1d(*(f[TIME_COLUMN].to_numpy() for f in parts))
        out = {TIME_COLUMN: t}
        for f in parts:
            ft = f[TIME_COLUMN].to_numpy()
            held = np.searchsorted(ft, t, side="right") - 1
            for col in f.columns:
                if col != TIME_COLUMN:
                    v = f[col].to_numpy(dtype=np.float64)[np.maximum(held, 0)]
                    out[col] = np.where(held >= 0, v, np.nan)
        return pd.DataFrame(out)

    # -- inspection --------------------------------------------------------------------------
    def _tables(self) -> dict[str, pd.DataFrame]:
        tables = {FBG_FILE: self.fbg, TEMPERATURES_FILE: self.temperatures, REFERENCE_FILE: self.reference}
        if self.loads is not None:
            tables[LOADS_FILE] = self.loads
        if self.heat is not None:
            tables[HEAT_FILE] = self.heat
        return tables

    def gaps(self) -> dict[str, list[tuple[float, float]]]:
        """Per file, the sampling gaps longer than ``GAP_FACTOR`` x its median interval, each as
        (last sample before, first sample after) in s; files without one are left out.
        :meth:`aligned` interpolates across a gap: what it gives inside one is no reading."""
        spans = (
            (role, _sampling_gaps(frame[TIME_COLUMN].to_numpy())) for role, frame in self._tables().items()
        )
        return {role: found for role, found in spans if found}

    def summary(self) -> dict:
        """What ``fbgcomp inspect`` shows: per-file statistics, the alignment overlap and
        non-fatal problems. Only builtins (JSON-serialisable)."""
        problems: list[str] = []
        files = {}
        for role, frame in self._tables().items():
            t = frame[TIME_COLUMN].to_numpy()
            step = np.diff(t)
            median = float(np.median(step)) if step.size else None
            info = {
                "rows": int(t.size),
                "start_s": float(t[0]),
                "end_s": float(t[-1]),
                "duration_s": float(t[-1] - t[0]),
                "median_interval_s": median,
                "rate_hz": (1.0 / median) if median else None,
                "columns": {
                    c: {"min": float(frame[c].min()), "max": float(frame[c].max())}
                    for c in frame.columns
                    if c != TIME_COLUMN
                },
            }
            found = _sampling_gaps(t)
            info["gaps"] = len(found)
            if found:
                a, b = max(found, key=lambda g: g[1] - g[0])
                row = int(np.searchsorted(t, b)) + 1  # data rows count from 1
                problems.append(
                    f"{role}: {len(found)} gap(s) longer than {GAP_FACTOR:g} x the median "
                    f"interval ({median:g} s); longest {b - a:g} s before row {row} (t = {b:g} s)"
                )
            files[role] = info

        spans = self._spans()
        t0 = max(span[0] for span in spans.values())
        t1 = min(span[1] for span in spans.values())
        ref_t = self.reference[TIME_COLUMN].to_numpy()
        if t0 <= t1:
            overlap = [t0, t1]
            before = int(np.searchsorted(ref_t, t0, side="left"))
            after = int(ref_t.size - np.searchsorted(ref_t, t1, side="right"))
            if before + after:
                problems.append(
                    f"{before + after} reference sample(s) outside the overlap "
                    f"{t0:g} to {t1:g} s will be dropped ({before} before, "
                    f"{after} after)"
                )
            if self.loads is not None:
                lt = self.loads[TIME_COLUMN].to_numpy()
                inside = ref_t[(ref_t >= t0) & (ref_t <= t1)]
                uncovered = int(((inside < lt[0]) | (inside > lt[-1])).sum())
                if uncovered:
                    problems.append(
                        f"{LOADS_FILE} covers {lt[0]:g} to {lt[-1]:g} s only: "
                        f"{uncovered} aligned sample(s) will have NaN loads"
                    )
        else:
            overlap, before, after = None, int(ref_t.size), 0
            problems.append("fbg.csv, temperatures.csv and reference.csv do not overlap in time")

        if self.loads is not None:
            moving = moving_in_window(
                self.loads[TIME_COLUMN].to_numpy(), self.loads[list(LOAD_COLUMNS)].to_numpy(float), 10.0
            )
            if moving is not None:
                row, col, change = moving
                problems.append(
                    f"{LOADS_FILE}: column {LOAD_COLUMNS[col]} changes by {change:+.0f} N at row "
                    f"{row + 1}, within the default 10 s zero window: fit and validate refuse a "
                    "zero state not taken at rest"
                )
        for probe in self.undeclared_probes:
            problems.append(
                f"{TEMPERATURES_FILE}: column {probe}_C is not declared in "
                f"campaign.yaml temperature_probes (used as probe {probe!r})"
            )
        for role, frame in self._tables().items():
            for column in frame.attrs.get("ignored_columns", []):
                problems.append(f"{role}: column {column!r} is not part of the format and was ignored")
        for i, sensor in enumerate(self.meta.sensors):
            for key in sensor.model_extra or {}:
                problems.append(f"{META_FILE}: sensors[{i}] has unrecognised key {key!r} (kept; a typo?)")

        return {
            "name": self.name,
            "kind": self.meta.kind,
            "description": self.meta.description,
            "start": self.meta.start.isoformat(),
            "path": None if self.path is None else str(self.path),
            "files": files,
            "overlap_s": overlap,
            "reference_outside_overlap": {"before": before, "after": after},
            "sensors": [
                {"name": s.name, "lambda0_nm": s.lambda0_nm, "temperature_probe": s.temperature_probe}
                for s in self.meta.sensors
            ],
            "probes": self.probe_names,
            "undeclared_probes": self.undeclared_probes,
            "problems": problems,
        }

    def summary_text(self) -> str:
        """:meth:`summary` as a human-readable report."""
        s = self.summary()
        lines = [f"campaign {s['name']!r} ({s['kind']}), start {s['start']}"]
        if s["path"]:
            lines.append(f"  folder: {s['path']}")
        if s["description"]:
            lines.append(f"  {s['description']}")
        for role, info in s["files"].items():
            rate = (
                f"every {info['median_interval_s']:g} s ({info['rate_hz']:.4g} Hz)"
                if info["median_interval_s"]
                else "single sample"
            )
            lines.append(
                f"{role}: {info['rows']} rows, {info['start_s']:g} to {info['end_s']:g} s "
                f"({info['duration_s']:g} s), {rate}"
            )
            for column, mm in info["columns"].items():
                lines.append(f"    {column:<16} min {mm['min']:.12g}  max {mm['max']:.12g}")
        if s["overlap_s"] is None:
            lines.append("overlap: none")
        else:
            out = s["reference_outside_overlap"]
            lines.append(
                f"overlap: {s['overlap_s'][0]:g} to {s['overlap_s'][1]:g} s; reference "
                f"samples outside: {out['before']} before, {out['after']} after"
            )
        probes = {sensor["name"]: sensor["temperature_probe"] for sensor in s["sensors"]}
        lines.append(
            "sensors: "
            + ", ".join(
                f"{name} (probe {probe})" if probe else f"{name} (uncompensated)"
                for name, probe in probes.items()
            )
        )
        lines.append("probes: " + (", ".join(s["probes"]) or "none"))
        if s["problems"]:
            lines.append("problems:")
            lines.extend(f"  - {p}" for p in s["problems"])
        else:
            lines.append("problems: none")
        return "\n".join(lines)


def read_campaign(path: str | Path) -> Campaign:
    """Read and validate a campaign folder.

    Raises
    ------
    InputError
        For anything wrong with the folder, naming the file and, where it applies, the 1-based
        data row and the column (or the YAML field path).
    """
    folder = Path(path)
    if not folder.exists():
        raise InputError("campaign folder not found", file=folder)
    if not folder.is_dir():
        raise InputError("expected a campaign folder, found a file", file=folder)
    meta = read_meta(folder)
    fbg = read_table(folder, FBG_FILE, meta)
    temperatures = read_table(folder, TEMPERATURES_FILE, meta)
    reference = read_table(folder, REFERENCE_FILE, meta)
    loads = read_table(folder, LOADS_FILE, meta) if (folder / LOADS_FILE).exists() else None
    heat = read_table(folder, HEAT_FILE, meta) if (folder / HEAT_FILE).exists() else None
    return Campaign(
        path=folder,
        meta=meta,
        fbg=fbg,
        temperatures=temperatures,
        reference=reference,
        loads=loads,
        heat=heat,
    )


def write_campaign(campaign: Campaign, path: str | Path) -> Path:
    """Write a campaign folder atomically and return its path.

    Everything is written into a temporary sibling folder first; an existing campaign folder at
    ``path`` is replaced only once the new one is complete, and nothing temporary is left behind
    on failure. A folder that is not a campaign folder (no campaign.yaml) is never replaced.
    """
    target = Path(path)
    if target.exists() and not target.is_dir():
        raise InputError("cannot write a campaign folder: a file of that name exists", file=target)
    if target.is_dir() and any(target.iterdir()) and not (target / META_FILE).is_file():
        raise InputError(
            "refusing to replace a folder that is not a campaign folder (it has no campaign.yaml)",
            file=target,
        )
    checked = campaign.validate()
    with staged_dir(target) as staging:
        write_csv(checked.fbg, staging / FBG_FILE)
        write_csv(checked.temperatures, staging / TEMPERATURES_FILE)
        write_csv(checked.reference, staging / REFERENCE_FILE)
        if checked.loads is not None:
            write_csv(checked.loads, staging / LOADS_FILE)
        if checked.heat is not None:
            write_csv(checked.heat, staging / HEAT_FILE)
        # Metadata last: a folder with campaign.yaml is a complete one.
        # Written like the tables (into the staging folder, so not atomic itself) so that every
        # file of the folder gets the same permissions.
        text = meta_yaml(checked.meta, target / META_FILE)
        with open(staging / META_FILE, "w", encoding="utf-8", newline="\n") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
    return target
