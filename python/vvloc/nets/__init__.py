"""VVLoc networks in PyTorch (CPU and CUDA): BEV encoder, polar transform, global heads,
local-view decoder (RASA), interactor (TASA + MHCA), the full :class:`VVLocNet` and its config.

Conventions (BEV (B, H, W, C) channels-last, row i ↔ x forward, column j ↔ y left, polar angles
from +y towards +x, roll, padding) are those of DESIGN.md §3.
"""

import os

import torch

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


def _one_torch_thread_after_fork() -> None:
    """A child forked after torch ran a parallel CPU kernel inherits none of its OpenMP threads,
    and GNU OpenMP (torch's Linux wheels) waits for them for ever at the child's next parallel
    kernel: every child forked once this module is imported starts with torch on one thread,
    as torch's DataLoader workers do (whether the parent ran such a kernel cannot be told; a
    child whose parent ran none may raise it again with ``torch.set_num_threads``)."""
    torch.set_num_threads(1)


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_one_torch_thread_after_fork)
