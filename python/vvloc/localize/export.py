"""Exports of localization results: loop closures (CSV, g2o) and trajectories (TUM).

Conventions (DESIGN.md §3), written into every file's header where the format has comments:

* World frame: x east, y north, z up. Vehicle frame: x forward, y left, z up. Metres.
* A pose is (x, y, yaw), yaw counter-clockwise positive about z, radians, wrapped to (−π, π].
* A relative pose ξ_{i→j} = (x, y, yaw) is keyframe j's pose expressed in keyframe i's frame:
  T_world_j = T_world_i · ξ_{i→j}. This is exactly g2o's ``EDGE_SE2 i j`` measurement.

All writers take plain arrays, validate them (``TypeError``/``ValueError`` naming the argument),
write numbers with Python's shortest round-trip ``repr`` (reading back gives the same float64),
and write atomically (:mod:`vvloc._io`): a failed write leaves no partial file and leaves an
existing file untouched. Each ``read_*`` function reads back what its writer wrote (and common
files of that format from other tools).
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, SupportsFloat

import numpy as np

from vvloc._checks import finite_float, flag
from vvloc._io import FLOAT_TEXT, INT_TEXT, atomic_write, check_readable_file
from vvloc.geometry import relative as relative_pose
from vvloc.geometry import wrap_angle

__all__ = [
    "DEFAULT_LOOP_SIGMAS",
    "DEFAULT_ODOMETRY_SIGMAS",
    "G2O_CONVENTIONS",
    "G2OGraph",
    "KeyframeTable",
    "LoopClosures",
    "g2o_text",
    "information_from_sigmas",
    "keyframe_csv_text",
    "loop_csv_text",
    "read_g2o",
    "read_keyframe_csv",
    "read_loop_csv",
    "read_tum",
    "relative_pose",
    "tum_text",
    "wrap_angle",
    "write_g2o",
    "write_loop_csv",
    "write_tum",
]

PathLike = str | os.PathLike[str]

#: Default standard deviations (x m, y m, yaw rad) of odometry edges between consecutive
#: keyframes of a session: their poses come from the session's own trajectory (GPS/INS or SLAM),
#: trusted to a few centimetres and a fraction of a degree.
DEFAULT_ODOMETRY_SIGMAS: tuple[float, float, float] = (0.05, 0.05, math.radians(0.5))
#: Default standard deviations (x m, y m, yaw rad) of loop-closure edges: a typical metric
#: localization error of the visual matcher (half a metre, two degrees).
DEFAULT_LOOP_SIGMAS: tuple[float, float, float] = (0.5, 0.5, math.radians(2.0))

G2O_CONVENTIONS = """\
vvloc pose graph (g2o, 2D):
  VERTEX_SE2 id x y theta: keyframe pose in the world frame (x east, y north, metres;
    theta counter-clockwise about z, radians).
  EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33: measurement xi_{i->j}, the pose of
    vertex j expressed in the frame of vertex i (vehicle frame: x forward, y left), i.e.
    T_world_j = T_world_i * xi; followed by the upper triangle of the 3x3 information matrix
    (inverse covariance) of (dx, dy, dtheta), row by row.
  Odometry edges link consecutive keyframes of a session; loop-closure edges follow them.
  Vertex ids are non-negative (g2o refuses negative ones); theta is wrapped to (-pi, pi].
  No vertex is fixed (the file has no FIX line): anchor the graph's gauge yourself, and note
  that a session with no accepted loop closure is joined to the others by nothing, so fix one
  of its vertices too (or leave it out) before optimising.
"""

_FRAME_COMMENTS = (
    "frames (DESIGN.md 3): world x east, y north, z up; vehicle x forward, y left, z up; metres",
    "yaw: counter-clockwise positive about z, radians wrapped to (-pi, pi]",
)


#: The largest vertex id a g2o file takes (g2o reads ids as 32-bit ints).
G2O_MAX_ID = 2**31 - 1


def _r(x: SupportsFloat) -> str:
    """Shortest text that parses back to the same float64."""
    return repr(float(x))


def _int_field(text: str, what: str) -> int:
    """A field of a file read as a 64-bit integer, as C's strtol reads it (Python alone reads
    ``1_000``: :data:`vvloc._io.INT_TEXT`); ``ValueError`` naming ``what`` otherwise."""
    if not INT_TEXT.fullmatch(text):
        raise ValueError(f"{what}: expected an integer, got {text!r:.60}")
    v = int(text)
    if not -(2**63) <= v < 2**63:
        raise ValueError(f"{what}: {text:.60} does not fit in a 64-bit integer")
    return v


def _float_field(text: str, what: str) -> float:
    """A field of a file read as a finite float, as C's strtod reads it
    (:data:`vvloc._io.FLOAT_TEXT`); ``ValueError`` naming ``what`` otherwise."""
    if not FLOAT_TEXT.fullmatch(text):
        raise ValueError(f"{what}: expected a number, got {text!r:.60}")
    v = float(text)
    if not math.isfinite(v):
        raise ValueError(f"{what}: non-finite value {text!r:.60} (nan or inf)")
    return v


def _vertex_id(text: str, what: str) -> int:
    v = _int_field(text, what)
    if not 0 <= v <= G2O_MAX_ID:
        raise ValueError(f"{what}: g2o vertex ids lie in [0, {G2O_MAX_ID}], got {v}")
    return v


def _to_array(x: Any, name: str) -> np.ndarray:
    if hasattr(x, "detach") and hasattr(x, "cpu"):  # torch.Tensor, without importing torch
        x = x.detach().cpu().numpy()
    if x is None or isinstance(x, (str, bytes)):
        raise TypeError(f"{name}: expected an array, got {type(x).__name__}")
    return np.asarray(x)


def _floats(x: Any, name: str, shape_doc: str, shape: tuple[int | None, ...]) -> np.ndarray:
    arr = _to_array(x, name)
    if arr.dtype == object or arr.dtype.kind not in "fiu":
        raise TypeError(f"{name}: expected a real-valued array {shape_doc}, got dtype {arr.dtype}")
    if arr.ndim != len(shape) or any(
        e is not None and a != e for a, e in zip(arr.shape, shape, strict=True)
    ):
        raise ValueError(f"{name}: expected shape {shape_doc}, got shape {arr.shape}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    return arr


def _ints(x: Any, name: str, n: int) -> np.ndarray:
    arr = _to_array(x, name)
    if arr.shape == (0,) and n == 0:
        return np.zeros(0, np.int64)
    if arr.dtype.kind not in "iu":
        raise TypeError(f"{name}: expected an integer array ({n},), got dtype {arr.dtype}")
    if arr.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got shape {arr.shape}")
    if arr.dtype.kind == "u" and n and int(arr.max()) > np.iinfo(np.int64).max:
        raise ValueError(f"{name}: ids beyond int64 ({int(arr.max())}) cannot be kept exactly")
    return np.ascontiguousarray(arr, dtype=np.int64)


def _information(x: Any, name: str, k: int) -> np.ndarray:
    """(3, 3) or (k, 3, 3) symmetric positive-definite → (k, 3, 3) float64."""
    arr = _to_array(x, name)
    if arr.shape == (3, 3):
        arr = np.broadcast_to(arr, (k, 3, 3))
    arr = _floats(arr, name, f"(3, 3) or ({k}, 3, 3)", (k, 3, 3))
    if not np.allclose(arr, np.swapaxes(arr, 1, 2), rtol=1e-9, atol=0.0):
        raise ValueError(f"{name}: information matrices must be symmetric")
    if k and np.linalg.eigvalsh(arr).min() <= 0.0:
        raise ValueError(f"{name}: information matrices must be positive definite")
    return arr


def information_from_sigmas(sigma_x: float, sigma_y: float, sigma_yaw: float) -> np.ndarray:
    """(3, 3) diagonal information matrix diag(1/σx², 1/σy², 1/σyaw²) (metres, radians); each
    σ a real number > 0 whose 1/σ² is a finite, non-zero float64 (about 1e-154 to 1e154)."""
    sig = np.array(
        [
            finite_float(v, n)
            for v, n in zip((sigma_x, sigma_y, sigma_yaw), _SIGMA_NAMES, strict=True)
        ]
    )
    if (sig <= 0).any():
        raise ValueError(f"sigmas: standard deviations must be > 0, got {sig.tolist()}")
    with np.errstate(over="ignore", divide="ignore", under="ignore"):
        info = 1.0 / sig**2
    if not (np.isfinite(info) & (info > 0)).all():  # inf, or 0: a singular matrix
        raise ValueError(
            f"sigmas: 1/sigma^2 must be a finite float > 0, got {info.tolist()} for {sig.tolist()}"
        )
    return np.diag(info)


_SIGMA_NAMES = ("sigma_x", "sigma_y", "sigma_yaw")


def _comment_lines(comments: Iterable[str]) -> list[str]:
    if isinstance(comments, str):
        comments = [comments]
    try:
        lines = list(comments)
    except TypeError:
        raise TypeError(
            f"comments: expected an iterable of str lines, got {type(comments).__name__}"
        ) from None
    out: list[str] = []
    for c in lines:
        if not isinstance(c, str):
            raise TypeError(f"comments: expected str lines, got {type(c).__name__}")
        out.extend(f"# {line}".rstrip() for line in c.splitlines() or [""])
    return out


# ---------------------------------------------------------------------------------------------
# Loop closures


@dataclass(frozen=True, eq=False)
class LoopClosures:
    """K loop-closure results (validated and converted on construction).

    Attributes:
        i: (K,) int64 source keyframe ids.
        j: (K,) int64 target keyframe ids.
        relative_poses: (K, 3) float64 ξ_{i→j} = (x, y, yaw): keyframe j in keyframe i's
            frame (metres, radians CCW, yaw wrapped to (−π, π]).
        costs: (K,) float64 matching costs (lower is more confident).
        accepted: (K,) bool, typically ``costs < threshold``.
        provenance: lines that say what the poses and costs depend on besides the two
            keyframes: the model's architecture and weights fingerprints and the metric
            search's settings (:func:`vvloc.localize.loops.loop_provenance`, which
            ``detect_loops`` fills in). The CSV writer writes them as ``#`` lines and
            :func:`read_loop_csv` reads them back; ``detect_loops(previous=...)`` keeps an
            earlier result's pairs only when they are its own. Empty (the default): not known.
    """

    i: np.ndarray
    j: np.ndarray
    relative_poses: np.ndarray
    costs: np.ndarray
    accepted: np.ndarray
    provenance: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        i = _to_array(self.i, "i")
        if i.ndim != 1:
            raise ValueError(f"i: expected shape (K,), got shape {i.shape}")
        k = i.shape[0]
        acc = _to_array(self.accepted, "accepted")
        if acc.shape == (0,):
            acc = acc.astype(bool)
        if acc.dtype != np.bool_:
            raise TypeError(f"accepted: expected a bool array ({k},), got dtype {acc.dtype}")
        if acc.shape != (k,):
            raise ValueError(f"accepted: expected shape ({k},), got shape {acc.shape}")
        poses = _floats(self.relative_poses, "relative_poses", f"({k}, 3)", (k, 3)).copy()
        poses[:, 2] = wrap_angle(poses[:, 2])
        values = {
            "i": _ints(self.i, "i", k),
            "j": _ints(self.j, "j", k),
            "relative_poses": poses,
            "costs": _floats(self.costs, "costs", f"({k},)", (k,)),
            "accepted": acc.copy(),
        }
        same = np.flatnonzero(values["i"] == values["j"])
        if same.size:  # g2o readers (ours too) refuse the edge such a loop becomes
            raise ValueError(
                f"i, j: a loop joins two keyframes, got keyframe {int(values['i'][same[0]])} to "
                f"itself (row {int(same[0])})"
            )
        for name, arr in values.items():
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "provenance", _provenance_lines(self.provenance))

    def __len__(self) -> int:
        return int(self.i.shape[0])

    def select(self, mask: Any) -> LoopClosures:
        """The subset given by a boolean mask (K,) or integer indices in [0, K) (in their
        order); ``TypeError``/``ValueError`` naming ``mask`` otherwise."""
        mask = _selection(mask, len(self), "mask")
        return LoopClosures(
            self.i[mask],
            self.j[mask],
            self.relative_poses[mask],
            self.costs[mask],
            self.accepted[mask],
            self.provenance,
        )


def _provenance_lines(lines: Any) -> tuple[str, ...]:
    """``lines`` checked as :attr:`LoopClosures.provenance`: an iterable of one-line strings
    that :func:`read_loop_csv` would read back as such (:data:`_PROVENANCE`); returned sorted,
    each once (the order :func:`~vvloc.localize.loops.loop_provenance` gives), so that the
    same lines in another order are the same provenance."""
    if isinstance(lines, str):
        raise TypeError("provenance: expected an iterable of str lines, got one str")
    try:
        out = tuple(lines)
    except TypeError:
        raise TypeError(
            f"provenance: expected an iterable of str lines, got {type(lines).__name__}"
        ) from None
    for line in out:
        if not isinstance(line, str):
            raise TypeError(f"provenance: expected str lines, got {type(line).__name__}")
        # one line as the CSV's comments split them (\r, \x0b, \u2028 too), or it is lost there
        if not _PROVENANCE.fullmatch(line) or line.splitlines() != [line]:
            raise ValueError(
                "provenance: expected lines 'model config <hex>', 'model weights <hex>' or "
                f"'search SearchConfig(...)' (loop_provenance), got {line!r}"
            )
    return tuple(sorted(set(out)))


#: A provenance line of a loop-closure CSV (:attr:`LoopClosures.provenance`), as ``vvloc
#: loops`` has written them into ``loops.csv`` since 2026-12-06.
_PROVENANCE = re.compile(
    r"model config [0-9a-f]+|model weights [0-9a-f]+|search SearchConfig\([^\n]*\)"
)


def _selection(sel: Any, n: int, name: str) -> np.ndarray:
    """``sel`` checked as a selection of ``n`` rows: a bool mask (n,) or integer indices in
    [0, n) (any order, repeats allowed), as an array numpy indexing takes; ``TypeError`` /
    ``ValueError`` naming ``name`` for anything else (numpy's ``IndexError`` named neither)."""
    arr = np.asarray(sel)
    if arr.dtype == np.bool_:
        if arr.shape != (n,):
            raise ValueError(f"{name}: expected a bool mask ({n},), got shape {arr.shape}")
        return arr
    if arr.size == 0:
        return np.zeros(0, np.int64)
    if not np.issubdtype(arr.dtype, np.integer):
        raise TypeError(f"{name}: expected a bool mask ({n},) or int indices, got {arr.dtype}")
    if arr.ndim != 1:
        raise ValueError(f"{name}: expected indices of shape (k,), got shape {arr.shape}")
    if arr.min() < 0 or arr.max() >= n:
        raise ValueError(f"{name}: expected indices in [0, {n}), got {arr.min()}..{arr.max()}")
    return arr


_LOOP_COLUMNS = ("i", "j", "x", "y", "yaw", "yaw_deg", "cost", "accepted")


def write_loop_csv(path: PathLike, loops: LoopClosures, *, comments: Iterable[str] = ()) -> Path:
    """Write loop closures as CSV: ``i,j,x,y,yaw,yaw_deg,cost,accepted``, one row per loop.

    ``#`` comment lines first state the conventions, then the loops' provenance (the model and
    search settings their poses came from, :attr:`LoopClosures.provenance`), then
    ``comments`` (e.g. the threshold or the map file); then a header row. ``accepted`` is
    written as 1/0. Read with :func:`read_loop_csv` or e.g. ``pandas.read_csv(path,
    comment="#")``. The file's text is :func:`loop_csv_text`.
    """
    text = loop_csv_text(loops, comments=comments)
    with atomic_write(path, "w", newline="") as f:
        f.write(text)
    return Path(path)


def loop_csv_text(loops: LoopClosures, *, comments: Iterable[str] = ()) -> str:
    """The text :func:`write_loop_csv` writes (``\\n`` line ends), for callers that write
    several files as one change (:func:`vvloc._io.write_together`)."""
    if not isinstance(loops, LoopClosures):
        raise TypeError(f"loops: expected LoopClosures, got {type(loops).__name__}")
    extra = _comment_lines(comments)  # once: comments may be a generator
    said = [c[2:] for c in extra if _PROVENANCE.fullmatch(c[2:])]
    if said:  # read back, it would pass for the loops' provenance
        raise ValueError(
            f"comments: {said[0]!r} reads as a provenance line; give the loops' provenance as "
            "LoopClosures.provenance"
        )
    header = (
        _comment_lines(
            [
                "vvloc loop closures",
                "i, j: keyframe ids; (x, y, yaw) = xi_{i->j}, the pose of keyframe j expressed in "
                "the frame of keyframe i (T_world_j = T_world_i * xi)",
                *_FRAME_COMMENTS,
                "yaw_deg: yaw in degrees; cost: matching cost (lower is better); "
                "accepted: 1 if the closure passed the cost threshold, else 0",
                *loops.provenance,
            ]
        )
        + extra
    )
    rows = []
    for r in range(len(loops)):
        x, y, yaw = loops.relative_poses[r]
        rows.append(
            [
                int(loops.i[r]),
                int(loops.j[r]),
                _r(x),
                _r(y),
                _r(yaw),
                _r(math.degrees(yaw)),
                _r(loops.costs[r]),
                int(bool(loops.accepted[r])),
            ]
        )
    return _csv_text(header, _LOOP_COLUMNS, rows)


def _csv_text(header: Iterable[str], columns: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    """``#`` header lines, then a CSV table (``\n`` line ends; fields quoted as RFC 4180 needs)."""
    f = io.StringIO(newline="")
    for line in header:
        f.write(line + "\n")
    w = csv.writer(f, lineterminator="\n")
    w.writerow(columns)
    w.writerows(rows)
    return f.getvalue()


_KEYFRAME_COLUMNS = ("id", "session", "seq", "timestamp", "floor", "x", "y", "yaw")


def keyframe_csv_text(
    ids: Any,
    sessions: Sequence[str],
    seq: Any,
    timestamps: Any,
    floors: Any,
    poses: Any,
    *,
    comments: Iterable[str] = (),
    digests: Sequence[str] | None = None,
) -> str:
    r"""The keyframe table beside a pose graph: one row per g2o vertex id with its session,
    sequence number, timestamp and floor, so that an optimised graph (keyed by vertex id) maps
    back to sessions and times. ``\n`` line ends, ``#`` header lines.

    Args:
        ids: (N,) int vertex ids (the map's keyframe ids).
        sessions: N session names; seq: (N,) int sequence numbers within a session.
        timestamps: (N,) seconds (written with microseconds kept: ``repr`` of the float;
            ``round(t * 1e6)``, not ``int``, gives back the microseconds, as the float is the
            nearest to them).
        floors: (N,) int storeys; poses: (N, 3) world (x, y, yaw), metres and radians CCW,
            the graph's initial vertex poses.
        digests: N strings for a last column ``descriptor_sha256`` (``vvloc loops``: a digest
            of each keyframe's stored local-view descriptors, which ``--reuse`` matches), or
            None for no such column.
    """
    p = _floats(poses, "poses", "(N, 3)", (None, 3))
    n = p.shape[0]
    vid, sq, fl = _ints(ids, "ids", n), _ints(seq, "seq", n), _ints(floors, "floors", n)
    t = _floats(timestamps, "timestamps", f"({n},)", (n,))
    if isinstance(sessions, str) or len(sessions) != n:
        raise ValueError(f"sessions: expected {n} session names")
    if digests is not None and (isinstance(digests, str) or len(digests) != n):
        raise ValueError(f"digests: expected {n} strings or None")
    header = _comment_lines(
        [
            "vvloc keyframes: the g2o vertex ids of graph.g2o and loops.csv (i, j), with their "
            "session, sequence number within it, timestamp (s; round(timestamp * 1e6) is the "
            "dataset's microseconds) and floor",
            "x, y, yaw: the keyframe's world pose, the graph's initial vertex pose",
            *_FRAME_COMMENTS,
            *(
                []
                if digests is None
                else [
                    "descriptor_sha256: 16 hex digits of the SHA-256 of the keyframe's stored "
                    "local-view descriptors (vvloc loops --reuse matches keyframes by them)"
                ]
            ),
        ]
    ) + _comment_lines(comments)
    rows = [
        [int(vid[r]), str(sessions[r]), int(sq[r]), _r(t[r]), int(fl[r]), _r(p[r, 0]),
         _r(p[r, 1]), _r(wrap_angle(p[r, 2]))]
        for r in range(n)
    ]  # fmt: skip
    if digests is None:
        return _csv_text(header, _KEYFRAME_COLUMNS, rows)
    for row, digest in zip(rows, digests, strict=True):
        row.append(str(digest))
    return _csv_text(header, (*_KEYFRAME_COLUMNS, "descriptor_sha256"), rows)


def _text_lines(p: Path, newline: str | None = None) -> list[str]:
    """The lines of the UTF-8 text file ``p`` (a BOM dropped), ``ValueError`` naming it when it
    is no regular file (a named pipe would block the reader forever) or not UTF-8 text."""
    check_readable_file(p)
    try:
        with open(p, encoding="utf-8-sig", newline=newline) as f:
            return f.readlines()
    except UnicodeDecodeError as e:
        raise ValueError(f"{p}: not UTF-8 text ({e})") from None


def _csv_fields(line: str) -> list[str]:
    """One CSV line's fields; ``ValueError`` for what the csv module refuses (a field beyond
    its size limit, an unclosed quote)."""
    try:
        return next(csv.reader([line]), [])
    except csv.Error as e:
        raise ValueError(f"not a CSV line ({e})") from None


def read_loop_csv(path: PathLike) -> LoopClosures:
    """Read a loop-closure CSV written by :func:`write_loop_csv`.

    ``#`` and blank lines are skipped, but for the provenance lines (``# model config …``,
    ``# model weights …``, ``# search SearchConfig(…)``), which become
    :attr:`LoopClosures.provenance`; the first other line is the header, which must name
    the columns ``i, j, x, y, yaw, cost, accepted`` once each (others, such as ``yaw_deg``, are
    ignored); every row has the header's number of fields. Ids are integers, values finite
    numbers as C reads them, ``accepted`` is 1/0/true/false. Anything else raises
    ``ValueError`` naming the file, the line and the column.
    """
    p = Path(os.fspath(path))
    need = ("i", "j", "x", "y", "yaw", "cost", "accepted")
    flags = {"1": True, "0": False, "true": True, "false": False}
    cols: dict[str, list[Any]] = {c: [] for c in need}
    for lineno, fields, at in _csv_table(p, need, _LOOP_COLUMNS, "loop-closure"):
        try:
            for c in ("i", "j"):
                cols[c].append(_int_field(fields[at[c]], c))
            for c in ("x", "y", "yaw", "cost"):
                cols[c].append(_float_field(fields[at[c]], c))
            flag = fields[at["accepted"]]
            if flag.lower() not in flags:
                raise ValueError(f"accepted: expected 1, 0, true or false, got {flag!r}")
            cols["accepted"].append(flags[flag.lower()])
            if cols["i"][-1] == cols["j"][-1]:
                raise ValueError(f"i, j: a loop joins two keyframes, got {cols['i'][-1]} twice")
        except ValueError as e:
            raise ValueError(f"{p}:{lineno}: malformed loop-closure row: {e}") from None
    return LoopClosures(
        i=np.array(cols["i"], np.int64),
        j=np.array(cols["j"], np.int64),
        relative_poses=np.array([cols["x"], cols["y"], cols["yaw"]], np.float64).T.reshape(-1, 3),
        costs=np.array(cols["cost"], np.float64),
        accepted=np.array(cols["accepted"], bool),
        provenance=_provenance_comments(p),
    )


def _provenance_comments(p: Path) -> tuple[str, ...]:
    """The provenance lines among the ``#`` lines of ``p`` before its header, read up to the
    header alone (``p`` has been read whole as a loop-closure CSV already: UTF-8 text)."""
    found: list[str] = []
    with open(p, encoding="utf-8-sig", newline="") as f:
        for line in f:
            text = line.strip()
            if text and not text.startswith("#"):
                break  # the header
            if _PROVENANCE.fullmatch(text[1:].strip()):
                found.append(text[1:].strip())
    return tuple(found)


def _csv_table(
    p: Path, need: Sequence[str], columns: Sequence[str], what: str
) -> Iterable[tuple[int, list[str], dict[str, int]]]:
    """The rows of the CSV file ``p`` written by one of this module's writers: ``#`` and blank
    lines skipped, the first other line the header, which must name each of ``need`` once
    (``columns``: the writer's, for the message); yields ``(line number, fields, column
    index by name)`` for each row, which has the header's number of fields. ``ValueError``
    naming the file and line otherwise (``what``: the table, for the message)."""
    lines = [
        (n, line)
        for n, line in enumerate(_text_lines(p, newline=""), start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not lines:
        raise ValueError(
            f"{p}: no header line (columns {', '.join(columns)}): not a vvloc {what} CSV"
        )
    head_line, head = lines[0]
    try:
        header = [h.strip() for h in _csv_fields(head)]
    except ValueError as e:
        raise ValueError(f"{p}:{head_line}: {e}") from None
    missing = [c for c in need if c not in header]
    if missing:
        raise ValueError(f"{p}:{head_line}: the header lacks columns {missing}, got {header}")
    repeated = sorted({c for c in need if header.count(c) > 1})
    if repeated:
        raise ValueError(f"{p}:{head_line}: the header names columns {repeated} more than once")
    at = {c: header.index(c) for c in need}
    for lineno, line in lines[1:]:
        try:
            fields = [v.strip() for v in _csv_fields(line)]
            if len(fields) != len(header):
                raise ValueError(f"expected the header's {len(header)} fields, got {len(fields)}")
        except ValueError as e:
            raise ValueError(f"{p}:{lineno}: malformed {what} row: {e}") from None
        yield lineno, fields, at


@dataclass(frozen=True, eq=False)
class KeyframeTable:
    """The keyframes of a pose graph, as ``keyframes.csv`` (:func:`keyframe_csv_text`) lists
    them: row k describes g2o vertex ``ids[k]``.

    Attributes:
        ids: (N,) int64 vertex ids (the map's keyframe ids).
        sessions: N session names.
        seq: (N,) int64 sequence numbers within their sessions.
        timestamps: (N,) float64 seconds; :attr:`timestamps_us` the dataset's microseconds.
        floors: (N,) int64 storeys, as each session numbers them.
        poses: (N, 3) float64 world poses (x, y in metres, yaw in radians CCW), the graph's
            initial vertex poses.
    """

    ids: np.ndarray
    sessions: tuple[str, ...]
    seq: np.ndarray
    timestamps: np.ndarray
    floors: np.ndarray
    poses: np.ndarray

    @property
    def timestamps_us(self) -> np.ndarray:
        """(N,) int64 microseconds: the timestamps rounded back to the dataset's."""
        return np.round(self.timestamps * 1e6).astype(np.int64)


def read_keyframe_csv(path: PathLike) -> KeyframeTable:
    """Read a ``keyframes.csv`` written by ``vvloc loops`` (:func:`keyframe_csv_text`).

    ``#`` and blank lines are skipped; the first other line is the header, which must name the
    columns ``id, session, seq, timestamp, floor, x, y, yaw`` once each (others are ignored);
    every row has the header's number of fields (a session name holding a comma is quoted).
    Ids, sequence numbers and floors are integers and the rest finite numbers, as C reads them;
    anything else raises ``ValueError`` naming the file, the line and the column.
    """
    p = Path(os.fspath(path))
    ints, floats = ("id", "seq", "floor"), ("timestamp", "x", "y", "yaw")
    cols: dict[str, list[Any]] = {c: [] for c in _KEYFRAME_COLUMNS}
    for lineno, fields, at in _csv_table(p, _KEYFRAME_COLUMNS, _KEYFRAME_COLUMNS, "keyframe"):
        try:
            for c in ints:
                cols[c].append(_int_field(fields[at[c]], c))
            for c in floats:
                cols[c].append(_float_field(fields[at[c]], c))
            cols["session"].append(fields[at["session"]])
        except ValueError as e:
            raise ValueError(f"{p}:{lineno}: malformed keyframe row: {e}") from None
    return KeyframeTable(
        ids=np.array(cols["id"], np.int64),
        sessions=tuple(cols["session"]),
        seq=np.array(cols["seq"], np.int64),
        timestamps=np.array(cols["timestamp"], np.float64),
        floors=np.array(cols["floor"], np.int64),
        poses=np.array([cols["x"], cols["y"], cols["yaw"]], np.float64).T.reshape(-1, 3),
    )


# ---------------------------------------------------------------------------------------------
# g2o


@dataclass(frozen=True, eq=False)
class G2OGraph:
    """A 2D pose graph read from a g2o file.

    Attributes:
        vertex_ids: (N,) int64, in file order.
        vertex_poses: (N, 3) float64 world poses (x, y, theta): metres, radians
            counter-clockwise, as the file holds them.
        edges: (E, 2) int64 (i, j) vertex ids, in file order.
        measurements: (E, 3) float64 ξ_{i→j} (vertex j in vertex i's frame): metres,
            radians.
        information: (E, 3, 3) float64 symmetric information matrices.
    """

    vertex_ids: np.ndarray
    vertex_poses: np.ndarray
    edges: np.ndarray
    measurements: np.ndarray
    information: np.ndarray


def _odometry_pairs(n: int, sessions: Sequence[Any] | None, seq: np.ndarray | None) -> np.ndarray:
    """(E, 2) rows (a, b) of consecutive keyframes within each session."""
    if sessions is None:
        labels: list[Any] = [0] * n
    else:
        labels = list(sessions)
        if len(labels) != n:
            raise ValueError(f"sessions: expected {n} session labels, got {len(labels)}")
    groups: dict[Any, list[int]] = {}
    for r, s in enumerate(labels):
        try:
            groups.setdefault(s, []).append(r)
        except TypeError:
            raise TypeError(
                f"sessions: labels must be hashable (str, int, ...), got {type(s).__name__} "
                f"at row {r}"
            ) from None
    pairs: list[tuple[int, int]] = []
    for rows_list in groups.values():
        rows = np.array(rows_list, np.int64)
        if seq is not None:
            rows = rows[np.argsort(seq[rows], kind="stable")]
        pairs.extend(zip(rows[:-1].tolist(), rows[1:].tolist(), strict=True))
    return np.array(pairs, np.int64).reshape(-1, 2)


def write_g2o(
    path: PathLike,
    poses: Any,
    loops: LoopClosures | None = None,
    *,
    ids: Any = None,
    sessions: Sequence[Any] | None = None,
    seq: Any = None,
    odometry_information: Any = None,
    loop_information: Any = None,
    only_accepted: bool = True,
) -> Path:
    """Write a 2D pose graph in g2o format (the text of :func:`g2o_text`).

    Args:
        path: output file.
        poses: (N, 3) world poses (x, y, yaw) of the keyframes, metres and radians
            counter-clockwise (the map's world frame): one ``VERTEX_SE2`` each.
        loops: loop closures; ``loops.i``/``loops.j`` are vertex ids (entries of ``ids``).
            Each becomes ``EDGE_SE2 i j x y yaw`` + information (only the accepted ones unless
            ``only_accepted`` is false).
        ids: (N,) int vertex ids (keyframe ids), unique, in [0, 2^31 - 1] (g2o's vertex ids
            are non-negative C ints); default ``0..N-1``.
        sessions: (N,) session labels (any hashable): an odometry ``EDGE_SE2`` links each pair
            of consecutive keyframes of a session, its measurement the relative pose of the two
            poses (:func:`relative_pose`). Default: all N keyframes form one session.
        seq: (N,) int order of keyframes within their session; default: array order.
        odometry_information: (3, 3) information matrix of the odometry edges; default
            :func:`information_from_sigmas` of :data:`DEFAULT_ODOMETRY_SIGMAS`.
        loop_information: (3, 3), or (K, 3, 3) one per loop (all K, before the ``accepted``
            filter), information matrices of the loop edges; default
            :func:`information_from_sigmas` of :data:`DEFAULT_LOOP_SIGMAS`. Constant by
            default because the matching cost is a confidence score, not a calibrated
            covariance; pass per-loop matrices to weight loops by cost or by a learned model.
        only_accepted: write only loops with ``accepted`` true (a bool).

    Vertex thetas are written wrapped to (−π, π]. The file holds ``VERTEX_SE2`` lines, then
    odometry edges (sessions in order of first appearance), then loop edges, and no comment
    lines (not every g2o reader skips them); its conventions are in :data:`G2O_CONVENTIONS`.
    Information matrices are written as the upper triangle I11 I12 I13 I22 I23 I33 of
    (dx, dy, dtheta).
    """
    text = g2o_text(
        poses,
        loops,
        ids=ids,
        sessions=sessions,
        seq=seq,
        odometry_information=odometry_information,
        loop_information=loop_information,
        only_accepted=only_accepted,
    )
    with atomic_write(path, "w") as f:
        f.write(text)
    return Path(path)


def g2o_text(
    poses: Any,
    loops: LoopClosures | None = None,
    *,
    ids: Any = None,
    sessions: Sequence[Any] | None = None,
    seq: Any = None,
    odometry_information: Any = None,
    loop_information: Any = None,
    only_accepted: bool = True,
) -> str:
    """The g2o text :func:`write_g2o` writes (arguments as there; ``\\n`` line ends), for
    callers that write several files as one change (:func:`vvloc._io.write_together`)."""
    p = _floats(poses, "poses", "(N, 3)", (None, 3))
    n = p.shape[0]
    vid = np.arange(n, dtype=np.int64) if ids is None else _ints(ids, "ids", n)
    if np.unique(vid).size != n:
        raise ValueError("ids: vertex ids must be unique")
    if n and (vid.min() < 0 or vid.max() > G2O_MAX_ID):
        raise ValueError(
            f"ids: g2o vertex ids must lie in [0, {G2O_MAX_ID}], got {int(vid.min())}.."
            f"{int(vid.max())}"
        )
    flag(only_accepted, "only_accepted")
    seq_arr = None if seq is None else _ints(seq, "seq", n)
    if isinstance(sessions, str):
        raise TypeError("sessions: expected a sequence of N labels, got a str")
    pairs = _odometry_pairs(n, sessions, seq_arr)
    odo_info = information_from_sigmas(*DEFAULT_ODOMETRY_SIGMAS)
    if odometry_information is not None:
        odo_info = _information(odometry_information, "odometry_information", 1)[0]
    if loops is not None and not isinstance(loops, LoopClosures):
        raise TypeError(f"loops: expected LoopClosures or None, got {type(loops).__name__}")
    k = 0 if loops is None else len(loops)
    if loop_information is None:
        loop_info = np.broadcast_to(information_from_sigmas(*DEFAULT_LOOP_SIGMAS), (k, 3, 3))
    else:
        loop_info = _information(loop_information, "loop_information", k)

    edge_lines: list[str] = []

    def edge(a: int, b: int, xi: np.ndarray, info: np.ndarray) -> None:
        upper = (info[0, 0], info[0, 1], info[0, 2], info[1, 1], info[1, 2], info[2, 2])
        edge_lines.append(
            f"EDGE_SE2 {a} {b} {_r(xi[0])} {_r(xi[1])} {_r(xi[2])} "
            + " ".join(_r(v) for v in upper)
        )

    xi_odo = relative_pose(p[pairs[:, 0]], p[pairs[:, 1]])
    for (a, b), xi in zip(pairs, xi_odo, strict=True):
        edge(int(vid[a]), int(vid[b]), xi, odo_info)
    if loops is not None:
        known = set(vid.tolist())
        for name, arr in (("loops.i", loops.i), ("loops.j", loops.j)):
            unknown = sorted(set(arr.tolist()) - known)
            if unknown:
                raise ValueError(f"{name}: ids {unknown[:5]} are not vertex ids")
        for r in range(k):
            if only_accepted and not loops.accepted[r]:
                continue
            edge(int(loops.i[r]), int(loops.j[r]), loops.relative_poses[r], loop_info[r])

    vertex_lines = [
        f"VERTEX_SE2 {v} {_r(x)} {_r(y)} {_r(wrap_angle(th))}"
        for v, (x, y, th) in zip(vid.tolist(), p, strict=True)
    ]
    return "".join(line + "\n" for line in (*vertex_lines, *edge_lines))


def read_g2o(path: PathLike) -> G2OGraph:
    """Read the ``VERTEX_SE2`` and ``EDGE_SE2`` lines of a g2o file.

    Blank lines and ``#`` comments are skipped, as are lines with other tags (``FIX``, 3D
    types, ...), but a file of such lines alone, without one ``VERTEX_SE2`` or ``EDGE_SE2`` line
    (a 3D graph, or no g2o file at all: a TUM trajectory or a CSV), is refused with
    ``ValueError`` naming its tags; an empty file (or one of comments) is an empty graph.
    ``ValueError`` naming the file and line for a malformed vertex or edge line
    (field count, a number C would not read, a non-finite value, a vertex id outside
    [0, :data:`G2O_MAX_ID`]), a repeated vertex id, an edge from a vertex to itself, an
    information matrix that is not positive definite, or an edge whose endpoints no
    ``VERTEX_SE2`` line defines: what :func:`write_g2o` refuses to write.
    """
    p = Path(os.fspath(path))
    vids: list[int] = []
    vposes: list[list[float]] = []
    edges: list[tuple[int, int]] = []
    edge_lines: list[int] = []
    meas: list[list[float]] = []
    upper: list[list[float]] = []
    seen: set[int] = set()
    skipped: list[str] = []  # the other tags, in the order they first appear
    edge_fields = ("dx", "dy", "dtheta", "I11", "I12", "I13", "I22", "I23", "I33")
    for lineno, line in enumerate(_text_lines(p), start=1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        if tok[0] not in ("VERTEX_SE2", "EDGE_SE2") and tok[0] not in skipped:
            skipped.append(tok[0])
        try:
            if tok[0] == "VERTEX_SE2":
                if len(tok) != 5:
                    raise ValueError(f"expected 'VERTEX_SE2 id x y theta', got {len(tok)} fields")
                v = _vertex_id(tok[1], "id")
                if v in seen:
                    raise ValueError(f"vertex id {v} repeated")
                seen.add(v)
                vids.append(v)
                xyt = zip(tok[2:], ("x", "y", "theta"), strict=True)
                vposes.append([_float_field(t, n) for t, n in xyt])
            elif tok[0] == "EDGE_SE2":
                if len(tok) != 12:
                    raise ValueError(
                        "expected 'EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33', "
                        f"got {len(tok)} fields"
                    )
                a, b = _vertex_id(tok[1], "i"), _vertex_id(tok[2], "j")
                if a == b:
                    raise ValueError(f"an edge from vertex {a} to itself")
                values = [_float_field(t, n) for t, n in zip(tok[3:], edge_fields, strict=True)]
                edges.append((a, b))
                edge_lines.append(lineno)
                meas.append(values[:3])
                upper.append(values[3:])
        except ValueError as err:
            raise ValueError(f"{p}:{lineno}: malformed g2o line: {err}") from None
    if skipped and not vids and not edges:  # it read as an empty graph, without a word
        tags = ", ".join(repr(t[:40]) for t in skipped[:3]) + (", ..." if len(skipped) > 3 else "")
        raise ValueError(
            f"{p}: no VERTEX_SE2 or EDGE_SE2 line, only lines tagged {tags}: not a 2D g2o pose "
            "graph"
        )
    u = np.array(upper, np.float64).reshape(-1, 6)
    info = u[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3)
    if len(info):
        bad = np.flatnonzero(np.linalg.eigvalsh(info).min(axis=1) <= 0.0)
        if bad.size:
            raise ValueError(
                f"{p}:{edge_lines[bad[0]]}: malformed g2o line: the information matrix is not "
                "positive definite"
            )
    for (a, b), lineno in zip(edges, edge_lines, strict=True):
        for v in (a, b):
            if v not in seen:
                raise ValueError(
                    f"{p}:{lineno}: EDGE_SE2 {a} {b} joins vertex {v}, which no VERTEX_SE2 line "
                    "defines"
                )
    return G2OGraph(
        vertex_ids=np.array(vids, np.int64),
        vertex_poses=np.array(vposes, np.float64).reshape(-1, 3),
        edges=np.array(edges, np.int64).reshape(-1, 2),
        measurements=np.array(meas, np.float64).reshape(-1, 3),
        information=info,
    )


# ---------------------------------------------------------------------------------------------
# TUM trajectories


def write_tum(
    path: PathLike,
    timestamps: Any,
    poses: Any,
    *,
    z: Any = 0.0,
    comments: Iterable[str] = (),
) -> Path:
    """Write a trajectory in TUM format: ``timestamp tx ty tz qx qy qz qw`` per line (the
    text of :func:`tum_text`).

    Args:
        timestamps: (N,) seconds.
        poses: (N, 3) world poses (x, y, yaw), metres and radians CCW.
        z: height tz, a float or (N,) metres (default 0: vvloc's poses are 3-DoF; the
            header then says so, and to compare them in the plane).
        comments: extra ``#`` header lines (e.g. the map, the session).

    The orientation is the rotation by yaw (wrapped to (−π, π]) about the world z axis, as a
    unit quaternion (qx, qy, qz, qw) = (0, 0, sin(yaw/2), cos(yaw/2)). ``#`` header lines
    state the conventions (TUM/evo readers skip them).
    """
    text = tum_text(timestamps, poses, z=z, comments=comments)
    with atomic_write(path, "w") as f:
        f.write(text)
    return Path(path)


def tum_text(timestamps: Any, poses: Any, *, z: Any = 0.0, comments: Iterable[str] = ()) -> str:
    """The TUM text :func:`write_tum` writes (arguments as there; ``\\n`` line ends), for
    callers that write several files as one change (:func:`vvloc._io.write_together`)."""
    t = _floats(timestamps, "timestamps", "(N,)", (None,))
    n = t.shape[0]
    p = _floats(poses, "poses", f"({n}, 3)", (n, 3))
    z_arr = _to_array(z, "z")
    if z_arr.ndim == 0:
        z_arr = np.full(n, z_arr)
    zz = _floats(z_arr, "z", f"float or ({n},)", (n,))
    height = (
        "tz = 0: the poses are 3-DoF (x, y, yaw), no height is estimated; compare them in the "
        "x-y plane (e.g. evo's --project_to_plane xy)"
        if not zz.any()
        else "tz: height of the vehicle origin, as given with the poses"
    )
    header = _comment_lines(
        [
            "vvloc trajectory, TUM format: timestamp tx ty tz qx qy qz qw",
            "timestamp: seconds; (tx, ty, tz): vehicle origin in the world frame, metres",
            height,
            "(qx, qy, qz, qw): unit quaternion (scalar last) of the vehicle-to-world rotation, "
            "a rotation by yaw about z: (0, 0, sin(yaw/2), cos(yaw/2))",
            *_FRAME_COMMENTS,
        ]
    ) + _comment_lines(comments)
    lines = list(header)
    for r in range(n):
        half = 0.5 * float(wrap_angle(p[r, 2]))
        values = (t[r], p[r, 0], p[r, 1], zz[r], 0.0, 0.0, math.sin(half), math.cos(half))
        lines.append(" ".join(_r(v) for v in values))
    return "".join(line + "\n" for line in lines)


def read_tum(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory: (timestamps (N,) float64 s, poses (N, 3) float64 (x, y, yaw)).

    ``#`` and blank lines are skipped. The yaw is the heading of the rotation (its angle
    about z after projecting the rotated x axis onto the x-y plane), wrapped to (−π, π]; for
    planar rotations that is exactly the rotation angle. tz, roll and pitch are dropped.
    """
    p = Path(os.fspath(path))
    rows: list[list[float]] = []
    names = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
    for lineno, line in enumerate(_text_lines(p), start=1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        if len(tok) != 8:
            raise ValueError(
                f"{p}:{lineno}: expected 8 fields 'timestamp tx ty tz qx qy qz qw', got {len(tok)}"
            )
        try:
            row = [_float_field(v, n) for v, n in zip(tok, names, strict=True)]
        except ValueError as e:
            raise ValueError(f"{p}:{lineno}: malformed TUM line: {e}") from None
        rows.append(row)
    a = np.array(rows, np.float64).reshape(-1, 8)
    q = a[:, 4:8]
    # scaled by its largest entry first: (0, 0, 1e308, 1e308), a 90° yaw, overflowed the norm
    # to inf and read as 0°, and (0, 0, 1e-170, 1e-170) underflowed to a "zero quaternion"
    big = np.abs(q).max(axis=1, initial=0.0)
    if (big == 0).any():
        raise ValueError(f"{p}: zero quaternion at data row {int(np.argmin(big)) + 1}")
    q = q / big[:, None]
    norm = np.linalg.norm(q, axis=1)
    qx, qy, qz, qw = (q / norm[:, None]).T
    yaw = np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    poses = np.stack([a[:, 1], a[:, 2], wrap_angle(yaw)], axis=1)
    return a[:, 0].copy(), poses
