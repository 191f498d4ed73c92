"""Local-view descriptor decoder (RASA + radial merge) and the interactor (TASA + MHCA)."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

from vvloc.nets.attention import (
    CrossAttentionLayer,
    RelativeAttentionLayer,
    angular_embedding,
    radial_embedding,
)
from vvloc.nets.config import ModelConfig


class LocalViewDecoder(nn.Module):
    """Polar BEV (N, T, R, C) → local-view descriptor D (N, T, C).

    RASA layers attend along the R radial samples of each angle independently (relative radial
    embedding, σ_r), then an MLP merges the R features of an angle into one C-dim row. Every
    operation is per angle, so rolling the input along T rolls the output by the same amount.
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c, r = cfg.channels, cfg.num_radii
        self.layers = nn.ModuleList(
            RelativeAttentionLayer(c, cfg.decoder_heads, cfg.dropout)
            for _ in range(cfg.decoder_layers)
        )
        rel = radial_embedding(r, cfg.max_radius, cfg.sigma_r, c)
        self.register_buffer("rel", rel, persistent=False)
        self.merge = nn.Sequential(nn.Linear(r * c, c), nn.ReLU(inplace=True), nn.Linear(c, c))
        self.shape = (cfg.num_angles, r, c)

    def forward(self, polar: Tensor) -> Tensor:
        """Local-view descriptors (N, T, C) of polar BEVs ``polar`` (N, T, R, C), in the
        module's dtype (float32 unless converted); each angle row is decoded alone."""
        if polar.ndim != 4 or tuple(polar.shape[1:]) != self.shape:
            raise ValueError(
                f"polar: expected shape (N, {', '.join(map(str, self.shape))}), "
                f"got {tuple(polar.shape)}"
            )
        n, t, r, c = polar.shape
        x = polar.reshape(n * t, r, c)
        for layer in self.layers:
            x = layer(x, self.rel)
        return self.merge(x.reshape(n, t, r * c))


class Interactor(nn.Module):
    """(Ds, Dt) (P, T, C) → (Ds', Dt') with L2-normalised rows.

    Each round applies TASA (self-attention over the T angle bins with the circular angular
    embedding, σ_a) to each side with shared weights, then multi-head cross-attention both ways
    (source attends to target and target to source, simultaneously, shared weights). Exactly
    equivariant to circular shifts of either side's angle axis.
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c = cfg.channels
        self.tasa = nn.ModuleList(
            RelativeAttentionLayer(c, cfg.interactor_heads, cfg.dropout)
            for _ in range(cfg.interactor_rounds)
        )
        self.cross = nn.ModuleList(
            CrossAttentionLayer(c, cfg.interactor_heads, cfg.dropout)
            for _ in range(cfg.interactor_rounds)
        )
        rel = angular_embedding(cfg.num_angles, cfg.sigma_a, c)
        self.register_buffer("rel", rel, persistent=False)
        self.shape = (cfg.num_angles, c)

    def _check(self, name: str, d: Tensor) -> None:
        if d.ndim != 3 or tuple(d.shape[1:]) != self.shape:
            raise ValueError(
                f"{name}: expected shape (P, {self.shape[0]}, {self.shape[1]}), "
                f"got {tuple(d.shape)}"
            )

    def forward(self, src: Tensor, tgt: Tensor) -> tuple[Tensor, Tensor]:
        """The P pairs' local-view descriptors after interaction: ``src`` and ``tgt``
        (P, T, C) each → (P, T, C) each, L2-normalised per angle row, in the module's dtype."""
        self._check("local_src", src)
        self._check("local_tgt", tgt)
        if src.shape[0] != tgt.shape[0]:
            raise ValueError(
                f"local_src, local_tgt: expected the same number of pairs P, got "
                f"{src.shape[0]} and {tgt.shape[0]}"
            )
        src = self.first_tasa(src)
        return self.after_first_tasa(src, self.first_tasa(tgt))

    def first_tasa(self, d: Tensor) -> Tensor:
        """The first round's TASA, (P, T, C) → (P, T, C): it sees one side alone, so a side
        shared by many pairs (the source of several targets, a target of many hypotheses) can
        go through it once. ``forward(s, t) == after_first_tasa(first_tasa(s), first_tasa(t))``,
        operation for operation. With ``interactor_rounds = 0`` it returns ``d``."""
        self._check("local", d)
        return self.tasa[0](d, self.rel) if len(self.tasa) else d

    def after_first_tasa(self, src: Tensor, tgt: Tensor) -> tuple[Tensor, Tensor]:
        """The rest of :meth:`forward` on (P, T, C) pairs that went through
        :meth:`first_tasa`: the first round's cross-attention, the further rounds, the L2
        normalisation; → (Ds', Dt') (P, T, C)."""
        for i, (tasa, cross) in enumerate(zip(self.tasa, self.cross, strict=True)):
            if i > 0:
                src, tgt = tasa(src, self.rel), tasa(tgt, self.rel)
            src, tgt = cross(src, tgt), cross(tgt, src)
        return F.normalize(src, dim=-1), F.normalize(tgt, dim=-1)
