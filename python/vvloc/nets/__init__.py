"""VVLoc networks in PyTorch (CPU and CUDA): BEV encoder, polar transform, global heads,
local-view decoder (RASA), interactor (TASA + MHCA), the full :class:`VVLocNet` and its config.

Conventions (BEV (B, H, W, C) channels-last, row i ↔ x forward, column j ↔ y left, polar angles
from +y towards +x, roll, padding) are those of DESIGN.md §3.
"""

from vvloc.nets.config import ModelConfig
from vvloc.nets.decoder import Interactor, LocalViewDecoder
from vvloc.nets.encoder import BevEncoder, bev_cell_centres, project_points
from vvloc.nets.heads import DiscoHead, GeMHead, NetVLADHead, make_global_head
from vvloc.nets.model import EncoderOutput, VVLocNet
from vvloc.nets.polar import bev_pad, polar_sample, roll_interp

__all__ = [
    "BevEncoder",
    "DiscoHead",
    "EncoderOutput",
    "GeMHead",
    "Interactor",
    "LocalViewDecoder",
    "ModelConfig",
    "NetVLADHead",
    "VVLocNet",
    "bev_cell_centres",
    "bev_pad",
    "make_global_head",
    "polar_sample",
    "project_points",
    "roll_interp",
]
