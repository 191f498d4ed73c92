"""Literal references of the matching kernels (numpy, float64).

The yaw cost curve of DESIGN.md §3: ``c(s) = (1/T)·Σᵢ ‖ρ(Ds, s)ᵢ − Dtᵢ‖₂`` with the interpolated
roll ``ρ(D, s) = (1 − w)·roll(D, k) + w·roll(D, k + 1)`` (``k = ⌊s⌋``, ``w = s − k``,
``roll(D, k)[i] = D[(i − k) mod T]``). These functions evaluate it literally, one shift at a
time, and find the continuous minimum by a dense sub-bin scan plus a local refinement. Slow on
purpose: they are the tests' oracle.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from scipy.optimize import minimize_scalar

from vvloc.geometry import wrap_angle

F64 = npt.NDArray[np.float64]

#: Spacing of the dense sub-bin scan of :func:`estimate_yaw`, in bins.
SCAN_STEP = 0.01


def roll_rows(d: npt.ArrayLike, s: float) -> F64:
    """Interpolated circular roll of the rows of ``d`` (T, C) by a real shift ``s`` (bins)."""
    d = np.asarray(d, dtype=np.float64)
    k = math.floor(s)
    w = s - k
    return (1.0 - w) * np.roll(d, k, axis=0) + w * np.roll(d, k + 1, axis=0)


def matching_cost(a: npt.ArrayLike, b: npt.ArrayLike) -> F64:
    """``δ(A, B) = (1/T)·Σᵢ ‖Aᵢ − Bᵢ‖₂`` over the last two axes of (..., T, C) arrays → (...)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.linalg.norm(a - b, axis=-1).mean(axis=-1)


def shift_cost(src: npt.ArrayLike, tgt: npt.ArrayLike, s: float) -> float:
    """Cost ``c(s)`` of one pair ``src``, ``tgt`` (T, C) at the real shift ``s`` (bins)."""
    return float(matching_cost(roll_rows(src, s), tgt))


def yaw_costs(src: npt.ArrayLike, tgt: npt.ArrayLike) -> F64:
    """Integer-shift cost curves of pairs (P, T, C) → (P, T), by a literal roll loop."""
    src = np.asarray(src, dtype=np.float64)
    tgt = np.broadcast_to(np.asarray(tgt, dtype=np.float64), src.shape)
    p, t, _ = src.shape
    out = np.empty((p, t))
    for q in range(p):
        for k in range(t):
            out[q, k] = shift_cost(src[q], tgt[q], k)
    return out


def estimate_yaw_pair(src: npt.ArrayLike, tgt: npt.ArrayLike) -> tuple[float, float, float]:
    """(s*, φ̂, c(s*)) of one pair (T, C): dense scan every ``SCAN_STEP`` bins, then a bounded
    scalar minimisation within one scan step on each side of every local minimum of the scan
    (the lowest wins, ties to the lower shift): two basins whose scan points tie, or nearly,
    may hide the global minimum in either (a half-turn-periodic scene)."""
    src = np.asarray(src, dtype=np.float64)
    t = src.shape[0]
    shifts = np.arange(round(t / SCAN_STEP)) * SCAN_STEP
    costs = np.array([shift_cost(src, tgt, float(s)) for s in shifts])
    i = int(np.argmin(costs))
    best_s, best_c = float(shifts[i]), float(costs[i])
    lowest = (costs <= np.roll(costs, 1)) & (costs <= np.roll(costs, -1))  # circular
    for j in np.flatnonzero(lowest).tolist():
        at = float(shifts[j])
        for lo, hi in ((at - SCAN_STEP, at), (at, at + SCAN_STEP)):
            r = minimize_scalar(
                lambda s: shift_cost(src, tgt, s),
                bounds=(lo, hi),
                method="bounded",
                options={"xatol": 1e-10},
            )
            if r.fun < best_c:
                best_s, best_c = float(r.x), float(r.fun)
    best_s %= t
    # in bins first: s = T/2 gives exactly π (2π·s/T can round above π and wrap to −π)
    signed = best_s if best_s <= t / 2 else best_s - t
    yaw = math.pi * (2.0 * signed / t)
    return best_s, yaw, best_c


def estimate_yaw(src: npt.ArrayLike, tgt: npt.ArrayLike) -> tuple[F64, F64, F64]:
    """Per-pair (shift (P,), yaw (P,), cost (P,)) of pairs (P, T, C) (``tgt`` may broadcast)."""
    src = np.asarray(src, dtype=np.float64)
    tgt = np.broadcast_to(np.asarray(tgt, dtype=np.float64), src.shape)
    res = np.array([estimate_yaw_pair(s, t) for s, t in zip(src, tgt, strict=True)]).reshape(-1, 3)
    return res[:, 0].copy(), res[:, 1].copy(), res[:, 2].copy()


def rerank(src: npt.ArrayLike, tgt: npt.ArrayLike) -> tuple[npt.NDArray[np.int64], F64, F64, F64]:
    """(order, cost, yaw, shift) of K candidates: order by cost ascending, ties by lower index."""
    shift, yaw, cost = estimate_yaw(src, tgt)
    order = np.lexsort((np.arange(len(cost)), cost)).astype(np.int64)
    return order, cost, yaw, shift


# --- translation search ----------------------------------------------------------------------

_MASK = (1 << 64) - 1
_GOLDEN = 0x9E3779B97F4A7C15


class SplitMix64:
    """SplitMix64 (Steele, Lea & Flood 2014), bit-identical to the Rust core's generator."""

    def __init__(self, seed: int) -> None:
        self.state = seed & _MASK

    def next_u64(self) -> int:
        self.state = (self.state + _GOLDEN) & _MASK
        z = self.state
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK
        return z ^ (z >> 31)

    def next_f64(self) -> float:
        return (self.next_u64() >> 11) * (1.0 / (1 << 53))


class TranslationSearch:
    """Python loop over the same coarse-to-fine schedule as the Rust ``TranslationSearch``.

    Stage 0: the grid ``{i·step : |i·step| ≤ half_range}²`` (x outer, y inner). Stage s ≥ 1:
    ``fine_samples`` uniform points in the square of half-size ``step·shrink^(s−1)`` around the
    best so far, clamped to ``[−half_range, half_range]²``, drawn from
    ``SplitMix64(seed ^ (s·0x9E3779B97F4A7C15))`` (x then y per sample).
    """

    def __init__(
        self,
        half_range: float,
        step: float,
        fine_samples: int,
        stages: int,
        shrink: float,
        seed: int,
    ) -> None:
        self.half_range, self.step = float(half_range), float(step)
        self.fine_samples, self.stages = int(fine_samples), int(stages)
        self.shrink, self.seed = float(shrink), int(seed)
        self.stage = 0
        self._best: tuple[float, float, float, float] | None = None
        self._hist: list[tuple[float, float, float, float, int]] = []
        self._pending = self._make_proposals()

    @property
    def done(self) -> bool:
        return self.stage >= self.stages

    def proposals(self) -> F64:
        return np.array(self._pending, dtype=np.float64).reshape(-1, 2)

    def report(self, costs: npt.ArrayLike, yaws: npt.ArrayLike) -> None:
        costs = np.asarray(costs, dtype=np.float64)
        yaws = wrap_angle(np.asarray(yaws, dtype=np.float64))  # stored in (−π, π]
        if self.done:
            raise ValueError("report: the search is already done")
        n = len(self._pending)
        if costs.shape != (n,) or yaws.shape != (n,):
            raise ValueError(f"costs, yaws: expected shape ({n},)")
        for (x, y), c, w in zip(self._pending, costs, yaws, strict=True):
            if self._best is None or c < self._best[3]:
                self._best = (x, y, float(w), float(c))
            self._hist.append((x, y, float(w), float(c), self.stage))
        self.stage += 1
        self._pending = [] if self.done else self._make_proposals()

    def best(self) -> tuple[float, float, float, float] | None:
        return self._best

    def history(self) -> tuple[F64, F64, F64, npt.NDArray[np.int64]]:
        h = self._hist
        xy = np.array([(r[0], r[1]) for r in h], dtype=np.float64).reshape(-1, 2)
        return (
            xy,
            np.array([r[2] for r in h], dtype=np.float64),
            np.array([r[3] for r in h], dtype=np.float64),
            np.array([r[4] for r in h], dtype=np.int64),
        )

    def _make_proposals(self) -> list[tuple[float, float]]:
        if self.stage == 0:
            m = math.floor(self.half_range / self.step + 1e-9)
            hr = self.half_range  # i·step can round one ulp past it (3 × 0.1 > 0.3)
            ticks = [min(max((i - m) * self.step, -hr), hr) for i in range(2 * m + 1)]
            return [(x, y) for x in ticks for y in ticks]
        cx, cy = (0.0, 0.0) if self._best is None else self._best[:2]
        half = self.step
        for _ in range(1, self.stage):
            half *= self.shrink  # repeated products, as in the Rust core (bit-identical)
        rng = SplitMix64(self.seed ^ ((self.stage * _GOLDEN) & _MASK))
        r = self.half_range
        out = []
        for _ in range(self.fine_samples):
            x = cx + (2.0 * rng.next_f64() - 1.0) * half
            y = cy + (2.0 * rng.next_f64() - 1.0) * half
            out.append((min(max(x, -r), r), min(max(y, -r), r)))
        return out
