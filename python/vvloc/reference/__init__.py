"""Pure-Python (numpy/torch) reference implementations of every Rust kernel.

They are literal and readable, follow the paper's formulas and DESIGN.md §3, and serve as the
tests' oracle and the benchmarks' baseline. They are not meant to be fast.
"""
