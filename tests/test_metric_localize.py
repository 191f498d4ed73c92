"""Geometry oracle of metric localization: a smooth world feature field sampled into BEVs at two
known world poses; ``metric_localize`` with ``RadialMeanDecoder`` must recover ξ_{s→t}
(DESIGN.md §3: target origin in source coordinates, yaw_t − yaw_s). This pins the frame, BEV,
polar-angle, padding, roll and yaw sign conventions end to end."""

from __future__ import annotations

import numpy as np
import pytest

from vvloc import kernels as K
from vvloc.localize.metric import RadialMeanDecoder, SearchConfig, metric_localize

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
