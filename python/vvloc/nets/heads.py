"""Global descriptor heads over the polar BEV (B, T, R, C) → (B, Dg), L2-normalised.

Each head pools over every polar cell, so it is invariant to circular shifts along the angle axis
(a yaw rotation of the vehicle): GeM and NetVLAD because they sum over cells, DiSCO because the
magnitude of a 2-D DFT ignores circular shifts.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from vvloc.nets.config import ModelConfig
from vvloc.nets.polar import float_tensor


def _check_polar(polar: Tensor, channels: int) -> None:
    """``TypeError``/``ValueError`` naming ``polar`` unless it is a floating-point tensor
    (B, T, R, C) with C = ``channels`` (the model's) and T, R >= 1."""
    float_tensor(polar, "polar", "(B, T, R, C)")
    if polar.ndim != 4 or polar.shape[-1] != channels or min(polar.shape[1:3]) < 1:
        raise ValueError(
            f"polar: expected shape (B, T, R, {channels}), T, R >= 1, got {tuple(polar.shape)}"
        )


class GeMHead(nn.Module):
    """Generalised-mean pooling with a learnable exponent p (init ``cfg.gem_p`` = 3): Dg = C."""

    def __init__(self, cfg: ModelConfig, eps: float = 1e-6) -> None:
        super().__init__()
        self.p = nn.Parameter(torch.tensor(float(cfg.gem_p)))
        self.eps = eps
        self.out_dim = cfg.channels

    def forward(self, polar: Tensor) -> Tensor:
        """Polar BEV (B, T, R, C) → global descriptors (B, C), unit L2 norm."""
        _check_polar(polar, self.out_dim)
        x = polar.clamp(min=self.eps).pow(self.p).mean(dim=(1, 2)).pow(1.0 / self.p)
        return F.normalize(x, dim=-1)


class NetVLADHead(nn.Module):
    """NetVLAD with K clusters: soft assignment, residual aggregation, intra-normalisation,
    global L2, optional linear projection to ``global_dim`` (0 = none) and a final L2.

    Dg = global_dim if > 0 else K·C.
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        k, c = cfg.netvlad_clusters, cfg.channels
        self.assign = nn.Linear(c, k)
        self.centroids = nn.Parameter(torch.rand(k, c))
        self.proj: nn.Linear | None = nn.Linear(k * c, cfg.global_dim) if cfg.global_dim else None
        self.out_dim = cfg.global_dim or k * c

    @torch.no_grad()
    def init_from_features(
        self, cells: Tensor, iterations: int = 20, alpha: float = 10.0, seed: int = 0
    ) -> None:
        """Data-driven initialisation: spherical k-means (k-means++ seeding) of ``cells`` (P, C)
        polar-cell features (any scale; L2-normalised here) gives the K centroids, and the soft
        assignment starts as ``alpha`` · cosine similarity to them (bias 0). Seeded; P ≥ K."""
        k = self.centroids.shape[0]
        # on the CPU: the same seeded result on every device (the generator is a CPU one)
        x = F.normalize(cells.detach().float().cpu().reshape(-1, cells.shape[-1]), dim=-1)
        if x.shape[0] < k:
            raise ValueError(f"cells: expected at least {k} rows (clusters), got {x.shape[0]}")
        gen = torch.Generator().manual_seed(seed)
        # k-means++ seeding: each next centroid drawn in proportion to its cosine distance
        c = x[torch.randint(x.shape[0], (1,), generator=gen)].clone()
        for _ in range(1, k):
            far = (1.0 - (x @ c.T).max(dim=1).values).clamp(min=0.0) + 1e-12
            c = torch.cat([c, x[torch.multinomial(far, 1, generator=gen)]])
        for _ in range(iterations):
            assign = (x @ c.T).argmax(dim=1)
            for j in range(k):
                members = x[assign == j]
                if len(members):
                    c[j] = F.normalize(members.mean(dim=0), dim=0)
        self.centroids.copy_(c.to(self.centroids))
        self.assign.weight.copy_((alpha * c).to(self.assign.weight))
        self.assign.bias.zero_()

    def forward(self, polar: Tensor) -> Tensor:
        """Polar BEV (B, T, R, C) → global descriptors (B, Dg), unit L2 norm."""
        _check_polar(polar, self.centroids.shape[1])
        x = F.normalize(polar.flatten(1, 2), dim=-1)  # (B, N, C)
        a = self.assign(x).softmax(dim=-1)  # (B, N, K)
        vlad = a.transpose(1, 2) @ x - a.sum(dim=1)[..., None] * self.centroids  # (B, K, C)
        vlad = F.normalize(F.normalize(vlad, dim=-1).flatten(1), dim=-1)
        if self.proj is not None:
            vlad = F.normalize(self.proj(vlad), dim=-1)
        return vlad


class DiscoHead(nn.Module):
    """DiSCO-style: 1-channel projection → |2-D DFT| (orthonormal) over (T, R) → fftshift →
    central crop (ct, cr) → flatten → L2. Dg = ct·cr. Invariant to circular angle shifts."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.proj = nn.Linear(cfg.channels, 1)
        self.crop = cfg.disco_crop
        self.out_dim = cfg.disco_crop[0] * cfg.disco_crop[1]

    def forward(self, polar: Tensor) -> Tensor:
        """Polar BEV (B, T, R, C) → global descriptors (B, ct·cr), unit L2 norm; T >= ct and
        R >= cr (the crop)."""
        _check_polar(polar, self.proj.in_features)
        ct, cr = self.crop
        if polar.shape[1] < ct or polar.shape[2] < cr:
            raise ValueError(
                f"polar: expected T >= {ct} and R >= {cr} (the DiSCO crop), got "
                f"{tuple(polar.shape)}"
            )
        x = self.proj(polar).squeeze(-1)  # (B, T, R)
        spec = torch.fft.fftshift(torch.fft.fft2(x, norm="ortho").abs(), dim=(1, 2))
        t, r = x.shape[1:]
        t0, r0 = t // 2 - ct // 2, r // 2 - cr // 2
        return F.normalize(spec[:, t0 : t0 + ct, r0 : r0 + cr].flatten(1), dim=-1)


def make_global_head(cfg: ModelConfig) -> nn.Module:
    """The head selected by ``cfg.global_head`` ("gem" | "netvlad" | "disco")."""
    heads: dict[str, type[nn.Module]] = {"gem": GeMHead, "netvlad": NetVLADHead, "disco": DiscoHead}
    return heads[cfg.global_head](cfg)
