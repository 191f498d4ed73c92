"""Shared helpers of the CLI commands: error reporting with trustworthy exit codes."""

from __future__ import annotations

import contextlib
import math
import os
import sys
from collections.abc import Iterable, Iterator, Sequence
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    import torch

    from vvloc.data import Dataset

#: Exit codes: 0 success, 1 runtime failure, 2 bad arguments or inputs (missing file, wrong
#: checkpoint, malformed data).
EXIT_FAILURE = 1
EXIT_USAGE = 2

#: ``--metric_candidates`` of ``eval`` and ``localize`` (see ``Localizer(metric_candidates=)``);
#: its default is the library's, :data:`vvloc.localize.metric.METRIC_CANDIDATES`.
MetricCandidates = Annotated[
    int,
    typer.Option(
        "--metric_candidates",
        min=1,
        help="Run the coarse translation search against M candidates (see --metric_from; the "
        "query decoded once) and refine the one of lowest cost (plus --retrieval_weight × "
        "descriptor distance).",
    ),
]


#: ``--threads`` of the commands that run the networks (``eval``, ``localize``, ``loops``,
#: ``map build``, ``calibrate``, ``demo``): PyTorch's CPU threads, as :func:`set_torch_threads`
#: sets them.
Threads = Annotated[
    int | None,
    typer.Option(
        "--threads",
        min=1,
        max=4096,
        help="PyTorch CPU threads for the networks (default: torch's, all cores). On a machine "
        "that other work keeps busy, 1 can be many times faster (README, 'Threads'). The Rust "
        "kernels' pool is set apart: VVLOC_NUM_THREADS.",
    ),
]


def set_torch_threads(threads: int | None) -> None:
    """``torch.set_num_threads(threads)`` when ``threads`` is given (the networks' CPU threads;
    None leaves torch's default, which ``OMP_NUM_THREADS`` sets). vvloc's Rust kernels keep
    their own pool (``VVLOC_NUM_THREADS``); answers can move in their last bits with the torch
    thread count (README, "Threads")."""
    if threads is not None:
        import torch

        torch.set_num_threads(threads)


class MetricFromChoice(str, Enum):
    """The orderings ``--metric_from`` takes its candidates from: ``Localizer(metric_from=)``'s
    ``METRIC_FROM``, spelled out as a class so that typer lists them and type checkers see them
    (a test keeps the two equal)."""

    retrieval = "retrieval"
    rerank = "rerank"


#: ``--metric_from`` of ``eval`` and ``localize`` (see ``Localizer(metric_from=)``).
MetricFrom = Annotated[
    MetricFromChoice,
    typer.Option(
        "--metric_from",
        help="Take the M metric candidates from the retrieval order ('retrieval') or from the "
        "yaw re-ranking ('rerank').",
    ),
]


def _a_weight(value: float) -> float:
    # a weight of inf or NaN would be refused by the Localizer only after the map is built
    if not (math.isfinite(value) and value >= 0):
        raise typer.BadParameter(f"expected a finite weight >= 0, got {value}")
    return value


#: ``--retrieval_weight`` of ``eval``, ``localize`` and ``calibrate`` (see
#: ``Localizer(retrieval_weight=)``); its default is the library's,
#: :data:`vvloc.localize.metric.RETRIEVAL_WEIGHT`. NaN, inf and negative values exit 2.
RetrievalWeight = Annotated[
    float,
    typer.Option(
        "--retrieval_weight",
        callback=_a_weight,
        help="Order the M metric candidates by coarse matching cost plus this weight times "
        "their global-descriptor distance (0: the cost alone).",
    ),
]


def _a_cost(value: float) -> float:
    # costs are >= 0 and a result is accepted when its cost is below the threshold: NaN would
    # accept nothing without saying so, a negative value is a mistake (0 accepts nothing, as
    # the library's -inf does)
    if math.isnan(value) or value < 0:
        raise typer.BadParameter(f"expected a matching cost >= 0, got {value}")
    return value


#: ``--threshold`` of ``localize``, ``loops`` and ``calibrate``: a result is accepted when its
#: matching cost is below it (the paper's 0.75); NaN and negative values are refused (exit 2).
CostThreshold = Annotated[
    float,
    typer.Option("--threshold", help="Accept cost below.", callback=_a_cost),
]

#: ``--snap/--no_snap`` of ``eval``, ``localize`` and ``calibrate`` (see ``Localizer(snap=)``);
#: ``--no-snap``, its name before 2026-12-05, still works (every other flag uses ``_``).
Snap = Annotated[
    bool,
    typer.Option(
        "--snap/--no_snap",
        " /--no-snap",
        help="Report the retrieved keyframe nearest to the metric pose (same floor).",
    ),
]


def error_text(e: BaseException) -> str:
    """The message of ``e`` for one line: a ``KeyError``'s key, and for an exception that a
    DataLoader worker raised (torch re-raises it in the main process as the same type, its
    message "Caught ... in DataLoader worker process N." and the worker's whole traceback)
    the worker's own message."""
    if isinstance(e, KeyError) and e.args:
        return str(e.args[0])
    text = str(e)
    head, sep, trace = text.partition("\nOriginal Traceback")
    if not (head.startswith("Caught ") and sep):
        return text
    lines = trace.splitlines()
    message = text
    for k in range(len(lines) - 1, -1, -1):  # the last "module.ErrorType: message" line
        name, colon, first = lines[k].partition(": ")
        if colon and not name.startswith(" ") and name.split(".")[-1] == type(e).__name__:
            message = "\n".join([first, *lines[k + 1 :]]).strip()
            break
    return f"{message} ({head.removeprefix('Caught ').split(' ', 1)[-1].rstrip('.')})"


def with_option_name(text: str, argv: Sequence[str] | None = None) -> str:
    """``text`` with a leading library argument's name (``window: ...``, :func:`named`'s
    convention) said as the command-line option of that name (``--window: ...``) when that
    option was given in ``argv`` (default: ``sys.argv``), so that its value came from there;
    other text as it is."""
    arg, sep, rest = text.partition(": ")
    if not (sep and arg.isidentifier()):
        return text
    given = {a.partition("=")[0] for a in (sys.argv[1:] if argv is None else argv)}
    return f"--{arg}: {rest}" if f"--{arg}" in given else text


@contextlib.contextmanager
def cli_errors(command: str) -> Iterator[None]:
    """Turn library exceptions into one-line messages and exit code 2 (bad input) or 1. A bad
    input's message that starts with a library argument's name says the option of that name
    instead when it was given (:func:`with_option_name`)."""
    try:
        yield
    except typer.Exit:  # a command's own exit (a RuntimeError subclass): already reported
        raise
    except (
        FileNotFoundError,
        FileExistsError,
        IsADirectoryError,
        NotADirectoryError,
        PermissionError,
        ValueError,
        KeyError,
        TypeError,
    ) as e:
        typer.echo(f"vvloc {command}: error: {with_option_name(error_text(e))}", err=True)
        raise typer.Exit(code=EXIT_USAGE) from e
    except (RuntimeError, OSError, ArithmeticError, MemoryError) as e:  # e.g. a non-finite loss
        typer.echo(f"vvloc {command}: failed: {error_text(e)}", err=True)
        raise typer.Exit(code=EXIT_FAILURE) from e


@contextlib.contextmanager
def named(option: str, *types: type[Exception]) -> Iterator[None]:
    """Prefix the message of an exception of ``types`` raised in the block with ``option``
    (the CLI option its input came from), keeping its type: ``--map: map file not found: ...``
    rather than the library's words alone."""
    try:
        yield
    except types as e:
        raise type(e)(f"{option}: {error_text(e)}") from None


def check_sessions(dataset: Path, sessions: Iterable[tuple[str, str]]) -> Dataset:
    """Open ``dataset`` and check each ``(option, name)`` of ``sessions`` before any model or
    map loads: ``KeyError`` naming the option (and the dataset's sessions) when there is no
    session ``name``, ``ValueError`` naming it when the session holds no frames. Returns the
    opened dataset; a ``UserWarning`` when it is an NCLT or RobotCar raw folder, which the
    command reads with the reader's defaults."""
    import warnings

    from vvloc.data import RAW_FOLDER, detect_format, open_dataset
    from vvloc.data.vvloc_format import DatasetFormatError

    with named("--dataset", FileNotFoundError, NotADirectoryError, DatasetFormatError):
        fmt = detect_format(dataset)
    if fmt != "vvloc":  # said before the reader's own errors (e.g. a camera folder missing)
        warnings.warn(
            f"--dataset: {dataset} is {RAW_FOLDER[fmt]}, read with the reader's defaults: its "
            "native image size, every frame, the ego origin left above the ground; convert it "
            "once with vvloc convert --ego_height <metres> (docs/dataset-format.md)",
            UserWarning,
            stacklevel=2,
        )
    with named("--dataset", FileNotFoundError, NotADirectoryError):
        ds = open_dataset(dataset, format=fmt)
    for option, name in sessions:
        with named(option, KeyError):
            sess = ds.session(name)
        if len(sess) == 0:
            raise ValueError(f"{option}: session {name!r} of {dataset} has no frames")
    return ds


def parse_device(device: str) -> torch.device:
    """``--device``: ``cpu``, ``cuda``, ``cuda:N`` or ``auto`` (``ValueError`` naming
    ``--device`` when torch cannot use it)."""
    from vvloc.nets.model import resolve_device

    return resolve_device(device, argument="--device")


def split_names(text: str, option: str, *, what: str | None = None) -> list[str]:
    """A comma-separated option's names: ``'s1, s2'`` → ``['s1', 's2']``. Read as a CSV line,
    so a name holding a comma is given in double quotes: ``'"day,1",s2'`` → ``['day,1', 's2']``
    (``vvloc convert`` keeps a source's session names, commas included). With ``what`` (e.g.
    ``"session name"``), text naming nothing (``""``, ``","``) is a ``ValueError`` saying so."""
    import csv

    try:
        fields = next(csv.reader([text], skipinitialspace=True, strict=True), [])
    except csv.Error as e:
        raise ValueError(
            f"{option}: cannot read {text!r} as comma-separated names ({e}); a name holding a "
            'comma goes in double quotes: "day,1",s2'
        ) from None
    names = [s.strip() for s in fields if s.strip()]
    if what is not None and not names:
        raise ValueError(f"{option}: expected at least one {what}, got {text!r}")
    return names


@contextlib.contextmanager
def as_options(options: dict[str, str]) -> Iterator[None]:
    """Say an error whose message starts with a library argument's name (``min_angle_deg:
    ...``, :func:`named`'s convention) with the option its value came from (``--min_angle:
    ...``), keeping its type; other errors pass as they are."""
    try:
        yield
    except (ValueError, TypeError, KeyError) as e:
        arg, sep, rest = error_text(e).partition(": ")
        if not (sep and arg in options):
            raise
        raise type(e)(f"{options[arg]}: {rest}") from None


def check_out_folder(
    out: Path, option: str = "--out", *, outside: Path | None = None, own: bool = False
) -> None:
    """Said before any work, not after it: ``NotADirectoryError`` naming ``option`` when
    ``out``, or a folder above it, exists and is not a folder; ``PermissionError`` when the
    folder, or the nearest one above it that exists, cannot be written (a read-only file
    system: found after every frame was localized before); ``ValueError`` when ``out`` is or
    lies inside ``outside`` (the dataset, whose folders the outputs would corrupt) or inside
    any other vvloc dataset (a folder with ``rig.json`` beside ``sessions/``), and with
    ``own`` when it is the working directory or a folder above it: the outputs go to a folder
    of their own, and an empty value (an unset shell variable: ``--out "$OUT"``) reads as the
    working directory, where they mixed with whatever was there."""
    if own:
        target, cwd = Path(os.path.realpath(out)), Path.cwd().resolve()
        if target == cwd or target in cwd.parents:
            raise ValueError(
                f"{option}: {str(out)!r} is the working directory or a folder above it (as is "
                "an empty value); write the outputs to a folder of their own, e.g. runs/out"
            )
    if out.is_symlink() and not out.exists():  # found only when the outputs were written
        raise FileExistsError(
            f"{option}: {out} is a symbolic link to {os.readlink(out)}, which does not exist "
            "(or loops); expected a folder"
        )
    for p in (out, *out.parents):
        if p.exists():
            if not p.is_dir():
                what = "exists" if p == out else f"lies below {p}, which exists"
                raise NotADirectoryError(f"{option}: {out} {what} and is a file; expected a folder")
            if not os.access(p, os.W_OK | os.X_OK):
                what = "" if p == out else f", the folder {out} is to be made in,"
                raise PermissionError(f"{option}: {p}{what} is not writable")
            break
    if outside is not None:
        from vvloc.data.sampling import inside_folder

        if inside_folder(out, outside):
            raise ValueError(
                f"{option}: {out} is or lies inside the dataset {outside}; write outputs to a "
                "folder of their own"
            )
    for folder in (out, *Path(os.path.abspath(out)).parents):  # any other vvloc dataset too
        if (folder / "rig.json").is_file() and (folder / "sessions").is_dir():
            raise ValueError(
                f"{option}: {out} is or lies inside the dataset {folder}; write outputs to a "
                "folder of their own"
            )
