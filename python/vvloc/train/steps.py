"""The losses of one training step: :func:`global_losses` (triplet + hinge, stages 1-2 and the
head stage), :func:`training_losses` (a stage 1-2 step), the local stage's near translation loss
(:func:`near_losses`) and its seed stream (:func:`near_seed`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from vvloc import geometry
from vvloc.losses import (
    hinge_loss,
    near_translation_loss,
    rerank_loss,
    translation_bias_loss,
    triplet_loss,
    yaw_matching_loss,
)
from vvloc.nets import VVLocNet
from vvloc.train.config import TrainConfig


@dataclass
class StepLosses:
    """Loss values of one step (floats; zero where a loss is not active in the stage)."""

    total: float
    triplet: float
    hinge: float
    yaw: float
    tbias: float
    rerank: float
    violated: int
    tbias_near: float = 0.0


def global_losses(
    g: torch.Tensor, cfg: TrainConfig
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The global-descriptor losses of triplets ``g`` (3, B, Dg) (anchor, positive, negative
    descriptors): (triplet loss, hinge loss, correct (B,) bool); a triplet is correct for
    hard mining when ‖g_a − g_p‖ + margin < ‖g_a − g_n‖.

    The terms are built in this order (triplet, then the distances and the hinge) on purpose:
    autograd sums the gradients of ``g`` in the reverse order of the graph, so another order
    changes the weights' last bits, and over a training run the weights themselves; this is
    the order that trained the committed models' steps since 2026-12-02
    (models/synth-small-v3/MODEL_CARD.md)."""
    l_tri = triplet_loss(g[0], g[1], g[2], cfg.triplet_margin)
    d_pos = (g[0] - g[1]).norm(dim=-1)
    d_neg = (g[0] - g[2]).norm(dim=-1)
    l_hinge = hinge_loss(d_pos, d_neg, cfg.hinge_pos, cfg.hinge_neg)
    return l_tri, l_hinge, (d_pos + cfg.triplet_margin < d_neg).detach()


def training_losses(
    model: VVLocNet,
    batch: dict[str, torch.Tensor],
    cfg: TrainConfig,
    stage: int,
    step: int,
    device: torch.device,
) -> tuple[torch.Tensor, StepLosses, np.ndarray]:
    """Forward one batch of B triplets and return (total loss, its parts, correct mask (B,)).

    The three frames of each triplet are encoded in one call (3B samples). Stage 1 uses the
    triplet and hinge losses of the global descriptors; stage 2 adds the yaw matching loss and
    the translation bias loss (weights ``yaw_weight``, ``tbias_weight``) on (anchor, positive)
    with the ground-truth relative pose ξ_{a→p} (with ``tbias_near_weight`` > 0 also the near
    translation loss, :func:`near_losses`), and, when ``rerank_weight`` > 0, the
    re-ranking loss on (anchor, positive, negative). A triplet is "correct" for hard mining when
    ‖g_a − g_p‖ + margin < ‖g_a − g_n‖.
    """
    images = batch["images"].to(device)  # (B, 3, M, 3, H, W)
    b = images.shape[0]
    flat = lambda x: x.to(device).transpose(0, 1).reshape(3 * b, *x.shape[2:])  # noqa: E731
    out = model.encode(flat(images), flat(batch["intrinsics"]), flat(batch["cam_to_ego"]))
    l_tri, l_hinge, correct_t = global_losses(out.global_desc.view(3, b, -1), cfg)
    total = l_tri + l_hinge
    l_yaw = torch.zeros((), device=device)
    l_tb = torch.zeros((), device=device)
    l_rr = torch.zeros((), device=device)
    l_near = torch.zeros((), device=device)
    if stage == 2:
        poses = batch["poses"].numpy()
        xi = geometry.relative(poses[:, 0], poses[:, 1])  # (B, 3): positive in anchor frame
        t = torch.as_tensor(xi[:, :2], dtype=torch.float32, device=device)
        yaw = torch.as_tensor(xi[:, 2], dtype=torch.float32, device=device)
        bev = out.bev.view(3, b, *out.bev.shape[1:])
        loc = out.local_desc.view(3, b, *out.local_desc.shape[1:])
        # Written out here and in Trainer.local_losses on purpose: the same calls made through
        # one shared function gave the same forward values but gradients that differ in the
        # last bits (2026-12-04, stage 2 of configs/synth-small-rerank.yaml: step 1's joint
        # epochs parted from the committed run), so `make model` no longer retrained
        # models/synth-small's bytes. Check that before refactoring this path.
        l_yaw = yaw_matching_loss(
            model, bev[0], loc[1], t, yaw, cfg.yaw_gamma, cfg.yaw_theta_p, cfg.yaw_theta_n
        )
        l_tb = translation_bias_loss(
            model, bev[0], loc[1], t, yaw, margin=cfg.tbias_margin, seed=cfg.seed * 1_000_003 + step
        )
        total = total + cfg.yaw_weight * l_yaw + cfg.tbias_weight * l_tb
        if cfg.tbias_near_weight > 0:  # only when on, like the re-ranking loss below
            l_near = near_losses(model, bev[0], loc[1], t, yaw, cfg, step)
            total = total + cfg.tbias_near_weight * l_near
        if cfg.rerank_weight > 0:  # only when on: any extra term would move the committed weights
            l_rr = rerank_loss(model, loc[0], loc[1], loc[2], cfg.rerank_margin)
            total = total + cfg.rerank_weight * l_rr
    correct = correct_t.cpu().numpy()
    parts = StepLosses(
        total=float(total.detach()),
        triplet=float(l_tri.detach()),
        hinge=float(l_hinge.detach()),
        yaw=float(l_yaw.detach()),
        tbias=float(l_tb.detach()),
        rerank=float(l_rr.detach()),
        violated=int((~correct).sum()),
        tbias_near=float(l_near.detach()),
    )
    return total, parts, correct


def near_losses(
    model: VVLocNet,
    bev_src: torch.Tensor,
    local_tgt: torch.Tensor,
    translation: torch.Tensor,
    yaw: torch.Tensor,
    cfg: TrainConfig,
    step: int,
) -> torch.Tensor:
    """:func:`vvloc.losses.near_translation_loss` with the config's ``tbias_near_*`` settings,
    seeded by the run's seed and ``step``: source BEVs (B, H, W, C), target local-view
    descriptors (B, T, C), ground-truth ξ_{s→t} translation (B, 2) metres and yaw (B,) radians."""
    lo, hi = (float(v) for v in cfg.tbias_near_range)
    return near_translation_loss(
        model,
        bev_src,
        local_tgt,
        translation,
        yaw,
        slope=float(cfg.tbias_near_slope),
        bias_range=(lo, hi),
        zero_share=float(cfg.tbias_near_zero),
        seed=near_seed(cfg.seed, step),
    )


def near_seed(seed: int, step: int) -> int:
    """The generator seed of :func:`near_losses` at ``step`` of a run seeded ``seed``: a stream
    of its own, 63 bits of numpy's ``SeedSequence([seed, step, 1])``. The translation-bias loss
    keeps ``seed · 1 000 003 + step``; until 2026-12-05 the near loss used ``seed · 1 000 033 +
    step``, which at seed 0 is the same number, so each pair's near offset was a rescaled copy
    of its bias offset (``models/synth-small/HISTORY.md``, "Step 5 again")."""
    hi, lo = np.random.SeedSequence([seed, step, 1]).generate_state(2, np.uint32)
    return (int(hi) << 31) | (int(lo) >> 1)
