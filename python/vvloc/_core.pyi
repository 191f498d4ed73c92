"""Type stubs of the Rust extension ``vvloc._core`` (checked by ``python -m mypy.stubtest``)."""

from typing import final

import numpy as np
import numpy.typing as npt
from numpy.typing import NDArray

__all__ = [
    "DescriptorIndex",
    "TranslationSearch",
    "__version__",
    "_after_fork_in_child",
    "_after_fork_in_parent",
    "_before_fork",
    "_panic_for_tests",
    "_reset_pool_after_fork",
    "bev_pad",
    "build_profile",
    "estimate_yaw",
    "get_num_threads",
    "matching_cost",
    "pad_polar",
    "polar_sample",
    "rerank",
    "roll_interp",
    "set_num_threads",
    "yaw_costs",
]

__version__: str
build_profile: str

def set_num_threads(n: int) -> None: ...
def get_num_threads() -> int: ...
def _reset_pool_after_fork() -> None: ...
def _before_fork() -> None: ...
def _after_fork_in_parent() -> None: ...
def _after_fork_in_child() -> None: ...
def _panic_for_tests(in_pool: bool) -> None: ...

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

# --- matching kernels ---------------------------------------------------------------------------

def matching_cost(
    a: npt.NDArray[np.float32], b: npt.NDArray[np.float32]
) -> npt.NDArray[np.float64]: ...
def yaw_costs(
    src: npt.NDArray[np.float32], tgt: npt.NDArray[np.float32]
) -> npt.NDArray[np.float64]: ...
def estimate_yaw(
    src: npt.NDArray[np.float32], tgt: npt.NDArray[np.float32]
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
def rerank(
    src: npt.NDArray[np.float32], tgt: npt.NDArray[np.float32]
) -> tuple[
    npt.NDArray[np.int64], npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]
]: ...

@final
class TranslationSearch:
    def __new__(
        cls,
        half_range: float,
        step: float,
        fine_samples: int,
        stages: int,
        shrink: float,
        seed: int,
    ) -> TranslationSearch: ...
    def proposals(self) -> npt.NDArray[np.float64]: ...
    def report(self, costs: npt.NDArray[np.float64], yaws: npt.NDArray[np.float64]) -> None: ...
    @property
    def done(self) -> bool: ...
    @property
    def stage(self) -> int: ...
    def best(self) -> tuple[float, float, float, float] | None: ...
    def history(
        self,
    ) -> tuple[
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.int64],
    ]: ...

# --- retrieval -------------------------------------------------------------------------------

from typing_extensions import final  # noqa: E402

# The extension's runtime __all__ (PyModule.add appends every name): keep in sync.
@final
class DescriptorIndex:
    def __new__(
        cls,
        descriptors: npt.NDArray[np.float32],
        dtype: str = "float32",
        groups: npt.NDArray[np.int64] | None = None,
        seqs: npt.NDArray[np.int64] | None = None,
    ) -> DescriptorIndex: ...
    def add(
        self,
        descriptors: npt.NDArray[np.float32],
        groups: npt.NDArray[np.int64] | None = None,
        seqs: npt.NDArray[np.int64] | None = None,
    ) -> None: ...
    def topk(
        self,
        queries: npt.NDArray[np.float32],
        k: int,
        exclude: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], int, bool] | None = None,
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]: ...
    def radius(
        self,
        queries: npt.NDArray[np.float32],
        r: float,
        exclude: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], int, bool] | None = None,
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.float32]]: ...
    def to_bytes(self) -> bytes: ...
    @staticmethod
    def load(path: str) -> DescriptorIndex: ...
    def descriptors(self) -> npt.NDArray[np.float32]: ...
    def groups(self) -> npt.NDArray[np.int64]: ...
    def seqs(self) -> npt.NDArray[np.int64]: ...
    def __len__(self) -> int: ...
    @property
    def dim(self) -> int: ...
    @property
    def dtype(self) -> str: ...
