"""Geometry oracle through the whole Localizer (retrieve → re-rank → metric search → global pose).

A smooth world feature field is sampled into BEVs at known map poses and at a query pose; with
the non-learned radial-mean decoder the localizer must pick the nearest map keyframe and recover
the query's world pose. This pins the localizer's frames (ξ_{m→q}, T_world_q = T_world_m · ξ)
end to end, independently of any training.
"""

from __future__ import annotations

import copy
import inspect

import numpy as np
import pytest
import torch

from nets_helpers import tiny_config
from test_metric_localize import bev_at, compose, world_field, wrap
from vvloc import kernels
from vvloc.commands._util import MetricFromChoice
from vvloc.commands.evaluate import eval_command
from vvloc.commands.localize import localize as localize_command
from vvloc.localize import localizer as localizer_module
from vvloc.localize.localizer import (
    METRIC_CANDIDATES,
    METRIC_FROM,
    RETRIEVAL_WEIGHT,
    Localizer,
)
from vvloc.localize.mapdb import MapDatabase, MapError
from vvloc.localize.metric import RadialMeanDecoder, SearchConfig
from vvloc.nets import ModelConfig, VVLocNet

G, T, R, C = 0.3, 120, 25, 8


def _model() -> VVLocNet:
    cfg = ModelConfig.small()
    cfg.bev_height = cfg.bev_width = 100
    cfg.grid_size, cfg.num_angles, cfg.num_radii, cfg.channels = G, T, R, C
    return VVLocNet(cfg)


def _save_map(model, tmp_path, poses, glob, local, floors=None):
    """A one-session map of keyframes at ``poses`` (N, 3) with global descriptors ``glob``
    (N, Dg) and local-view descriptors ``local`` (N, T, C), saved in ``tmp_path``."""
    db = MapDatabase.from_arrays(
        poses=poses,
        timestamps=np.arange(float(len(poses))),
        sessions="s0",
        global_descriptors=glob,
        local_descriptors=local,
        model_config=model.config.to_dict(),
        grid_size=G,
        config_hash=model.config_hash(),
        weights_hash=model.weights_hash(),
        floors=floors,
    )
    return db.save(tmp_path / "map.h5")


@pytest.mark.parametrize(("seed", "metric_candidates"), [(0, 1), (1, 1), (2, 1), (0, 3)])
def test_localizer_recovers_the_query_world_pose(seed, metric_candidates, tmp_path):
    rng = np.random.default_rng(seed)
    field = world_field(seed)
    model = _model()
    decode = RadialMeanDecoder()
    map_poses = np.array([(4.0 * k, 0.5 * k, rng.uniform(-np.pi, np.pi)) for k in range(5)])
    bevs = np.stack([bev_at(field, p) for p in map_poses])
    local = decode(kernels.polar_sample(bevs, T, R, G))
    glob = rng.standard_normal((5, model.global_dim)).astype(np.float32)
    glob /= np.linalg.norm(glob, axis=1, keepdims=True)
    path = _save_map(model, tmp_path, map_poses, glob, local)
    target = 2
    xi = (rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-np.pi, np.pi))
    q_pose = np.array(compose(map_poses[target], xi))
    q_bev = bev_at(field, q_pose)
    q_local = decode(kernels.polar_sample(q_bev, T, R, G))
    # a unit global descriptor orthogonal to every keyframe's: equally far from each, it tells
    # nothing (as a query descriptor of zeros did, which the localizer now refuses)
    basis = np.linalg.qr(glob.T.astype(np.float64))[0]
    q_g = np.ones(model.global_dim) - basis @ (basis.T @ np.ones(model.global_dim))
    q_g = (q_g / np.linalg.norm(q_g)).astype(np.float32)
    assert np.ptp(np.linalg.norm(glob - q_g, axis=1)) < 1e-5
    search = SearchConfig(half_range=3.0, step=0.6, fine_samples=32, stages=5, seed=seed)
    with MapDatabase.open(path, expected_config_hash=model.config_hash()) as mapdb:
        loc = Localizer(
            model,
            mapdb,
            top_k=5,
            search=search,
            decoder="radial_mean",
            metric_candidates=metric_candidates,
            metric_from="rerank",  # the query's global descriptor tells nothing
        )
        res = loc.localize_encoded(q_g, q_local, q_bev)
        if metric_candidates > 1:
            # the first M re-ranked candidates are ordered by their coarse-stage cost, and the
            # lowest one is refined (snapping off: the order is the search's alone)
            kw = {"top_k": 5, "search": search, "decoder": "radial_mean", "snap": False}
            kw["metric_from"] = "rerank"
            one = Localizer(model, mapdb, metric_candidates=1, **kw)
            ref = one.localize_encoded(q_g, q_local, q_bev)
            many = Localizer(model, mapdb, metric_candidates=metric_candidates, **kw)
            got = many.localize_encoded(q_g, q_local, q_bev)
            m = metric_candidates
            coarse = {}
            for row in ref.reranked[:m]:
                hist = one.metric(q_bev, int(row))[2]
                coarse[int(row)] = hist.cost[hist.stage == 0].min()
            assert got.reranked[m:].tolist() == ref.reranked[m:].tolist()
            assert got.reranked[:m].tolist() == sorted(coarse, key=coarse.__getitem__)
            assert got.metric_row == got.map_row == got.reranked[0]
            assert got.cost == pytest.approx(one.metric(q_bev, got.map_row)[1])
    assert res.map_row == target
    # for these seeds the query is nearest its own keyframe, so snapping keeps it
    assert res.metric_row == target
    assert np.hypot(*(res.global_pose[:2] - q_pose[:2])) < 0.15, (res.global_pose, q_pose)
    assert abs(np.degrees(wrap(res.global_pose[2] - q_pose[2]))) < 1.0
    np.testing.assert_allclose(res.relative_pose[:2], xi[:2], atol=0.15)


@pytest.mark.parametrize("metric_from", ["retrieval", "rerank"])
@pytest.mark.parametrize("weight", [0.0, 0.3, 100.0])
def test_metric_candidates_are_the_first_of_the_chosen_ordering(metric_from, weight, tmp_path):
    """The M metric candidates are the first M retrieved (``metric_from="retrieval"``) or the
    first M yaw re-ranked; they lead ``reranked`` by coarse cost plus ``retrieval_weight`` ×
    descriptor distance, the rest follow in yaw re-ranked order. The query's global descriptor
    is keyframe 4's, so retrieval puts 4 first while the yaw re-ranking puts the query's own
    keyframe, 2, first."""
    rng = np.random.default_rng(0)
    field = world_field(0)
    model = _model()
    decode = RadialMeanDecoder()
    map_poses = np.array([(4.0 * k, 0.5 * k, rng.uniform(-np.pi, np.pi)) for k in range(5)])
    local = decode(kernels.polar_sample(np.stack([bev_at(field, p) for p in map_poses]), T, R, G))
    glob = np.eye(5, model.global_dim, dtype=np.float32)
    glob[3, 4] = glob[1, 3] = 0.5  # retrieval order from keyframe 4's descriptor: 4, 3, ...
    glob /= np.linalg.norm(glob, axis=1, keepdims=True)
    path = _save_map(model, tmp_path, map_poses, glob, local)
    q_pose = np.array(compose(map_poses[2], (0.7, -0.4, 0.3)))
    q_bev = bev_at(field, q_pose)
    q_local = decode(kernels.polar_sample(q_bev, T, R, G))
    search = SearchConfig(half_range=3.0, step=0.6, fine_samples=32, stages=5, seed=0)
    kw = {"top_k": 5, "search": search, "decoder": "radial_mean", "snap": False}
    m = 2
    with MapDatabase.open(path, expected_config_hash=model.config_hash()) as mapdb:
        # M = 1 from the re-ranking leaves the yaw re-ranked order as it is
        yaw = Localizer(model, mapdb, metric_candidates=1, metric_from="rerank", **kw)
        ref = yaw.localize_encoded(glob[4], q_local, q_bev)
        yaw_order = ref.reranked.tolist()
        loc = Localizer(
            model,
            mapdb,
            metric_candidates=m,
            metric_from=metric_from,
            retrieval_weight=weight,
            **kw,
        )
        got = loc.localize_encoded(glob[4], q_local, q_bev)
        coarse = {}
        for row in range(5):
            hist = yaw.metric(q_bev, row)[2]
            coarse[row] = hist.cost[hist.stage == 0].min()
    assert got.retrieved[:2].tolist() == [4, 3]
    assert yaw_order[0] == 2
    pool = got.retrieved[:m].tolist() if metric_from == "retrieval" else yaw_order[:m]
    dist = dict(zip(got.retrieved.tolist(), got.retrieval_dist.tolist(), strict=True))
    score = {r: coarse[r] + weight * dist[r] for r in pool}
    assert got.reranked[:m].tolist() == sorted(pool, key=score.__getitem__)
    if weight == 0.0 and metric_from == "rerank":  # the cost alone: the query's own keyframe
        assert got.reranked[0] == 2
    if weight == 100.0 and metric_from == "retrieval":  # the distance dominates: 4 (0), 3
        assert got.reranked[:m].tolist() == [4, 3]
    assert got.reranked[m:].tolist() == [r for r in yaw_order if r not in pool]
    # rerank_cost follows its rows
    cost_of = dict(zip(yaw_order, ref.rerank_cost.tolist(), strict=True))
    assert got.rerank_cost.tolist() == [cost_of[r] for r in got.reranked.tolist()]
    assert got.metric_row == got.map_row == got.reranked[0]


def _one_keyframe_map(model, *, fingerprint=True):
    """An in-memory map of one keyframe at the origin for ``model``; with ``fingerprint`` it
    records the model's weights fingerprint, without it it is like a map of an older vvloc."""
    return MapDatabase.from_arrays(
        poses=np.zeros((1, 3)),
        timestamps=np.zeros(1),
        sessions="s0",
        global_descriptors=np.ones((1, model.global_dim), np.float32) / model.global_dim**0.5,
        local_descriptors=np.ones((1, T, C)),
        model_config=model.config.to_dict(),
        grid_size=G,
        config_hash=model.config_hash(),
        weights_hash=model.weights_hash() if fingerprint else None,
    )


def test_unknown_decoder_is_refused():
    model = _model()
    db = _one_keyframe_map(model)
    with pytest.raises(ValueError, match="decoder"):
        Localizer(model, db, decoder="magic")
    with pytest.raises(ValueError, match="metric_candidates"):
        Localizer(model, db, metric_candidates=0)
    for bad in (2.0, True):
        with pytest.raises(TypeError, match="metric_candidates"):
            Localizer(model, db, metric_candidates=bad)
    with pytest.raises(TypeError, match="snap"):
        Localizer(model, db, snap="yes")
    with pytest.raises(ValueError, match="metric_from"):
        Localizer(model, db, metric_from="global")
    with pytest.raises(TypeError, match="metric_from"):
        Localizer(model, db, metric_from=None)
    for bad in (-0.1, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="retrieval_weight"):
            Localizer(model, db, retrieval_weight=bad)
    for bad in (True, "1", None):
        with pytest.raises(TypeError, match="retrieval_weight"):
            Localizer(model, db, retrieval_weight=bad)
    # eval's and localize's --retrieval_weight and --metric_candidates default to the library's
    assert Localizer(model, db).retrieval_weight == RETRIEVAL_WEIGHT
    assert Localizer(model, db).metric_candidates == METRIC_CANDIDATES
    for command in (eval_command, localize_command):
        params = inspect.signature(command).parameters
        assert params["retrieval_weight"].default == RETRIEVAL_WEIGHT
        assert params["metric_candidates"].default == METRIC_CANDIDATES
    # the CLI's --metric_from offers exactly the library's choices
    assert [c.value for c in MetricFromChoice] == list(METRIC_FROM)


def test_a_map_is_used_only_with_the_weights_that_built_it(tmp_path):
    model = _model()
    rng = np.random.default_rng(0)
    glob = rng.standard_normal((2, model.global_dim)).astype(np.float32)
    glob /= np.linalg.norm(glob, axis=1, keepdims=True)
    path = _save_map(model, tmp_path, np.zeros((2, 3)), glob, np.ones((2, T, C), np.float32))
    # the same architecture, other weights (one weight changed): the same config hash
    other = copy.deepcopy(model)
    with torch.no_grad():
        next(other.parameters()).view(-1)[0] += 1.0
    assert other.config_hash() == model.config_hash()
    assert other.weights_hash() != model.weights_hash()
    with MapDatabase.open(path) as mapdb:
        Localizer(model, mapdb)
        with pytest.raises(MapError, match=r"map\.h5.*other weights"):
            Localizer(other, mapdb)
    with pytest.raises(MapError, match="other weights"):
        MapDatabase.open(path, expected_weights_hash=other.weights_hash())
    MapDatabase.open(path, expected_weights_hash=model.weights_hash()).close()
    # the fingerprint survives a checkpoint round trip
    assert VVLocNet.load(model.save(tmp_path / "ckpt")).weights_hash() == model.weights_hash()


def test_a_map_without_weights_fingerprint_warns():
    model = _model()
    db = _one_keyframe_map(model, fingerprint=False)
    with pytest.warns(UserWarning, match="no weights fingerprint"):
        Localizer(model, db)


@pytest.mark.parametrize("upper_floor", [False, True])
def test_snapping_reports_the_keyframe_nearest_to_the_metric_pose(upper_floor, tmp_path):
    """Keyframes every 1.5 m along x; the query lies 0.4 m past keyframe 3 but its global
    descriptor retrieves keyframe 2 first (no re-ranking), so the metric pose is estimated
    against keyframe 2; snapping must report keyframe 3 (keyframe 4 when 3 is on another
    floor), with the world pose unchanged and the relative pose in the reported frame."""
    rng = np.random.default_rng(7)
    field = world_field(7)
    model = _model()
    decode = RadialMeanDecoder()
    n = 6
    map_poses = np.array([(1.5 * k, 0.0, rng.uniform(-np.pi, np.pi)) for k in range(n)])
    local = decode(kernels.polar_sample(np.stack([bev_at(field, p) for p in map_poses]), T, R, G))
    glob = np.eye(n, model.global_dim, dtype=np.float32)
    floors = np.zeros(n, np.int64)
    if upper_floor:
        floors[3] = 1
    path = _save_map(model, tmp_path, map_poses, glob, local, floors)
    q_pose = np.array([4.9, 0.3, 0.4])
    q_bev = bev_at(field, q_pose)
    q_local = decode(kernels.polar_sample(q_bev, T, R, G))
    search = SearchConfig(half_range=3.0, step=0.6, fine_samples=32, stages=5, seed=0)
    with MapDatabase.open(path, expected_config_hash=model.config_hash()) as mapdb:
        kw = {"top_k": n, "search": search, "decoder": "radial_mean", "rerank": False}
        kw["metric_candidates"] = 1  # the metric pose against the first retrieved: keyframe 2
        snapped = Localizer(model, mapdb, **kw).localize_encoded(glob[2], q_local, q_bev)
        plain = Localizer(model, mapdb, snap=False, **kw).localize_encoded(glob[2], q_local, q_bev)
    want = 4 if upper_floor else 3
    assert plain.map_row == plain.metric_row == snapped.metric_row == 2
    assert snapped.map_row == want and snapped.reranked[0] == want
    assert sorted(snapped.reranked.tolist()) == list(range(n))
    np.testing.assert_allclose(snapped.global_pose, plain.global_pose)
    assert np.hypot(*(snapped.global_pose[:2] - q_pose[:2])) < 0.15
    back = compose(map_poses[want], snapped.relative_pose)
    np.testing.assert_allclose(back[:2], snapped.global_pose[:2], atol=1e-9)
    assert abs(wrap(back[2] - snapped.global_pose[2])) < 1e-9
    assert snapped.cost == plain.cost


@pytest.mark.parametrize("hypotheses", [1, 7, 16])
def test_the_decoder_in_chunks_equals_one_batch(hypotheses, monkeypatch):
    """The metric stage decodes a search stage's hypotheses in chunks on the CPU; the decoder
    treats each (hypothesis, angle) row alone, so the chunks must give the batch's result (bit
    for bit with this machine's BLAS; a float tolerance where another BLAS picks other kernels
    for other batch sizes)."""
    torch.manual_seed(0)
    model = VVLocNet(tiny_config()).eval()
    cfg = model.config
    polar = torch.randn(hypotheses, cfg.num_angles, cfg.num_radii, cfg.channels)
    with torch.no_grad():
        whole = model.decode_polar(polar)
        per_hypothesis = cfg.num_angles * cfg.num_radii * cfg.channels
        # chunks of 3 hypotheses (a remainder for 7 and 16), and of one for a budget below one
        for budget in (3 * per_hypothesis, per_hypothesis // 2):
            monkeypatch.setattr(localizer_module, "DECODE_CHUNK_ELEMENTS", budget)
            chunked = localizer_module.decode_in_chunks(model, polar)
            assert chunked.shape == whole.shape
            torch.testing.assert_close(chunked, whole, rtol=1e-6, atol=1e-6)


def plain_interactor(it, src, tgt):
    """The interactor's forward as it was written before it was split into first_tasa and
    after_first_tasa: the reference the parts are held to, bit for bit."""
    for tasa, cross in zip(it.tasa, it.cross, strict=True):
        src, tgt = tasa(src, it.rel), tasa(tgt, it.rel)
        src, tgt = cross(src, tgt), cross(tgt, src)
    return torch.nn.functional.normalize(src, dim=-1), torch.nn.functional.normalize(tgt, dim=-1)


@pytest.mark.parametrize("rounds", [0, 1, 2])
def test_the_interactor_in_parts_equals_the_interactor(rounds):
    """The metric stage runs the interactor's first TASA once per side (each target once, the
    hypotheses with the decoder, once for every target) and the rest per pair: the matcher must
    give ``model.interact`` of the decoded hypotheses against each target, and
    ``model.interact`` (which training runs) the plain loop's numbers."""
    torch.manual_seed(1)
    model = VVLocNet(tiny_config(interactor_rounds=rounds)).eval()
    it = model.interactor
    t, c = model.config.num_angles, model.config.channels
    ds, tgts = torch.randn(11, t, c), torch.randn(3, t, c)
    # bit for bit where torch's BLAS is MKL (the rows of a batch of >= 4 sequences do not
    # depend on its size there); within float rounding with another BLAS
    exact = torch.backends.mkl.is_available()
    with torch.no_grad():
        expanded = tgts[1].expand(11, t, c)
        for a, b in zip(
            model.interact(ds, expanded), plain_interactor(it, ds, expanded), strict=True
        ):
            assert torch.equal(a, b)  # the same operations in the same order
        decode, interact = localizer_module.learned_matcher(model, tgts.numpy())
        r = model.config.num_radii
        stages = [torch.randn(n, t, r, c) for n in (11, 9, 3)]  # coarse, fine, a small stage
        decoded = [decode(p.numpy()) for p in stages]
        # targets in any order, one twice (its first TASA is kept), then new hypotheses, and a
        # stage of fewer hypotheses than TARGET_COPIES (its own copies of the target, as before)
        for stage, k in ((0, 0), (0, 2), (0, 1), (0, 1), (1, 1), (1, 0), (2, 1)):
            d = model.decode_polar(stages[stage])
            want = plain_interactor(it, d, tgts[k].expand(len(d), t, c))
            got = interact(decoded[stage], k)
            for a, b in zip(got, want, strict=True):
                assert isinstance(a, np.ndarray) and a.dtype == np.float32
                if exact or len(d) < localizer_module.TARGET_COPIES:
                    np.testing.assert_array_equal(a, b.numpy())
                else:
                    np.testing.assert_allclose(a, b.numpy(), rtol=1e-5, atol=1e-6)
        with pytest.raises(ValueError, match="local: expected shape"):
            it.first_tasa(torch.randn(2, t + 1, c))


@pytest.mark.parametrize("k", [3, 11])
def test_the_learned_rerank_runs_the_querys_first_tasa_once_and_changes_nothing(k):
    """Re-ranking runs the query's first TASA once (on up to TARGET_COPIES copies) instead of
    once per candidate: costs, shifts and order must be those of the plain interactor."""
    torch.manual_seed(2)
    model = VVLocNet(tiny_config()).eval()
    t, c = model.config.num_angles, model.config.channels
    query, cands = torch.randn(t, c), torch.randn(k, t, c)
    with torch.no_grad():
        a, b = plain_interactor(model.interactor, query.expand(k, t, c), cands)
    want = kernels.rerank(a.numpy(), b.numpy())
    got = localizer_module.rerank_learned(model, query, cands)
    if torch.backends.mkl.is_available() or k < localizer_module.TARGET_COPIES:
        for x, y in zip(got, want, strict=True):
            np.testing.assert_array_equal(x, y)
    else:
        np.testing.assert_array_equal(got.order, want.order)
        np.testing.assert_allclose(got.cost, want.cost, rtol=1e-5, atol=1e-6)
