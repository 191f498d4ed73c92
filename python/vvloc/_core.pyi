"""Type stubs of the Rust extension ``vvloc._core`` (checked by ``python -m mypy.stubtest``)."""

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
