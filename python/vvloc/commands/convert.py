"""``vvloc convert``: turn an NCLT / Oxford RobotCar raw folder (or a vvloc dataset) into a
small vvloc-format dataset of keyframes that every other command reads quickly."""

from __future__ import annotations

import warnings
from enum import Enum
from pathlib import Path
from typing import Annotated, Any

import typer

from vvloc.commands._util import EXIT_USAGE, as_options, cli_errors, named, split_names

#: convert_dataset's arguments and reader options, as the command line spells them.
_OPTION_OF = {
    "sessions": "--sessions",
    "every": "--every",
    "min_distance": "--min_distance",
    "min_angle_deg": "--min_angle",
    "image_size": "--width/--height",
    "cameras": "--cameras",
    "ego_height": "--ego_height",
    "tolerance_us": "--tolerance_us",
}


class SourceFormat(str, Enum):
    """Dataset formats ``vvloc convert`` reads (``vvloc.data.FORMATS``)."""

    auto = "auto"
    vvloc = "vvloc"
    nclt = "nclt"
    oxford = "oxford"


def _fail(message: str) -> None:
    typer.echo(f"vvloc convert: error: {message}", err=True)
    raise typer.Exit(code=EXIT_USAGE)


def convert(
    src: Annotated[Path, typer.Option("--src", help="Dataset folder to read.")],
    out: Annotated[
        Path, typer.Option("--out", help="vvloc dataset to write (must not exist or be empty).")
    ],
    format: Annotated[
        SourceFormat, typer.Option("--format", help="Format of --src (auto: detected).")
    ] = SourceFormat.auto,
    sessions: Annotated[
        str | None,
        typer.Option(
            "--sessions",
            help="Comma-separated sessions to convert (default all); a raw folder's other "
            "sessions are not read (RobotCar's first, which sets the world origin, is).",
        ),
    ] = None,
    every: Annotated[
        int, typer.Option("--every", min=1, help="Keep every n-th frame of a session first.")
    ] = 1,
    min_distance: Annotated[
        float,
        typer.Option(
            "--min_distance",
            min=0.0,
            help=(
                "Then keep a keyframe once the vehicle has moved this far (m, in space) from "
                "the last, and the first on another floor."
            ),
        ),
    ] = 0.0,
    min_angle: Annotated[
        float,
        typer.Option(
            "--min_angle", min=0.0, help="... or turned this far (degrees) from the last."
        ),
    ] = 0.0,
    width: Annotated[
        int | None,
        typer.Option(
            "--width", min=1, help="Image width, pixels (with --height; default: the source's)."
        ),
    ] = None,
    height: Annotated[
        int | None,
        typer.Option(
            "--height", min=1, help="Image height, pixels (with --width; default: the source's)."
        ),
    ] = None,
    cameras: Annotated[
        str | None,
        typer.Option(
            "--cameras",
            help="Comma-separated cameras in image order (NCLT: 1-5, e.g. 1,2,3,4,5; RobotCar: "
            "stereo_centre,mono_left,mono_rear,mono_right; a vvloc dataset: names of its "
            "rig.json cameras, to keep some). Default: the reader's, or all.",
        ),
    ] = None,
    ego_height: Annotated[
        float | None,
        typer.Option(
            "--ego_height",
            help="NCLT / RobotCar: height of the dataset's vehicle-frame origin above the "
            "ground (m), where vvloc's ego origin goes (default 0: kept).",
        ),
    ] = None,
    tolerance_us: Annotated[
        int | None,
        typer.Option(
            "--tolerance_us",
            min=0,
            help="NCLT / RobotCar: largest time gap (microseconds) joined between an image and "
            "its ground truth or INS row, and between RobotCar's cameras (default 50000).",
        ),
    ] = None,
    level: Annotated[
        bool | None,
        typer.Option(
            "--level/--no_level",
            help="NCLT / RobotCar: make each frame's ego frame level, the vehicle's roll and "
            "pitch going into that frame's extrinsics (default: level; --no_level keeps the "
            "tilting vehicle frame).",
        ),
    ] = None,
    motion_compensation: Annotated[
        bool | None,
        typer.Option(
            "--motion_compensation/--no_motion_compensation",
            help="RobotCar: place each camera where it was at its own exposure (default: on).",
        ),
    ] = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace an existing --out.")
    ] = False,
) -> None:
    """Convert a dataset into the vvloc format: keyframes, resized images, poses in vvloc's
    frames (docs/dataset-format.md). Convert a public dataset once, then train, map and
    evaluate on the result."""
    from vvloc.data import convert_dataset, detect_format
    from vvloc.data.vvloc_format import DatasetFormatError, check_dataset_target

    if (width is None) != (height is None):
        _fail("--width and --height go together")
    with cli_errors("convert"):
        with named("--src", FileNotFoundError, NotADirectoryError, DatasetFormatError):
            fmt = detect_format(src, format.value)
        chosen = (
            None if sessions is None else split_names(sessions, "--sessions", what="session name")
        )
        options = _reader_options(
            fmt,
            cameras=cameras,
            ego_height=ego_height,
            tolerance_us=tolerance_us,
            level=level,
            motion_compensation=motion_compensation,
        )
        if fmt != "vvloc" and "ego_height" not in options:
            check_dataset_target(out, overwrite)  # a refused command says one line, no warning
            # the default keeps the dataset's origin, which sits above the ground, where vvloc's
            # BEV plane lies: the cameras come out too low and Frame.z too high
            frame = "NCLT's body frame" if fmt == "nclt" else "RobotCar's vehicle frame (roof)"
            warnings.warn(
                f"--ego_height not given: the ego origin stays at {frame}, above the ground; "
                "vvloc's ego origin (the BEV plane) is the ground under the vehicle: give the "
                "height of that frame above the ground in metres (docs/dataset-format.md, 'The "
                "ego origin')",
                UserWarning,
                stacklevel=2,
            )
        with as_options(_OPTION_OF):
            path = convert_dataset(
                src,
                out,
                format=fmt,
                sessions=chosen,
                every=every,
                min_distance=min_distance,
                min_angle_deg=min_angle,
                image_size=(width, height) if width is not None and height is not None else None,
                overwrite=overwrite,
                progress=True,
                **options,
            )
    typer.echo(f"wrote {path}")
    _say_left_out(path)


def _reader_options(fmt: str, **given: Any) -> dict[str, Any]:
    """The reader options of a ``fmt`` source (``vvloc.data.FORMATS``) from the command's
    options ``given`` (None: not given); ``--cameras`` split at commas (NCLT's as ints). An
    option the source's reader does not take fails the command naming it."""
    options: dict[str, Any] = {}
    if given["cameras"] is not None:
        names = split_names(given["cameras"], "--cameras", what="camera")
        if fmt == "nclt":
            if not all(n.isdigit() for n in names):
                _fail(f"--cameras: NCLT cameras are numbers 1-5, got {given['cameras']!r}")
            options["cameras"] = [int(n) for n in names]
        else:  # RobotCar's names, or a vvloc rig's
            options["cameras"] = names
    raw_only = {
        "ego_height": "--ego_height",
        "tolerance_us": "--tolerance_us",
        "level": "--level/--no_level",
    }
    for key, flag in raw_only.items():
        if given[key] is not None:
            if fmt == "vvloc":
                _fail(f"{flag} applies to NCLT and RobotCar sources only")
            options[key] = given[key]
    if given["motion_compensation"] is not None:
        if fmt != "oxford":
            _fail("--motion_compensation applies to RobotCar sources only")
        options["motion_compensation"] = given["motion_compensation"]
    return options


def _say_left_out(path: Path) -> None:
    """One line per converted session whose reader left frames out, with the reasons."""
    from vvloc.data import open_dataset

    frames = open_dataset(path, format="vvloc").meta["converted_from"]["source_frames"]
    for name, counts in frames.items():
        left_out = counts["left_out"]
        if left_out:
            total = sum(left_out.values())
            reasons = "; ".join(f"{n}: {why}" for why, n in left_out.items())
            typer.echo(
                f"{name}: the reader left out {total} of {counts['read'] + total} frames "
                f"({reasons})"
            )
