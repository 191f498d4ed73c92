"""Multi-scale deformable attention in pure PyTorch (``grid_sample``), BEVFormer-style."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def ms_deform_sample(
    values: list[Tensor], locations: Tensor, weights: Tensor, num_heads: int
) -> Tensor:
    """Weighted bilinear sampling of multi-level value maps.

    values: per level (B, C, H_l, W_l) (C = heads × C_h); locations (B, Q, heads, L, P, 2) as
    (x, y) normalised to [0, 1] over the level's image extent (pixel-edge convention,
    ``align_corners=False``); weights (B, Q, heads, L, P). Returns (B, Q, C); taps outside read 0.
    """
    b, q, h, _n_levels, p, _ = locations.shape
    out = None
    grids = 2.0 * locations - 1.0
    for lvl, value in enumerate(values):
        c = value.shape[1]
        v = value.reshape(b * h, c // h, value.shape[2], value.shape[3])
        g = grids[:, :, :, lvl].permute(0, 2, 1, 3, 4).reshape(b * h, q, p, 2)
        sampled = F.grid_sample(v, g, mode="bilinear", padding_mode="zeros", align_corners=False)
        wl = weights[:, :, :, lvl].permute(0, 2, 1, 3).reshape(b * h, 1, q, p)
        term = (sampled * wl).sum(-1)  # (B·h, C_h, Q)
        out = term if out is None else out + term
    assert out is not None
    return out.reshape(b, h * out.shape[1], q).transpose(1, 2)


class DeformableAttention(nn.Module):
    """Deformable attention head block: offsets and weights predicted from the query.

    Each of ``num_heads`` heads samples ``num_points`` points per level per anchor around the
    query's reference point(s); offsets are in units of the level's cells. Initialised as in
    BEVFormer/Deformable DETR: zero offset weights with directional biases (head h points along
    angle 2πh/heads, point k at distance k+1), zero attention logits (uniform attention).
    """

    def __init__(
        self, channels: int, num_heads: int, num_levels: int, num_anchors: int, num_points: int
    ) -> None:
        super().__init__()
        self.channels, self.num_heads = channels, num_heads
        self.num_levels, self.num_anchors, self.num_points = num_levels, num_anchors, num_points
        n = num_heads * num_levels * num_anchors * num_points
        self.sampling_offsets = nn.Linear(channels, n * 2)
        self.attention_weights = nn.Linear(channels, n)
        self.value_proj = nn.Linear(channels, channels)
        self.output_proj = nn.Linear(channels, channels)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        nn.init.zeros_(self.sampling_offsets.weight)
        theta = torch.arange(self.num_heads, dtype=torch.float32) * (2.0 * math.pi / self.num_heads)
        grid = torch.stack([theta.cos(), theta.sin()], -1)
        grid = grid / grid.abs().max(-1, keepdim=True).values
        grid = grid.view(self.num_heads, 1, 1, 1, 2).repeat(
            1, self.num_levels, self.num_anchors, self.num_points, 1
        )
        grid = grid * torch.arange(1, self.num_points + 1, dtype=torch.float32).view(1, 1, 1, -1, 1)
        with torch.no_grad():
            self.sampling_offsets.bias.copy_(grid.reshape(-1))
        nn.init.zeros_(self.attention_weights.weight)
        nn.init.zeros_(self.attention_weights.bias)
        nn.init.xavier_uniform_(self.value_proj.weight)
        nn.init.zeros_(self.value_proj.bias)
        nn.init.xavier_uniform_(self.output_proj.weight)
        nn.init.zeros_(self.output_proj.bias)

    def offsets_and_weights(self, query: Tensor) -> tuple[Tensor, Tensor]:
        """query (B, Q, C) → offsets (B, Q, heads, L, A, P, 2) cells, weights (B, Q, heads, L,
        A·P) softmax-normalised over levels × anchors × points of each head."""
        b, q, _ = query.shape
        h, n_l, a, p = self.num_heads, self.num_levels, self.num_anchors, self.num_points
        off = self.sampling_offsets(query).view(b, q, h, n_l, a, p, 2)
        w = self.attention_weights(query).view(b, q, h, n_l * a * p).softmax(-1)
        return off, w.view(b, q, h, n_l, a * p)

    def project_values(self, feat: Tensor) -> Tensor:
        """Value projection of a level map (N, C, H_l, W_l) (a linear map per pixel)."""
        return self.value_proj(feat.permute(0, 2, 3, 1)).permute(0, 3, 1, 2).contiguous()

    @staticmethod
    def sampling_locations(
        reference: Tensor, offsets: Tensor, level_shapes: list[tuple[int, int]]
    ) -> Tensor:
        """reference (B, Q, A, 2) in [0, 1] (x, y); offsets (B, Q, heads, L, A, P, 2) in level
        cells → locations (B, Q, heads, L, A·P, 2) in [0, 1]."""
        norm = torch.tensor(
            [[w, h] for h, w in level_shapes], dtype=offsets.dtype, device=offsets.device
        )  # (L, 2) as (x, y) extents
        loc = (
            reference[:, :, None, None, :, None, :]
            + offsets / norm[None, None, None, :, None, None]
        )
        b, q, h, n_l, a, p, _ = loc.shape
        return loc.reshape(b, q, h, n_l, a * p, 2)
