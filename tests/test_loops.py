"""Sequence-consistent loop candidates (vvloc.localize.loops) on hand-made descriptors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vvloc.localize.loops import (
    confirm_sequence,
    descriptor_loop_candidates,
    sequence_distance,
    sweep_radius,
)


def brute_sequence_distance(g, sessions, seqs, i, j, half, window=0):
    """Reference: each session's rows sorted by sequence number, neighbours by position; a
    neighbour pair of one session within ``window`` sequence numbers is not admissible."""
    rows = {s: sorted(np.flatnonzero(sessions == s), key=lambda r: seqs[r]) for s in set(sessions)}
    place = {r: (s, k) for s, rr in rows.items() for k, r in enumerate(rr)}

    def nb(r, k):
        s, p = place[r]
        return rows[s][p + k] if 0 <= p + k < len(rows[s]) else None

    out = []
    for a, b in zip(i, j, strict=True):
        best = np.inf
        for sign in (1, -1):
            ds = []
            for k in range(-half, half + 1):
                x, y = nb(a, k), nb(b, sign * k)
                if x is None or y is None:
                    break
                if sessions[x] == sessions[y] and abs(seqs[x] - seqs[y]) <= window:
                    break
                ds.append(float(np.linalg.norm(g[x] - g[y])))
            else:
                best = min(best, sum(ds) / len(ds))
        out.append(best)
    return np.array(out)


def two_drives(n: int = 12, reverse: bool = False, d: int = 8, seed: int = 0):
    """Session 0 drives places 0..n-1; session 1 the same places (backwards if ``reverse``) with
    small descriptor noise; sequence numbers of session 1 have gaps (keyframe selection)."""
    rng = np.random.default_rng(seed)
    places = rng.standard_normal((n, d))
    places /= np.linalg.norm(places, axis=1, keepdims=True)
    second = places[::-1] if reverse else places
    g = np.concatenate([places, second + 0.01 * rng.standard_normal((n, d))])
    sessions = np.repeat([0, 1], n)
    seqs = np.concatenate([np.arange(n), 3 * np.arange(n) + 100])
    return g, sessions, seqs


@settings(max_examples=40, deadline=None)
@given(
    st.integers(2, 30),
    st.integers(1, 3),
    st.integers(0, 3),
    st.integers(0, 6),
    st.integers(0, 10_000),
)
def test_sequence_distance_matches_the_brute_force_reference(n, n_sessions, half, window, seed):
    rng = np.random.default_rng(seed)
    g = rng.standard_normal((n, 4))
    sessions = rng.integers(0, n_sessions, n)
    seqs = rng.permutation(5 * n)[:n]  # unsorted rows, gaps between sequence numbers
    i, j = rng.integers(0, n, (2, 3 * n))
    got = sequence_distance(g, sessions, seqs, i, j, half, window)
    want = brute_sequence_distance(g, sessions, seqs, i, j, half, window)
    np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
    fin = np.isfinite(want)
    np.testing.assert_allclose(got[fin], want[fin], rtol=1e-12, atol=1e-12)


def test_half_window_zero_is_the_pair_distance():
    g, sessions, seqs = two_drives()
    i, j = np.array([0, 3, 11]), np.array([12, 20, 23])
    got = sequence_distance(g, sessions, seqs, i, j, 0)
    np.testing.assert_allclose(got, np.linalg.norm(g[i] - g[j], axis=1))


@pytest.mark.parametrize("reverse", [False, True])
def test_a_revisit_in_either_direction_is_consistent(reverse):
    g, sessions, seqs = two_drives(reverse=reverse)
    a = 5
    b = 12 + (12 - 1 - a if reverse else a)  # session 1's row of the same place
    d = sequence_distance(g, sessions, seqs, np.array([a]), np.array([b]), 2)
    assert d[0] < 0.05  # noise 0.01 per component, D = 8
    # one place off: every neighbour pair is two different places
    off = sequence_distance(g, sessions, seqs, np.array([a]), np.array([b + 1]), 2)
    assert off[0] > 0.5


def test_a_window_leaving_the_session_gives_inf():
    g, sessions, seqs = two_drives(n=6)
    # row 0 has no predecessor; its revisit (row 6) has none either: no direction is complete
    d = sequence_distance(g, sessions, seqs, np.array([0, 2]), np.array([6, 8]), 1)
    assert np.isinf(d[0]) and np.isfinite(d[1])


def test_an_isolated_look_alike_is_rejected_by_the_sequence_check():
    g, sessions, seqs = two_drives(n=12)
    # session 1's frame at place 7 looks like place 3 (the other floor's copy of it)
    look = 12 + 7
    g[look] = g[3] + 1e-4
    single = descriptor_loop_candidates(g, sessions, seqs, radius=0.1, window=2, sequence=0)
    pairs = set(zip(single.i.tolist(), single.j.tolist(), strict=True))
    assert (3, look) in pairs
    seq = descriptor_loop_candidates(g, sessions, seqs, radius=0.1, window=2, sequence=1)
    seq_pairs = set(zip(seq.i.tolist(), seq.j.tolist(), strict=True))
    assert (3, look) not in seq_pairs
    # the true revisits with a full window survive, scored by max(pair, sequence) distance
    assert {(p, 12 + p) for p in range(1, 11) if p not in (6, 7, 8)} <= seq_pairs
    assert np.all(seq.distance < 0.1)
    full = sequence_distance(g, sessions, seqs, seq.i, seq.j, 1)
    pair = np.linalg.norm(g[seq.i] - g[seq.j], axis=1)  # the index's distances are float32
    np.testing.assert_allclose(seq.distance, np.maximum(full, pair), atol=1e-4)


def test_neighbour_pairs_inside_the_temporal_window_do_not_count():
    """Rows of one session, keyframes 10 sequence numbers apart, the pair (3, 6) and L = 1: the
    reverse direction pairs (2, 7), (3, 6), (4, 5), and (4, 5) are temporal neighbours at
    window 10; the forward direction pairs (2, 5), (3, 6), (4, 7), 30 sequence numbers apart."""
    rng = np.random.default_rng(1)
    g = rng.standard_normal((9, 4))
    g[6], g[5] = g[3], g[4]  # the reverse direction looks good: two of its pairs are equal
    sessions = np.zeros(9, dtype=np.int64)
    seqs = 10 * np.arange(9)
    forward = np.mean([np.linalg.norm(g[a] - g[a + 3]) for a in (2, 3, 4)])
    reverse = np.linalg.norm(g[2] - g[7]) / 3
    assert reverse < forward
    i, j = np.array([3]), np.array([6])
    assert sequence_distance(g, sessions, seqs, i, j, 1)[0] == pytest.approx(reverse)
    assert sequence_distance(g, sessions, seqs, i, j, 1, window=10)[0] == pytest.approx(forward)
    # with window 30 the forward pairs are temporal neighbours too: no complete direction
    assert np.isinf(sequence_distance(g, sessions, seqs, i, j, 1, window=30)[0])
    # a keyframe is never compared with itself: (4, 4) in the reverse direction of (3, 5)
    g[5] = g[3]
    fwd_35 = np.mean([np.linalg.norm(g[a] - g[a + 2]) for a in (2, 3, 4)])
    got = sequence_distance(g, sessions, seqs, i, np.array([5]), 1)[0]
    assert got == pytest.approx(fwd_35)


def test_a_window_longer_than_every_session_gives_inf():
    g, sessions, seqs = two_drives(n=4)
    d = sequence_distance(g, sessions, seqs, np.array([1, 2]), np.array([5, 6]), 2)
    assert np.isinf(d).all() and d.dtype == np.float64
    empty = sequence_distance(g, sessions, seqs, np.array([], np.int64), np.array([], np.int64), 1)
    assert empty.shape == (0,)


def test_bad_arguments_name_the_argument():
    g, sessions, seqs = two_drives(n=4)
    one = np.array([0])
    with pytest.raises(ValueError, match="half_window"):
        sequence_distance(g, sessions, seqs, one, one, -1)
    with pytest.raises(ValueError, match="window"):
        sequence_distance(g, sessions, seqs, one, one, 1, window=-1)
    with pytest.raises(TypeError, match="i: expected an integer array"):
        sequence_distance(g, sessions, seqs, np.array([0.9]), one, 1)
    with pytest.raises(TypeError, match="sessions: expected an integer array"):
        sequence_distance(g, sessions + 0.5, seqs, one, one, 1)
    with pytest.raises(TypeError, match="sequence"):
        descriptor_loop_candidates(g, sessions, seqs, sequence=True)
    with pytest.raises(ValueError, match="sessions, seqs"):
        sequence_distance(g, sessions[:3], seqs, one, one, 1)
    with pytest.raises(ValueError, match="i, j"):
        sequence_distance(g, sessions, seqs, one, np.array([0, 1]), 1)
    with pytest.raises(ValueError, match="i, j"):
        sequence_distance(g, sessions, seqs, one, np.array([8]), 1)
    with pytest.raises(ValueError, match="descriptors"):
        sequence_distance(g[0], sessions, seqs, one, one, 1)


def random_drives(n: int, sessions: int = 3, d: int = 16, seed: int = 0):
    rng = np.random.default_rng(seed)
    g = rng.standard_normal((n, d)).astype(np.float32)
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    sess = np.arange(n) % sessions
    seqs = np.arange(n) // sessions
    return g, sess, seqs


@pytest.mark.parametrize("max_pairs", [1, 7, 50, 400])
def test_sweep_radius_is_exact_on_small_sets(max_pairs):
    g, sess, seqs = random_drives(60)
    full = descriptor_loop_candidates(g, sess, seqs, radius=1.2, window=2)
    r = sweep_radius(g, sess, seqs, max_pairs, window=2, r_max=1.2)
    got = descriptor_loop_candidates(g, sess, seqs, radius=r, window=2)
    assert len(got.i) <= max_pairs
    if len(full.i) <= max_pairs:
        assert r == 1.2
    else:  # the largest such radius: one step beyond it holds more pairs than allowed
        more = descriptor_loop_candidates(g, sess, seqs, radius=r * (1 + 1e-6), window=2)
        assert len(more.i) > max_pairs


def test_sweep_radius_estimates_large_sets():
    g, sess, seqs = random_drives(3000, d=8, seed=1)
    budget = 200_000
    r = sweep_radius(g, sess, seqs, budget, window=2, r_max=1.0, sample=256)
    n = len(descriptor_loop_candidates(g, sess, seqs, radius=r, window=2).i)
    assert 0.8 * budget <= n <= 1.2 * budget  # sampled rows scale to all rows
    with pytest.raises(ValueError, match="max_pairs"):
        sweep_radius(g, sess, seqs, 0)
    with pytest.raises(TypeError, match="max_pairs"):
        sweep_radius(g, sess, seqs, 10.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="r_max"):
        sweep_radius(g, sess, seqs, 10, r_max=0.0)
    with pytest.raises(ValueError, match="sample"):
        sweep_radius(g, sess, seqs, 10, sample=0)


@pytest.mark.parametrize("half", [1, 2])
def test_confirming_single_candidates_equals_the_sequence_query(half):
    g, sess, seqs = random_drives(90, sessions=3, d=4, seed=2)
    single = descriptor_loop_candidates(g, sess, seqs, radius=0.9, window=2)
    got = confirm_sequence(single, g, sess, seqs, 0.9, half, window=2)
    want = descriptor_loop_candidates(g, sess, seqs, radius=0.9, window=2, sequence=half)
    assert 0 < len(want.i) < len(single.i)
    np.testing.assert_array_equal(got.i, want.i)
    np.testing.assert_array_equal(got.j, want.j)
    np.testing.assert_array_equal(got.distance, want.distance)
