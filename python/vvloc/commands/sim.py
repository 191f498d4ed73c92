"""``vvloc sim``: render a synthetic multi-camera dataset in the vvloc format."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from vvloc.commands._util import cli_errors


class Scene(str, Enum):
    """Scenes ``vvloc sim`` can render."""

    parking = "parking"
    garage = "garage"


class FloorMarking(str, Enum):
    """How ``vvloc sim --scene garage`` marks its floors."""

    walls = "walls"
    pillars = "pillars"


def sim(
    out: Annotated[Path, typer.Option("--out", help="Output folder (must not exist or be empty).")],
    scene: Annotated[Scene, typer.Option("--scene", help="World to render.")] = Scene.parking,
    sessions: Annotated[
        int, typer.Option("--sessions", min=1, help="Sessions (s0 maps, the others query).")
    ] = 3,
    frames: Annotated[int, typer.Option("--frames", min=1, help="Keyframes per session.")] = 600,
    floors: Annotated[
        int | None,
        typer.Option(
            "--floors",
            min=1,
            max=16,  # vvloc.sim.simulate.MAX_FLOORS (not imported here: it loads the renderer)
            help="Garage storeys (garage scene only; default 2).",
        ),
    ] = None,
    floor_marking: Annotated[
        FloorMarking | None,
        typer.Option(
            "--floor_marking",
            help="Garage only: level signs on the walls alone (look-alike floors; the default), "
            "or also a level colour and number on every pillar.",
        ),
    ] = None,
    seed: Annotated[
        int, typer.Option("--seed", min=0, help="Seed of the world, the drives' wobble and cars.")
    ] = 0,
    cameras: Annotated[
        int,
        typer.Option(
            "--cameras",
            min=1,
            max=12,
            help="Number of cameras in the rig, 1-12, evenly round the vehicle, front first "
            "(1 or 2 leave gaps between their views; 3 just cover the circle).",
        ),
    ] = 4,
    width: Annotated[int, typer.Option("--width", min=8, help="Image width, pixels.")] = 160,
    height: Annotated[int, typer.Option("--height", min=8, help="Image height, pixels.")] = 96,
    texture_strength: Annotated[
        float,
        typer.Option(
            "--texture_strength", min=0.0, help="Procedural texture amplitude (0 = flat)."
        ),
    ] = 1.0,
    lighting: Annotated[
        str,
        typer.Option(
            "--lighting",
            help="Comma-separated presets cycled over the sessions (default: per scene; "
            "day, dusk, night, rain, fog, garage, garage_dim).",
        ),
    ] = "",
    max_roll: Annotated[
        float,
        typer.Option(
            "--max_roll",
            min=0.0,
            max=30.0,
            help="Tilt the query sessions' vehicle: a roll drawn within +-this many degrees "
            "for each keyframe (written as each frame's own extrinsics, cam_to_ego.csv).",
        ),
    ] = 0.0,
    max_pitch: Annotated[
        float,
        typer.Option(
            "--max_pitch", min=0.0, max=30.0, help="... and a pitch within +-this many degrees."
        ),
    ] = 0.0,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace an existing --out.")
    ] = False,
) -> None:
    """Render a synthetic multi-camera dataset (vvloc format) of a parking lot or a garage."""
    from vvloc.sim import simulate_dataset

    presets = [s.strip() for s in lighting.split(",") if s.strip()] or None
    if scene is not Scene.garage:
        for option, value in (("--floors", floors), ("--floor_marking", floor_marking)):
            if value is not None:
                typer.echo(f"vvloc sim: error: {option} applies to --scene garage only", err=True)
                raise typer.Exit(code=2)
    with cli_errors("sim"):
        path = simulate_dataset(
            out,
            scene=scene.value,
            sessions=sessions,
            frames=frames,
            floors=floors,
            floor_marking=(floor_marking or FloorMarking.walls).value,
            seed=seed,
            cameras=cameras,
            width=width,
            height=height,
            texture_strength=texture_strength,
            lighting=presets,
            max_roll=max_roll,
            max_pitch=max_pitch,
            overwrite=overwrite,
        )
    typer.echo(f"wrote {sessions} sessions x {frames} frames ({cameras} cameras) to {path}")
