"""The BEV car probe (vvloc.sim.bev_probe): its geometry against BEVs painted from the world, the
probe's figures on hand-made data, and a run on a rendered garage."""

from __future__ import annotations

import numpy as np
import pytest

from vvloc.sim import bev_probe, floor_cues
from vvloc.sim.simulate import build_world


def _painted_bevs(world, states, kf, h=40, g=0.6):
    """BEVs whose channel 0 is 1 within 1.2 m of an occupied bay of the keyframe's floor and
    session, built cell by cell from ego to world (the inverse of what the probe does)."""
    per_floor = len(world.bays) // len(world.floor_z)
    centres = np.array([(b.x, b.y) for b in world.bays[:per_floor]])
    c = (np.arange(h) - (h - 1) / 2) * g
    ex, ey = np.meshgrid(c, c, indexing="ij")  # row i ↔ ego x, column j ↔ ego y
    rng = np.random.default_rng(1)
    bevs = rng.normal(size=(len(kf["z"]), h, h, 2)).astype(np.float32)
    for r, (px, py, yaw) in enumerate(kf["pose"]):
        wx = px + np.cos(yaw) * ex - np.sin(yaw) * ey
        wy = py + np.sin(yaw) * ex + np.cos(yaw) * ey
        first = kf["floor"][r] * per_floor
        occ = states[kf["session"][r], first : first + per_floor]
        d = np.hypot(wx[..., None] - centres[:, 0], wy[..., None] - centres[:, 1])
        bevs[r, ..., 0] = ((d <= 1.2) & (occ != -1)).any(axis=-1)
    return bevs


def _keyframes(world, n=120, seed=0):
    rng = np.random.default_rng(seed)
    per_floor = len(world.bays) // len(world.floor_z)
    near = rng.integers(0, per_floor, n)
    xy = np.array([(world.bays[k].x, world.bays[k].y) for k in near]) + rng.uniform(-4, 4, (n, 2))
    pose = np.concatenate([xy, rng.uniform(-np.pi, np.pi, (n, 1))], axis=1)
    return {
        "pose": pose,
        "z": np.zeros(n),
        "floor": rng.integers(0, 2, n),
        "session": np.repeat([0, 1], n // 2),
        "seq": np.arange(n),
    }


def test_probe_reads_cars_painted_where_the_conventions_put_them():
    world = build_world("garage", 0, 2, "walls")
    specs = [{"change_fraction": 0.15, "seed": 3}, {"change_fraction": 0.15, "seed": 4}]
    states = floor_cues.bay_states(world, specs)
    kf = _keyframes(world)
    bevs = _painted_bevs(world, states, kf)
    x, y, s = bev_probe.bay_features(bevs, kf, world, states, 0.6)
    assert len(x) > 200 and 0.2 < y.mean() < 0.9
    assert np.array_equal(x[:, 0] > 0.5, y)  # the painted car is under every bay sampled
    fit = bev_probe.fit_probe(x[s == 0], y[s == 0], x[s == 1], y[s == 1])
    assert fit["accuracy"] == 1.0 and fit["balanced_accuracy"] == 1.0
    xm, ym, sm = bev_probe.bay_features(bevs, kf, world, states, 0.6, mirror=True)
    control = bev_probe.fit_probe(xm[sm == 0], ym[sm == 0], xm[sm == 1], ym[sm == 1])
    assert control["balanced_accuracy"] < 0.8  # away from the bay the car is not read
    with pytest.raises(ValueError, match="bevs"):
        bev_probe.bay_features(bevs[:-1], kf, world, states, 0.6)


def test_fit_probe_figures_on_hand_made_data():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2000, 4))
    y = x[:, 1] > 0.3
    fit = bev_probe.fit_probe(x[:1000], y[:1000], x[1000:], y[1000:])
    assert fit["accuracy"] > 0.98 and fit["balanced_accuracy"] > 0.98
    assert fit["majority"] == pytest.approx(np.mean(~y[1000:]))  # the majority answer: empty
    noise = rng.random(2000) < 0.7  # labels unrelated to the features
    fit = bev_probe.fit_probe(x[:1000], noise[:1000], x[1000:], noise[1000:])
    assert abs(fit["balanced_accuracy"] - 0.5) < 0.05
    assert fit["majority"] == pytest.approx(np.mean(noise[1000:]))
    again = bev_probe.fit_probe(x[:1000], noise[:1000], x[1000:], noise[1000:])
    assert again == fit  # deterministic
    one_class = bev_probe.fit_probe(x[:1000], y[:1000], x[1000:][y[1000:]], y[1000:][y[1000:]])
    assert one_class["accuracy"] > 0.98 and np.isnan(one_class["balanced_accuracy"])
    with pytest.raises(ValueError, match="both classes"):
        bev_probe.fit_probe(x[:10], np.ones(10, bool), x[10:20], y[10:20])
    with pytest.raises(ValueError, match="at least one"):
        bev_probe.fit_probe(x[:0], y[:0], x[:5], y[:5])


def test_probe_of_a_model_on_a_rendered_garage(egl, tmp_path):
    from nets_helpers import tiny_config
    from vvloc.nets import VVLocNet
    from vvloc.sim import simulate_dataset

    out = tmp_path / "garage"
    simulate_dataset(
        out, scene="garage", sessions=2, frames=40, width=48, height=32, progress=False
    )
    ckpt = tmp_path / "model"
    VVLocNet(tiny_config(bev_height=40, bev_width=40, grid_size=0.6)).save(ckpt)
    r = bev_probe.probe(str(ckpt), str(out), ["s0"], ["s1"])
    for name in ("aligned", "control"):
        o = r[name]
        assert o["train_samples"] > 0 and o["test_samples"] > 0
        assert all(0.0 <= o[k] <= 1.0 for k in ("accuracy", "majority", "balanced_accuracy"))
    assert "| at the bay |" in bev_probe.markdown(r)
    with pytest.raises(ValueError, match="disjoint"):
        bev_probe.probe(str(ckpt), str(out), ["s0"], ["s0"])
    with pytest.raises(KeyError, match="s7"):
        bev_probe.probe(str(ckpt), str(out), ["s0"], ["s7"])
    with pytest.raises(ValueError, match="near"):
        bev_probe.probe(str(ckpt), str(out), ["s0"], ["s1"], near=0.0)
    park = tmp_path / "park"
    simulate_dataset(park, sessions=2, frames=4, width=16, height=16, progress=False)
    with pytest.raises(ValueError, match="garage"):
        bev_probe.probe(str(ckpt), str(park), ["s0"], ["s1"])
