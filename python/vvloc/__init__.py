"""vvloc: prior-free 3-DoF multi-camera vehicle visual localization.

Networks run in PyTorch (:mod:`vvloc.nets`); BEV padding, interpolated rolling, yaw matching,
the coarse-to-fine translation search and descriptor retrieval run in the Rust extension
``vvloc._core`` behind the gateway :mod:`vvloc.kernels`. Conventions (frames, BEV indexing,
polar angles, roll, padding, pose signs) are those of DESIGN.md §3.
"""

from __future__ import annotations

import logging
import os

from vvloc import _core

__version__: str = _core.__version__

logging.getLogger("vvloc").addHandler(logging.NullHandler())


#: The most threads vvloc's kernel pool takes (the extension's bound).
MAX_THREADS = 1024


def set_num_threads(n: int) -> None:
    """Set the number of threads of vvloc's Rust kernel pool (``1 <= n <= 1024``).

    The default is ``VVLOC_NUM_THREADS`` or the number of available cores. Results are identical
    for any thread count.
    """
    import numpy as np

    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise TypeError(f"n: expected an int in [1, {MAX_THREADS}], got {type(n).__name__}")
    if not 1 <= int(n) <= MAX_THREADS:
        raise ValueError(f"n: expected an int in [1, {MAX_THREADS}], got {int(n)}")
    _core.set_num_threads(int(n))


def get_num_threads() -> int:
    """Return the number of threads of vvloc's Rust kernel pool."""
    return int(_core.get_num_threads())


#: The blanks around ``VVLOC_NUM_THREADS``'s digits that the pool skips (Rust's
#: ``char::is_ascii_whitespace``: space, tab, line feed, form feed, carriage return).
_ASCII_BLANKS = " \t\n\x0c\r"


def _check_threads_variable() -> None:
    """Warn when ``VVLOC_NUM_THREADS`` is set but is no int in [1, 1024] written in ASCII digits
    alone (blanks around them allowed): the pool then uses every core, as if it were unset, or
    1024 for a larger number, as the Rust pool reads it."""
    text = os.environ.get("VVLOC_NUM_THREADS")
    if text is None:
        return
    digits = text.strip(_ASCII_BLANKS)  # str.strip() would also take \x1c-\x1f, Rust's not
    if digits == "":
        return
    # not int() alone: it also takes "+4", "2_0" and other scripts' digits, which the pool
    # does not, and refuses more than 4300 digits (a ValueError at import)
    significant = digits.lstrip("0")  # int() counts leading zeros toward its limit too
    ok = (
        digits.isascii()
        and digits.isdigit()
        and len(significant) <= 4
        and 1 <= int(significant or "0") <= MAX_THREADS
    )
    if not ok:
        import warnings

        shown = repr(text) if len(text) <= 40 else f"{text[:20]!r}... ({len(text)} characters)"

        warnings.warn(
            f"VVLOC_NUM_THREADS={shown} is not an int in [1, {MAX_THREADS}]; vvloc's kernels use "
            f"{get_num_threads()} threads",
            RuntimeWarning,
            stacklevel=3,
        )


_check_threads_variable()

# A forked child (e.g. a DataLoader worker) has no pool threads: let it build its own. A fork
# waits until no thread is inside a DescriptorIndex call, so no child inherits a locked index.
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_core._reset_pool_after_fork)
    os.register_at_fork(
        before=_core._before_fork,
        after_in_parent=_core._after_fork_in_parent,
        after_in_child=_core._after_fork_in_child,
    )

from vvloc import kernels  # noqa: E402
from vvloc.retrieval import DescriptorIndex, Exclusion  # noqa: E402

# Heavy (torch-importing) parts load on first use, so `import vvloc` stays light.
_LAZY = {
    "Localizer": ("vvloc.localize.localizer", "Localizer"),
    "build_map": ("vvloc.localize.localizer", "build_map"),
    "LocalizationResult": ("vvloc.localize.localizer", "LocalizationResult"),
    "MapDatabase": ("vvloc.localize.mapdb", "MapDatabase"),
    "nets": ("vvloc.nets", None),
    "data": ("vvloc.data", None),
    "losses": ("vvloc.losses", None),
    "localize": ("vvloc.localize", None),
    "evaluate": ("vvloc.evaluate", None),
}


def __getattr__(name: str) -> object:
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        mod = importlib.import_module(module)
        return mod if attr is None else getattr(mod, attr)
    raise AttributeError(f"module 'vvloc' has no attribute {name!r}")


__all__ = [
    "DescriptorIndex",
    "Exclusion",
    "LocalizationResult",
    "Localizer",
    "MapDatabase",
    "__version__",
    "build_map",
    "get_num_threads",
    "kernels",
    "set_num_threads",
]
