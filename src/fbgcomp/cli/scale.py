"""The Parquet dataset command: ``fbgcomp ingest`` (mounted by :mod:`fbgcomp.cli.app`).

The dataset module (pyarrow) is imported inside the command so that ``fbgcomp --help`` starts
fast.
"""

from __future__ import annotations

from pathlib import Path

import typer

from fbgcomp.errors import InputError


def any_dataset(paths) -> bool:
    """Whether any of the ``fbgcomp fit`` arguments is a dataset rather than a campaign folder."""
    from fbgcomp.io.dataset import is_dataset

    return any(is_dataset(p) for p in paths)


def ingest(
    sources: list[Path] = typer.Argument(..., help="Campaign folders or runtime run-log folders."),
    to: Path = typer.Option(..., "--to", help="Dataset folder (created if missing)."),
    machine: str | None = typer.Option(
        None, "--machine", help="Machine name when campaign.yaml has no 'machine' key (default: 'default')."
    ),
    zero_window: float = typer.Option(
        10.0, "--zero-window", help="Zero state stored with each campaign: mean of the first N seconds."
    ),
    rows_per_file: int = typer.Option(
        1_000_000, "--rows-per-file", help="Rows per Parquet file (one file = one distributed task)."
    ),
    reference: Path | None = typer.Option(
        None,
        "--reference",
        help="For a run log: measured TTP deviation CSV (time_s on the "
        "log's clock from its first frame, dx_um, dy_um, dz_um).",
    ),
):
    """Convert campaign folders (and run logs) into one partitioned Parquet dataset."""
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.io.dataset import ingest_campaign, is_run_log
    from fbgcomp.runtime.log import ingest_run_log

    if rows_per_file < 1:
        raise InputError(
            "--rows-per-file must be at least 1", file="<command line>", column="option --rows-per-file"
        )

    def report(part):
        typer.echo(
            f"machine={part.machine} campaign={part.campaign}: {part.n_rows} rows "
            f"in {len(part.files)} file(s) -> {part.path}"
        )

    parts = []
    for src in sources:
        if is_run_log(src):
            part = ingest_run_log(
                src,
                to,
                machine=machine,
                zero_window_s=zero_window,
                rows_per_file=rows_per_file,
                reference_csv=reference,
            )
        else:
            part = ingest_campaign(
                read_campaign(src),
                to,
                machine=machine,
                zero_window_s=zero_window,
                rows_per_file=rows_per_file,
            )
        report(part)
        parts.append(part)
    typer.echo(f"{len(parts)} campaign(s), {sum(p.n_rows for p in parts)} rows ingested into {to}")
