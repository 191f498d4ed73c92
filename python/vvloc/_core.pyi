"""Type stubs of the Rust extension ``vvloc._core`` (checked by ``python -m mypy.stubtest``)."""

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "__version__",
    "_reset_pool_after_fork",
    "bev_pad",
    "build_profile",
    "get_num_threads",
    "pad_polar",
    "polar_sample",
    "roll_interp",
    "set_num_threads",
]

__version__: str
build_profile: str
__all__ = [
    "__version__",
    "_reset_pool_after_fork",
    "build_profile",
    "get_num_threads",
    "set_num_threads",
]

def set_num_threads(n: int) -> None: ...
def get_num_threads() -> int: ...
def _reset_pool_after_fork() -> None: ...

# --- spatial kernels ---
def roll_interp(x: NDArray[np.float32], shift: float, axis: int) -> NDArray[np.float32]: ...
def bev_pad(
    bev: NDArray[np.float32], translations: NDArray[np.float64], grid_size: float
) -> NDArray[np.float32]: ...
def polar_sample(
    bev: NDArray[np.float32], num_angles: int, num_radii: int, grid_size: float
) -> NDArray[np.float32]: ...
def pad_polar(
    bev: NDArray[np.float32],
    translations: NDArray[np.float64],
    num_angles: int,
    num_radii: int,
    grid_size: float,
) -> NDArray[np.float32]: ...
