"""``vvloc loops``: detect loop closures in a map and export CSV + g2o + TUM."""

from __future__ import annotations

import hashlib
import math
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from vvloc.checkpoints import checkpoint_folder
from vvloc.commands._util import (
    CostThreshold,
    Threads,
    check_out_folder,
    cli_errors,
    named,
    parse_device,
    set_torch_threads,
)

if TYPE_CHECKING:  # imported where used: the CLI loads no torch before a command runs
    from vvloc.localize.export import LoopClosures
    from vvloc.localize.mapdb import MapDatabase

#: The most characters of a session name that go into its trajectory's file name: longer
#: ones are cut and end in a hash of the whole name (file names hold 255 bytes, and the
#: temporary file written first adds about 20).
MAX_SESSION_IN_NAME = 120


def trajectory_file_names(sessions: Sequence[str]) -> dict[str, str]:
    """File name ``trajectory_<session>.tum`` of each map session, safe on every file system.

    A session name is used as it is when it holds only letters, digits, ``.``, ``_`` and
    ``-`` (the usual case: ``s0``, ``2012-01-08``); other characters (``/``, spaces, ...)
    become ``_``, a name longer than :data:`MAX_SESSION_IN_NAME` is cut and ends in 12 hex
    digits of its SHA-256, and a name that would then repeat another's gets ``-2``, ``-3``,
    ... so that no session's file overwrites another's. The TUM file's header names its
    session.
    """
    names: dict[str, str] = {}
    taken: set[str] = set()
    for session in sessions:
        safe = re.sub(r"[^A-Za-z0-9._-]", "_", session)
        if len(safe) > MAX_SESSION_IN_NAME:  # file names hold 255 bytes, temporaries more
            digest = hashlib.sha256(session.encode()).hexdigest()[:12]
            safe = f"{safe[: MAX_SESSION_IN_NAME - 13]}-{digest}"
        stem = "trajectory_" + safe
        file_name, k = f"{stem}.tum", 1
        while file_name.lower() in taken:  # case-insensitive file systems too
            k += 1
            file_name = f"{stem}-{k}.tum"
        taken.add(file_name.lower())
        names[session] = file_name
    return names


def keyframe_digests(db: MapDatabase) -> list[str]:
    """16 hex digits of the SHA-256 of each map keyframe's local-view descriptors (as read
    back: float32), in map row order: ``--reuse`` matches a keyframe of an earlier run only when
    its descriptors are the same (a map rebuilt from other images, extrinsics or with
    ``--float16`` has other ones)."""
    import numpy as np

    out = []
    for start in range(0, len(db), 256):
        rows = np.arange(start, min(start + 256, len(db)))
        for block in np.ascontiguousarray(db.local_descriptors(rows), dtype=np.float32):
            out.append(hashlib.sha256(block.tobytes()).hexdigest()[:16])
    return out


def reusable_loops(
    out: Path, provenance: Sequence[str], db: MapDatabase, digests: Sequence[str]
) -> tuple[LoopClosures | None, str]:
    """The loop closures an earlier ``vvloc loops`` run wrote into ``out``, in the ids of map
    ``db``: its ``loops.csv`` pairs whose two keyframes this map holds too, matched through its
    ``keyframes.csv`` by session, sequence number, timestamp and descriptor digest
    (``digests``, :func:`keyframe_digests` of ``db``; a map built again with more or reordered
    sessions numbers its keyframes anew). A pair this map orders the other way round (two
    sessions listed in the other order) is left out: its search pads the other keyframe.
    Returns (LoopClosures or None, a line to print). ``ValueError`` when that run used another
    model or search settings than ``provenance`` (this run's
    :func:`~vvloc.localize.loops.loop_provenance`), or wrote no record of them (a vvloc before
    2026-12-06)."""
    import numpy as np

    from vvloc.localize.export import (
        _KEYFRAME_COLUMNS,
        LoopClosures,
        _csv_table,
        read_keyframe_csv,
        read_loop_csv,
    )

    csv_path, kf_path = out / "loops.csv", out / "keyframes.csv"
    missing = [p.name for p in (csv_path, kf_path) if not p.is_file()]
    if missing:
        return None, f"--reuse: no {' or '.join(missing)} in {out}: every pair searched"
    before = read_loop_csv(csv_path)  # ValueError naming the file and line when malformed
    if set(before.provenance) != set(provenance):
        raise ValueError(
            f"--reuse: {csv_path} was written with another model or search settings than "
            "these (or by a vvloc before 2026-12-06, which did not record them); run without "
            "--reuse"
        )
    kf = read_keyframe_csv(kf_path)  # ValueError naming the file and line when malformed
    with open(kf_path, encoding="utf-8") as f:
        header = next((line for line in f if line.strip() and not line.startswith("#")), "")
    if "descriptor_sha256" not in header.strip().split(","):
        raise ValueError(
            f"--reuse: {kf_path} has no descriptor_sha256 column (a vvloc before 2026-12-06); "
            "run without --reuse"
        )
    columns = (*_KEYFRAME_COLUMNS, "descriptor_sha256")
    digest_col = [
        fields[at["descriptor_sha256"]]
        for _, fields, at in _csv_table(kf_path, columns, columns, "keyframe")
    ]
    key_of = {
        i: (s, q, t, d)
        for i, s, q, t, d in zip(
            kf.ids.tolist(),
            kf.sessions,
            kf.seq.tolist(),
            kf.timestamps_us.tolist(),
            digest_col,
            strict=True,
        )
    }
    times = np.round(np.asarray(db.timestamps) * 1e6).astype(np.int64).tolist()
    keys = [(db.session_of(r), int(db.seq[r]), t, digests[r]) for r, t in enumerate(times)]
    row_of = {key: r for r, key in enumerate(keys)}
    ids = np.asarray(db.ids).tolist()
    keep, i_new, j_new, reversed_ = [], [], [], 0
    for k, (i, j) in enumerate(zip(before.i.tolist(), before.j.tolist(), strict=True)):
        a, b = row_of.get(key_of.get(i)), row_of.get(key_of.get(j))  # type: ignore[arg-type]
        if a is None or b is None:
            continue
        if a > b:  # candidates are ordered by map row: this pair is (b, a) here
            reversed_ += 1
            continue
        keep.append(k)
        i_new.append(ids[a])
        j_new.append(ids[b])
    rows = np.asarray(keep, dtype=np.int64)
    loops = LoopClosures(
        np.asarray(i_new, dtype=np.int64),
        np.asarray(j_new, dtype=np.int64),
        before.relative_poses[rows].reshape(-1, 3),
        before.costs[rows],
        np.asarray(before.accepted)[rows],
        before.provenance,
    )
    line = f"--reuse: the earlier run in {out} searched {len(keep)} pairs of this map's keyframes"
    if reversed_:
        line += f" ({reversed_} more ordered the other way round here: searched again)"
    return loops, line


def _written_by_loops(path: Path) -> bool:
    """Whether ``path`` is a trajectory file ``vvloc loops`` wrote (its header says so)."""
    try:
        with open(path, encoding="utf-8") as f:
            head = [f.readline() for _ in range(16)]
    except (OSError, UnicodeDecodeError):
        return False
    return head[0].startswith("# vvloc trajectory") and any(
        line.startswith("# map session ") for line in head
    )


def _starts_with(path: Path, head: str) -> bool:
    try:
        with open(path, encoding="utf-8") as f:
            return f.readline().startswith(head)
    except (OSError, UnicodeDecodeError):
        return False


def check_loops_folder(out: Path, trajectory_files: Iterable[str]) -> None:
    """``FileExistsError`` (``--out``) when ``out`` holds a file this run would write
    (``loops.csv``, ``graph.g2o``, ``keyframes.csv``, its ``trajectory_*.tum``) that no earlier
    ``vvloc loops`` wrote: an earlier run's ``loops.csv`` starts with its header (and vouches
    for the ``graph.g2o`` beside it, which g2o readers allow no header in), its
    ``keyframes.csv`` and trajectories with theirs. A user's files are never replaced. (An
    ``out`` inside a vvloc dataset is refused before, by ``check_out_folder``: the map does
    not say which dataset built it.)"""
    if not out.is_dir():
        return
    ours = _starts_with(out / "loops.csv", "# vvloc loop closures")
    clash = [name for name in ("loops.csv", "graph.g2o") if (out / name).exists() and not ours]
    if (out / "keyframes.csv").exists() and not _starts_with(
        out / "keyframes.csv", "# vvloc keyframes"
    ):
        clash.append("keyframes.csv")
    clash += [
        name
        for name in trajectory_files
        if (out / name).exists() and not _written_by_loops(out / name)
    ]
    if clash:
        raise FileExistsError(
            f"--out: {out} holds {', '.join(clash)}, which no earlier vvloc loops wrote; its "
            "outputs would replace them: choose another folder"
        )


def _stat(path: Path) -> os.stat_result | None:
    try:
        return path.stat()
    except OSError:
        return None


def remove_stale_trajectories(out: Path, keep: Iterable[str]) -> list[Path]:
    """Delete the ``trajectory_*.tum`` files of an earlier ``vvloc loops`` run into ``out``
    that this run does not write (sessions of another map), so that the folder holds one
    run's trajectories only. Files without that run's header are left alone. Returns the
    deleted paths."""
    keep = set(keep)
    # on a case-insensitive file system a kept file may be listed under an earlier run's
    # spelling (trajectory_S0.tum for trajectory_s0.tum): the same file, compared by inode
    kept = {(st.st_dev, st.st_ino) for st in (_stat(out / k) for k in keep) if st is not None}

    def is_kept(p: Path) -> bool:
        st = _stat(p)
        return p.name in keep or (st is not None and (st.st_dev, st.st_ino) in kept)

    stale = [
        p
        for p in sorted(out.glob("trajectory_*.tum"))
        if not is_kept(p) and p.is_file() and _written_by_loops(p)
    ]
    for p in stale:
        p.unlink()
    return stale


def _a_radius(value: float) -> float:
    # said before the map and the model load; NaN would pass typer's max=2 (NaN > 2 is false)
    if not (math.isfinite(value) and 0.0 < value <= 2.0):
        raise typer.BadParameter(f"expected a descriptor distance in (0, 2], got {value}")
    return value


def loops(
    map_path: Annotated[Path, typer.Option("--map", help="Map file (.h5) with BEVs.")],
    out: Annotated[Path, typer.Option("--out", help="Output folder.")],
    checkpoint: Annotated[
        Path,
        typer.Option(
            "--checkpoint", help="The model (run or checkpoint folder) that built the map."
        ),
    ],
    radius: Annotated[
        float,
        typer.Option(
            "--radius",
            callback=_a_radius,
            help="Global-descriptor L2 distance below which a pair is a candidate (unit-norm "
            "descriptors: distances lie in [0, 2]; every candidate is verified metrically).",
        ),
    ] = 0.1,
    window: Annotated[
        int,
        typer.Option(
            "--window", min=0, help="Exclude same-session pairs within this many keyframes."
        ),
    ] = 10,
    sequence: Annotated[
        int,
        typer.Option(
            "--sequence",
            min=0,
            help="Half-window L: the ±L neighbouring keyframe pairs must match too (0: off).",
        ),
    ] = 1,
    check_floors: Annotated[
        bool,
        typer.Option(
            "--check_floors/--no_check_floors",
            help="Keep only loops that agree with the floors of the map's sessions "
            "(each session's own floor numbers; a vote per session pair).",
        ),
    ] = True,
    threshold: CostThreshold = 0.75,
    max_pairs: Annotated[
        int,
        typer.Option(
            "--max_pairs",
            min=0,
            help="Closest candidates to verify (0: all). Each is a metric search (0.26 s for the "
            "small model on 2 CPU cores): a model that tells places apart poorly can give "
            "thousands.",
        ),
    ] = 0,
    max_per_keyframe: Annotated[
        int,
        typer.Option(
            "--max_per_keyframe",
            min=0,
            help="Verify only the candidates among the N closest (in descriptor space) of "
            "either of their keyframes (0: all; applied before --max_pairs): with many sessions "
            "revisiting the same places the candidates grow about as the square of the "
            "sessions, this bounds them by the keyframes.",
        ),
    ] = 0,
    device: Annotated[str, typer.Option("--device", help="cpu, cuda[:N] or auto.")] = "cpu",
    threads: Threads = None,
    reuse: Annotated[
        bool,
        typer.Option(
            "--reuse",
            help="Keep the poses and costs of the pairs an earlier run wrote into --out (its "
            "loops.csv and keyframes.csv; the same model, refused otherwise; keyframes matched "
            "by session, sequence number, timestamp and descriptors) and search only the new "
            "pairs: for a map built again with more sessions.",
        ),
    ] = False,
) -> None:
    """Write loops.csv, graph.g2o, keyframes.csv (each vertex id's session, sequence number,
    timestamp and floor) and one TUM trajectory per session into --out, as one change
    (a failed or stopped run leaves an earlier run's files as they were); the trajectories an
    earlier run left there for sessions this map lacks are then removed."""
    import numpy as np

    from vvloc._io import made_folders, write_together
    from vvloc.localize.export import G2O_MAX_ID
    from vvloc.localize.loops import detect_loops, loop_provenance
    from vvloc.localize.mapdb import MapDatabase, MapError
    from vvloc.nets import VVLocNet

    with cli_errors("loops"):
        set_torch_threads(threads)
        check_out_folder(out, own=True)
        model = VVLocNet.load(checkpoint_folder(checkpoint, "--checkpoint")).to(
            parse_device(device)
        )
        # detect_loops checks the weights fingerprint (once, so an old map warns once)
        with named("--map", MapError, FileNotFoundError):
            db = MapDatabase.open(map_path, expected_config_hash=model.config_hash())
        trajectories = trajectory_file_names(db.sessions)
        check_loops_folder(out, trajectories.values())  # before the long detection
        ids = np.asarray(db.ids)
        if len(ids) and (ids.min() < 0 or ids.max() > G2O_MAX_ID):  # before the long detection
            raise ValueError(
                f"{map_path}: keyframe ids {int(ids.min())}..{int(ids.max())} do not fit g2o's "
                f"vertex ids [0, {G2O_MAX_ID}] (vvloc map build numbers them 0..N-1)"
            )
        digests = keyframe_digests(db)
        previous = None
        if reuse:  # the weights are hashed anew, not taken from the checkpoint's record
            previous, line = reusable_loops(out, loop_provenance(model), db, digests)
            typer.echo(line)
        found = detect_loops(
            model,
            db,
            radius=radius,
            window=window,
            sequence=sequence,
            check_floors=check_floors,
            cost_threshold=threshold,
            max_pairs=max_pairs or None,
            max_per_keyframe=max_per_keyframe or None,
            previous=previous,
        )
        if previous is not None:
            known = set(zip(previous.i.tolist(), previous.j.tolist(), strict=True))
            kept = sum(p in known for p in zip(found.i.tolist(), found.j.tolist(), strict=True))
            typer.echo(f"--reuse: {kept} of {len(found)} pairs kept, {len(found) - kept} searched")
        files = _output_files(db, found, map_path, digests, trajectories)
        with made_folders(out):  # those made here are removed again if the write fails
            write_together(out, {name: text.encode() for name, text in files.items()})
        remove_stale_trajectories(out, trajectories.values())
        n_acc = int(np.sum(found.accepted))
    typer.echo(f"{len(found.i)} candidates, {n_acc} accepted loop closures; outputs in {out}")


def _output_files(
    db: MapDatabase,
    found: LoopClosures,
    map_path: Path,
    digests: Sequence[str],
    trajectories: dict[str, str],
) -> dict[str, str]:
    """The texts ``vvloc loops`` writes, by file name: ``loops.csv`` (with its provenance:
    model, search), ``graph.g2o``, ``keyframes.csv`` (with each keyframe's descriptor digest,
    which ``--reuse`` matches) and each map session's TUM trajectory of keyframe poses under
    its name in ``trajectories`` (:func:`trajectory_file_names`)."""
    from vvloc.localize.export import g2o_text, keyframe_csv_text, loop_csv_text, tum_text

    sessions = [db.session_of(i) for i in range(len(db))]
    files = {
        "loops.csv": loop_csv_text(found),
        "graph.g2o": g2o_text(db.poses, found, ids=db.ids, sessions=sessions, seq=db.seq),
        "keyframes.csv": keyframe_csv_text(
            db.ids,
            sessions,
            db.seq,
            db.timestamps,
            db.floors,
            db.poses,
            comments=[f"map {map_path}"],
            digests=digests,
        ),
    }
    for name, file_name in trajectories.items():
        rows = db.session_rows(name)
        files[file_name] = tum_text(
            db.timestamps[rows],
            db.poses[rows],
            comments=[f"map session {name!r} of {map_path}: its keyframes' poses"],
        )
    return files
