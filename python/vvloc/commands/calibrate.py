"""``vvloc calibrate``: measure when a checkpoint's localizations can be accepted."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Annotated, Any

import typer

from vvloc.checkpoints import checkpoint_folder
from vvloc.commands._util import (
    EXIT_FAILURE,
    CostThreshold,
    MetricCandidates,
    MetricFrom,
    MetricFromChoice,
    RetrievalWeight,
    Snap,
    Threads,
    check_sessions,
    cli_errors,
    parse_device,
    set_torch_threads,
    split_names,
)
from vvloc.localize.metric import METRIC_CANDIDATES, RETRIEVAL_WEIGHT


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
        typer.Option("--precision", help="Target share of accepted right, in (0, 1]."),
    ] = 0.9,
    min_accepted: Annotated[
        int, typer.Option("--min_accepted", min=1, help="Fewest accepted queries to trust.")
    ] = 10,
    threshold: CostThreshold = 0.75,
    metric_candidates: MetricCandidates = METRIC_CANDIDATES,
    metric_from: MetricFrom = MetricFromChoice.retrieval,
    retrieval_weight: RetrievalWeight = RETRIEVAL_WEIGHT,
    snap: Snap = True,
    device: Annotated[str, typer.Option("--device", help="cpu, cuda[:N] or auto.")] = "cpu",
    threads: Threads = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace the checkpoint's calibration.json.")
    ] = False,
) -> None:
    """Write calibration.json beside the checkpoint's weights: the distinctiveness threshold at
    which the localizer's accepted answers (with these localizer options, which it records) are
    right (reported keyframe within 2 m) at the target precision on the held-out sessions. The
    Localizer (and localize/eval) then accept only those.
    An existing calibration.json is replaced only with --overwrite; when no threshold reaches
    the target, nothing is written and the command fails (exit 1)."""
    import tempfile

    import numpy as np

    from vvloc._io import atomic_write
    from vvloc.data.sampling import check_query_sessions
    from vvloc.localize.calibrate import calibrate_localizer, check_revisits
    from vvloc.localize.evaluation import trained_on
    from vvloc.localize.localizer import Localizer, build_map
    from vvloc.localize.mapdb import MapDatabase
    from vvloc.nets import VVLocNet
    from vvloc.nets.model import CALIBRATION_FILE, calibration_json

    with cli_errors("calibrate"):
        set_torch_threads(threads)
        names = split_names(queries, "--queries", what="session name")
        if not 0.0 < precision <= 1.0:
            raise ValueError(f"--precision: expected a value in (0, 1], got {precision}")
        if threshold == 0:  # found after the map was built and every query localized
            raise ValueError(
                "--threshold: 0 accepts no answer (matching costs are >= 0), so there is nothing "
                "to calibrate; the paper's is 0.75"
            )
        ckpt = checkpoint_folder(checkpoint, "--checkpoint")
        target = ckpt / CALIBRATION_FILE
        if target.exists() and not overwrite:
            raise FileExistsError(
                f"{target} exists (the checkpoint's calibration): pass --overwrite to replace it"
            )
        check_query_sessions(database, names, "--queries")
        ds = check_sessions(dataset, [("--database", database), *(("--queries", n) for n in names)])
        model = VVLocNet.load(ckpt).to(parse_device(device))
        seen = trained_on(model.training_record, dataset, names, opened=ds)
        if seen:  # as vvloc eval says: a threshold measured on them accepts too much elsewhere
            warnings.warn(
                f"--queries {seen} of {dataset} were trained on (the checkpoint's training "
                "record): a threshold measured on them is too lenient for new sessions; "
                "calibrate on held-out sessions",
                UserWarning,
                stacklevel=1,
            )
        # what would fail after the map is built fails before it (from the poses alone)
        check_revisits(  # the queries a calibration is measured on
            np.concatenate([ds.session(n).poses[::every] for n in names]),
            np.concatenate([ds.session(n).floors[::every] for n in names]),
            ds.session(database).poses,
            ds.session(database).floors,
            "--queries",
        )
        frames = [f for name in names for f in ds.session(name)[::every]]  # loads only these
        if min_accepted > len(frames):
            raise ValueError(
                f"--min_accepted: {min_accepted} accepted queries can never be reached with "
                f"{len(frames)} query frames (--queries, --every)"
            )
        with tempfile.TemporaryDirectory(prefix="vvloc-calibrate-") as tmp:
            map_path = build_map(model, ds, [database], Path(tmp) / "map.h5", store_bev=False)
            with MapDatabase.open(map_path, expected_config_hash=model.config_hash()) as db:
                loc = Localizer(
                    model,
                    db,
                    top_k=top_k,
                    accept_threshold=threshold,
                    min_distinctiveness=0.0,  # measure every answer, whatever the old threshold
                    metric_candidates=metric_candidates,
                    metric_from=metric_from.value,
                    retrieval_weight=retrieval_weight,
                    snap=snap,
                )
                kw: dict[str, Any] = {"target_precision": precision, "min_accepted": min_accepted}
                cal = calibrate_localizer(loc, frames, progress=True, **kw)
        cal |= {"dataset": str(dataset), "database": database, "sessions": names, "every": every}
        if not cal["accepted"]:
            why = (
                f"none of the {cal['queries']} queries passes the cost rule (cost < {threshold})"
                if not cal["passing_cost"]
                else f"no threshold reaches precision {precision:.0%} on {min_accepted}+ of "
                f"{cal['passing_cost']} queries that pass the cost rule (all {cal['queries']} "
                f"accepted: {cal['base_precision']:.1%} right)"
            )
            hint = (
                "a higher --threshold"
                if not cal["passing_cost"]
                else "a lower --precision or --min_accepted, more --queries"
            )
            typer.echo(
                f"vvloc calibrate: failed: {why}; "
                + (f"{target} is left as it was" if target.exists() else "nothing was written")
                + f". Try {hint} or a better-trained checkpoint.",
                err=True,
            )
            raise typer.Exit(code=EXIT_FAILURE)
        with atomic_write(target) as f:
            f.write(calibration_json(cal))
    typer.echo(
        f"min_distinctiveness {cal['min_distinctiveness']:.4f}: accepts "
        f"{cal['accepted_share']:.1%} of the {cal['queries']} queries with a map keyframe "
        f"within 2 m (of {len(frames)} localized) at precision {cal['precision']:.1%} (all of "
        f"them: {cal['base_precision']:.1%})"
    )
    typer.echo(f"calibration: {target}")
