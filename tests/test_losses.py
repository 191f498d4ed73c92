"""Losses: hand-computed values on tiny examples, zero when margins are met, a geometric oracle
for the pose sign conventions of the yaw-matching path, gradients, and a tiny overfitting run."""

from __future__ import annotations

import math
import types

import pytest
import torch
import torch.nn.functional as F
from torch import Tensor

from nets_helpers import make_rig, random_images, tiny_config
from vvloc import losses
from vvloc.nets import ModelConfig, VVLocNet, polar_sample
from vvloc.reference.matching import yaw_costs

pytestmark = pytest.mark.usefixtures("one_torch_thread")

# --- triplet and hinge --------------------------------------------------------------------


def test_triplet_loss_hand_computed():
    a = torch.tensor([[1.0, 0.0]])
    p = torch.tensor([[0.6, 0.8]])  # |a - p| = sqrt(0.8)
    n_close = torch.tensor([[0.8, 0.6]])  # |a - n| = sqrt(0.4)
    n_far = torch.tensor([[0.0, 1.0]])  # |a - n| = sqrt(2)
    want = math.sqrt(0.8) - math.sqrt(0.4) + 0.1
    assert losses.triplet_loss(a, p, n_close).item() == pytest.approx(want, abs=1e-6)
    assert losses.triplet_loss(a, p, n_far).item() == 0.0
    both = torch.stack([n_close, n_far], dim=1)  # (B, K=2, D)
    assert losses.triplet_loss(a, p, both).item() == pytest.approx(want / 2, abs=1e-6)
    assert losses.triplet_loss(a, p, n_close, margin=0.5).item() == pytest.approx(
        want + 0.4, abs=1e-6
    )


def test_losses_of_no_pair_are_zero_and_keep_the_graph():
    # mean() of nothing is nan, which would stop training at the step that drew no triplet
    a = torch.randn(0, 4, requires_grad=True)
    empty = losses.triplet_loss(a, a, a)
    no_negatives = losses.triplet_loss(torch.randn(3, 4), torch.randn(3, 4), torch.zeros(3, 0, 4))
    d = torch.randn(0, 6, 4, requires_grad=True)
    circle = losses.yaw_circle_loss(d, d)
    for loss in (empty, no_negatives, circle):
        assert loss.shape == () and loss.item() == 0.0
    (empty + circle).backward()  # still part of the graph, so a step over it runs
    assert a.grad is not None and d.grad is not None


def test_hinge_loss_hand_computed():
    pos = torch.tensor([0.05, 0.3])
    neg = torch.tensor([0.1, 0.5])
    # mean(relu(pos - 0.1)) = 0.1, mean(relu(0.2 - neg)) = 0.05
    assert losses.hinge_loss(pos, neg).item() == pytest.approx(0.15, abs=1e-6)
    assert losses.hinge_loss(torch.tensor([0.0, 0.1]), torch.tensor([0.2, 1.0])).item() == 0.0
    assert losses.hinge_loss(pos, torch.zeros(0)).item() == pytest.approx(0.1, abs=1e-6)


def test_matching_cost_is_mean_row_distance():
    a = torch.tensor([[[0.0, 0.0], [1.0, 1.0]]])
    b = torch.tensor([[[3.0, 4.0], [1.0, 1.0]]])
    assert losses.matching_cost(a, b).item() == pytest.approx(2.5, abs=1e-5)


# --- yaw circle loss ----------------------------------------------------------------------


def test_yaw_circle_loss_hand_computed():
    src = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]])
    tgt = torch.tensor([[[0.6, 0.8], [0.0, 1.0]]])
    gamma, tp, tn = 40.0, 0.1, 1.4
    # row 0: positive distance sqrt(0.8) > 0.1; negative distance sqrt(2) > 1.4 (margin met)
    s_p0 = gamma * (math.sqrt(0.8) - tp) ** 2
    l0 = math.log(1 + math.exp(s_p0) * math.exp(0.0)) - math.log(2)
    # row 1: positive distance 0; negative distance sqrt(0.4) < 1.4
    s_n1 = gamma * (tn - math.sqrt(0.4)) ** 2
    l1 = math.log(1 + math.exp(0.0) * math.exp(s_n1)) - math.log(2)
    got = losses.yaw_circle_loss(src, tgt)
    assert got.item() == pytest.approx((l0 + l1) / 2, rel=1e-5)


def test_yaw_circle_loss_zero_when_margins_met_and_gradients_only_for_violations():
    eye = torch.eye(4)[None]
    assert losses.yaw_circle_loss(eye, eye.clone()).item() == 0.0
    # Target row 0 moves: source row 0's positive and source row 1's negative (distance 1.19 <
    # 1.4) are violated; rows 2 and 3 still meet every margin and get no gradient.
    src = eye.clone().requires_grad_(True)
    tgt = eye.clone()
    tgt[0, 0] = F.normalize(torch.tensor([1.0, 0.3, 0.0, 0.0]), dim=0)
    loss = losses.yaw_circle_loss(src, tgt)
    loss.backward()
    assert loss.item() > 0
    assert src.grad is not None and src.grad[0, 0].abs().sum() > 0
    assert src.grad[0, 1].abs().sum() > 0
    assert src.grad[0, 2:].abs().sum() == 0


# --- re-ranking loss (ours) --------------------------------------------------------------


class _IdentityInteractor:
    """A stand-in for VVLocNet whose interactor passes the pair through unchanged."""

    def interact(self, src: Tensor, tgt: Tensor) -> tuple[Tensor, Tensor]:
        return src, tgt


def test_roll_min_cost_is_the_lowest_integer_roll_of_the_reference():
    gen = torch.Generator().manual_seed(4)
    src = F.normalize(torch.randn(5, 12, 6, generator=gen), dim=-1)
    tgt = F.normalize(torch.randn(5, 12, 6, generator=gen), dim=-1)
    want = yaw_costs(src.double().numpy(), tgt.double().numpy()).min(axis=1)
    got = losses.roll_min_cost(src, tgt)
    assert got.shape == (5,)
    assert torch.allclose(got.double(), torch.from_numpy(want), atol=1e-5)
    # a rolled copy costs (almost) nothing, whatever the roll
    assert losses.roll_min_cost(src, torch.roll(src, 7, dims=1)).max().item() < 1e-5


def test_rerank_loss_hand_computed_and_zero_when_the_margin_is_met():
    model = _IdentityInteractor()
    a = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]])
    pos = torch.roll(a, 1, dims=1)  # the anchor seen under another yaw: cost 0
    neg = torch.tensor([[[0.6, 0.8], [0.6, 0.8]]])
    # the negative's best roll: rows (1,0)->(0.6,0.8) sqrt(0.8), (0,1)->(0.6,0.8) sqrt(0.4)
    c_neg = (math.sqrt(0.8) + math.sqrt(0.4)) / 2
    assert losses.rerank_loss(model, a, pos, neg).item() == 0.0  # c_neg > 0 + 0.1
    # float32 (0.6 and 0.8 are not exact there; torch 2.15 lands 1.03e-6 from the float64 value)
    assert losses.rerank_loss(model, a, neg, pos).item() == pytest.approx(c_neg + 0.1, abs=1e-5)
    assert losses.rerank_loss(model, a, pos, neg, margin=1.0).item() == pytest.approx(
        1.0 - c_neg, abs=1e-5
    )


def test_rerank_loss_gradient_pulls_the_positive_and_pushes_the_negative():
    model = _IdentityInteractor()
    gen = torch.Generator().manual_seed(5)
    a = F.normalize(torch.randn(2, 8, 4, generator=gen), dim=-1)
    pos = F.normalize(torch.randn(2, 8, 4, generator=gen), dim=-1).requires_grad_()
    neg = (a + 0.01 * torch.randn(2, 8, 4, generator=gen)).requires_grad_()
    loss = losses.rerank_loss(model, a, pos, neg)
    assert loss.item() > 0
    loss.backward()
    step = 0.05
    with torch.no_grad():
        after = losses.rerank_loss(model, a, pos - step * pos.grad, neg - step * neg.grad)
    assert after.item() < loss.item()


# --- the yaw-matching path: a geometric oracle for the pose signs ---------------------------


def _field(x: Tensor, y: Tensor) -> Tensor:
    """A smooth world feature field (4 channels) at world points (x, y) metres."""
    return torch.stack(
        [
            torch.sin(0.35 * x + 0.1),
            torch.cos(0.3 * y - 0.2),
            torch.sin(0.2 * (x + 2 * y)),
            torch.cos(0.25 * (x - y)),
        ],
        dim=-1,
    )


def _bev_at_pose(h: int, g: float, x0: float, y0: float, yaw: float) -> Tensor:
    """(1, H, H, 4) BEV of the field seen from a vehicle at world pose (x0, y0, yaw)."""
    c = (torch.arange(h, dtype=torch.float64) - (h - 1) / 2) * g
    xe, ye = torch.meshgrid(c, c, indexing="ij")  # ego x along rows, ego y along columns
    xw = x0 + math.cos(yaw) * xe - math.sin(yaw) * ye
    yw = y0 + math.sin(yaw) * xe + math.cos(yaw) * ye
    return _field(xw, yw).float()[None]


class _InnerRadiiModel(torch.nn.Module):
    """Stand-in network: decoder = concatenation of the inner radii (ignores the unseen border),
    interactor = identity. Keeps the geometry of the real pipeline, no learning."""

    def __init__(self, cfg: ModelConfig, inner: int) -> None:
        super().__init__()
        self.config = cfg
        self.inner = inner

    def decode_polar(self, polar: Tensor) -> Tensor:
        return polar[:, :, : self.inner].flatten(2)

    def interact(self, a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
        return a, b


def test_aligned_descriptors_follow_design_pose_signs():
    h, g, t_bins, r_bins = 48, 0.5, 36, 12
    cfg = tiny_config(
        bev_height=h, bev_width=h, grid_size=g, num_angles=t_bins, num_radii=r_bins, channels=4
    )
    stub = _InnerRadiiModel(cfg, inner=6)  # radii up to 6 m; translation 2.2 m stays inside
    bev_s = _bev_at_pose(h, g, 0.0, 0.0, 0.0)
    x, y, yaw = 1.5, -1.0, 4 * 2 * math.pi / t_bins  # target pose in the source frame
    bev_t = _bev_at_pose(h, g, x, y, yaw)
    dt = stub.decode_polar(polar_sample(bev_t, t_bins, r_bins, g))
    t = torch.tensor([[x, y]])

    def cost(tr: Tensor, phi: float) -> float:
        ds, dtt = losses.aligned_descriptors(stub, bev_s, dt, tr, torch.tensor([phi]))  # type: ignore[arg-type]
        return losses.matching_cost(ds, dtt).item()

    best = cost(t, yaw)
    assert best < 0.05
    step = 2 * math.pi / t_bins
    for wrong in (-yaw, yaw + step, yaw - step, yaw + math.pi):
        assert cost(t, wrong) > 3 * best
    for wrong_t in ([[-x, -y]], [[y, x]], [[x + 1.0, y]]):
        assert cost(torch.tensor(wrong_t), yaw) > 3 * best


# --- the learned pipeline: gradients and overfitting --------------------------------------


def _triplet_batch(cfg: ModelConfig, n: int, seed: int):
    """n triplets (anchor, positive, negative) of random frames on a 4-camera rig, and the
    relative pose anchor -> positive."""
    frames = random_images(3 * n, 4, cfg.image_height, cfg.image_width, seed)
    intr, ext = make_rig(3 * n, 4, cfg.image_height, cfg.image_width)
    gen = torch.Generator().manual_seed(seed)
    translation = (torch.rand(n, 2, generator=gen) - 0.5) * 2.0
    yaw = (torch.rand(n, generator=gen) - 0.5) * 1.0
    return frames, intr, ext, translation, yaw


def _total_loss(model: VVLocNet, batch, seed: int = 0) -> dict[str, Tensor]:
    frames, intr, ext, translation, yaw = batch
    n = translation.shape[0]
    out = model.encode(frames, intr, ext)
    g = out.global_desc.view(3, n, -1)
    loc = out.local_desc.view(3, n, *out.local_desc.shape[1:])
    bev = out.bev.view(3, n, *out.bev.shape[1:])
    ds, dt = losses.aligned_descriptors(model, bev[0], loc[1], translation, yaw)
    cost_neg = losses.matching_cost(*model.interact(loc[0], loc[2]))
    return {
        "triplet": losses.triplet_loss(g[0], g[1], g[2]),
        "yaw": losses.yaw_circle_loss(ds, dt),
        "bias": losses.translation_bias_loss(model, bev[0], loc[1], translation, yaw, seed=seed),
        "hinge": losses.hinge_loss(losses.matching_cost(ds, dt), cost_neg),
    }


def test_gradients_reach_every_parameter():
    cfg = tiny_config(global_head="netvlad", encoder_layers=1)
    torch.manual_seed(0)
    model = VVLocNet(cfg)
    batch = _triplet_batch(cfg, 1, seed=1)
    # The BEV positional encoding only feeds the deformable offsets/weights, whose projections
    # start at zero (BEVFormer initialisation): its gradient is exactly zero before the first
    # update. Take one step, then every parameter must receive a gradient.
    opt = torch.optim.SGD(model.parameters(), lr=1e-2)
    for _ in range(2):
        opt.zero_grad()
        total = sum(_total_loss(model, batch).values())
        total.backward()  # type: ignore[union-attr]
        opt.step()
    dead = [
        name
        for name, p in model.named_parameters()
        if p.grad is None or not bool(p.grad.abs().sum() > 0)
    ]
    assert dead == []


def test_tiny_model_overfits_two_triplets():
    cfg = tiny_config()
    torch.manual_seed(0)
    model = VVLocNet(cfg)
    batch = _triplet_batch(cfg, 2, seed=2)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    first: dict[str, float] = {}
    for _ in range(40):
        parts = _total_loss(model, batch)
        first = first or {k: float(v.detach()) for k, v in parts.items()}
        opt.zero_grad()
        sum(parts.values()).backward()  # type: ignore[union-attr]
        opt.step()
    with torch.no_grad():
        last = {k: float(v) for k, v in _total_loss(model, batch).items()}
    assert sum(first.values()) > 0
    assert sum(last.values()) <= 0.2 * sum(first.values()), (first, last)
    for name, v0 in first.items():
        if v0 > 0:
            assert last[name] <= 0.2 * v0, (name, first, last)


# --- the near translation loss (ours) -----------------------------------------------------


def _near_setup():
    cfg = tiny_config(bev_height=12, bev_width=12, grid_size=0.5, num_angles=8, num_radii=4)
    torch.manual_seed(0)
    model = VVLocNet(cfg).eval()
    gen = torch.Generator().manual_seed(1)
    bev = torch.rand(3, 12, 12, cfg.channels, generator=gen)
    tgt = model.decode_polar(model.polar(torch.rand(3, 12, 12, cfg.channels, generator=gen)))
    t = torch.tensor([[0.8, -0.3], [0.1, 0.05], [-1.2, 0.4]])
    yaw = torch.tensor([0.2, -0.1, 0.0])
    return model, bev, tgt, t, yaw


def _cost(model, bev, tgt, t, yaw) -> Tensor:
    return losses.matching_cost(*losses.aligned_descriptors(model, bev, tgt, t, yaw))


def test_near_translation_loss_is_the_hinge_on_offsets_of_the_drawn_length():
    model, bev, tgt, t, yaw = _near_setup()
    with torch.no_grad():
        got = losses.near_translation_loss(model, bev, tgt, t, yaw, 0.1, (0.25, 1.0), seed=5)
        delta = losses.random_translation_bias(3, (0.25, 1.0), seed=5)
        assert torch.all((delta.norm(dim=1) >= 0.25) & (delta.norm(dim=1) <= 1.0))
        margin = 0.1 * delta.norm(dim=1)
        want = F.relu(
            _cost(model, bev, tgt, t, yaw) - _cost(model, bev, tgt, t + delta, yaw) + margin
        )
    torch.testing.assert_close(got, want.mean())


def test_near_translation_loss_compares_with_the_zero_translation_when_asked():
    model, bev, tgt, t, yaw = _near_setup()
    with torch.no_grad():
        got = losses.near_translation_loss(model, bev, tgt, t, yaw, 0.1, (0.25, 1.0), 1.0, seed=5)
        # every pair is picked, but the second is nearer zero than 0.25 m: it keeps its offset
        delta = losses.random_translation_bias(3, (0.25, 1.0), seed=5)
        other = torch.stack([-t[0], delta[1], -t[2]])
        margin = 0.1 * other.norm(dim=1)
        want = F.relu(
            _cost(model, bev, tgt, t, yaw) - _cost(model, bev, tgt, t + other, yaw) + margin
        )
    torch.testing.assert_close(got, want.mean())


@pytest.mark.parametrize(
    ("kw", "match"), [({"slope": -0.1}, "slope"), ({"zero_share": 1.5}, "zero_share")]
)
def test_near_translation_loss_refuses_bad_settings(kw, match):
    model, bev, tgt, t, yaw = _near_setup()
    with pytest.raises(ValueError, match=match):
        losses.near_translation_loss(model, bev, tgt, t, yaw, **kw)


def test_losses_refuse_shapes_that_would_broadcast():
    a = F.normalize(torch.rand(4, 8), dim=-1)
    with pytest.raises(ValueError, match="anchor, positive"):
        losses.triplet_loss(a, a[:1], a)
    with pytest.raises(ValueError, match="negative"):
        losses.triplet_loss(a, a, a[:, :4])
    assert losses.triplet_loss(a, a, torch.stack([a, a], 1)).item() == pytest.approx(0.1)
    d = F.normalize(torch.rand(3, 6, 4), dim=-1)
    with pytest.raises(ValueError, match="src, tgt"):
        losses.yaw_circle_loss(d, d[:1])
    # one yaw for a batch of three pairs (it turned every pair by the first pair's yaw)
    bev = torch.zeros(3, 4, 4, 2)
    for yaw in (torch.zeros(1), torch.tensor(0.5), torch.zeros(3, 1)):
        with pytest.raises(ValueError, match=r"yaw: expected shape \(3,\), one per pair"):
            losses.aligned_descriptors(
                types.SimpleNamespace(config=None),  # type: ignore[arg-type]
                bev,
                d,
                torch.zeros(3, 2),
                yaw,
            )


def test_losses_name_inputs_they_cannot_use():
    import numpy as np

    a = torch.randn(3, 5, 4)
    # a (T, C) target was broadcast against (P, T, C) without a word
    with pytest.raises(ValueError, match=r"^a, b: expected two \(\.\.\., T, C\) tensors"):
        losses.matching_cost(a, a[0])
    with pytest.raises(ValueError, match=r"^a, b: "):
        losses.matching_cost(torch.randn(4), torch.randn(4))  # a scalar came back
    with pytest.raises(TypeError, match=r"^a: expected a torch.Tensor, got ndarray"):
        losses.matching_cost(np.ones((2, 3)), np.ones((2, 3)))
    with pytest.raises(ValueError, match=r"^src, tgt: expected two \(P, T, C\)"):
        losses.roll_min_cost(a[0], a[0])  # a 0-d tensor came back
    with pytest.raises(TypeError, match=r"^src: expected a torch.Tensor"):
        losses.yaw_circle_loss(np.ones((2, 6, 4)), np.ones((2, 6, 4)))
    with pytest.raises(TypeError, match=r"^pos_dist: expected a torch.Tensor"):
        losses.hinge_loss(np.ones(3), np.ones(3))
    with pytest.raises(TypeError, match=r"^anchor: expected a torch.Tensor"):
        losses.triplet_loss(np.ones((2, 3)), torch.ones(2, 3), torch.ones(2, 3))
    with pytest.raises(ValueError, match=r"^n: expected an int >= 0, got -1"):
        losses.random_translation_bias(-1)
    with pytest.raises(TypeError, match=r"^n: "):
        losses.random_translation_bias(2.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^bias_range: expected 0 <= low <= high"):
        losses.random_translation_bias(2, (3.0, 1.0))
    # a range of three values or a bare number, a seed torch would truncate or wrap
    with pytest.raises(ValueError, match=r"^bias_range: expected \(low, high\) metres, got 3"):
        losses.random_translation_bias(2, (1.0, 2.0, 3.0))  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"^bias_range: expected \(low, high\) metres, got 2.0"):
        losses.random_translation_bias(2, 2.0)  # type: ignore[arg-type]
    for seed, err in ((1.5, TypeError), (-1, ValueError), (2**64, ValueError)):
        with pytest.raises(err, match=r"^seed: expected an int"):
            losses.random_translation_bias(2, seed=seed)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^n: expected an int <= "):
        losses.random_translation_bias(2**62)
    # what they take still works, and the unchecked broadcast inside roll_min_cost too
    assert losses.matching_cost(a, a).shape == (3,)
    assert losses.roll_min_cost(a, a).shape == (3,)
    assert losses.random_translation_bias(0).shape == (0, 2)
