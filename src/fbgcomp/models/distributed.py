"""Fits over any number of rows, on the scale-out engine (:mod:`fbgcomp.cluster`).

The regression's sufficient statistics are a QR factor of ``[X | Y]`` that is small
((p+k) x (p+k)), streamable and mergeable (:class:`fbgcomp.models.regression.QRAccumulator`): a fit
over any number of rows is a *map* (one task per data file: stream it in row groups into a
factor) followed by a *tree reduction* (merge factors pairwise on the workers). Only factors
travel over the network, never rows; each worker holds one row group at a time, so its memory
does not grow with the data. Stepwise selection, the ANOVA and the fallback models then run on
the final factor in the client without reading the data again
(:meth:`fbgcomp.models.base.MRAModel.fit_factor`).

Autocorrelation-robust (Newey-West) inference, the default, needs one more read: a second
map, one task per campaign (its files in order, one series), adds the lagged score sums about
the pooled full model's coefficients (:meth:`~fbgcomp.models.regression.QRAccumulator.begin_hac`);
these add up in the client. Every path (campaign folders in-process, datasets, a cluster)
then gives the same inference as :meth:`~fbgcomp.models.base.MRAModel.fit`.

``dask`` arguments everywhere accept ``None`` (in-process, no Dask import), a scheduler address
``tcp://HOST:8786``, ``local:N`` (a LocalCluster of N single-threaded worker processes, started
and stopped around the call) or an existing ``distributed.Client``.

Workers must be able to import fbgcomp and see the same paths as the client (a shared file
system or the same machine).
"""

from __future__ import annotations

import functools
from pathlib import Path

from fbgcomp.atomic import json_safe
from fbgcomp.cluster import cluster, pairwise
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import SensorSpec, read_campaign, read_meta
from fbgcomp.io.dataset import Partition, check_partition, is_dataset, open_dataset, partition_design
from fbgcomp.models.base import campaign_weights_for, check_compatible
from fbgcomp.models.mra import MRAModel
from fbgcomp.models.regression import QRAccumulator

__all__ = ["accumulate_paths", "fit_paths"]

# --------------------------------------------------------------------------------------------
# Fitting: sources are dataset files and campaign folders
# --------------------------------------------------------------------------------------------


def _model_params(model) -> dict:
    params = model.get_params()
    roles = params["roles"]
    if roles is not None and not isinstance(roles, dict):
        params["roles"] = roles.as_dict()
    return params


def _worker_model(spec):
    model = MRAModel(**spec["params"])
    model.new_accumulator([SensorSpec(**s) for s in spec["sensors"]])
    return model


def _accumulate_source(source: dict, spec: dict) -> dict:
    """First-pass task: a dataset file or a campaign folder -> {"acc": state, "training": [...]}
    (the factor only; the autocorrelation statistics come in :func:`_second_pass`)."""
    model = _worker_model(spec)
    acc = model.new_accumulator(model.sensors_)
    entry = {"key": source["key"]}
    for design, ref in _source_rows(model, source, entry):
        acc.update(design, ref)
    entry["n_samples"] = int(acc.n_obs)
    return {"acc": acc.to_dict(), "training": [entry]}


def _source_rows(model, source: dict, info: dict | None = None):
    """Yield ``(design, reference_um)`` batches of one source (dataset file or campaign
    folder, checked against the model); ``info`` gets the campaign's dropped samples."""
    if source["kind"] == "file":
        partition = Partition.from_entry(Path(source["root"]), source["entry"])
        yield from partition_design(model, partition, source["file"])
    else:
        campaign = read_campaign(source["path"])
        check_compatible(model, campaign)
        aligned = campaign.aligned(zero_window_s=model.zero_window_s)
        if info is not None:
            info["dropped"] = json_safe(aligned.dropped)
        w, t, w0, t0 = model.instrument_arrays(aligned)
        chunk = 100_000
        for lo in range(0, len(aligned), chunk):
            yield (
                model.design_from_arrays(w[lo : lo + chunk], t[lo : lo + chunk], w0, t0),
                aligned.reference_um[lo : lo + chunk],
            )


def _hac_campaign(sources: list, spec: dict, acc, weight: float) -> tuple:
    """Second-pass task: one campaign's autocorrelation statistics (its files in order, one
    series, as :meth:`MRAModel.fit` sees it) about the pooled factor's full-model
    coefficients (``acc`` after ``begin_hac``), rows weighted as in the fit. Returns
    ``(g0, k, ka, rows)``, which add across campaigns (same pilot, same scales)."""
    model = _worker_model(spec)
    acc = acc.copy()
    for source in sources:
        for design, ref in _source_rows(model, source):
            acc.update_hac(design, ref, weights=weight)
    return acc.hac_g0_, acc.hac_k_, acc.hac_ka_, acc.hac_n_obs_


def _merge_states(a: dict, b: dict) -> dict:
    acc = QRAccumulator.from_dict(a["acc"]).merge(QRAccumulator.from_dict(b["acc"]))
    return {"acc": acc.to_dict(), "training": a["training"] + b["training"]}


def _plan(model, paths) -> tuple[list, list, dict]:
    """Sources (one per task), the training description skeleton, and the worker spec."""
    sources, described, first_sensors = [], [], None
    partitions_seen = []
    for raw in paths:
        path = Path(raw).resolve()
        if is_dataset(path):
            ds = open_dataset(path)
            for part in ds.partitions:
                key = f"{path}::{part.machine}/{part.campaign}"
                if first_sensors is None:
                    first_sensors = part.sensors()
                partitions_seen.append(part)
                described.append(
                    {
                        "key": key,
                        "name": part.campaign,
                        "kind": part.kind,
                        "machine": part.machine,
                        "path": str(part.path),
                        "dropped": part.dropped,
                    }
                )
                entry = part.to_entry()
                for f in part.file_paths:
                    sources.append(
                        {"kind": "file", "root": str(path), "entry": entry, "file": str(f), "key": key}
                    )
        else:
            if not path.is_dir():
                raise InputError("campaign folder or dataset not found", file=raw)
            meta = read_meta(path)
            if first_sensors is None:
                first_sensors = list(meta.sensors)
            key = str(path)
            described.append({"key": key, "name": meta.name, "kind": meta.kind, "path": str(raw)})
            sources.append({"kind": "campaign", "path": str(path), "key": key})
    if not sources:
        raise ValueError("fit needs at least one campaign or dataset")
    model.new_accumulator(first_sensors)
    for part in partitions_seen:
        check_partition(model, part)
    spec = {"params": _model_params(model), "sensors": [s.model_dump(mode="json") for s in model.sensors_]}
    return sources, described, spec


def _campaign_weights(model, counts: list) -> list:
    """Row weight of each campaign exactly as :meth:`MRAModel.fit` pools them."""
    return [float(v) for v in campaign_weights_for(counts, model.campaign_weights)]


def _pool(states: list, weights: list):
    """Merge per-campaign factors with their campaign weights (``QRAccumulator.merge``)."""
    first = QRAccumulator.from_dict(states[0]["acc"])
    acc = QRAccumulator(
        first.n_features, first.n_targets, first.feature_names, first.target_names, precision=first.precision
    )
    for st, w in zip(states, weights):
        acc.merge(QRAccumulator.from_dict(st["acc"]), weight=w)
    return acc


def _second_pass(acc, spec: dict, sources: list, weights: dict, client) -> None:
    """Fill ``acc``'s autocorrelation statistics from every campaign again, about the pooled
    full model (:meth:`~fbgcomp.models.regression.QRAccumulator.begin_hac`). A campaign's files
    are one series (its lags cross the file cuts), so one task per campaign."""
    acc.begin_hac()
    groups: dict = {}
    for src in sources:
        groups.setdefault(src["key"], []).append(src)
    if client is None:
        parts = [_hac_campaign(g, spec, acc, weights[k]) for k, g in groups.items()]
    else:
        shared = client.scatter(acc, broadcast=True)
        futures = [
            client.submit(_hac_campaign, g, spec, shared, weights[k], pure=False) for k, g in groups.items()
        ]
        parts = client.gather(futures)
    for g0, k, ka, rows in parts:
        acc.hac_g0_ += g0
        acc.hac_k_ += k
        acc.hac_ka_ += ka
        acc.hac_n_obs_ += rows


def accumulate_paths(model, paths, dask=None):
    """Reduce campaign folders and datasets to one factor: ``(accumulator, training)``.

    ``model`` gets its sensor set from the first source (as :meth:`MRAModel.fit` does). Files
    are reduced per campaign (on the cluster when given); the campaign factors, a few KB each,
    are then weighted as :meth:`MRAModel.fit` weights campaigns and merged in the client.
    """
    sources, described, spec = _plan(model, paths)
    task = functools.partial(_accumulate_source, spec=spec)
    keys = [d["key"] for d in described]
    with cluster(dask) as client:
        if client is None:
            groups: dict = {k: [] for k in keys}
            for src in sources:
                groups[src["key"]].append(task(src))
            per_campaign = [pairwise(_merge_states, groups[k]) for k in keys]
        else:
            futures = client.map(task, sources, pure=False)
            groups = {k: [] for k in keys}
            for src, fut in zip(sources, futures):
                groups[src["key"]].append(fut)
            reduced = [
                pairwise(lambda a, b: client.submit(_merge_states, a, b, pure=False), groups[k]) for k in keys
            ]
            per_campaign = client.gather(reduced)
        counts = [int(st["acc"]["n_obs"]) for st in per_campaign]
        weights = _campaign_weights(model, counts)
        acc = _pool(per_campaign, weights)
        if acc.hac_lags_ is not None:
            _second_pass(acc, spec, sources, dict(zip(keys, weights)), client)
    dropped = {t["key"]: t["dropped"] for st in per_campaign for t in st["training"] if "dropped" in t}
    campaigns = []
    for d, n, w in zip(described, counts, weights):
        entry = {k: v for k, v in d.items() if k != "key"}
        entry["n_samples"] = n
        entry["row_weight"] = float(w)
        if d["key"] in dropped:
            entry["dropped"] = dropped[d["key"]]
        campaigns.append(entry)
    training = {"campaigns": campaigns, "n_samples": int(acc.n_obs)}
    return acc, training


def fit_paths(model, paths, dask=None):
    """Fit ``model`` on campaign folders and/or datasets, in-process or on a Dask cluster; the
    selection (stepwise, fallbacks) runs on the reduced factor. Returns the fitted model."""
    acc, training = accumulate_paths(model, paths, dask=dask)
    return model.fit_factor(acc, training=training)
