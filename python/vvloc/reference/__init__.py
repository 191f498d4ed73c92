"""Pure-Python (numpy/torch) reference implementations of every Rust kernel.

They are literal and readable, follow the paper's formulas and DESIGN.md §3, and serve as the
tests' oracle and the benchmarks' baseline. They are not meant to be fast.

The submodules (``spatial``, ``matching``, ``retrieval``, ``torch_spatial``) load on first use:
``import vvloc`` (whose gateway names this package) must not import torch or scipy.
"""

from __future__ import annotations

import importlib

#: The spatial kernels, re-exported here for convenience (``vvloc.reference.bev_pad`` etc.).
_SPATIAL = ("bev_pad", "pad_polar", "polar_sample", "roll_interp")

__all__ = list(_SPATIAL)


def __getattr__(name: str) -> object:
    if name in _SPATIAL:
        return getattr(importlib.import_module("vvloc.reference.spatial"), name)
    raise AttributeError(f"module 'vvloc.reference' has no attribute {name!r}")
