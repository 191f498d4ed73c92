"""Shared helpers of the network and loss tests: a tiny model config and a camera rig."""

from __future__ import annotations

import math

import torch

from vvloc.nets import ModelConfig


def tiny_config(**overrides: object) -> ModelConfig:
    """A model small enough for many forward/backward passes in a test."""
    base: dict[str, object] = dict(
        image_height=32,
        image_width=48,
        bev_height=12,
        bev_width=12,
        channels=16,
        grid_size=1.0,
        num_angles=12,
        num_radii=4,
        backbone_widths=(8, 8, 16, 16),
        backbone_blocks=(1, 1, 1, 1),
        num_levels=2,
        max_cameras=6,
        encoder_layers=1,
        encoder_heads=2,
        ffn_dim=32,
        pillar_heights=(0.0, 1.0),
        cross_points=1,
        self_points=2,
        dropout=0.0,
        decoder_layers=1,
        decoder_heads=2,
        interactor_rounds=1,
        interactor_heads=2,
        global_head="gem",
        netvlad_clusters=4,
        global_dim=8,
        disco_crop=(4, 4),
    )
    base.update(overrides)
    return ModelConfig(**base)  # type: ignore[arg-type]


# OpenCV camera axes (x right, y down, z forward) in the ego frame of a forward-looking camera.
CAM_AXES_FORWARD = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_pose(
    yaw: float, height: float = 1.5, xy: tuple[float, float] = (0.0, 0.0)
) -> torch.Tensor:
    """cam_to_ego (4, 4) of a level camera at ``height`` m looking along ego yaw ``yaw`` (rad)."""
    c, s = math.cos(yaw), math.sin(yaw)
    rz = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t = torch.eye(4)
    t[:3, :3] = rz @ CAM_AXES_FORWARD
    t[:3, 3] = torch.tensor([xy[0], xy[1], height])
    return t


def make_rig(
    batch: int, cameras: int, height: int, width: int, focal: float | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """(intrinsics (B, M, 3, 3), cam_to_ego (B, M, 4, 4)) of M cameras evenly spread in yaw;
    each batch item's rig is turned by a different small angle (per-sample calibration)."""
    f = focal if focal is not None else width / 2.0
    k = torch.tensor([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    intr = k.expand(batch, cameras, 3, 3).clone()
    ext = torch.stack(
        [
            torch.stack([camera_pose(2 * math.pi * m / cameras + 0.1 * b) for m in range(cameras)])
            for b in range(batch)
        ]
    )
    return intr, ext


def random_images(batch: int, cameras: int, height: int, width: int, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.randint(
        0, 256, (batch, cameras, 3, height, width), dtype=torch.uint8, generator=gen
    )
