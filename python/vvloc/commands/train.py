"""``vvloc train``: train a model from a YAML config (two-stage recipe, checkpoints, resume)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from vvloc.checkpoints import resolve_checkpoint
from vvloc.commands._util import check_out_folder, cli_errors, named
from vvloc.provenance import summarize


def train(
    config: Annotated[Path, typer.Option("--config", help="YAML training config.")],
    out: Annotated[Path, typer.Option("--out", help="Run folder (checkpoint, logs).")],
    resume: Annotated[
        bool, typer.Option("--resume", help="Continue the run in --out from its last epoch.")
    ] = False,
    device: Annotated[
        str | None,
        typer.Option(
            "--device",
            help="cpu, cuda[:N] or auto; replaces the config's `device` (a resumed run may "
            "change it). CUDA runs are not bit-reproducible.",
        ),
    ] = None,
) -> None:
    """Train VVLoc (stage 1 global descriptors, stage 2 joint) and checkpoint every epoch."""
    import dataclasses

    from vvloc.nets.model import resolve_device
    from vvloc.train import TrainConfig
    from vvloc.train import train as run_training

    with cli_errors("train"):
        check_out_folder(out)
        with named("--config", FileNotFoundError, IsADirectoryError):
            cfg = TrainConfig.from_yaml(config)
        if device is not None:
            resolve_device(device, argument="--device")  # refused by name before any work
            cfg = dataclasses.replace(cfg, device=device)
        try:
            trainer = run_training(cfg, out, resume=resume)
        except KeyboardInterrupt:  # Ctrl-C: where the run stands, not half a progress bar
            typer.echo("", err=True)
            typer.echo(f"vvloc train: interrupted; {_where_it_stands(out)}", err=True)
            raise typer.Exit(130) from None
    start, end = int(trainer.process["epochs"][0]), trainer.epoch  # this process's epochs
    if end == start:
        done = f"nothing to train: the run had done its {end} epoch{'' if end == 1 else 's'}"
    elif start:
        which = f"epoch {end}" if end == start + 1 else f"epochs {start + 1}-{end}"
        done = f"trained {which} (resumed after epoch {start})"
    else:
        done = f"trained {end} epoch{'' if end == 1 else 's'}"
    typer.echo(f"{done}; latest checkpoint: {trainer.checkpoint_dir}")
    if trainer.joint_stopped is not None:
        typer.echo(
            f"the joint stage stopped early after epoch {trainer.joint_stopped} "
            f"(patience {trainer.cfg.patience})"
        )
    if trainer.best is not None:
        val = trainer.best["val"]
        typer.echo(
            f"best by validation: epoch {trainer.best['epoch']} (Recall@1 2 m "
            f"{val['r1_reranked']:.1%} re-ranked, {val['r1_retrieval']:.1%} retrieval): "
            f"{trainer.best_dir} (the one `vvloc eval --checkpoint {out}` uses)"
        )
    ckpt = resolve_checkpoint(out)
    if (ckpt / "config.json").is_file():  # none when the config has no epochs
        from vvloc.nets import VVLocNet

        with cli_errors("train"):  # the record as written (checked against the weights)
            produced = VVLocNet.load(ckpt).training_record
        typer.echo(f"trained on: {summarize(produced)}")


def _where_it_stands(out: Path) -> str:
    """What an interrupted run left in ``out`` and how to go on, in words."""
    if (out / "trainer_state.pt").is_file():
        return (
            f"{out} holds the run up to its last finished epoch: rerun with --resume to "
            "continue it (on the CPU, as if it had never stopped)"
        )
    if out.is_dir():
        return f"no epoch had finished: rerun without --resume to start it again in {out}"
    return "no epoch had finished and nothing was written"
