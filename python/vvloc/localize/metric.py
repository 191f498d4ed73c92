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
from vvloc._checks import as_array, positive_int

__all__ = [
    "METRIC_CANDIDATES",
    "RETRIEVAL_WEIGHT",
    "BestMatch",
    "Decoder",
    "MetricResult",
    "RadialMeanDecoder",
    "SearchConfig",
    "metric_localize",
    "metric_localize_best",
    "metric_localize_each",
    "search_config",
]

Decoder = Callable[[npt.NDArray[np.float32]], Any]
"""A local-view decoder: polar BEVs (N, T, R, C) float32 → descriptors (N, T, C) (numpy or
torch), or the pair (Ds', Dt') of (N, T, C) (:func:`metric_localize`'s ``decode``)."""

#: The localizer's defaults (``Localizer``, ``vvloc eval`` / ``vvloc localize``): M, the
#: metric candidates given to :func:`metric_localize_best`, chosen by coarse matching cost +
#: λ × global-descriptor distance (``retrieval_weight``, the ``bias`` here). Chosen together on
#: the parking validation sessions of two trained models (models/synth-small/HISTORY.md, "Metric
#: candidates ordered with the descriptor distance"): M = 3, λ = 0 (the defaults before
#: 2026-12-03) gave 83.5 % and 81.1 % Recall@1 at 2 m, M = 5, λ = 2 85.7 % and 83.9 %. Kept
#: here, beside the search, so that the CLI reads them without importing the localizer.
METRIC_CANDIDATES = 5
RETRIEVAL_WEIGHT = 2.0


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
    ``fine_samples`` seeded samples in squares of half-size ``step·shrink^(stage−1)``, clamped
    to that square (:class:`vvloc.kernels.TranslationSearch`). The square is in the source's
    frame, the one the hypotheses shift (in the localizer, the query's): a query within
    ``half_range`` of a keyframe along the keyframe's axes can lie outside it along the query's
    (ξ = (2.5, 2.5, 45°) one way is x = −3.54 m the other way), and a translation outside the
    square is answered on its edge, with a cost that may still pass the acceptance rule.
    Widen ``half_range`` where revisits can be further off."""

    half_range: float = 3.0
    step: float = 0.6
    fine_samples: int = 32
    stages: int = 4
    shrink: float = 0.5
    seed: int = 0

    def validate(self) -> None:
        """``ValueError``/``TypeError`` naming the field when the search cannot run."""
        _search(self, "reference")


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


def search_config(config: Any, name: str = "config") -> SearchConfig:
    """``config`` as a :class:`SearchConfig` (None: the defaults); ``TypeError`` naming
    ``name`` for anything else."""
    if config is None:
        return SearchConfig()
    if not isinstance(config, SearchConfig):
        raise TypeError(f"{name}: expected a SearchConfig or None, got {type(config).__name__}")
    return config


def _search(cfg: SearchConfig, backend: kernels.Backend) -> kernels.TranslationSearch:
    return kernels.TranslationSearch(
        cfg.half_range,
        cfg.step,
        cfg.fine_samples,
        cfg.stages,
        cfg.shrink,
        cfg.seed,
        backend=backend,
    )


def _score(
    desc: Any, tgt: npt.NDArray[np.float32], backend: kernels.Backend
) -> kernels.YawEstimate:
    """Exact yaw minimum of decoded hypotheses: ``desc`` is (N, T, C), or the pair (Ds', Dt')
    of a learned interactor; ``tgt`` (T, C) is used only for a plain (N, T, C). A decoder whose
    output does not fit is named (not the kernel's arguments)."""
    if isinstance(desc, tuple):  # a learned decoder + interactor refines both sides
        if len(desc) != 2:
            raise ValueError(f"decode/interact: expected a pair (Ds', Dt'), got {len(desc)} items")
        src, t = (_numpy(d) for d in desc)
        if np.ndim(src) != 3 or np.shape(t) not in (np.shape(src), (1, *np.shape(src)[1:])):
            raise ValueError(
                "decode/interact: expected a pair (Ds', Dt') of shapes (N, T, C) and (N, T, C) "
                f"or (1, T, C), got {np.shape(src)} and {np.shape(t)}"
            )
    else:
        src, t = _numpy(desc), tgt
        if np.ndim(src) != 3 or np.shape(src)[1:] != tgt.shape:
            raise ValueError(
                f"decode: returned shape {np.shape(src)}; expected (N, {tgt.shape[0]}, "
                f"{tgt.shape[1]}), descriptors of the target's T and C"
            )
    try:
        return kernels.estimate_yaw(src, t, backend=backend)
    except ValueError as e:  # named after the kernel's arguments, src and tgt
        side, _, fault = str(e).partition(": ")
        pair = isinstance(desc, tuple)  # else tgt is the caller's, checked up front
        if side == "src" or (side == "tgt" and pair):
            raise ValueError(
                f"{'decode/interact' if pair else 'decode'}: returned "
                f"{'source' if side == 'src' else 'target'} descriptors that the yaw estimation "
                f"refuses: {fault}"
            ) from None
        raise


def _report(search: kernels.TranslationSearch, est: kernels.YawEstimate, n: int) -> None:
    """Report the scores of a stage's ``n`` hypotheses to ``search``, a decoder that returned
    another number of them named (not the search's ``costs``)."""
    if len(est.cost) != n:
        raise ValueError(
            f"decode: returned {len(est.cost)} descriptor sets for {n} hypotheses (one per "
            "polar BEV it is given)"
        )
    search.report(est.cost, est.yaw)


def _finish(
    search: kernels.TranslationSearch,
    bev_src: Any,
    score: Callable[[npt.NDArray[np.float32]], kernels.YawEstimate],
    num_angles: int,
    num_radii: int,
    grid_size: float,
    backend: kernels.Backend,
) -> MetricResult:
    """Run the remaining stages of ``search``: pad + polar-sample the source at each stage's
    proposals, ``score`` the polar BEVs (N, T, R, C), report; return the best hypothesis."""
    while not search.done:
        xy = search.proposals()
        polar = kernels.pad_polar(  # type: ignore[attr-defined]  # spatial section of kernels
            bev_src, xy, num_angles, num_radii, grid_size, backend=backend
        )
        _report(search, score(polar), len(xy))
    best = search.best()
    assert best is not None  # at least one stage was reported
    return MetricResult((best.x, best.y, best.yaw), best.cost, search.history())


def metric_localize(
    bev_src: Any,
    desc_tgt: Any,
    decode: Decoder,
    config: SearchConfig | None,
    grid_size: float,
    num_angles: int,
    num_radii: int,
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
        grid_size: BEV cell size g, metres: the model's (``ModelConfig.grid_size``), which
            made ``bev_src``; no default (another cell size scales every translation wrongly
            at a cost as low as the right one's).
        num_angles, num_radii: polar grid T × R the decoder was trained on
            (``ModelConfig.num_angles``, ``num_radii``); no default.
        backend: kernel backend of the padding, the yaw estimation and the search.

    Returns:
        :class:`MetricResult` with the best (x, y, yaw) in the source frame (metres, radians).
    """
    cfg = search_config(config)
    _check_callables(decode)
    t = kernels._as_f32(desc_tgt, "desc_tgt", 2, "(T, C)")
    num_angles = positive_int(num_angles, "num_angles", minimum=3)
    if t.shape[0] != num_angles:
        raise ValueError(f"desc_tgt: expected (T={num_angles}, C), got shape {t.shape}")
    kernels._check_row_norms(t, "desc_tgt")
    return _finish(
        _search(cfg, backend),
        bev_src,
        lambda polar: _score(decode(polar), t, backend),
        num_angles,
        num_radii,
        grid_size,
        backend,
    )


class BestMatch(NamedTuple):
    """Result of :func:`metric_localize_best`: ``index`` of the chosen target, its
    :class:`MetricResult` (``result``), every target's lowest coarse-stage cost
    (``coarse_cost`` (M,) float64) and the score the target was chosen by (``score`` (M,)
    float64: ``coarse_cost + bias``; ``index`` is the first of its lowest)."""

    index: int  # type: ignore[assignment]  # the field shadows tuple.index (public API)
    result: MetricResult
    coarse_cost: npt.NDArray[np.float64]
    score: npt.NDArray[np.float64]


def metric_localize_best(
    bev_src: Any,
    desc_tgts: Any,
    decode: Decoder,
    interact: Callable[[Any, int], tuple[Any, Any]] | None,
    config: SearchConfig | None,
    grid_size: float,
    num_angles: int,
    num_radii: int,
    *,
    bias: npt.ArrayLike | None = None,
    backend: kernels.Backend = "rust",
) -> BestMatch:
    """Metric localization of one source BEV against the best of several targets.

    The coarse stage (the grid of :class:`SearchConfig`) is run against every target with the
    source padded and decoded once (the decoder's work is shared; only the interactor and the
    yaw estimation run per target); the target of lowest score, its coarse cost plus its
    ``bias`` (the first on ties), then goes through the fine stages alone. With one target this
    equals :func:`metric_localize`.

    Args:
        bev_src: source BEV queries (H, W, C) float, channels-last, cell size ``grid_size``.
        desc_tgts: (M, T, C) float: the targets' local-view descriptors, T = ``num_angles``.
        decode: maps polar BEVs (N, T, R, C) float32 to source descriptors (N, T, C).
        interact: ``interact(ds, k)`` refines the decoded source descriptors ds (N, T, C)
            against target k into the pair (Ds', Dt') of (N, T, C) (the learned interactor);
            None matches ``decode``'s output against ``desc_tgts[k]`` directly.
        bias: (M,) finite float, added to each target's coarse cost to choose the one refined
            (e.g. a weighted global-descriptor distance, ``Localizer(retrieval_weight=)``);
            None = zeros, the coarse cost alone.
        config, grid_size, num_angles, num_radii, backend: as :func:`metric_localize`.

    Returns:
        :class:`BestMatch`: the chosen target, its pose ξ_{s→t} (metres, radians, source frame)
        and cost, and each target's coarse-stage cost.
    """
    cfg = search_config(config)
    _check_callables(decode, interact)
    tgts = _targets(desc_tgts, num_angles)
    if bias is None:
        offsets = np.zeros(len(tgts))
    else:
        try:
            raw = as_array(bias, "bias", f"({len(tgts)},)")
        except ValueError as e:
            raise TypeError(f"bias: expected ({len(tgts)},) real numbers, got {bias!r:.80}") from e
        if raw.dtype.kind not in "iuf":  # strings would be parsed, bools read as 1 and 0
            raise TypeError(f"bias: expected ({len(tgts)},) real numbers, got dtype {raw.dtype}")
        offsets = raw.astype(np.float64)
        if offsets.shape != (len(tgts),):
            raise ValueError(
                f"bias: expected shape ({len(tgts)},), one per target, got {offsets.shape}"
            )
        if not np.isfinite(offsets).all():
            raise ValueError(f"bias: expected finite values, got {offsets}")

    shared = _SharedCoarse(bev_src, tgts, decode, interact, cfg, grid_size, num_radii, backend)
    scores = shared.coarse + offsets
    k = int(np.argmin(scores))  # finite: TranslationSearch.report refuses NaN and inf
    return BestMatch(k, shared.finish(k), shared.coarse, scores)


def metric_localize_each(
    bev_src: Any,
    desc_tgts: Any,
    decode: Decoder,
    interact: Callable[[Any, int], tuple[Any, Any]] | None,
    config: SearchConfig | None,
    grid_size: float,
    num_angles: int,
    num_radii: int,
    *,
    backend: kernels.Backend = "rust",
) -> list[MetricResult]:
    """Metric localization of one source BEV against each of several targets (e.g. the loop
    candidates of one keyframe): the coarse stage is shared as in :func:`metric_localize_best`
    (the source padded and decoded once), then every target goes through the fine stages on its
    own. Result k is :func:`metric_localize` of ``desc_tgts[k]`` with ``decode`` followed by
    ``interact(·, k)``.

    Args:
        bev_src, desc_tgts, decode, interact, config, grid_size, num_angles, num_radii,
        backend: as :func:`metric_localize_best`.

    Returns:
        M :class:`MetricResult`: pose ξ_{s→t_k} (metres, radians, source frame), cost, history.
    """
    cfg = search_config(config)
    _check_callables(decode, interact)
    tgts = _targets(desc_tgts, num_angles)
    shared = _SharedCoarse(bev_src, tgts, decode, interact, cfg, grid_size, num_radii, backend)
    return [shared.finish(k) for k in range(len(tgts))]


def _check_callables(decode: Any, interact: Any = None) -> None:
    """``TypeError`` naming ``decode`` (a callable) or ``interact`` (a callable or None); an
    object that is neither failed at the first search stage as "'NoneType' object is not
    callable"."""
    if not callable(decode):
        raise TypeError(
            "decode: expected a callable mapping polar BEVs (N, T, R, C) to descriptors, got "
            f"{type(decode).__name__}"
        )
    if interact is not None and not callable(interact):
        raise TypeError(f"interact: expected a callable or None, got {type(interact).__name__}")


def _targets(desc_tgts: Any, num_angles: int) -> npt.NDArray[np.float32]:
    """``desc_tgts`` as (M ≥ 1, T = ``num_angles``, C) float32, or a ValueError naming it."""
    num_angles = positive_int(num_angles, "num_angles", minimum=3)  # the kernels' T >= 3
    tgts = kernels._as_f32(desc_tgts, "desc_tgts", 3, "(M, T, C)")
    if tgts.shape[0] < 1 or tgts.shape[1] != num_angles:
        raise ValueError(f"desc_tgts: expected (M >= 1, T={num_angles}, C), got shape {tgts.shape}")
    kernels._check_row_norms(tgts, "desc_tgts")
    return tgts


class _SharedCoarse:
    """The coarse stage of one source against M targets (M searches, the source padded and
    decoded once, ``interact`` or the plain match per target; ``coarse`` (M,) their lowest
    costs); :meth:`finish` runs target k's fine stages."""

    def __init__(
        self,
        bev_src: Any,
        tgts: npt.NDArray[np.float32],
        decode: Decoder,
        interact: Callable[[Any, int], tuple[Any, Any]] | None,
        cfg: SearchConfig,
        grid_size: float,
        num_radii: int,
        backend: kernels.Backend,
    ) -> None:
        self.bev_src, self.tgts, self.decode, self.interact = bev_src, tgts, decode, interact
        self.grid = (tgts.shape[1], num_radii, grid_size)
        self.backend = backend
        self.searches = [_search(cfg, backend) for _ in range(len(tgts))]
        xy = self.searches[0].proposals()  # the coarse grid: the same for every search
        polar = kernels.pad_polar(  # type: ignore[attr-defined]  # spatial section of kernels
            bev_src, xy, *self.grid, backend=backend
        )
        ds = decode(polar)
        self.coarse = np.empty(len(tgts))
        for k, search in enumerate(self.searches):
            _report(search, self._score(ds, k), len(xy))
            best = search.best()
            assert best is not None
            self.coarse[k] = best.cost

    def _score(self, ds: Any, k: int) -> kernels.YawEstimate:
        if self.interact is not None:
            pair = self.interact(ds, k)
            if not isinstance(pair, tuple):  # one array would be matched against the target
                raise TypeError(
                    "interact: expected the pair (Ds', Dt') of (N, T, C) arrays, got "
                    f"{type(pair).__name__}"
                )
            return _score(pair, self.tgts[k], self.backend)
        if isinstance(ds, tuple):
            raise TypeError(
                "decode: expected source descriptors (N, T, C) when interact is None, got a pair"
            )
        return _score(ds, self.tgts[k], self.backend)

    def finish(self, k: int) -> MetricResult:
        return _finish(
            self.searches[k],
            self.bev_src,
            lambda polar: self._score(self.decode(polar), k),
            *self.grid,
            self.backend,
        )
