"""``vvloc targets``: compare a checkpoint's test reports with the small model's targets."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from vvloc.commands._util import cli_errors


def targets(
    parking: Annotated[
        Path, typer.Option("--parking", help="Report folder of vvloc eval on the parking test.")
    ],
    pillars: Annotated[
        Path | None,
        typer.Option("--pillars", help="Report folder of vvloc eval --loops, pillar garage."),
    ] = None,
    garage: Annotated[
        Path | None,
        typer.Option("--garage", help="Report folder of vvloc eval --loops, default garage."),
    ] = None,
    out: Annotated[
        Path | None, typer.Option("--out", help="Also write the figures here (.json).")
    ] = None,
    strict: Annotated[
        bool, typer.Option("--strict", help="Exit with status 1 when a figure is missed.")
    ] = False,
) -> None:
    """Print which of the issue's targets (Recall@1, re-ranking gain, AOE/APE, CFER, training
    time; vvloc.targets) the reports of one checkpoint meet, as a Markdown table."""
    from vvloc._io import atomic_write
    from vvloc.targets import check_targets, figures_json, read_report, targets_markdown

    with cli_errors("targets"):
        park = read_report(parking)
        figures = check_targets(
            park,
            None if pillars is None else read_report(pillars),
            None if garage is None else read_report(garage),
        )
        weights = park["meta"].get("model_weights_hash")
        if out is not None:
            out.parent.mkdir(parents=True, exist_ok=True)
            with atomic_write(out, "w") as f:
                json.dump({"weights_hash": weights, "figures": figures_json(figures)}, f, indent=1)
    typer.echo(targets_markdown(figures, weights), nl=False)
    if strict and any(f.met is False for f in figures):
        raise typer.Exit(code=1)
