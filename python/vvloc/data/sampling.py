"""Ground-truth neighbours: triplet sampling with hard-sample mining, and evaluation splits.

Neighbours are found with ``scipy.spatial.cKDTree`` on (x, y, level · floor_separation): frames
on different storeys of a garage are different places even at the same (x, y), so a large
``floor_separation`` keeps them apart (and makes them valid negatives). The level is the floor,
offset by ``WORLD_LEVELS`` per dataset when a sampler draws from several datasets (worlds):
frames of different worlds are never positives, whatever their coordinates.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from vvloc._checks import flag, int_array, positive_int
from vvloc._io import list_entries
from vvloc.data.frame import Dataset, Frame
from vvloc.data.vvloc_format import rig_meta

FLOOR_SEPARATION = 1000.0
#: Levels reserved per world (dataset) when a sampler spans several: floors must stay below it.
WORLD_LEVELS = 1000


def _triplets(triplets: Any) -> np.ndarray:
    """(T, 3) int64 frame-id triplets, named ``triplets`` otherwise (rows neither truncated from
    floats nor refolded from another shape)."""
    return int_array(triplets, "triplets", "(T, 3)", 2, 3)


def _positions(poses: np.ndarray, floors: np.ndarray, floor_separation: float) -> np.ndarray:
    return np.column_stack([poses[:, 0], poses[:, 1], floors.astype(np.float64) * floor_separation])


class TripletSampler:
    """Seeded (anchor, positive, negative) triplets across the sessions of a dataset.

    A positive lies within ``pos_radius`` metres of the anchor (same floor) in *another* session
    (``cross_session=True``, the default) or any other frame; with ``revisit_gap`` N > 0 also a
    frame of the anchor's own session at least N frames away (a drive that returns to a place,
    e.g. a dataset of single long sessions; nearer frames are the same pass). A negative lies
    beyond ``neg_radius`` metres (or on another floor); an anchor needs both. Triplets are
    (T, 3) int64 arrays of *global* frame ids; :meth:`locate` and :meth:`frame` map an id back
    to (session, index) and a Frame.

    Hard-sample mining: :meth:`mark_hard` adds triplets the model got wrong to a pool; each
    :meth:`sample` call draws up to ``hard_fraction`` of its triplets from that pool until
    :meth:`resolve` removes them, i.e. they are re-drawn until the model gets them right.
    :meth:`update` does both from a per-triplet correctness mask. The draws walk the pool in
    insertion order from a cursor, cycling. The cursor is a position, not a triplet: resolving
    triplets before it shifts the rest under it, so some wait a lap longer than "oldest first"
    would have them wait (with the committed step 1's pool of 600-1 700 triplets and 350 hard
    slots an epoch, up to about 17 epochs instead of 5). The committed models were trained
    this way; a change would retrain them differently, so it waits for the next retraining.
    The pool has no size limit.

    Several datasets: ``extra`` lists further ``(dataset, sessions or None)`` sources (e.g. a
    garage next to a parking lot, rendered with the same rig). Their sessions are labelled
    ``"<dataset folder name>/<session>"`` in :attr:`sessions`; each is its own world (never a
    positive of another). ``cross_floor_fraction`` is the share of negatives drawn, where the
    anchor's world has other floors, from another floor within ``neg_radius`` metres in x-y of
    the anchor: the look-alike places a multi-storey loop closure must tell apart.
    ``cross_floor_same_session`` is the share of those cross-floor negatives drawn from the
    anchor's own session where it has such frames (the same drive on the other floor: same
    lighting, same path, only the parked cars differ); 0 (default) draws from every session of
    the world, exactly as a sampler without the argument.
    ``anchor_shares`` (one per ``extra`` source, or empty): the share of fresh anchors drawn from
    that world (a float in (0, 1)), or None for the default, in proportion to its frames; the
    primary dataset and the None worlds share the rest in proportion to their frames. With no
    shares set the draws are exactly those of a sampler without the argument.

    Frames found unusable while training (the trainer's: no image content, every camera's
    picture flat) are taken out with :meth:`exclude` (:attr:`usable`, (N,) bool, is False for
    them): never drawn again as anchor, positive or negative, and the hard triplets holding them
    leave the pool. A sampler that excluded nothing draws exactly what one without the method
    would.
    """

    def __init__(
        self,
        ds: Dataset,
        pos_radius: float = 2.0,
        neg_radius: float = 3.0,
        seed: int = 0,
        sessions: Sequence[str] | None = None,
        *,
        cross_session: bool = True,
        revisit_gap: int = 0,
        hard_fraction: float = 0.5,
        floor_separation: float = FLOOR_SEPARATION,
        extra: Sequence[tuple[Dataset, Sequence[str] | None]] = (),
        cross_floor_fraction: float = 0.0,
        cross_floor_same_session: float = 0.0,
        anchor_shares: Sequence[float | None] = (),
    ) -> None:
        if isinstance(revisit_gap, bool) or not isinstance(revisit_gap, (int, np.integer)):
            raise TypeError(f"revisit_gap: expected an int >= 0, got {type(revisit_gap).__name__}")
        if revisit_gap < 0:
            raise ValueError(f"revisit_gap: expected an int >= 0, got {revisit_gap}")
        pos_radius = _real(pos_radius, "pos_radius")
        neg_radius = _real(neg_radius, "neg_radius")
        hard_fraction = _real(hard_fraction, "hard_fraction")
        cross_floor_fraction = _real(cross_floor_fraction, "cross_floor_fraction")
        cross_floor_same_session = _real(cross_floor_same_session, "cross_floor_same_session")
        floor_separation = _real(floor_separation, "floor_separation")
        flag(cross_session, "cross_session")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed: expected an int >= 0, got {seed!r}")
        if not (pos_radius > 0 and neg_radius >= pos_radius):
            raise ValueError(
                f"pos_radius, neg_radius: expected 0 < pos_radius <= neg_radius, "
                f"got {pos_radius}, {neg_radius}"
            )
        if not 0.0 <= hard_fraction <= 1.0:
            raise ValueError(f"hard_fraction: expected a value in [0, 1], got {hard_fraction}")
        if not 0.0 <= cross_floor_fraction <= 1.0:
            raise ValueError(
                f"cross_floor_fraction: expected a value in [0, 1], got {cross_floor_fraction}"
            )
        if not 0.0 <= cross_floor_same_session <= 1.0:
            raise ValueError(
                "cross_floor_same_session: expected a value in [0, 1], "
                f"got {cross_floor_same_session}"
            )
        _check_floor_separation(floor_separation, neg_radius, "neg_radius")  # >= pos_radius
        if isinstance(sessions, str):
            raise TypeError(f"sessions: expected a list of session names, got the str {sessions!r}")
        if sessions is not None:
            sessions = list(sessions)  # once: an iterator would be spent by the check
            if len(set(sessions)) != len(sessions):
                raise ValueError(f"sessions: names repeated in {sessions}")
        roots = [src.root for src in [ds, *(e[0] for e in extra)]]
        for k, root in enumerate(roots[1:]):
            if any(same_folder(root, r) for r in roots[: k + 1]):
                raise ValueError(
                    f"extra: dataset {k} ({root}) is "
                    + ("the primary dataset" if same_folder(root, roots[0]) else "listed twice")
                    + ": its frames would pair as another world's (its own places drawn as "
                    "negatives); list the sessions it should give in one entry instead"
                )
        self.ds = ds
        # (dataset, session name, label) of each session slot, the primary dataset's first
        self._slots: list[tuple[Dataset, str, str]] = []
        for w, (src, names) in enumerate([(ds, sessions), *extra]):
            chosen = list(names) if names is not None else src.sessions
            if not chosen:
                raise ValueError(f"sessions: expected at least one session of {src.root}")
            prefix = "" if w == 0 else f"{Path(src.root).name}/"
            self._slots += [(src, name, prefix + name) for name in chosen]
        self.sessions = [label for _, _, label in self._slots]
        if len(set(self.sessions)) != len(self.sessions):
            raise ValueError(f"extra: session labels collide: {self.sessions}")
        self.pos_radius = float(pos_radius)
        self.neg_radius = float(neg_radius)
        self.hard_fraction = float(hard_fraction)
        self.cross_floor_fraction = float(cross_floor_fraction)
        self.cross_floor_same_session = float(cross_floor_same_session)
        self.rng = np.random.default_rng(seed)
        sess_ids, idx, pos, levels = [], [], [], []
        worlds = {id(src): w for w, src in enumerate([ds, *(e[0] for e in extra)])}
        # each world's lowest floor becomes its level 0 (basements may be numbered below 0;
        # only differences between floors matter)
        lowest: dict[int, int] = {}
        for src, name, _ in self._slots:
            fl = src.session(name).floors
            if len(fl):
                w = worlds[id(src)]
                lowest[w] = min(lowest.get(w, int(fl.min())), int(fl.min()))
        for k, (src, name, _) in enumerate(self._slots):
            s = src.session(name)
            w = worlds[id(src)]
            rel = s.floors - lowest.get(w, 0)
            if len(rel) and rel.max() >= WORLD_LEVELS:
                raise ValueError(
                    f"session {name!r} of {src.root}: floors must span fewer than "
                    f"{WORLD_LEVELS} levels"
                )
            level = rel + WORLD_LEVELS * w
            sess_ids.append(np.full(len(s), k, dtype=np.int64))
            idx.append(np.arange(len(s), dtype=np.int64))
            pos.append(_positions(s.poses, level, floor_separation))
            levels.append(level)
        self.session_of = np.concatenate(sess_ids)
        self.index_of = np.concatenate(idx)
        self.positions = np.concatenate(pos)
        self.level_of = np.concatenate(levels)
        self.tree = cKDTree(self.positions)
        self.cross_floor = self._cross_floor_neighbours() if cross_floor_fraction > 0 else None
        near = self.tree.query_ball_point(self.positions, r=self.pos_radius)
        self.positives: list[np.ndarray] = []
        for i, cand in enumerate(near):
            c = np.asarray(sorted(cand), dtype=np.int64)
            c = c[c != i]
            if cross_session:
                other = self.session_of[c] != self.session_of[i]
                if revisit_gap > 0:  # a return to the place within the same drive counts too
                    other |= np.abs(self.index_of[c] - self.index_of[i]) >= revisit_gap
                c = c[other]
            self.positives.append(c)
        # an anchor needs a negative too: a frame beyond neg_radius (another floor is far)
        within = self.tree.query_ball_point(self.positions, r=self.neg_radius, return_length=True)
        has_negative = np.asarray(within) < len(self.positions)
        self.anchors = np.array(
            [i for i, p in enumerate(self.positives) if len(p) and has_negative[i]], dtype=np.int64
        )
        if len(self.anchors) == 0 and any(len(p) for p in self.positives):
            raise ValueError(
                f"no frame with a positive has a negative beyond {self.neg_radius} m "
                f"(sessions {self.sessions}): the data covers too small an area"
            )
        if len(self.anchors) == 0:
            raise ValueError(
                f"no frame has a positive within {self.pos_radius} m "
                f"{'in another session ' if cross_session else ''}(sessions {self.sessions}); "
                "a dataset of single drives that revisit places: set revisit_gap"
            )
        self._anchor_shares = list(anchor_shares)
        self._n_extra = len(extra)
        p = self._anchor_probabilities(self._anchor_shares, self._n_extra)
        self._anchor_cdf = None if p is None else np.cumsum(p)
        self._hard: dict[tuple[int, int, int], None] = {}
        self._hard_cursor = 0
        # (N,) False for the frames taken out by exclude()
        self.usable = np.ones(len(self.positions), dtype=bool)

    def _anchor_probabilities(
        self, shares: Sequence[float | None], n_extra: int
    ) -> np.ndarray | None:
        """Per-anchor draw probabilities (A,) for ``anchor_shares``, None when none is set."""
        shares = list(shares)
        if shares and len(shares) != n_extra:
            raise ValueError(
                f"anchor_shares: expected one entry per extra dataset ({n_extra}), "
                f"got {len(shares)}"
            )
        if all(v is None for v in shares):
            return None
        for v in shares:
            if v is not None and (isinstance(v, bool) or not 0.0 < float(v) < 1.0):
                raise ValueError(f"anchor_shares: expected None or a share in (0, 1), got {v!r}")
        fixed = sum(float(v) for v in shares if v is not None)
        if not fixed < 1.0:
            raise ValueError(
                f"anchor_shares: the shares must leave some for the primary dataset, sum {fixed}"
            )
        world = self.level_of[self.anchors] // WORLD_LEVELS
        share_of = [None, *shares]  # world 0 is the primary dataset
        free = np.array([share_of[int(w)] is None for w in world])
        p = np.empty(len(self.anchors))
        p[free] = (1.0 - fixed) / max(int(free.sum()), 1)
        for w, v in enumerate(share_of):
            here = world == w
            if v is not None:
                if not here.any():
                    raise ValueError(f"anchor_shares: extra dataset {w - 1} has no anchor")
                p[here] = float(v) / int(here.sum())
        return p / p.sum()

    def _cross_floor_neighbours(self) -> list[np.ndarray]:
        """Per frame, the frames of its world on another floor within ``neg_radius`` in x-y."""
        xy_tree = cKDTree(self.positions[:, :2])
        world = self.level_of // WORLD_LEVELS
        out = []
        for i, cand in enumerate(xy_tree.query_ball_point(self.positions[:, :2], self.neg_radius)):
            c = np.asarray(sorted(cand), dtype=np.int64)
            out.append(c[(world[c] == world[i]) & (self.level_of[c] != self.level_of[i])])
        return out

    @property
    def slots(self) -> list[tuple[Dataset, str, str]]:
        """``(dataset, session name, label)`` of each session drawn from, in the order of
        :attr:`sessions` (the primary dataset's first)."""
        return list(self._slots)

    def __len__(self) -> int:
        """Number of frames indexed (global ids run from 0 to len - 1)."""
        return len(self.positions)

    def locate(self, gid: int) -> tuple[str, int]:
        """(session label, frame index) of global frame id ``gid`` (an int in [0, len))."""
        gid = self._gid(gid)
        return self.sessions[int(self.session_of[gid])], int(self.index_of[gid])

    def _gid(self, gid: int) -> int:
        """``gid`` checked: an int in [0, len(self)), named otherwise (not read from the end)."""
        return positive_int(gid, "gid", minimum=0, maximum=len(self) - 1)

    def frame(self, gid: int) -> Frame:
        """The :class:`Frame` of global frame id ``gid`` (an int in [0, len); loads its
        images)."""
        gid = self._gid(gid)
        src, name, _ = self._slots[int(self.session_of[gid])]
        return src.session(name)[int(self.index_of[gid])]

    def _negative(self, anchor: int) -> int:
        if self.cross_floor is not None and len(self.cross_floor[anchor]):
            if self.rng.random() < self.cross_floor_fraction:
                near = self.cross_floor[anchor]
                if self.cross_floor_same_session > 0:
                    own = near[self.session_of[near] == self.session_of[anchor]]
                    if len(own) and self.rng.random() < self.cross_floor_same_session:
                        near = own
                return int(near[self.rng.integers(len(near))])
        for _ in range(64):
            cand = int(self.rng.integers(len(self.positions)))
            far = np.linalg.norm(self.positions[cand] - self.positions[anchor]) > self.neg_radius
            if far and self.usable[cand]:
                return cand
        far = np.linalg.norm(self.positions - self.positions[anchor], axis=1) > self.neg_radius
        choices = np.flatnonzero(far & self.usable)
        if len(choices) == 0:
            left = "" if self.usable.all() else " among the frames not excluded"
            raise ValueError(f"frame {anchor} has no negative beyond {self.neg_radius} m{left}")
        return int(self.rng.choice(choices))

    def sample_random(self, n: int) -> np.ndarray:
        """(n, 3) int64 fresh random triplets (no hard ones)."""
        out = np.empty((n, 3), dtype=np.int64)
        for k in range(n):
            if self._anchor_cdf is None:
                pick = int(self.rng.integers(len(self.anchors)))
            else:  # inverse-CDF draw, O(log A)
                u = self.rng.random() * self._anchor_cdf[-1]
                pick = min(
                    int(np.searchsorted(self._anchor_cdf, u, side="right")), len(self.anchors) - 1
                )
            a = int(self.anchors[pick])
            pos = self.positives[a]
            out[k] = (a, int(pos[self.rng.integers(len(pos))]), self._negative(a))
        return out

    def sample(self, n: int) -> np.ndarray:
        """(n, 3) int64 triplets: up to ``hard_fraction·n`` from the hard pool, the rest random."""
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"n: expected an int >= 0, got {n!r}")
        hard = list(self._hard)
        k = min(len(hard), round(self.hard_fraction * n))
        picked = []
        for j in range(k):
            picked.append(hard[(self._hard_cursor + j) % len(hard)])
        if hard:
            self._hard_cursor = (self._hard_cursor + k) % len(hard)
        fresh = self.sample_random(n - k)
        out = np.concatenate([np.array(picked, dtype=np.int64).reshape(-1, 3), fresh])
        return out[self.rng.permutation(len(out))]

    def mark_hard(self, triplets: np.ndarray) -> None:
        """Add (T, 3) triplets (frame ids in ``[0, len(self))``) the model got wrong to the
        hard pool."""
        t = _triplets(triplets)
        if t.size and (t.min() < 0 or t.max() >= len(self)):
            raise ValueError(f"triplets: frame ids must lie in [0, {len(self)})")
        for row in t:
            self._hard[(int(row[0]), int(row[1]), int(row[2]))] = None

    def resolve(self, triplets: np.ndarray) -> None:
        """Remove (T, 3) int triplets the model now gets right from the hard pool."""
        for t in _triplets(triplets):
            self._hard.pop((int(t[0]), int(t[1]), int(t[2])), None)

    def update(self, triplets: np.ndarray, correct: np.ndarray) -> None:
        """Mark the wrong triplets hard and resolve the right ones (``triplets`` (T, 3) int
        frame ids, ``correct`` (T,) bool)."""
        t = _triplets(triplets)
        ok = np.asarray(correct)
        if ok.dtype != bool:
            raise TypeError(f"correct: expected (T,) bool flags, got dtype {ok.dtype}")
        ok = ok.reshape(-1)
        if len(ok) != len(t):
            raise ValueError(f"correct: expected {len(t)} flags, got {len(ok)}")
        self.mark_hard(t[~ok])
        self.resolve(t[ok])

    @property
    def hard(self) -> np.ndarray:
        """(H, 3) int64 triplets currently in the hard pool."""
        return np.array(list(self._hard), dtype=np.int64).reshape(-1, 3)

    @property
    def excluded(self) -> np.ndarray:
        """(E,) int64 sorted ids of the frames taken out by :meth:`exclude`."""
        return np.flatnonzero(~self.usable).astype(np.int64)

    def exclude(self, gids: Any) -> np.ndarray:
        """Take frames (``gids`` (E,) ints in ``[0, len(self))``) out of every later draw: as
        anchors, positives (an anchor left without one is no anchor) and negatives; the hard
        triplets holding one leave the pool. Returns the (E',) int64 sorted ids newly taken out
        (those excluded before are skipped). An anchor needs a positive and a negative among the
        frames left. ``ValueError`` (nothing excluded) when no anchor would be left, or none in
        an ``extra`` world that ``anchor_shares`` gives a share."""
        ids = int_array(gids, "gids", "(E,)", 1)
        if ids.size and (ids.min() < 0 or ids.max() >= len(self)):
            raise ValueError(f"gids: frame ids must lie in [0, {len(self)})")
        new = np.unique(ids[self.usable[ids]])
        if not len(new):
            return new
        usable = self.usable.copy()
        usable[new] = False
        positives = [p[usable[p]] for p in self.positives]
        anchors = np.array(
            [a for a in self.anchors if usable[a] and len(positives[a])], dtype=np.int64
        )
        if len(anchors):  # an anchor needs a negative too: a usable frame beyond neg_radius
            within = self.tree.query_ball_point(self.positions[anchors], r=self.neg_radius)
            near_usable = np.array([int(usable[list(w)].sum()) for w in within])
            anchors = anchors[near_usable < int(usable.sum())]
        if len(anchors) == 0:
            raise ValueError(
                f"exclude: no anchor would be left (sessions {self.sessions}; "
                f"{int((~usable).sum())} of {len(self)} frames excluded)"
            )
        kept_anchors = self.anchors
        self.anchors = anchors
        try:
            p = self._anchor_probabilities(self._anchor_shares, self._n_extra)
        except ValueError as e:
            self.anchors = kept_anchors
            raise ValueError(f"exclude: {e} left") from None
        self.usable = usable
        self.positives = positives
        self._anchor_cdf = None if p is None else np.cumsum(p)
        if self.cross_floor is not None:
            self.cross_floor = [c[usable[c]] for c in self.cross_floor]
        for t in list(self._hard):
            if not usable[list(t)].all():
                del self._hard[t]
        self._hard_cursor = self._hard_cursor % len(self._hard) if self._hard else 0
        return new

    def restart_hard_pool(self) -> None:
        """Take the next hard triplets from the pool's first (oldest) one again; the pool itself
        is kept (the trainer's ``hard_pool_restarts``)."""
        self._hard_cursor = 0

    def state_dict(self) -> dict[str, Any]:
        """Everything that decides the next draws: the generator's state, the hard pool in its
        order ((H, 3) int64) and the position in it from which :meth:`sample` takes next. A
        sampler built on the same data and given this by :meth:`load_state_dict` draws what this
        one would (the trainer's ``--resume``), once it excluded the same frames: the state
        lists them (``excluded``, (E,) int64), and :meth:`load_state_dict` excludes them."""
        return {
            "rng": self.rng.bit_generator.state,
            "hard": self.hard,
            "hard_cursor": self._hard_cursor,
            "excluded": self.excluded,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore a :meth:`state_dict` (the hard pool replaces this sampler's). A state without
        ``hard_cursor`` (saved by vvloc before 2026-12-03) starts the pool from its first
        triplet, as those versions did on resume; one without ``excluded`` (before 2026-12-07)
        excludes nothing. ``ValueError`` when this sampler excludes a frame the state does not
        (load into a fresh sampler): it would draw otherwise."""
        excluded = np.asarray(state.get("excluded", []), dtype=np.int64).reshape(-1)
        extra = np.setdiff1d(self.excluded, excluded)
        if len(extra):
            raise ValueError(
                f"state: this sampler excludes frames the state does not ({len(extra)}, ids "
                f"{list_entries([str(g) for g in extra])}); load it into a fresh sampler"
            )
        self.exclude(excluded)
        self.rng.bit_generator.state = state["rng"]
        self._hard = {}
        self.mark_hard(np.asarray(state["hard"], dtype=np.int64))
        self._hard_cursor = int(state.get("hard_cursor", 0))


@dataclass(frozen=True)
class EvalSplit:
    """A retrieval/localization evaluation split.

    Attributes:
        database: the map session's name; ``database_indices`` (D,) its frames.
        query_sessions: (Q,) session name per query; ``query_indices`` (Q,) frame indices.
        nearest_database: (Q,) index (into the database session) of the nearest map frame.
        nearest_distance: (Q,) its distance, metres (same floor; always <= revisit_radius).
        revisit_radius: the radius a query needed a map frame within to be kept.
    """

    database: str
    database_indices: np.ndarray
    query_sessions: np.ndarray
    query_indices: np.ndarray
    nearest_database: np.ndarray
    nearest_distance: np.ndarray
    revisit_radius: float


def check_session_names(
    argument: str, ds: Dataset, names: Sequence[str], where: str, note: str = ""
) -> None:
    """``ValueError`` naming ``argument`` when ``names`` repeat a session or name one that the
    dataset ``ds`` (called ``where`` in the message, ``note`` after it) lacks."""
    from vvloc._io import list_entries

    names = list(names)
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"{argument}: {repeated} named more than once")
    known = set(ds.sessions)
    missing = [n for n in names if n not in known]
    if missing:
        raise ValueError(
            f"{argument}: {missing} not in {where}{note}; its sessions: "
            f"{list_entries(sorted(known), 12)}"
        )


def check_query_sessions(
    database: str, queries: Iterable[str], argument: str = "queries"
) -> list[str]:
    """The query sessions ``queries`` as a list (an iterator read once), checked: a
    ``TypeError`` naming ``argument`` for one str (it would be split into letters), a
    ``ValueError`` when they repeat a name or include the map session ``database``: its frames
    would find themselves (100 % recall, a calibration learnt on the map), or a session would
    count twice."""
    if isinstance(queries, (str, bytes)):  # "s1" would be the sessions 's' and '1'
        raise TypeError(
            f"{argument}: expected a sequence of session names, got one str {queries!r:.60} "
            f"(pass [{queries!r:.60}])"
        )
    names = list(queries)
    repeated = sorted({q for q in names if names.count(q) > 1})
    if repeated:
        raise ValueError(f"{argument}: sessions named more than once: {repeated}")
    if database in names:
        raise ValueError(
            f"{argument}: the map session {database!r} is among the queries: its frames would "
            "find themselves; query other sessions"
        )
    return names


def same_folder(a: Any, b: Any) -> bool:
    """Whether two dataset paths name one folder, however spelt (``./data/x``, ``data/x/``,
    relative to the working directory); False when either is not a path."""
    if not isinstance(a, (str, os.PathLike)) or not isinstance(b, (str, os.PathLike)):
        return False
    return os.path.realpath(a) == os.path.realpath(b)  # Path.resolve raises on a symlink loop


def sim_world(sim: dict[str, Any]) -> dict[str, Any]:
    """The world a ``sim`` section (arguments of :func:`vvloc.sim.simulate_dataset`) renders:
    scene, seed, the query vehicle's tilt bounds (degrees), and for a garage its floors and
    floor marking, with the simulator's defaults filled in."""
    world = {"scene": sim.get("scene", "parking"), "seed": sim.get("seed", 0)}
    for key in ("max_roll", "max_pitch"):
        world[key] = float(sim.get(key, 0.0))
    if world["scene"] == "garage":
        world |= {
            "floors": sim.get("floors", 2),
            "floor_marking": sim.get("floor_marking", "walls"),
        }
    return world


def rendered_world(root: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The world ``vvloc sim`` recorded in ``root``'s ``rig.json`` (``meta``), in the form of
    :func:`sim_world`; None for a dataset that ``vvloc sim`` did not render."""
    meta = rig_meta(root)
    if meta is None or meta.get("generator") != "vvloc.sim":
        return None
    world = {"scene": meta.get("scene"), "seed": meta.get("seed")}
    try:
        for key in ("max_roll", "max_pitch"):  # absent from a level dataset's meta
            world[key] = float(meta.get(key, 0.0))
    except (ValueError, TypeError):  # not this one's
        return None
    if world["scene"] == "garage":
        world |= {"floors": meta.get("floors"), "floor_marking": meta.get("floor_marking", "walls")}
    return world


def inside_folder(path: str | os.PathLike[str], folder: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is ``folder`` or lies inside it, however spelt (resolved like
    :func:`same_folder`): an output written there would land in the folder's contents."""
    p, f = Path(os.path.realpath(path)), Path(os.path.realpath(folder))  # a loop: no error
    return p == f or f in p.parents


def _real(value: Any, name: str) -> float:
    """A finite real number (numpy scalars included, bool not) as float, else an error naming
    ``name``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise TypeError(f"{name}: expected a number, got {type(value).__name__}")
    if not np.isfinite(value):
        raise ValueError(f"{name}: expected a finite number, got {value}")
    return float(value)


def _check_floor_separation(separation: float, radius: float, radius_name: str) -> None:
    """Floors are kept apart by a vertical offset of ``floor_separation`` per floor: it must
    exceed every radius, or frames of two floors would pair."""
    if not (isinstance(separation, (int, float, np.number)) and separation > radius):
        raise ValueError(
            f"floor_separation: expected a distance (m) greater than {radius_name} ({radius}), "
            f"got {separation!r}: frames of two floors would pair"
        )


def evaluation_split(
    ds: Dataset,
    database: str | None = None,
    queries: Sequence[str] | None = None,
    revisit_radius: float = 2.0,
    floor_separation: float = FLOOR_SEPARATION,
) -> EvalSplit:
    """Database session vs query sessions; a query is kept only when a map frame (same floor)
    lies within ``revisit_radius`` metres (2 m: the radius ``vvloc eval`` keeps queries at,
    :func:`vvloc.evaluate.recall_at_n`; 3 m before 2026-12-05), as the standard
    place-recognition protocol does.

    Defaults: the first session (sorted) is the database, all others are queries.
    """
    names = ds.sessions
    if database is None and not names:
        raise ValueError("ds: the dataset has no sessions (no database session to default to)")
    database = database if database is not None else names[0]
    if queries is None:
        queries = [n for n in names if n != database]
    queries = check_query_sessions(database, queries)  # a list (a generator read once)
    if (
        isinstance(revisit_radius, bool)
        or not isinstance(revisit_radius, (int, float, np.number))
        or not 0 < revisit_radius < np.inf
    ):
        raise ValueError(
            f"revisit_radius: expected a finite distance > 0 m, got {revisit_radius!r}"
        )
    _check_floor_separation(floor_separation, revisit_radius, "revisit_radius")
    db = ds.session(database)
    tree = cKDTree(_positions(db.poses, db.floors, floor_separation))
    qs, qi, nn, nd = [], [], [], []
    for name in queries:
        s = ds.session(name)
        d, j = tree.query(_positions(s.poses, s.floors, floor_separation), k=1)
        keep = np.flatnonzero(d <= revisit_radius)
        qs.extend([name] * len(keep))
        qi.append(keep)
        nn.append(j[keep])
        nd.append(d[keep])
    cat = lambda a, dt: np.concatenate(a).astype(dt) if a else np.zeros(0, dt)  # noqa: E731
    return EvalSplit(
        database=database,
        database_indices=np.arange(len(db), dtype=np.int64),
        query_sessions=np.array(qs, dtype=object),
        query_indices=cat(qi, np.int64),
        nearest_database=cat(nn, np.int64),
        nearest_distance=cat(nd, np.float64),
        revisit_radius=float(revisit_radius),
    )
