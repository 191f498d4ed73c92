"""VVLoc networks: shapes, geometry of the projection, camera locality, polar/padding parity,
heads' and decoder/interactor's behaviour under circular angle shifts, gradients, checkpoints."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import stat
import sys

import numpy as np
import pytest
import torch

from nets_helpers import make_rig, random_images, tiny_config
from vvloc import kernels
from vvloc.nets import (
    DiscoHead,
    GeMHead,
    ModelConfig,
    NetVLADHead,
    VVLocNet,
    bev_pad,
    polar_sample,
    project_points,
    roll_interp,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _model(cfg: ModelConfig, seed: int = 0) -> VVLocNet:
    torch.manual_seed(seed)
    return VVLocNet(cfg).eval()


def _encode(model: VVLocNet, batch: int, cameras: int, seed: int = 0):
    cfg = model.config
    intr, ext = make_rig(batch, cameras, cfg.image_height, cfg.image_width)
    imgs = random_images(batch, cameras, cfg.image_height, cfg.image_width, seed)
    return model.encode(imgs, intr, ext)


def _check_shapes(out, cfg: ModelConfig, batch: int, dg: int) -> None:
    assert out.bev.shape == (batch, cfg.bev_height, cfg.bev_width, cfg.channels)
    assert out.polar.shape == (batch, cfg.num_angles, cfg.num_radii, cfg.channels)
    assert out.global_desc.shape == (batch, dg)
    assert out.local_desc.shape == (batch, cfg.num_angles, cfg.channels)
    for t in (out.bev, out.polar, out.global_desc, out.local_desc):
        assert t.dtype == torch.float32 and torch.isfinite(t).all()
    np.testing.assert_allclose(out.global_desc.norm(dim=-1).detach().numpy(), 1.0, atol=1e-5)


# --- config -------------------------------------------------------------------------------


def test_config_presets_and_json_roundtrip():
    paper = ModelConfig.paper()
    assert (paper.image_height, paper.image_width) == (256, 448)
    assert (paper.bev_height, paper.bev_width, paper.channels) == (100, 100, 256)
    assert (paper.grid_size, paper.num_angles, paper.num_radii) == (0.3, 120, 40)
    assert (paper.sigma_r, paper.sigma_a) == (4.8, 15.0)
    for cfg in (paper, ModelConfig.small(), tiny_config(global_head="disco")):
        back = ModelConfig.from_json(cfg.to_json())
        assert back == cfg
        assert back.config_hash() == cfg.config_hash()
    assert paper.config_hash() != ModelConfig.small().config_hash()
    with pytest.raises(ValueError, match=r"^text: not the JSON of a ModelConfig"):
        ModelConfig.from_json("{")
    with pytest.raises(
        TypeError, match=r"^text: expected the JSON text of a ModelConfig, got dict"
    ):
        ModelConfig.from_json({})  # type: ignore[arg-type]
    assert len(paper.config_hash()) == 16
    # equal configs hash the same, however their numbers were written (a YAML override of
    # sigma_a: 15 against a checkpoint's 15.0 read as another model before)
    small = ModelConfig.small()
    for a, b in (
        ({"sigma_a": 15}, {"sigma_a": 15.0}),
        ({"grid_size": 1}, {"grid_size": 1.0}),
        ({"pillar_heights": (-0.0, 1)}, {"pillar_heights": [0.0, 1.0]}),
    ):
        x, y = dataclasses.replace(small, **a), dataclasses.replace(small, **b)
        assert x == y and x.config_hash() == y.config_hash()


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="global_head"):
        tiny_config(global_head="max")
    with pytest.raises(ValueError, match="encoder_heads"):
        tiny_config(encoder_heads=3)
    with pytest.raises(ValueError, match="unknown fields"):
        ModelConfig.from_dict({"channels": 8, "colour": 1})
    # a model_overrides typo: the field it was meant to be, and the known ones
    with pytest.raises(
        ValueError, match=r"\['chanels'\] \(did you mean 'chanels' → 'channels'\?\); known: \["
    ):
        ModelConfig.from_dict({"chanels": 8})
    with pytest.raises(ValueError, match="disco_crop"):
        tiny_config(disco_crop=(20, 2))
    for name, bad in (("grid_size", math.inf), ("gem_p", math.inf), ("sigma_a", math.nan)):
        with pytest.raises(ValueError, match=f"ModelConfig.{name}: expected a finite number"):
            tiny_config(**{name: bad})
    for name, bad in (("grid_size", "0.6"), ("sigma_r", True), ("dropout", None)):
        with pytest.raises(TypeError, match=f"ModelConfig.{name}: expected a number"):
            tiny_config(**{name: bad})
    # no string split into digits, no float truncated, no list cut short: the field is named
    for name, bad in (
        ("backbone_widths", "8888"),
        ("backbone_widths", [8.9, 8, 8, 8]),
        ("backbone_blocks", None),
        ("pillar_heights", ["a"]),
        ("pillar_heights", [True, False]),
        ("disco_crop", 4),
        ("bev_self_attention", "false"),
        ("global_head", None),
    ):
        with pytest.raises(TypeError, match=f"ModelConfig.{name}: expected"):
            tiny_config(**{name: bad})
    for bad in ([4, 4, 9], [4]):
        with pytest.raises(ValueError, match=r"ModelConfig.disco_crop: expected \(T, R\)"):
            tiny_config(disco_crop=bad)
    with pytest.raises(ValueError, match="pillar_heights: expected finite"):
        tiny_config(pillar_heights=(0.0, math.inf))
    with pytest.raises(ValueError, match="backbone_widths"):
        tiny_config(backbone_widths=(8, 0, 8, 8))
    # a stage of 0 blocks built the network of 1 under another config hash
    with pytest.raises(ValueError, match=r"backbone_blocks: expected widths >= 1 and blocks >= 1"):
        tiny_config(backbone_blocks=(0, 1, 1, 1))
    # a GeM exponent past float32's reach gave NaN global descriptors
    with pytest.raises(ValueError, match=r"ModelConfig\.gem_p: expected at most 16"):
        tiny_config(global_head="gem", gem_p=1000.0)
    assert tiny_config(global_head="gem", gem_p=16.0).gem_p == 16.0
    # a yaw needs 3 angle bins (with 2 its sign is undetermined): refused before training
    for t in (1, 2):
        with pytest.raises(ValueError, match=r"ModelConfig\.num_angles: expected >= 3 angle"):
            tiny_config(num_angles=t, disco_crop=(1, 1))
    assert tiny_config(num_angles=3, disco_crop=(1, 1)).num_angles == 3


# --- shapes -------------------------------------------------------------------------------


@pytest.mark.parametrize("cameras", [1, 4, 6])
def test_encode_shapes_odd_rigs(cameras):
    cfg = tiny_config()
    model = _model(cfg)
    with torch.no_grad():
        out = _encode(model, 2, cameras)
    _check_shapes(out, cfg, 2, cfg.channels)


@pytest.mark.parametrize(("head", "dg"), [("gem", 16), ("netvlad", 8), ("disco", 16)])
def test_global_head_dims(head, dg):
    cfg = tiny_config(global_head=head)
    model = _model(cfg)
    with torch.no_grad():
        out = _encode(model, 1, 2)
    _check_shapes(out, cfg, 1, dg)
    assert model.global_dim == dg


def test_netvlad_without_projection_has_k_times_c_dims():
    cfg = tiny_config(global_head="netvlad", global_dim=0)
    assert _model(cfg).global_dim == cfg.netvlad_clusters * cfg.channels


def test_small_config_shapes():
    cfg = ModelConfig.small()
    model = _model(cfg)
    with torch.no_grad():
        out = _encode(model, 1, 4)
    _check_shapes(out, cfg, 1, model.global_dim)


def test_paper_config_forward_once():
    cfg = ModelConfig.paper()
    model = _model(cfg)
    with torch.no_grad():
        out = _encode(model, 1, 1)
    _check_shapes(out, cfg, 1, model.global_dim)


def test_uint8_and_float_images_agree():
    cfg = tiny_config()
    model = _model(cfg)
    intr, ext = make_rig(1, 2, cfg.image_height, cfg.image_width)
    imgs = random_images(1, 2, cfg.image_height, cfg.image_width)
    with torch.no_grad():
        a = model.encode(imgs, intr, ext).bev
        b = model.encode(imgs.float() / 255.0, intr, ext).bev
    torch.testing.assert_close(a, b)


def test_encode_rejects_bad_inputs():
    cfg = tiny_config()
    model = _model(cfg)
    intr, ext = make_rig(1, 2, cfg.image_height, cfg.image_width)
    imgs = random_images(1, 2, cfg.image_height, cfg.image_width)
    with pytest.raises(ValueError, match="images"):
        model.encode(imgs[0], intr, ext)
    with pytest.raises(ValueError, match="intrinsics"):
        model.encode(imgs, intr[:, :1], ext)
    with pytest.raises(ValueError, match="cam_to_ego"):
        model.encode(imgs, intr, ext[..., :3, :])
    with pytest.raises(TypeError, match="intrinsics"):
        model.encode(imgs, intr.numpy(), ext)
    with pytest.raises(ValueError, match=r"max_cameras=6 .*model_overrides: \{max_cameras: N\}"):
        i7, e7 = make_rig(1, 7, cfg.image_height, cfg.image_width)
        model.encode(random_images(1, 7, cfg.image_height, cfg.image_width), i7, e7)
    with pytest.raises(ValueError, match="local_src"):
        model.interact(torch.zeros(2, 5, 16), torch.zeros(2, 12, 16))
    # a BEV of another grid, or of another dtype, is named (it sampled the wrong radii)
    bev = torch.zeros(1, cfg.bev_height, cfg.bev_width, cfg.channels)
    assert model.polar(bev).shape == (1, cfg.num_angles, cfg.num_radii, cfg.channels)
    with pytest.raises(ValueError, match=r"bev: expected shape \(B, "):
        model.polar(bev[:, :-1])
    with pytest.raises(TypeError, match=r"bev: expected torch.float32 \(the model's dtype\)"):
        model.polar(bev.double())
    with pytest.raises(TypeError, match=r"polar: expected torch.float32"):
        model.decode_polar(model.polar(bev).double())
    # no frame or no camera: named, not torch's max() of an empty tensor deep in the encoder
    with pytest.raises(ValueError, match=r"images: expected at least one frame \(B >= 1\)"):
        model.encode(imgs[:0], intr[:0], ext[:0])
    with pytest.raises(ValueError, match=r"of at least one camera \(M >= 1\)"):
        model.encode(imgs[:, :0], intr[:, :0], ext[:, :0])
    # float images on the 0-255 scale, or NaN: refused (the first read 255 times too bright)
    with pytest.raises(ValueError, match=r"images: float images must lie in \[0, 1\]"):
        model.encode(imgs.float(), intr, ext)
    nan = imgs.float() / 255
    nan[0, 0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="images: holds non-finite"):
        model.encode(nan, intr, ext)
    # calibration that lets no camera see a cell encoded every frame as the same "no image"
    for k, edit in (
        ("intrinsics", lambda t: t[0, 0, 0, 0].fill_(float("nan"))),
        ("intrinsics", lambda t: t.zero_()),
        ("intrinsics", lambda t: t[0, 1, 2, 2].fill_(2.0)),
        ("cam_to_ego", lambda t: t[0, 0, 0, 3].fill_(float("nan"))),
        ("cam_to_ego", lambda t: t.mul_(2.0)),
        ("cam_to_ego", lambda t: t[0, 1, :3, :3].zero_()),
    ):
        bad = {"intrinsics": intr.clone(), "cam_to_ego": ext.clone()}
        edit(bad[k])
        with pytest.raises(ValueError, match=f"^{k}: expected a "):
            model.encode(imgs, bad["intrinsics"], bad["cam_to_ego"])


# --- geometry of the spatial cross-attention ----------------------------------------------


def test_projection_of_known_points():
    # Forward camera at 1.5 m height, f = 100 px, principal point (79.5, 47.5), image 160x96.
    intr, ext = make_rig(1, 1, 96, 160, focal=100.0)
    pts = torch.tensor(
        [
            [10.0, 0.0, 1.5],  # straight ahead at camera height -> principal point
            [10.0, 2.0, 0.5],  # 2 m left, 1 m below -> u = cx - 20, v = cy + 10
            [-10.0, 0.0, 1.5],  # behind the camera
            [2.0, 10.0, 1.5],  # far to the left, outside the image
        ]
    )
    ref, vis = project_points(pts, intr, ext, (96, 160))
    assert ref.shape == (1, 1, 4, 2) and vis.shape == (1, 1, 4)
    assert vis[0, 0].tolist() == [True, True, False, False]
    u = ref[0, 0, :2, 0] * 160 - 0.5
    v = ref[0, 0, :2, 1] * 96 - 0.5
    torch.testing.assert_close(u, torch.tensor([79.5, 59.5]))
    torch.testing.assert_close(v, torch.tensor([47.5, 57.5]))


def test_zeroed_camera_changes_only_the_cells_it_sees():
    cfg = tiny_config(bev_self_attention=False, encoder_layers=2)
    model = _model(cfg)
    intr, ext = make_rig(1, 4, cfg.image_height, cfg.image_width)
    imgs = random_images(1, 4, cfg.image_height, cfg.image_width)
    size = (cfg.image_height, cfg.image_width)
    with torch.no_grad():
        feats = model.image_features(imgs)
        bev = model.bev_from_features(feats, intr, ext, size)
        zeroed = [f.clone() for f in feats]
        for f in zeroed:
            f[:, 1] = 0.0
        bev0 = model.bev_from_features(zeroed, intr, ext, size)
    _, vis = project_points(model.encoder.pillars.reshape(-1, 3), intr, ext, size)
    seen = vis[0, 1].reshape(cfg.bev_height, cfg.bev_width, -1).any(-1)
    changed = (bev - bev0).abs().amax(-1)[0]
    assert 0 < int(seen.sum()) < seen.numel()
    assert bool((changed[~seen] == 0).all())
    assert bool((changed[seen] > 1e-5).all())


# --- polar transform and padding ----------------------------------------------------------


def _literal_polar(q: np.ndarray, t_bins: int, r_bins: int, g: float) -> np.ndarray:
    """Bilinear sampling loop of DESIGN.md §3 (fill 1 outside), float64."""
    h, w, c = q.shape
    r_max = min(h, w) * g / 2
    out = np.empty((t_bins, r_bins, c))
    for k in range(t_bins):
        th = (k + 0.5) * 2 * math.pi / t_bins
        for m in range(r_bins):
            r = (m + 0.5) * r_max / r_bins
            fi, fj = r * math.sin(th) / g + (h - 1) / 2, r * math.cos(th) / g + (w - 1) / 2
            i0, j0 = math.floor(fi), math.floor(fj)
            acc = np.zeros(c)
            for di, wi in ((0, 1 - (fi - i0)), (1, fi - i0)):
                for dj, wj in ((0, 1 - (fj - j0)), (1, fj - j0)):
                    ii, jj = i0 + di, j0 + dj
                    inside = 0 <= ii < h and 0 <= jj < w
                    acc += wi * wj * (q[ii, jj] if inside else 1.0)
            out[k, m] = acc
    return out


def _roll_interp_np(x: np.ndarray, s: float, axis: int) -> np.ndarray:
    k = math.floor(s)
    w = s - k
    return (1 - w) * np.roll(x, k, axis) + w * np.roll(x, k + 1, axis)


def _literal_pad(q: np.ndarray, t: tuple[float, float], g: float) -> np.ndarray:
    """Paper Alg. 1 with corrected negative shifts (DESIGN.md §3)."""
    h, w, _ = q.shape
    sx, sy = t[0] / g, t[1] / g
    out = _roll_interp_np(_roll_interp_np(q, -sx, 0), -sy, 1)
    if sx >= 0:
        out[h - math.ceil(sx) :] = 1.0
    else:
        out[: math.ceil(-sx)] = 1.0
    if sy >= 0:
        out[:, w - math.ceil(sy) :] = 1.0
    else:
        out[:, : math.ceil(-sy)] = 1.0
    return out


@pytest.mark.parametrize(
    ("h", "w", "t_bins", "r_bins", "g"), [(9, 9, 12, 4, 0.5), (10, 7, 7, 5, 0.3)]
)
def test_polar_sample_matches_literal_loop(h, w, t_bins, r_bins, g):
    rng = np.random.default_rng(1)
    q = rng.standard_normal((2, h, w, 3))
    got = polar_sample(torch.tensor(q, dtype=torch.float32), t_bins, r_bins, g).numpy()
    for b in range(2):
        np.testing.assert_allclose(got[b], _literal_polar(q[b], t_bins, r_bins, g), atol=1e-5)


@pytest.mark.parametrize("t", [(0.0, 0.0), (1.0, -2.0), (0.7, 1.3), (-1.45, -0.2), (3.3, 0.5)])
def test_bev_pad_matches_literal_algorithm(t):
    rng = np.random.default_rng(2)
    q = rng.standard_normal((8, 9, 3))
    got = bev_pad(torch.tensor(q, dtype=torch.float32), torch.tensor([t]), 0.5).numpy()[0]
    np.testing.assert_allclose(got, _literal_pad(q, t, 0.5), atol=1e-5)


def test_bev_pad_batched_form_and_gradient():
    q = torch.randn(3, 6, 6, 2, requires_grad=True)
    t = torch.tensor([[0.0, 0.0], [0.5, 0.0], [-1.0, 0.25]])
    out = bev_pad(q, t, 0.5)
    assert out.shape == (3, 6, 6, 2)
    torch.testing.assert_close(out[0], q[0])
    single = bev_pad(q[1], t[1:2], 0.5)[0]
    torch.testing.assert_close(out[1], single)
    out.sum().backward()
    assert q.grad is not None and q.grad.abs().sum() > 0


def test_roll_interp_per_row_shifts():
    x = torch.randn(3, 8, 2)
    shifts = torch.tensor([0.0, 2.0, -1.25])
    out = roll_interp(x, shifts, dim=1)
    for p, s in enumerate(shifts.tolist()):
        ref = _roll_interp_np(x[p].numpy(), s, 0)
        np.testing.assert_allclose(out[p].numpy(), ref, atol=1e-6)


def test_polar_and_pad_equal_rust_kernels():
    rng = np.random.default_rng(3)
    q = rng.standard_normal((2, 20, 18, 5)).astype(np.float32)
    got = polar_sample(torch.from_numpy(q), 24, 8, 0.3).numpy()
    want = kernels.polar_sample(q, 24, 8, 0.3)
    np.testing.assert_allclose(got, want, atol=1e-5)
    t = np.array([[0.0, 0.0], [0.45, -1.2], [-2.0, 0.7]], dtype=np.float32)
    got_pad = bev_pad(torch.from_numpy(q[0]), torch.from_numpy(t), 0.3).numpy()
    want_pad = kernels.bev_pad(q[0], t, 0.3)
    np.testing.assert_allclose(got_pad, want_pad, atol=1e-5)
    # the per-item (batched) form used by the losses
    got_items = bev_pad(torch.from_numpy(q[:1]).expand(3, -1, -1, -1), torch.from_numpy(t), 0.3)
    np.testing.assert_allclose(got_items.numpy(), want_pad, atol=1e-5)


# --- heads, decoder, interactor under circular angle shifts -------------------------------


@pytest.mark.parametrize("head_cls", [DiscoHead, GeMHead, NetVLADHead])
def test_global_heads_invariant_to_angle_shifts(head_cls):
    torch.manual_seed(0)
    cfg = tiny_config(num_angles=24, num_radii=6, disco_crop=(8, 4))
    head = head_cls(cfg)
    polar = torch.randn(2, 24, 6, cfg.channels).abs()
    base = head(polar)
    np.testing.assert_allclose(base.norm(dim=-1).detach().numpy(), 1.0, atol=1e-5)
    for k in (1, 5, 23):
        torch.testing.assert_close(head(torch.roll(polar, k, dims=1)), base, atol=1e-5, rtol=1e-5)


def test_disco_head_is_not_trivially_constant():
    torch.manual_seed(0)
    cfg = tiny_config(global_head="disco")
    head = DiscoHead(cfg)
    with torch.no_grad():
        a, b = head(torch.randn(1, 12, 4, 16)), head(torch.randn(1, 12, 4, 16))
    assert float((a - b).abs().max()) > 1e-3


def test_decoder_is_equivariant_to_angle_rolls():
    cfg = tiny_config(decoder_layers=2)
    model = _model(cfg)
    polar = torch.randn(2, cfg.num_angles, cfg.num_radii, cfg.channels)
    with torch.no_grad():
        base = model.decode_polar(polar)
        for k in (1, 5, 11):
            rolled = model.decode_polar(torch.roll(polar, k, dims=1))
            torch.testing.assert_close(rolled, torch.roll(base, k, dims=1), atol=1e-5, rtol=1e-5)


def test_interactor_is_equivariant_to_angle_rolls():
    cfg = tiny_config(interactor_rounds=2)
    model = _model(cfg)
    ds = torch.randn(3, cfg.num_angles, cfg.channels)
    dt = torch.randn(3, cfg.num_angles, cfg.channels)
    with torch.no_grad():
        s1, t1 = model.interact(ds, dt)
        np.testing.assert_allclose(s1.norm(dim=-1).numpy(), 1.0, atol=1e-5)
        np.testing.assert_allclose(t1.norm(dim=-1).numpy(), 1.0, atol=1e-5)
        for k in (1, 4, 7):
            s2, t2 = model.interact(torch.roll(ds, k, dims=1), dt)
            torch.testing.assert_close(s2, torch.roll(s1, k, dims=1), atol=1e-5, rtol=1e-5)
            torch.testing.assert_close(t2, t1, atol=1e-5, rtol=1e-5)
            s3, t3 = model.interact(ds, torch.roll(dt, k, dims=1))
            torch.testing.assert_close(s3, s1, atol=1e-5, rtol=1e-5)
            torch.testing.assert_close(t3, torch.roll(t1, k, dims=1), atol=1e-5, rtol=1e-5)
        # attention is really mixing angles: changing one target row changes every source row
        dt2 = dt.clone()
        dt2[:, 0] += 1.0
        s4, _ = model.interact(ds, dt2)
        assert bool(((s4 - s1).abs().amax(-1) > 1e-6).all())


# --- checkpoints --------------------------------------------------------------------------


def test_save_load_roundtrip(tmp_path):
    cfg = tiny_config(global_head="netvlad")
    model = _model(cfg, seed=3)
    model.save(tmp_path / "ckpt")
    assert sorted(p.name for p in (tmp_path / "ckpt").iterdir()) == [
        "config.json",
        "model.safetensors",
    ]
    meta = json.loads((tmp_path / "ckpt" / "config.json").read_text())
    assert meta["version"] == 1 and meta["config_hash"] == model.config_hash()
    loaded = VVLocNet.load(tmp_path / "ckpt").eval()
    assert loaded.config == cfg and loaded.config_hash() == model.config_hash()
    with torch.no_grad():
        a, b = _encode(model, 1, 2), _encode(loaded, 1, 2)
    torch.testing.assert_close(a.global_desc, b.global_desc, rtol=0, atol=0)
    torch.testing.assert_close(a.local_desc, b.local_desc, rtol=0, atol=0)


def test_a_failed_save_leaves_the_previous_checkpoint_whole(tmp_path, monkeypatch):
    """Every file is serialised, then written and flushed, before the first replaces its
    destination: a save that fails (or is interrupted) while writing changes no file."""
    import vvloc._io as io

    ckpt = tmp_path / "ckpt"
    old = _model(tiny_config(), seed=0)
    old.calibration = {"min_distinctiveness": 0.25, "top_k": 5}
    old.save(ckpt)
    before = {p.name: p.read_bytes() for p in ckpt.iterdir()}
    new = _model(tiny_config(), seed=1)
    new.calibration = {"min_distinctiveness": np.float32(0.3)}  # not JSON: fails serialising
    with pytest.raises(TypeError):
        new.save(ckpt)
    assert {p.name: p.read_bytes() for p in ckpt.iterdir()} == before
    new.calibration = {"min_distinctiveness": 0.3}
    calls = []
    real_fsync = io._fsync_file

    def interrupted(path):  # Ctrl-C while the second file is flushed
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt
        real_fsync(path)

    monkeypatch.setattr(io, "_fsync_file", interrupted)
    with pytest.raises(KeyboardInterrupt):
        new.save(ckpt)
    monkeypatch.setattr(io, "_fsync_file", real_fsync)
    assert {p.name: p.read_bytes() for p in ckpt.iterdir()} == before  # no temporary either
    assert VVLocNet.load(ckpt).weights_hash() == old.weights_hash()
    new.save(ckpt)
    assert VVLocNet.load(ckpt).weights_hash() == new.weights_hash()
    assert VVLocNet.load(ckpt).calibration == {"min_distinctiveness": 0.3}


def test_weights_of_another_dtype_are_refused_not_cast(tmp_path):
    from safetensors.torch import load_file, save_file

    model = _model(tiny_config(), seed=0)
    with pytest.raises(TypeError, match=r"torch.bfloat16.*save a float32 model"):
        _model(tiny_config(), seed=0).to(torch.bfloat16).save(tmp_path / "bf16")
    assert not (tmp_path / "bf16" / "model.safetensors").exists()
    model.save(tmp_path)
    state = load_file(str(tmp_path / "model.safetensors"))
    for dtype in (torch.int32, torch.float16):  # would load truncated / rounded
        save_file({k: v.to(dtype) for k, v in state.items()}, str(tmp_path / "model.safetensors"))
        with pytest.raises(ValueError, match=f"checkpoint {dtype} vs model torch.float32"):
            VVLocNet.load(tmp_path)
    save_file(state, str(tmp_path / "model.safetensors"))
    assert VVLocNet.load(tmp_path, map_location="auto").weights_hash() == model.weights_hash()
    with pytest.raises(ValueError, match="map_location: expected 'cpu', 'cuda'"):
        VVLocNet.load(tmp_path, map_location="bogus")


def test_a_checkpoint_saved_before_configs_were_normalised_still_loads(tmp_path):
    """Before 2026-12-05 a config's numbers were hashed as written: a run with the YAML
    override sigma_a: 15 saved that int and its hash. Such a checkpoint loads, with a warning
    that its hash now reads otherwise (maps built with it must be rebuilt)."""
    import hashlib

    model = _model(tiny_config(), seed=0)
    model.save(tmp_path)
    meta_path = tmp_path / "config.json"
    meta = json.loads(meta_path.read_text())
    meta["config"]["sigma_a"] = int(meta["config"]["sigma_a"])
    old_json = json.dumps(meta["config"], sort_keys=True)
    meta["config_hash"] = hashlib.sha256(old_json.encode()).hexdigest()[:16]
    meta_path.write_text(json.dumps(meta))
    with pytest.warns(UserWarning, match="before vvloc normalised config numbers"):
        loaded = VVLocNet.load(tmp_path)
    assert loaded.config_hash() == model.config_hash()
    meta["config_hash"] = "0123456789abcdef"  # any other hash is an edited file, as before
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="edited"):
        VVLocNet.load(tmp_path)


def test_a_checkpoint_folder_resolves_to_itself_whatever_it_holds(tmp_path):
    from vvloc.checkpoints import resolve_checkpoint

    _model(tiny_config(), seed=0).save(tmp_path / "ckpt")
    _model(tiny_config(), seed=1).save(tmp_path / "ckpt" / "best")  # e.g. a user's copy
    assert resolve_checkpoint(tmp_path / "ckpt") == tmp_path / "ckpt"
    run = tmp_path / "run"  # a run whose best/ lost its weights: its checkpoint/ is taken
    _model(tiny_config(), seed=0).save(run / "checkpoint")
    (run / "best").mkdir()
    (run / "best" / "config.json").write_text("{}")
    assert resolve_checkpoint(run) == run / "checkpoint"


def test_checkpoint_files_get_the_mode_of_a_plain_open(tmp_path):
    # atomic writes must not leave 0o600 files behind (shared run folders, committed models)
    old = os.umask(0o022)
    try:
        _model(tiny_config(), seed=0).save(tmp_path / "ckpt")
    finally:
        os.umask(old)
    for p in (tmp_path / "ckpt").iterdir():
        assert stat.S_IMODE(p.stat().st_mode) == 0o644, p.name


def test_load_rejects_mismatched_checkpoints(tmp_path):
    cfg = tiny_config()
    _model(cfg).save(tmp_path)
    meta_path = tmp_path / "config.json"
    meta = json.loads(meta_path.read_text())

    def write_consistent(meta: dict) -> None:  # a config whose hash is recorded, other weights
        meta["config_hash"] = ModelConfig.from_dict(meta["config"]).config_hash()
        meta_path.write_text(json.dumps(meta))

    meta["config"]["ffn_dim"] = 48
    write_consistent(meta)
    with pytest.raises(ValueError, match=r"shape or dtype mismatches .*ffn"):
        VVLocNet.load(tmp_path)
    meta["config"]["ffn_dim"] = cfg.ffn_dim
    meta["config"]["global_head"] = "disco"
    write_consistent(meta)
    with pytest.raises(ValueError, match=r"missing .*unexpected"):
        VVLocNet.load(tmp_path)
    for version in (99, True, 1.0, "1"):  # True == 1 and 1.0 == 1 once passed
        meta["version"] = version
        meta_path.write_text(json.dumps(meta))
        with pytest.raises(ValueError, match=f"version {version!r} is not supported"):
            VVLocNet.load(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"directory: \S*nothing does not exist \(expected"):
        VVLocNet.load(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=r"directory: .*empty.*not a vvloc checkpoint\)"):
        VVLocNet.load(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match=r"model.safetensors is a file, not a folder"):
        VVLocNet.load(meta_path.parent / "model.safetensors")
    run = tmp_path / "run"  # a training run's folder: the message points at its checkpoints
    _model(tiny_config(), seed=1).save(run / "checkpoint")
    with pytest.raises(FileNotFoundError, match=r"is a training run: load \S*/run/checkpoint\)"):
        VVLocNet.load(run)
    # the CLI's form: a run resolves to its checkpoint, a bad path names the option
    from vvloc.checkpoints import checkpoint_folder

    assert checkpoint_folder(run) == run / "checkpoint"
    with pytest.raises(FileNotFoundError, match=r"^--checkpoint: .*empty.*config.json not found"):
        checkpoint_folder(tmp_path / "empty", "--checkpoint")


def test_non_finite_weights_are_never_saved_or_loaded(tmp_path):
    from safetensors.torch import load_file, save_file

    model = _model(tiny_config(), seed=1)
    model.save(tmp_path / "good")
    broken = _model(tiny_config(), seed=1)
    with torch.no_grad():
        next(broken.decoder.parameters()).fill_(float("nan"))
    with pytest.raises(ValueError, match=r"non-finite weights \(decoder\..*Not saved"):
        broken.save(tmp_path / "bad")
    assert not (tmp_path / "bad").exists()
    # a file whose weights turned NaN: refused by name, whether config.json records a
    # fingerprint, records null, or (saved before 2026-12-05) records none
    w_path, meta_path = tmp_path / "good" / "model.safetensors", tmp_path / "good" / "config.json"
    state = load_file(str(w_path))
    key = next(k for k in state if k.startswith("decoder."))
    state[key] = torch.full_like(state[key], float("inf"))
    save_file(state, str(w_path))
    meta = json.loads(meta_path.read_text())
    for recorded in (meta["weights_hash"], None, "absent"):
        meta["weights_hash"] = recorded
        if recorded == "absent":
            del meta["weights_hash"]
        meta_path.write_text(json.dumps(meta))
        with pytest.raises(
            ValueError, match=rf"model.safetensors: holds non-finite weights \({key}"
        ):
            VVLocNet.load(tmp_path / "good")
    # a null fingerprint (not an old checkpoint's absent one) is checked like any other
    model.save(tmp_path / "null")
    meta = json.loads((tmp_path / "null" / "config.json").read_text())
    meta["weights_hash"] = None
    (tmp_path / "null" / "config.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="fingerprint"):
        VVLocNet.load(tmp_path / "null")


def test_load_refuses_edited_truncated_or_malformed_checkpoints(tmp_path):
    # fields such as num_angles or grid_size shape no weight: only the recorded hash tells
    model = _model(tiny_config(), seed=1)
    model.save(tmp_path)
    meta_path, w_path = tmp_path / "config.json", tmp_path / "model.safetensors"
    good_meta, good_weights = meta_path.read_text(), w_path.read_bytes()
    loaded = VVLocNet.load(tmp_path)
    assert not loaded.training  # eval mode: dropout off at inference
    meta = json.loads(good_meta)
    meta["config"]["num_angles"] = 2 * meta["config"]["num_angles"]
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"config_hash .* edited"):
        VVLocNet.load(tmp_path)
    meta = json.loads(good_meta)
    del meta["config"]["grid_size"]
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"lacks the fields \['grid_size'\]"):
        VVLocNet.load(tmp_path)
    no_config = '{"format": "vvloc.nets.VVLocNet", "version": 1}'
    for text, match in (("[1, 2]", "JSON object"), ("{not json", "not a JSON file"),
                        (no_config, "'config'")):  # fmt: skip
        meta_path.write_text(text)
        with pytest.raises(ValueError, match=match):
            VVLocNet.load(tmp_path)
    meta_path.write_text(good_meta)
    cal_path = tmp_path / "calibration.json"
    bad_calibrations = (
        ('{"min_distinct', "calibration.json: not a JSON file"),
        ('{"min_distinctiveness": NaN}', "calibration.json: min_distinct"),
    )
    for text, match in bad_calibrations:
        cal_path.write_text(text)
        with pytest.raises(ValueError, match=match):
            VVLocNet.load(tmp_path)
    cal_path.write_text('{"min_distinctiveness": null}')  # no threshold reached: accept nothing
    assert VVLocNet.load(tmp_path).calibration["min_distinctiveness"] == math.inf
    for text, field in (
        ('{"min_distinctiveness": true}', "min_distinctiveness"),
        ('{"min_distinctiveness": 0.2, "top_k": "twenty"}', "top_k"),
        ('{"min_distinctiveness": 0.2, "top_k": 0}', "top_k"),
        ('{"min_distinctiveness": 0.2, "accept_threshold": "x"}', "accept_threshold"),
    ):  # fields the localizer reads: refused by name at load, not deep in a Localizer
        cal_path.write_text(text)
        with pytest.raises(ValueError, match=f"calibration.json: {field} must be"):
            VVLocNet.load(tmp_path)
    cal_path.write_text('{"min_distinctiveness": null}')
    assert VVLocNet.load(tmp_path).calibration["min_distinctiveness"] == math.inf
    cal_path.unlink()
    w_path.write_bytes(good_weights[: len(good_weights) // 2])
    with pytest.raises(ValueError, match="not a readable safetensors file"):
        VVLocNet.load(tmp_path)
    # a damaged weights file that still parses (a flipped byte inside a tensor) is refused by
    # the fingerprint config.json records; a checkpoint saved before it recorded one loads
    damaged = bytearray(good_weights)
    damaged[-7] ^= 0x10
    w_path.write_bytes(bytes(damaged))
    with pytest.raises(ValueError, match=r"model.safetensors: its weights' fingerprint .* damaged"):
        VVLocNet.load(tmp_path)
    meta = json.loads(good_meta)
    assert meta["weights_hash"] == model.weights_hash()
    del meta["weights_hash"]
    meta_path.write_text(json.dumps(meta))
    VVLocNet.load(tmp_path)  # an older checkpoint: nothing to check against


def test_a_float64_model_encodes_in_float64():
    cfg = tiny_config()
    model = _model(cfg, seed=0)
    with torch.no_grad():
        a = _encode(model, 1, 2)
        b = _encode(model.double(), 1, 2)
    assert b.bev.dtype == torch.float64 and b.global_desc.dtype == torch.float64
    torch.testing.assert_close(b.global_desc.float(), a.global_desc, rtol=0, atol=1e-4)


def test_resolve_device_names_the_argument_and_refuses_what_torch_cannot_use():
    import torch

    from vvloc.nets.model import resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    for bad in ("gpu", "xla", "cuda:x", ""):
        with pytest.raises(ValueError, match="--device: expected 'cpu'"):
            resolve_device(bad, argument="--device")
    with pytest.raises(ValueError, match=r"'mps' is not supported .*float64"):
        resolve_device("mps")  # the camera geometry runs in float64, which MPS lacks
    with pytest.raises(ValueError, match="expected 'cpu'"):
        resolve_device(torch.device("meta"))
    with pytest.raises(TypeError, match="device"):
        resolve_device(0)  # type: ignore[arg-type]
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            resolve_device("cuda")
    else:
        with pytest.raises(ValueError, match="CUDA device"):
            resolve_device(f"cuda:{torch.cuda.device_count()}")


def test_training_path_spatial_ops_check_their_arguments_like_the_kernels():
    bev = torch.rand(1, 6, 6, 2)
    for args, match in (((8, 4, 0.0), "grid_size"), ((8, 4, math.nan), "grid_size"),
                        ((0, 4, 0.5), "num_angles"), ((8, 0, 0.5), "num_radii")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            polar_sample(bev, *args)
    with pytest.raises(ValueError, match="grid_size"):
        bev_pad(bev[0], torch.zeros(1, 2), 0.0)
    with pytest.raises(ValueError, match="translations: contains non-finite"):
        bev_pad(bev[0], torch.tensor([[math.nan, 0.0]]), 0.5)
    torch.testing.assert_close(bev_pad(bev[0], torch.zeros(1, 2), 0.5)[0], bev[0])


def test_the_training_paths_ops_name_inputs_they_cannot_use():
    from vvloc.nets.encoder import bev_cell_centres

    b = torch.rand(2, 6, 6, 3)
    with pytest.raises(ValueError, match=r"^shift: contains non-finite"):
        roll_interp(torch.arange(4.0)[None], float("nan"))  # all NaN came back
    with pytest.raises(ValueError, match=r"^dim: expected an axis of x after its first"):
        roll_interp(torch.arange(4.0)[None], 1.0, dim=5)  # IndexError
    with pytest.raises(ValueError, match=r"^dim: "):
        roll_interp(torch.rand(2, 4), torch.ones(2), dim=0)  # the per-item axis itself
    with pytest.raises(TypeError, match=r"^x: expected a torch.Tensor"):
        roll_interp(np.ones((2, 3)), 1.0)  # type: ignore[arg-type]
    x = torch.rand(3, 5, 4)
    shift = torch.tensor([0.5, 1.0, 2.0])
    assert torch.equal(roll_interp(x, shift, dim=-2), roll_interp(x, shift, dim=1))
    with pytest.raises(
        TypeError, match=r"^bev: expected a floating-point tensor .*got torch.int64"
    ):
        polar_sample(b.long(), 8, 3, 0.5)
    with pytest.raises(TypeError, match=r"^bev: expected a floating-point tensor"):
        bev_pad(b[0].long(), torch.zeros(2, 2), 0.5)  # torch said "not implemented for Long"
    with pytest.raises(TypeError, match=r"^bev: expected a torch.Tensor \(H, W, C\) or"):
        bev_pad(np.ones((6, 6, 3)), torch.zeros(1, 2), 0.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^bev: expected H, W, C >= 1"):
        polar_sample(torch.rand(1, 0, 4, 3), 8, 3, 0.5)  # grid_sampler's RuntimeError
    with pytest.raises(TypeError, match=r"^translations: expected real numbers"):
        bev_pad(b[0], torch.zeros(2, 2, dtype=torch.complex64), 0.5)  # cast with a warning
    with pytest.raises(ValueError, match=r"^height: expected an int >= 1, got -1"):
        bev_cell_centres(-1, 2, 0.5)
    with pytest.raises(ValueError, match=r"^grid_size: expected a finite value > 0"):
        bev_cell_centres(2, 2, float("nan"))  # garbage came back
    assert bev_cell_centres(2, 3, 0.5).dtype == torch.float32
    k = torch.eye(3)[None, None].repeat(1, 2, 1, 1)
    e = torch.eye(4)[None, None].repeat(1, 2, 1, 1)
    with pytest.raises(ValueError, match=r"^points: expected shape \(N, 3\), got \(5, 2\)"):
        project_points(torch.rand(5, 2), k, e, (10, 12))
    with pytest.raises(TypeError, match=r"^points: expected a torch.Tensor \(N, 3\), got ndarray"):
        project_points(np.ones((5, 3)), k, e, (10, 12))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^cam_to_ego: a transform cannot be inverted"):
        project_points(torch.rand(5, 3), k, torch.zeros(1, 2, 4, 4), (10, 12))
    with pytest.raises(ValueError, match=r"^image_size: expected an int >= 1, got 0"):
        project_points(torch.rand(5, 3), k, e, (10, 0))


def test_heads_and_the_interactor_name_inputs_they_cannot_use():
    cfg = tiny_config()
    c = cfg.channels
    for head in (GeMHead(cfg), NetVLADHead(cfg), DiscoHead(cfg)):
        # another channel count, or a missing batch axis, gave a descriptor of another size
        with pytest.raises(ValueError, match=rf"^polar: expected shape \(B, T, R, {c}\)"):
            head(torch.ones(1, cfg.num_angles, cfg.num_radii, c + 1))
        with pytest.raises(ValueError, match=r"^polar: expected shape"):
            head(torch.ones(cfg.num_angles, cfg.num_radii, c))
    model = _model(cfg)
    d = torch.rand(2, cfg.num_angles, c)
    with pytest.raises(TypeError, match=r"^local_src: expected a torch.Tensor, got ndarray"):
        model.interact(d.numpy(), d)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"^local_tgt: expected torch.float32 \(the model's"):
        model.interact(d, d.double())
    assert model.interact(d, d)[0].shape == d.shape


def test_shifts_and_translations_given_as_numbers_keep_float64_precision():
    # they went through float32 first: roll_interp(float64 x, 2.1) weighted by 0.10000000149
    x = torch.arange(4.0, dtype=torch.float64)[None]
    assert roll_interp(x, 2.1)[0, 3].item() == pytest.approx(0.9, abs=1e-15)
    bev = torch.rand(6, 6, 3, dtype=torch.float64)
    assert torch.equal(
        bev_pad(bev, [[0.1, 0.2]], 0.5),
        bev_pad(bev, torch.tensor([[0.1, 0.2]], dtype=torch.float64), 0.5),
    )


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status")
def test_loading_a_checkpoint_again_and_again_keeps_no_memory(one_torch_thread):
    # safetensors' load_file kept about 8 KB per call (its file mapping; safetensors 0.8): a
    # service opening localizers grew by it. Measured after malloc_trim, so freed memory is
    # returned and only kept memory counts; building the model keeps about 0.4 KB per call.
    import ctypes
    import gc

    libc = ctypes.CDLL("libc.so.6")

    def rss_kb() -> int:
        gc.collect()
        libc.malloc_trim(0)
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmRSS"))

    for _ in range(30):
        VVLocNet.load("models/synth-small")
    before = rss_kb()
    for _ in range(300):
        VVLocNet.load("models/synth-small")
    assert (rss_kb() - before) / 300 < 3.0  # KB per load
