"""``vvloc demo``: render a small synthetic world, localize two held-out query sessions against a
map of another session, print the metrics and write plots to ``runs/demo/``."""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Annotated

import typer

from vvloc.commands._util import Threads, check_out_folder, cli_errors, set_torch_threads

#: Where the committed trained small model lives (relative to the repository root).
DEFAULT_MODEL = Path(__file__).resolve().parents[3] / "models" / "synth-small"

#: The demo's sessions: the committed model trained on s0, s1, s2, s5..s17 of this world (see
#: configs/synth-small-rerank.yaml, step 1 of `make model`), so the queries are the held-out s3
#: (rain, reversed drive) and s4 (fog, +1.5 m lateral offset), localized against a map of s0
#: (day).
SESSIONS = 5
MAP_SESSION = "s0"
QUERY_SESSIONS = ["s3", "s4"]

UNTRAINED = (
    "WARNING: no trained model found at {path}: this demo runs an UNTRAINED (randomly "
    "initialised) small model, so its retrieval and poses are meaningless. Train one with "
    "`vvloc train --config configs/synth-small-rerank.yaml --out runs/synth-small` and pass "
    "--checkpoint runs/synth-small (`make model` runs the committed model's five-step recipe)."
)


def _reusable(data: Path, frames: int, seed: int) -> bool:
    """Whether ``data`` already holds the demo's world: a readable dataset rendered from parking
    world ``seed`` with the map and query sessions of ``frames`` keyframes each."""
    from vvloc.data import open_dataset
    from vvloc.data.vvloc_format import rig_meta

    try:
        meta = rig_meta(data) or {}
        ds = open_dataset(data)
        names = [MAP_SESSION, *QUERY_SESSIONS]
        return (
            meta.get("scene") == "parking"
            and meta.get("seed") == seed
            and set(names) <= set(ds.sessions)
            and all(len(ds.session(n)) == frames for n in names)
        )
    except (OSError, ValueError):
        return False


def _ours_to_replace(data: Path) -> bool:
    """Whether the demo may (re)render ``data``: it is missing or empty, or a parking world
    that ``vvloc sim`` rendered with the demo's sessions and nothing else (another dataset
    there, or one with more sessions, is never replaced)."""
    if not data.exists() or (data.is_dir() and not any(data.iterdir())):
        return True
    from vvloc.data.vvloc_format import rig_meta

    meta = rig_meta(data) or {}
    if not (meta.get("generator") == "vvloc.sim" and meta.get("scene") == "parking"):
        return False
    sessions = data / "sessions"
    found = {p.name for p in sessions.iterdir()} if sessions.is_dir() else set()
    return found <= {f"s{i}" for i in range(SESSIONS)}


def status_warning(card: str) -> str | None:
    """The warning for a model card whose first line (``Status: ...``, any case, Markdown
    emphasis allowed) does not say OK; None when it does."""
    lines = card.lstrip("\ufeff").splitlines()
    first = lines[0].strip() if lines else ""
    if re.match(r"\W*status\W*:\W*ok\b", first, re.IGNORECASE):
        return None
    status = re.sub(r"^\W*status\W*:\s*", "", first, flags=re.IGNORECASE)
    return f"WARNING: the committed model is {status or 'of unknown status'}"


def demo(
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("runs/demo"),
    checkpoint: Annotated[
        Path | None, typer.Option("--checkpoint", help="Model (default: the committed one).")
    ] = None,
    frames: Annotated[int, typer.Option("--frames", min=10, help="Keyframes per session.")] = 120,
    every: Annotated[int, typer.Option("--every", min=1, help="Localize every n-th query.")] = 3,
    seed: Annotated[int, typer.Option("--seed", min=0, help="World seed.")] = 0,
    threads: Threads = None,
) -> None:
    """Render a small synthetic parking lot (5 sessions) into --out/data, or reuse the one an
    earlier demo rendered there; map its session s0 (day) with the committed model (or
    --checkpoint), localize the held-out query sessions s3 (rain, reversed drive) and s4 (fog,
    +1.5 m lateral offset) against it, print the metrics, and write the report and plots into
    --out."""
    from vvloc.checkpoints import checkpoint_folder
    from vvloc.localize.evaluation import check_report_folder, run_evaluation
    from vvloc.nets import ModelConfig, VVLocNet
    from vvloc.sim import simulate_dataset

    t0 = time.perf_counter()
    with cli_errors("demo"):
        set_torch_threads(threads)
        check_out_folder(out, own=True)
        check_report_folder(out, "--out")  # the report's files, refused before minutes of rendering
        data = out / "data"
        if checkpoint is not None:  # checked before minutes of rendering; a run folder works
            checkpoint = checkpoint_folder(checkpoint, "--checkpoint")
            try:
                VVLocNet.load(checkpoint)
            except (FileNotFoundError, ValueError) as e:
                raise ValueError(f"--checkpoint: {e}") from None
        if not _reusable(data, frames, seed):
            if not _ours_to_replace(data):
                raise FileExistsError(
                    f"--out: {data} holds a dataset the demo did not render; the demo renders "
                    "its world there, so choose another --out"
                )
            typer.echo(
                f"rendering a synthetic parking lot ({frames} keyframes x {SESSIONS} sessions)..."
            )
            simulate_dataset(
                data, scene="parking", sessions=SESSIONS, frames=frames, seed=seed, overwrite=True
            )
        warning = None
        ckpt = checkpoint or DEFAULT_MODEL
        card = DEFAULT_MODEL / "MODEL_CARD.md"
        if checkpoint is None and card.exists():
            warning = status_warning(card.read_text())
            if warning:
                warning = f"{warning} (details: {card})"
                typer.secho(warning, fg=typer.colors.RED, err=True)
        if checkpoint is None and not (DEFAULT_MODEL / "config.json").exists():
            warning = UNTRAINED.format(path=DEFAULT_MODEL)
            typer.secho(warning, fg=typer.colors.RED, err=True)
            ckpt = out / "untrained-checkpoint"
            VVLocNet(ModelConfig.small()).save(ckpt)
        metrics = run_evaluation(
            ckpt, data, MAP_SESSION, QUERY_SESSIONS, out, every=every, untrained_warning=warning
        )
    rec = metrics["global_localization"]
    typer.echo("")
    typer.echo(f"{'method':<10} {'R@1 2m':>8} {'R@5 2m':>8} {'R@1 5m':>8}")
    for name, r in rec.items():
        cells = [r.at(1, 2.0), r.at(5, 2.0) if 5 in r.top_n else float("nan"), r.at(1, 5.0)]
        typer.echo(f"{name:<10} " + " ".join(f"{100 * c:7.1f}%" for c in cells))
    pa = metrics["pose_accuracy"]["VVLoc-ML"]["true_revisit"]
    typer.echo(
        f"AOE@50 {pa.get('AOE@50', float('nan')):.2f} deg, "
        f"APE@50 {pa.get('APE@50', float('nan')):.2f} m (queries with a correct top-1)"
    )
    typer.echo(f"accepted share: {metrics['accepted_share']:.1%}")
    lat = metrics["latency"]
    typer.echo(
        "median latency per query: "
        + ", ".join(f"{k} {v['median_ms']:.1f} ms" for k, v in lat.items())
    )
    typer.echo(f"report: {out / 'report.md'} (plots beside it); {time.perf_counter() - t0:.0f} s")
    if warning:
        typer.secho(warning, fg=typer.colors.RED, err=True)
