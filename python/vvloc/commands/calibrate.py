"""``vvloc calibrate``: measure when a checkpoint's localizations can be accepted."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from vvloc.checkpoints import resolve_checkpoint
from vvloc.commands._util import cli_errors, split_names


def calibrate(
    checkpoint: Annotated[Path, typer.Option("--checkpoint", help="Checkpoint or run folder.")],
    dataset: Annotated[Path, typer.Option("--dataset", help="Dataset folder.")],
    queries: Annotated[
        str,
        typer.Option("--queries", help="Held-out sessions (never trained on), comma-separated."),
    ],
    database: Annotated[str, typer.Option("--database", help="Map session.")] = "s0",
    every: Annotated[int, typer.Option("--every", min=1, help="Use every n-th query.")] = 1,
    top_k: Annotated[int, typer.Option("--top_k", min=1, help="Retrieved candidates.")] = 20,
    precision: Annotated[
        float,
        typer.Option("--precision", min=0.0, max=1.0, help="Target share of accepted right."),
    ] = 0.9,
    min_accepted: Annotated[
        int, typer.Option("--min_accepted", min=1, help="Fewest accepted queries to trust.")
    ] = 10,
    device: Annotated[str, typer.Option("--device", help="cpu or cuda.")] = "cpu",
) -> None:
    """Write calibration.json beside the checkpoint's weights: the distinctiveness threshold at
    which accepted localizations are right (top-1 within 2 m) at the target precision on the
    held-out sessions. The Localizer (and map/localize/eval) then accept only those."""
    import torch

    from vvloc._io import atomic_write
    from vvloc.data import open_dataset
    from vvloc.localize.calibrate import calibrate as run_calibration
    from vvloc.nets import VVLocNet
    from vvloc.nets.model import CALIBRATION_FILE

    with cli_errors("calibrate"):
        names = split_names(queries)
        if not names:
            raise ValueError("--queries: expected at least one session name")
        ckpt = resolve_checkpoint(checkpoint)
        model = VVLocNet.load(ckpt).to(torch.device(device))
        cal = run_calibration(
            model,
            open_dataset(dataset),
            database,
            names,
            every=every,
            top_k=top_k,
            target_precision=precision,
            min_accepted=min_accepted,
        )
        text = json.dumps(cal, indent=2)
        with atomic_write(ckpt / CALIBRATION_FILE) as f:
            f.write(text)
    if cal["accepted"]:
        typer.echo(
            f"min_distinctiveness {cal['min_distinctiveness']:.4f}: accepts "
            f"{cal['accepted_share']:.1%} of {cal['queries']} queries at precision "
            f"{cal['precision']:.1%} (all queries: {cal['base_precision']:.1%})"
        )
    else:
        typer.echo(
            f"no threshold reaches precision {precision:.0%} on {cal['min_accepted']}+ queries "
            f"(all queries: {cal['base_precision']:.1%}): nothing will be accepted"
        )
    typer.echo(f"calibration: {ckpt / CALIBRATION_FILE}")
