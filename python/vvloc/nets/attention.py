"""Self-attention with a relative geometric embedding (RASA / TASA) and its building blocks."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn


def sinusoidal_embedding(pos: Tensor, channels: int) -> Tensor:
    """Sinusoidal embedding of real positions: (...) → (..., C) = [sin(p·f_k), cos(p·f_k)],
    f_k = 10000^(−2k/C), k = 0..C/2−1."""
    half = channels // 2
    freq = torch.exp(
        torch.arange(half, dtype=torch.float64) * (-2.0 * math.log(10000.0) / channels)
    )
    ang = pos.to(torch.float64)[..., None] * freq
    return torch.cat([ang.sin(), ang.cos()], dim=-1).to(torch.float32)


def radial_embedding(num_radii: int, max_radius: float, sigma_r: float, channels: int) -> Tensor:
    """RASA embedding (R, R, C) of d_ij/σ_r, d_ij = |i − j|·r_max/R metres between radial
    samples i and j of one angle."""
    idx = torch.arange(num_radii, dtype=torch.float64)
    d = (idx[:, None] - idx[None, :]).abs() * (max_radius / num_radii)
    return sinusoidal_embedding(d / sigma_r, channels)


def angular_embedding(num_angles: int, sigma_a: float, channels: int) -> Tensor:
    """TASA embedding (T, T, C) of θ_ij/σ_a, θ_ij = circular distance between angle bins i and j
    in degrees, min(|i − j|, T − |i − j|)·360/T. Circulant, hence roll-equivariant."""
    idx = torch.arange(num_angles, dtype=torch.float64)
    diff = (idx[:, None] - idx[None, :]).abs()
    theta = torch.minimum(diff, num_angles - diff) * (360.0 / num_angles)
    return sinusoidal_embedding(theta / sigma_a, channels)


class RelativeSelfAttention(nn.Module):
    """Multi-head self-attention with e_ij = (x_i W^Q)·(x_j W^K + r_ij W^R)/√C_h per head.

    forward(x (N, S, C), rel (S, S, C)) → (N, S, C). No absolute position enters, so the
    operator commutes with any permutation of the S positions that preserves ``rel``.
    """

    def __init__(self, channels: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.q = nn.Linear(channels, channels)
        self.k = nn.Linear(channels, channels)
        self.v = nn.Linear(channels, channels)
        self.r = nn.Linear(channels, channels, bias=False)
        self.out = nn.Linear(channels, channels)

    def forward(self, x: Tensor, rel: Tensor) -> Tensor:
        n, s, c = x.shape
        h = self.num_heads
        ch = c // h
        q = self.q(x).view(n, s, h, ch).transpose(1, 2)  # (N, h, S, Ch)
        k = self.k(x).view(n, s, h, ch).transpose(1, 2)
        v = self.v(x).view(n, s, h, ch).transpose(1, 2)
        r = self.r(rel).view(s, s, h, ch).permute(2, 0, 1, 3)  # (h, S, S, Ch)
        scores = q @ k.transpose(-1, -2) + torch.einsum("nhic,hijc->nhij", q, r)
        attn = (scores / math.sqrt(ch)).softmax(dim=-1)
        out = (attn @ v).transpose(1, 2).reshape(n, s, c)
        return self.out(out)


def feed_forward(channels: int) -> nn.Sequential:
    """The layers' position-wise FFN: Linear(C, 2C), ReLU, Linear(2C, C); (..., C) → (..., C)."""
    return nn.Sequential(
        nn.Linear(channels, 2 * channels),
        nn.ReLU(inplace=True),
        nn.Linear(2 * channels, channels),
    )


class RelativeAttentionLayer(nn.Module):
    """[relative self-attention, residual, norm, FFN, residual, norm]; (N, S, C) → (N, S, C)."""

    def __init__(self, channels: int, num_heads: int, dropout: float) -> None:
        super().__init__()
        self.attn = RelativeSelfAttention(channels, num_heads)
        self.norm1 = nn.LayerNorm(channels)
        self.ffn = feed_forward(channels)
        self.norm2 = nn.LayerNorm(channels)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: Tensor, rel: Tensor) -> Tensor:
        x = self.norm1(x + self.dropout(self.attn(x, rel)))
        return self.norm2(x + self.dropout(self.ffn(x)))


class CrossAttentionLayer(nn.Module):
    """Multi-head cross-attention (no positional input) + FFN; x attends to ``context``."""

    def __init__(self, channels: int, num_heads: int, dropout: float) -> None:
        super().__init__()
        self.attn = nn.MultiheadAttention(channels, num_heads, dropout=dropout, batch_first=True)
        self.norm1 = nn.LayerNorm(channels)
        self.ffn = feed_forward(channels)
        self.norm2 = nn.LayerNorm(channels)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: Tensor, context: Tensor) -> Tensor:
        out, _ = self.attn(x, context, context, need_weights=False)
        x = self.norm1(x + self.dropout(out))
        return self.norm2(x + self.dropout(self.ffn(x)))
