"""Training losses of VVLoc, with the paper's constants as defaults.

* :func:`triplet_loss` — global descriptors (margin 0.1).
* :func:`hinge_loss` — separate positive and negative distances/costs (margins 0.1 and 0.2).
* :func:`yaw_circle_loss` — circle-style loss on aligned local descriptors (γ = 40, ϑp = 0.1,
  ϑn = 1.4); :func:`yaw_matching_loss` builds the aligned pair from a source BEV, the ground-truth
  relative pose and the target's local descriptor.
* :func:`translation_bias_loss` — the matching cost at the true translation must beat a randomly
  biased translation by a margin (0.1).
* :func:`near_translation_loss` — ours, not the paper's (off unless ``tbias_near_weight`` > 0):
  the same for nearby translations (0.25-1 m off), with a margin proportional to the offset.
* :func:`rerank_loss` — ours, not the paper's (off unless ``rerank_weight`` > 0): the re-ranking
  cost of the anchor against its positive must beat its cost against the negative by a margin.

Poses follow DESIGN.md §3: ξ_{s→t} = (x, y, φ) is the target pose in the source frame; padding the
source BEV with t = (x, y) re-centres it at the target origin and Dt ≈ ρ(Ds, φ·T/2π).
Every loss returns a scalar tensor (mean over the batch) and is exactly zero when all margins are
met.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor

from vvloc._checks import finite_float, positive_int
from vvloc.nets.polar import bev_pad, float_tensor, polar_sample, roll_interp

__all__ = [
    "aligned_descriptors",
    "hinge_loss",
    "matching_cost",
    "near_translation_loss",
    "random_translation_bias",
    "rerank_loss",
    "roll_min_cost",
    "translation_bias_loss",
    "triplet_loss",
    "yaw_circle_loss",
    "yaw_matching_loss",
]

if TYPE_CHECKING:
    from vvloc.nets.model import VVLocNet


def _tensors(**named: object) -> None:
    """``TypeError`` naming the first argument of ``named`` that is not a floating-point
    tensor."""
    for name, x in named.items():
        float_tensor(x, name, "")


def _pairs(a: Tensor, b: Tensor, names: str, shape: str, ndim: int | None = None) -> None:
    """``TypeError``/``ValueError`` naming ``names`` unless ``a`` and ``b`` are floating-point
    tensors of one ``shape`` (``ndim`` axes, or at least 2), T, C >= 1."""
    first, second = names.split(", ")
    _tensors(**{first: a, second: b})
    if (
        a.shape != b.shape
        or (a.ndim != ndim if ndim is not None else a.ndim < 2)
        or min(a.shape[-2:], default=0) < 1
    ):
        raise ValueError(
            f"{names}: expected two {shape} tensors of one shape, T, C >= 1, got "
            f"{tuple(a.shape)} and {tuple(b.shape)}"
        )


def _pairwise_distance(a: Tensor, b: Tensor) -> Tensor:
    """Euclidean distances (..., n, m) between rows of a (..., n, C) and b (..., m, C); the
    square root is taken of a value clamped at 1e-12 so the gradient stays finite at 0."""
    sq = (
        (a * a).sum(-1)[..., :, None]
        + (b * b).sum(-1)[..., None, :]
        - 2.0 * a @ b.transpose(-1, -2)
    )
    return sq.clamp(min=1e-12).sqrt()


def matching_cost(a: Tensor, b: Tensor) -> Tensor:
    """δ(A, B) = (1/T)·Σᵢ ‖Aᵢ − Bᵢ‖₂ (not squared), DESIGN.md §3: (..., T, C) × 2 → (...),
    both of one shape (no broadcasting)."""
    _pairs(a, b, "a, b", "(..., T, C)")
    return _cost(a, b)


def _cost(a: Tensor, b: Tensor) -> Tensor:
    """:func:`matching_cost` unchecked, broadcasting ``a`` and ``b`` (the losses' own use)."""
    return (a - b).pow(2).sum(-1).clamp(min=1e-12).sqrt().mean(-1)


def triplet_loss(anchor: Tensor, positive: Tensor, negative: Tensor, margin: float = 0.1) -> Tensor:
    """Triplet margin loss on L2-normalised global descriptors.

    anchor, positive (B, Dg); negative (B, Dg) or (B, K, Dg) (K negatives per anchor).
    L = mean over (b, k) of max(0, ‖a − p‖₂ − ‖a − n_k‖₂ + margin); 0 for no triplet (B = 0 or
    K = 0), as :func:`hinge_loss` gives for an empty tensor.
    """
    _tensors(anchor=anchor, positive=positive, negative=negative)
    if anchor.ndim != 2 or positive.shape != anchor.shape:
        raise ValueError(
            f"anchor, positive: expected two (B, Dg) tensors of one shape, got "
            f"{tuple(anchor.shape)} and {tuple(positive.shape)}"
        )
    if negative.ndim == anchor.ndim:
        negative = negative[:, None]
    if (
        negative.ndim != 3
        or negative.shape[0] != anchor.shape[0]
        or (negative.shape[2] != anchor.shape[1])
    ):
        raise ValueError(
            f"negative: expected shape {tuple(anchor.shape)} or ({anchor.shape[0]}, K, "
            f"{anchor.shape[1]}), got {tuple(negative.shape)}"
        )
    d_pos = (anchor - positive).norm(dim=-1)  # (B,)
    d_neg = (anchor[:, None] - negative).norm(dim=-1)  # (B, K)
    terms = F.relu(d_pos[:, None] - d_neg + margin)
    return terms.mean() if terms.numel() else terms.sum()  # no triplet: 0, not mean()'s nan


def hinge_loss(
    pos_dist: Tensor, neg_dist: Tensor, pos_margin: float = 0.1, neg_margin: float = 0.2
) -> Tensor:
    """Double hinge: pull positive distances/costs below ``pos_margin`` and push negative ones
    above ``neg_margin``: mean(max(0, d⁺ − pos_margin)) + mean(max(0, neg_margin − d⁻))
    (defaults 0.1 and 0.2).

    ``pos_dist`` and ``neg_dist`` are any-shape tensors of distances (e.g. yaw-matching costs
    :func:`matching_cost` of positive and negative pairs); an empty tensor contributes 0.
    """
    _tensors(pos_dist=pos_dist, neg_dist=neg_dist)
    pos = F.relu(pos_dist - pos_margin)
    neg = F.relu(neg_margin - neg_dist)
    zero = pos_dist.new_zeros(())
    return (pos.mean() if pos.numel() else zero) + (neg.mean() if neg.numel() else zero)


def yaw_circle_loss(
    src: Tensor, tgt: Tensor, gamma: float = 40.0, theta_p: float = 0.1, theta_n: float = 1.4
) -> Tensor:
    """Circle-style matching loss between aligned local descriptors (P, T, C) (rows normalised).

    δ_ij = ‖src_i − tgt_j‖₂. Row i of the source is the positive of target row i (δ_ii should be
    < ϑp); every other target row j ≠ i is a negative (δ_ij should be > ϑn). Following circle
    loss's self-paced weighting, the logits are
        s_p = γ·α_p·(δ_ii − ϑp),  α_p = max(0, δ_ii − ϑp) (detached),
        s_n = γ·α_n·(ϑn − δ_ij),  α_n = max(0, ϑn − δ_ij) (detached),
    so the paper's squared terms max(0, δ − ϑ)² appear with the weight treated as a constant, and
        Lᵢ = log(1 + exp(s_p)·Σ_{j≠i} exp(s_n,ij)) − log T.
    Subtracting the floor log T (all logits 0 ⇒ log(1 + (T − 1))) makes a row whose margins are all
    met contribute exactly 0 without changing any gradient. Returns the mean over (P, T), 0 for
    P = 0.
    """
    _pairs(src, tgt, "src, tgt", "(P, T, C)", 3)
    _p, t, _ = src.shape
    dist = _pairwise_distance(src, tgt)  # (P, T, T)
    eye = torch.eye(t, dtype=torch.bool, device=src.device)
    d_pos = dist.diagonal(dim1=-2, dim2=-1)  # (P, T)
    alpha_p = F.relu(d_pos - theta_p).detach()
    alpha_n = F.relu(theta_n - dist).detach()
    s_p = gamma * alpha_p * (d_pos - theta_p)
    s_n = (gamma * alpha_n * (theta_n - dist)).masked_fill(eye, float("-inf"))
    row = (F.softplus(s_p + torch.logsumexp(s_n, dim=-1)) - math.log(t)).clamp(min=0.0)
    return row.mean() if row.numel() else row.sum()  # no pair: 0, not mean()'s nan


def aligned_descriptors(
    model: VVLocNet,
    bev_src: Tensor,
    local_tgt: Tensor,
    translation: Tensor,
    yaw: Tensor,
) -> tuple[Tensor, Tensor]:
    """Source BEV padded with ``translation``, polar-sampled, decoded, rolled by ``yaw``, and
    passed through the interactor with the target descriptor.

    bev_src (B, H, W, C); local_tgt (B, T, C); translation (B, 2) metres and yaw (B,) radians:
    the relative pose ξ_{s→t}. The roll is ρ(Ds, φ·T/2π) (DESIGN.md §3). Returns (Ds', Dt')
    (B, T, C), rows L2-normalised; at the true pose row i of each should describe the same view.
    """
    cfg = model.config
    if tuple(torch.as_tensor(yaw).shape) != (bev_src.shape[0],):  # one yaw would fit all pairs
        raise ValueError(
            f"yaw: expected shape ({bev_src.shape[0]},), one per pair, got "
            f"{tuple(torch.as_tensor(yaw).shape)}"
        )
    padded = bev_pad(bev_src, translation, cfg.grid_size)
    ds = model.decode_polar(polar_sample(padded, cfg.num_angles, cfg.num_radii, cfg.grid_size))
    shift = torch.as_tensor(yaw, dtype=torch.float64, device=ds.device) * (
        cfg.num_angles / (2.0 * math.pi)
    )
    return model.interact(roll_interp(ds, shift, dim=1), local_tgt)


def yaw_matching_loss(
    model: VVLocNet,
    bev_src: Tensor,
    local_tgt: Tensor,
    translation: Tensor,
    yaw: Tensor,
    gamma: float = 40.0,
    theta_p: float = 0.1,
    theta_n: float = 1.4,
) -> Tensor:
    """:func:`yaw_circle_loss` on :func:`aligned_descriptors` at the ground-truth pose."""
    ds, dt = aligned_descriptors(model, bev_src, local_tgt, translation, yaw)
    return yaw_circle_loss(ds, dt, gamma, theta_p, theta_n)


def random_translation_bias(
    n: int, bias_range: tuple[float, float] = (1.0, 3.0), seed: int = 0
) -> Tensor:
    """n random 2-D offsets (n, 2) float32 metres: uniform direction, length uniform in
    ``bias_range`` (0 <= low <= high, finite), drawn from a generator seeded with ``seed``."""
    n = positive_int(n, "n", minimum=0, maximum=2**40)  # 16 TiB of offsets: a mistake
    if isinstance(bias_range, (str, bytes)) or not hasattr(bias_range, "__len__"):
        raise TypeError(f"bias_range: expected (low, high) metres, got {bias_range!r:.60}")
    if len(bias_range) != 2:
        raise ValueError(f"bias_range: expected (low, high) metres, got {len(bias_range)} values")
    lo, hi = (finite_float(v, "bias_range") for v in bias_range)
    if not 0.0 <= lo <= hi:
        raise ValueError(f"bias_range: expected 0 <= low <= high metres, got {bias_range}")
    # torch seeds with a uint64; 1.5 was truncated to 1, -1 taken as 2**64 - 1
    gen = torch.Generator().manual_seed(positive_int(seed, "seed", minimum=0, maximum=2**64 - 1))
    ang = torch.rand(n, generator=gen, dtype=torch.float64) * (2.0 * math.pi)
    mag = lo + (hi - lo) * torch.rand(n, generator=gen, dtype=torch.float64)
    return torch.stack([mag * ang.cos(), mag * ang.sin()], -1).to(torch.float32)


def translation_bias_loss(
    model: VVLocNet,
    bev_src: Tensor,
    local_tgt: Tensor,
    translation: Tensor,
    yaw: Tensor,
    margin: float = 0.1,
    bias_range: tuple[float, float] = (1.0, 3.0),
    seed: int = 0,
) -> Tensor:
    """The matching cost at the true translation must be lower, by ``margin``, than at a
    randomly biased one t + Δ (Δ from :func:`random_translation_bias`, seeded, same yaw):
    L = mean(max(0, c(t) − c(t + Δ) + margin)), c = :func:`matching_cost` of
    :func:`aligned_descriptors`. The range of |Δ| (metres) is our choice; the paper does not
    state it."""
    t = torch.as_tensor(translation, dtype=torch.float32, device=bev_src.device)
    delta = random_translation_bias(t.shape[0], bias_range, seed).to(t.device)
    return _offset_hinge(model, bev_src, local_tgt, t, yaw, delta, margin)


def _offset_hinge(
    model: VVLocNet,
    bev_src: Tensor,
    local_tgt: Tensor,
    t: Tensor,
    yaw: Tensor,
    delta: Tensor,
    margin: float | Tensor,
) -> Tensor:
    """mean(max(0, c(t) − c(t + Δ) + margin)): translations t and offsets Δ (B, 2) metres,
    ``margin`` a float or (B,); c = :func:`matching_cost` of :func:`aligned_descriptors`."""
    cost_true = _cost(*aligned_descriptors(model, bev_src, local_tgt, t, yaw))
    cost_bias = _cost(*aligned_descriptors(model, bev_src, local_tgt, t + delta, yaw))
    return F.relu(cost_true - cost_bias + margin).mean()


def near_translation_loss(
    model: VVLocNet,
    bev_src: Tensor,
    local_tgt: Tensor,
    translation: Tensor,
    yaw: Tensor,
    slope: float = 0.1,
    bias_range: tuple[float, float] = (0.25, 1.0),
    zero_share: float = 0.0,
    seed: int = 0,
) -> Tensor:
    """Ours, not the paper's: the matching cost at the true translation t must be lower than at
    a nearby t + Δ by a margin proportional to the offset:
    L = mean(max(0, c(t) − c(t + Δ) + slope·‖Δ‖)), ``slope`` in cost per metre, Δ from
    :func:`random_translation_bias` with ‖Δ‖ in ``bias_range`` (metres, seeded, same yaw).
    With ``zero_share`` > 0 that share of the pairs (every k-th, k = round(1 / zero_share)),
    when ‖t‖ ≥ ``bias_range[0]``, is compared with the zero translation instead (Δ = −t).

    Why: :func:`translation_bias_loss` only asks the truth to beat hypotheses 1-3 m off, so
    nothing ranks the last metre around the minimum, where the metric pose's error lives; and
    the zero translation is the one hypothesis whose padded BEV has no padded border (it looks
    most like the unpadded target), which no training pair shows as wrong unless asked.
    """
    if not slope >= 0:
        raise ValueError(f"slope: expected >= 0, got {slope!r}")
    if not 0.0 <= zero_share <= 1.0:
        raise ValueError(f"zero_share: expected a value in [0, 1], got {zero_share!r}")
    t = torch.as_tensor(translation, dtype=torch.float32, device=bev_src.device)
    delta = random_translation_bias(t.shape[0], bias_range, seed).to(t.device)
    if zero_share > 0:
        every = max(1, round(1.0 / zero_share))
        pick = (torch.arange(t.shape[0], device=t.device) % every == 0) & (
            t.norm(dim=1) >= bias_range[0]
        )
        delta = torch.where(pick[:, None], -t, delta)
    return _offset_hinge(model, bev_src, local_tgt, t, yaw, delta, slope * delta.norm(dim=1))


def roll_min_cost(src: Tensor, tgt: Tensor) -> Tensor:
    """Lowest matching cost over the T integer rolls of pairs (P, T, C) → (P,):
    min_k δ(ρ(src, k), tgt), ρ(D, k)[i] = D[(i − k) mod T] (DESIGN.md §3).

    This is the re-ranking cost (:func:`vvloc.kernels.rerank`) without its sub-bin refinement:
    the kernel minimises over real shifts, a superset of these, so its cost is at most this one.
    The gradient flows through the best roll only."""
    _pairs(src, tgt, "src, tgt", "(P, T, C)", 3)
    t = src.shape[1]
    k = torch.arange(t, device=src.device)
    rolled = src[:, (k[None, :] - k[:, None]) % t]  # (P, K, T, C): row k is ρ(src, k)
    return _cost(rolled, tgt[:, None]).min(dim=-1).values


def rerank_loss(
    model: VVLocNet,
    local_anchor: Tensor,
    local_pos: Tensor,
    local_neg: Tensor,
    margin: float = 0.1,
) -> Tensor:
    """Re-ranking loss (ours; the paper trains no such term): the anchor's re-ranking cost
    against its positive must be lower, by ``margin``, than against its negative.

    local_anchor, local_pos, local_neg (B, T, C) local-view descriptors (the anchor is the
    query, the others map keyframes, as in :meth:`vvloc.Localizer.rerank`: the
    interactor on the unpadded pair, then the lowest cost over yaw rolls,
    :func:`roll_min_cost`). L = mean(max(0, c(a, p) − c(a, n) + margin)).

    Why: the yaw and translation-bias losses only see positive pairs at or near their true
    pose, so nothing in the paper's losses asks the cost of a wrong place to be high, yet
    re-ranking orders candidates by exactly that cost."""
    cost_pos = roll_min_cost(*model.interact(local_anchor, local_pos))
    cost_neg = roll_min_cost(*model.interact(local_anchor, local_neg))
    return F.relu(cost_pos - cost_neg + margin).mean()
