"""``vvloc map build``: encode sessions with a model into an HDF5 map; ``vvloc map info``:
what a map holds, and whether every byte of it is intact."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any

import typer

from vvloc._io import made_folders
from vvloc.checkpoints import checkpoint_folder
from vvloc.commands._util import (
    EXIT_USAGE,
    Threads,
    check_sessions,
    cli_errors,
    named,
    parse_device,
    set_torch_threads,
    split_names,
)

map_app = typer.Typer(help="Build and inspect map databases.", no_args_is_help=True)


def _s(n: int) -> str:
    """The plural ending of a count's noun: "" for 1, "s" otherwise."""
    return "" if n == 1 else "s"


def check_map_out(out: Path, *, overwrite: bool, dataset: Path) -> None:
    """``vvloc map build --out``, said before the model loads: a file path in a writable folder
    (made when missing, as other commands make theirs, once every check has passed), outside
    the dataset; an existing file only with ``overwrite``, and then
    only a vvloc map (the README: outputs never replace what vvloc did not write)."""
    from vvloc._io import _is_stream, symlink_loop
    from vvloc.data.sampling import inside_folder
    from vvloc.localize.mapfile import is_map_file

    if out.name in ("", ".", ".."):
        raise ValueError(f"--out: expected the path of a map file (.h5), got {str(out)!r}")
    loop = symlink_loop(out)
    if loop:
        raise FileExistsError(f"--out: {loop}; expected the path of a map file")
    if out.is_dir():
        raise IsADirectoryError(f"--out: {out} is a folder; expected the path of a map file")
    if _is_stream(out):
        raise ValueError(
            f"--out: {out} is not a regular file (a device, pipe or socket); a map is written "
            "to a file"
        )
    if dataset.exists() and inside_folder(out, dataset):
        raise ValueError(
            f"--out: {out} lies inside the dataset {dataset}; write the map outside it"
        )
    parent = Path(os.path.realpath(out)).parent
    existing = parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent  # the folders below it are made before the map is written
    if not existing.is_dir():
        raise NotADirectoryError(f"--out: {existing} is a file, not a folder to write the map in")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(f"--out: the folder {existing} is not writable")
    if out.exists():
        if not overwrite:
            raise FileExistsError(f"--out: {out} exists; pass --overwrite to replace it")
        if not is_map_file(out):
            raise FileExistsError(
                f"--out: {out} exists and is not a vvloc map; --overwrite replaces only a map "
                "(remove the file yourself if it is a damaged one)"
            )


def check_base(base: Path, sessions: list[str], *, float16: bool, no_bev: bool) -> None:
    """``vvloc map build --base``, said before the dataset is read and the model loads: a vvloc
    map that holds none of ``sessions``, whose descriptor dtype and BEVs ``--float16`` and
    ``--no_bev`` (when given) agree with."""
    from vvloc.localize import MapDatabase, MapError

    with (
        named("--base", MapError, FileNotFoundError, IsADirectoryError),
        MapDatabase.open(base) as db,
    ):
        have = db.sessions
        again = [s for s in sessions if s in have]
        stored = db.metadata.descriptor_dtype
        has_bev = db.has_bev
    if again:
        raise ValueError(
            f"--sessions: {', '.join(again)} already in the --base map {base} (sessions: "
            f"{', '.join(have)}); a session is added once"
        )
    if float16 and stored != "float16":
        raise ValueError(
            f"--float16: the --base map {base} stores {stored} descriptors, and one map holds "
            "one dtype; leave --float16 out (the grown map takes the base's)"
        )
    if no_bev and has_bev:
        raise ValueError(
            f"--no_bev: the --base map {base} stores BEVs, and every keyframe of a map has one "
            "or none has; leave --no_bev out (the grown map takes the base's)"
        )


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
    threads: Threads = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace an existing vvloc map at --out.")
    ] = False,
    base: Annotated[
        Path | None,
        typer.Option(
            "--base",
            help="Grow this map: its keyframes as stored (not encoded again), then --sessions'. "
            "Same model and rig; its dtype and BEVs are kept. Read only; --out may name it "
            "(with --overwrite).",
        ),
    ] = None,
) -> None:
    """Build a map (global + local-view descriptors, poses, BEVs) from dataset sessions.

    An existing map at --out is replaced only with --overwrite (then atomically: the old map
    stays whole until the new one is complete); any other file there, and an --out inside the
    dataset, are refused. With --base, the new map holds that map's keyframes first, as it
    stores them, then the frames of --sessions (sessions new to it), numbered on from its
    largest keyframe id."""

    from vvloc.data.sampling import check_session_names
    from vvloc.nets import VVLocNet

    with cli_errors("map build"):
        set_torch_threads(threads)
        check_map_out(out, overwrite=overwrite, dataset=dataset)
        names = split_names(sessions, "--sessions", what="session name")
        if base is not None:  # before the dataset is read and the model loads
            check_base(base, names, float16=float16, no_bev=no_bev)
        # each exists and holds frames (an empty one was left out of the map without a word)
        ds = check_sessions(dataset, [("--sessions", name) for name in names])
        check_session_names("--sessions", ds, names, str(dataset))  # named once each
        model = VVLocNet.load(checkpoint_folder(checkpoint, "--checkpoint")).to(
            parse_device(device)
        )
        with made_folders(Path(os.path.realpath(out)).parent):  # as eval, loops, train do
            path = _build(model, ds, names, out, base, float16, no_bev, overwrite)
    typer.echo(f"map: {path}")


def _build(
    model: Any,
    ds: Any,
    names: list[str],
    out: Path,
    base: Path | None,
    float16: bool,
    no_bev: bool,
    overwrite: bool,
) -> Path:
    """``vvloc map build``'s map, once its arguments have been checked."""
    from vvloc.localize import MapError
    from vvloc.localize.localizer import build_map

    if base is None:
        return build_map(
            model,
            ds,
            names,
            out,
            dtype="float16" if float16 else "float32",
            store_bev=not no_bev,
            overwrite=overwrite,  # a map alone (check_map_out)
        )
    # the base's dtype and BEVs (check_base refused flags that ask for others)
    with named("--base", MapError, FileNotFoundError, IsADirectoryError):
        return build_map(model, ds, names, out, base=base, overwrite=overwrite)


@map_app.command("info")
def info(
    map_path: Annotated[
        Path | None, typer.Argument(help="Map file (.h5); or --map.", metavar="MAP")
    ] = None,
    map_option: Annotated[
        Path | None,
        typer.Option("--map", help="Map file (.h5), as localize and loops take it."),
    ] = None,
    verify: Annotated[
        bool,
        typer.Option(
            "--verify",
            help="Also check the SHA-256 of every dataset, the lazily read local-view "
            "descriptors and BEVs included, and that those are finite (reads the whole file).",
        ),
    ] = False,
) -> None:
    """Print what a map holds: format version, keyframes per session, floors, descriptor
    shapes and dtype, BEVs, the model's config hash and weights fingerprint, the rig.

    Opening checks the map's structure and the SHA-256 of its poses, ids and global
    descriptors; a damaged or foreign file exits 2 with the reason."""
    import numpy as np

    from vvloc.localize import MapDatabase

    if (map_path is None) == (map_option is None):
        typer.echo(
            "vvloc map info: error: give the map once: vvloc map info MAP or --map MAP", err=True
        )
        raise typer.Exit(code=EXIT_USAGE)
    map_path = map_path if map_path is not None else map_option
    assert map_path is not None
    with cli_errors("map info"), MapDatabase.open(map_path) as db:
        if verify:
            db.verify()
        meta = db.metadata
        lines = [
            f"map: {map_path}",
            f"format version {meta.format_version}, written by vvloc {meta.vvloc_version} at "
            f"{meta.created_utc}",
            f"keyframes: {len(db)} in {len(db.sessions)} session{_s(len(db.sessions))}",
        ]
        for s, name in enumerate(db.sessions):
            rows = db.session_index == s
            floors = sorted(int(f) for f in np.unique(db.floors[rows]))
            n = int(rows.sum())
            floor_list = ", ".join(str(f) for f in floors)
            lines.append(f"  {name}: {n} keyframe{_s(n)}, floor{_s(len(floors))} {floor_list}")
        bev = "none (no loop detection)" if db.bev_shape is None else f"{db.bev_shape} float16"
        lines += [
            f"descriptors ({meta.descriptor_dtype}): global ({db.global_dim},), local-view "
            f"{db.local_shape}; BEV {bev}; grid {meta.grid_size:g} m",
            f"model config hash {meta.model_config_hash}",
            f"weights fingerprint {meta.model_weights_hash or '(not recorded)'}",
            "rig: "
            + (
                "(not recorded)"
                if meta.rig is None
                else ", ".join(f"{c['name']} {c['width']}x{c['height']}" for c in meta.rig)
            ),
        ]
        if meta.format_version < 2:
            lines.append(
                "note: format version 1 has no checksums on its HDF5 structures; "
                "MapDatabase.open(old).save(new) rewrites it as version 2"
            )
        lines.append(
            "verified: every dataset's SHA-256"
            if verify
            else "verified on open: ids, poses, global descriptors (--verify: every dataset)"
        )
    typer.echo("\n".join(lines))
