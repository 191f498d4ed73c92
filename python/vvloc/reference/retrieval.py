"""Brute-force reference of descriptor retrieval (numpy, float64), the oracle of the Rust index.

Distances are L2 (not squared), computed in float64 with the same formula as the Rust index,
``sqrt(max(0, ‖q‖² + ‖x‖² − 2 q·x))``; results are sorted by distance then index.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


def distances(queries: npt.ArrayLike, descriptors: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """All L2 distances, float64 (nq, N), between queries (nq, d) and descriptors (N, d)."""
    q = np.asarray(queries, dtype=np.float64)
    x = np.asarray(descriptors, dtype=np.float64)
    sq = (q * q).sum(1)[:, None] + (x * x).sum(1)[None, :] - 2.0 * q @ x.T
    return np.sqrt(np.maximum(sq, 0.0))


def excluded(
    map_groups: npt.ArrayLike,
    map_seqs: npt.ArrayLike,
    query_groups: npt.ArrayLike,
    query_seqs: npt.ArrayLike,
    window: int,
    whole_group: bool = False,
) -> npt.NDArray[np.bool_]:
    """Exclusion mask (nq, N): same group and (whole group or |seq difference| <= window).

    Sequence numbers are int64; their difference is taken exactly in uint64 (``ms - qs`` in
    int64 overflows when the two lie near opposite ends of the range)."""
    mg, qg = np.asarray(map_groups)[None, :], np.asarray(query_groups)[:, None]
    ms = np.asarray(map_seqs, dtype=np.int64)[None, :]
    qs = np.asarray(query_seqs, dtype=np.int64)[:, None]
    same = mg == qg
    if whole_group:
        return same
    um, uq = ms.astype(np.uint64), qs.astype(np.uint64)  # two's complement: wraps exactly
    gap = np.where(ms >= qs, um - uq, uq - um)  # |ms - qs| in [0, 2^64), exact
    return same & (gap <= np.uint64(window))


def topk(
    queries: npt.ArrayLike,
    descriptors: npt.ArrayLike,
    k: int,
    mask: npt.NDArray[np.bool_] | None = None,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """The k nearest descriptors of each query, (indices int64 (nq, k), distances (nq, k)).

    ``mask`` (nq, N) marks excluded entries. Rows are padded with -1 / +inf when fewer than k
    entries are eligible.
    """
    dist = distances(queries, descriptors)
    nq, n = dist.shape
    idx = np.full((nq, k), -1, dtype=np.int64)
    out = np.full((nq, k), np.inf)
    for i in range(nq):
        keep = np.arange(n) if mask is None else np.flatnonzero(~mask[i])
        order = keep[np.lexsort((keep, dist[i, keep]))][:k]
        idx[i, : len(order)] = order
        out[i, : len(order)] = dist[i, order]
    return idx, out


def radius(
    queries: npt.ArrayLike,
    descriptors: npt.ArrayLike,
    r: float,
    mask: npt.NDArray[np.bool_] | None = None,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """Every descriptor at distance < r of each query, CSR (offsets, indices, distances)."""
    dist = distances(queries, descriptors)
    offsets, idx, out = [0], [], []
    for i in range(dist.shape[0]):
        hit = dist[i] < r
        if mask is not None:
            hit &= ~mask[i]
        cand = np.flatnonzero(hit)
        cand = cand[np.lexsort((cand, dist[i, cand]))]
        idx.append(cand)
        out.append(dist[i, cand])
        offsets.append(offsets[-1] + len(cand))
    cat = np.concatenate
    return (
        np.asarray(offsets, dtype=np.int64),
        cat(idx).astype(np.int64) if idx else np.zeros(0, np.int64),
        cat(out) if out else np.zeros(0),
    )
