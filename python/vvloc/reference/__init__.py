"""Pure-Python (numpy/torch) reference implementations of every Rust kernel.

They are literal and readable, follow the paper's formulas and DESIGN.md §3, and serve as the
tests' oracle and the benchmarks' baseline. They are not meant to be fast.
"""

from vvloc.reference.spatial import bev_pad as bev_pad
from vvloc.reference.spatial import pad_polar as pad_polar
from vvloc.reference.spatial import polar_sample as polar_sample
from vvloc.reference.spatial import roll_interp as roll_interp
