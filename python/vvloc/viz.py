"""Evaluation plots (matplotlib, Agg, saved to files).

Figures are built with the object-oriented API (:class:`matplotlib.figure.Figure` on an Agg
canvas): no pyplot, no global state, no GUI backend, safe in worker threads. Every function takes
plain arrays, writes one image (format from the suffix: ``.png``, ``.svg``, ``.pdf``) atomically
— a temporary file renamed into place, so no partial file is left behind — and returns its path.

Units: metres for positions and translations, degrees on every angle axis (inputs in radians are
said so).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import matplotlib
import numpy as np
import numpy.typing as npt
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from vvloc._io import atomic_write
from vvloc.geometry import wrap_angle

_DPI = 120
# Fixed metadata so that the same inputs give byte-identical files.
_METADATA: dict[str, dict[str, str | None]] = {
    "png": {"Software": None},
    "svg": {"Date": None, "Creator": None},
    "pdf": {"CreationDate": None, "Creator": None, "Producer": None},
}


def _new_figure(width: float = 6.4, height: float = 4.8) -> Figure:
    fig = Figure(figsize=(width, height), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: str | os.PathLike[str]) -> Path:
    """Write ``fig`` to ``path`` atomically (parent folders created); return the path."""
    out = Path(path)
    fmt = out.suffix.lstrip(".").lower()
    if fmt not in _METADATA:
        raise ValueError(f"path: expected a .png, .svg or .pdf file name, got {out.name!r}")
    out.parent.mkdir(parents=True, exist_ok=True)
    # svg.hashsalt: matplotlib names SVG clip paths with random ids otherwise
    with atomic_write(out, "wb") as f, matplotlib.rc_context({"svg.hashsalt": "vvloc"}):
        fig.savefig(f, format=fmt, metadata=_METADATA[fmt])
    return out


def _no_data(ax: Axes, what: str) -> None:
    """Say on the axes that there is nothing to draw (instead of a blank plot)."""
    ax.text(
        0.5,
        0.5,
        f"no data: {what}",
        transform=ax.transAxes,
        ha="center",
        va="center",
        color="0.4",
    )


def _vector(x: npt.ArrayLike, name: str, length: int | None = None) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 1 or (length is not None and arr.shape[0] != length):
        want = f"({length},)" if length is not None else "(n,)"
        raise ValueError(f"{name}: expected shape {want}, got {arr.shape}")
    return arr


def _share(x: npt.ArrayLike, name: str, length: int | None = None) -> np.ndarray:
    """:func:`_vector` of fractions in [0, 1] (NaN: undefined): a percentage, plotted ×100 off
    the axes, drew an empty plot without a word."""
    arr = _vector(x, name, length)
    if ((arr < 0) | (arr > 1)).any():
        raise ValueError(
            f"{name}: expected fractions in [0, 1], got values in [{np.nanmin(arr):g}, "
            f"{np.nanmax(arr):g}] (percentages?)"
        )
    return arr


def _magnitudes(x: npt.ArrayLike, name: str, length: int | None = None) -> np.ndarray:
    """:func:`_vector` of absolute errors >= 0 (NaN and inf allowed: left out)."""
    arr = _vector(x, name, length)
    if (arr < 0).any():
        raise ValueError(f"{name}: expected absolute errors >= 0, got {np.nanmin(arr):g}")
    return arr


def _mask(x: npt.ArrayLike, name: str, length: int) -> np.ndarray:
    """A ``(length,)`` bool array from bools or 0/1 integers (a float, NaN included, is no
    answer to "correct?")."""
    arr = np.asarray(x)
    if arr.shape != (length,):
        raise ValueError(f"{name}: expected shape ({length},), got {arr.shape}")
    if arr.dtype != bool and not (
        np.issubdtype(arr.dtype, np.integer) and np.isin(arr, (0, 1)).all()
    ):
        raise TypeError(f"{name}: expected bools (or 0/1 integers), got dtype {arr.dtype}")
    return arr.astype(bool)


def _points(x: npt.ArrayLike, name: str) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name}: expected shape (n, 2), got {arr.shape}")
    return arr


def plot_recall_curves(
    path: str | os.PathLike[str],
    curves: Mapping[str, tuple[npt.ArrayLike, npt.ArrayLike]],
    *,
    radius: float = 2.0,
) -> Path:
    """Recall@N against N, one line per method.

    Args:
        path: output image.
        curves: ``{method: (ns (K,), recall (K,))}``, recall as fractions in [0, 1]
            (``RecallResult.curve(radius)``).
        radius: the revisit radius (m) of the curves, for the title.
    """
    fig = _new_figure()
    ax = fig.add_subplot()
    drawn = False
    for name, (ns, recall) in curves.items():
        n = _vector(ns, f"curves[{name!r}] ns")
        r = _share(recall, f"curves[{name!r}] recall", n.shape[0])
        if np.isfinite(r).any():
            ax.plot(n, 100.0 * r, marker="o", markersize=3, label=str(name))
            drawn = True
    if not drawn:
        _no_data(ax, "no query kept")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("N (number of top candidates)")
    ax.set_ylabel("Recall@N (%)")
    ax.set_ylim(0, 100)
    ax.set_title(f"Recall@N at {radius:g} m")
    ax.grid(True, alpha=0.3)
    if drawn:
        ax.legend(loc="lower right")
    return save_figure(fig, path)


def _cdf_panel(ax: Axes, errors: Mapping[str, npt.ArrayLike], xlabel: str) -> None:
    for name, e in errors.items():
        v = _magnitudes(e, f"errors[{name!r}]")
        v = np.sort(v[np.isfinite(v)])
        if v.size == 0:
            continue
        share = np.arange(0, v.size + 1) / v.size  # starts at 0 % below the smallest error
        ax.step(np.r_[0.0, v], 100.0 * share, where="post", label=f"{name} (n = {v.size})")
    if not ax.get_legend_handles_labels()[0]:
        _no_data(ax, "no query to score")
    ax.set_xlabel(xlabel)
    ax.set_xlim(left=0.0)
    ax.set_ylabel("queries with error ≤ x (%)")
    ax.set_ylim(0, 100)
    ax.grid(True, alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower right")


def plot_error_cdfs(
    path: str | os.PathLike[str],
    yaw_errors_deg: Mapping[str, npt.ArrayLike],
    position_errors_m: Mapping[str, npt.ArrayLike],
) -> Path:
    """Cumulative distributions of absolute yaw error (°) and position error (m), side by side;
    each curve's label gets its number of queries, and the labels should say which queries
    they are (e.g. "VVLoc-ML, top-1 true revisits").

    Args:
        path: output image.
        yaw_errors_deg: ``{label: (n,) errors in degrees}`` (:func:`vvloc.evaluate.pose_errors`).
        position_errors_m: ``{label: (n,) errors in metres}``.
    """
    fig = _new_figure(10.0, 4.2)
    ax_yaw, ax_pos = fig.subplots(1, 2)
    _cdf_panel(ax_yaw, yaw_errors_deg, "absolute yaw error (°)")
    _cdf_panel(ax_pos, position_errors_m, "position error (m)")
    ax_yaw.set_title("AOE cumulative distribution")
    ax_pos.set_title("APE cumulative distribution")
    return save_figure(fig, path)


def plot_precision_recall(
    path: str | os.PathLike[str],
    curves: Mapping[str, Mapping[str, npt.ArrayLike]],
) -> Path:
    """Loop-closure precision–recall curves, best-F1 point marked (its F1 in the legend).

    Args:
        path: output image.
        curves: ``{name: sweep}`` with ``sweep`` holding equal-length ``precision``, ``recall``
            and ``f1`` arrays (``LoopClosureCurve.sweep()``), fractions in [0, 1].
    """
    fig = _new_figure()
    ax = fig.add_subplot()
    for name, sweep in curves.items():
        p = _share(sweep["precision"], f"curves[{name!r}]['precision']")
        r = _share(sweep["recall"], f"curves[{name!r}]['recall']", p.shape[0])
        f1 = _share(sweep["f1"], f"curves[{name!r}]['f1']", p.shape[0])
        if p.size == 0 or not (np.isfinite(p) & np.isfinite(r)).any():
            continue  # e.g. no true revisit: recall is undefined everywhere
        best = None if np.isnan(f1).all() else int(np.nanargmax(f1))
        # the best F1 goes into the legend: annotations of nearby curves overlap
        label = str(name) if best is None else f"{name} (best F1 {f1[best]:.3f})"
        (line,) = ax.plot(100.0 * r, 100.0 * p, label=label)
        if best is not None:
            ax.plot(100.0 * r[best], 100.0 * p[best], "o", color=line.get_color())
    ax.set_xlabel("Recall@2m (%)")
    ax.set_ylabel("Precision@2m (%)")
    ax.set_xlim(0, 100)
    ax.set_ylim(0, 102)
    ax.set_title("Loop closure: precision–recall")
    ax.grid(True, alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower left")
    else:
        _no_data(ax, "no loop candidate, or no true revisit")
    return save_figure(fig, path)


def plot_trajectory(
    path: str | os.PathLike[str],
    db_positions: npt.ArrayLike,
    query_positions: npt.ArrayLike,
    correct: npt.ArrayLike,
    *,
    kept: npt.ArrayLike | None = None,
    retrieved_positions: npt.ArrayLike | None = None,
    method: str = "retrieval",
) -> Path:
    """Map and query trajectories, each query coloured by the correctness of its retrieval.

    Args:
        path: output image.
        db_positions: ``(N, 2)`` world x, y of the map frames (m), drawn as a grey line.
        query_positions: ``(Q, 2)`` ground-truth world x, y of the queries (m).
        correct: ``(Q,)`` bool, top-1 is a true revisit (green) or not (red).
        kept: optional ``(Q,)`` bool; excluded queries (no map frame within 2 m) are grey crosses.
        retrieved_positions: optional ``(Q, 2)`` position of each query's top-1 map frame; a thin
            segment joins the query to it.
        method: what ranked the top-1, named in the title (``"Top-1 <method>: ..."``).
    """
    db = _points(db_positions, "db_positions")
    q = _points(query_positions, "query_positions")
    ok = _mask(correct, "correct", q.shape[0])
    keep = np.ones_like(ok) if kept is None else _mask(kept, "kept", q.shape[0])
    fig = _new_figure(7.0, 6.0)
    ax = fig.add_subplot()
    ax.plot(db[:, 0], db[:, 1], color="0.6", linewidth=1.0, label="map", zorder=1)
    if retrieved_positions is not None:
        rp = _points(retrieved_positions, "retrieved_positions")
        if rp.shape != q.shape:
            raise ValueError(f"retrieved_positions: expected shape {q.shape}, got {rp.shape}")
        for sel, color in ((keep & ok, "tab:green"), (keep & ~ok, "tab:red")):
            for a, b in zip(q[sel], rp[sel], strict=True):
                ax.plot([a[0], b[0]], [a[1], b[1]], color=color, alpha=0.3, linewidth=0.6)
    groups = (
        (keep & ok, "tab:green", "o", "correct"),
        (keep & ~ok, "tab:red", "o", "wrong"),
        (~keep, "0.4", "x", "excluded (no map frame within 2 m)"),
    )
    for sel, color, marker, label in groups:
        if sel.any():
            ax.scatter(q[sel, 0], q[sel, 1], s=10, c=color, marker=marker, label=label, zorder=2)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    n_keep = int(keep.sum())
    if n_keep:
        share = 100.0 * (keep & ok).sum() / n_keep
        ax.set_title(f"Top-1 {method}: {share:.1f}% correct of {n_keep} queries")
    else:
        ax.set_title(f"Top-1 {method}: no query has a map frame within 2 m")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return save_figure(fig, path)


def plot_yaw_cost_curve(
    path: str | os.PathLike[str],
    costs: npt.ArrayLike,
    *,
    estimated_yaw: float | None = None,
    true_yaw: float | None = None,
) -> Path:
    """The yaw cost curve c(s) of one pair against the yaw it stands for.

    Args:
        path: output image.
        costs: ``(T,)`` integer-shift cost curve (``kernels.yaw_costs`` row): shift s ↔ yaw
            ``wrap(2π s / T)``, drawn in degrees over (−180°, 180°].
        estimated_yaw, true_yaw: optional yaw (radians) to mark with vertical lines.
    """
    c = _vector(costs, "costs")
    if c.size == 0:
        raise ValueError("costs: expected a non-empty cost curve (T,)")
    yaw = np.degrees(wrap_angle(2.0 * np.pi * np.arange(c.size) / c.size))
    order = np.argsort(yaw, kind="stable")
    yaw, c = yaw[order], c[order]
    # the curve is periodic: one sample beyond each end, so that it reaches ±180° whatever T
    # (2π s / T lands an ulp off π for some even T, and no sample lands there for odd T)
    yaw, c = np.r_[yaw[-1] - 360.0, yaw, yaw[0] + 360.0], np.r_[c[-1], c, c[0]]
    fig = _new_figure(6.4, 3.6)
    ax = fig.add_subplot()
    ax.plot(yaw, c, color="tab:blue", label="matching cost")
    if estimated_yaw is not None:
        ax.axvline(
            float(np.degrees(wrap_angle(estimated_yaw))),
            color="tab:orange",
            linestyle="--",
            label="estimate",
        )
    if true_yaw is not None:
        ax.axvline(
            float(np.degrees(wrap_angle(true_yaw))),
            color="tab:green",
            linestyle=":",
            label="ground truth",
        )
    ax.set_xlim(-180, 180)
    ax.set_xlabel("yaw φ (°)")
    ax.set_ylabel("cost δ")
    ax.set_title("Yaw cost curve")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return save_figure(fig, path)


def plot_translation_costs(
    path: str | os.PathLike[str],
    hypotheses: npt.ArrayLike,
    costs: npt.ArrayLike,
    *,
    estimate: npt.ArrayLike | None = None,
    truth: npt.ArrayLike | None = None,
) -> Path:
    """Heat map of the matching cost over translation hypotheses (coarse-to-fine samples).

    Args:
        path: output image.
        hypotheses: ``(N, 2)`` translation hypotheses (x, y) in the source frame (m).
        costs: ``(N,)`` matching cost of each hypothesis (lower is better).
        estimate, truth: optional ``(2,)`` translations (m) to mark.
    """
    h = _points(hypotheses, "hypotheses")
    c = _vector(costs, "costs", h.shape[0])
    if h.shape[0] == 0:
        raise ValueError("hypotheses: expected at least one hypothesis")
    fig = _new_figure(6.0, 5.0)
    ax = fig.add_subplot()
    # Coarse samples first, fine (dense) ones on top: draw in descending cost order.
    order = np.argsort(-c, kind="stable")
    sc = ax.scatter(h[order, 0], h[order, 1], c=c[order], cmap="viridis_r", s=28, marker="s")
    fig.colorbar(sc, ax=ax, label="matching cost (lower is better)")
    for point, color, marker, label in (
        (estimate, "tab:red", "x", "estimate"),
        (truth, "black", "+", "ground truth"),
    ):
        if point is not None:
            p = _vector(point, label, 2)
            ax.scatter([p[0]], [p[1]], c=color, marker=marker, s=90, linewidths=2, label=label)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m, source frame)")
    ax.set_ylabel("y (m, source frame)")
    ax.set_title("Translation cost")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8)
    return save_figure(fig, path)


def plot_confidence_curve(path: str | os.PathLike[str], curve: Mapping[str, npt.ArrayLike]) -> Path:
    """Share of loop pairs kept vs their mean errors as the cost threshold moves.

    Args:
        path: output image.
        curve: ``vvloc.evaluate.confidence_curve`` output (``kept_share``, ``mRRE_deg``,
            ``mRTE_m`` arrays of equal length; the means are nan where every kept pair joins
            two floors, which the means leave out).
    """
    kept = _share(curve["kept_share"], "curve['kept_share']")
    rre = _magnitudes(curve["mRRE_deg"], "curve['mRRE_deg']", kept.shape[0])
    rte = _magnitudes(curve["mRTE_m"], "curve['mRTE_m']", kept.shape[0])
    fig = _new_figure()
    ax = fig.add_subplot()
    # markers: a curve of one point (one verified pair) is otherwise not drawn
    ax.plot(100.0 * kept, rre, color="tab:blue", marker="o", markersize=2, label="mRRE (°)")
    if not len(kept):
        _no_data(ax, "no verified pair")
    elif not np.isfinite(rre).any():  # pairs verified, each joining two floors (left out)
        _no_data(ax, "no verified pair on one floor")
    ax.set_xlabel("pairs kept (%)")
    ax.set_ylabel("mRRE (°)", color="tab:blue")
    ax2 = ax.twinx()
    ax2.plot(100.0 * kept, rte, color="tab:orange", marker="o", markersize=2, label="mRTE (m)")
    ax2.set_ylabel("mRTE (m)", color="tab:orange")
    ax.set_xlim(0, 100)
    ax.set_title("Confidence curve (cost threshold sweep)")
    ax.grid(True, alpha=0.3)
    return save_figure(fig, path)
