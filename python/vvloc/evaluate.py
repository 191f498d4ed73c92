"""Evaluation metrics of vvloc (the paper's protocol), on plain numpy arrays.

Units: positions and translation errors in metres; angles are radians in every input and degrees in
every output (errors, percentiles, report). Poses are ``(x, y, yaw)`` rows as in DESIGN.md §3;
relative poses are ξ_{s→t} = T_world_s⁻¹ · T_world_t (:func:`vvloc.geometry.relative`).

The functions know nothing about networks or datasets: the ``vvloc eval`` command runs the
localizer, then hands positions, retrieved indices, estimated poses and matching costs to them.

* Global localization — :func:`recall_at_n` (Recall@N at revisit radii), :func:`pose_accuracy`
  (AOE/APE percentiles), :func:`evaluate_robustness` (the same per perturbation).
* Loop closure — :func:`loop_closure_curve` (Precision/Recall@2m, PR sweep, best F1, CFER),
  :func:`cross_floor_events` (CFER over distinct events, with an upper confidence bound).
* Pose on loop pairs — :func:`loop_pose_metrics` (mRRE, mRTE, RR, confidence filter) and
  :func:`confidence_curve`.
* Latency — :func:`latency_summary`.

Undefined values (e.g. a recall with no eligible query) are ``nan``; the report writes them as
``null`` (JSON) and ``–`` (Markdown).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from vvloc._checks import (
    as_array,
    bool_array,
    finite_float,
    flag,
    int_array,
    positive_float,
    positive_int,
    real_array,
    real_number,
)
from vvloc._io import atomic_write
from vvloc.geometry import wrap_angle

__all__ = [
    "DEFAULT_COST_THRESHOLD",
    "DEFAULT_PERCENTILES",
    "DEFAULT_RADII",
    "DEFAULT_TOP_N",
    "SUMMARY_RECALLS",
    "SUMMARY_SWEEP_POINTS",
    "LoopClosureCurve",
    "RecallResult",
    "calibrate_acceptance",
    "confidence_curve",
    "cross_floor_events",
    "distinctiveness",
    "error_percentiles",
    "evaluate_robustness",
    "latency_summary",
    "loop_closure_curve",
    "loop_pose_metrics",
    "nearest_map_distance",
    "pose_accuracy",
    "pose_errors",
    "recall_at_n",
    "relative_pose_errors",
    "render_markdown",
    "self_loop_closure_curve",
    "thin_sweep",
    "to_jsonable",
    "write_report",
]

F64Array = npt.NDArray[np.float64]
I64Array = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: Revisit radii (m) of the paper's global-localization tables.
DEFAULT_RADII: tuple[float, ...] = (2.0, 5.0, 10.0, 20.0)
#: Ranks N of the paper's Recall@N tables.
DEFAULT_TOP_N: tuple[int, ...] = (1, 5)
#: Percentiles (%) of the AOE/APE tables.
DEFAULT_PERCENTILES: tuple[float, ...] = (25.0, 50.0, 75.0, 95.0)
#: The paper's confidence filter: keep loop pairs with matching cost below this value.
DEFAULT_COST_THRESHOLD = 0.75


# ----------------------------------------------------------------------------- validation


def _share(x: Any, name: str, closed_above: bool) -> float:
    """A finite share in (0, 1] (``closed_above``) or (0, 1), named in the error."""
    v = finite_float(x, name)
    if not (0.0 < v <= 1.0 if closed_above else 0.0 < v < 1.0):
        raise ValueError(
            f"{name}: expected a value in (0, {'1]' if closed_above else '1)'}, got {v}"
        )
    return v


def _sequence(x: Any, name: str, what: str) -> list[Any]:
    """The items of a non-string sequence (``radii=2.0`` refused naming ``name``)."""
    if isinstance(x, (str, bytes)) or not isinstance(x, (Sequence, np.ndarray)):
        raise TypeError(f"{name}: expected a sequence of {what}, got {x!r}")
    return list(np.asarray(x).reshape(-1)) if isinstance(x, np.ndarray) else list(x)


def _rank(n: Any, name: str) -> int:
    """An int rank (1.5 is not Recall@1 or Recall@2)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise TypeError(f"{name}: expected an int rank, got {n!r}")
    return int(n)


def _floors(
    query_floors: Any, db_floors: Any, num_queries: int, num_db: int
) -> tuple[I64Array, I64Array] | None:
    """Validate optional floor labels; both or neither must be given."""
    if query_floors is None and db_floors is None:
        return None
    if query_floors is None or db_floors is None:
        raise ValueError("query_floors and db_floors: give both or neither")
    qf = int_array(query_floors, "query_floors", f"({num_queries},)", 1)
    df = int_array(db_floors, "db_floors", f"({num_db},)", 1)
    if qf.shape[0] != num_queries:
        raise ValueError(f"query_floors: expected shape ({num_queries},), got {qf.shape}")
    if df.shape[0] != num_db:
        raise ValueError(f"db_floors: expected shape ({num_db},), got {df.shape}")
    return qf, df


def _pair_array(pairs: Any) -> I64Array:
    """``pairs`` as a ``(P, 2)`` int64 array (an empty input of any shape: no pairs)."""
    if not np.size(pairs):
        return np.zeros((0, 2), np.int64)
    return int_array(pairs, "pairs", "(P, 2)", 2, 2)


def _ratio(num: float, den: float) -> float:
    return float(num) / float(den) if den > 0 else float("nan")


# ----------------------------------------------------------------------------- ground truth


def nearest_map_distance(
    query_positions: npt.ArrayLike,
    db_positions: npt.ArrayLike,
    query_floors: npt.ArrayLike | None = None,
    db_floors: npt.ArrayLike | None = None,
) -> F64Array:
    """Distance (m) from each query to its nearest map frame (on the same floor when given).

    Args:
        query_positions: ``(Q, 2)`` world x, y of the queries (m).
        db_positions: ``(N, 2)`` world x, y of the map frames (m).
        query_floors, db_floors: optional ``(Q,)`` / ``(N,)`` integer floor labels.

    Returns:
        ``(Q,)`` float64 distances; ``inf`` where no map frame shares the query's floor.
    """
    q = real_array(query_positions, "query_positions", "(Q, 2)", 2, 2)
    d = real_array(db_positions, "db_positions", "(N, 2)", 2, 2)
    floors = _floors(query_floors, db_floors, q.shape[0], d.shape[0])
    out = np.full(q.shape[0], np.inf)
    if floors is None:
        if d.shape[0]:
            out[:] = cKDTree(d).query(q)[0]
        return out
    qf, df = floors
    for floor in np.unique(qf):
        on_floor = df == floor
        if on_floor.any():
            sel = qf == floor
            out[sel] = cKDTree(d[on_floor]).query(q[sel])[0]
    return out


# ----------------------------------------------------------------------------- global localization


@dataclass(frozen=True)
class RecallResult:
    """Recall@N of a ranked retrieval, per revisit radius (see :func:`recall_at_n`).

    Attributes:
        top_n: the ranks N of the table, e.g. ``(1, 5)``.
        radii: the revisit radii (m), e.g. ``(2, 5, 10, 20)``.
        recall: ``(len(top_n), len(radii))`` fractions in [0, 1] over the kept queries
            (``nan`` when no query is kept).
        kept: ``(Q,)`` bool, queries with a map frame within the eligibility radius.
        first_hit: ``(Q, len(radii))`` int64, 0-based rank of the first retrieved map frame
            within the radius (same floor when floors are given), ``-1`` when none of the K is.
        num_retrieved: K, the number of ranked results per query.
        eligibility_radius: the keep rule's radius (m): a query is kept when a map frame lies
            within it (see :func:`recall_at_n`).
    """

    top_n: tuple[int, ...]
    radii: tuple[float, ...]
    recall: F64Array
    kept: BoolArray
    first_hit: I64Array
    num_retrieved: int
    eligibility_radius: float = 2.0

    @property
    def num_queries(self) -> int:
        """Number of queries given (Q)."""
        return int(self.kept.shape[0])

    @property
    def num_kept(self) -> int:
        """Number of queries kept by the eligibility rule (the recall denominator)."""
        return int(self.kept.sum())

    def _radius_index(self, radius: float) -> int:
        radius = positive_float(radius, "radius")
        for i, r in enumerate(self.radii):  # exactly first: 2.0 and 2.00001 are two radii
            if r == radius:
                return i
        for i, r in enumerate(self.radii):  # then as typed (0.1 + 0.2 for 0.3)
            if np.isclose(r, radius, rtol=1e-12, atol=0.0):
                return i
        raise ValueError(f"radius: {radius} m is not one of the evaluated radii {self.radii}")

    def correct(self, n: int = 1, radius: float = 2.0) -> BoolArray:
        """``(Q,)`` bool: kept queries with a map frame within ``radius`` among their top ``n``.

        Excluded queries are False. ``correct(1, 2.0)`` marks the queries whose top-1 is a true
        revisit (the AOE/APE subset). ``radius`` (m) must be one of the evaluated
        :attr:`radii` (``ValueError`` otherwise: run :func:`recall_at_n` with it).
        """
        n = _rank(n, "n")
        if not 1 <= n <= self.num_retrieved:
            raise ValueError(f"n: expected 1 <= n <= K = {self.num_retrieved}, got {n}")
        hit = self.first_hit[:, self._radius_index(radius)]
        return self.kept & (hit >= 0) & (hit < n)

    def at(self, n: int, radius: float) -> float:
        """Recall@``n`` at ``radius`` (m, one of the evaluated :attr:`radii`), a fraction over
        the kept queries (``nan`` if none)."""
        return _ratio(self.correct(n, radius).sum(), self.num_kept)

    def curve(self, radius: float = 2.0) -> tuple[I64Array, F64Array]:
        """Recall@N for N = 1..K at ``radius`` (m, one of the evaluated :attr:`radii`):
        ``(ns (K,) int64, recall (K,) float64)``."""
        hit = self.first_hit[self.kept, self._radius_index(radius)]
        ns = np.arange(1, self.num_retrieved + 1, dtype=np.int64)
        if hit.size == 0:
            return ns, np.full(ns.shape, np.nan)
        counts = np.array([(hit >= 0) & (hit < n) for n in ns]).sum(axis=1)
        return ns, counts / hit.size

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly summary: counts and ``recall[str(N)][f"{radius:g}"]``."""
        return {
            "num_queries": self.num_queries,
            "num_kept": self.num_kept,
            "eligibility_radius_m": self.eligibility_radius,
            "top_n": list(self.top_n),
            "radii_m": list(self.radii),
            "recall": {
                str(n): {f"{r:g}": float(self.recall[i, j]) for j, r in enumerate(self.radii)}
                for i, n in enumerate(self.top_n)
            },
        }


def recall_at_n(
    query_positions: npt.ArrayLike,
    db_positions: npt.ArrayLike,
    retrieved: npt.ArrayLike,
    *,
    query_floors: npt.ArrayLike | None = None,
    db_floors: npt.ArrayLike | None = None,
    top_n: Sequence[int] = DEFAULT_TOP_N,
    radii: Sequence[float] = DEFAULT_RADII,
    eligibility_radius: float = 2.0,
) -> RecallResult:
    """Recall@N of a ranked retrieval at several revisit radii.

    Definition: a query is *kept* when at least one map frame lies within
    ``eligibility_radius`` (2 m, on the same floor when floors are given) of its ground-truth
    position — queries of places the map never visited are left out, as the standard protocol
    does, whatever the revisit radius. A kept query counts for Recall@N at radius r when any of
    its top-N retrieved map frames lies within r (Euclidean distance ≤ r in the x-y plane) and, when
    floors are given, on the query's floor. Recall@N(r) = counted queries / kept queries.

    The same function scores retrieval alone and after metric re-ranking: pass the re-ranked
    indices for the latter (method labels such as ``-G``/``-N``/``-V``/``-ML`` are the caller's).

    Args:
        query_positions: ``(Q, 2)`` ground-truth world x, y of the queries (m).
        db_positions: ``(N, 2)`` world x, y of the map frames (m).
        retrieved: ``(Q, K)`` integer map indices, best first; ``-1`` marks an empty slot.
        query_floors, db_floors: optional ``(Q,)`` / ``(N,)`` integer floor labels (both or none).
        top_n: the ranks N to tabulate, each in ``1..K``.
        radii: the revisit radii (m), each > 0.
        eligibility_radius: the radius (m) of the keep rule.

    Returns:
        A :class:`RecallResult` (``num_kept`` says how many queries were kept).
    """
    q = real_array(query_positions, "query_positions", "(Q, 2)", 2, 2)
    d = real_array(db_positions, "db_positions", "(N, 2)", 2, 2)
    idx = int_array(retrieved, "retrieved", "(Q, K)", 2)
    num_q, num_db = q.shape[0], d.shape[0]
    if idx.shape[0] != num_q:
        raise ValueError(f"retrieved: expected {num_q} rows (one per query), got {idx.shape}")
    k = idx.shape[1]
    if idx.size and (idx.min() < -1 or idx.max() >= num_db):
        raise ValueError(f"retrieved: indices must lie in [-1, {num_db}) (N = {num_db} map frames)")
    floors = _floors(query_floors, db_floors, num_q, num_db)
    ranks = _sequence(top_n, "top_n", "int ranks")
    if not all(isinstance(n, (int, np.integer)) and not isinstance(n, bool) for n in ranks):
        raise TypeError(f"top_n: expected a sequence of int ranks, got {top_n!r}")  # 1.5 as 1
    ns = tuple(int(n) for n in ranks)
    if not ns or any(not 1 <= n <= k for n in ns):
        hint = ""
        if top_n is DEFAULT_TOP_N:  # the caller set no top_n: say what the default asks
            hint = (
                f" (the default top_n {DEFAULT_TOP_N} needs K >= {max(DEFAULT_TOP_N)} "
                "retrieved per query; pass top_n=(1,) or retrieve more)"
            )
        raise ValueError(f"top_n: expected ranks in 1..K = {k}, got {ns}{hint}")
    repeated = sorted({n for n in ns if ns.count(n) > 1})
    if repeated:
        raise ValueError(f"top_n: ranks {repeated} listed more than once")
    rs = tuple(positive_float(r, "radii") for r in _sequence(radii, "radii", "radii (m)"))
    if not rs:
        raise ValueError("radii: expected at least one radius")
    labels = [f"{r:g}" for r in rs]  # the keys of to_dict() and of the report
    same = sorted({lab for lab in labels if labels.count(lab) > 1})
    if same:
        raise ValueError(
            f"radii: {[r for r in rs if f'{r:g}' in same]} are one radius in the report "
            f"(labelled {same}); give each radius once"
        )
    elig = positive_float(eligibility_radius, "eligibility_radius")

    nearest = nearest_map_distance(q, d, *(floors if floors is not None else (None, None)))
    kept = nearest <= elig

    valid = idx >= 0
    safe = np.where(valid, idx, 0)
    dist = (
        np.linalg.norm(d[safe] - q[:, None, :], axis=-1) if num_db else np.full(idx.shape, np.inf)
    )
    if floors is not None and num_db:  # an empty map has no floor to compare with
        valid &= floors[1][safe] == floors[0][:, None]
    first_hit = np.full((num_q, len(rs)), -1, dtype=np.int64)
    for j, r in enumerate(rs):
        hit = valid & (dist <= r)
        any_hit = hit.any(axis=1)
        first_hit[any_hit, j] = hit[any_hit].argmax(axis=1)

    num_kept = int(kept.sum())
    recall = np.full((len(ns), len(rs)), np.nan)
    for i, n in enumerate(ns):
        counted = kept[:, None] & (first_hit >= 0) & (first_hit < n)
        recall[i] = counted.sum(axis=0) / num_kept if num_kept else np.nan
    return RecallResult(ns, rs, recall, kept, first_hit, k, elig)


def evaluate_robustness(
    query_positions: npt.ArrayLike,
    db_positions: npt.ArrayLike,
    retrieved: Mapping[str, npt.ArrayLike],
    **kwargs: Any,
) -> dict[str, RecallResult]:
    """Recall@N per perturbation: ``{name: recall_at_n(query_positions, db_positions, r, **kw)}``.

    ``retrieved`` maps a perturbation name (e.g. ``"none"``, ``"fog"``, ``"drop-camera"``) to the
    ``(Q, K)`` ranked indices obtained with perturbed query images; the ground-truth positions are
    the same for all. ``kwargs`` go to :func:`recall_at_n` (floors, top_n, radii, ...). The order of
    ``retrieved`` is kept.
    """
    if not isinstance(retrieved, Mapping):
        raise TypeError("retrieved: expected a mapping {perturbation name: (Q, K) indices}")
    return {
        str(name): recall_at_n(query_positions, db_positions, r, **kwargs)
        for name, r in retrieved.items()
    }


# ----------------------------------------------------------------------------- pose errors


def pose_errors(estimated: npt.ArrayLike, ground_truth: npt.ArrayLike) -> tuple[F64Array, F64Array]:
    """Absolute yaw and position errors of poses.

    Args:
        estimated: ``(Q, 3)`` estimated poses (x, y in m, yaw in rad), any common frame.
        ground_truth: ``(Q, 3)`` true poses in the same frame.

    Returns:
        ``(yaw_error_deg (Q,), position_error_m (Q,))``: ``|wrap(yaw_est − yaw_gt)|`` in degrees
        (in [0, 180], so 179° vs −179° is 2°) and the Euclidean distance of the x, y parts.
    """
    est = real_array(estimated, "estimated", "(Q, 3)", 2, 3)
    gt = real_array(ground_truth, "ground_truth", "(Q, 3)", 2, 3)
    if est.shape != gt.shape:
        raise ValueError(f"estimated, ground_truth: shapes differ ({est.shape} vs {gt.shape})")
    yaw = np.degrees(np.abs(wrap_angle(est[:, 2] - gt[:, 2])))
    return yaw, np.linalg.norm(est[:, :2] - gt[:, :2], axis=1)


def relative_pose_errors(
    estimated: npt.ArrayLike, ground_truth: npt.ArrayLike
) -> tuple[F64Array, F64Array]:
    """Relative rotation / translation errors (RRE °, RTE m) of relative poses ξ_{s→t}.

    Both inputs are ``(P, 3)`` relative poses in the source frame (DESIGN.md §3; build the ground
    truth with :func:`vvloc.geometry.relative`). RRE = ``|wrap(φ_est − φ_gt)|`` in degrees,
    RTE = ``‖t_est − t_gt‖`` in metres (both translations in source coordinates). Returns
    (RRE (P,), RTE (P,)), float64.
    """
    return pose_errors(estimated, ground_truth)


def _absolute_errors(x: npt.ArrayLike, name: str) -> F64Array:
    """``x`` as a finite ``(n,)`` float64 array of absolute errors, a negative one refused: a
    signed sample's percentiles or means say nothing about the error's size."""
    e = real_array(x, name, "(n,)", 1)
    if (e < 0).any():
        raise ValueError(
            f"{name}: expected absolute errors (>= 0), got {int((e < 0).sum())} negative, the "
            f"smallest {float(e.min()):.6g}: pass np.abs() of a signed error"
        )
    return e


def error_percentiles(
    errors: npt.ArrayLike, percentiles: Sequence[float] = DEFAULT_PERCENTILES
) -> F64Array:
    """Percentiles of an error sample: the smallest error e with at least p% of samples ≤ e.

    ``errors`` is ``(n,)`` of absolute errors (≥ 0, e.g. degrees or metres), finite. A signed
    sample (yaw differences in (−180°, 180°]) is refused rather than ranked: its percentiles
    would rank −170° below 1°; pass its absolute values. This is the inverted-CDF percentile (no
    interpolation), so every value is an observed error:
    ``error_percentiles([0, 0, 0, 90], (50, 75, 95)) == [0, 0, 90]``. Returns ``(len(p),)``
    float64, ``nan`` for an empty sample.
    """
    e = _absolute_errors(errors, "errors")
    items = _sequence(percentiles, "percentiles", "percentages in [0, 100]")
    p = np.array([finite_float(v, "percentiles") for v in items], dtype=np.float64)
    if ((p < 0) | (p > 100)).any():
        raise ValueError(f"percentiles: expected values in [0, 100], got {p.tolist()}")
    if e.size == 0:
        return np.full(p.shape, np.nan)
    # the k-th smallest, k = ceil(n p / 100): taken in n p / 100 order and rounded to 1e-9, so
    # that float noise never moves k up one sample (numpy's inverted_cdf rounds p / 100 first:
    # p = 7 of 100 samples took the 8th); k >= 1 (p = 0: the smallest)
    k = np.maximum(np.ceil(np.round(e.size * p / 100.0, 9)).astype(np.int64), 1)
    return np.sort(e)[k - 1]


def _aoe_ape(yaw_deg: F64Array, pos_m: F64Array, percentiles: Sequence[float]) -> dict[str, Any]:
    aoe = error_percentiles(yaw_deg, percentiles)
    ape = error_percentiles(pos_m, percentiles)
    out: dict[str, Any] = {"count": int(yaw_deg.size)}
    for p, a in zip(percentiles, aoe, strict=True):
        out[f"AOE@{p:g}"] = float(a)
    for p, a in zip(percentiles, ape, strict=True):
        out[f"APE@{p:g}"] = float(a)
    return out


def pose_accuracy(
    estimated: npt.ArrayLike,
    ground_truth: npt.ArrayLike,
    correct: npt.ArrayLike,
    *,
    kept: npt.ArrayLike | None = None,
    same_floor: npt.ArrayLike | None = None,
    pose_keyframe_correct: npt.ArrayLike | None = None,
    percentiles: Sequence[float] = DEFAULT_PERCENTILES,
) -> dict[str, dict[str, Any]]:
    """AOE/APE@p: percentiles of absolute yaw error (°) and position error (m) of global poses.

    Args:
        estimated: ``(Q, 3)`` metric-localization world poses (x, y in m, yaw in rad).
        ground_truth: ``(Q, 3)`` true world poses.
        correct: ``(Q,)`` bool, queries whose top-1 is a true revisit
            (``RecallResult.correct(1, 2.0)`` after re-ranking).
        kept: ``(Q,)`` bool, the evaluated queries (``RecallResult.kept``); default all.
        same_floor: ``(Q,)`` bool, whether the keyframe the estimate was built on is on the
            query's floor; default all. An estimate on another floor joins different places
            (a (x, y, yaw) error of 0 there would be no success), so the ``all`` row leaves
            those queries out and counts them (``other_floor``).
        pose_keyframe_correct: optional ``(Q,)`` bool, whether the keyframe the estimate was
            built on (``metric_row``, chosen before the pose) is a true revisit. With snapping
            the reported top-1 is the retrieved keyframe nearest the estimated pose, so
            ``correct`` depends on the pose: a pose far off moves the top-1 away and leaves the
            query out of ``true_revisit``. This subset is chosen without the pose's error.
        percentiles: the p of AOE@p / APE@p, in %.

    Returns:
        ``{"true_revisit": row, "all": row, "every_query": row}``, plus ``"pose_keyframe":
        row`` (after ``true_revisit``) when ``pose_keyframe_correct`` is given; a row is
        ``{"count", "AOE@25", …, "APE@25", …}`` (see :func:`error_percentiles`).
        ``true_revisit`` covers ``correct & kept`` queries (a true revisit is on the query's
        floor), ``pose_keyframe`` ``pose_keyframe_correct & kept``, ``all`` every kept query
        answered on its floor, plus ``other_floor``, the kept queries answered on another floor
        (left out). ``every_query`` covers all Q queries, kept or not, whatever floor they
        were answered on (x-y and yaw errors only: an answer on another floor counts by its
        planar error, which may be small).
    """
    yaw, pos = pose_errors(estimated, ground_truth)
    n = yaw.shape[0]
    corr = bool_array(correct, "correct", n)
    keep = np.ones(n, dtype=bool) if kept is None else bool_array(kept, "kept", n)
    floor_ok = (
        np.ones(n, dtype=bool) if same_floor is None else bool_array(same_floor, "same_floor", n)
    )
    sub = corr & keep
    every = keep & floor_ok
    rows = {"true_revisit": _aoe_ape(yaw[sub], pos[sub], percentiles)}
    if pose_keyframe_correct is not None:
        basis = bool_array(pose_keyframe_correct, "pose_keyframe_correct", n) & keep
        rows["pose_keyframe"] = _aoe_ape(yaw[basis], pos[basis], percentiles)
    rows["all"] = _aoe_ape(yaw[every], pos[every], percentiles) | {
        "other_floor": int((keep & ~floor_ok).sum())
    }
    rows["every_query"] = _aoe_ape(yaw, pos, percentiles)
    return rows


# ----------------------------------------------------------------------------- loop closure


#: Recall levels of the fixed-recall operating points in :meth:`LoopClosureCurve.summary`.
SUMMARY_RECALLS = (0.05, 0.1, 0.2)
#: Points of the precision–recall sweep kept in :meth:`LoopClosureCurve.summary` (the JSON).
SUMMARY_SWEEP_POINTS = 256


@dataclass(frozen=True)
class LoopClosureCurve:
    """Loop-closure detection scored against ground truth (see :func:`loop_closure_curve`).

    Attributes:
        distances: ``(P,)`` sorted ascending scores of the evaluated candidate pairs.
        is_true: ``(P,)`` bool, pair is a true loop (same order as ``distances``).
        is_cross_floor: ``(P,)`` bool, pair joins different floors (all False without floors).
        has_floors: whether floor labels were given (CFER is ``nan`` otherwise).
        query_first_true: ``(Q_pos,)`` per query with a true revisit, the lowest score among its
            true candidate pairs (``inf`` when it has none): it is detected at τ iff this is ≤ τ.
        num_queries: number of queries evaluated.
        radius: the true-loop radius (m).
    """

    distances: F64Array
    is_true: BoolArray
    is_cross_floor: BoolArray
    has_floors: bool
    query_first_true: F64Array
    num_queries: int
    radius: float

    @property
    def num_positive_queries(self) -> int:
        """The recall denominator: queries with at least one true revisit."""
        return int(self.query_first_true.shape[0])

    def at(self, threshold: float, *, strict: bool = False) -> dict[str, Any]:
        """Metrics when pairs with score ≤ ``threshold`` are accepted (``strict``: score <
        ``threshold``, the loop detector's rule at its radius; the two differ only for scores
        exactly at the threshold).

        Returns ``{"threshold", "strict", "accepted", "true_accepted", "precision", "recall",
        "f1", "cfer"}``: precision = true accepted pairs / accepted pairs; recall = queries with ≥ 1
        accepted true pair / :attr:`num_positive_queries`; F1 = 2PR/(P+R) (0 when P = R = 0,
        and when nothing is accepted while positive queries exist: 2TP/(2TP + FP + FN) = 0);
        CFER = accepted pairs joining different floors / accepted pairs. Undefined → ``nan``.
        """
        t = real_number(threshold, "threshold")
        k = int(np.searchsorted(self.distances, t, side="left" if strict else "right"))
        tp = int(self.is_true[:k].sum())
        precision = _ratio(tp, k)
        first = self.query_first_true  # inf: no true candidate, found at no threshold
        found = np.isfinite(first) & ((first < t) if strict else (first <= t))
        recall = _ratio(found.sum(), self.num_positive_queries)
        cfer = _ratio(self.is_cross_floor[:k].sum(), k) if self.has_floors else float("nan")
        return {
            "threshold": t,
            "strict": bool(strict),
            "accepted": k,
            "true_accepted": tp,
            "precision": precision,
            "recall": recall,
            "f1": _f1(precision, recall),
            "cfer": cfer,
        }

    def sweep(self) -> dict[str, F64Array]:
        """The precision–recall sweep over every distinct score as threshold.

        Returns arrays of equal length M (distinct scores, ascending): ``threshold``,
        ``precision``, ``recall``, ``f1``, ``cfer`` (definitions of :meth:`at`).
        """
        if self.distances.size == 0:
            empty = np.zeros(0)
            return {k: empty for k in ("threshold", "precision", "recall", "f1", "cfer")}
        last = np.flatnonzero(np.append(np.diff(self.distances) > 0, True))  # last of each score
        thresholds = self.distances[last]
        accepted = last + 1.0
        true = np.cumsum(self.is_true)[last].astype(np.float64)
        precision = true / accepted
        first = np.sort(self.query_first_true)
        detected = np.searchsorted(first, thresholds, side="right").astype(np.float64)
        npos = float(self.num_positive_queries)
        recall = detected / npos if npos else np.full(thresholds.shape, np.nan)
        # F1 = 2PR / (P + R) = 2·TP·D / (TP·Q + D·A) (TP true pairs, A accepted, D detected of
        # Q positive queries): whole numbers (exact below 2**53) and one correctly rounded
        # division, so that equal F1s are equal floats and best_f1 takes the lowest threshold
        # (2PR / (P + R) rounded them an ulp apart, and nanargmax took a later one)
        den = true * npos + detected * accepted
        with np.errstate(invalid="ignore", divide="ignore"):
            f1 = np.where(den > 0, 2.0 * true * detected / np.where(den > 0, den, 1.0), 0.0)
        f1 = np.where(np.isnan(recall), np.nan, f1)
        cfer = (
            np.cumsum(self.is_cross_floor)[last] / accepted
            if self.has_floors
            else np.full(thresholds.shape, np.nan)
        )
        return {
            "threshold": thresholds,
            "precision": precision,
            "recall": recall,
            "f1": f1,
            "cfer": cfer,
        }

    def best_f1(self, sweep: dict[str, F64Array] | None = None) -> dict[str, Any]:
        """:meth:`at` the threshold of the sweep with the highest F1 (lowest such threshold).
        ``sweep``: this curve's :meth:`sweep`, when the caller already has it."""
        s = self.sweep() if sweep is None else sweep
        if s["f1"].size == 0 or np.isnan(s["f1"]).all():
            return _undefined_point()
        return self.at(float(s["threshold"][int(np.nanargmax(s["f1"]))]))

    def at_recall(self, recall: float, sweep: dict[str, F64Array] | None = None) -> dict[str, Any]:
        """:meth:`at` the lowest threshold of the sweep whose recall reaches ``recall`` (a share
        in (0, 1]), plus ``"target_recall"``: the operating point at a fixed recall, which
        compares detectors whose descriptor distances have different scales (a fixed radius
        does not). When no threshold reaches it among the evaluated pairs, every figure is
        ``nan`` (counts 0). ``sweep``: this curve's :meth:`sweep`, when the caller has it."""
        r = _share(recall, "recall", closed_above=True)
        s = self.sweep() if sweep is None else sweep
        reached = np.flatnonzero(s["recall"] >= r)
        point = self.at(float(s["threshold"][reached[0]])) if reached.size else _undefined_point()
        return {"target_recall": r} | point

    def summary(
        self,
        threshold: float,
        recalls: tuple[float, ...] = SUMMARY_RECALLS,
        *,
        strict: bool = False,
    ) -> dict[str, Any]:
        """JSON-friendly: metrics :meth:`at` ``threshold`` (``strict`` as there), ``best_f1``,
        :meth:`at_recall` of
        each of ``recalls`` (``at_recall``, a list), the counts (one sweep for all) and the
        precision–recall sweep itself at up to :data:`SUMMARY_SWEEP_POINTS` thresholds
        (``sweep``: :func:`thin_sweep` of :meth:`sweep`; it keeps the best-F1 point)."""
        sweep = self.sweep()
        return {
            "radius_m": self.radius,
            "num_queries": self.num_queries,
            "num_positive_queries": self.num_positive_queries,
            "num_pairs": int(self.distances.size),
            "at_threshold": self.at(threshold, strict=strict),
            "best_f1": self.best_f1(sweep),
            "at_recall": [self.at_recall(r, sweep) for r in recalls],
            "sweep": thin_sweep(sweep, SUMMARY_SWEEP_POINTS),
        }


def thin_sweep(sweep: Mapping[str, npt.ArrayLike], points: int) -> dict[str, F64Array]:
    """At most about ``points`` (an int >= 1) entries of a sweep (1-D real arrays of one length
    keyed by name, NaN allowed): half evenly spaced by rank, half (when ``recall`` is there) the
    first entry to reach each of evenly spaced recall levels, plus the first and last entries
    and the best F1 (when ``f1`` is there). A sweep over millions of pairs keeps its shape along
    both axes in a few kilobytes of JSON (by rank alone, the low-recall end would be one
    segment). Returns float64 arrays under the same names."""
    points = positive_int(points, "points")
    arrays = {}
    for k, v in sweep.items():
        arr = as_array(v, f"sweep[{k!r}]", "(n,)")
        if arr.dtype.kind not in "fiu" or arr.ndim != 1:  # no bool, complex or object
            raise ValueError(
                f"sweep[{k!r}]: expected a 1-D real array (n,), got {arr.dtype} {arr.shape}"
            )
        arrays[k] = arr.astype(np.float64)
    lengths = {k: len(v) for k, v in arrays.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"sweep: expected arrays of one length, got {lengths}")
    n = len(next(iter(arrays.values()))) if arrays else 0
    if n <= points:
        return arrays
    half = max(points // 2, 2)
    keep = [np.linspace(0, n - 1, half).round().astype(np.int64), np.array([0, n - 1])]
    recall = arrays.get("recall")
    if recall is not None and np.isfinite(recall).any():
        r = np.fmax.accumulate(np.nan_to_num(recall, nan=-np.inf))  # recall never falls
        levels = np.linspace(0.0, float(r[-1]), half)
        keep.append(np.minimum(np.searchsorted(r, levels, side="left"), n - 1))
    f1 = arrays.get("f1")
    if f1 is not None and np.isfinite(f1).any():
        keep.append(np.array([int(np.nanargmax(f1))]))
    idx = np.unique(np.concatenate(keep))
    return {k: v[idx] for k, v in arrays.items()}


def _undefined_point() -> dict[str, Any]:
    """A :meth:`LoopClosureCurve.at` result with no threshold: figures ``nan``, counts 0."""
    nan = float("nan")
    keys = ("threshold", "precision", "recall", "f1", "cfer")
    return {k: nan for k in keys} | {"accepted": 0, "true_accepted": 0}


def _f1(precision: float, recall: float) -> float:
    """2PR/(P+R); 0 when P = R = 0 and when nothing is accepted (P undefined) while positive
    queries exist (R = 0): F1 = 2TP/(2TP + FP + FN) = 0 then; ``nan`` without positives."""
    if np.isnan(recall):
        return float("nan")
    if np.isnan(precision):  # nothing accepted: TP = FP = 0, FN > 0
        return 0.0
    s = precision + recall
    return 2.0 * precision * recall / s if s > 0 else 0.0


def loop_closure_curve(
    pairs: npt.ArrayLike,
    distances: npt.ArrayLike,
    query_positions: npt.ArrayLike,
    db_positions: npt.ArrayLike,
    *,
    query_floors: npt.ArrayLike | None = None,
    db_floors: npt.ArrayLike | None = None,
    query_times: npt.ArrayLike | None = None,
    db_times: npt.ArrayLike | None = None,
    time_window: float = 0.0,
    causal: bool = False,
    symmetric: bool = False,
    radius: float = 2.0,
) -> LoopClosureCurve:
    """Score loop-closure candidates: Precision@2m / Recall@2m, PR sweep, best F1, CFER.

    Definitions. An *admissible* (query q, map frame j) pair is one outside the temporal-exclusion
    window: ``|t_q − t_j| > time_window`` and, when ``causal``, ``t_j < t_q`` (without times every
    pair is admissible). A pair is a *true loop* when admissible, ``‖p_q − p_j‖ ≤ radius`` and, with
    floors, on the same floor. A query is *positive* when it has at least one true loop among all
    map frames (the ground truth, not only the candidates): the recall denominator. Candidate pairs
    that are not admissible are ignored (the detector should not propose them). At a threshold τ,
    candidates with score ≤ τ are accepted; see :meth:`LoopClosureCurve.at` for precision, recall,
    F1 and CFER (share of accepted pairs joining different floors).

    For loop closure within one sequence pass the same positions/floors/times as query and map,
    and ``symmetric=True``: a detector lists each pair once (e.g. i < j), and a true pair then
    detects both of its frames, each of which is a query with a revisit (without it only the
    pair's first frame would count, and a perfect detector would score a recall of about 1/2).

    Args:
        pairs: ``(P, 2)`` integer (query index, map index) candidate pairs, each listed once (a
            pair listed twice is refused: it would count twice).
        distances: ``(P,)`` score of each pair, lower is better (descriptor distance, or the
            matching cost after metric verification).
        query_positions, db_positions: ``(Q, 2)`` / ``(N, 2)`` world x, y (m).
        query_floors, db_floors: optional ``(Q,)`` / ``(N,)`` integer floors (both or none).
        query_times, db_times: optional ``(Q,)`` / ``(N,)`` timestamps (s) or frame numbers.
        time_window: temporal-exclusion window, same unit as the times (≥ 0).
        causal: only earlier map frames count (loop closure against the past).
        symmetric: query and map are the same frames and each pair is listed once: a true pair
            detects both frames, and a frame is never its own loop (not with ``causal``).
        radius: true-loop radius (m).
    """
    q = real_array(query_positions, "query_positions", "(Q, 2)", 2, 2)
    d = real_array(db_positions, "db_positions", "(N, 2)", 2, 2)
    num_q, num_db = q.shape[0], d.shape[0]
    pr = _pair_array(pairs)
    dist = real_array(distances, "distances", "(P,)", 1)
    if dist.shape[0] != pr.shape[0]:
        raise ValueError(f"distances: expected shape ({pr.shape[0]},), got {dist.shape}")
    if pr.size and not (
        (pr[:, 0] >= 0).all()
        and (pr[:, 0] < num_q).all()
        and (pr[:, 1] >= 0).all()
        and (pr[:, 1] < num_db).all()
    ):
        raise ValueError(f"pairs: indices must lie in [0, {num_q}) x [0, {num_db})")
    floors = _floors(query_floors, db_floors, num_q, num_db)
    if (query_times is None) != (db_times is None):
        raise ValueError("query_times and db_times: give both or neither")
    times = None
    if query_times is not None:
        qt = real_array(query_times, "query_times", f"({num_q},)", 1)
        dt = real_array(db_times, "db_times", f"({num_db},)", 1)
        if qt.shape[0] != num_q or dt.shape[0] != num_db:
            raise ValueError("query_times, db_times: expected shapes (Q,) and (N,)")
        times = (qt, dt)
    window = finite_float(time_window, "time_window")
    if window < 0:
        raise ValueError(f"time_window: expected a finite value >= 0, got {time_window}")
    rad = positive_float(radius, "radius")
    causal, symmetric = flag(causal, "causal"), flag(symmetric, "symmetric")
    if symmetric and (causal or num_q != num_db):
        raise ValueError(
            "symmetric: needs the same frames as query and map (Q == N) and causal=False"
        )
    if pr.size:  # a pair listed twice (symmetric: also in both orders) would count twice
        keyed = np.sort(pr, axis=1) if symmetric else pr
        if symmetric:
            keyed = keyed[keyed[:, 0] != keyed[:, 1]]
        rows, counts = np.unique(keyed, axis=0, return_counts=True)
        if (counts > 1).any():
            first = int(np.argmax(counts > 1))
            listed = "once (e.g. i < j)" if symmetric else "once"
            raise ValueError(
                f"pairs: each pair is listed {listed}; ({rows[first, 0]}, {rows[first, 1]}) is "
                f"listed {counts[first]} times"
            )

    def admissible(qi: I64Array, dj: I64Array) -> BoolArray:
        # a frame is not its own loop (symmetric: the same frames as query and map)
        ok = qi != dj if symmetric else np.ones(qi.shape, dtype=bool)
        if times is not None:
            tq, td = times[0][qi], times[1][dj]
            ok &= np.abs(tq - td) > window
            if causal:
                ok &= td < tq
        return ok

    def same_floor(qi: I64Array, dj: I64Array) -> BoolArray:
        if floors is None:
            return np.ones(qi.shape, dtype=bool)
        return floors[0][qi] == floors[1][dj]

    # Ground truth: every admissible map frame within the radius, on the same floor.
    if num_q and num_db:
        # a little beyond the radius, then the pairs' own test below (the tree compares
        # squared distances: a pair at 2.0 m by norm could fall out of it)
        wide = rad * (1.0 + 1e-9) + 1e-12
        near = cKDTree(q).sparse_distance_matrix(cKDTree(d), wide, output_type="ndarray")
        gi, gj = near["i"].astype(np.int64), near["j"].astype(np.int64)
        within = np.linalg.norm(q[gi] - d[gj], axis=1) <= rad
        ok = admissible(gi, gj) & same_floor(gi, gj) & within
        positive = np.unique(gi[ok])
    else:
        positive = np.zeros(0, dtype=np.int64)

    keep = admissible(pr[:, 0], pr[:, 1])
    pr, dist = pr[keep], dist[keep]
    order = np.argsort(dist, kind="stable")
    pr, dist = pr[order], dist[order]
    close = np.linalg.norm(q[pr[:, 0]] - d[pr[:, 1]], axis=1) <= rad
    is_true = close & same_floor(pr[:, 0], pr[:, 1])
    cross = ~same_floor(pr[:, 0], pr[:, 1])

    first_true = np.full(num_q, np.inf)
    np.minimum.at(first_true, pr[is_true, 0], dist[is_true])
    if symmetric:  # the pair's other frame has found its revisit as well
        np.minimum.at(first_true, pr[is_true, 1], dist[is_true])
    return LoopClosureCurve(
        distances=dist,
        is_true=is_true,
        is_cross_floor=cross,
        has_floors=floors is not None,
        query_first_true=first_true[positive],
        num_queries=num_q,
        radius=rad,
    )


# ----------------------------------------------------------------------------- pose on loop pairs


def self_loop_closure_curve(
    pairs: npt.ArrayLike,
    distances: npt.ArrayLike,
    positions: npt.ArrayLike,
    floors: npt.ArrayLike,
    sessions: npt.ArrayLike,
    seqs: npt.ArrayLike,
    window: int,
    radius: float = 2.0,
) -> LoopClosureCurve:
    """:func:`loop_closure_curve` for loop closure within one set of frames (every frame is
    both query and map entry): ``positions`` (N, 2) world x, y (m); ``floors``, ``sessions``
    and ``seqs`` (N,) integers. Pairs of one session within ``window`` sequence numbers are
    temporal neighbours (not admissible); pairs of two sessions always are admissible. Each
    pair is listed once; a true pair detects both of its frames (``symmetric``)."""
    n = real_array(positions, "positions", "(N, 2)", 2, 2).shape[0]
    arrays = {}
    for name, x in (("floors", floors), ("sessions", sessions), ("seqs", seqs)):
        arrays[name] = int_array(x, name, f"({n},)", 1)
        if arrays[name].shape != (n,):
            raise ValueError(f"{name}: expected shape ({n},), got {arrays[name].shape}")
    w = positive_int(window, "window", minimum=0)
    # Times that loop_closure_curve compares in float64: each session's sequence numbers counted
    # from its first (only differences within a session matter, so nanosecond stamps of 10**18
    # lose nothing), the sessions laid end to end 2 spans apart, so that they never overlap.
    _, rank = np.unique(arrays["sessions"], return_inverse=True)
    rank = rank.reshape(-1)
    seq = arrays["seqs"]
    first = np.full(int(rank.max(initial=-1)) + 1, np.iinfo(np.int64).max, dtype=np.int64)
    np.minimum.at(first, rank, seq)
    rel = seq - first[rank]  # >= 0 unless a session spans 2**63 or more (int64 wraps)
    if (rel < 0).any():
        raise ValueError("seqs: expected each session's sequence numbers to span less than 2**63")
    longest = int(rel.max(initial=0))
    w = min(w, longest + 1)  # a wider window excludes the same pairs
    span = longest + w + 1
    if 2 * span * max(first.size, 1) >= 2**53:
        raise ValueError(
            f"seqs: each session's sequence numbers span up to {longest}, too many to compare "
            f"exactly over {first.size} sessions (expected under 2**53 in all)"
        )
    times = (rel + 2 * span * rank).astype(np.float64)
    return loop_closure_curve(
        pairs,
        distances,
        positions,
        positions,
        query_floors=floors,
        db_floors=floors,
        query_times=times,
        db_times=times,
        time_window=w,
        symmetric=True,
        radius=radius,
    )


def cross_floor_events(
    pairs: npt.ArrayLike,
    positions: npt.ArrayLike,
    floors: npt.ArrayLike,
    sessions: npt.ArrayLike,
    *,
    cell: float = 10.0,
    confidence: float = 0.95,
) -> dict[str, Any]:
    """CFER over distinct loop *events*, with its one-sided upper confidence bound.

    Accepted loop pairs come in runs (neighbouring keyframes of the same two drives), so they are
    not independent trials and a bound counted over pairs is too optimistic. An event is a
    distinct (unordered session pair, floor of the pair's first keyframe, ``cell``-metre grid
    cell of the first keyframe's x, y); it joins two floors when any of its pairs does.

    Args:
        pairs: ``(P, 2)`` integer indices of accepted pairs into the frame arrays; the first
            column is the pair's first keyframe (pass every pair in one orientation, e.g. the
            lower row first, so that a pair and its reverse fall into the same event).
        positions: ``(N, 2)`` world x, y (m); ``floors`` and ``sessions``: ``(N,)`` integers.
        cell: event grid size, m.
        confidence: level of the one-sided Clopper–Pearson upper bound (for no cross-floor event
            among n it is 1 − (1 − confidence)^(1/n), ≈ 3/n at 95 %).

    Returns ``{"events", "cross_floor_events", "cfer", "cfer_upper", "confidence", "cell_m"}``:
    CFER = cross-floor events / events and its bound (``nan`` without events).
    """
    pos = real_array(positions, "positions", "(N, 2)", 2, 2)
    n = pos.shape[0]
    fl = int_array(floors, "floors", "(N,)", 1)
    ses = int_array(sessions, "sessions", "(N,)", 1)
    if fl.shape != (n,) or ses.shape != (n,):
        raise ValueError(f"floors, sessions: expected ({n},) each, got {fl.shape} and {ses.shape}")
    pr = _pair_array(pairs)
    if pr.size and (pr.min() < 0 or pr.max() >= n):
        raise ValueError(f"pairs: expected indices in [0, {n}), got values outside it")
    cell = positive_float(cell, "cell")
    confidence = _share(confidence, "confidence", closed_above=False)
    a, b = pr[:, 0], pr[:, 1]
    with np.errstate(over="ignore"):
        cells = np.floor(pos[a] / cell)
    if not (np.abs(cells) < 2.0**62).all():  # astype would merge them into one wrapped cell
        raise ValueError(
            f"cell: {cell} m cells number more than 2**62 across the positions; take larger cells"
        )
    grid = cells.astype(np.int64)
    keys = np.stack(
        [np.minimum(ses[a], ses[b]), np.maximum(ses[a], ses[b]), fl[a], grid[:, 0], grid[:, 1]],
        axis=1,
    )
    _, event = np.unique(keys, axis=0, return_inverse=True)
    num = int(event.max()) + 1 if event.size else 0
    cross = np.zeros(num, dtype=bool)
    np.logical_or.at(cross, event.reshape(-1), fl[a] != fl[b])
    k = int(cross.sum())
    if num == 0:
        upper = float("nan")
    elif k == num:
        upper = 1.0
    else:
        from scipy.stats import beta

        upper = float(beta.ppf(confidence, k + 1, num - k))
    return {
        "events": num,
        "cross_floor_events": k,
        "cfer": _ratio(k, num),
        "cfer_upper": upper,
        "confidence": float(confidence),
        "cell_m": cell,
    }


def _loop_pose_row(
    rre: F64Array,
    rte: F64Array,
    on_floor: npt.NDArray[np.bool_],
    total: int,
    rot_threshold_deg: float,
    trans_threshold_m: float,
) -> dict[str, Any]:
    n, m = int(rre.size), int(on_floor.sum())
    return {
        "count": n,
        "share": _ratio(n, total),
        "cross_floor": n - m,
        "mRRE_deg": float(rre[on_floor].mean()) if m else float("nan"),
        "mRTE_m": float(rte[on_floor].mean()) if m else float("nan"),
        "RR_rot": _ratio((on_floor & (rre < rot_threshold_deg)).sum(), n),
        "RR_trans": _ratio((on_floor & (rte < trans_threshold_m)).sum(), n),
    }


def loop_pose_metrics(
    estimated: npt.ArrayLike,
    ground_truth: npt.ArrayLike,
    costs: npt.ArrayLike | None = None,
    *,
    cost_threshold: float = DEFAULT_COST_THRESHOLD,
    rot_threshold_deg: float = 5.0,
    trans_threshold_m: float = 2.0,
    same_floor: npt.ArrayLike | None = None,
) -> dict[str, dict[str, Any]]:
    """Relative-pose accuracy on detected loop pairs, with and without the confidence filter.

    Args:
        estimated: ``(P, 3)`` estimated relative poses ξ_{s→t} (m, rad).
        ground_truth: ``(P, 3)`` true relative poses (:func:`vvloc.geometry.relative`).
        costs: optional ``(P,)`` matching costs (lower = more confident).
        cost_threshold: the confidence filter keeps pairs with cost < this (paper: 0.75).
        rot_threshold_deg, trans_threshold_m: the RR thresholds (5°, 2 m).
        same_floor: optional ``(P,)`` bool, whether the pair's keyframes share a floor (default
            all). A cross-floor pair joins different places: its (x, y, yaw) errors mean
            nothing, so it counts as registered in neither RR and is left out of the means.

    Returns:
        ``{"all": row}`` plus ``{"confident": row}`` when costs are given. A row is
        ``{"count", "share", "cross_floor", "mRRE_deg", "mRTE_m", "RR_rot", "RR_trans"}``: mean
        RRE (°) and RTE (m) (:func:`relative_pose_errors`) over the pairs on one floor, RR_rot =
        share of the count on one floor with RRE < ``rot_threshold_deg``, RR_trans = with RTE <
        ``trans_threshold_m``, share = count / P, cross_floor = pairs across floors among the
        count. Undefined means are ``nan``.
    """
    rre, rte = relative_pose_errors(estimated, ground_truth)
    n = rre.shape[0]
    rot_t = positive_float(rot_threshold_deg, "rot_threshold_deg")
    trans_t = positive_float(trans_threshold_m, "trans_threshold_m")
    floor_ok = (
        np.ones(n, dtype=bool) if same_floor is None else bool_array(same_floor, "same_floor", n)
    )
    out = {"all": _loop_pose_row(rre, rte, floor_ok, n, rot_t, trans_t)}
    if costs is not None:
        c = real_array(costs, "costs", f"({n},)", 1)
        if c.shape[0] != n:
            raise ValueError(f"costs: expected shape ({n},), got {c.shape}")
        threshold = real_number(cost_threshold, "cost_threshold")
        keep = c < threshold
        row = _loop_pose_row(rre[keep], rte[keep], floor_ok[keep], n, rot_t, trans_t)
        out["confident"] = row | {"cost_threshold": threshold}
    return out


def confidence_curve(
    costs: npt.ArrayLike,
    rre_deg: npt.ArrayLike,
    rte_m: npt.ArrayLike,
    *,
    rot_threshold_deg: float = 5.0,
    trans_threshold_m: float = 2.0,
    same_floor: npt.ArrayLike | None = None,
) -> dict[str, F64Array]:
    """Share of pairs kept vs their error as the matching-cost threshold moves.

    For each distinct cost c (ascending) the pairs with cost ≤ c are kept. Returns float64
    arrays of length M (the number of distinct costs): ``threshold`` (c), ``kept_share`` (kept /
    P), ``mRRE_deg``, ``mRTE_m`` (means over the kept pairs on one floor), ``RR_rot`` and
    ``RR_trans`` (shares of kept pairs on one floor with RRE < ``rot_threshold_deg`` / RTE <
    ``trans_threshold_m``, of all kept pairs).

    Args:
        costs: ``(P,)`` matching costs; rre_deg, rte_m: ``(P,)`` errors of the same pairs, °
            and m (:func:`relative_pose_errors`).
        rot_threshold_deg, trans_threshold_m: the RR thresholds (5°, 2 m).
        same_floor: optional ``(P,)`` bool, whether each pair's keyframes share a floor
            (default all; as in :func:`loop_pose_metrics`).
    """
    c = real_array(costs, "costs", "(P,)", 1)
    rre = _absolute_errors(rre_deg, "rre_deg")
    rte = _absolute_errors(rte_m, "rte_m")
    if not c.shape == rre.shape == rte.shape:
        raise ValueError(
            f"costs, rre_deg, rte_m: shapes differ ({c.shape}, {rre.shape}, {rte.shape})"
        )
    rot_t = positive_float(rot_threshold_deg, "rot_threshold_deg")
    trans_t = positive_float(trans_threshold_m, "trans_threshold_m")
    ok = (
        np.ones(c.size, dtype=bool)
        if same_floor is None
        else bool_array(same_floor, "same_floor", c.size)
    )
    order = np.argsort(c, kind="stable")
    c, rre, rte, ok = c[order], rre[order], rte[order], ok[order]
    last = np.flatnonzero(np.append(np.diff(c) > 0, True)) if c.size else np.zeros(0, np.int64)
    kept = last + 1.0
    on_floor = np.cumsum(ok)[last].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):  # no pair on one floor yet: nan
        return {
            "threshold": c[last],
            "kept_share": kept / max(c.size, 1),
            "mRRE_deg": np.cumsum(np.where(ok, rre, 0.0))[last] / on_floor,
            "mRTE_m": np.cumsum(np.where(ok, rte, 0.0))[last] / on_floor,
            "RR_rot": np.cumsum(ok & (rre < rot_t))[last] / kept,
            "RR_trans": np.cumsum(ok & (rte < trans_t))[last] / kept,
        }


def distinctiveness(rerank_costs: npt.ArrayLike) -> F64Array:
    """How much the best candidate stands out: mean minus minimum of each query's re-ranking
    costs.

    Definition: for a query whose K retrieved candidates have yaw matching costs c_1..c_K (any
    order), distinctiveness = mean(c) − min(c) ≥ 0 (0 when K = 1). The absolute cost of the best
    candidate depends on how textured the place is; how far it lies below the other candidates'
    costs says whether the place was recognised, which is what a confidence must tell.

    Args:
        rerank_costs: ``(Q, K)`` finite costs, K ≥ 1.

    Returns:
        ``(Q,)`` float64, ≥ 0.
    """
    c = real_array(rerank_costs, "rerank_costs", "(Q, K)", 2)
    if c.shape[1] == 0:
        raise ValueError(f"rerank_costs: expected shape (Q, K) with K >= 1, got {c.shape}")
    return np.maximum(c.mean(axis=1) - c.min(axis=1), 0.0)


def calibrate_acceptance(
    score: npt.ArrayLike,
    correct: npt.ArrayLike,
    *,
    target_precision: float = 0.9,
    min_accepted: int = 10,
) -> dict[str, Any]:
    """The lowest score threshold whose accepted results are correct often enough.

    Definition: a result is accepted when ``score ≥ threshold`` (e.g. :func:`distinctiveness`).
    Over the candidate thresholds (the distinct scores), the smallest one is chosen whose
    accepted set has at least ``min_accepted`` results and precision (correct / accepted) ≥
    ``target_precision``; it accepts the most results that meet the target. If none does, the
    threshold is +inf (accept nothing), and precision is NaN.

    Args:
        score: ``(Q,)`` finite confidence scores, higher = more confident.
        correct: ``(Q,)`` bool, whether each result is right (e.g. top-1 within 2 m).
        target_precision: in (0, 1].
        min_accepted: the fewest accepted results a threshold may rest on (≥ 1).

    Returns:
        ``{"threshold", "precision", "accepted_share", "accepted", "queries",
        "target_precision", "min_accepted", "base_precision"}`` (``base_precision`` = share of
        correct results when everything is accepted).
    """
    sc = real_array(score, "score", "(Q,)", 1)
    ok = bool_array(correct, "correct", sc.shape[0])
    tp = _share(target_precision, "target_precision", closed_above=True)
    if isinstance(min_accepted, bool) or not isinstance(min_accepted, (int, np.integer)):
        raise TypeError(f"min_accepted: expected an int, got {type(min_accepted).__name__}")
    if min_accepted < 1:
        raise ValueError(f"min_accepted: expected >= 1, got {min_accepted}")
    order = np.argsort(-sc, kind="stable")
    hits = np.cumsum(ok[order])
    n = np.arange(1, len(order) + 1)
    # the accepted set of threshold sc[order[i]] is everything up to its last tie
    last = np.append(np.diff(sc[order]) < 0, True) if len(order) else np.zeros(0, bool)
    good = last & (n >= min_accepted) & (hits >= tp * n - 1e-12)
    out: dict[str, Any] = {
        "queries": int(sc.shape[0]),
        "target_precision": tp,
        "min_accepted": int(min_accepted),
        "base_precision": _ratio(float(ok.sum()), float(sc.shape[0])),
    }
    if not good.any():
        return out | {
            "threshold": float("inf"),
            "precision": float("nan"),
            "accepted": 0,
            "accepted_share": 0.0,
        }
    i = int(np.flatnonzero(good)[-1])
    return out | {
        "threshold": float(sc[order[i]]),
        "precision": float(hits[i] / n[i]),
        "accepted": int(n[i]),
        "accepted_share": _ratio(float(n[i]), float(sc.shape[0])),
    }


# ----------------------------------------------------------------------------- latency


def latency_summary(samples_ms: Mapping[str, npt.ArrayLike]) -> dict[str, dict[str, Any]]:
    """Per-stage latency statistics from timing samples in milliseconds.

    ``samples_ms`` maps a stage name (e.g. ``"encoder"``, ``"retrieval"``, ``"re-ranking"``,
    ``"metric"``) to its ``(n,)`` samples. Returns ``{stage: {"count", "mean_ms", "median_ms",
    "p95_ms"}}`` in the given order. The median and p95 are taken by the inverted CDF, as
    :func:`error_percentiles` does: a sample, the lower middle one for an even count.
    """
    if not isinstance(samples_ms, Mapping):
        raise TypeError(
            f"samples_ms: expected a mapping of stage name to samples, got "
            f"{type(samples_ms).__name__}"
        )
    out: dict[str, dict[str, Any]] = {}
    for stage, samples in samples_ms.items():
        s = real_array(samples, f"samples_ms[{stage!r}]", "(n,)", 1)
        if (s < 0).any():
            raise ValueError(
                f"samples_ms[{stage!r}]: expected durations >= 0 ms, got {float(s.min()):.6g}"
            )
        out[str(stage)] = {
            "count": int(s.size),
            "mean_ms": float(s.mean()) if s.size else float("nan"),
            "median_ms": float(error_percentiles(s, (50.0,))[0]),
            "p95_ms": float(error_percentiles(s, (95.0,))[0]),
        }
    return out


# ----------------------------------------------------------------------------- report


def to_jsonable(value: Any) -> Any:
    """Convert metric results to plain JSON types.

    Objects with ``to_dict()`` (:class:`RecallResult`) are summarised, numpy scalars and arrays
    become numbers and lists, tuples become lists, mapping keys become strings, and non-finite
    floats (undefined metrics) become ``None``.
    """
    if hasattr(value, "to_dict"):
        return to_jsonable(value.to_dict())
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if np.isfinite(v) else None
    if value is None or isinstance(value, str):
        return value
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"metrics: cannot write a {type(value).__name__} to JSON")


def _pct(v: Any, digits: int = 1) -> str:
    return "–" if v is None else f"{100.0 * v:.{digits}f}"


def _one_label(values: set[str], default: str) -> str:
    """The one label the rows share, ``default`` when none gives one; several: "per row"."""
    if not values:
        return default
    return next(iter(values)) if len(values) == 1 else "(per row: see the JSON)"


def _num(v: Any, digits: int = 2) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return [*lines, ""]


def _recall_table(results: Mapping[str, Any], first: str, define_kept: bool = False) -> list[str]:
    """Rows: ``first`` column (method / perturbation) then Recall@N at each radius, in %;
    ``define_kept`` adds a line under the table saying what the "kept" column counts."""
    any_res = next(iter(results.values()))
    ns, radii = any_res["top_n"], any_res["radii_m"]
    header = [first, "kept"] + [f"R@{n} {r:g} m" for n in ns for r in radii]
    rows = []
    for name, res in results.items():
        cells = [_pct(res["recall"].get(str(n), {}).get(f"{r:g}")) for n in ns for r in radii]
        rows.append([name, f"{res['num_kept']}/{res['num_queries']}", *cells])
    if not define_kept:
        return _table(header, rows)
    elig = {res.get("eligibility_radius_m") for res in results.values()}
    within = f"{elig.pop():g} m" if len(elig) == 1 and None not in elig else "the keep radius"
    return [
        *_table(header, rows)[:-1],
        "",
        f"*kept*: queries with a map frame within {within} of their true position (on their "
        "floor where floors are known), out of all; recall is over the kept ones (a query "
        "without a true revisit in the map is left out).",
        "",
    ]


def _pose_table(
    results: Mapping[str, Any], first_column: str = "method", define: bool = True
) -> list[str]:
    """AOE/APE rows of ``{name: pose_accuracy(...)}``, the names under ``first_column``; with
    ``define``, how AOE/APE@p are taken is said under the table (the report's first such)."""
    subsets = {
        "true_revisit": "top-1 true revisit",
        "pose_keyframe": "pose's keyframe a true revisit",
        "all": "all kept queries on their floor",
        "every_query": "every query (kept or not, any floor; x-y error)",
    }
    first = next(iter(next(iter(results.values())).values()))
    aoe = [k for k in first if k.startswith("AOE@")]
    ape = [k for k in first if k.startswith("APE@")]
    header = [first_column, "queries", "n"]
    header += [f"{k}% (°)" for k in aoe] + [f"{k}% (m)" for k in ape]
    rows = []
    for name, res in results.items():
        for key, label in subsets.items():
            if key in res:
                row = res[key]
                cells = [_num(row[k]) for k in aoe] + [_num(row[k]) for k in ape]
                other = row.get("other_floor", 0)
                shown = f"{label} ({other} answered on another floor left out)" if other else label
                rows.append([name, shown, str(row["count"]), *cells])
    if not define:
        return _table(header, rows)
    return [
        *_table(header, rows)[:-1],
        "",
        "AOE@p / APE@p: the smallest absolute yaw / position error with at least p % of the "
        "row's queries at or below it (the inverted-CDF percentile, no interpolation: each is "
        "an observed error; vvloc.evaluate.error_percentiles).",
        "",
    ]


def _accept_rule(strict: bool | None) -> str:
    """The prefix of a loop row's threshold: the rule it was computed with (``<``: strict, the
    detector's; ``≤``: :meth:`LoopClosureCurve.at`'s default); none for a report written before
    2026-12-07, which did not record it."""
    if strict is None:
        return ""
    return "< " if strict else "≤ "


def _loop_table(results: Mapping[str, Any]) -> list[str]:
    # the bound's level and the recall targets as the rows hold them (one header for all)
    levels = {
        f"{100 * r['events']['confidence']:g}"
        for r in results.values()
        if r.get("events", {}).get("confidence") is not None
    }
    targets = {
        " / ".join(f"{100 * o['target_recall']:g}" for o in r["at_recall"])
        for r in results.values()
        if r.get("at_recall")
    }
    default_targets = " / ".join(f"{100 * r:g}" for r in SUMMARY_RECALLS)
    header = [
        "name",
        "accepted at distance",
        "accepted",
        "Precision@2m (%)",
        "Recall@2m (%)",
        "F1",
        "CFER (%)",
        "events",
        "CFER, events (%)",
        f"CFER {_one_label(levels, '95')} % bound, events (%)",
        f"CFER at Recall@2m {_one_label(targets, default_targets)} % (%)",
        "best F1",
        "best-F1 threshold (accepted: distance ≤ it)",
    ]
    rows = []
    for name, res in results.items():
        at, best = res["at_threshold"], res["best_f1"]
        ev = res.get("events", {})
        rows.append(
            [
                name,
                _accept_rule(at.get("strict")) + _num(at["threshold"], 3),
                str(at["accepted"]),
                _pct(at["precision"]),
                _pct(at["recall"]),
                _num(at["f1"], 3),
                _pct(at["cfer"], 2),  # two decimals: 0.26 % is a target
                str(ev["events"]) if ev else "–",
                _pct(ev.get("cfer"), 2),
                "–" if ev.get("cfer_upper") is None else _num(100.0 * ev["cfer_upper"]),
                " / ".join(_pct(o["cfer"], 2) for o in res.get("at_recall", [])) or "–",
                _num(best["f1"], 3),
                _num(best["threshold"], 3),
            ]
        )
    return _table(header, rows)


def _loop_pose_table(results: Mapping[str, Any]) -> list[str]:
    header = [
        "name",
        "pairs",
        "n",
        "across floors",
        "mRRE (°), same floor",
        "mRTE (m), same floor",
        "RR(<5°) (%)",
        "RR(<2 m) (%)",
    ]
    rows = []
    for name, res in results.items():
        for key in ("all", "confident"):
            if key in res:
                row = res[key]
                label = "all" if key == "all" else f"cost < {row.get('cost_threshold', 0.75):g}"
                rows.append(
                    [
                        name,
                        label,
                        str(row["count"]),
                        str(row.get("cross_floor", 0)),
                        _num(row["mRRE_deg"]),
                        _num(row["mRTE_m"]),
                        _pct(row["RR_rot"]),
                        _pct(row["RR_trans"]),
                    ]
                )
    return [
        *_table(header, rows)[:-1],
        "",
        "mRRE and mRTE are means over the n pairs less those across floors (two floors have no "
        "true relative pose to err from); RR counts all n, a pair across floors registering "
        "none.",
        "",
    ]


def _latency_table(results: Mapping[str, Any]) -> list[str]:
    header = ["stage", "n", "mean (ms)", "median (ms)", "p95 (ms)"]
    rows = [
        [stage, str(r["count"]), _num(r["mean_ms"]), _num(r["median_ms"]), _num(r["p95_ms"])]
        for stage, r in results.items()
    ]
    return _table(header, rows)


#: Report sections: metrics key → (heading, first column of a Recall table or None).
_SECTIONS = {
    "global_localization": ("Global localization (Recall@N, %)", "method"),
    "per_session": ("Global localization per query session (Recall@N, %)", "session, method"),
    "pose_accuracy": ("Metric pose accuracy (AOE / APE percentiles)", None),
    "loop_closure": ("Loop closure", None),
    "loop_pose": ("Relative pose on detected loop pairs", None),
    "robustness": ("Robustness (Recall@N under perturbations, %)", "perturbation, method"),
    "robustness_pose": ("Robustness (metric pose accuracy under perturbations)", None),
    "latency": ("Latency per stage", None),
}


def _brief(x: Any) -> str:
    """``repr(x)`` cut to 60 characters, for messages."""
    r = repr(x)
    return r if len(r) <= 60 else r[:57] + "..."


def render_markdown(
    metrics: Mapping[str, Any],
    *,
    title: str = "vvloc evaluation",
    figures: Mapping[str, str] | None = None,
) -> str:
    """The Markdown report of a metrics dict (see :func:`write_report` for its layout)."""
    m = to_jsonable(metrics)
    lines = [f"# {title}", ""]
    meta = m.get("meta") or {}
    if not isinstance(meta, dict):
        raise TypeError(f"metrics['meta']: expected a mapping of key to value, got {_brief(meta)}")
    for k, v in meta.items():
        if isinstance(v, dict):  # e.g. the world: "scene: parking, seed: 0"
            v = ", ".join(f"{a}: {b}" for a, b in v.items())
        elif v is None and k == "scene":  # a dataset that vvloc sim did not render
            v = "– (not rendered by vvloc sim)"
        lines.append(f"- **{k}**: {v}")
    if meta:
        lines.append("")
    pose_columns = {"pose_accuracy": "method", "robustness_pose": "perturbation"}
    builders = {
        "loop_closure": _loop_table,
        "loop_pose": _loop_pose_table,
        "latency": _latency_table,
    }
    kept_defined = pose_defined = False
    for key, (heading, first) in _SECTIONS.items():
        section = m.get(key)
        if not section:
            continue
        lines += [f"## {heading}", ""]
        try:
            if first:
                lines += _recall_table(section, first, define_kept=not kept_defined)
                kept_defined = True
            elif key in pose_columns:
                lines += _pose_table(section, pose_columns[key], define=not pose_defined)
                pose_defined = True
            else:
                lines += builders[key](section)
        except (TypeError, AttributeError, KeyError, IndexError, ValueError) as e:
            # a hand-made section that is not what this module's functions return
            raise TypeError(
                f"metrics[{key!r}]: expected the layout write_report documents for it, got "
                f"{type(section).__name__} {_brief(section)} ({type(e).__name__}: {e})"
            ) from e
    notes = m.get("notes")
    if notes:
        if isinstance(notes, str):
            notes = [notes]
        if not isinstance(notes, list) or not all(isinstance(n, str) for n in notes):
            raise TypeError(
                f"metrics['notes']: expected a string or a list of strings, got {_brief(notes)}"
            )
        lines += ["## Notes", ""]
        lines += [f"- {n}" for n in notes]
        lines.append("")
    if figures:
        lines += ["## Figures", ""]
        for name, rel in figures.items():
            lines += [f"### {name}", "", f"![{name}]({rel})", ""]
    return "\n".join(lines).rstrip("\n") + "\n"


def write_report(
    out_dir: str | os.PathLike[str],
    metrics: Mapping[str, Any],
    *,
    title: str = "vvloc evaluation",
    figures: Mapping[str, str | os.PathLike[str]] | None = None,
    stem: str = "report",
) -> tuple[Path, Path]:
    """Write ``<stem>.md`` (tables in the paper's layout) and ``<stem>.json`` into ``out_dir``.

    ``metrics`` layout (every section optional; sections keep their order; values may be the
    objects/dicts returned by this module):

    * ``"meta"``: ``{key: value}`` printed as a list (checkpoint, dataset, hardware, seed, ...).
    * ``"global_localization"``: ``{method: RecallResult}`` e.g. ``"VVLoc-G"``, ``"VVLoc-ML"``.
    * ``"per_session"``: ``{"<session>, <method>": RecallResult}`` (several query sessions).
    * ``"pose_accuracy"``: ``{method: pose_accuracy(...)}``.
    * ``"loop_closure"``: ``{name: LoopClosureCurve.summary(threshold)}``.
    * ``"loop_pose"``: ``{name: loop_pose_metrics(...)}``.
    * ``"robustness"``: ``{"<perturbation>, <method>": RecallResult}`` (or
      ``{perturbation: RecallResult}``, :func:`evaluate_robustness`).
    * ``"robustness_pose"``: ``{perturbation: pose_accuracy(...)}``.
    * ``"latency"``: ``latency_summary(...)``.
    * ``"notes"``: a string or list of strings (e.g. a missed target and why).

    Any other key is written to the JSON only. ``figures`` maps a caption to an image path; paths
    inside ``out_dir`` are linked relatively. Files are written atomically (temporary file +
    rename). Returns ``(markdown_path, json_path)``.
    """
    if not isinstance(out_dir, (str, os.PathLike)):
        raise TypeError(
            f"out_dir: expected a path (str or os.PathLike), got {type(out_dir).__name__}"
        )
    out = Path(out_dir)
    if not isinstance(metrics, Mapping):
        raise TypeError(f"metrics: expected a mapping of sections, got {type(metrics).__name__}")
    if not isinstance(stem, str):
        raise TypeError(
            f"stem: expected a file name without suffix (str), got {type(stem).__name__}"
        )
    if stem in ("", ".", "..") or Path(stem).name != stem or "\\" in stem or "\0" in stem:
        # "../x" wrote x.md beside out_dir, not into it
        raise ValueError(f"stem: expected a plain file name (no folder), got {stem!r:.60}")
    links: dict[str, str] = {}
    for name, p in (figures or {}).items():
        fp = Path(p)
        try:
            links[str(name)] = fp.resolve().relative_to(out.resolve()).as_posix()
        except ValueError:
            links[str(name)] = fp.as_posix()
    data = to_jsonable(metrics)
    if links:
        data = {**data, "figures": links}
    text_json = json.dumps(data, indent=2, sort_keys=False, allow_nan=False) + "\n"
    text_md = render_markdown(metrics, title=title, figures=links)
    md_path, json_path = out / f"{stem}.md", out / f"{stem}.json"
    out.mkdir(parents=True, exist_ok=True)
    for path, text in ((json_path, text_json), (md_path, text_md)):
        with atomic_write(path) as f:
            f.write(text)
    return md_path, json_path
