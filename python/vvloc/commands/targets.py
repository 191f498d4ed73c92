"""``vvloc targets``: compare a checkpoint's test reports with the small model's targets."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from vvloc.commands._util import cli_errors, named

#: The keys of the JSON ``vvloc targets --out`` writes: an existing file is replaced only when
#: it holds exactly these (an earlier run's figures), never a report or a user's file.
OUT_KEYS = frozenset({"weights_hash", "figures"})


def check_targets_out(out: Path) -> None:
    """``--out`` of ``vvloc targets``, said before the reports are read: a new path, a stream,
    or a file that an earlier ``vvloc targets`` wrote (it replaced any file, the report it read
    included)."""
    from vvloc._io import _is_stream

    for p in out.parents:  # found before the reports are read, not when writing
        if p.exists():
            if not p.is_dir():
                raise NotADirectoryError(f"--out: {out} lies below {p}, which is a file")
            break
    if not out.exists() or _is_stream(out):
        return
    if out.is_dir():
        raise IsADirectoryError(f"--out: {out} is a folder; expected the path of a .json file")
    try:
        doc = json.loads(out.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        doc = None
    if not (isinstance(doc, dict) and set(doc) == OUT_KEYS):
        raise FileExistsError(
            f"--out: {out} exists and is not a figures file that vvloc targets wrote; it would "
            "be replaced: choose another path"
        )


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
        if out is not None:
            check_targets_out(out)
        reports = {}
        for option, path in (("--parking", parking), ("--pillars", pillars), ("--garage", garage)):
            if path is not None:  # a missing or unreadable report names its option
                with named(option, FileNotFoundError, ValueError):
                    reports[option] = read_report(path)
        park = reports["--parking"]
        figures = check_targets(park, reports.get("--pillars"), reports.get("--garage"))
        weights = park["meta"].get("model_weights_hash")
        if out is not None:
            out.parent.mkdir(parents=True, exist_ok=True)
            with atomic_write(out, "w") as f:
                doc = {"weights_hash": weights, "figures": figures_json(figures)}
                assert set(doc) == OUT_KEYS
                json.dump(doc, f, indent=1)
    typer.echo(targets_markdown(figures, weights), nl=False)
    if strict and any(f.met is False for f in figures):
        raise typer.Exit(code=1)
