"""The ``vvloc`` command line. Each command is a thin function that parses options and
delegates to a library function; commands live in :mod:`vvloc.commands` modules and are
registered on ``app`` here (add yours with ``app.command("name")(function)``)."""

from __future__ import annotations

import logging

import typer

from vvloc.commands.calibrate import calibrate
from vvloc.commands.demo import demo
from vvloc.commands.evaluate import eval_command
from vvloc.commands.localize import localize
from vvloc.commands.loops import loops
from vvloc.commands.mapping import map_app
from vvloc.commands.sim import sim
from vvloc.commands.targets import targets
from vvloc.commands.train import train

app = typer.Typer(
    name="vvloc",
    help="Prior-free 3-DoF multi-camera vehicle visual localization (VVLoc).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details."),
) -> None:
    """vvloc: synthetic data, training, evaluation and localization."""
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )


app.command("sim")(sim)
app.command("train")(train)
app.command("eval")(eval_command)
app.command("calibrate")(calibrate)
app.add_typer(map_app, name="map")
app.command("localize")(localize)
app.command("loops")(loops)
app.command("demo")(demo)
app.command("targets")(targets)


def main() -> None:
    """Entry point of the ``vvloc`` console script."""
    app()


if __name__ == "__main__":
    main()
