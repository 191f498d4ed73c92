"""Metric localization: coarse-to-fine translation search with exact yaw per hypothesis.

For each translation hypothesis t (source frame, metres) the source BEV is re-centred at t and
polar-sampled in one fused kernel (``kernels.pad_polar``), decoded into local-view descriptors
(T, C), and matched against the target's descriptors with the exact yaw minimum
(``kernels.estimate_yaw``). The search (``kernels.TranslationSearch``) keeps the lowest cost.
The result is the relative pose ξ_{s→t} = (x, y, yaw) of DESIGN.md §3: the target origin in
source coordinates and yaw_t − yaw_s.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from vvloc import kernels

Decoder = Callable[[npt.NDArray[np.float32]], Any]


class RadialMeanDecoder:
    """Non-learned local-view decoder: mean over radius of a polar BEV, rows L2-normalised.

    ``(..., T, R, C)`` float → ``(..., T, C)`` float32. A baseline, and the geometry tests'
    decoder. Rows with zero norm stay zero.
    """

    def __init__(self, eps: float = 1e-12) -> None:
        self.eps = float(eps)

    def __call__(self, polar: Any) -> npt.NDArray[np.float32]:
        p = np.asarray(polar, dtype=np.float32)
        if p.ndim < 3:
            raise ValueError(f"polar: expected shape (..., T, R, C), got {p.shape}")
        d = p.mean(axis=-2)
        n = np.linalg.norm(d, axis=-1, keepdims=True)
        return (d / np.maximum(n, self.eps)).astype(np.float32)


@dataclass(frozen=True)
class SearchConfig:
    """Translation search of :func:`metric_localize` (metres): the coarse grid covers
    ``[−half_range, half_range]²`` every ``step``; then ``stages − 1`` stages of
    ``fine_samples`` seeded samples in squares of half-size ``step·shrink^(stage−1)``."""

    half_range: float = 3.0
    step: float = 0.6
    fine_samples: int = 32
    stages: int = 4
    shrink: float = 0.5
    seed: int = 0


class MetricResult(NamedTuple):
    """Result of :func:`metric_localize`: ``pose`` ξ_{s→t} = (x m, y m, yaw rad), its
    ``cost``, and every evaluated hypothesis (``history``: xy (M, 2), yaw (M,), cost (M,),
    stage (M,))."""

    pose: tuple[float, float, float]
    cost: float
    history: kernels.SearchHistory


def _numpy(x: Any) -> npt.NDArray[np.float32]:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float32)


def metric_localize(
    bev_src: Any,
    desc_tgt: Any,
    decode: Decoder,
    config: SearchConfig | None = None,
    grid_size: float = 0.3,
    num_angles: int = 120,
    num_radii: int = 25,
    *,
    backend: kernels.Backend = "rust",
) -> MetricResult:
    """Relative pose ξ_{s→t} of a target view against a source BEV.

    Args:
        bev_src: source BEV queries (H, W, C) float, channels-last, cell size ``grid_size``.
        desc_tgt: target local-view descriptors (T, C) (e.g. ``decode`` of the target's polar
            BEV), T = ``num_angles``.
        decode: maps polar BEVs (N, T, R, C) float32 to descriptors (N, T, C) (numpy or torch),
            or to a pair (Ds', Dt') of (N, T, C) when the target side is refined per hypothesis
            too (the learned interactor); ``desc_tgt`` then only fixes T.
        config: the translation search; :class:`SearchConfig` defaults when None.
        grid_size: BEV cell size g, metres.
        num_angles, num_radii: polar grid T × R.
        backend: kernel backend of the padding, the yaw estimation and the search.

    Returns:
        :class:`MetricResult` with the best (x, y, yaw) in the source frame (metres, radians).
    """
    cfg = config or SearchConfig()
    t = kernels._as_f32(desc_tgt, "desc_tgt", 2, "(T, C)")
    if t.shape[0] != num_angles:
        raise ValueError(f"desc_tgt: expected (T={num_angles}, C), got shape {t.shape}")
    search = kernels.TranslationSearch(
        cfg.half_range,
        cfg.step,
        cfg.fine_samples,
        cfg.stages,
        cfg.shrink,
        cfg.seed,
        backend=backend,
    )
    while not search.done:
        xy = search.proposals()
        polar = kernels.pad_polar(  # type: ignore[attr-defined]  # spatial section of kernels
            bev_src, xy, num_angles, num_radii, grid_size, backend=backend
        )
        desc = decode(polar)
        if isinstance(desc, tuple):  # a learned decoder + interactor refines both sides
            src, tgt = (_numpy(d) for d in desc)
        else:
            src, tgt = _numpy(desc), t
        est = kernels.estimate_yaw(src, tgt, backend=backend)
        search.report(est.cost, est.yaw)
    best = search.best()
    assert best is not None  # at least one stage was reported
    return MetricResult((best.x, best.y, best.yaw), best.cost, search.history())
