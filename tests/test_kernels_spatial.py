"""Spatial kernels: Rust vs the literal reference vs the vectorised torch path (DESIGN.md §3–4)."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import vvloc
from memory_helpers import run_limited
from vvloc import kernels as K
from vvloc.reference import torch_spatial as TS

TOL = 1e-5


def field(rng: np.random.Generator, *shape: int) -> np.ndarray:
    return rng.standard_normal(shape).astype(np.float32)


def close(a: np.ndarray, b: np.ndarray, tol: float = TOL) -> None:
    assert a.shape == b.shape and a.dtype == np.float32
    np.testing.assert_allclose(a, b, rtol=tol, atol=tol)


# Shifts in metres: fractional, negative, integer multiples of g, zero, beyond the map.
shift_values = st.one_of(
    st.floats(-3.0, 3.0, allow_nan=False),
    st.integers(-8, 8).map(lambda k: k * 0.3),
    st.just(0.0),
    st.sampled_from([1e3, -1e6, 1e30]),
)


@settings(max_examples=40, deadline=None)
@given(
    shape=st.lists(st.integers(1, 6), min_size=1, max_size=4),
    shift=st.one_of(st.floats(-20, 20), st.integers(-9, 9).map(float), st.just(1e18 + 0.5)),
    data=st.data(),
)
def test_roll_interp_matches_reference(shape, shift, data):
    axis = data.draw(st.integers(-len(shape), len(shape) - 1))
    x = field(np.random.default_rng(len(shape)), *shape)
    close(K.roll_interp(x, shift, axis), K.roll_interp(x, shift, axis, backend="reference"))


def test_a_read_only_array_is_read_without_a_warning_by_either_backend():
    # torch.from_numpy warned on a read-only array (a memory-mapped map, a frozen batch)
    x = np.random.default_rng(0).normal(size=(8, 3)).astype(np.float32)
    x.setflags(write=False)
    for backend in ("rust", "reference"):
        out = K.roll_interp(x, 1.5, backend=backend)
        np.testing.assert_allclose(out, K.roll_interp(x.copy(), 1.5), atol=1e-6)


def test_roll_interp_is_torch_roll_at_integers_and_continuous():
    x = field(np.random.default_rng(0), 7, 3)
    np.testing.assert_array_equal(K.roll_interp(x, 3.0), torch.roll(torch.from_numpy(x), 3, 0))
    np.testing.assert_array_equal(K.roll_interp(x, -2.0, axis=1), np.roll(x, -2, axis=1))
    close(K.roll_interp(x, 3.0 - 1e-7), K.roll_interp(x, 3.0), 1e-5)
    half = 0.5 * (np.roll(x, 1, 0) + np.roll(x, 2, 0))
    close(K.roll_interp(x, 1.5), half)


@settings(max_examples=30, deadline=None)
@given(
    h=st.integers(1, 9),
    w=st.integers(1, 9),
    c=st.integers(1, 5),
    g=st.sampled_from([0.3, 0.25, 1.0]),
    t=st.lists(st.tuples(shift_values, shift_values), min_size=1, max_size=4),
)
def test_bev_pad_matches_algorithm_one(h, w, c, g, t):
    bev = field(np.random.default_rng(h * 10 + w), h, w, c)
    tr = np.array(t, dtype=np.float64)
    close(K.bev_pad(bev, tr, g), K.bev_pad(bev, tr, g, backend="reference"))


@settings(max_examples=30, deadline=None)
@given(
    shape=st.tuples(st.integers(1, 3), st.integers(1, 9), st.integers(1, 9), st.integers(1, 5)),
    batched=st.booleans(),
    num_angles=st.integers(1, 13),
    num_radii=st.integers(1, 7),
    g=st.sampled_from([0.3, 0.5]),
)
def test_polar_sample_matches_reference(shape, batched, num_angles, num_radii, g):
    bev = field(np.random.default_rng(sum(shape)), *shape)
    if not batched:
        bev = bev[0]
    got = K.polar_sample(bev, num_angles, num_radii, g)
    close(got, K.polar_sample(bev, num_angles, num_radii, g, backend="reference"))
    assert got.shape == (*bev.shape[:-3], num_angles, num_radii, bev.shape[-1])


@settings(max_examples=25, deadline=None)
@given(
    h=st.integers(1, 9),
    w=st.integers(1, 9),
    c=st.integers(1, 5),
    num_angles=st.integers(1, 9),
    num_radii=st.integers(1, 5),
    t=st.lists(st.tuples(shift_values, shift_values), min_size=1, max_size=3),
)
def test_pad_polar_equals_composition_and_reference(h, w, c, num_angles, num_radii, t):
    bev = field(np.random.default_rng(h + 7 * w), h, w, c)
    tr = np.array(t, dtype=np.float64)
    fused = K.pad_polar(bev, tr, num_angles, num_radii, 0.3)
    composed = K.polar_sample(K.bev_pad(bev, tr, 0.3), num_angles, num_radii, 0.3)
    close(fused, composed)
    close(fused, K.pad_polar(bev, tr, num_angles, num_radii, 0.3, backend="reference"))


def test_zero_shift_unchanged_and_huge_shift_all_ones():
    bev = field(np.random.default_rng(1), 6, 5, 4)
    out = K.bev_pad(bev, [[0.0, 0.0], [0.0, 1e6], [-50.0, 0.0]], 0.3)
    np.testing.assert_array_equal(out[0], bev)
    assert (out[1:] == 1.0).all()
    polar = K.pad_polar(bev, [[0.0, 0.0], [1e300, -1e300]], 8, 3, 0.3)
    np.testing.assert_array_equal(polar[0], K.polar_sample(bev, 8, 3, 0.3))
    assert (polar[1] == 1.0).all()
    # shifts in cells beyond float64 (1e300 m in cells of 1e-300 m): all ones, in both backends
    for backend in ("rust", "reference"):
        far = K.bev_pad(bev, [[1e300, 0.0], [1.0, -2.0]], 1e-300, backend=backend)
        assert (far == 1.0).all(), backend
        far = K.pad_polar(bev, [[0.0, 1.0]], 8, 3, 5e-324, backend=backend)
        assert (far == 1.0).all(), backend


def test_float32_translation_on_the_grid_is_an_exact_cell_shift():
    # 0.3 m in float32 is 1.0000000397 cells of 0.3 m: snapped to exactly one cell.
    bev = field(np.random.default_rng(2), 5, 4, 3)
    out = K.bev_pad(bev, np.array([[0.3, -0.6]], dtype=np.float32), 0.3)[0]
    np.testing.assert_array_equal(out[:4, 2:], bev[1:, :2])
    assert (out[4] == 1.0).all() and (out[:, :2] == 1.0).all()


def test_paper_size_once():
    rng = np.random.default_rng(3)
    bev = field(rng, 100, 100, 256)
    tr = np.array([[0.0, 0.0], [0.45, -1.2], [-1.5, 0.3]])
    got = K.pad_polar(bev, tr, 120, 40, 0.3)
    assert got.shape == (3, 120, 40, 256)
    close(got[1:2], K.pad_polar(bev, tr[1:2], 120, 40, 0.3, backend="reference"))
    close(got, K.polar_sample(K.bev_pad(bev, tr, 0.3), 120, 40, 0.3))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_torch_training_path_equals_kernels(dtype):
    rng = np.random.default_rng(4)
    bev = field(rng, 2, 11, 9, 6)
    tr = np.array([[0.0, 0.0], [0.3, -0.6], [0.41, 0.07], [-0.95, 1.3], [20.0, 0.0]])
    tol = TOL if dtype == torch.float64 else 1e-4  # float32 grid coordinates: ~n·2⁻²⁴ cells
    tb = torch.from_numpy(bev).to(dtype)
    tt = torch.from_numpy(tr)
    padded = TS.torch_bev_pad(tb, tt, 0.3)
    polar = TS.torch_polar_sample(tb, 10, 4, 0.3)
    fused = TS.torch_pad_polar(tb, tt, 10, 4, 0.3, chunk=2)
    for b in range(2):
        close(padded[b].float().numpy(), K.bev_pad(bev[b], tr, 0.3), tol)
        close(polar[b].float().numpy(), K.polar_sample(bev[b], 10, 4, 0.3), tol)
        close(fused[b].float().numpy(), K.pad_polar(bev[b], tr, 10, 4, 0.3), tol)


def test_torch_training_path_is_differentiable():
    tb = torch.randn(1, 8, 8, 3, dtype=torch.float64, requires_grad=True)
    out = TS.torch_pad_polar(tb, torch.tensor([[0.2, -0.1]]), 6, 3, 0.3)
    out.square().sum().backward()
    assert tb.grad is not None and tb.grad.abs().sum() > 0


def test_non_contiguous_float64_and_torch_inputs_are_converted():
    rng = np.random.default_rng(5)
    base = rng.standard_normal((7, 9, 12))
    bev = base[:, ::2, ::3]  # float64, non-contiguous
    tr = np.array([[0.1, 0.2], [0.5, -0.4]])[:, ::-1]
    bev32 = np.ascontiguousarray(bev, dtype=np.float32)
    want = K.pad_polar(bev32, np.ascontiguousarray(tr), 5, 3, 0.3)
    close(K.pad_polar(bev, tr, 5, 3, 0.3), want)
    close(K.pad_polar(torch.from_numpy(bev), torch.from_numpy(tr.copy()), 5, 3, 0.3), want)
    close(K.bev_pad(bev, tr, 0.3), K.bev_pad(bev.astype(np.float32), tr, 0.3, backend="reference"))
    close(K.polar_sample(bev, 5, 3, 0.3), K.polar_sample(bev, 5, 3, 0.3, backend="reference"))
    close(K.roll_interp(bev.T, 1.25, 1), K.roll_interp(bev.T, 1.25, 1, backend="reference"))


def test_one_and_two_threads_give_identical_results():
    rng = np.random.default_rng(6)
    bev = field(rng, 40, 30, 48)
    tr = rng.uniform(-2, 2, size=(17, 2))
    before = vvloc.get_num_threads()
    results = []
    try:
        for n in (1, 2):
            vvloc.set_num_threads(n)
            results.append(
                (
                    K.pad_polar(bev, tr, 30, 12, 0.3),
                    K.bev_pad(bev, tr, 0.3),
                    K.polar_sample(bev[None].repeat(3, 0), 30, 12, 0.3),
                    K.roll_interp(bev, 2.7, 1),
                )
            )
    finally:
        vvloc.set_num_threads(before)
    for a, b in zip(*results, strict=True):
        np.testing.assert_array_equal(a, b)


def test_python_threads_can_call_kernels_concurrently():
    rng = np.random.default_rng(7)
    bev = field(rng, 30, 30, 32)
    tr = rng.uniform(-1, 1, size=(9, 2))
    want = K.pad_polar(bev, tr, 24, 8, 0.3)
    errors: list[BaseException] = []

    def work() -> None:
        try:
            for _ in range(3):
                np.testing.assert_array_equal(K.pad_polar(bev, tr, 24, 8, 0.3), want)
        except BaseException as e:  # pragma: no cover - reported below
            errors.append(e)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors


BEV = np.zeros((4, 5, 2), dtype=np.float32)
TR = np.zeros((1, 2))


@pytest.mark.parametrize("backend", ["rust", "reference"])
@pytest.mark.parametrize(
    ("call", "exc", "arg"),
    [
        (lambda b: K.bev_pad(np.zeros((4, 5)), TR, 0.3, backend=b), ValueError, "bev"),
        (lambda b: K.bev_pad(np.zeros((0, 5, 2)), TR, 0.3, backend=b), ValueError, "bev"),
        (lambda b: K.bev_pad(BEV, np.zeros((2, 3)), 0.3, backend=b), ValueError, "translations"),
        (lambda b: K.bev_pad(BEV, np.zeros(2), 0.3, backend=b), ValueError, "translations"),
        (lambda b: K.bev_pad(BEV, [[0.0, np.nan]], 0.3, backend=b), ValueError, "translations"),
        (lambda b: K.bev_pad(BEV, "t", 0.3, backend=b), TypeError, "translations"),
        (lambda b: K.bev_pad(BEV, TR, 0.0, backend=b), ValueError, "grid_size"),
        (lambda b: K.bev_pad(BEV, TR, -1.0, backend=b), ValueError, "grid_size"),
        (lambda b: K.bev_pad(BEV, TR, "0.3", backend=b), TypeError, "grid_size"),
        (lambda b: K.bev_pad(np.full((4, 5, 2), np.inf), TR, 0.3, backend=b), ValueError, "bev"),
        (lambda b: K.bev_pad("map", TR, 0.3, backend=b), TypeError, "bev"),
        (
            lambda b: K.polar_sample(np.zeros((2, 2, 4, 5, 6)), 4, 4, 0.3, backend=b),
            ValueError,
            "bev",
        ),
        (lambda b: K.polar_sample(BEV, 0, 4, 0.3, backend=b), ValueError, "num_angles"),
        (lambda b: K.polar_sample(BEV, 4, 0, 0.3, backend=b), ValueError, "num_radii"),
        (lambda b: K.polar_sample(BEV, 4.0, 4, 0.3, backend=b), TypeError, "num_angles"),
        (lambda b: K.polar_sample(BEV, 4, 4, np.nan, backend=b), ValueError, "grid_size"),
        (lambda b: K.pad_polar(BEV, TR, 4, -1, 0.3, backend=b), ValueError, "num_radii"),
        (lambda b: K.pad_polar(BEV[None], TR, 4, 4, 0.3, backend=b), ValueError, "bev"),
        (lambda b: K.pad_polar(BEV, TR, 4, 4, 0.0, backend=b), ValueError, "grid_size"),
        (lambda b: K.roll_interp(BEV, 1.0, 3, backend=b), ValueError, "axis"),
        (lambda b: K.roll_interp(BEV, 1.0, -4, backend=b), ValueError, "axis"),
        (lambda b: K.roll_interp(BEV, 1.0, 1.5, backend=b), TypeError, "axis"),
        (lambda b: K.roll_interp(BEV, np.inf, backend=b), ValueError, "shift"),
        (lambda b: K.roll_interp(np.float32(1.0), 1.0, backend=b), ValueError, "x"),
        # more dimensions than the Rust binding's arrays hold: was a PanicException
        (lambda b: K.roll_interp(np.ones((1,) * 33), 0.5, backend=b), ValueError, "x: .* 32"),
        # nested sequences of unequal lengths: was numpy's "inhomogeneous shape" alone
        (lambda b: K.bev_pad(BEV, [[0.3], [0.3, 0.0]], 0.3, backend=b), ValueError, "transl"),
        (lambda b: K.roll_interp([[1.0], [1.0, 2.0]], 0.5, backend=b), ValueError, "x: .*rect"),
        # a polar radius past float64: the reference said OverflowError without a name
        (lambda b: K.polar_sample(BEV, 4, 4, 1e308, backend=b), ValueError, "grid_size"),
        (lambda b: K.pad_polar(BEV, TR, 4, 4, 1e308, backend=b), ValueError, "grid_size"),
    ],
)
def test_bad_input_names_the_argument(backend, call, exc, arg):
    with pytest.raises(exc, match=rf"^{arg}"):
        call(backend)


def test_bad_backend():
    with pytest.raises(ValueError, match="backend"):
        K.bev_pad(BEV, TR, 0.3, backend="cuda")  # type: ignore[arg-type]


def test_extension_rejects_bad_values_without_panicking():
    from vvloc import _core

    with pytest.raises(ValueError, match=r"^translations"):
        _core.pad_polar(BEV, np.array([[np.nan, 0.0]]), 3, 3, 0.3)
    with pytest.raises(ValueError, match=r"^num_angles"):
        _core.polar_sample(BEV, -1, 3, 0.3)
    with pytest.raises(ValueError, match=r"^axis"):
        _core.roll_interp(BEV, 1.0, -1)
    with pytest.raises(ValueError, match=r"^grid_size"):
        _core.bev_pad(BEV, TR, float("inf"))
    # more dimensions than rust-numpy's views hold (the gateway refuses them first)
    deep = np.zeros((1,) * 33, np.float32)
    with pytest.raises(ValueError, match=r"^x: expected at most 32 dimensions, got 33"):
        _core.roll_interp(deep, 0.5, 0)
    with pytest.raises(ValueError, match=r"^bev: expected at most 32 dimensions, got 33"):
        _core.polar_sample(deep, 2, 2, 0.3)


def test_outputs_larger_than_memory_raise_memory_error():
    q = np.zeros((8, 8, 4), np.float32)
    cases = [
        (lambda: K.polar_sample(q, 2**40, 1, 0.3), "num_angles"),
        (lambda: K.polar_sample(np.zeros((8, 8, 0), np.float32), 2**40, 1, 0.3), "num_angles"),
        (lambda: K.polar_sample(q, 2**32, 2**32, 0.3), "num_angles"),  # T·R wraps usize
        (lambda: K.pad_polar(q, [[0.0, 0.0]], 2**62, 4, 0.3), "num_angles"),
        (
            lambda: K.bev_pad(np.zeros((1000, 1000, 8), np.float32), np.zeros((1000, 2)), 0.3),
            "translations",
        ),  # 32 GB
    ]
    for call, name in cases:
        with pytest.raises(MemoryError, match=f"^{name}: the result needs"):
            call()
    # sizes beyond what the kernels' integers hold are named (not 'int too big to convert')
    with pytest.raises(ValueError, match=r"^num_angles: expected an int <= "):
        K.polar_sample(q, 2**70, 1, 0.3)
    # and so are ints beyond a float (not a bare OverflowError)
    with pytest.raises(ValueError, match=r"^grid_size: expected a finite value"):
        K.bev_pad(q, [[0.0, 0.0]], 10**400)
    with pytest.raises(ValueError, match=r"^shift: expected a finite value"):
        K.roll_interp(q, -(10**400))


@pytest.mark.parametrize("backend", ["rust", "reference"])
def test_polar_outputs_larger_than_memory_are_named_by_both_backends(backend):
    q = np.zeros((8, 8, 4), np.float32)
    for call in (
        lambda: K.polar_sample(q, 10**12, 2, 0.3, backend=backend),  # 7 TiB
        lambda: K.polar_sample(q, 2**62, 2**62, 0.3, backend=backend),  # past the address space
        lambda: K.pad_polar(q, [[0.0, 0.0]], 10**12, 2, 0.3, backend=backend),
    ):
        with pytest.raises(MemoryError, match=r"^num_angles: the result needs"):
            call()


@pytest.mark.parametrize("backend", ["rust", "reference"])
def test_bev_pad_outputs_larger_than_memory_are_named_by_both_backends(backend):
    # the reference let numpy's own errors through ("Unable to allocate 29.1 TiB", "array is
    # too big") where polar_sample and pad_polar named the argument
    for bev, n in [
        (np.zeros((1000, 1000, 8), np.float32), 1_000_000),  # 32 TB
        (np.zeros((2**30, 2**30, 0), np.float32), 8),  # empty, yet past numpy's bound
    ]:
        with pytest.raises(MemoryError, match=r"^translations: the result needs"):
            K.bev_pad(bev, np.zeros((n, 2)), 0.3, backend=backend)


def test_roll_interp_out_of_memory_is_a_memory_error_not_an_abort():
    # its output was an infallible Rust allocation: under an address-space limit the process
    # aborted where bev_pad raised MemoryError
    lines = run_limited("""
import numpy as np
from vvloc import kernels as K
x = np.ones((100_000_000,), np.float32)  # 400 MB, allocated before the limit
limit(200)
attempt("roll_interp", lambda: K.roll_interp(x, 0.5))
""")
    assert lines == [
        "roll_interp MemoryError x: the result needs 100000000 elements of 4 bytes, "
        "more than this machine can allocate"
    ], lines


@pytest.mark.parametrize("value", [np.finfo(np.float32).max, -np.finfo(np.float32).max])
def test_finite_maps_at_float32s_maximum_give_finite_outputs(value):
    # the blend's float32 weights can sum to 1 + 1 ulp: at ±float32 max the Rust kernels
    # returned ±inf where the reference is finite
    tr = [[0.1, 0.07], [0.33, -0.21], [0.0, 0.0]]
    for shape in [(2, 2, 1), (6, 5, 3), (7, 9, 40)]:
        bev = np.full(shape, value, np.float32)
        for call in (
            lambda b, q=bev: K.polar_sample(q, 7, 3, 0.3, backend=b),
            lambda b, q=bev: K.polar_sample(q, 4, 1, 0.3, backend=b),
            lambda b, q=bev: K.bev_pad(q, tr, 0.3, backend=b),
            lambda b, q=bev: K.pad_polar(q, tr, 7, 3, 0.3, backend=b),
        ):
            got, want = call("rust"), call("reference")
            assert np.isfinite(got).all() and np.isfinite(want).all()
            close(got, want)


def test_empty_outputs_whose_other_axes_no_array_can_have_are_errors_not_crashes():
    """An output with a 0 axis holds nothing, yet numpy bounds its other axes (their product,
    in bytes, must fit a signed 64-bit size): (0, 4, 2, 2^59) is a MemoryError naming the
    argument, not a segfault in numpy. In a child process, so a crash fails only this test."""
    import subprocess
    import sys

    code = """
import numpy as np
from vvloc import kernels as K
for call in (lambda: K.polar_sample(np.zeros((0, 1, 1, 2**59), np.float32), 4, 2, 0.3),
             lambda: K.polar_sample(np.zeros((0, 1, 1, 2**42), np.float32), 1024, 1024, 0.3),
             lambda: K.bev_pad(np.zeros((2**30, 2**30, 0), np.float32), np.zeros((8, 2)), 0.3)):
    try:
        call()
    except MemoryError as e:
        print("MemoryError", e)
print(K.polar_sample(np.zeros((0, 1, 1, 2**20), np.float32), 4, 2, 0.3).shape)
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 4, r.stdout
    assert lines[0].startswith("MemoryError num_angles: the result needs")
    assert lines[1].startswith("MemoryError num_angles: the result needs")
    assert lines[2].startswith("MemoryError translations: the result needs")
    assert lines[3] == "(0, 4, 2, 1048576)"


def test_vast_broadcast_inputs_and_overflowing_radii_are_errors_not_aborts():
    """A broadcast view of a few bytes standing for terabytes, passed to the raw extension
    (the gateway copies first and fails in numpy), is a MemoryError, and a grid size whose
    polar radius overflows is a ValueError naming it; run in a child process, so that an
    abort would fail this test instead of ending the run."""
    import subprocess
    import sys

    code = """
import numpy as np
from vvloc import _core, kernels
vast = np.broadcast_to(np.zeros(1, np.float32), (2**40,))
bev = np.broadcast_to(np.zeros((1, 1, 1), np.float32), (2**20, 2**10, 2**10))
for call in (lambda: _core.roll_interp(vast, 1.0, 0),
             lambda: _core.bev_pad(bev, np.zeros((1, 2)), 0.3)):
    try:
        call()
    except MemoryError as e:
        print("MemoryError", e)
try:
    kernels.polar_sample(np.full((8, 8, 1), 2, np.float32), 4, 2, 1e308)
except ValueError as e:
    print("ValueError", e)
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 3, r.stdout
    assert lines[0].startswith("MemoryError x:") and lines[1].startswith("MemoryError bev:")
    assert lines[2].startswith("ValueError grid_size:")


def test_huge_pages_can_be_turned_off_and_change_no_value(tmp_path):
    # VVLOC_MADVISE_HUGEPAGE=0 (read once per process) trades the 2 MiB pages' occasional
    # compaction stall for 4 KiB pages; the output must be the same bytes either way
    import subprocess
    import sys

    code = (
        "import numpy as np, sys; from vvloc import kernels as K; "
        "rng = np.random.default_rng(0); bev = rng.standard_normal((30, 30, 64), np.float32); "
        "t = rng.uniform(-1, 1, (40, 2)); "
        "np.save(sys.argv[1], K.pad_polar(bev, t, 60, 20, 0.3))"  # 12 MB: above 2 MiB
    )
    for value in ("1", "0"):
        env = {**os.environ, "VVLOC_MADVISE_HUGEPAGE": value}
        run = subprocess.run(
            [sys.executable, "-c", code, str(tmp_path / f"{value}.npy")], env=env, check=False
        )
        assert run.returncode == 0
    assert np.array_equal(np.load(tmp_path / "1.npy"), np.load(tmp_path / "0.npy"))


def _misaligned(a: np.ndarray) -> np.ndarray:
    """A C-contiguous copy of ``a`` whose elements lie one byte off their alignment."""
    buf = np.zeros(a.nbytes + 1, np.uint8)
    out = np.frombuffer(buf.data, dtype=a.dtype, count=a.size, offset=1).reshape(a.shape)
    out[...] = a
    assert out.flags.c_contiguous and not out.flags.aligned
    return out


def test_misaligned_arrays_are_refused_by_the_extension_and_copied_by_the_gateway():
    """A buffer viewed at an odd byte offset reached ndarray's views and slices unchecked: a
    panic in a debug build, reads through misaligned references (undefined behaviour) in
    release. ``_core`` refuses it naming the argument; the gateways copy it first."""
    from vvloc import _core

    rng = np.random.default_rng(0)
    bev = rng.standard_normal((6, 6, 3)).astype(np.float32)
    desc = rng.standard_normal((2, 8, 4)).astype(np.float32)
    tr = np.array([[0.2, -0.4]])
    odd_bev, odd_desc, odd_tr = _misaligned(bev), _misaligned(desc), _misaligned(tr)
    refused = [
        ("bev", lambda: _core.bev_pad(odd_bev, tr, 0.3)),
        ("translations", lambda: _core.bev_pad(bev, odd_tr, 0.3)),
        ("translations", lambda: _core.pad_polar(bev, odd_tr, 4, 2, 0.3)),
        ("bev", lambda: _core.polar_sample(odd_bev, 4, 2, 0.3)),
        ("x", lambda: _core.roll_interp(odd_bev, 0.5, 0)),
        ("a", lambda: _core.matching_cost(odd_desc, desc)),
        ("tgt", lambda: _core.yaw_costs(desc, odd_desc)),
        ("src", lambda: _core.estimate_yaw(odd_desc, desc)),
        ("src", lambda: _core.rerank(odd_desc, desc)),
        (
            "descriptors",
            lambda: _core.DescriptorIndex(odd_desc.reshape(8, 8), "float32", None, None),
        ),
    ]
    for name, call in refused:
        with pytest.raises(ValueError, match=rf"^{name}: expected an aligned array"):
            call()
    np.testing.assert_array_equal(K.bev_pad(odd_bev, odd_tr, 0.3), K.bev_pad(bev, tr, 0.3))
    np.testing.assert_array_equal(K.yaw_costs(odd_desc, desc), K.yaw_costs(desc, desc))
    index = vvloc.DescriptorIndex(_misaligned(desc.reshape(8, 8)))
    np.testing.assert_array_equal(index.descriptors, desc.reshape(8, 8))


def test_an_empty_misaligned_array_is_refused_or_copied_too():
    # numpy calls every empty array aligned, whatever its address; ndarray asserts the pointer
    from vvloc import _core

    buf = np.zeros(64, np.uint8)
    empty = np.ndarray((0, 4, 5), np.float32, buffer=buf, offset=1)
    assert empty.flags.aligned and empty.ctypes.data % 4 == 1
    with pytest.raises(ValueError, match=r"^a: expected an aligned array"):
        _core.matching_cost(empty, np.zeros((0, 4, 5), np.float32))
    assert K.matching_cost(empty, np.zeros((0, 4, 5), np.float32)).shape == (0,)


def test_polar_sampling_needs_no_table_of_its_sample_points():
    # a table of 16 bytes a point (T·R points) was built before the output's size was checked,
    # also for an empty output: 8192 × 8192 bins of C = 0 took 1 GiB, and a T·R near 1e9 could
    # pass the allocation probe and fill 16 GiB
    lines = run_limited("""
import numpy as np
from vvloc import kernels as K
bev = np.ones((4, 4, 0), np.float32)
limit(64)
attempt("empty", lambda: print(K.polar_sample(bev, 8192, 8192, 1.0).shape))
attempt("pad_polar", lambda: print(K.pad_polar(bev, [[0.0, 0.0]], 8192, 8192, 1.0).shape))
""")
    assert lines == ["(8192, 8192, 0)", "empty fitted", "(1, 8192, 8192, 0)", "pad_polar fitted"]
