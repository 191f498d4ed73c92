"""Model configuration of the VVLoc networks: one dataclass, JSON round trip, stable hash."""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from vvloc.kernels import MIN_YAW_BINS

CONFIG_VERSION = 1
GLOBAL_HEADS = ("gem", "netvlad", "disco")
#: The largest GeM exponent a config may start from (:class:`vvloc.nets.heads.GeM`).
MAX_GEM_P = 16.0


#: The fields that are real numbers (stored as float whatever number was given).
_FLOAT_FIELDS = ("grid_size", "sigma_r", "sigma_a", "dropout", "gem_p")
_REAL = (int, float, np.integer, np.floating)


def _sequence(value: Any, name: str) -> list[Any]:
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
        raise TypeError(f"ModelConfig.{name}: expected a list, got {value!r}")
    return list(value)


def _int_tuple(value: Any, name: str) -> tuple[int, ...]:
    items = _sequence(value, name)
    if any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) for v in items):
        raise TypeError(f"ModelConfig.{name}: expected a list of ints, got {value!r}")
    return tuple(int(v) for v in items)


@dataclass
class ModelConfig:
    """Hyper-parameters of :class:`vvloc.nets.VVLocNet` (sizes in cells/pixels, lengths in metres;
    ``sigma_r`` in metres but ``sigma_a`` in degrees, the widths of the radius- and
    theta-aware attentions' relative embeddings).

    ``image_height``/``image_width`` are the nominal input size (the networks accept any size; the
    intrinsics must describe the pixels actually given); they count in :meth:`config_hash` like
    every field, so another value makes another model. The BEV grid is ``bev_height`` ×
    ``bev_width`` cells of ``grid_size`` metres (row i ↔ ego x, column j ↔ ego y, DESIGN.md §3);
    the polar grid is ``num_angles`` (T) × ``num_radii`` (R). ``pillar_heights`` are the ego-frame
    z (metres) of the D reference points of each BEV cell's pillar.
    """

    # input and grids
    image_height: int = 256
    image_width: int = 448
    bev_height: int = 100
    bev_width: int = 100
    channels: int = 256
    grid_size: float = 0.3
    num_angles: int = 120
    num_radii: int = 40
    sigma_r: float = 4.8
    sigma_a: float = 15.0
    # image backbone (ResNet-like, GroupNorm) + FPN
    backbone_widths: tuple[int, ...] = (64, 128, 256, 512)
    backbone_blocks: tuple[int, ...] = (2, 2, 2, 2)
    num_levels: int = 3
    max_cameras: int = 8
    # BEV encoder
    encoder_layers: int = 3
    encoder_heads: int = 8
    ffn_dim: int = 512
    pillar_heights: tuple[float, ...] = (-1.0, 0.0, 1.0, 2.0)
    cross_points: int = 2
    bev_self_attention: bool = True
    self_points: int = 4
    dropout: float = 0.1
    # local-view decoder (RASA) and interactor (TASA + MHCA)
    decoder_layers: int = 2
    decoder_heads: int = 8
    interactor_rounds: int = 2
    interactor_heads: int = 8
    # global head
    global_head: str = "netvlad"
    netvlad_clusters: int = 64
    global_dim: int = 256
    disco_crop: tuple[int, int] = (16, 16)
    gem_p: float = 3.0

    def __post_init__(self) -> None:
        # Normalised before validation, so that equal configs hash the same (15 and 15.0,
        # -0.0 and 0.0) and a string is never split into digits ("1632" is no width list).
        for name in _FLOAT_FIELDS:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise TypeError(f"ModelConfig.{name}: expected a number, got {v!r}")
            setattr(self, name, float(v) + 0.0)
        self.backbone_widths = _int_tuple(self.backbone_widths, "backbone_widths")
        self.backbone_blocks = _int_tuple(self.backbone_blocks, "backbone_blocks")
        heights = _sequence(self.pillar_heights, "pillar_heights")
        if any(isinstance(v, bool) or not isinstance(v, _REAL) for v in heights):
            raise TypeError(f"ModelConfig.pillar_heights: expected numbers, got {heights!r}")
        self.pillar_heights = tuple(float(v) + 0.0 for v in heights)
        crop = _int_tuple(self.disco_crop, "disco_crop")
        if len(crop) != 2:
            raise ValueError(f"ModelConfig.disco_crop: expected (T, R) crop sizes, got {crop}")
        self.disco_crop = (crop[0], crop[1])
        if not isinstance(self.bev_self_attention, (bool, np.bool_)):
            raise TypeError(
                f"ModelConfig.bev_self_attention: expected a bool, got {self.bev_self_attention!r}"
            )
        self.bev_self_attention = bool(self.bev_self_attention)
        if not isinstance(self.global_head, str):
            raise TypeError(f"ModelConfig.global_head: expected a str, got {self.global_head!r}")
        self.validate()

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first inconsistent field."""
        positive = (
            "image_height image_width bev_height bev_width channels num_angles num_radii "
            "num_levels max_cameras encoder_heads ffn_dim cross_points self_points decoder_heads "
            "interactor_heads netvlad_clusters"
        ).split()
        for name in positive:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"ModelConfig.{name}: expected an int >= 1, got {v!r}")
        for name in ("encoder_layers", "decoder_layers", "interactor_rounds", "global_dim"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"ModelConfig.{name}: expected an int >= 0, got {v!r}")
        for name in ("grid_size", "sigma_r", "sigma_a", "gem_p"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < math.inf:
                raise ValueError(f"ModelConfig.{name}: expected a finite number > 0, got {v!r}")
        if self.num_angles < MIN_YAW_BINS:
            raise ValueError(
                f"ModelConfig.num_angles: expected >= {MIN_YAW_BINS} angle bins (a yaw is "
                f"estimated from them: with 2 its sign is undetermined), got {self.num_angles}"
            )
        if self.bev_height < 2 or self.bev_width < 2:
            raise ValueError("ModelConfig.bev_height/bev_width: expected >= 2 cells")
        if len(self.backbone_widths) != 4 or len(self.backbone_blocks) != 4:
            raise ValueError("ModelConfig.backbone_widths/backbone_blocks: expected 4 stages")
        if self.num_levels > 4:
            raise ValueError(f"ModelConfig.num_levels: expected 1..4, got {self.num_levels}")
        if not self.pillar_heights:
            raise ValueError("ModelConfig.pillar_heights: expected at least one height")
        if not all(math.isfinite(v) for v in self.pillar_heights):
            raise ValueError(
                f"ModelConfig.pillar_heights: expected finite metres, got {self.pillar_heights}"
            )
        if min(self.backbone_widths) < 1 or min(self.backbone_blocks) < 1:
            raise ValueError(  # a stage always has its first block: 0 built the same net as 1
                "ModelConfig.backbone_widths/backbone_blocks: expected widths >= 1 and blocks "
                f">= 1, got {self.backbone_widths} / {self.backbone_blocks}"
            )
        if self.gem_p > MAX_GEM_P:
            raise ValueError(
                f"ModelConfig.gem_p: expected at most {MAX_GEM_P:g}, got {self.gem_p!r} (the "
                "mean of x**p overflows float32 for features of a few units; a large p is max "
                "pooling)"
            )
        for heads_name in ("encoder_heads", "decoder_heads", "interactor_heads"):
            if self.channels % getattr(self, heads_name):
                raise ValueError(f"ModelConfig.{heads_name}: must divide channels={self.channels}")
        if self.channels % 2:
            raise ValueError("ModelConfig.channels: expected an even number")
        if self.global_head not in GLOBAL_HEADS:
            raise ValueError(
                f"ModelConfig.global_head: expected one of {GLOBAL_HEADS}, got {self.global_head!r}"
            )
        ct, cr = self.disco_crop
        if not (1 <= ct <= self.num_angles and 1 <= cr <= self.num_radii):
            raise ValueError(
                f"ModelConfig.disco_crop: expected 1..T x 1..R = {self.num_angles}x"
                f"{self.num_radii}, got {self.disco_crop}"
            )
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"ModelConfig.dropout: expected [0, 1), got {self.dropout}")

    # --- presets ---------------------------------------------------------------------------

    @classmethod
    def paper(cls) -> ModelConfig:
        """The paper's sizes: images 256×448, BEV 100×100×256 at 0.3 m, T=120, R=40."""
        return cls()

    @classmethod
    def small(cls) -> ModelConfig:
        """A CPU-friendly model for the synthetic benchmark and tests.

        Images 96×160, BEV 40×40×64 at 0.6 m (24 m × 24 m), T=60, R=16, one encoder layer. One
        training step on a triplet (3 frames × 4 cameras) is measured in BENCHMARKS.md.
        """
        return cls(
            image_height=96,
            image_width=160,
            bev_height=40,
            bev_width=40,
            channels=64,
            grid_size=0.6,
            num_angles=60,
            num_radii=16,
            backbone_widths=(16, 32, 64, 96),
            backbone_blocks=(1, 1, 1, 1),
            num_levels=2,
            encoder_layers=1,
            encoder_heads=4,
            ffn_dim=128,
            pillar_heights=(-0.5, 0.5, 1.5, 2.5),
            cross_points=1,
            self_points=4,
            dropout=0.0,
            decoder_layers=1,
            decoder_heads=4,
            interactor_rounds=1,
            interactor_heads=4,
            global_head="gem",
            netvlad_clusters=16,
            global_dim=64,
            disco_crop=(12, 8),
        )

    # --- serialisation ---------------------------------------------------------------------

    def check_num_cameras(self, m: int, name: str = "images") -> None:
        """Raise ``ValueError`` naming ``name`` (the argument that holds the cameras) when ``m``
        cameras exceed ``max_cameras``."""
        if m > self.max_cameras:
            raise ValueError(
                f"{name}: {m} cameras exceed ModelConfig.max_cameras={self.max_cameras} "
                "(the camera embeddings a model holds; a training config raises it with "
                "model_overrides: {max_cameras: N}, which makes another model)"
            )

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-compatible dict (tuples become lists)."""
        d = dataclasses.asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        if not isinstance(d, dict):
            raise TypeError(f"d: expected a dict, got {type(d).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            near = {k: difflib.get_close_matches(str(k), names, n=1) for k in unknown}
            meant = [f"{k!r} → {m[0]!r}" for k, m in near.items() if m]
            hint = f" (did you mean {', '.join(meant)}?)" if meant else ""
            raise ValueError(f"ModelConfig: unknown fields {unknown}{hint}; known: {sorted(names)}")
        return cls(**d)

    def to_json(self) -> str:
        """Canonical JSON (sorted keys)."""
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> ModelConfig:
        """Inverse of :meth:`to_json`."""
        if not isinstance(text, (str, bytes, bytearray)):
            raise TypeError(
                f"text: expected the JSON text of a ModelConfig, got {type(text).__name__}"
            )
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"text: not the JSON of a ModelConfig ({e})") from None
        return cls.from_dict(raw)

    def config_hash(self) -> str:
        """Stable 16-hex-digit hash of the canonical JSON (same config ⇒ same hash)."""
        return hashlib.sha256(self.to_json().encode()).hexdigest()[:16]

    @property
    def max_radius(self) -> float:
        """r_max = min(H, W)·g/2 in metres (DESIGN.md §3)."""
        return min(self.bev_height, self.bev_width) * self.grid_size / 2.0
