"""Geometry oracle through the whole Localizer (retrieve → re-rank → metric search → global pose).

A smooth world feature field is sampled into BEVs at known map poses and at a query pose; with
the non-learned radial-mean decoder the localizer must pick the nearest map keyframe and recover
the query's world pose. This pins the localizer's frames (ξ_{m→q}, T_world_q = T_world_m · ξ)
end to end, independently of any training.
"""

from __future__ import annotations

import numpy as np
import pytest

from test_metric_localize import bev_at, compose, world_field, wrap
from vvloc import kernels
from vvloc.localize.localizer import Localizer
from vvloc.localize.mapdb import MapDatabase
from vvloc.localize.metric import RadialMeanDecoder, SearchConfig
from vvloc.nets import ModelConfig, VVLocNet

G, T, R, C = 0.3, 120, 25, 8


def _model() -> VVLocNet:
    cfg = ModelConfig.small()
    cfg.bev_height = cfg.bev_width = 100
    cfg.grid_size, cfg.num_angles, cfg.num_radii, cfg.channels = G, T, R, C
    return VVLocNet(cfg)


@pytest.mark.parametrize(("seed", "metric_candidates"), [(0, 1), (1, 1), (2, 1), (0, 3)])
def test_localizer_recovers_the_query_world_pose(seed, metric_candidates, tmp_path):
    rng = np.random.default_rng(seed)
    field = world_field(seed)
    model = _model()
    decode = RadialMeanDecoder()
    map_poses = np.array([(4.0 * k, 0.5 * k, rng.uniform(-np.pi, np.pi)) for k in range(5)])
    bevs = np.stack([bev_at(field, p) for p in map_poses])
    local = decode(kernels.polar_sample(bevs, T, R, G))
    glob = rng.standard_normal((5, 16)).astype(np.float32)
    db = MapDatabase.from_arrays(
        poses=map_poses,
        timestamps=np.arange(5.0),
        sessions="s0",
        global_descriptors=glob / np.linalg.norm(glob, axis=1, keepdims=True),
        local_descriptors=local,
        model_config=model.config.to_dict(),
        grid_size=G,
        config_hash=model.config_hash(),
    )
    path = db.save(tmp_path / "map.h5")
    target = 2
    xi = (rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-np.pi, np.pi))
    q_pose = np.array(compose(map_poses[target], xi))
    q_bev = bev_at(field, q_pose)
    q_local = decode(kernels.polar_sample(q_bev, T, R, G))
    search = SearchConfig(half_range=3.0, step=0.6, fine_samples=32, stages=5, seed=seed)
    with MapDatabase.open(path, expected_config_hash=model.config_hash()) as mapdb:
        loc = Localizer(
            model,
            mapdb,
            top_k=5,
            search=search,
            decoder="radial_mean",
            metric_candidates=metric_candidates,
        )
        res = loc.localize_encoded(np.zeros(16, np.float32), q_local, q_bev)
        if metric_candidates > 1:
            # the first M re-ranked candidates are ordered by re-rank + metric cost
            one = Localizer(model, mapdb, top_k=5, search=search, decoder="radial_mean")
            ref = one.localize_encoded(np.zeros(16, np.float32), q_local, q_bev)
            m = metric_candidates
            metric_cost = {int(row): one.metric(q_bev, int(row))[1] for row in ref.reranked[:m]}
            score = {
                int(row): c + metric_cost[int(row)]
                for row, c in zip(ref.reranked[:m], ref.rerank_cost[:m], strict=True)
            }
            assert sorted(res.reranked.tolist()) == sorted(ref.reranked.tolist())
            assert res.reranked[m:].tolist() == ref.reranked[m:].tolist()
            assert res.reranked[:m].tolist() == sorted(score, key=score.__getitem__)
            assert res.cost == pytest.approx(metric_cost[res.map_row])
    assert res.map_row == target
    assert np.hypot(*(res.global_pose[:2] - q_pose[:2])) < 0.15, (res.global_pose, q_pose)
    assert abs(np.degrees(wrap(res.global_pose[2] - q_pose[2]))) < 1.0
    np.testing.assert_allclose(res.relative_pose[:2], xi[:2], atol=0.15)


def test_unknown_decoder_is_refused(tmp_path):
    model = _model()
    db = MapDatabase.from_arrays(
        poses=np.zeros((1, 3)),
        timestamps=np.zeros(1),
        sessions="s0",
        global_descriptors=np.ones((1, 4), np.float32) / 2,
        local_descriptors=np.ones((1, T, C)),
        model_config=model.config.to_dict(),
        grid_size=G,
        config_hash=model.config_hash(),
    )
    with pytest.raises(ValueError, match="decoder"):
        Localizer(model, db, decoder="magic")
    with pytest.raises(ValueError, match="metric_candidates"):
        Localizer(model, db, metric_candidates=0)
    for bad in (2.0, True):
        with pytest.raises(TypeError, match="metric_candidates"):
            Localizer(model, db, metric_candidates=bad)
