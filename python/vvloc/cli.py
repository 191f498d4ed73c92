"""The ``vvloc`` command line. Each command is a thin function that parses options and
delegates to a library function; commands live in :mod:`vvloc.commands` modules and are
registered on ``app`` here (add yours with ``app.command("name")(function)``)."""

from __future__ import annotations

import logging
import os
import re
import signal
import sys
import threading
import warnings
from types import FrameType

import typer

from vvloc.commands.calibrate import calibrate
from vvloc.commands.convert import convert
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
    # plain help: rich's option table cuts long option names (--metric_candidat…) on 80 columns
    rich_markup_mode=None,
)


def _print_version(value: bool) -> None:
    if value:
        from vvloc import __version__

        typer.echo(f"vvloc {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details."),
    version: bool = typer.Option(
        False, "--version", callback=_print_version, is_eager=True, help="Print the version."
    ),
) -> None:
    """vvloc: synthetic data, training, evaluation and localization."""
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )


app.command("sim")(sim)
app.command("convert")(convert)
app.command("train")(train)
app.command("eval")(eval_command)
app.command("calibrate")(calibrate)
app.add_typer(map_app, name="map")
app.command("localize")(localize)
app.command("loops")(loops)
app.command("demo")(demo)
app.command("targets")(targets)


def _quiet_broken_connections(args: threading.ExceptHookArgs) -> None:
    """The thread exception hook of the command's forked children (data-loading workers): a
    broken connection (``ConnectionError``, ``EOFError``), what a stopping parent leaves them,
    is not printed (the parent reports its own end); anything else is."""
    if args.exc_type is not None and issubclass(args.exc_type, (ConnectionError, EOFError)):
        return
    threading.__excepthook__(args)


def _exit_on_sigterm() -> None:
    """Make ``SIGTERM`` (``kill``, ``timeout``, job schedulers) end the command the way Ctrl-C
    does, by an exception, so that every atomic writer removes its temporary file (a killed
    ``map build`` leaves no ``.map.h5.*.tmp`` behind). Exit status 143 = 128 + SIGTERM.

    Child processes (data-loading workers) inherit the handler. A worker whose vvloc parent
    lives lets the first ``SIGTERM`` pass: a group kill (``kill -TERM -PGID``, systemd, Slurm)
    reaches the parent too, which then shuts its workers down; a worker that died first made
    the parent fail with "DataLoader worker ... is killed by signal" (exit 1, or 143 with a
    traceback). A second ``SIGTERM`` (torch terminates a worker that does not stop), or one
    once the parent is gone, ends the worker. A stopping parent leaves a batch a worker sends
    untaken, which breaks torch's fd-sharing connection in a thread of that worker: forked
    children print no traceback for a broken connection (:func:`_quiet_broken_connections`),
    from their start, since the parent may stop before the worker's own handler runs."""
    pid = os.getpid()

    def handler(signum: int, frame: FrameType | None) -> None:
        if os.getpid() != pid:  # a child
            signal.signal(signum, signal.SIG_DFL)
            if os.getppid() != pid:
                os.kill(os.getpid(), signum)
            return
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, handler)

    def quiet_child() -> None:
        threading.excepthook = _quiet_broken_connections

    os.register_at_fork(after_in_child=quiet_child)


def _quiet_when_logged() -> None:
    """When stderr is not a terminal (a log file, CI), progress bars redraw every 30 s instead
    of ten times a second (``TQDM_MININTERVAL``; an explicit setting wins), and warnings print as
    one line, ``vvloc: warning: ...``, without a source line, on a line of its own while a
    progress bar is drawn (:func:`_show_warning`)."""
    if not sys.stderr.isatty():
        os.environ.setdefault("TQDM_MININTERVAL", "30")

    def one_line(message, category, filename, lineno, line=None):  # type: ignore[no-untyped-def]
        return f"vvloc: warning: {message}\n"

    warnings.formatwarning = one_line
    warnings.showwarning = _show_warning


def _show_warning(  # type: ignore[no-untyped-def]
    message, category, filename, lineno, file=None, line=None
) -> None:
    """``warnings.showwarning`` of the CLI: a warning given while a progress bar is drawn was
    glued to the bar's line (``map:   0%|...|vvloc: warning: ...``). On a terminal the bars
    are cleared, the warning written and the bars drawn again below it (tqdm's
    ``external_write_mode``); in a log, where a bar's line is not ended until the bar closes,
    the warning starts a line of its own."""
    stream = sys.stderr if file is None else file
    if stream is None:  # pythonw: nowhere to write
        return
    text = warnings.formatwarning(message, category, filename, lineno, line)
    from tqdm import tqdm

    try:
        if not getattr(tqdm, "_instances", None):
            stream.write(text)
        elif stream.isatty():
            with tqdm.external_write_mode(file=stream):
                stream.write(text)
        else:
            stream.write("\n" + text)
    except OSError:  # the stream closed (a broken pipe): the warning is lost, as Python's own
        pass


def _show_parse_error(e: typer.TyperException) -> None:
    """A refusal of the option parser (a missing or unknown option, a value of the wrong type
    or out of range) in the commands' own style: ``vvloc <command>: error: <what>`` on one
    line, then where the help is (the parser's default was a usage block, then ``Error:``)."""
    format_message = getattr(e, "format_message", None)
    if format_message is None or type(e).__name__ == "NoArgsIsHelpError":
        show = getattr(e, "show", None)  # the help of a bare group
        if show is not None:
            show()
        else:
            typer.echo(f"vvloc: error: {e}", err=True)
        return
    ctx = getattr(e, "ctx", None)
    # an option missing its value is refused before the command has a context
    path = ctx.command_path if ctx is not None else _command_path(sys.argv[1:])
    message = str(format_message())
    # "Invalid value for '--threshold': expected ..." → "--threshold: expected ...", as the
    # commands name an option
    m = re.fullmatch(r"Invalid value for '([^']+)': (.*)", message, flags=re.DOTALL)
    if m:
        message = f"{m.group(1)}: {m.group(2)}"
    typer.echo(f"{path}: error: {message}", err=True)
    typer.echo(f"Try '{path} --help' for help.", err=True)


def _command_path(args: list[str]) -> str:
    """``vvloc`` and the names of the command and subcommand that begin ``args``."""
    command = typer.main.get_command(app)
    path = ["vvloc"]
    for word in args:
        commands = getattr(command, "commands", None)
        if not commands or word not in commands:
            break
        path.append(word)
        command = commands[word]
    return " ".join(path)


def main() -> None:
    """Entry point of the ``vvloc`` console script."""
    _exit_on_sigterm()
    _quiet_when_logged()
    try:
        # prog_name: the commands' own errors say "vvloc <command>", under python -m too
        code = app(prog_name="vvloc", standalone_mode=False)
    except typer.TyperException as e:  # the parser's refusals (exit 2) and other click errors
        _show_parse_error(e)
        sys.exit(int(getattr(e, "exit_code", 1)))
    except typer.Abort:  # end of input at a prompt
        typer.echo("Aborted!", err=True)
        sys.exit(1)
    sys.exit(code if isinstance(code, int) else 0)  # typer.Exit's code, else 0


if __name__ == "__main__":
    main()
