"""``vvloc localize``: localize every frame of a session against a map."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer

from vvloc.checkpoints import checkpoint_folder
from vvloc.commands._util import (
    CostThreshold,
    MetricCandidates,
    MetricFrom,
    MetricFromChoice,
    RetrievalWeight,
    Snap,
    Threads,
    check_out_folder,
    check_sessions,
    cli_errors,
    named,
    parse_device,
    set_torch_threads,
)
from vvloc.localize.metric import METRIC_CANDIDATES, RETRIEVAL_WEIGHT

if TYPE_CHECKING:
    from vvloc.data import Frame
    from vvloc.localize.localizer import LocalizationResult
    from vvloc.localize.mapdb import MapDatabase

#: The matching cost below which a query answered by the map keyframe of its own session and
#: timestamp found itself: the same images gave 0, the same poses in another scene 0.018 and
#: more (the pillar-marked garage's s1 against a map of the default garage's: median 0.12).
SELF_MATCH_COST = 1e-3

#: How localize's queries.csv starts: an earlier localize's outputs are the ones it replaces.
MARKER = "# vvloc localize."
HEADER = (
    f"{MARKER} timestamp: seconds. Frames (DESIGN.md §3): world x east, y north, z up "
    "(m); yaw CCW "
    "(deg in this file). relative_* = the query frame expressed in the map keyframe's frame "
    "(x forward, y left). cost = matching cost, lower is better; distinctiveness = mean minus "
    "minimum of the re-ranking costs, higher is more confident; accepted = cost < threshold and "
    "distinctiveness >= min_distinctiveness (the model's calibration, or --min_distinctiveness). "
    "map_row = the reported keyframe (snapped: the retrieved one nearest the metric pose); "
    "metric_row = the keyframe the pose was estimated against; map_floor = map_row's floor, as "
    "its session numbers them (the query's storey when the answer is right); has_content = 0 for "
    "a frame whose every camera's picture is flat (a covered rig, a black stretch: never "
    "accepted); map_seq = map_row's sequence number in its session map_session (for a map of "
    "vvloc map build its frame index there; map_id counts the map's rows)."
)


#: The files ``vvloc localize`` writes into its --out.
OUTPUTS = ("poses.tum", "poses-all.tum", "queries.csv", "timings.json")


def _check_localize_folder(out: Path) -> None:
    """``FileExistsError`` when ``out`` holds files named as localize's outputs that an earlier
    ``vvloc localize`` did not write (its ``queries.csv`` starts with :data:`MARKER`): a
    ``vvloc eval`` report's ``queries.csv``, or a user's files, are never replaced."""
    if not out.is_dir():
        return
    try:
        with open(out / "queries.csv", encoding="utf-8") as f:
            ours = f.readline().startswith(MARKER)
    except (OSError, UnicodeDecodeError):
        ours = False
    clash = [name for name in OUTPUTS if (out / name).exists()]
    if clash and not ours:
        raise FileExistsError(
            f"--out: {out} holds {', '.join(clash)}, which no earlier vvloc localize wrote; "
            "its outputs would replace them: choose another folder"
        )


def _warn_if_found_themselves(
    db: MapDatabase, session: str, frames: Sequence[Frame], results: Sequence[LocalizationResult]
) -> None:
    """A ``UserWarning`` when frames of ``--session`` found themselves in the map: their pose
    was estimated against the map's keyframe of the same session name and timestamp (to the
    microsecond) at a cost near 0 (below :data:`SELF_MATCH_COST`). Such a run says nothing of
    how the map localizes (``vvloc eval`` refuses the map session among its queries). The name
    and time alone do not tell: synthetic worlds share both across scenes (a garage and its
    pillar-marked copy drive the same poses at the same times), and such a run is a fair test."""
    import warnings

    if session not in db.sessions:
        return
    stamps = np.round(np.asarray(db.timestamps) * 1e6).astype(np.int64)
    same = sum(
        0 <= r.metric_row < len(db)
        and r.cost < SELF_MATCH_COST
        and db.session_of(r.metric_row) == session
        and int(stamps[r.metric_row]) == round(f.t * 1e6)
        for f, r in zip(frames, results, strict=True)
    )
    if same:
        warnings.warn(
            f"--session {session}: {same} of {len(frames)} frames found themselves in the map "
            f"(its keyframe of session {session!r} at the same timestamp, cost below "
            f"{SELF_MATCH_COST:g}): this says nothing of how the map localizes; query a session "
            "the map does not hold",
            UserWarning,
            stacklevel=2,
        )


def localize(
    map_path: Annotated[Path, typer.Option("--map", help="Map file (.h5).")],
    dataset: Annotated[Path, typer.Option("--dataset", help="Dataset folder.")],
    session: Annotated[str, typer.Option("--session", help="Query session.")],
    out: Annotated[Path, typer.Option("--out", help="Output folder.")],
    checkpoint: Annotated[
        Path,
        typer.Option(
            "--checkpoint", help="The model (run or checkpoint folder) that built the map."
        ),
    ],
    top_k: Annotated[int, typer.Option("--top_k", min=1, help="Retrieved candidates.")] = 20,
    threshold: CostThreshold = 0.75,
    min_distinctiveness: Annotated[
        float | None,
        typer.Option(
            "--min_distinctiveness",
            min=0.0,
            help="Accept distinctiveness at or above (default: the model's calibration, else 0).",
        ),
    ] = None,
    metric_candidates: MetricCandidates = METRIC_CANDIDATES,
    metric_from: MetricFrom = MetricFromChoice.retrieval,
    retrieval_weight: RetrievalWeight = RETRIEVAL_WEIGHT,
    snap: Snap = True,
    device: Annotated[str, typer.Option("--device", help="cpu, cuda[:N] or auto.")] = "cpu",
    threads: Threads = None,
) -> None:
    """Write poses.tum (the accepted global poses), poses-all.tum (every frame's), queries.csv
    and timings.json into --out, as one change (a failed or stopped run leaves an earlier
    run's four files as they were)."""
    import json

    from vvloc._io import csv_row, write_together
    from vvloc.localize.export import tum_text
    from vvloc.localize.localizer import Localizer
    from vvloc.localize.mapdb import MapError

    with cli_errors("localize"):
        set_torch_threads(threads)
        check_out_folder(out, outside=dataset, own=True)
        _check_localize_folder(out)
        ds = check_sessions(dataset, [("--session", session)])
        sess = ds.session(session)
        ckpt = checkpoint_folder(checkpoint, "--checkpoint")
        with named("--map", MapError, FileNotFoundError):
            loc = Localizer.open(
                map_path,
                ckpt,
                device=parse_device(device),
                top_k=top_k,
                accept_threshold=threshold,
                min_distinctiveness=min_distinctiveness,
                metric_candidates=metric_candidates,
                metric_from=metric_from.value,
                retrieval_weight=retrieval_weight,
                snap=snap,
            )
        loc.model.config.check_num_cameras(len(ds.cameras), f"--dataset: {dataset}")  # up front
        frames = list(sess)
        if frames:  # a rig other than the map's is said of the session, not of frames[0]
            loc._check_rig(frames[0], f"--session {session} of --dataset {dataset}")
        results = loc.localize_batch(frames, progress=True)
        _warn_if_found_themselves(loc.map, session, frames, results)
        out.mkdir(parents=True, exist_ok=True)
        poses = np.stack([r.global_pose for r in results])
        stamps = np.array([f.t for f in frames])
        ok = np.array([r.accepted for r in results], dtype=bool)
        tum_header = [
            f"vvloc localize: global poses of session {session} of {dataset}, localized in the "
            f"map {map_path}",
            "pose = the map keyframe's pose composed with the estimated relative pose; accepted "
            "= cost < threshold and distinctiveness >= the model's calibration "
            "(or --min_distinctiveness)",
        ]
        accepted_tum = tum_text(
            stamps[ok],
            poses[ok],
            comments=[
                *tum_header,
                f"accepted localizations only: {int(ok.sum())} of {len(frames)} frames "
                "(every frame: poses-all.tum and queries.csv)",
            ],
        )
        all_tum = tum_text(
            stamps,
            poses,
            comments=[
                *tum_header,
                f"every frame, accepted or not ({int(ok.sum())} of {len(frames)} accepted: "
                "poses.tum; queries.csv has the accepted column)",
            ],
        )
        lines = [
            HEADER,
            "index,timestamp,map_row,map_id,map_session,relative_x,relative_y,"
            "relative_yaw_deg,global_x,global_y,global_yaw_deg,cost,distinctiveness,accepted,"
            "metric_row,map_floor,has_content,map_seq",
        ]
        for f, r in zip(frames, results, strict=True):
            rel, g = r.relative_pose, r.global_pose
            lines.append(  # a session name with a comma is quoted (RFC 4180)
                csv_row(
                    f.index,
                    f"{f.t:.6f}",
                    r.map_row,
                    r.map_id,
                    r.map_session,
                    f"{rel[0]:.4f}",
                    f"{rel[1]:.4f}",
                    f"{np.degrees(rel[2]):.3f}",
                    f"{g[0]:.4f}",
                    f"{g[1]:.4f}",
                    f"{np.degrees(g[2]):.3f}",
                    f"{r.cost:.5f}",
                    f"{r.distinctiveness:.5f}",
                    int(r.accepted),
                    r.metric_row,
                    r.map_floor,
                    int(r.has_content),
                    r.map_seq,
                )
            )
        stages = ("encode", "retrieve", "rerank", "metric")
        timings = {s: float(np.median([r.timings_ms[s] for r in results])) for s in stages}
        write_together(
            out,
            {
                "poses.tum": accepted_tum.encode(),
                "poses-all.tum": all_tum.encode(),
                "queries.csv": ("\n".join(lines) + "\n").encode(),
                "timings.json": json.dumps({"median_ms": timings}, indent=2).encode(),
            },
        )
    acc = np.mean([r.accepted for r in results])
    typer.echo(f"localized {len(results)} frames ({acc:.0%} accepted); outputs in {out}")
    typer.echo("median ms per stage: " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
