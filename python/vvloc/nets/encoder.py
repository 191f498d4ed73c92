"""BEVFormer-style BEV encoder without temporal input (DESIGN.md §1, §3).

Learned BEV queries (H·W, C) with a learned positional encoding go through L layers of
[BEV self-attention, norm, spatial cross-attention, norm, FFN, norm]. Spatial cross-attention
lifts each BEV cell to a pillar of D reference points (ego frame, heights ``pillar_heights``),
projects them into every camera through the per-sample rig calibration, and attends to the
multi-level image features around them with deformable attention; the result is averaged over
the cameras that see the cell. The BEV self-attention is deformable attention over the BEV map
itself (one level, reference = the cell centre), switchable off with
``ModelConfig.bev_self_attention``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from vvloc._checks import positive_float, positive_int
from vvloc.nets.config import ModelConfig
from vvloc.nets.deformable import DeformableAttention, ms_deform_sample
from vvloc.nets.polar import float_tensor

_MIN_DEPTH = 1e-3  # metres: a point must be at least this far in front of the camera


def bev_cell_centres(height: int, width: int, grid_size: float) -> Tensor:
    """Ego-frame (x, y) metres of every BEV cell, (H·W, 2) float32, row-major over (i, j)
    (DESIGN §3); ``height``, ``width`` ints >= 1 and ``grid_size`` (m, finite, > 0) checked."""
    height, width = positive_int(height, "height"), positive_int(width, "width")
    grid_size = positive_float(grid_size, "grid_size")
    i = torch.arange(height, dtype=torch.float32)
    j = torch.arange(width, dtype=torch.float32)
    x = (i - (height - 1) / 2.0) * grid_size
    y = (j - (width - 1) / 2.0) * grid_size
    xx, yy = torch.meshgrid(x, y, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=-1)


def project_points(
    points: Tensor, intrinsics: Tensor, cam_to_ego: Tensor, image_size: tuple[int, int]
) -> tuple[Tensor, Tensor]:
    """Project ego-frame points into every camera.

    points (N, 3) metres, ego frame (x forward, y left, z up); intrinsics (B, M, 3, 3) pixels;
    cam_to_ego (B, M, 4, 4) maps OpenCV camera coordinates (x right, y down, z forward) to ego;
    image_size (Hi, Wi). Returns ``ref`` (B, M, N, 2): (u + 0.5)/Wi, (v + 0.5)/Hi, i.e. the
    pixel position normalised to [0, 1] with pixel centres at integer (u, v) (OpenCV), and
    ``visible`` (B, M, N) bool: depth > 1 mm and inside the image. Invisible points get finite
    placeholder coordinates (−1). ``TypeError``/``ValueError`` naming the argument for other
    types or shapes, and for a ``cam_to_ego`` that cannot be inverted.
    """
    float_tensor(points, "points", "(N, 3)")
    float_tensor(intrinsics, "intrinsics", "(B, M, 3, 3)")
    float_tensor(cam_to_ego, "cam_to_ego", "(B, M, 4, 4)")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {tuple(points.shape)}")
    if intrinsics.ndim != 4 or intrinsics.shape[2:] != (3, 3):
        raise ValueError(f"intrinsics: expected shape (B, M, 3, 3), got {tuple(intrinsics.shape)}")
    if cam_to_ego.shape != (*intrinsics.shape[:2], 4, 4):
        raise ValueError(
            f"cam_to_ego: expected shape ({intrinsics.shape[0]}, {intrinsics.shape[1]}, 4, 4) "
            f"like intrinsics, got {tuple(cam_to_ego.shape)}"
        )
    if not isinstance(image_size, (tuple, list)) or len(image_size) != 2:
        raise TypeError(f"image_size: expected a pair (Hi, Wi) of ints, got {image_size!r}")
    hi, wi = (positive_int(v, "image_size") for v in image_size)
    try:
        ego_to_cam = torch.linalg.inv(cam_to_ego.to(torch.float64))
    except torch.linalg.LinAlgError as e:
        raise ValueError(f"cam_to_ego: a transform cannot be inverted ({e})") from None
    rot, trans = ego_to_cam[..., :3, :3], ego_to_cam[..., :3, 3]
    p = points.to(torch.float64)
    p_cam = torch.einsum("bmij,nj->bmni", rot, p) + trans[:, :, None, :]
    uvw = torch.einsum("bmij,bmnj->bmni", intrinsics.to(torch.float64), p_cam)
    depth = p_cam[..., 2]
    in_front = depth > _MIN_DEPTH
    safe = torch.where(in_front, uvw[..., 2], torch.ones_like(depth))
    ref = torch.stack([(uvw[..., 0] / safe + 0.5) / wi, (uvw[..., 1] / safe + 0.5) / hi], dim=-1)
    inside = (ref >= 0).all(-1) & (ref <= 1).all(-1)
    visible = in_front & inside
    ref = torch.where(visible[..., None], ref, torch.full_like(ref, -1.0))
    return ref.to(points.dtype), visible


class EncoderLayer(nn.Module):
    """[BEV self-attention, norm, spatial cross-attention, norm, FFN, norm]."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c = cfg.channels
        self.self_attn: DeformableAttention | None = None
        if cfg.bev_self_attention:
            self.self_attn = DeformableAttention(c, cfg.encoder_heads, 1, 1, cfg.self_points)
            self.norm_self = nn.LayerNorm(c)
        self.cross_attn = DeformableAttention(
            c, cfg.encoder_heads, cfg.num_levels, len(cfg.pillar_heights), cfg.cross_points
        )
        self.norm_cross = nn.LayerNorm(c)
        self.ffn = nn.Sequential(
            nn.Linear(c, cfg.ffn_dim),
            nn.ReLU(inplace=True),
            nn.Dropout(cfg.dropout),
            nn.Linear(cfg.ffn_dim, c),
        )
        self.norm_ffn = nn.LayerNorm(c)
        self.dropout = nn.Dropout(cfg.dropout)
        self.bev_shape = (cfg.bev_height, cfg.bev_width)

    def _self_attention(self, bev: Tensor, pos: Tensor, ref_bev: Tensor) -> Tensor:
        assert self.self_attn is not None
        attn = self.self_attn
        b, _q, c = bev.shape
        h, w = self.bev_shape
        value = attn.value_proj(bev).transpose(1, 2).reshape(b, c, h, w)
        off, wts = attn.offsets_and_weights(bev + pos)
        loc = attn.sampling_locations(ref_bev.expand(b, -1, -1, -1), off, [(h, w)])
        out = ms_deform_sample([value], loc, wts, attn.num_heads)
        return attn.output_proj(out)

    def _cross_attention(
        self, bev: Tensor, pos: Tensor, values: list[Tensor], ref_cam: Tensor, visible: Tensor
    ) -> Tensor:
        """Spatial cross-attention, computed per camera only for the cells it sees.

        The cells a camera sees (any pillar point visible) are gathered to the front of a
        (B, L) batch (L = the most seen by any batch item; padding is masked out), sampled,
        and scattered back; every cell's sum is divided by the number of cameras seeing it.
        """
        attn = self.cross_attn
        b, m, _q = ref_cam.shape[:3]
        shapes = [(v.shape[-2], v.shape[-1]) for v in values]
        off, wts = attn.offsets_and_weights(bev + pos)
        off_flat, wts_flat = off.flatten(2), wts.flatten(2)
        acc = torch.zeros_like(bev)
        count = torch.zeros((*bev.shape[:2], 1), dtype=bev.dtype, device=bev.device)
        for cam in range(m):
            seen = visible[:, cam].any(-1)  # (B, Q)
            n_seen = seen.sum(1)
            n_max = int(n_seen.max())
            if n_max == 0:
                continue
            # stable sort puts the seen cells first, in cell order
            order = torch.argsort((~seen).to(torch.int8), dim=1, stable=True)[:, :n_max]
            keep = (torch.arange(n_max, device=bev.device)[None, :] < n_seen[:, None]).to(bev.dtype)

            def take(x: Tensor, idx: Tensor = order) -> Tensor:
                index = idx.reshape(idx.shape + (1,) * (x.ndim - 2)).expand(
                    (-1, -1, *tuple(x.shape[2:]))
                )
                return torch.gather(x, 1, index)

            cam_off = take(off_flat).view((b, n_max, *tuple(off.shape[2:])))
            cam_wts = take(wts_flat).view((b, n_max, *tuple(wts.shape[2:])))
            loc = attn.sampling_locations(take(ref_cam[:, cam]), cam_off, shapes)
            out = ms_deform_sample([v[:, cam] for v in values], loc, cam_wts, attn.num_heads)
            index = order[..., None].expand(-1, -1, bev.shape[-1])
            acc = acc.scatter_add(1, index, out * keep[..., None])
            count = count + seen[..., None].to(bev.dtype)
        return attn.output_proj(acc / count.clamp(min=1.0))

    def forward(
        self,
        bev: Tensor,
        pos: Tensor,
        values: list[Tensor],
        ref_cam: Tensor,
        visible: Tensor,
        ref_bev: Tensor,
    ) -> Tensor:
        """bev (B, Q, C); pos (1, Q, C); values per level (B, M, C, H_l, W_l) (value-projected by
        this layer's cross-attention); ref_cam (B, M, Q, D, 2); visible (B, M, Q, D);
        ref_bev (1, Q, 1, 2). Returns (B, Q, C)."""
        if self.self_attn is not None:
            bev = self.norm_self(bev + self.dropout(self._self_attention(bev, pos, ref_bev)))
        cross = self._cross_attention(bev, pos, values, ref_cam, visible)
        bev = self.norm_cross(bev + self.dropout(cross))
        return self.norm_ffn(bev + self.dropout(self.ffn(bev)))


class BevEncoder(nn.Module):
    """Image features of a rig → BEV queries (B, H, W, C) channels-last (DESIGN.md §3)."""

    pillars: Tensor  # (H·W, D, 3) ego-frame reference points, buffer
    ref_bev: Tensor  # (1, H·W, 1, 2) normalised (x ↔ column, y ↔ row) cell centres, buffer

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c, h, w = cfg.channels, cfg.bev_height, cfg.bev_width
        self.cfg = cfg
        self.queries = nn.Parameter(torch.randn(h * w, c))
        self.row_embed = nn.Parameter(torch.rand(h, c // 2))
        self.col_embed = nn.Parameter(torch.rand(w, c - c // 2))
        self.camera_embed = nn.Parameter(torch.randn(cfg.max_cameras, c) * 0.02)
        self.level_embed = nn.Parameter(torch.randn(cfg.num_levels, c) * 0.02)
        self.layers = nn.ModuleList(EncoderLayer(cfg) for _ in range(cfg.encoder_layers))
        centres = bev_cell_centres(h, w, cfg.grid_size)  # (Q, 2)
        heights = torch.tensor(cfg.pillar_heights, dtype=torch.float32)
        pillars = torch.cat(
            [
                centres[:, None, :].expand(-1, len(heights), -1),
                heights[None, :, None].expand(centres.shape[0], -1, 1),
            ],
            dim=-1,
        )  # (Q, D, 3)
        self.register_buffer("pillars", pillars, persistent=False)
        ii, jj = torch.meshgrid(
            torch.arange(h, dtype=torch.float32),
            torch.arange(w, dtype=torch.float32),
            indexing="ij",
        )
        ref_bev = torch.stack([(jj + 0.5) / w, (ii + 0.5) / h], -1).reshape(1, h * w, 1, 2)
        self.register_buffer("ref_bev", ref_bev, persistent=False)

    def positional_encoding(self) -> Tensor:
        """Learned positional encoding (1, H·W, C): row embedding ⊕ column embedding."""
        h, w = self.cfg.bev_height, self.cfg.bev_width
        pos = torch.cat(
            [
                self.row_embed[:, None, :].expand(h, w, -1),
                self.col_embed[None, :, :].expand(h, w, -1),
            ],
            dim=-1,
        )
        return pos.reshape(1, h * w, -1)

    def forward(
        self,
        feats: list[Tensor],
        intrinsics: Tensor,
        cam_to_ego: Tensor,
        image_size: tuple[int, int],
    ) -> Tensor:
        """feats: per level (B, M, C, H_l, W_l) finest first; intrinsics (B, M, 3, 3) pixels of
        the input images of size ``image_size`` (Hi, Wi); cam_to_ego (B, M, 4, 4).
        Returns the BEV (B, H, W, C)."""
        b, m = feats[0].shape[:2]
        self.cfg.check_num_cameras(m)
        n_d = len(self.cfg.pillar_heights)
        q = self.pillars.shape[0]
        ref, visible = project_points(
            self.pillars.reshape(-1, 3), intrinsics, cam_to_ego, image_size
        )
        ref_cam = ref.reshape(b, m, q, n_d, 2)
        visible = visible.reshape(b, m, q, n_d)
        feats = [
            f + self.camera_embed[:m, :, None, None] + self.level_embed[lvl, :, None, None]
            for lvl, f in enumerate(feats)
        ]
        pos = self.positional_encoding()
        bev = self.queries[None].expand(b, -1, -1)
        for layer in self.layers:
            assert isinstance(layer, EncoderLayer)
            values = [
                layer.cross_attn.project_values(f.flatten(0, 1)).unflatten(0, (b, m)) for f in feats
            ]
            bev = layer(bev, pos, values, ref_cam, visible, self.ref_bev)
        return bev.reshape(b, self.cfg.bev_height, self.cfg.bev_width, -1)
