"""Geometry oracle of metric localization: a smooth world feature field sampled into BEVs at two
known world poses; ``metric_localize`` with ``RadialMeanDecoder`` must recover ξ_{s→t}
(DESIGN.md §3: target origin in source coordinates, yaw_t − yaw_s). This pins the frame, BEV,
polar-angle, padding, roll and yaw sign conventions end to end."""

from __future__ import annotations

import numpy as np
import pytest

from vvloc import kernels as K
from vvloc.localize.metric import (
    RadialMeanDecoder,
    SearchConfig,
    metric_localize,
    metric_localize_best,
    metric_localize_each,
)

H = W = 100
G = 0.3
T, R, C = 120, 25, 8


def world_field(seed: int):
    """Random Fourier features: C channels, 6 plane waves each, wavelengths 3–10 m."""
    rng = np.random.default_rng(seed)
    f = 6
    freq = rng.standard_normal((C, f, 2)) * (2 * np.pi / rng.uniform(3, 10, (C, f, 1))) / np.sqrt(2)
    phase = rng.uniform(0, 2 * np.pi, (C, f))
    amp = rng.standard_normal((C, f)) / np.sqrt(f)

    def field(p: np.ndarray) -> np.ndarray:  # world points (..., 2) -> (..., C)
        return (amp * np.cos(np.einsum("...d,cfd->...cf", p, freq) + phase)).sum(-1)

    return field


def bev_at(field, pose) -> np.ndarray:
    """BEV (H, W, C) of a vehicle at world pose (x, y, yaw): row i ↔ ego x, column j ↔ ego y."""
    x0, y0, yaw = pose
    xs = (np.arange(H) - (H - 1) / 2) * G
    ys = (np.arange(W) - (W - 1) / 2) * G
    xx, yy = np.meshgrid(xs, ys, indexing="ij")
    c, s = np.cos(yaw), np.sin(yaw)
    world = np.stack([x0 + c * xx - s * yy, y0 + s * xx + c * yy], axis=-1)
    return field(world).astype(np.float32)


def compose(a, b):
    """T_world_a · b for 3-DoF poses."""
    c, s = np.cos(a[2]), np.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2])


def case(seed: int):
    rng = np.random.default_rng(1000 + seed)
    src_pose = (rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(-np.pi, np.pi))
    xi = (rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-np.pi, np.pi))
    field = world_field(seed)
    bev_s = bev_at(field, src_pose)
    bev_t = bev_at(field, compose(src_pose, xi))
    decode = RadialMeanDecoder()
    desc_t = decode(K.polar_sample(bev_t, T, R, G))
    return xi, bev_s, desc_t, decode


def wrap(a: float) -> float:
    return float(np.angle(np.exp(1j * a)))


@pytest.mark.parametrize("seed", range(8))
def test_metric_localize_recovers_the_relative_pose(seed):
    xi, bev_s, desc_t, decode = case(seed)
    cfg = SearchConfig(half_range=3.6, step=0.6, fine_samples=32, stages=5, shrink=0.5, seed=seed)
    res = metric_localize(bev_s, desc_t, decode, cfg, G, T, R)
    x, y, yaw = res.pose
    assert abs(np.degrees(wrap(yaw - xi[2]))) < 1.0, (res.pose, xi)
    assert np.hypot(x - xi[0], y - xi[1]) < 0.15, (res.pose, xi)
    assert res.cost == pytest.approx(res.history.cost.min())
    assert set(np.unique(res.history.stage)) == set(range(5))


@pytest.mark.parametrize("seed", range(4))
def test_cost_at_the_true_pose_beats_poses_one_metre_away(seed):
    xi, bev_s, desc_t, decode = case(seed)
    ang = np.arange(8) * np.pi / 4
    xy = np.concatenate([[xi[:2]], np.asarray(xi[:2]) + np.stack([np.cos(ang), np.sin(ang)], 1)])
    est = K.estimate_yaw(decode(K.pad_polar(bev_s, xy, T, R, G)), desc_t)
    assert np.all(est.cost[0] < est.cost[1:]), est.cost


def test_radial_mean_decoder_shapes_and_normalisation():
    rng = np.random.default_rng(0)
    polar = rng.standard_normal((3, 12, 5, 4)).astype(np.float32)
    d = RadialMeanDecoder()(polar)
    assert d.shape == (3, 12, 4) and d.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, rtol=1e-6)
    want = polar.mean(axis=2)
    np.testing.assert_allclose(d, want / np.linalg.norm(want, axis=-1, keepdims=True), rtol=1e-5)
    assert np.all(RadialMeanDecoder()(np.zeros((2, 3, 4))) == 0)
    with pytest.raises(ValueError, match="polar"):
        RadialMeanDecoder()(np.zeros((3, 4)))


def test_metric_localize_rejects_mismatched_target():
    with pytest.raises(ValueError, match="desc_tgt"):
        metric_localize(
            np.zeros((10, 10, 4)), np.zeros((7, 4)), RadialMeanDecoder(), None, 0.3, 8, 3
        )


def test_metric_localize_takes_the_models_grid_not_a_default():
    # the defaults (0.3 m, 120 x 25) matched no model: a 0.5 m BEV searched with 0.3 m cells
    # answered a translation 0.6 x the true one at as low a cost
    bev, tgt, tgts = np.zeros((10, 10, 4)), np.zeros((8, 4)), np.zeros((2, 8, 4))
    for call in (
        lambda: metric_localize(bev, tgt, RadialMeanDecoder(), None),  # type: ignore[call-arg]
        lambda: metric_localize_best(bev, tgts, RadialMeanDecoder(), None, None),  # type: ignore[call-arg]
        lambda: metric_localize_each(bev, tgts, RadialMeanDecoder(), None, None, 0.3),  # type: ignore[call-arg]
    ):
        with pytest.raises(TypeError, match=r"missing \d required positional argument"):
            call()


def _targets(seed: int, n: int):
    """A source BEV and n targets around it (offsets within ±2.5 m, any yaw)."""
    rng = np.random.default_rng(2000 + seed)
    field = world_field(seed)
    src_pose = (rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(-np.pi, np.pi))
    xis = [(*rng.uniform(-2.5, 2.5, 2), rng.uniform(-np.pi, np.pi)) for _ in range(n)]
    decode = RadialMeanDecoder()
    tgts = np.stack(
        [decode(K.polar_sample(bev_at(field, compose(src_pose, xi)), T, R, G)) for xi in xis]
    )
    return bev_at(field, src_pose), tgts, xis, decode


def test_metric_localize_best_of_one_equals_metric_localize():
    bev_s, tgts, _, decode = _targets(0, 1)
    cfg = SearchConfig(stages=3, seed=3)
    one = metric_localize(bev_s, tgts[0], decode, cfg, G, T, R)
    best = metric_localize_best(bev_s, tgts, decode, None, cfg, G, T, R)
    assert best.index == 0
    assert best.result.pose == one.pose and best.result.cost == one.cost
    for a, b in zip(best.result.history, one.history, strict=True):
        np.testing.assert_array_equal(a, b)
    assert best.coarse_cost[0] == one.history.cost[one.history.stage == 0].min()
    # a config that is not one, and a bias that is not numbers, are named
    with pytest.raises(TypeError, match="config: expected a SearchConfig or None, got str"):
        metric_localize(bev_s, tgts[0], decode, "x", G, T, R)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="config: expected a SearchConfig"):
        metric_localize_best(bev_s, tgts, decode, None, {}, G, T, R)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"bias: expected \(1,\) real numbers"):
        metric_localize_best(bev_s, tgts, decode, None, cfg, G, T, R, bias=["a"])
    # numbers as text were parsed, bools read as 1 and 0
    for bad, dtype in ((["1"], "<U1"), ([True], "bool"), ([1j], "complex128")):
        with pytest.raises(
            TypeError, match=rf"bias: expected \(1,\) real numbers, got dtype {dtype}"
        ):
            metric_localize_best(bev_s, tgts, decode, None, cfg, G, T, R, bias=bad)


@pytest.mark.parametrize("seed", range(3))
def test_metric_localize_best_refines_the_target_of_lowest_coarse_cost(seed):
    bev_s, tgts, xis, decode = _targets(seed, 4)
    # a fifth target from another place of another world: it must lose
    other = decode(K.polar_sample(bev_at(world_field(seed + 50), (3.0, -4.0, 1.0)), T, R, G))
    tgts = np.concatenate([tgts, other[None]])
    cfg = SearchConfig(stages=4, seed=seed)
    singles = [metric_localize(bev_s, t, decode, cfg, G, T, R) for t in tgts]
    coarse = [r.history.cost[r.history.stage == 0].min() for r in singles]
    best = metric_localize_best(bev_s, tgts, decode, None, cfg, G, T, R)
    np.testing.assert_array_equal(best.coarse_cost, coarse)
    assert best.index == int(np.argmin(coarse)) != 4
    want = singles[best.index]
    assert best.result.pose == want.pose and best.result.cost == want.cost
    x, y, yaw = best.result.pose
    xi = xis[best.index]
    assert np.hypot(x - xi[0], y - xi[1]) < 0.2 and abs(np.degrees(wrap(yaw - xi[2]))) < 1.5


@pytest.mark.parametrize("seed", range(2))
def test_metric_localize_best_chooses_by_coarse_cost_plus_bias(seed):
    bev_s, tgts, _, decode = _targets(seed, 4)
    cfg = SearchConfig(stages=2, seed=seed)
    plain = metric_localize_best(bev_s, tgts, decode, None, cfg, G, T, R)
    np.testing.assert_array_equal(plain.score, plain.coarse_cost)  # no bias: the cost alone
    # a bias that makes another target the cheapest: it is the one refined
    want = (plain.index + 1) % len(tgts)
    bias = np.full(len(tgts), 10.0)
    bias[want] = 0.0
    best = metric_localize_best(bev_s, tgts, decode, None, cfg, G, T, R, bias=bias)
    np.testing.assert_array_equal(best.coarse_cost, plain.coarse_cost)
    np.testing.assert_array_equal(best.score, plain.coarse_cost + bias)
    assert best.index == want
    single = metric_localize(bev_s, tgts[want], decode, cfg, G, T, R)
    assert best.result.pose == single.pose and best.result.cost == single.cost
    # a constant bias changes nothing
    same = metric_localize_best(bev_s, tgts, decode, None, cfg, G, T, R, bias=np.full(4, 0.3))
    assert same.index == plain.index and same.result.pose == plain.result.pose
    for bad in (np.zeros(3), np.array([0.0, np.nan, 0.0, 0.0]), np.full(4, np.inf)):
        with pytest.raises(ValueError, match="bias"):
            metric_localize_best(bev_s, tgts, decode, None, cfg, G, T, R, bias=bad)


def test_metric_localize_best_calls_the_interactor_per_target():
    bev_s, tgts, _, decode = _targets(1, 3)
    seen: list[int] = []

    def interact(ds, k):
        seen.append(k)
        return ds, np.broadcast_to(tgts[k], ds.shape)

    decoded: list[int] = []

    def counting(polar):
        decoded.append(len(polar))
        return decode(polar)

    cfg = SearchConfig(stages=2, seed=0)
    plain = metric_localize_best(bev_s, tgts, decode, None, cfg, G, T, R)
    inter = metric_localize_best(bev_s, tgts, counting, interact, cfg, G, T, R)
    assert inter.index == plain.index and inter.result.pose == plain.result.pose
    # the coarse stage once per target, then one fine stage for the chosen one
    assert seen == [0, 1, 2, plain.index]
    # the source is decoded once per stage, whatever the number of targets
    assert decoded == [121, cfg.fine_samples]
    with pytest.raises(TypeError, match="decode"):
        metric_localize_best(bev_s, tgts, lambda p: (decode(p), decode(p)), None, cfg, G, T, R)
    for bad, err in (("36", TypeError), (2, ValueError)):  # "36" != 36 said desc_tgt was wrong
        with pytest.raises(err, match=r"^num_angles: expected an int"):
            metric_localize_best(bev_s, tgts, decode, None, cfg, G, bad, R)
        with pytest.raises(err, match=r"^num_angles: expected an int"):
            metric_localize(bev_s, tgts[0], decode, cfg, G, bad, R)
    # an interactor that returns one array, not the pair: it was matched against the target
    with pytest.raises(TypeError, match=r"interact: expected the pair \(Ds', Dt'\) .* ndarray"):
        metric_localize_best(bev_s, tgts, decode, lambda ds, k: ds, cfg, G, T, R)


def test_metric_localize_best_refuses_a_non_finite_cost(monkeypatch):
    bev_s, tgts, _, decode = _targets(2, 3)
    real = K.estimate_yaw

    def nan_costs(src, tgt, **kw):
        est = real(src, tgt, **kw)
        return est._replace(cost=np.full_like(est.cost, np.nan))

    monkeypatch.setattr(K, "estimate_yaw", nan_costs)
    with pytest.raises(ValueError, match="costs: contains non-finite"):
        metric_localize_best(bev_s, tgts, decode, None, SearchConfig(stages=2), G, T, R)


@pytest.mark.parametrize("seed", [0, 1])
def test_metric_localize_each_equals_one_search_per_target(seed):
    """The targets share the coarse stage's padding and decoding; each result must be the one
    search of its target alone, history included, and (with a plain match) the true pose."""
    bev_s, tgts, xis, decode = _targets(seed, 3)
    cfg = SearchConfig(stages=3, seed=5)
    calls = []

    def counting(polar):
        calls.append(len(polar))
        return decode(polar)

    each = metric_localize_each(bev_s, tgts, counting, None, cfg, G, T, R)
    # one coarse grid for all three targets, then each target's two fine stages
    assert calls == [121] + [cfg.fine_samples] * 2 * 3
    for res, tgt, xi in zip(each, tgts, xis, strict=True):
        one = metric_localize(bev_s, tgt, decode, cfg, G, T, R)
        assert res.pose == one.pose and res.cost == one.cost
        for a, b in zip(res.history, one.history, strict=True):
            np.testing.assert_array_equal(a, b)
        assert np.hypot(res.pose[0] - xi[0], res.pose[1] - xi[1]) < 0.3
        assert abs(wrap(res.pose[2] - xi[2])) < np.deg2rad(3)
    with pytest.raises(ValueError, match="desc_tgts"):
        metric_localize_each(bev_s, tgts[:, :7], decode, None, cfg, G, T, R)


def test_a_decoder_whose_output_does_not_fit_is_named():
    _xi, bev_s, desc_t, decode = case(0)
    cfg = SearchConfig(half_range=1.2, step=0.6, fine_samples=4, stages=1, shrink=0.5, seed=0)
    # channels other than the target's: the kernel's 'tgt: expected shape ...' named neither
    with pytest.raises(ValueError, match=rf"^decode: returned shape \(\d+, {T}, 4\); expected"):
        metric_localize(bev_s, desc_t, lambda p: decode(p)[..., :4], cfg, G, T, R)
    # one descriptor set short: the search's 'costs: expected shape (N,)'
    with pytest.raises(ValueError, match=r"^decode: returned \d+ descriptor sets for \d+ hypo"):
        metric_localize(bev_s, desc_t, lambda p: decode(p)[1:], cfg, G, T, R)
    with pytest.raises(ValueError, match=r"^decode/interact: expected a pair"):
        metric_localize(bev_s, desc_t, lambda p: (decode(p), decode(p)[:, :2]), cfg, G, T, R)


def test_a_decoder_that_is_none_or_returns_nan_is_named():
    _xi, bev_s, desc_t, decode = case(0)
    cfg = SearchConfig(half_range=1.2, step=0.6, fine_samples=4, stages=1, shrink=0.5, seed=0)
    tgts = desc_t[None]
    # "'NoneType' object is not callable" at the first stage named nothing
    with pytest.raises(TypeError, match=r"^decode: expected a callable mapping polar BEVs"):
        metric_localize(bev_s, desc_t, None, cfg, G, T, R)  # type: ignore[arg-type]
    for call in (metric_localize_best, metric_localize_each):
        with pytest.raises(TypeError, match=r"^decode: expected a callable .*got int"):
            call(bev_s, tgts, 3, None, cfg, G, T, R)  # type: ignore[arg-type]
        with pytest.raises(TypeError, match=r"^interact: expected a callable or None, got str"):
            call(bev_s, tgts, decode, "x", cfg, G, T, R)  # type: ignore[arg-type]

    # the kernel named its own argument: "src: contains non-finite values"
    def nan(p):
        return np.full_like(decode(p), np.nan)

    with pytest.raises(ValueError, match=r"^decode: returned source descriptors that the yaw "
                       r"estimation refuses: contains non-finite values"):  # fmt: skip
        metric_localize(bev_s, desc_t, nan, cfg, G, T, R)
    with pytest.raises(ValueError, match=r"^decode/interact: returned target descriptors .*"
                       r"refuses: values too large"):  # fmt: skip
        metric_localize(bev_s, desc_t, lambda p: (decode(p), decode(p) * 1e30), cfg, G, T, R)
    # a target too large to match is the caller's, named before any stage
    with pytest.raises(ValueError, match=r"^desc_tgt: values too large"):
        metric_localize(bev_s, desc_t * 1e30, decode, cfg, G, T, R)
    with pytest.raises(ValueError, match=r"^desc_tgts: values too large"):
        metric_localize_each(bev_s, tgts * 1e30, decode, None, cfg, G, T, R)
