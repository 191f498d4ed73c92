"""Type stubs of the Rust extension ``vvloc._core`` (checked by ``python -m mypy.stubtest``)."""

__version__: str
build_profile: str

def set_num_threads(n: int) -> None: ...
def get_num_threads() -> int: ...
def _reset_pool_after_fork() -> None: ...

# --- retrieval -------------------------------------------------------------------------------

import numpy as np  # noqa: E402
import numpy.typing as npt  # noqa: E402
from typing_extensions import final  # noqa: E402

# The extension's runtime __all__ (PyModule.add appends every name): keep in sync.
__all__ = [
    "DescriptorIndex",
    "__version__",
    "_reset_pool_after_fork",
    "build_profile",
    "get_num_threads",
    "set_num_threads",
]

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
    def save(self, path: str) -> None: ...
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
