"""``vvloc map build``: encode sessions with a model into an HDF5 map."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from vvloc.checkpoints import resolve_checkpoint
from vvloc.commands._util import cli_errors, parse_device, split_names

map_app = typer.Typer(help="Build map databases.", no_args_is_help=True)


@map_app.command("build")
def build(
    checkpoint: Annotated[Path, typer.Option("--checkpoint", help="Checkpoint or run folder.")],
    dataset: Annotated[Path, typer.Option("--dataset", help="Dataset folder.")],
    sessions: Annotated[str, typer.Option("--sessions", help="Sessions, comma-separated.")],
    out: Annotated[Path, typer.Option("--out", help="Map file (.h5), written atomically.")],
    float16: Annotated[
        bool, typer.Option("--float16", help="Store descriptors as float16.")
    ] = False,
    no_bev: Annotated[
        bool, typer.Option("--no_bev", help="Do not store BEVs (then no loop detection).")
    ] = False,
    device: Annotated[str, typer.Option("--device", help="cpu, cuda[:N] or auto.")] = "cpu",
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace an existing map file at --out.")
    ] = False,
) -> None:
    """Build a map (global + local-view descriptors, poses, BEVs) from dataset sessions.

    An existing file at --out is replaced only with --overwrite (then atomically: the old map
    stays whole until the new one is complete)."""

    from vvloc.data import open_dataset
    from vvloc.localize.localizer import build_map
    from vvloc.nets import VVLocNet

    with cli_errors("map build"):
        if out.is_file() and not overwrite:
            raise FileExistsError(f"--out: {out} exists; pass --overwrite to replace it")
        model = VVLocNet.load(resolve_checkpoint(checkpoint)).to(parse_device(device))
        ds = open_dataset(dataset)
        path = build_map(
            model,
            ds,
            split_names(sessions),
            out,
            dtype="float16" if float16 else "float32",
            store_bev=not no_bev,
        )
    typer.echo(f"map: {path}")
