"""``vvloc eval``: evaluate a checkpoint (map from one session, queries from others)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from vvloc.checkpoints import checkpoint_folder
from vvloc.commands._util import (
    MetricCandidates,
    MetricFrom,
    MetricFromChoice,
    RetrievalWeight,
    Snap,
    Threads,
    check_out_folder,
    check_sessions,
    cli_errors,
    parse_device,
    set_torch_threads,
    split_names,
)
from vvloc.localize.metric import METRIC_CANDIDATES, RETRIEVAL_WEIGHT


def _a_loop_radius(value: float) -> float:
    # NaN would pass a min/max range (every comparison with it is false)
    if not 0.0 < value <= 0.5:
        raise typer.BadParameter(f"expected a descriptor distance in (0, 0.5], got {value}")
    return value


def eval_command(
    checkpoint: Annotated[Path, typer.Option("--checkpoint", help="Checkpoint or run folder.")],
    dataset: Annotated[Path, typer.Option("--dataset", help="Dataset folder.")],
    database: Annotated[str, typer.Option("--database", help="Map session.")] = "s0",
    queries: Annotated[
        str, typer.Option("--queries", help="Query sessions, comma-separated.")
    ] = "s1",
    out: Annotated[Path, typer.Option("--out", help="Report folder.")] = Path("runs/eval"),
    top_k: Annotated[int, typer.Option("--top_k", min=1, help="Retrieved candidates.")] = 20,
    every: Annotated[int, typer.Option("--every", min=1, help="Use every n-th query.")] = 1,
    device: Annotated[str, typer.Option("--device", help="cpu, cuda[:N] or auto.")] = "cpu",
    threads: Threads = None,
    robustness: Annotated[
        bool,
        typer.Option(
            "--robustness",
            help="Also localize the queries under 5 perturbations (camera masked, blur, "
            "regions masked, under-exposure, noise): the same metrics for each, about 6x the "
            "time.",
        ),
    ] = False,
    metric_candidates: MetricCandidates = METRIC_CANDIDATES,
    metric_from: MetricFrom = MetricFromChoice.retrieval,
    retrieval_weight: RetrievalWeight = RETRIEVAL_WEIGHT,
    snap: Snap = True,
    loops: Annotated[
        bool, typer.Option("--loops", help="Also evaluate loop closure (P/R, CFER, poses).")
    ] = False,
    loop_pairs: Annotated[
        int, typer.Option("--loop_pairs", min=1, help="Detected pairs to verify metrically.")
    ] = 200,
    loop_radius: Annotated[
        float,
        typer.Option(
            "--loop_radius",
            callback=_a_loop_radius,
            help="Loop closures accepted below this global-descriptor distance, in (0, 0.5].",
        ),
    ] = 0.1,
    loop_sequence: Annotated[
        int,
        typer.Option(
            "--loop_sequence",
            min=0,
            help="Also score loops whose ±L neighbouring keyframes match too (0: off).",
        ),
    ] = 1,
    loop_sweep_pairs: Annotated[
        int,
        typer.Option(
            "--loop_sweep_pairs",
            min=1,
            help="Memory bound of the loops' precision-recall sweep, in pairs (≈ 150 B each; "
            "20 M ≈ 3 GB): beyond it the sweep stops below descriptor distance 0.5 (the report "
            "says where).",
        ),
    ] = 20_000_000,
) -> None:
    """Write report.md/report.json/plots with Recall@N, AOE/APE and per-stage latency."""
    from vvloc.data.sampling import check_query_sessions
    from vvloc.localize.evaluation import check_report_folder, run_evaluation

    with cli_errors("eval"):
        set_torch_threads(threads)
        check_out_folder(out, outside=dataset, own=True)
        check_report_folder(out, "--out")
        names = split_names(queries, "--queries", what="session name")
        check_query_sessions(database, names, "--queries")
        check_sessions(dataset, [("--database", database), *(("--queries", n) for n in names)])
        run_evaluation(
            checkpoint_folder(checkpoint, "--checkpoint"),
            dataset,
            database,
            names,
            out,
            top_k=top_k,
            metric_candidates=metric_candidates,
            metric_from=metric_from.value,
            retrieval_weight=retrieval_weight,
            snap=snap,
            every=every,
            device=str(parse_device(device)),
            robustness=robustness,
            loops=loops,
            loop_pairs=loop_pairs,
            loop_radius=loop_radius,
            loop_sequence=loop_sequence,
            loop_sweep_pairs=loop_sweep_pairs,
        )
    typer.echo(f"report: {out / 'report.md'}")
