"""Matching kernels: Rust vs the literal references, exactness of the yaw minimum, re-ranking,
the translation search schedule, thread-count independence and bad inputs."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import vvloc
from memory_helpers import run_limited
from vvloc import kernels as K
from vvloc.reference import matching as ref


def _unit_rows(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    x = rng.standard_normal(shape).astype(np.float32)
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _smooth_rows(rng: np.random.Generator, p: int, t: int, c: int) -> np.ndarray:
    """Descriptors that vary smoothly with the angle bin (like real local-view descriptors)."""
    ang = 2 * np.pi * np.arange(t) / t
    coef = rng.standard_normal((p, 3, 2, c))
    x = sum(
        coef[:, f, 0, None, :] * np.cos((f + 1) * ang)[None, :, None]
        + coef[:, f, 1, None, :] * np.sin((f + 1) * ang)[None, :, None]
        for f in range(3)
    )
    x = np.asarray(x, dtype=np.float32)
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _fractional_roll(src: np.ndarray, s: float) -> np.ndarray:
    return ref.roll_rows(src, s).astype(np.float32)


# --- parity ----------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    p=st.integers(1, 3),
    t=st.integers(2, 16),
    c=st.integers(1, 20),
    seed=st.integers(0, 2**32 - 1),
    scale=st.sampled_from([1.0, 0.01, 30.0, 1e-19, 1e-21, 1e-23, 1e-25, 1e-30, 1e-38, 1e-41]),
)
def test_yaw_costs_equal_reference(p, t, c, seed, scale):
    # at tiny scales the squared distances fell below float32's normal range (1.2e-38) in the
    # f32 tables: at 1e-23 the curve was 15 % off, at 1e-25 all zeros (estimate_yaw was right:
    # its exact polish); such pairs are rescaled by a power of two first
    rng = np.random.default_rng(seed)
    src = (rng.standard_normal((p, t, c)) * scale).astype(np.float32)
    tgt = (rng.standard_normal((p, t, c)) * scale).astype(np.float32)
    src[0, 0, 0] = scale  # not all zeros, even where float32 flushes most of them (1e-41)
    got = K.yaw_costs(src, tgt)
    want = K.yaw_costs(src, tgt, backend="reference")
    assert got.shape == (p, t) and got.dtype == np.float64
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6 * float(np.abs(src).max()))
    if t < K.MIN_YAW_BINS:  # two bins: cost curves, but no yaw (its sign is undetermined)
        for backend in ("rust", "reference"):
            with pytest.raises(ValueError, match=r"^src: expected \(P, T, C\) with T >= 3 angle"):
                K.estimate_yaw(src, tgt, backend=backend)
        return
    est = K.estimate_yaw(src, tgt)
    for q in range(p):
        lit = ref.shift_cost(src[q], tgt[q], float(est.shift[q]))
        assert est.cost[q] == pytest.approx(lit, rel=1e-9)
        assert est.cost[q] <= want[q].min() * (1 + 1e-9)


@settings(max_examples=20, deadline=None)
@given(
    p=st.integers(1, 3),
    t=st.integers(3, 14),
    c=st.integers(1, 24),
    seed=st.integers(0, 2**32 - 1),
    smooth=st.booleans(),
)
def test_estimate_yaw_is_at_least_as_good_as_the_dense_reference(p, t, c, seed, smooth):
    rng = np.random.default_rng(seed)
    if smooth:
        src, tgt = _smooth_rows(rng, p, t, c), _smooth_rows(rng, p, t, c)
    else:
        src, tgt = _unit_rows(rng, (p, t, c)), _unit_rows(rng, (p, t, c))
    got = K.estimate_yaw(src, tgt)
    want = K.estimate_yaw(src, tgt, backend="reference")
    for q in range(p):
        # The reported cost is the literal cost at the reported shift ...
        lit = ref.shift_cost(src[q], tgt[q], float(got.shift[q]))
        assert got.cost[q] == pytest.approx(lit, abs=1e-9)
        # ... and no larger than the reference's dense-scan minimum.
        assert got.cost[q] <= want.cost[q] + 1e-6
        assert 0.0 <= got.shift[q] < t
        assert -np.pi < got.yaw[q] <= np.pi
        np.testing.assert_allclose(
            np.exp(1j * got.yaw[q]), np.exp(2j * np.pi * got.shift[q] / t), atol=1e-12
        )
        # Where the minimum is unique (clear gap to the second-best integer bin), s* agrees.
        curve = ref.yaw_costs(src[q : q + 1], tgt[q : q + 1])[0]
        srt = np.sort(curve)
        if t > 3 and srt[1] - srt[0] > 0.05:
            d = abs(got.shift[q] - want.shift[q])
            assert min(d, t - d) < 1e-3


@pytest.mark.parametrize("s_true", [0.0, 0.37, 5.5, 47.99, 71.25])
def test_estimate_yaw_recovers_an_exact_fractional_roll(s_true):
    rng = np.random.default_rng(1)
    t, c = 72, 32
    src = _unit_rows(rng, (1, t, c))
    tgt = _fractional_roll(src[0], s_true)[None]
    est = K.estimate_yaw(src, tgt)
    d = abs(est.shift[0] - s_true)
    assert min(d, t - d) < 1e-4
    assert est.cost[0] < 1e-5
    yaw = 2 * np.pi * s_true / t
    assert np.angle(np.exp(1j * (est.yaw[0] - yaw))) == pytest.approx(0.0, abs=1e-5)


@pytest.mark.parametrize("eps", [3e-5, 1e-4, 2.5e-4])
def test_estimate_yaw_finds_a_close_match_just_below_a_whole_bin(eps):
    # the Rust kernel picked the next interval's local minimum (~2e-4 bins off, its cost ~1e-4
    # above) for a minimum this close below a whole bin; the reference did not
    rng = np.random.default_rng(7)
    t, c = 40, 16
    src = _unit_rows(rng, (4, t, c))
    s_true = np.array([2.0, 11.0, 25.0, 39.0]) - eps
    tgt = np.stack([_fractional_roll(src[q], s_true[q]) for q in range(4)])
    for backend in ("rust", "reference"):
        est = K.estimate_yaw(src, tgt, backend=backend)
        d = np.abs(est.shift - s_true)
        assert np.all(np.minimum(d, t - d) < 1e-6), (backend, est.shift - s_true)


def test_estimate_yaw_with_rows_of_very_different_sizes_matches_the_reference():
    # rows of sizes 1 to 1e6 in one descriptor: the kernel's float32 end slope of the best
    # interval had the wrong sign (b - a + e cancels), the interval was taken as minimal at an
    # end, and the yaw came out half a turn off (-0.05 rad against -3.09), without an error
    src = np.float32([[-1.0], [1.1e6], [1.0], [-130.0]])[None]
    tgt = np.float32([[35000.0], [-180.0], [4000.0], [-17.0]])[None]
    want = K.estimate_yaw(src, tgt, backend="reference")
    for got in (K.estimate_yaw(src, tgt), K.rerank(src, tgt)):
        assert got.shift[0] == pytest.approx(want.shift[0], abs=1e-6)
        assert got.cost[0] == pytest.approx(want.cost[0], rel=1e-12)
    assert want.yaw[0] == pytest.approx(-3.0916, abs=1e-4)


def test_estimate_yaw_keeps_the_best_interval_of_rows_of_very_different_sizes():
    # the first pass's lower bounds, built from float32 slopes of rows of very different
    # sizes, pruned the best interval: a review's fuzz (rows of sizes 1 to 3e6: shift 5.0 at
    # cost 588 622.6 against 0.971 at 588 577.5) and an audit's case (T = 3, sizes up to
    # 6e12: one bin off, 0.37 % too costly); such pairs now take the kernel's exact path
    cases = [
        ([-18271.859375, -394.004974, 2963412.5, 100.926277, 515.355102],
         [-3.365183, -26.200469, 85942.0859375, -1.846915, 48154.277343]),
        ([-920.0, 6.1e12, -2.2e12], [7.0, 9.4e9, -2.0]),
    ]  # fmt: skip
    for s, g in cases:
        src, tgt = np.float32(s)[None, :, None], np.float32(g)[None, :, None]
        want = K.estimate_yaw(src, tgt, backend="reference")
        for got in (K.estimate_yaw(src, tgt), K.rerank(src, tgt)):
            assert got.shift[0] == pytest.approx(want.shift[0], abs=1e-6)
            assert got.cost[0] == pytest.approx(want.cost[0], rel=1e-8)


@settings(max_examples=40, deadline=None)
@given(
    p=st.integers(1, 4),
    t=st.integers(3, 8),
    c=st.integers(1, 3),
    span=st.floats(0.0, 6.5),
    seed=st.integers(0, 2**32 - 1),
)
def test_estimate_yaw_of_rows_of_any_sizes_is_at_least_as_good_as_the_reference(
    p, t, c, span, seed
):
    # entries of sizes 1 to 10^span and random signs (the review's fuzz found a few pairs per
    # thousand in another basin at span 6.5 before the exact path)
    rng = np.random.default_rng(seed)

    def rows() -> np.ndarray:
        mag = 10 ** rng.uniform(0, span, size=(p, t, c))
        return (mag * rng.choice([-1.0, 1.0], size=mag.shape)).astype(np.float32)

    src, tgt = rows(), rows()
    got = K.estimate_yaw(src, tgt)
    want = K.estimate_yaw(src, tgt, backend="reference")
    for q in range(p):
        lit = ref.shift_cost(src[q], tgt[q], float(got.shift[q]))
        assert got.cost[q] == pytest.approx(lit, rel=1e-9)
        # at a kink (C = 1: a row's distance passes through 0) the minimisers stop ~1e-8 bins
        # apart, so a cost a hair above the reference's must be at the reference's shift
        assert got.cost[q] <= want.cost[q] * (1 + 1e-7)
        if got.cost[q] > want.cost[q] * (1 + 1e-12):
            d = abs(got.shift[q] - want.shift[q])
            assert min(d, t - d) < 1e-4


def test_rows_with_a_large_common_part_keep_the_best_interval():
    # a review's case: the wide rows above plus a constant second channel K, which cancels in
    # every distance (the same cost curve) but makes the rows' norms alike (no exact path):
    # with K = 3e7 or 4e7 the first pass pruned the best interval (shift 5.0 at 588 622.6
    # against 0.971 at 588 577.5) while the polish margin followed the cost, not the rows' size
    s = np.float32([-18271.859375, -394.004974, 2963412.5, 100.926277, 515.355102])
    g = np.float32([-3.365183, -26.200469, 85942.0859375, -1.846915, 48154.277343])
    want = K.estimate_yaw(s[None, :, None], g[None, :, None], backend="reference")
    for k in (1e7, 2e7, 3e7, 4e7, 6e7):
        src = np.stack([s, np.full(5, k, np.float32)], 1)[None]
        tgt = np.stack([g, np.full(5, k, np.float32)], 1)[None]
        got = K.estimate_yaw(src, tgt)
        assert got.shift[0] == pytest.approx(want.shift[0], abs=1e-5), k
        assert got.cost[0] == pytest.approx(want.cost[0], rel=1e-7), k


@settings(max_examples=30, deadline=None)
@given(
    t=st.integers(3, 40),
    c=st.integers(1, 16),
    twin=st.booleans(),
    seed=st.integers(0, 2**32 - 1),
)
def test_estimate_yaw_is_the_same_for_a_pair_scaled_by_a_power_of_two(t, c, twin, seed):
    # every step of the kernel is homogeneous in the rows' size, so a pair scaled by 2^k (exact
    # in float32) has the same shift and 2^k times the cost; the polish margin once followed
    # the cost alone, and a half-turn-twin pair came out half a turn off at scales 2^6-2^12
    rng = np.random.default_rng(seed)
    src = _unit_rows(rng, (4, t, c))
    if twin and t % 2 == 0:
        src[:, t // 2 :] = src[:, : t // 2] + np.float32(1e-6) * rng.standard_normal(
            (4, t // 2, c)
        ).astype(np.float32)
    s0 = rng.uniform(0, t, size=4)
    tgt = np.stack([_fractional_roll(src[q], s0[q]) for q in range(4)])
    tgt += (10 ** rng.uniform(-3, -1) * rng.standard_normal(tgt.shape)).astype(np.float32)
    base = K.estimate_yaw(src, tgt)
    for e in (-60, -20, -6, 6, 12, 40):
        f = np.float32(2.0**e)
        got = K.estimate_yaw(src * f, tgt * f)
        np.testing.assert_array_equal(got.shift, base.shift, err_msg=f"2^{e}")
        np.testing.assert_allclose(got.cost, base.cost * 2.0**e, rtol=1e-12, err_msg=f"2^{e}")


def test_a_near_perfect_match_keeps_its_basin_against_a_half_turn_twin():
    # each source's two halves differ by 1e-5 and its target is it rolled by s0: the basin half
    # a turn away costs ~1e-5 more, within the float32 tables' error near a perfect match, and
    # the kernel's approximate stage alone picked it for 17 of 40 such pairs
    rng = np.random.default_rng(11)
    p, t, c = 16, 24, 16
    half = _unit_rows(rng, (p, t // 2, c)).astype(np.float64)
    src64 = np.concatenate([half, half + 1e-5 * rng.standard_normal(half.shape)], axis=1)
    s0 = rng.uniform(0, t, size=p)
    src = src64.astype(np.float32)
    tgt = np.stack([ref.roll_rows(src[q], s0[q]) for q in range(p)]).astype(np.float32)
    got = K.estimate_yaw(src, tgt)
    for q in range(p):
        at_s0 = ref.shift_cost(src[q], tgt[q], float(s0[q]))
        assert ref.shift_cost(src[q], tgt[q], float(s0[q]) + t / 2) > at_s0 + 1e-6
        d = abs(got.shift[q] - s0[q])
        assert min(d, t - d) < 1e-3, (q, got.shift[q], s0[q])
        assert got.cost[q] <= at_s0 + 1e-9


def test_the_reference_refines_every_basin_when_scan_points_tie():
    # a half-turn-periodic pair: the scan costs at shifts 1 and 3 tie exactly, the minimum lies
    # just below 3; the reference refined only around the first tied point (shift 1, a half
    # turn off: yaw +90° against the kernel's right -90.4°)
    a = np.array(
        [[[-0.7019236, -0.4623309], [-0.05116928, 1.1469532], [-1.2918115, 0.4667015],
          [0.6099724, 0.5582887]]], np.float32,
    )  # fmt: skip
    assert ref.shift_cost(a[0], -a[0], 1.0) == ref.shift_cost(a[0], -a[0], 3.0)
    got = K.estimate_yaw(a, -a)
    want = K.estimate_yaw(a, -a, backend="reference")
    assert got.shift[0] == pytest.approx(2.99583, abs=1e-4)
    assert want.shift[0] == pytest.approx(got.shift[0], abs=1e-6)
    assert want.cost[0] == pytest.approx(got.cost[0], abs=1e-9)


def test_estimate_yaw_paper_size_matches_reference_on_two_pairs():
    rng = np.random.default_rng(2)
    src = _smooth_rows(rng, 2, 120, 64)
    tgt = np.stack([_fractional_roll(src[0], 33.3), _smooth_rows(rng, 1, 120, 64)[0]])
    tgt[0] += 0.01 * rng.standard_normal(tgt[0].shape).astype(np.float32)
    got = K.estimate_yaw(src, tgt)
    want = K.estimate_yaw(src, tgt, backend="reference")
    assert np.all(got.cost <= want.cost + 1e-6)
    assert abs(got.shift[0] - 33.3) < 0.05


def test_matching_cost_any_leading_shape():
    rng = np.random.default_rng(3)
    a = rng.standard_normal((2, 3, 5, 4)).astype(np.float32)
    b = rng.standard_normal((2, 3, 5, 4)).astype(np.float32)
    got = K.matching_cost(a, b)
    assert got.shape == (2, 3)
    np.testing.assert_allclose(got, K.matching_cost(a, b, backend="reference"), rtol=1e-12)
    assert K.matching_cost(a[0, 0], b[0, 0]).shape == ()


@pytest.mark.parametrize("backend", ["rust", "reference"])
def test_matching_cost_of_an_empty_batch_is_empty(backend):
    # "(0, T, C)" was refused ("a: expected a non-empty array") while the docstring allowed it
    for lead in [(0,), (2, 0), (0, 3)]:
        a = np.zeros((*lead, 4, 3), np.float32)
        got = K.matching_cost(a, a, backend=backend)
        assert got.shape == lead and got.dtype == np.float64
    for shape in [(2, 0, 3), (2, 4, 0), (4,)]:  # T, C >= 1 still
        with pytest.raises(ValueError, match=r"^a: expected shape \(\.\.\., T, C\) with T, C >= 1"):
            K.matching_cost(np.zeros(shape), np.zeros(shape), backend=backend)


def test_non_contiguous_and_float64_inputs():
    rng = np.random.default_rng(4)
    big = rng.standard_normal((3, 10, 16))
    src, tgt = big[:, :, ::2], big[::-1, :, 1::2]
    got = K.estimate_yaw(src, tgt)
    want = K.estimate_yaw(np.ascontiguousarray(src), np.ascontiguousarray(tgt))
    np.testing.assert_array_equal(got.cost, want.cost)


def test_shared_target_broadcasts():
    rng = np.random.default_rng(5)
    src, tgt = _unit_rows(rng, (4, 9, 6)), _unit_rows(rng, (9, 6))
    a = K.estimate_yaw(src, tgt)
    b = K.estimate_yaw(src, np.broadcast_to(tgt, src.shape))
    np.testing.assert_array_equal(a.cost, b.cost)
    np.testing.assert_array_equal(a.shift, b.shift)


# --- rerank ----------------------------------------------------------------------------------


def test_rerank_orders_by_cost_with_ties_by_index():
    rng = np.random.default_rng(6)
    k, t, c = 12, 16, 8
    query = _unit_rows(rng, (t, c))
    cands = _unit_rows(rng, (k, t, c))
    cands[7] = _fractional_roll(query, 3.4)  # the true match
    cands[3] = cands[9] = cands[5]  # exact ties
    r = K.rerank(cands, query)
    assert r.order[0] == 7
    assert sorted(r.order.tolist()) == list(range(k))
    assert np.all(np.diff(r.cost[r.order]) >= 0)
    pos = {int(i): n for n, i in enumerate(r.order)}
    assert pos[3] < pos[5] < pos[9]
    ref_r = K.rerank(cands, query, backend="reference")
    np.testing.assert_array_equal(r.order, ref_r.order)
    assert np.all(r.cost <= ref_r.cost + 1e-6)


# --- threads ---------------------------------------------------------------------------------


def test_results_identical_for_one_and_two_threads():
    rng = np.random.default_rng(7)
    src, tgt = _smooth_rows(rng, 9, 40, 33), _smooth_rows(rng, 9, 40, 33)
    before = vvloc.get_num_threads()
    try:
        vvloc.set_num_threads(1)
        a = (K.estimate_yaw(src, tgt), K.yaw_costs(src, tgt), K.rerank(src, tgt))
        vvloc.set_num_threads(2)
        b = (K.estimate_yaw(src, tgt), K.yaw_costs(src, tgt), K.rerank(src, tgt))
    finally:
        vvloc.set_num_threads(before)
    for x, y in zip(a, b, strict=True):
        for u, v in zip(x, y, strict=True):
            np.testing.assert_array_equal(u, v)
    np.testing.assert_array_equal(a[1], b[1])


# --- translation search ----------------------------------------------------------------------


def _drive(search, f):
    while not search.done:
        xy = search.proposals()
        costs = np.array([f(x, y) for x, y in xy])
        search.report(costs, 0.1 * costs)
    return search


@settings(max_examples=15, deadline=None)
@given(
    half=st.floats(0.5, 5.0),
    step_frac=st.floats(0.1, 1.0),
    fine=st.integers(1, 20),
    stages=st.integers(1, 5),
    shrink=st.floats(0.1, 1.0),
    seed=st.integers(0, 2**64 - 1),
)
def test_search_schedule_identical_on_both_backends(half, step_frac, fine, stages, shrink, seed):
    step = half * step_frac

    def f(x, y):
        return np.cos(1.7 * x) + np.sin(0.9 * y) + 0.1 * x * y

    args = (half, step, fine, stages, shrink, seed)
    a = _drive(K.TranslationSearch(*args), f)
    b = _drive(K.TranslationSearch(*args, backend="reference"), f)
    for u, v in zip(a.history(), b.history(), strict=True):
        np.testing.assert_array_equal(u, v)
    assert a.best() == b.best()


def test_search_finds_a_smooth_minimum_and_records_stages():
    s = _drive(
        K.TranslationSearch(3.0, 0.5, fine_samples=24, stages=4, shrink=0.5, seed=3),
        lambda x, y: np.hypot(x - 1.23, y + 2.04),
    )
    h = s.history()
    assert (h.stage == 0).sum() == 13 * 13
    assert len(h.cost) == 169 + 3 * 24
    assert np.all(np.abs(h.xy) <= 3.0)
    best = s.best()
    assert best is not None
    assert np.hypot(best.x - 1.23, best.y + 2.04) < 0.1
    assert best.cost == h.cost.min()
    assert s.proposals().shape == (0, 2)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"step": 0.0}, "step"),
        ({"step": -1.0}, "step"),
        ({"stages": 0}, "stages"),
        ({"half_range": 0.1}, "half_range"),
        ({"shrink": 1.5}, "shrink"),
        ({"shrink": 0.0}, "shrink"),
        ({"fine_samples": 0}, "fine_samples"),
        ({"seed": -1}, "seed"),
        ({"half_range": 1e300, "step": 1e-300}, "step"),  # an infinite ratio, not OverflowError
        ({"half_range": 1e4, "step": 1e-3}, "step"),
    ],
)
@pytest.mark.parametrize("backend", ["rust", "reference"])
def test_search_rejects_bad_configuration(kwargs, name, backend):
    cfg = {"half_range": 2.0, "step": 0.5, "fine_samples": 4, "stages": 3, "shrink": 0.5}
    with pytest.raises(ValueError, match=name):
        K.TranslationSearch(**{**cfg, **kwargs}, backend=backend)


@pytest.mark.parametrize("backend", ["rust", "reference"])
def test_search_keeps_to_its_square_and_wraps_reported_yaws(backend):
    s = K.TranslationSearch(0.3, 0.1, fine_samples=4, stages=2, backend=backend)
    grid = s.proposals()
    assert len(grid) == 49 and np.abs(grid).max() == 0.3  # 3 × 0.1 rounded one ulp past it
    n = len(grid)
    s.report(np.arange(n, dtype=float), np.full(n, 100.0))  # a yaw far outside (−π, π]
    best = s.best()
    assert best is not None and best.yaw == pytest.approx(100.0 - 32 * np.pi)
    assert np.all(np.abs(s.history().yaw) <= np.pi)


def test_search_wraps_huge_yaws_to_the_same_bits_on_both_backends():
    # the reference's wrap lost the remainder of large yaws (1e16 rad gave 2.0, 1e17 gave 0.0)
    yaws = np.array([100.0, -7.5, 1e6, 1e10, 1e16, -1e16, 1e17, 1e300, -np.pi, np.pi])
    got = {}
    for backend in ("rust", "reference"):
        s = K.TranslationSearch(0.5, 0.5, fine_samples=1, stages=1, backend=backend)
        s.report(np.arange(9.0), np.resize(yaws, 9))
        h = s.history()
        assert np.all((h.yaw > -np.pi) & (h.yaw <= np.pi)), backend
        got[backend] = h.yaw
    np.testing.assert_array_equal(got["rust"], got["reference"])
    assert got["rust"][4] == 2.637242432414304 and got["rust"][8] == np.pi


def test_search_rejects_bad_reports():
    s = K.TranslationSearch(1.0, 0.5, fine_samples=3, stages=2)
    n = len(s.proposals())
    with pytest.raises(ValueError, match="costs"):
        s.report(np.zeros(n + 1), np.zeros(n))
    with pytest.raises(ValueError, match="yaws"):
        s.report(np.zeros(n), np.full(n, np.nan))
    s.report(np.zeros(n), np.zeros(n))
    s.report(np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="done"):
        s.report(np.zeros(0), np.zeros(0))


# --- bad inputs ------------------------------------------------------------------------------

_OK = np.zeros((2, 8, 4), dtype=np.float32)


@pytest.mark.parametrize("fn", [K.yaw_costs, K.estimate_yaw, K.rerank])
@pytest.mark.parametrize(
    ("src", "tgt", "name"),
    [
        (_OK, np.zeros((2, 7, 4)), "tgt"),  # T mismatch
        (_OK, np.zeros((2, 8, 5)), "tgt"),  # C mismatch
        (_OK, np.zeros((3, 8, 4)), "tgt"),  # P mismatch
        (np.zeros((2, 1, 4)), np.zeros((2, 1, 4)), "src"),  # T < 2
        (np.zeros((0, 8, 4)), np.zeros((2, 8, 4)), "tgt"),  # an empty batch, 2 targets
        (np.zeros((2, 8, 0)), np.zeros((2, 8, 0)), "src"),  # no channels
        (np.zeros((8, 4)), np.zeros((8, 4)), "src"),  # wrong rank
        (np.full((2, 8, 4), np.nan), _OK, "src"),
        (_OK, np.full((2, 8, 4), np.inf), "tgt"),
    ],
)
@pytest.mark.parametrize("backend", ["rust", "reference"])
def test_bad_pairs_raise_value_error(fn, src, tgt, name, backend):
    with pytest.raises(ValueError, match=name):
        fn(src, tgt, backend=backend)


@pytest.mark.parametrize("backend", ["rust", "reference"])
@pytest.mark.parametrize("tgt_shape", [(0, 8, 4), (1, 8, 4), (8, 4)])
def test_the_yaw_kernels_of_an_empty_batch_are_empty(backend, tgt_shape):
    # they refused it (matching_cost already gave an empty result): a caller whose filter left
    # no candidate had to special-case it
    src, tgt = np.zeros((0, 8, 4), np.float32), np.ones(tgt_shape, np.float32)
    assert K.yaw_costs(src, tgt, backend=backend).shape == (0, 8)
    est = K.estimate_yaw(src, tgt, backend=backend)
    assert all(v.shape == (0,) and v.dtype == np.float64 for v in est)
    r = K.rerank(src, tgt, backend=backend)
    assert r.order.shape == (0,) and r.order.dtype == np.int64
    assert all(v.shape == (0,) for v in (r.cost, r.yaw, r.shift))


def test_bad_types_and_backend():
    with pytest.raises(TypeError, match="src"):
        K.estimate_yaw("abc", _OK)
    with pytest.raises(ValueError, match="backend"):
        K.estimate_yaw(_OK, _OK, backend="cuda")  # type: ignore[arg-type]
    # the message lists each shape the target may take once (P = 1: the shared one is (P, T, C))
    with pytest.raises(ValueError, match=r"tgt: expected shape \(1, 8, 4\) or \(8, 4\) to match"):
        K.estimate_yaw(np.zeros((1, 8, 4)), np.zeros((1, 8, 3)))
    with pytest.raises(ValueError, match=r"expected shape \(3, 8, 4\) or \(1, 8, 4\) or \(8, 4\)"):
        K.estimate_yaw(np.zeros((3, 8, 4)), np.zeros((2, 8, 4)))
    with pytest.raises(ValueError, match="b"):
        K.matching_cost(np.zeros((3, 4)), np.zeros((3, 5)))
    with pytest.raises(ValueError, match="a"):
        K.matching_cost(np.zeros((0, 4)), np.zeros((0, 4)))


def test_core_rejects_bad_shapes_without_panicking():
    from vvloc import _core

    with pytest.raises(ValueError, match="tgt"):
        _core.estimate_yaw(_OK, np.zeros((2, 8, 3), dtype=np.float32))
    with pytest.raises(ValueError, match="src"):
        _core.yaw_costs(np.zeros((0, 1, 4), np.float32), np.zeros((0, 1, 4), np.float32))
    with pytest.raises(ValueError, match="tgt"):  # an empty batch against two targets
        _core.yaw_costs(np.zeros((0, 8, 4), np.float32), np.zeros((2, 8, 4), np.float32))


def test_wide_inputs_beyond_float32_and_bfloat16_tensors():
    x = np.random.default_rng(4).random((2, 8, 4))
    with pytest.raises(ValueError, match=r"^src: values beyond float32's range"):
        K.yaw_costs(x * 1e300, x)  # finite in float64, inf after the cast
    with pytest.raises(ValueError, match=r"^tgt: contains non-finite values"):
        K.yaw_costs(x, np.full_like(x, np.inf))
    bf = torch.from_numpy(x).to(torch.bfloat16)  # numpy has no bfloat16
    np.testing.assert_array_equal(K.yaw_costs(bf, x), K.yaw_costs(bf.float().numpy(), x))


@pytest.mark.parametrize("backend", ["rust", "reference"])
@pytest.mark.parametrize("t", [11, 12, 13, 26])
def test_a_half_turn_is_yaw_pi_exactly(t, backend):
    # 2π·(T/2)/T rounds above π for some T, and the wrap then gave −π + 4e-16
    src = np.random.default_rng(t).integers(-8, 8, (t, 4)).astype(np.float32) * 2
    tgt = ref.roll_rows(src, t / 2).astype(np.float32)  # exact in float32 (half-sums of ints)
    est = K.estimate_yaw(src[None], tgt[None], backend=backend)
    assert est.shift[0] == t / 2 and est.yaw[0] == np.pi


@pytest.mark.parametrize("scale", [1.0, 1e6])
def test_the_cost_of_a_near_perfect_match_is_the_curve_summed_literally(scale):
    # near a perfect match (1−w)a + wb − w(1−w)e cancels: the cost must still be c(s*)
    rng = np.random.default_rng(3)
    src = rng.standard_normal((16, 32))
    src /= np.linalg.norm(src, axis=1, keepdims=True)
    tgt = ref.roll_rows(src, 5.37) + 1e-6 * rng.standard_normal((16, 32))
    src, tgt = (scale * src).astype(np.float32), (scale * tgt).astype(np.float32)
    est = K.estimate_yaw(src[None], tgt[None])
    literal = ref.shift_cost(src, tgt, float(est.shift[0]))
    assert est.cost[0] == pytest.approx(literal, rel=1e-9)
    assert abs(est.shift[0] - 5.37) < 1e-3


@pytest.mark.parametrize("backend", ["rust", "reference"])
def test_matching_cost_names_a_non_finite_argument_on_both_backends(backend):
    # the Rust path leaves the finiteness test to the kernel's row check: same message
    a = np.ones((2, 8, 4), dtype=np.float32)
    b = a.copy()
    b[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match=r"^b: contains non-finite values"):
        K.matching_cost(a, b, backend=backend)
    with pytest.raises(ValueError, match=r"^a: contains non-finite values"):
        K.matching_cost(np.full_like(a, np.inf), a, backend=backend)


def _message(fn, *args, **kw) -> str:
    with pytest.raises(ValueError) as err:
        fn(*args, **kw)
    return str(err.value)


@pytest.mark.parametrize("fn", [K.yaw_costs, K.estimate_yaw, K.rerank])
@pytest.mark.parametrize(
    "case",
    ["nan_and_short_T", "nan_and_bad_tgt", "large_src_and_inf_tgt", "nan_src_and_large_src"],
)
def test_both_backends_name_the_same_fault_first(fn, case):
    # the Rust backend checks values in the kernel, after the gateway's shapes: the reference
    # backend checks in the same order (shapes; src non-finite, src too large; then tgt)
    ok = np.ones((2, 6, 5), dtype=np.float32)
    src, tgt = ok.copy(), ok.copy()
    if case == "nan_and_short_T":
        src = np.full((2, 1, 5), np.nan, dtype=np.float32)
    elif case == "nan_and_bad_tgt":
        src[0, 0, 0], tgt = np.nan, ok[:, :3]
    elif case == "large_src_and_inf_tgt":
        src[1, 2, :] = 3e18
        tgt[0, 0, 0] = np.inf
    else:
        src[1, 2, :] = 3e18
        src[0, 0, 0] = np.nan
    rust = _message(fn, src, tgt)
    assert rust == _message(fn, src, tgt, backend="reference")
    want = {
        "nan_and_short_T": "src: expected (P, T, C) with T >= "
        + ("2" if fn is K.yaw_costs else "3"),
        "nan_and_bad_tgt": "tgt: expected shape",
        "large_src_and_inf_tgt": "src: values too large",
        "nan_src_and_large_src": "src: contains non-finite",
    }[case]
    assert rust.startswith(want)


def test_matching_cost_names_the_same_fault_first_on_both_backends():
    a = np.ones((2, 6, 5), dtype=np.float32)
    big, inf = a.copy(), a.copy()
    big[0, 1, :] = 3e18
    inf[1, 0, 0] = np.inf
    for x, y, want in [(big, inf, "a: values too large"), (inf, a[:, :3], "b: expected shape")]:
        rust = _message(K.matching_cost, x, y)
        assert rust == _message(K.matching_cost, x, y, backend="reference")
        assert rust.startswith(want)


@pytest.mark.parametrize("t", [3, 16, 17, 120])
def test_constant_descriptors_take_the_exact_path_everywhere(t):
    # every Gram entry of equal rows cancels: each is recomputed directly (in place, row by row)
    src = np.full((2, t, 8), 0.25, dtype=np.float32)
    src[1] = 0.0
    est = K.estimate_yaw(src, src)
    np.testing.assert_array_equal(est.cost, [0.0, 0.0])
    np.testing.assert_array_equal(K.yaw_costs(src, src), np.zeros((2, t)))


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="counts threads in /proc")
def test_single_pair_calls_start_no_thread_pool():
    # one pair runs sequentially, on the calling thread: neither vvloc's pool nor rayon's
    # global one may be started for it (asking rayon for its thread count would start the latter)
    code = (
        "import os, numpy as np\n"
        "from vvloc import kernels as K\n"
        "n = lambda: len(os.listdir('/proc/self/task'))\n"
        "a = np.random.default_rng(0).random((1, 8, 4), dtype=np.float32)\n"
        "before = n()\n"
        "K.estimate_yaw(a, a); K.yaw_costs(a, a); K.rerank(a, a[0]); K.matching_cost(a, a)\n"
        "K.roll_interp(a[0], 0.5)\n"
        "print(before, n())\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.split()
    assert out[0] == out[1], out


# --- out of memory ---------------------------------------------------------------------------


def test_pair_kernels_out_of_memory_is_a_memory_error_not_an_abort():
    # under an address-space limit, the result buffers of the pair kernels (and the arrays the
    # bindings made of them) were infallible Rust allocations: the process aborted
    lines = run_limited("""
import numpy as np
from vvloc import kernels as K
src = np.ones((10_000_000, 3, 1), np.float32)  # 120 MB, allocated before the limit
K.estimate_yaw(src[:8], src[0]); K.matching_cost(src[:8], src[:8])  # the pool's threads
limit(150)
attempt("yaw_costs", lambda: K.yaw_costs(src, src[0]))  # (P, T) f64: 240 MB
attempt("estimate_yaw", lambda: K.estimate_yaw(src, src[0]))  # P estimates: 240 MB
limit(None)
limit(60)
attempt("matching_cost", lambda: K.matching_cost(src, src))  # 80 MB
attempt("rerank", lambda: K.rerank(src, src[0]))
limit(None)
limit(150)  # 4e6 estimates fit (96 MB), their three columns of 32 MB do not
attempt("columns", lambda: K.estimate_yaw(src[:4_000_000], src[0]))
""")
    assert [" ".join(x.split()[:3]) for x in lines] == [
        "yaw_costs MemoryError src:",
        "estimate_yaw MemoryError src:",
        "matching_cost MemoryError a:",
        "rerank MemoryError src:",
        "columns MemoryError src:",
    ], lines
    assert "4000000 elements of 8 bytes" in lines[-1], lines[-1]


def test_search_out_of_memory_is_a_memory_error_on_both_backends():
    # a coarse grid within MAX_STAGE_POINTS (1e8 points, 1.6 GB) that the machine cannot hold
    # aborted the process (the reference raised MemoryError); a fine stage that does not fit
    # is refused by its report, which leaves the search as it was
    lines = run_limited("""
import numpy as np
from vvloc import kernels as K
limit(512)
for backend in ("rust", "reference"):
    attempt(backend, lambda: K.TranslationSearch(1.0, 1.0 / 4999.5, fine_samples=1, stages=1,
                                                 backend=backend))  # a 9999 x 9999 grid
s = K.TranslationSearch(0.5, 0.5, fine_samples=K.MAX_STAGE_POINTS, stages=2)
attempt("report", lambda: s.report(np.zeros(9), np.zeros(9)))
print(s.stage, len(s.history().cost), s.proposals().shape, s.best())
""")
    assert [" ".join(x.split()[:3]) for x in lines[:3]] == [
        "rust MemoryError step:",
        "reference MemoryError step:",
        "report MemoryError fine_samples:",
    ], lines
    assert lines[3] == "0 0 (9, 2) None", lines
