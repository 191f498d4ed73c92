"""End to end on a tiny rendered world: map build → localize → loops → exports, CLI included.

The model here is a small untrained network: these tests pin the plumbing, frames and files
(poses must be consistent with the map and the search), not accuracy. Accuracy of the metric
search itself is pinned by the geometry oracle (tests/test_metric_localize.py).
"""

from __future__ import annotations

import csv
import dataclasses
import importlib.util
import inspect
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from data_helpers import blank_frames
from vvloc import geometry
from vvloc.data import open_dataset
from vvloc.localize import MapDatabase, read_g2o, read_loop_csv, read_tum
from vvloc.localize.localizer import (
    METRIC_CANDIDATES,
    RETRIEVAL_WEIGHT,
    Localizer,
    build_map,
    check_training_rig,
    encode_frames,
    frames_to_tensors,
)
from vvloc.localize.loops import detect_loops, loop_candidates
from vvloc.localize.metric import SearchConfig
from vvloc.nets import ModelConfig, VVLocNet
from vvloc.provenance import cpu_model

#: A camera 1.5 m above the ground looking forward (OpenCV axes into the ego frame): an
#: identity cam_to_ego looks straight up, which opening a dataset warns about.
FORWARD = np.array([[0.0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1]])


def unit_rows(x: np.ndarray) -> np.ndarray:
    """``x`` (N, D) with each row divided by its L2 norm."""
    return x / np.linalg.norm(x, axis=1, keepdims=True)


SMALL_SEARCH = SearchConfig(half_range=1.2, step=0.6, fine_samples=8, stages=2)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    torch.manual_seed(0)
    d = tmp_path_factory.mktemp("ckpt") / "model"
    VVLocNet(ModelConfig.small()).save(d)
    return d


@pytest.fixture(scope="module")
def map_file(tiny_world, model_dir, tmp_path_factory):
    model = VVLocNet.load(model_dir)
    out = tmp_path_factory.mktemp("map") / "map.h5"
    build_map(model, open_dataset(tiny_world), ["s0"], out, progress=False)
    return out


def test_map_holds_every_keyframe_of_the_session(tiny_world, map_file, model_dir):
    ds = open_dataset(tiny_world)
    model = VVLocNet.load(model_dir)
    with MapDatabase.open(map_file, expected_config_hash=model.config_hash()) as db:
        assert len(db) == len(ds.session("s0"))
        np.testing.assert_allclose(db.poses, ds.session("s0").poses)
        assert db.has_bev
        cfg = model.config
        assert db.local_descriptors(0).shape == (cfg.num_angles, cfg.channels)


def test_map_from_another_model_is_refused(map_file, tmp_path):
    other = ModelConfig.small()
    other.channels = 32
    d = tmp_path / "other"
    VVLocNet(other).save(d)
    with pytest.raises(ValueError, match="model"):
        Localizer.open(map_file, d)


def test_a_map_whose_arrays_are_not_the_models_outputs_is_refused(map_file, model_dir):
    from vvloc.localize import MapError

    model = VVLocNet.load(model_dir)
    cfg = model.config
    with MapDatabase.open(map_file) as db:
        rows = np.arange(len(db))
        arrays = dict(
            poses=db.poses,
            timestamps=db.timestamps,
            sessions="s0",
            global_descriptors=db.global_descriptors,
            local_descriptors=db.local_descriptors(rows),
            bevs=db.bev(rows),
        )
    hashes = dict(
        model_config=cfg.to_dict(),
        config_hash=model.config_hash(),
        weights_hash=model.weights_hash(),
        grid_size=cfg.grid_size,
    )
    h, c = cfg.bev_height, cfg.channels
    changes = [
        ("bevs", arrays["bevs"][:, : h // 2, : h // 2], rf"BEVs are \({h // 2}, {h // 2}, {c}\)"),
        ("bevs", arrays["bevs"][..., : c // 2], rf"BEVs are \({h}, {h}, {c // 2}\)"),
        ("local_descriptors", arrays["local_descriptors"][..., : c // 2], "local-view desc"),
        (
            "global_descriptors",
            unit_rows(arrays["global_descriptors"][:, :4]),
            r"global descriptors are \(4,\)",
        ),
    ]
    for key, value, match in changes:
        mem = MapDatabase.from_arrays(**{**arrays, key: value}, **hashes)
        with pytest.raises(MapError, match=f"in-memory map: its {match}.* the model's"):
            Localizer(model, mem)
        with pytest.raises(MapError, match=f"in-memory map: its {match}"):
            detect_loops(model, mem, radius=2.0, window=0, progress=False)


def test_the_map_records_its_rig_and_the_localizer_compares_queries_with_it(
    tiny_world, map_file, model_dir, tmp_path
):
    import dataclasses
    import warnings

    ds = open_dataset(tiny_world)
    loc = Localizer.open(map_file, model_dir, top_k=3, search=SMALL_SEARCH)
    assert loc.map.rig == [c.to_json() for c in ds.cameras]
    resaved = MapDatabase.open(loc.map.save(tmp_path / "copy.h5"))
    assert resaved.rig == loc.map.rig  # save keeps it
    resaved.close()
    frame = ds.session("s1")[3]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loc.localize(frame)  # the map's own rig: no warning
    # a frame from another rig (one camera fewer): localized, with a warning, once
    other = dataclasses.replace(
        frame, images=frame.images[1:], K=frame.K[1:], cam_to_ego=frame.cam_to_ego[1:]
    )
    with pytest.warns(UserWarning, match=r"^frame: from another rig .*3 cameras"):
        loc.localize(other)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loc.localize(other)
    # a levelled frame of a tilting vehicle (its own cam_to_ego, 6° of pitch and 0.4 m of motion
    # compensation) is the map's rig; a camera mounted 20° lower is not
    tilt = np.eye(4)
    tilt[:3, :3] = Rotation.from_euler("y", 6, degrees=True).as_matrix()
    tilt[0, 3] = 0.4
    fresh = Localizer.open(map_file, model_dir, top_k=3, search=SMALL_SEARCH)
    # ... and so is one on a 25° slope whose cameras fired apart at speed (1.5 m between them)
    steep = np.eye(4)
    steep[:3, :3] = Rotation.from_euler("xy", [10, 25], degrees=True).as_matrix()
    fast = steep @ frame.cam_to_ego
    fast[:2, :3, 3] += steep[:3, 0] * 1.5
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fresh.localize(dataclasses.replace(frame, cam_to_ego=tilt @ frame.cam_to_ego))
        fresh.localize(dataclasses.replace(frame, cam_to_ego=fast))
    lower = frame.cam_to_ego.copy()
    lower[1, :3, :3] = Rotation.from_euler("y", 20, degrees=True).as_matrix() @ lower[1, :3, :3]
    with pytest.warns(
        UserWarning,
        match=r"rig than the map's \(cameras turned by up to 20\.0° and moved by up to 0\.00 m",
    ):
        fresh.localize(dataclasses.replace(frame, cam_to_ego=lower))
    fresh.map.close()
    # calibration a rig.json could not hold is refused, whatever the rig (a singular
    # cam_to_ego failed inside the encoder's matrix inverse, a zero K gave an answer)
    bad = dataclasses.replace(frame, K=np.full_like(frame.K, np.nan))
    with pytest.raises(
        ValueError,
        match=r"frames\[1\]\.K: expected finite \(4, 3, 3\) "
        r"intrinsics, got non-finite values$",
    ):  # it said "got (4, 3, 3)"
        loc.localize_batch([frame, bad])
    singular = frame.cam_to_ego.copy()
    singular[:, 3, :] = 0
    for change, match in [
        ({"cam_to_ego": singular}, r"^frame\.cam_to_ego: expected a finite rigid"),
        ({"K": np.zeros_like(frame.K)}, r"^frame\.K: expected a pinhole matrix"),
        ({"K": np.swapaxes(frame.K, 1, 2)}, r"^frame\.K: expected a pinhole matrix"),
        ({"K": frame.K[:3]}, r"^frame\.K: expected finite \(4, 3, 3\) intrinsics, got shape"),
    ]:
        with pytest.raises(ValueError, match=match):
            loc.localize(dataclasses.replace(frame, **change))
    assert len(loc.localize_batch(f for f in [frame])) == 1  # a generator is taken
    with pytest.raises(TypeError, match=r"^frames: expected a sequence of vvloc.data.Frame"):
        loc.localize_batch(frame)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"frames\[0\]: expected a vvloc.data.Frame"):
        loc.localize_batch([frame.images])
    with pytest.raises(ValueError, match="batch_size"):
        loc.localize_batch([frame], batch_size=0)
    # more cameras than the model holds embeddings for: named before any frame is encoded
    n = loc.model.config.max_cameras + 1
    many = np.arange(n) % len(frame.images)
    big = dataclasses.replace(
        frame, images=frame.images[many], K=frame.K[many], cam_to_ego=frame.cam_to_ego[many]
    )
    with pytest.raises(
        ValueError, match=rf"^frames\[1\]\.images: {n} cameras exceed ModelConfig\.max_cameras"
    ):
        loc.localize_batch([frame, big])
    # ... and by build_map, naming the dataset, before it writes anything
    from nets_helpers import tiny_config

    two = VVLocNet(tiny_config(max_cameras=2))
    with pytest.raises(
        ValueError, match=r"^dataset: .*tiny: 4 cameras exceed ModelConfig\.max_cameras=2 "
    ):
        build_map(two, ds, ["s0"], tmp_path / "two.h5", progress=False)
    assert not list(tmp_path.glob("*two.h5*"))
    # already-encoded queries of the wrong size are refused by name
    cfg = loc.model.config
    g = np.zeros(loc.map.global_descriptors.shape[1], np.float32)
    g[0] = 1.0  # unit length, as the encoder gives it
    lv = np.zeros(loc.map.local_shape, np.float32)
    bev = np.zeros((cfg.bev_height // 2, cfg.bev_width // 2, cfg.channels), np.float32)
    with pytest.raises(ValueError, match=r"^bev: expected shape"):
        loc.localize_encoded(g, lv, bev)
    with pytest.raises(ValueError, match=r"^loc: expected shape"):
        loc.localize_encoded(g, lv[:, :3], bev)
    bev = np.zeros((cfg.bev_height, cfg.bev_width, cfg.channels), np.float32)
    with pytest.raises(ValueError, match=r"^t_encode_ms: expected a finite time"):
        loc.localize_encoded(g, lv, bev, "x")  # type: ignore[arg-type]
    # a global descriptor that is not unit length would rank by its length: refused
    for bad, norm in ((g * 0, "0"), (g * 2, "2"), (g * 1.05, "1.05")):
        with pytest.raises(ValueError, match=rf"^g: expected L2-normalised .* norm {norm}"):
            loc.localize_encoded(bad, lv, bev)
    loc.close()
    # every stage of a closed localizer says so, those answering from memory too (retrieve
    # did) and before a query is encoded
    closed = r"^map \S+ is closed"
    for stage in (
        lambda: loc.retrieve(g),
        lambda: loc.rerank(lv, np.array([0])),
        lambda: loc.metric(bev, 0),
        lambda: loc.metric_best(bev, np.array([0])),
        lambda: loc.snap_row(np.zeros(3), np.array([0]), 0),
        lambda: loc.localize_encoded(g, lv, bev),
        lambda: loc.localize_batch([]),
    ):
        with pytest.raises(ValueError, match=closed):
            stage()
    with pytest.raises(FileNotFoundError, match=r"^checkpoint: \S*nothing does not exist"):
        Localizer.open(map_file, tmp_path / "nothing")


def test_one_localizer_serves_several_threads(tiny_world, map_file, model_dir):
    """A service shares one Localizer between threads: each answer is the one a call on its
    own gives (no state of one call leaks into another)."""
    from concurrent.futures import ThreadPoolExecutor

    session = open_dataset(tiny_world).session("s1")
    frames = [session[i] for i in (2, 9, 17, 30)]
    with Localizer.open(map_file, model_dir, top_k=3, search=SMALL_SEARCH) as loc:
        alone = [loc.localize(f) for f in frames]
        with ThreadPoolExecutor(4) as pool:
            together = list(pool.map(loc.localize, frames * 2))
    for got, want in zip(together, alone * 2, strict=True):
        assert (got.map_row, got.metric_row, got.accepted) == (
            want.map_row,
            want.metric_row,
            want.accepted,
        )
        np.testing.assert_array_equal(got.global_pose, want.global_pose)
        assert got.cost == want.cost


def test_a_rig_other_than_the_models_training_rig_is_warned_about_once(
    tiny_world, map_file, model_dir, tmp_path, monkeypatch
):
    import warnings

    import vvloc.localize.localizer as localizer

    monkeypatch.setattr(localizer, "_WARNED_RIGS", set())
    ds = open_dataset(tiny_world)
    model = VVLocNet.load(model_dir)
    assert model.training_rigs is None  # saved outside a run: nothing to compare with
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Localizer(model, MapDatabase.open(map_file), top_k=3).map.close()
    # weights trained on this rig: its map, and a recalibration of it, are the same rig
    rig = [c.to_json() for c in ds.cameras]
    model.training_record = {"runs": [{"rigs": [rig]}]}
    assert [[c.to_json() for c in r] for r in model.training_rigs] == [rig]
    K, cam_to_ego = ds.cameras[0].K, ds.cameras[0].cam_to_ego
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Localizer(model, MapDatabase.open(map_file), top_k=3).map.close()
        recalibrated = [
            dataclasses.replace(c, K=K * [[1.05], [1.05], [1.0]], cam_to_ego=cam_to_ego)
            if i == 0
            else c
            for i, c in enumerate(ds.cameras)
        ]
        assert check_training_rig(model, recalibrated, "recalibrated") == ""
    # weights trained on a 3-camera rig: building a map of the 4-camera dataset says so, and
    # localizing on that map in the same process does not say it again
    trained = VVLocNet.load(model_dir)
    trained.training_record = {"runs": [{"rigs": [rig]}, {"rigs": [rig[1:]]}]}  # the last run's
    ckpt = trained.save(tmp_path / "trained-on-3")
    trained = VVLocNet.load(ckpt)
    with pytest.warns(UserWarning) as caught:
        out = build_map(trained, ds, ["s2"], tmp_path / "m.h5", progress=False)
    (w,) = [str(c.message) for c in caught]
    assert w.startswith(
        "the dataset's rig is not the rig the model was trained on (4 cameras, against 3; "
        "trained on 3 cameras of 160x96 px)"
    )
    assert caught[0].filename == __file__  # named at the line that called build_map
    assert "Train on this rig's data" in w
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Localizer.open(out, ckpt, top_k=3).map.close()
    # another process (here: a cleared registry) opening that map is told too
    monkeypatch.setattr(localizer, "_WARNED_RIGS", set())
    with pytest.warns(UserWarning, match=r"map .*m\.h5's rig is not the rig the model was") as w:
        Localizer.open(out, ckpt, top_k=3).map.close()
    assert w[0].filename == __file__  # open's caller, not open's own line
    # images resized to half size (K scaled with them) are another rig to the networks
    half = [c.resized(80, 48) for c in ds.cameras]
    with pytest.warns(UserWarning, match="half is not the rig"):
        assert check_training_rig(model, half, "half") == "images of 80x48 px, against 160x96"
    # a run on two rigs (extra datasets of other cameras): a map of either is no surprise
    model.training_record = {"runs": [{"rigs": [rig, [c.to_json() for c in half]]}]}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert check_training_rig(model, half, "half") == ""
        assert check_training_rig(model, ds.cameras, "full") == ""
    with pytest.warns(UserWarning, match=r"\(3 cameras, against 4; .* px and 1 other rig\)"):
        check_training_rig(model, ds.cameras[1:], "three")


def test_localizer_options_are_checked_up_front(map_file, model_dir, tiny_world, tmp_path):
    model = VVLocNet.load(model_dir)
    db = MapDatabase.open(map_file)
    with pytest.raises(ValueError, match="step"):
        Localizer(model, db, search=SearchConfig(step=0.0))
    with pytest.raises(TypeError, match="rerank: expected a bool"):
        Localizer(model, db, rerank="no")
    assert Localizer(model, db, top_k=np.int64(4)).top_k == 4
    # a localizer made directly warns at its caller's line, as Localizer.open's callers are
    model.calibration = {"min_distinctiveness": 0.2, "top_k": 20}
    with pytest.warns(UserWarning, match=r"calibration was measured with top_k=20") as w:
        Localizer(model, db, top_k=3)
    with pytest.warns(UserWarning, match=r"rerank=False: the model's calibration") as w2:
        Localizer(model, db, top_k=20, rerank=False)
    assert w[0].filename == w2[0].filename == __file__
    # a map smaller than top_k cuts K to its keyframes: said, since no option of a command fixes
    # it (vvloc demo --frames 10 warned of "top_k=20" it was never given)
    n = len(db)
    model.calibration = {"min_distinctiveness": 0.2, "top_k": n + 5}
    said = rf"re-ranks {n} candidates \(all the map holds: {n} keyframes\).*; a map of more "
    with pytest.warns(UserWarning, match=said + "keyframes re-ranks the calibrated K$"):
        Localizer(model, db, top_k=n + 10)
    model.calibration = {}
    closed = MapDatabase.open(map_file)
    closed.close()  # refused when the localizer is made, not at its first query
    with pytest.raises(ValueError, match=r"map .*map\.h5 is closed"):
        Localizer(model, closed)
    # without re-ranking there is no distinctiveness: a calibration cannot apply
    model.calibration = {"min_distinctiveness": 0.2}
    with pytest.raises(ValueError, match=r"min_distinctiveness: 0\.1 needs re-ranking"):
        Localizer(model, db, rerank=False, min_distinctiveness=0.1)
    with pytest.warns(UserWarning, match="accepting by the cost rule alone"):
        loc = Localizer(model, db, rerank=False, top_k=3, search=SMALL_SEARCH)
    assert loc.min_distinctiveness == 0.0
    frame = open_dataset(tiny_world).session("s1")[2]
    r = loc.localize(frame)
    assert r.accepted == (r.cost < 0.75)
    assert r.map_floor == int(db.floors[r.map_row])  # the storey the answer puts the query on
    # printing a result gives one line with its answer, not every search hypothesis
    text = repr(r)
    assert "\n" not in text and len(text) < 600, text
    assert text.startswith(f"LocalizationResult(map_row={r.map_row}, map_id={r.map_id}, ")
    assert f"accepted={r.accepted}, cost={r.cost:.4f}" in text
    assert r.search is not None and f"search=<{len(r.search.cost)} hypotheses>" in text
    # images the network would misread are refused before any work, naming the frame
    bad = frame.images.astype(np.float32) / 255.0
    bad[0, 0, 3, 3] = np.nan  # spread through the BEV into the global descriptor
    bright = frame.images.astype(np.float32)  # the 0-255 scale in a float array
    for images, match in (
        (bad, r"frames\[1\]\.images: holds non-finite"),
        (bright, r"frames\[1\]\.images: float images must lie in \[0, 1\]"),
        (frame.images[0], r"frames\[1\]\.images: expected shape \(M, 3, H, W\)"),
    ):
        with pytest.raises(ValueError, match=match):
            loc.localize_batch([frame, dataclasses.replace(frame, images=images)])
    with pytest.raises(TypeError, match=r"frames\[0\]\.images: expected uint8 or float"):
        loc.localize_batch([dataclasses.replace(frame, images=frame.images.astype(np.int64))])
    # float [0, 1] images are the uint8 ones to float rounding
    same = loc.localize(dataclasses.replace(frame, images=frame.images / 255.0))
    assert same.map_row == r.map_row
    # encoded inputs of float64 are taken as float32 (the local descriptor reached the
    # interactor as double before)
    enc = encode_frames(model, [frame], keep_bev=True)
    assert enc.bev is not None
    r32 = loc.localize_encoded(enc.global_desc[0], enc.local_desc[0], enc.bev[0])
    r64 = loc.localize_encoded(
        *(a.astype(np.float64) for a in (enc.global_desc[0], enc.local_desc[0], enc.bev[0]))
    )
    assert r64.cost == r32.cost and np.array_equal(r64.global_pose, r32.global_pose)
    # values no encoder gives are refused by the argument's name, not by a kernel's
    encoded = {"g": enc.global_desc[0], "loc": enc.local_desc[0], "bev": enc.bev[0]}
    for name in encoded:
        with pytest.raises(ValueError, match=rf"{name}: values up to .* beyond ±1e\+06"):
            loc.localize_encoded(**{**encoded, name: encoded[name] * 1e20})
    # one candidate has distinctiveness 0: a calibration would accept nothing, and says so
    with pytest.warns(UserWarning, match="its distinctiveness is 0, below min_distinctiveness 0.1"):
        Localizer(model, db, top_k=1, min_distinctiveness=0.1, search=SMALL_SEARCH)
    with pytest.raises(TypeError, match="sessions: expected a list"):
        build_map(model, open_dataset(tiny_world), "s0", map_file.parent / "x.h5")
    # a path where an object belongs, or a batch size that is not one, is named
    ds = open_dataset(tiny_world)
    for call, error, match in [
        (lambda: build_map(model, str(tiny_world), ["s0"], tmp_path / "x.h5"), TypeError,
         r"dataset: expected a vvloc dataset \(vvloc.data.open_dataset\(path\)\), got str"),
        (lambda: build_map(str(model_dir), ds, ["s0"], tmp_path / "x.h5"), TypeError,
         r"model: expected a VVLocNet \(VVLocNet.load\(checkpoint\)\), got str"),
        (lambda: build_map(model, ds, ["s0"], tmp_path / "x.h5", batch_size=0), ValueError,
         "batch_size: expected an int >= 1, got 0"),
        (lambda: build_map(model, ds, ["s0"], tmp_path / "x.h5", batch_size=2.0), TypeError,
         "batch_size"),
        (lambda: build_map(model, ds, ["s0"], tmp_path / "x.h5", store_bev="no"), TypeError,
         "store_bev: expected a bool, got str"),
        (lambda: build_map(model, ds, [0], tmp_path / "x.h5"), TypeError,
         r"sessions: expected session names \(str\)"),
        (lambda: build_map(model, ds, ["s0", "s0"], tmp_path / "x.h5"), ValueError,
         r"sessions: \['s0'\] named more than once"),
        (lambda: build_map(model, ds, ["s9"], tmp_path / "x.h5"), ValueError,
         r"sessions: \['s9'\] not in the dataset; its sessions: s0, s1, s2"),
        (lambda: Localizer(model, str(map_file)), TypeError,
         r"mapdb: expected a MapDatabase \(MapDatabase.open\(path\), or Localizer.open"),
        (lambda: Localizer(None, db), TypeError, "model: expected a VVLocNet"),
    ]:  # fmt: skip
        with pytest.raises(error, match=match):
            call()
    assert not (tmp_path / "x.h5").exists()
    # a file at out is replaced only with overwrite, and only a map (as vvloc map build's
    # --out): the Python call replaced a user's file, and a map, without a word
    mine = tmp_path / "notes.txt"
    mine.write_text("hello")
    shutil.copy(map_file, tmp_path / "kept.h5")
    before = (tmp_path / "kept.h5").read_bytes()
    for out, kwargs, error, match in [
        (mine, {}, FileExistsError, r"^out: .*notes\.txt exists; pass overwrite=True"),
        (mine, {"overwrite": True}, FileExistsError, r"notes\.txt exists and is not a vvloc map"),
        (tmp_path / "kept.h5", {}, FileExistsError, r"kept\.h5 exists; pass overwrite=True"),
        (tmp_path, {}, IsADirectoryError, r"^out: .* is a folder; expected the path of a map"),
        ("", {}, IsADirectoryError, r"^out: \. is a folder"),
        (3, {}, TypeError, r"^out: expected the path of a map file, got int"),
        (tmp_path / "y.h5", {"overwrite": "yes"}, TypeError, r"^overwrite: expected a bool"),
    ]:
        with pytest.raises(error, match=match):
            build_map(model, ds, ["s0"], out, progress=False, **kwargs)
    assert mine.read_text() == "hello" and (tmp_path / "kept.h5").read_bytes() == before
    assert not (tmp_path / "y.h5").exists()
    # a generator of names is read once (its duplicate check consumed it: "[] hold no frames")
    gen = build_map(model, ds, (s for s in ["s0"]), tmp_path / "gen.h5", progress=False)
    with MapDatabase.open(gen) as built:
        assert list(built.sessions) == ["s0"]
    shutil.copytree(tiny_world, tmp_path / "empty")  # session "e": a poses.csv of no rows
    e = tmp_path / "empty" / "sessions" / "e"
    shutil.copytree(tmp_path / "empty" / "sessions" / "s0", e)
    (e / "poses.csv").write_text((e / "poses.csv").read_text().splitlines()[0] + "\n")
    for png in e.glob("*/*.png"):
        png.unlink()
    with pytest.raises(ValueError, match=r"sessions: \['e'\] hold no frames"):
        build_map(model, open_dataset(tmp_path / "empty"), ["e"], tmp_path / "e.h5")
    assert not (tmp_path / "e.h5").exists()
    with pytest.raises(TypeError, match="expected_config_hash"):
        MapDatabase.open(map_file, expected_config_hash=123)
    db.close()
    with Localizer.open(map_file, model_dir, top_k=2) as opened:
        assert len(opened.map) > 0
    run = tmp_path / "run"  # a training run's folder opens its best/ (else checkpoint/)
    shutil.copytree(model_dir, run / "checkpoint")
    with Localizer.open(map_file, run, top_k=2) as from_run:
        assert from_run.model.weights_hash() == model.weights_hash()
    with pytest.raises(ValueError, match="closed"):
        opened.map.local_descriptors(0)  # the with-block closed the map


def test_localize_poses_are_consistent_and_batch_equals_single(tiny_world, map_file, model_dir):
    loc = Localizer.open(map_file, model_dir, top_k=5, search=SMALL_SEARCH)
    frames = [open_dataset(tiny_world).session("s1")[i] for i in (0, 7)]
    batch = loc.localize_batch(frames)
    for f, r in zip(frames, batch, strict=True):
        single = loc.localize(f)
        assert single.map_row == r.map_row
        np.testing.assert_allclose(single.relative_pose, r.relative_pose, atol=1e-5)
        # the global pose is the map keyframe's pose composed with ξ_{m→q}
        np.testing.assert_allclose(
            r.global_pose, geometry.compose(loc.map.poses[r.map_row], r.relative_pose), atol=1e-9
        )
        assert r.map_row in r.retrieved
        assert sorted(r.reranked.tolist()) == sorted(r.retrieved.tolist())
        # the first M retrieved lead (the metric candidates, by coarse cost), the others follow
        # in yaw re-rank order; snapping may move a nearer keyframe to the front
        m = min(loc.metric_candidates, len(r.retrieved))
        pool = set(r.retrieved[:m].tolist())
        seq, cost = r.reranked.tolist(), r.rerank_cost
        if r.map_row != r.metric_row:
            pool.discard(seq[0])
            seq, cost = seq[1:], cost[1:]
        assert seq[0] == r.metric_row  # the refined one, the lowest coarse cost
        assert set(seq[: len(pool)]) == pool
        assert np.all(np.diff(cost[len(pool) :]) >= 0)
        assert abs(r.relative_pose[0]) <= 1.2 + 0.6 and abs(r.relative_pose[1]) <= 1.2 + 0.6
        assert set(r.timings_ms) == {"encode", "retrieve", "rerank", "metric"}
        assert r.accepted == (r.cost < 0.75)


def test_frames_without_image_content_are_left_out_of_maps_and_never_accepted(
    tiny_world, model_dir, tmp_path
):
    # two blank keyframes (a covered rig) encode alike wherever they were taken: in a map they
    # drew every blank query to them at cost ~0, accepted, and made false loop closures
    root = tmp_path / "world"
    shutil.copytree(tiny_world, root)
    blank_frames(root, "s0", [3, 4, 30])
    blank_frames(root, "s1", [5], value=255)  # blown out: no content either
    model = VVLocNet.load(model_dir)
    ds = open_dataset(root)
    with pytest.warns(
        UserWarning,
        match=r"session 's0': 3 of 40 frames have no image content "
        r"\(every camera's picture flat: frames 3, 4, 30\); left out of the map",
    ) as caught:
        build_map(model, ds, ["s0"], tmp_path / "map.h5", progress=False)
    assert caught[0].filename == __file__  # said at build_map's caller
    with MapDatabase.open(tmp_path / "map.h5") as db:
        kept = [i for i in range(40) if i not in (3, 4, 30)]
        assert db.seq.tolist() == kept
        np.testing.assert_allclose(db.poses, ds.session("s0").poses[kept])
    # every query accepted by a lenient localizer, but the blank one
    loc = Localizer.open(
        tmp_path / "map.h5",
        model_dir,
        top_k=3,
        search=SMALL_SEARCH,
        accept_threshold=float("inf"),
        min_distinctiveness=0.0,
    )
    frames = [ds.session("s1")[i] for i in (4, 5, 6)]
    with pytest.warns(
        UserWarning, match=r"1 of 3 query frames have no image content .*: frames 1\); not accepted"
    ):
        results = loc.localize_batch(frames)
    assert [r.accepted for r in results] == [True, False, True]
    assert [r.has_content for r in results] == [True, False, True]
    # with frames left out, a keyframe's id is no longer its frame: map_seq says which it is
    with MapDatabase.open(tmp_path / "map.h5") as db:
        for r in results:
            assert r.map_seq == kept[r.map_row] == int(db.seq[r.map_row])
    assert "accepted=False (no image content)" in repr(results[1])
    with pytest.warns(UserWarning, match=r"^the query frame has no image content") as caught:
        alone = loc.localize(frames[1])
    assert caught[0].filename == __file__  # the caller's line, not the localizer's
    assert not alone.accepted and not alone.has_content
    assert np.isfinite(results[1].cost)  # still localized, for who wants the answer
    loc.close()
    # a session of blank frames alone makes no map, and leaves no file
    blank_frames(root, "s2", range(40))
    with pytest.warns(UserWarning), pytest.raises(ValueError, match="none of the 40 frames"):
        build_map(model, open_dataset(root), ["s2"], tmp_path / "blank.h5", progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.h5", "world"]


def test_the_stage_methods_check_their_arguments_as_localize_encoded_does(
    tiny_world, map_file, model_dir
):
    loc = Localizer.open(map_file, model_dir, top_k=3, search=SMALL_SEARCH)
    frame = open_dataset(tiny_world).session("s1")[2]
    enc = encode_frames(loc.model, [frame], keep_bev=True)
    assert enc.bev is not None
    g, local, bev = enc.global_desc[0], enc.local_desc[0], enc.bev[0]
    rows, _ = loc.retrieve(g)
    r = loc.localize_encoded(g, local, bev)
    # the stages give what localize_encoded gives, float64 inputs as float32
    assert np.array_equal(loc.retrieve(g.astype(np.float64))[0], rows)
    rr = loc.rerank(local.astype(np.float64), rows)
    assert np.array_equal(rr.cost, loc.rerank(local, list(rows)).cost)
    xi, cost, _ = loc.metric(bev, int(r.metric_row))
    assert np.isfinite(cost) and xi.shape == (3,)
    assert loc.snap_row(r.global_pose, r.reranked, int(loc.map.floors[r.metric_row])) >= 0
    n = len(loc.map)
    for call, err, match in (
        (lambda: loc.retrieve(g[:-1]), ValueError, r"global_desc: expected shape"),
        (lambda: loc.retrieve(g * 2), ValueError, r"global_desc: .*unit"),
        (lambda: loc.rerank(local[:, :-1], rows), ValueError, r"local_desc: expected shape"),
        (lambda: loc.rerank(local, [-1]), ValueError, rf"rows: expected map rows in \[0, {n}\)"),
        (lambda: loc.rerank(local, [0.5]), TypeError, r"rows: expected an integer array"),
        (lambda: loc.rerank(local, []), ValueError, r"rows: expected at least one map row"),
        (lambda: loc.metric(bev, 1.7), TypeError, r"row: expected an int"),
        (lambda: loc.metric(bev, True), TypeError, r"row: expected an int"),
        (lambda: loc.metric(bev, n), ValueError, rf"row: expected map rows in \[0, {n}\)"),
        (lambda: loc.metric(bev[:5], 0), ValueError, r"bev: expected shape"),
        (lambda: loc.metric(bev * 1e30, 0), ValueError, r"bev: values up to"),
        (lambda: loc.metric_best(bev, [0, 1], bias=["a"]), TypeError, r"bias: expected a real"),
        (lambda: loc.metric_best(bev, [0, 1], bias=[0.0]), ValueError, r"bias: expected shape"),
        (lambda: loc.snap_row(r.global_pose[:1], rows, 0), ValueError, r"global_pose: expected"),
        (lambda: loc.snap_row([np.nan, 0, 0], rows, 0), ValueError, r"global_pose: .*non-finite"),
        (lambda: loc.snap_row(r.global_pose, [-1], 0), ValueError, r"rows: expected map rows"),
        (lambda: loc.snap_row(r.global_pose, rows, 0.5), TypeError, r"floor: expected an int"),
    ):
        with pytest.raises(err, match=match):
            call()


def test_frames_of_other_shapes_localize_in_one_call_as_alone(tiny_world, map_file, model_dir):
    loc = Localizer.open(map_file, model_dir, top_k=3, search=SMALL_SEARCH)
    f = open_dataset(tiny_world).session("s1")[2]
    three = dataclasses.replace(f, images=f.images[:3], K=f.K[:3], cam_to_ego=f.cam_to_ego[:3])
    with pytest.warns(UserWarning, match="from another rig"):  # once, for the 3-camera frame
        batch = loc.localize_batch([f, three, f])
    for frame, r in zip([f, three, f], batch, strict=True):
        single = loc.localize(frame)
        assert single.map_row == r.map_row
        np.testing.assert_allclose(single.relative_pose, r.relative_pose, atol=1e-5)
    with pytest.raises(ValueError, match=r"frames\[1\]: images \(3, 3, .*frames\[0\] \(4, 3"):
        frames_to_tensors([f, three], torch.device("cpu"))
    # uint8 (0-255) and float ([0, 1]) frames: each in a batch of its own kind (stacked, the
    # uint8 one read 255 times too bright)
    scaled = dataclasses.replace(f, images=f.images.astype(np.float32) / 255.0)
    for frames in ([f, scaled], [scaled, f, f]):
        for frame, r in zip(frames, loc.localize_batch(frames), strict=True):
            single = loc.localize(frame)
            assert single.map_row == r.map_row and abs(single.cost - r.cost) < 1e-6
            np.testing.assert_allclose(single.relative_pose, r.relative_pose, atol=1e-5)
    with pytest.raises(
        ValueError, match=r"frames\[1\]: images of dtype float32, frames\[0\] uint8"
    ):
        frames_to_tensors([f, scaled], torch.device("cpu"))


def test_loop_candidates_exclude_temporal_neighbours(map_file):
    with MapDatabase.open(map_file) as db:
        cand = loop_candidates(db, radius=2.0, window=3)
        assert np.all(cand.i < cand.j)
        same = db.session_index[cand.i] == db.session_index[cand.j]
        assert np.all(np.abs(db.seq[cand.i] - db.seq[cand.j])[same] > 3)


def test_cli_names_a_dataset_of_more_cameras_than_the_model_holds(map_file, model_dir, tmp_path):
    # the message named the encoder's 'images' argument, after the progress bar had started
    from vvloc.sim import simulate_dataset

    nine = tmp_path / "nine"
    simulate_dataset(nine, sessions=1, frames=2, cameras=9, width=32, height=24, progress=False)
    exe = [sys.executable, "-m", "vvloc.cli"]
    run = lambda *a: subprocess.run([*exe, *a], capture_output=True, text=True)  # noqa: E731
    common = ["--checkpoint", str(model_dir), "--dataset", str(nine)]
    said = rf"--dataset: {nine}: 9 cameras exceed ModelConfig.max_cameras=8 "
    new = tmp_path / "maps" / "m.h5"  # a folder made only once the build passes its checks
    r = run("map", "build", *common, "--sessions", "s0", "--out", str(new))
    assert r.returncode == 2 and f"vvloc map build: error: {said}" in r.stderr, r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["nine"]
    out = tmp_path / "loc"
    r = run("localize", *common, "--map", str(map_file), "--session", "s0", "--out", str(out))
    assert r.returncode == 2 and f"vvloc localize: error: {said}" in r.stderr, r.stderr
    assert not out.exists()


def test_cli_map_localize_loops_end_to_end(tiny_world, model_dir, tmp_path):
    exe = [sys.executable, "-m", "vvloc.cli"]
    map_path = tmp_path / "maps" / "m.h5"  # its folder is made, as eval and loops make theirs
    run = lambda *a: subprocess.run([*exe, *a], capture_output=True, text=True)  # noqa: E731
    r = run(
        "map",
        "build",
        "--checkpoint",
        str(model_dir),
        "--dataset",
        str(tiny_world),
        "--sessions",
        "s0,s1",
        "--out",
        str(map_path),
    )
    assert r.returncode == 0, r.stderr
    # bad outputs and inputs: exit code 2, a message naming the problem, no file left
    bad_map = lambda out, sessions="s0": run(  # noqa: E731
        "map", "build", "--checkpoint", str(model_dir), "--dataset", str(tiny_world),
        "--sessions", sessions, "--out", str(out),
    )  # fmt: skip
    # an existing map is kept unless --overwrite says to replace it
    before = map_path.read_bytes()
    r = bad_map(map_path)
    assert r.returncode == 2 and "--overwrite" in r.stderr and map_path.read_bytes() == before
    r = run("map", "build", "--checkpoint", str(model_dir), "--dataset", str(tiny_world),
            "--sessions", "s0,s1", "--out", str(map_path), "--overwrite")  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = bad_map(tmp_path / "nowhere" / "deeper" / "m.h5", "s0,s0")  # a refused build ...
    assert r.returncode == 2 and "more than once" in r.stderr
    assert not (tmp_path / "nowhere").exists()  # ... leaves no folder either
    r = bad_map(tmp_path / "maps" / "m.h5" / "m.h5")
    assert r.returncode == 2 and "m.h5 is a file, not a folder" in r.stderr, r.stderr
    r = bad_map(tmp_path)
    assert r.returncode == 2 and "is a folder" in r.stderr
    r = bad_map(tmp_path / "twice.h5", "s0,s0")
    assert r.returncode == 2 and "more than once" in r.stderr
    assert not list(tmp_path.glob(".*.tmp")) and not (tmp_path / "twice.h5").exists()
    r = run("map", "build", "--checkpoint", str(model_dir), "--dataset", str(tiny_world),
            "--sessions", "s0", "--out", str(tmp_path / "gpu.h5"), "--device", "gpu")  # fmt: skip
    assert r.returncode == 2 and "--device" in r.stderr

    def localize(out, *extra):
        common = ["--map", str(map_path), "--dataset", str(tiny_world), "--session", "s2"]
        return run("localize", *common, "--checkpoint", str(model_dir), "--out", out, *extra)

    r = localize(str(tmp_path / "loc"), "--top_k", "3", "--metric_candidates", "2")
    assert r.returncode == 0, r.stderr
    ts_all, _poses = read_tum(tmp_path / "loc" / "poses-all.tum")
    assert len(ts_all) == len(open_dataset(tiny_world).session("s2"))
    text = (tmp_path / "loc" / "queries.csv").read_text()
    assert text.startswith("# vvloc localize")
    assert text.splitlines()[1].split(",")[-4:] == [
        "metric_row", "map_floor", "has_content", "map_seq"
    ]  # fmt: skip
    # poses.tum holds the accepted localizations only (a trajectory evaluator's input)
    header = text.splitlines()[1].split(",")
    rows = [dict(zip(header, line.split(","), strict=True)) for line in text.splitlines()[2:]]
    ts, _poses = read_tum(tmp_path / "loc" / "poses.tum")
    accepted = [float(row["timestamp"]) for row in rows if row["accepted"] == "1"]
    np.testing.assert_allclose(ts, accepted, atol=1e-6)
    r = localize(str(tmp_path / "loc-none"), "--top_k", "3", "--threshold", "0")
    assert r.returncode == 0, r.stderr
    assert len(read_tum(tmp_path / "loc-none" / "poses.tum")[0]) == 0
    assert len(read_tum(tmp_path / "loc-none" / "poses-all.tum")[0]) == len(ts_all)
    for bad in ("nan", "-1"):  # costs are >= 0: either would accept nothing
        r = localize(str(tmp_path / "loc-nan"), "--threshold", bad)
        assert r.returncode == 2 and "--threshold" in r.stderr
        assert not (tmp_path / "loc-nan").exists()
    r = localize(str(tmp_path / "loc-rerank"), "--top_k", "3", "--metric_from", "rerank")
    assert r.returncode == 0, r.stderr
    r = localize(str(tmp_path / "loc-bad"), "--metric_from", "nearest")
    assert r.returncode == 2 and "--metric_from" in r.stderr
    r = localize(str(tmp_path / "loc-w"), "--metric_candidates", "2", "--retrieval_weight", "2")
    assert r.returncode == 0, r.stderr
    r = localize(str(tmp_path / "loc-bad-weight"), "--retrieval_weight", "-1")
    assert r.returncode == 2 and "--retrieval_weight" in r.stderr
    for flag in ("--no_snap", "--no-snap"):  # the second: its name before 2026-12-05
        r = localize(str(tmp_path / "loc-nosnap"), flag)
        assert r.returncode == 0, r.stderr
        lines = (tmp_path / "loc-nosnap" / "queries.csv").read_text().splitlines()
        header = lines[1].split(",")
        rows = [dict(zip(header, line.split(","), strict=True)) for line in lines[2:]]
        assert rows and all(row["map_row"] == row["metric_row"] for row in rows)
        assert all(row["map_floor"] == "0" for row in rows)  # the parking lot's one floor
        assert all(row["has_content"] == "1" for row in rows)
        # the keyframe's frame in its session: map_id counts the map's rows (s0 then s1)
        with MapDatabase.open(map_path) as db:
            for row in rows:
                map_row = int(row["map_row"])
                assert row["map_session"] == db.session_of(map_row)
                assert int(row["map_seq"]) == int(db.seq[map_row])
    loops_cli = lambda out, *a: run(  # noqa: E731
        "loops", "--map", str(map_path), "--checkpoint", str(model_dir), "--out", str(out), *a
    )
    r = loops_cli(tmp_path / "loops", "--radius", "0.5", "--max_pairs", "3")
    assert r.returncode == 0, r.stderr
    loops = read_loop_csv(tmp_path / "loops" / "loops.csv")
    graph = read_g2o(tmp_path / "loops" / "graph.g2o")
    assert len(graph.vertex_ids) == 2 * len(open_dataset(tiny_world).session("s0"))
    n_acc = int(loops.accepted.sum())
    assert len(graph.edges) == 2 * (len(graph.vertex_ids) // 2 - 1) + n_acc
    # keyframes.csv maps every vertex id back to its session, sequence number and time
    with MapDatabase.open(map_path) as db:
        text = (tmp_path / "loops" / "keyframes.csv").read_text()
        assert text.startswith("# vvloc keyframes")
        rows = list(csv.DictReader(line for line in text.splitlines() if line[0] != "#"))
        assert [int(r["id"]) for r in rows] == graph.vertex_ids.tolist() == db.ids.tolist()
        assert [r["session"] for r in rows] == [db.session_of(i) for i in range(len(db))]
        assert [float(r["timestamp"]) for r in rows] == db.timestamps.tolist()
        assert [int(r["seq"]) for r in rows] == db.seq.tolist()
        xyt = np.array([[float(r[k]) for k in ("x", "y", "yaw")] for r in rows])
        np.testing.assert_allclose(xyt, graph.vertex_poses, rtol=0, atol=1e-12)
    if importlib.util.find_spec("gtsam") is not None:  # a dev dependency: a real g2o reader
        import gtsam

        g, initial = gtsam.readG2o(str(tmp_path / "loops" / "graph.g2o"), False)
        assert (g.size(), initial.size()) == (len(graph.edges), len(graph.vertex_ids))
    assert len(loops.i) <= 3
    # the floor check (on by default) has nothing to judge on a one-floor map
    r = loops_cli(
        tmp_path / "loops-all", "--radius", "0.5", "--max_pairs", "3", "--no_check_floors"
    )
    assert r.returncode == 0, r.stderr
    unchecked = read_loop_csv(tmp_path / "loops-all" / "loops.csv")
    assert (unchecked.i.tolist(), unchecked.j.tolist()) == (loops.i.tolist(), loops.j.tolist())
    # the closest candidates of each keyframe, then the closest of those
    r = loops_cli(tmp_path / "loops-few", "--radius", "0.5", "--max_pairs", "2",
                  "--max_per_keyframe", "1")  # fmt: skip
    assert r.returncode == 0, r.stderr
    few = read_loop_csv(tmp_path / "loops-few" / "loops.csv")
    with MapDatabase.open(map_path) as db:
        kept = loop_candidates(db, 0.5, 10, 1, True).closest_per_keyframe(1)
        first = np.argsort(kept.distance, kind="stable")[:2]
        assert few.i.tolist() == db.ids[kept.i[first]].tolist()
        assert few.j.tolist() == db.ids[kept.j[first]].tolist()
    # bad input: exit code 2 and a message naming the problem
    r = loops_cli(tmp_path / "loops-bad", "--max_per_keyframe", "-1")
    assert r.returncode == 2 and "--max_per_keyframe" in r.stderr
    r = loops_cli(tmp_path / "loops-bad", "--sequence", "-1")
    assert r.returncode == 2 and "--sequence" in r.stderr
    r = loops_cli(tmp_path / "loops-bad", "--threshold", "nan")
    assert r.returncode == 2 and "--threshold" in r.stderr
    assert not (tmp_path / "loops-bad").exists()
    # a map written through the API with ids g2o cannot take is refused before the detection
    with MapDatabase.open(map_path) as db:
        rows = np.arange(len(db))
        ids = db.ids.copy()
        ids[-1] = 2**40
        MapDatabase.from_arrays(
            poses=db.poses,
            timestamps=db.timestamps,
            sessions=[db.session_of(i) for i in rows],
            global_descriptors=db.global_descriptors,
            local_descriptors=db.local_descriptors(rows),
            bevs=db.bev(rows),
            model_config=db.model_config,
            grid_size=db.grid_size,
            config_hash=db.config_hash,
            weights_hash=db.weights_hash,
            ids=ids,
            seq=db.seq,
            floors=db.floors,
            rig=db.rig,
        ).save(tmp_path / "big-ids.h5")
    r = run(
        "loops", "--map", str(tmp_path / "big-ids.h5"), "--checkpoint", str(model_dir),
        "--out", str(tmp_path / "loops-ids"),
    )  # fmt: skip
    assert r.returncode == 2 and "do not fit g2o's vertex ids" in r.stderr, r.stderr
    assert not (tmp_path / "loops-ids").exists()
    r = run(
        "localize",
        "--map",
        str(tmp_path / "missing.h5"),
        "--dataset",
        str(tiny_world),
        "--session",
        "s2",
        "--checkpoint",
        str(model_dir),
        "--out",
        str(tmp_path / "x"),
    )
    assert r.returncode == 2 and "missing.h5" in r.stderr


def test_detect_loops_api_returns_ids_and_costs(map_file, model_dir):
    model = VVLocNet.load(model_dir)
    with MapDatabase.open(map_file) as db:
        found = detect_loops(
            model, db, radius=2.0, window=3, max_pairs=2, search=SMALL_SEARCH, progress=False
        )
        assert len(found.i) == len(found.costs) <= 2
        assert set(found.i.tolist()) <= set(db.ids.tolist())
        assert np.all(found.accepted == (found.costs < 0.75))
        # the sequence check (default ±1 keyframe) keeps a subset of the single-keyframe pairs
        kw = {"radius": 2.0, "window": 3, "search": SMALL_SEARCH, "progress": False}
        checked = detect_loops(model, db, max_pairs=4, **kw)
        every = loop_candidates(db, radius=2.0, window=3)
        seq = loop_candidates(db, radius=2.0, window=3, sequence=1)
        assert len(seq.i) < len(every.i)
        assert set(zip(seq.i.tolist(), seq.j.tolist(), strict=True)) <= set(
            zip(every.i.tolist(), every.j.tolist(), strict=True)
        )
        ids = np.asarray(db.ids)
        seq_ids = set(zip(ids[seq.i].tolist(), ids[seq.j].tolist(), strict=True))
        assert len(checked.i) == min(4, len(seq.i))
        assert set(zip(checked.i.tolist(), checked.j.tolist(), strict=True)) <= seq_ids
        # a negative max_pairs would slice off the farthest candidates instead of failing
        with pytest.raises(ValueError, match="max_pairs"):
            detect_loops(model, db, max_pairs=-1, **kw)
        with pytest.raises(TypeError, match="max_pairs"):
            detect_loops(model, db, max_pairs=2.5, **kw)  # type: ignore[arg-type]
        assert len(detect_loops(model, db, max_pairs=0, **kw).i) == 0
        # the closest candidates of each keyframe, then the closest of those
        few = detect_loops(model, db, max_pairs=3, max_per_keyframe=1, **kw)
        kept = seq.closest_per_keyframe(1)
        assert 0 < len(kept.i) < len(seq.i)
        first = np.argsort(kept.distance, kind="stable")[:3]
        np.testing.assert_array_equal(few.i, ids[kept.i[first]])
        np.testing.assert_array_equal(few.j, ids[kept.j[first]])
        with pytest.raises(ValueError, match="max_per_keyframe: expected an int >= 1, got 0"):
            detect_loops(model, db, max_per_keyframe=0, **kw)
        # every argument is checked up front, by name, even when no pair is left to verify
        base = {"max_pairs": 0, "progress": False}
        for change, error, match in [
            ({"radius": "0.1"}, TypeError, "radius: expected a positive float, got str"),
            ({"radius": float("inf")}, ValueError, "radius: expected a finite value > 0"),
            ({"window": None}, TypeError, "window: expected an int >= 0, got NoneType"),
            ({"window": 1.7}, TypeError, "window: expected an int >= 0, got float"),
            (
                {"search": {"step": 0.6}},
                TypeError,
                "search: expected a SearchConfig or None, got dict",
            ),
            ({"search": SearchConfig(step=-1.0)}, ValueError, "step: expected a finite value"),
        ]:
            with pytest.raises(error, match=match):
                detect_loops(model, db, **{**base, **change})


def test_loops_cli_reuse_keeps_an_earlier_runs_pairs(tiny_world, model_dir, tmp_path):
    # the same keyframes: every pair kept; a map built again with its sessions in another order
    # numbers its keyframes anew: pairs of one session are found (session, sequence number,
    # time, descriptors) and kept, a pair across the two is ordered the other way round and
    # searched again; the result is a fresh run's either way
    model = VVLocNet.load(model_dir)
    ds = open_dataset(tiny_world)
    build_map(model, ds, ["s0", "s1"], tmp_path / "a.h5", progress=False)
    build_map(model, ds, ["s1", "s0"], tmp_path / "b.h5", progress=False)
    shutil.copy(tmp_path / "a.h5", tmp_path / "same.h5")
    exe = [sys.executable, "-m", "vvloc.cli", "loops", "--checkpoint", str(model_dir)]
    run = lambda m, out, *a: subprocess.run(  # noqa: E731
        [*exe, "--map", str(tmp_path / m), "--out", str(tmp_path / out), "--radius", "0.5",
         "--max_pairs", "4", *a],
        capture_output=True, text=True,
    )  # fmt: skip
    r = run("a.h5", "grown", "--reuse")  # nothing earlier there: every pair searched
    assert r.returncode == 0, r.stderr
    assert "no loops.csv or keyframes.csv in" in r.stdout, r.stdout
    first = read_loop_csv(tmp_path / "grown" / "loops.csv")
    assert len(first) == 4
    kf_text = (tmp_path / "grown" / "keyframes.csv").read_text()
    assert "# descriptor_sha256: 16 hex digits of the SHA-256" in kf_text
    r = run("same.h5", "grown", "--reuse")
    assert r.returncode == 0 and "--reuse: 4 of 4 pairs kept, 0 searched" in r.stdout, r.stdout
    with MapDatabase.open(tmp_path / "a.h5") as a:
        pairs = zip(first.i.tolist(), first.j.tolist(), strict=True)
        across = sum(a.session_of(i) != a.session_of(j) for i, j in pairs)
    r = run("b.h5", "grown", "--reuse")
    assert r.returncode == 0, r.stderr
    assert f"{4 - across} of 4 pairs kept, {across} searched" in r.stdout, r.stdout
    assert run("b.h5", "fresh").returncode == 0
    reused = (tmp_path / "grown" / "loops.csv").read_text()
    if torch.backends.mkl.is_available():  # bit for bit with MKL (test_verify_pairs...)
        assert reused == (tmp_path / "fresh" / "loops.csv").read_text()
    # another model's (or an older vvloc's) loops.csv is refused, not mixed in
    text = reused.replace("# model weights ", "# model weights 0")
    (tmp_path / "grown" / "loops.csv").write_text(text)
    r = run("b.h5", "grown", "--reuse")
    assert r.returncode == 2 and "with another model or search settings" in r.stderr, r.stderr
    assert (tmp_path / "grown" / "loops.csv").read_text() == text  # left as it was


def test_a_map_grows_from_a_base_map_without_encoding_its_frames_again(
    tiny_world, map_file, model_dir, tmp_path, monkeypatch
):
    import vvloc.localize.localizer as localizer_module
    from vvloc.localize import MapError
    from vvloc.localize.mapdb import MapWriter

    model = VVLocNet.load(model_dir)
    ds = open_dataset(tiny_world)
    encoded: list[int] = []
    encode = localizer_module.encode_frames

    def counting(model, frames, **kw):
        encoded.append(len(frames))
        return encode(model, frames, **kw)

    monkeypatch.setattr(localizer_module, "encode_frames", counting)
    grown = build_map(model, ds, ["s1"], tmp_path / "grown.h5", base=map_file, progress=False)
    assert sum(encoded) == len(ds.session("s1"))  # the base's frames were not encoded again
    fresh = build_map(model, ds, ["s0", "s1"], tmp_path / "fresh.h5", progress=False)
    with (
        MapDatabase.open(grown) as g,
        MapDatabase.open(fresh) as f,
        MapDatabase.open(map_file) as b,
    ):
        assert g.sessions == f.sessions == ("s0", "s1")
        for name in ["ids", "seq", "poses", "timestamps", "floors", "session_index"]:
            np.testing.assert_array_equal(getattr(g, name), getattr(f, name), err_msg=name)
        old = np.arange(len(b))
        np.testing.assert_array_equal(g.global_descriptors[old], b.global_descriptors)
        np.testing.assert_array_equal(g.local_descriptors(old), b.local_descriptors(old))
        np.testing.assert_array_equal(g.bev(old), b.bev(old))
        rows = np.arange(len(g))  # the new session's frames as a fresh build encodes them
        np.testing.assert_allclose(g.local_descriptors(rows), f.local_descriptors(rows), atol=1e-5)
        assert g.rig == b.rig and g.weights_hash == b.weights_hash
        n_fresh = len(f)
    # in place: the base file is replaced by the grown map once it is complete
    shutil.copy(map_file, tmp_path / "inplace.h5")
    build_map(model, ds, ["s1"], tmp_path / "inplace.h5", base=tmp_path / "inplace.h5",
              progress=False, overwrite=True)  # fmt: skip
    with MapDatabase.open(tmp_path / "inplace.h5") as m:
        assert m.sessions == ("s0", "s1") and len(m) == n_fresh
    # a float16 base stays float16 and its keyframes keep their stored values
    with MapDatabase.open(map_file) as b:
        b.save(tmp_path / "half.h5", dtype="float16")
    build_map(model, ds, ["s2"], tmp_path / "half2.h5", base=tmp_path / "half.h5", progress=False)
    with MapDatabase.open(tmp_path / "half2.h5") as h, MapDatabase.open(tmp_path / "half.h5") as b:
        assert h.metadata.descriptor_dtype == "float16" and len(h.sessions) == 2
        np.testing.assert_array_equal(h.global_descriptors[: len(b)], b.global_descriptors)
    # what cannot join the base is refused before anything is written
    other = VVLocNet(ModelConfig.small())  # its own random weights
    turned = [c.to_json() for c in ds.cameras]
    turned[1]["cam_to_ego"] = (  # turned 180° about its optical axis
        np.array(turned[1]["cam_to_ego"]) @ np.diag([-1.0, -1, 1, 1])
    ).tolist()
    with MapDatabase.open(map_file) as b, MapWriter(
        tmp_path / "rig.h5", model_config=b.model_config, grid_size=b.grid_size,
        config_hash=b.config_hash, weights_hash=b.weights_hash, rig=turned,
    ) as w:  # fmt: skip
        w.append_map(b)
    with MapDatabase.open(map_file) as b, MapWriter(
        tmp_path / "norig.h5", model_config=b.model_config, grid_size=b.grid_size,
        config_hash=b.config_hash, weights_hash=b.weights_hash,
    ) as w:  # fmt: skip
        w.append_map(b)  # as an older vvloc wrote maps: no rig recorded
    with pytest.warns(UserWarning, match=r"^base: map .*norig\.h5 records no rig") as caught:
        build_map(model, ds, ["s1"], tmp_path / "norig2.h5", base=tmp_path / "norig.h5",
                  progress=False)  # fmt: skip
    assert caught[0].filename == __file__
    with MapDatabase.open(tmp_path / "norig2.h5") as m:
        assert m.rig is None and m.sessions == ("s0", "s1")
    with MapDatabase.open(map_file) as b, MapWriter(
        tmp_path / "old.h5", model_config=b.model_config, grid_size=b.grid_size,
        config_hash=b.config_hash, rig=b.rig,
    ) as w:  # fmt: skip
        w.append_map(b)  # as an older vvloc wrote maps: no weights fingerprint
    for kwargs, error, match in [
        ({"base": tmp_path / "old.h5"}, MapError, r"^base: map .*old\.h5 records no weights"),
        ({"sessions": ["s0"]}, ValueError, r"^sessions: s0 already in the base map .*map\.h5"),
        ({"dtype": "float16"}, ValueError, r"^dtype: the base map .* stores float32 descrip"),
        ({"store_bev": False}, ValueError, r"^store_bev: the base map .* stores BEVs"),
        ({"model": other}, MapError, r"map built with other weights"),
        ({"base": tmp_path / "rig.h5"}, ValueError, r"^dataset: its rig is not the base map"),
        ({"base": "nowhere.h5"}, FileNotFoundError, r"nowhere\.h5"),
        ({"base": 3}, TypeError, r"^base: expected a MapDatabase or the path of a map, got int"),
    ]:
        args = {"model": model, "sessions": ["s1"], "base": map_file, **kwargs}
        with pytest.raises(error, match=match):
            build_map(args.pop("model"), ds, args.pop("sessions"), tmp_path / "bad.h5",
                      progress=False, **args)  # fmt: skip
        assert not list(tmp_path.glob("*bad.h5*")), kwargs


def test_cli_map_build_base_grows_a_map_and_loops_reuse_keeps_its_pairs(
    tiny_world, model_dir, map_file, tmp_path
):
    # the growing map's workflow: a session's map, its loops; the next session added with
    # --base (the map file replaced in place), loops again: the first session's pairs are kept
    shutil.copy(map_file, tmp_path / "map.h5")
    exe = [sys.executable, "-m", "vvloc.cli"]
    loops = [*exe, "loops", "--checkpoint", str(model_dir), "--map", str(tmp_path / "map.h5"),
             "--out", str(tmp_path / "loops"), "--radius", "0.018", "--reuse"]  # fmt: skip
    r = subprocess.run(loops, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    first = read_loop_csv(tmp_path / "loops" / "loops.csv")
    assert len(first) > 0, r.stdout  # the untrained model's descriptors lie within 0.02
    build = [*exe, "map", "build", "--checkpoint", str(model_dir), "--dataset", str(tiny_world),
             "--sessions", "s1", "--base", str(tmp_path / "map.h5"),
             "--out", str(tmp_path / "map.h5")]  # fmt: skip
    r = subprocess.run(build, capture_output=True, text=True)
    assert r.returncode == 2 and "pass --overwrite to replace it" in r.stderr, r.stderr
    r = subprocess.run([*build, "--overwrite"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    info = subprocess.run([*exe, "map", "info", str(tmp_path / "map.h5")], capture_output=True,
                          text=True)  # fmt: skip
    assert "in 2 sessions" in info.stdout and "  s1: 40 keyframes" in info.stdout, info.stdout
    r = subprocess.run(loops, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    grown = read_loop_csv(tmp_path / "loops" / "loops.csv")
    new = len(grown) - len(first)  # every earlier pair kept, only the new ones searched
    assert new > 0 and f"--reuse: {len(first)} of {len(grown)} pairs kept, {new} searched" in (
        r.stdout
    ), r.stdout
    fresh = [*loops[:-5], "--out", str(tmp_path / "fresh"), "--radius", "0.018"]
    assert subprocess.run(fresh, capture_output=True, text=True).returncode == 0
    if torch.backends.mkl.is_available():  # a fresh run's answer, bit for bit with MKL
        text = (tmp_path / "fresh" / "loops.csv").read_text()
        assert (tmp_path / "loops" / "loops.csv").read_text() == text
    again = subprocess.run([*build, "--overwrite"], capture_output=True, text=True)
    assert again.returncode == 2 and "--sessions: s1 already in the --base map" in again.stderr, (
        again.stderr
    )
    r = subprocess.run([*build, "--overwrite", "--sessions", "s2", "--float16"],
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 2 and "--float16: the --base map" in r.stderr, r.stderr
    r = subprocess.run([*build, "--overwrite", "--sessions", "s2", "--no_bev"],
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 2 and "--no_bev: the --base map" in r.stderr, r.stderr
    r = subprocess.run([*build[:-6], "--base", str(tmp_path / "nowhere.h5"), "--out",
                        str(tmp_path / "x.h5"), "--sessions", "s2"], capture_output=True,
                       text=True)  # fmt: skip
    assert r.returncode == 2 and "--base: map file not found" in r.stderr, r.stderr


def test_loops_cli_removes_only_its_own_stale_trajectories(tmp_path):
    from vvloc.commands.loops import remove_stale_trajectories
    from vvloc.localize.export import write_tum

    one = np.zeros((1, 3))
    for name in ("s0", "old"):  # an earlier run on a map with sessions s0 and old
        comment = f"map session {name!r} of earlier.h5: its keyframes' poses"
        write_tum(tmp_path / f"trajectory_{name}.tum", [0.0], one, comments=[comment])
    write_tum(tmp_path / "trajectory_mine.tum", [0.0], one)  # not written by vvloc loops
    (tmp_path / "trajectory_notes.tum").write_text("a user's file\n")
    gone = remove_stale_trajectories(tmp_path, ["trajectory_s0.tum"])
    assert gone == [tmp_path / "trajectory_old.tum"]
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == ["trajectory_mine.tum", "trajectory_notes.tum", "trajectory_s0.tum"]
    # an earlier run's session S0 is another file than s0's on a case-sensitive file system:
    # stale (it was kept, compared in lower case); one file on a case-insensitive one: kept
    comment = "map session 'S0' of earlier.h5: its keyframes' poses"
    write_tum(tmp_path / "trajectory_S0.tum", [0.0], one, comments=[comment])
    same = (tmp_path / "trajectory_S0.tum").samefile(tmp_path / "trajectory_s0.tum")
    gone = remove_stale_trajectories(tmp_path, ["trajectory_s0.tum"])
    assert gone == ([] if same else [tmp_path / "trajectory_S0.tum"])
    assert (tmp_path / "trajectory_s0.tum").is_file()


def test_loops_cli_leaves_no_folder_it_made_when_its_write_fails(
    map_file, model_dir, tmp_path, monkeypatch
):
    from typer.testing import CliRunner

    import vvloc._io
    from vvloc.cli import app

    def disk_full(*args: object, **kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(vvloc._io, "write_together", disk_full)
    out = tmp_path / "loops"
    args = ["loops", "--map", str(map_file), "--checkpoint", str(model_dir), "--out", str(out)]
    result = CliRunner().invoke(app, [*args, "--max_pairs", "2", "--threads", "1"])
    assert result.exit_code == 1 and "No space left on device" in result.output
    assert not out.exists()  # was left behind, empty
    out.mkdir()  # a folder of the user's stays
    result = CliRunner().invoke(app, [*args, "--max_pairs", "2", "--threads", "1"])
    assert result.exit_code == 1 and out.is_dir()


def test_loops_cli_never_replaces_files_it_did_not_write(tmp_path):
    from vvloc.commands.loops import check_loops_folder
    from vvloc.localize import LoopClosures
    from vvloc.localize.export import write_loop_csv, write_tum

    out = tmp_path / "out"
    out.mkdir()
    mine = ["trajectory_s0.tum"]
    check_loops_folder(out, mine)  # empty: fine
    (out / "graph.g2o").write_text("my own graph\n")
    with pytest.raises(FileExistsError, match=r"holds graph\.g2o, which no earlier vvloc loops"):
        check_loops_folder(out, mine)
    # an earlier run's loops.csv vouches for its graph.g2o; a user's trajectory is still kept
    none = LoopClosures(
        np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0),
        np.zeros(0, bool),
    )  # fmt: skip
    write_loop_csv(out / "loops.csv", none)
    check_loops_folder(out, mine)
    write_tum(out / "trajectory_s0.tum", [0.0], np.zeros((1, 3)))  # not vvloc loops' header
    with pytest.raises(FileExistsError, match=r"holds trajectory_s0\.tum"):
        check_loops_folder(out, mine)
    write_tum(
        out / "trajectory_s0.tum", [0.0], np.zeros((1, 3)),
        comments=["map session 's0' of map.h5: its keyframes' poses"],
    )  # fmt: skip
    check_loops_folder(out, mine)
    (out / "keyframes.csv").write_text("my,table\n")  # not vouched for by loops.csv
    with pytest.raises(FileExistsError, match=r"holds keyframes\.csv, which no earlier"):
        check_loops_folder(out, mine)
    (out / "keyframes.csv").write_text("# vvloc keyframes: ...\n")
    check_loops_folder(out, mine)
    (out / "loops.csv").write_text("my,csv\n")
    with pytest.raises(FileExistsError, match=r"holds loops\.csv, graph\.g2o"):
        check_loops_folder(out, mine)
    # nor inside a dataset, whose folders the outputs would corrupt: any dataset, not only
    # the command's own (vvloc eval --out wrote a report into another dataset's folder)
    from vvloc.commands._util import check_out_folder

    data = tmp_path / "data"
    (data / "sessions" / "s0").mkdir(parents=True)
    (data / "rig.json").write_text("{}")
    for inside in (data, data / "sessions" / "s0", data / "sessions" / "new" / "deeper"):
        with pytest.raises(ValueError, match=rf"^--out: .* lies inside the dataset {data}; "):
            check_out_folder(inside)
        with pytest.raises(ValueError, match=r"^--out: .* lies inside the dataset"):
            check_out_folder(inside, outside=tmp_path / "other")
    check_out_folder(tmp_path / "beside")  # beside a dataset: fine


def test_calibrate_cli_scores_the_localizers_answers_and_never_loses_a_calibration(
    tiny_world, tmp_path
):
    import json

    from vvloc.commands.demo import DEFAULT_MODEL

    # the committed model on the tiny world (its training world)
    ckpt = tmp_path / "model"
    VVLocNet.load(DEFAULT_MODEL).save(ckpt)
    before = (ckpt / "calibration.json").read_bytes()
    exe = [sys.executable, "-m", "vvloc.cli", "calibrate", "--checkpoint", str(ckpt),
           "--dataset", str(tiny_world), "--queries", "s1,s2", "--every", "4",
           "--top_k", "5"]  # fmt: skip
    run = lambda *a: subprocess.run([*exe, *a], capture_output=True, text=True)  # noqa: E731
    r = run("--precision", "0.5", "--min_accepted", "2")
    assert r.returncode == 2 and "--overwrite" in r.stderr  # an existing calibration is kept
    assert (ckpt / "calibration.json").read_bytes() == before
    r = run("--threshold", "1e-9", "--min_accepted", "2", "--overwrite")
    assert r.returncode == 1 and "passes the cost rule (cost < 1e-09)" in r.stderr, r.stderr
    assert "Try a higher --threshold" in r.stderr, r.stderr  # not a lower --precision
    assert r.stderr.count("vvloc calibrate:") == 1, r.stderr  # one message, no empty second one
    assert (ckpt / "calibration.json").read_bytes() == before  # nothing written on failure
    # what could only fail after the map is built fails before it (exit 2, no map encoded)
    for bad, said in (
        (("--min_accepted", "1000"), "--min_accepted: 1000 accepted queries can never be"),
        (("--retrieval_weight", "inf"), "--retrieval_weight"),
    ):
        r = run(*bad, "--overwrite")
        assert r.returncode == 2 and said in r.stderr, r.stderr
        assert "map:" not in r.stderr  # the map's progress bar never started
    # ... as does a query set with no revisit of the map (said after the whole map was built)
    far = tmp_path / "far"
    shutil.copytree(tiny_world, far)
    for name in ("s1", "s2"):
        poses = far / "sessions" / name / "poses.csv"
        head, *rows = poses.read_text().splitlines()
        assert head.startswith("timestamp,x,")
        cells = [row.split(",") for row in rows]
        shifted = [",".join([c[0], str(float(c[1]) + 500.0), *c[2:]]) for c in cells]
        poses.write_text("\n".join([head, *shifted]) + "\n")
    far_exe = [str(far) if a == str(tiny_world) else a for a in exe]
    r = subprocess.run([*far_exe, "--overwrite"], capture_output=True, text=True)
    assert r.returncode == 2 and "--queries: no query has a map keyframe within 2 m" in r.stderr
    assert "map:" not in r.stderr, r.stderr
    assert (ckpt / "calibration.json").read_bytes() == before
    r = run("--precision", "0.5", "--min_accepted", "2", "--overwrite", "--metric_candidates", "3")
    assert r.returncode == 0, r.stderr
    text = (ckpt / "calibration.json").read_text()
    cal = json.loads(text, parse_constant=lambda c: pytest.fail(f"not strict JSON: {c}"))
    assert cal["sessions"] == ["s1", "s2"] and cal["top_k"] == 5 and cal["database"] == "s0"
    # the tiny world is the committed model's training world: its s1, s2 are drives it
    # trained on, and calibrating on them is said to be too lenient, as vvloc eval says
    assert "warning: --queries ['s1', 's2'] of" in r.stderr and "were trained on" in r.stderr
    assert cal["target_precision"] == 0.5 and cal["every"] == 4
    assert cal["localizer"] == {
        "metric_candidates": 3,
        "metric_from": "retrieval",
        "retrieval_weight": RETRIEVAL_WEIGHT,
        "snap": True,
    }
    assert 2 <= cal["accepted"] <= cal["passing_cost"] <= cal["queries"] <= 20
    assert cal["precision"] >= 0.5 and cal["min_distinctiveness"] >= 0.0
    assert VVLocNet.load(ckpt).calibration == cal


def test_calibration_is_kept_with_the_checkpoint_and_gates_acceptance(
    tiny_world, map_file, model_dir, tmp_path
):
    import json

    ckpt = tmp_path / "model"
    model = VVLocNet.load(model_dir)
    # no threshold reached the target: accept nothing; the file stays strict JSON
    model.calibration = {"min_distinctiveness": float("inf"), "precision": float("nan")}
    model.save(ckpt)
    text = (ckpt / "calibration.json").read_text()
    assert json.loads(text) == {"min_distinctiveness": None, "precision": None}
    back = VVLocNet.load(ckpt).calibration
    assert back["min_distinctiveness"] == float("inf") and np.isnan(back["precision"])
    with pytest.warns(UserWarning, match="calibration accepts nothing"):  # shown from Python too
        Localizer.open(map_file, ckpt)
    cal = model.calibration = {"min_distinctiveness": 0.0123, "precision": 0.9, "queries": 40}
    model.save(ckpt)
    model = VVLocNet.load(ckpt)
    assert model.calibration == cal
    # the Localizer takes the model's threshold unless told otherwise
    assert Localizer.open(map_file, ckpt).min_distinctiveness == cal["min_distinctiveness"]
    # ... and says so when its K or cost rule is not the one the calibration was measured with
    model.calibration = {**cal, "top_k": 20, "accept_threshold": 0.75}
    model.save(ckpt)
    with pytest.warns(UserWarning, match="measured with top_k=20"):
        Localizer.open(map_file, ckpt, top_k=3)
    with pytest.warns(UserWarning, match="accept_threshold=0.75"):
        Localizer.open(map_file, ckpt, accept_threshold=0.5)
    model.calibration = cal
    model.save(ckpt)
    frames = [open_dataset(tiny_world).session("s1")[i] for i in range(0, 40, 8)]
    loc = Localizer.open(map_file, model_dir, top_k=5, search=SMALL_SEARCH)
    assert loc.min_distinctiveness == 0.0  # an uncalibrated model: the paper's cost rule alone
    res = loc.localize_batch(frames)
    d = np.array([x.distinctiveness for x in res])
    np.testing.assert_allclose(d, [x.rerank_cost.mean() - x.rerank_cost.min() for x in res])
    assert all(x.accepted == (x.cost < 0.75) for x in res)
    gate = float(np.median(d))
    strict = Localizer.open(
        map_file, model_dir, top_k=5, search=SMALL_SEARCH, min_distinctiveness=gate
    )
    for x in strict.localize_batch(frames):
        assert x.accepted == (x.cost < 0.75 and x.distinctiveness >= gate)
    for bad, err in ((-0.1, ValueError), ("high", TypeError)):
        with pytest.raises(err, match="min_distinctiveness"):
            Localizer.open(map_file, model_dir, min_distinctiveness=bad)
    for bad, err in ((float("nan"), ValueError), ("0.5", TypeError)):
        with pytest.raises(err, match="accept_threshold"):
            Localizer.open(map_file, model_dir, accept_threshold=bad)
    # saving weights without a calibration removes a stale one
    model.calibration = {}
    model.save(ckpt)
    assert not (ckpt / "calibration.json").exists()


def test_evaluation_scores_loop_closures_at_the_given_radius(tiny_world, model_dir, tmp_path):
    from vvloc.localize.evaluation import run_evaluation

    kw = {"every": 10, "search": SMALL_SEARCH, "progress": False, "loops": True, "loop_pairs": 2}
    with pytest.raises(ValueError, match="loop_radius"):
        run_evaluation(model_dir, tiny_world, "s0", ["s1"], tmp_path / "bad", loop_radius=0.0, **kw)
    with pytest.raises(ValueError, match="loop_sequence"):
        run_evaluation(
            model_dir, tiny_world, "s0", ["s1"], tmp_path / "bad", loop_sequence=-1, **kw
        )
    with pytest.raises(TypeError, match="loop_sequence"):
        run_evaluation(
            model_dir, tiny_world, "s0", ["s1"], tmp_path / "bad", loop_sequence=1.0, **kw
        )
    with pytest.raises(TypeError, match=r"queries: expected a sequence of session names"):
        run_evaluation(model_dir, tiny_world, "s0", "s1", tmp_path / "bad", **kw)  # not 's', '1'
    assert not (tmp_path / "bad").exists()
    m = run_evaluation(model_dir, tiny_world, "s0", ["s1"], tmp_path / "ev", loop_radius=0.3, **kw)
    world = {"scene": "parking", "seed": 0, "floors": 1, "floor_marking": "walls"}
    assert m["meta"]["scene"] == world  # from rig.json, for vvloc targets
    for name in ("VVLoc (descriptor radius)", "VVLoc + sequence (±1 keyframes)"):
        at = m["loop_closure"][name]["at_threshold"]
        assert at["threshold"] == 0.3
        # only pairs accepted at the radius are verified metrically (at most loop_pairs of them)
        assert m["loop_pose"][name]["all"]["count"] == min(2, at["accepted"])
        events = m["loop_closure"][name]["events"]
        assert 0 < events["events"] <= at["accepted"] or at["accepted"] == 0
        assert events["cross_floor_events"] <= events["events"]
    # the floor check's rows: a one-floor world gives it nothing to judge
    for name, checked in (
        ("VVLoc (descriptor radius)", "VVLoc + floor consensus"),
        ("VVLoc + sequence (±1 keyframes)", "VVLoc + sequence (±1 keyframes) + floor consensus"),
    ):
        a, b = (m["loop_closure"][k]["at_threshold"] for k in (name, checked))
        assert (a["accepted"], a["precision"], a["recall"]) == (
            b["accepted"],
            b["precision"],
            b["recall"],
        )
    single = m["loop_closure"]["VVLoc (descriptor radius)"]["at_threshold"]["accepted"]
    assert (
        m["loop_closure"]["VVLoc + sequence (±1 keyframes)"]["at_threshold"]["accepted"] <= single
    )
    meta = m["meta"]  # the defaults
    assert meta["snap"] is True and meta["metric_candidates"] == METRIC_CANDIDATES
    assert meta["metric_from"] == "retrieval"
    assert meta["retrieval_weight"] == RETRIEVAL_WEIGHT
    assert meta["cpu"] == cpu_model()  # the processor that evaluated
    # the report names the weights, not only the architecture (trained models share the latter)
    assert meta["model_weights_hash"] == VVLocNet.load(model_dir).weights_hash()
    # ... and says what produced them: here nothing recorded (weights saved outside a run)
    assert meta["trained_on"] == "no training record for these weights"
    assert m["training"] is None
    report = (tmp_path / "ev" / "report.md").read_text()
    assert f"then the first {METRIC_CANDIDATES} retrieved candidates put first" in report
    assert f"plus {RETRIEVAL_WEIGHT:g} × its global-descriptor distance" in report
    assert "| VVLoc (descriptor radius) | < 0.300 |" in report  # the detector's rule
    assert m["loop_sweep_radius"] == 0.5  # a tiny world: every pair within 0.5 is scored
    # the sweep and the verified pairs' confidence curve are in the JSON, and plotted
    for res in m["loop_closure"].values():
        sweep = res["sweep"]
        assert len(sweep["threshold"]) == len(sweep["recall"]) <= 256
    conf = m["loop_pose"]["VVLoc (descriptor radius)"]["confidence_curve"]
    assert len(conf["threshold"]) == len(conf["kept_share"]) <= 2
    assert (tmp_path / "ev" / "precision_recall.png").is_file()
    assert "Loop closure precision-recall" in report
    from vvloc.commands.evaluate import eval_command
    from vvloc.localize.evaluation import LOOP_SWEEP_PAIRS

    cli_default = inspect.signature(eval_command).parameters["loop_sweep_pairs"].default
    assert cli_default == LOOP_SWEEP_PAIRS
    with pytest.raises(ValueError, match="loop_sweep_pairs"):
        run_evaluation(
            model_dir, tiny_world, "s0", ["s1"], tmp_path / "bad", loop_sweep_pairs=0, **kw
        )
    assert not (tmp_path / "bad").exists()
    # a memory bound of one pair: the sweep shrinks to the acceptance radius, and says so;
    # these weights carry a training record, which the report summarises and keeps whole
    recorded = VVLocNet.load(model_dir)
    proc = {"hardware": "h", "device": "cpu", "device_name": None}
    recorded.training_record = {"runs": [{"seconds": 120.0, "processes": [proc]}]}
    recorded_dir = recorded.save(tmp_path / "recorded")
    m1 = run_evaluation(
        recorded_dir,
        tiny_world,
        "s0",
        ["s1"],
        tmp_path / "ev1",
        loop_radius=0.3,
        loop_sweep_pairs=1,
        **kw,
    )
    assert m1["meta"]["trained_on"] == "cpu on h; 1 run, 2.0 min"
    assert m1["training"] == recorded.training_record
    report1 = (tmp_path / "ev1" / "report.md").read_text()
    assert "- **trained_on**: cpu on h; 1 run, 2.0 min" in report1
    assert m1["loop_sweep_radius"] == pytest.approx(0.3)
    assert any("acceptance radius 0.3 only" in n and "loop_sweep_pairs" in n for n in m1["notes"])
    for name, curve in m1["loop_closure"].items():
        # the figures at the acceptance radius do not depend on the sweep's bound
        assert curve["at_threshold"] == m["loop_closure"][name]["at_threshold"]
        assert curve["best_f1"]["threshold"] <= 0.3 + 1e-9


def test_evaluation_breaks_recall_down_by_query_session(tiny_world, model_dir, tmp_path):
    from vvloc.localize.evaluation import run_evaluation

    kw = {"every": 5, "search": SMALL_SEARCH, "progress": False}
    m = run_evaluation(model_dir, tiny_world, "s0", ["s1", "s2"], tmp_path / "ev", **kw)
    per = m["per_session"]
    assert list(per) == ["s1, VVLoc-G", "s1, VVLoc-ML", "s2, VVLoc-G", "s2, VVLoc-ML"]
    for method in ("VVLoc-G", "VVLoc-ML"):
        whole = m["global_localization"][method]
        parts = [per[f"{s}, {method}"] for s in ("s1", "s2")]
        assert sum(p.num_queries for p in parts) == whole.num_queries
        assert sum(p.num_kept for p in parts) == whole.num_kept
        # the sessions' correct top-1 add up to the whole's
        assert sum(int(p.correct(1, 2.0).sum()) for p in parts) == int(whole.correct(1, 2.0).sum())
    assert "## Global localization per query session" in (tmp_path / "ev" / "report.md").read_text()
    # queries.csv carries what the report's rows select by: the kept count and the pose row
    # over the kept queries on their floor can be recomputed from it
    rows = list(
        csv.DictReader(
            line
            for line in (tmp_path / "ev" / "queries.csv").read_text().splitlines()
            if not line.startswith("#")
        )
    )
    whole = m["global_localization"]["VVLoc-ML"]
    assert len(rows) == whole.num_queries
    assert sum(int(r["kept"]) for r in rows) == whole.num_kept
    assert [int(r["kept"]) for r in rows] == whole.kept.astype(int).tolist()
    on_floor = [r for r in rows if r["kept"] == "1" and r["floor"] == r["map_floor"]]
    assert len(on_floor) == m["pose_accuracy"]["VVLoc-ML"]["all"]["count"]
    # a run into that folder that fails (or is stopped) after its map is built leaves the
    # earlier report whole: map, queries, figures and report as they were, nothing hidden
    import vvloc.localize.evaluation as ev

    before = {p.name: p.read_bytes() for p in (tmp_path / "ev").iterdir()}
    real_localizer = ev.Localizer

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    ev.Localizer = stopped  # type: ignore[assignment]
    try:
        with pytest.raises(KeyboardInterrupt):
            run_evaluation(model_dir, tiny_world, "s1", ["s2"], tmp_path / "ev", **kw)
    finally:
        ev.Localizer = real_localizer  # type: ignore[misc]
    assert {p.name: p.read_bytes() for p in (tmp_path / "ev").iterdir()} == before
    # robustness: the whole localizer under each perturbation, the same metrics as clean
    (tmp_path / "rob").mkdir()
    (tmp_path / "rob" / "precision_recall.png").write_bytes(b"an earlier run's loop figure")
    (tmp_path / "rob" / "loops_map.h5").write_bytes(b"an earlier run's loop map")
    (tmp_path / "rob" / "report.json").write_text('{"meta": {}, "global_localization": {}}')
    rob = run_evaluation(
        model_dir, tiny_world, "s0", ["s1"], tmp_path / "rob", robustness=True, **kw
    )
    for stale in ("precision_recall.png", "loops_map.h5"):  # no loops in this run
        assert not (tmp_path / "rob" / stale).exists()
    from vvloc.localize.evaluation import ROBUSTNESS

    want = [f"{p}, {m}" for p in ROBUSTNESS for m in ("VVLoc-G", "VVLoc-ML")]
    assert list(rob["robustness"]) == want
    assert list(rob["robustness_pose"]) == list(ROBUSTNESS)
    for label in ROBUSTNESS:
        clean = rob["global_localization"]["VVLoc-ML"]
        assert rob["robustness"][f"{label}, VVLoc-ML"].num_queries == clean.num_queries
        assert set(rob["robustness_pose"][label]) == {"true_revisit", "all", "every_query"}
    text = (tmp_path / "rob" / "report.md").read_text()
    assert "## Robustness (metric pose accuracy under perturbations)" in text
    assert "| motion blur, VVLoc-ML |" in text
    one = run_evaluation(model_dir, tiny_world, "s0", ["s1"], tmp_path / "one", **kw)
    assert one["per_session"] == {}
    assert "per query session" not in (tmp_path / "one" / "report.md").read_text()


def test_robustness_pose_leaves_out_answers_built_on_another_floor(monkeypatch):
    """Under perturbations as for the clean queries: a pose built on a keyframe of another
    floor is no success, however small its x-y error (it is counted in other_floor)."""
    from types import SimpleNamespace

    import vvloc.localize.evaluation as ev

    monkeypatch.setattr(ev, "perturbed", lambda frame, label: frame)
    db_pose, db_floor = np.zeros((2, 3)), np.array([0, 1])  # one spot, two floors
    q_pose, q_floor = np.array([[0.5, 0.0, 0.0], [0.5, 0.0, 0.0]]), np.array([0, 0])
    perfect = np.array([0.5, 0.0, 0.0])
    results = [
        SimpleNamespace(global_pose=perfect, retrieved=np.array(order), reranked=np.array(order),
                        metric_row=order[0])
        for order in ([0, 1], [1, 0])
    ]  # fmt: skip
    loc = SimpleNamespace(localize_batch=lambda frames, progress: results)
    _, poses = ev._robustness(loc, [None, None], q_pose, q_floor, db_pose, db_floor, 2, False)
    for label in ev.ROBUSTNESS:
        assert poses[label]["all"]["count"] == 1
        assert poses[label]["all"]["other_floor"] == 1


def test_calibration_of_results_scores_the_reported_keyframe_under_the_cost_rule():
    from types import SimpleNamespace

    from vvloc.localize.calibrate import calibration_of_results

    db = np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0], [30, 0, 0]])
    q = np.array([[0.5, 0, 0], [10.5, 0, 0], [20.5, 0, 0], [30.5, 0, 0], [100, 0, 0]])
    res = [  # (reported keyframe, cost, distinctiveness)
        SimpleNamespace(reranked=np.array([r, 1]), cost=c, distinctiveness=d, has_content=True)
        for r, c, d in [(0, 0.3, 0.9), (2, 0.3, 0.8), (2, 0.3, 0.7), (3, 0.9, 1.0), (0, 0.1, 5.0)]
    ]
    kw = {"query_floors": np.zeros(5, int), "db_poses": db, "db_floors": np.zeros(4, int)}
    # q3 fails the cost rule, q4 has no map keyframe within 2 m: the others are right, wrong,
    # right at 0.9, 0.8, 0.7, so 0.7 is the lowest threshold with precision >= 0.6
    cal = calibration_of_results(res, q, target_precision=0.6, min_accepted=1, **kw)
    assert cal["min_distinctiveness"] == 0.7 and cal["precision"] == pytest.approx(2 / 3)
    assert (cal["accepted"], cal["queries"], cal["passing_cost"]) == (3, 4, 3)
    assert cal["accepted_share"] == 0.75 and cal["base_precision"] == 0.75
    strict = calibration_of_results(res, q, target_precision=1.0, min_accepted=1, **kw)
    assert strict["min_distinctiveness"] == 0.9 and strict["accepted"] == 1
    loose = calibration_of_results(res, q, accept_threshold=1.0, target_precision=1.0, **kw)
    assert loose["passing_cost"] == 4 and loose["accepted"] == 0  # min_accepted 10 not reached
    # a query without image content is never accepted: it does not pass the cost rule either
    blank = [res[0], SimpleNamespace(**{**vars(res[1]), "has_content": False}), *res[2:]]
    cal = calibration_of_results(blank, q, target_precision=1.0, min_accepted=1, **kw)
    assert (cal["min_distinctiveness"], cal["accepted"], cal["passing_cost"]) == (0.7, 2, 2)
    with pytest.raises(ValueError, match="query_poses"):
        calibration_of_results(res, q[:3], **kw)
    with pytest.raises(ValueError, match="no query has a map keyframe within 2 m"):
        calibration_of_results(res, q + np.array([50.0, 0, 0]), **kw)  # another world
    # poses of the wrong width are refused by name (a (N, 2) array was regrouped into threes)
    from vvloc.localize.calibrate import check_revisits

    with pytest.raises(ValueError, match=r"db_poses: expected shape \(N, 3\), got \(3, 2\)"):
        check_revisits(db[:3], None, np.array([[50.0, 0], [0, 60], [0, 0]]), None)
    with pytest.raises(ValueError, match=r"db_poses: expected shape \(N, 3\), got \(4, 2\)"):
        calibration_of_results(res, q, **{**kw, "db_poses": db[:, :2]})
    with pytest.raises(ValueError, match=r"query_poses: expected shape \(5, 3\), got \(5, 2\)"):
        calibration_of_results(res, q[:, :2], **kw)


def test_the_trainers_calibration_leaves_queries_without_image_content_out():
    from vvloc.localize.calibrate import RerankedSplit, calibration_of

    db = np.array([[0.0, 0], [10, 0], [20, 0]])
    q = np.array([[0.5, 0], [10.5, 0], [20.5, 0], [0.2, 0]])
    split = RerankedSplit(  # right, wrong, right, right at distinctiveness 0.45, 0.4, 0.35, 0.3
        retrieved=np.array([[0, 1], [2, 1], [2, 0], [0, 1]]),
        reranked=np.array([[0, 1], [2, 1], [2, 0], [0, 1]]),
        rerank_cost=np.array([[0.1, 1.0], [0.2, 1.0], [0.3, 1.0], [0.4, 1.0]]),
        query_xy=q,
        db_xy=db,
        query_floors=np.zeros(4, np.int64),
        db_floors=np.zeros(3, np.int64),
        query_content=np.array([True, True, True, True]),
    )
    cal = calibration_of(split, target_precision=1.0, min_accepted=1)
    assert cal["min_distinctiveness"] == pytest.approx(0.45) and cal["accepted"] == 1
    # the wrong one is a blank frame, which the localizer never accepts: left out, every other
    # query is right
    blank = dataclasses.replace(split, query_content=np.array([True, False, True, True]))
    cal = calibration_of(blank, target_precision=1.0, min_accepted=1)
    assert cal["min_distinctiveness"] == pytest.approx(0.3) and cal["accepted"] == 3


def test_calibrate_localizer_refuses_queries_far_from_the_map_before_localizing_them():
    from types import SimpleNamespace

    from vvloc.localize.calibrate import calibrate_localizer

    def never(*args: object, **kwargs: object) -> None:
        pytest.fail("localized the queries before finding none revisits the map")

    db = SimpleNamespace(poses=np.array([[0.0, 0, 0], [10, 0, 0]]), floors=np.array([0, 1]))
    loc = SimpleNamespace(map=db, localize_batch=never, accept_threshold=0.75)
    frames = [SimpleNamespace(pose=np.array([10.5, 0, 0]), floor=0)]  # near a keyframe above
    with pytest.raises(ValueError, match="frames: no query has a map keyframe within 2 m"):
        calibrate_localizer(loc, frames)  # type: ignore[arg-type]


def test_cli_refuses_misleading_inputs_before_any_work(
    tiny_world, map_file, model_dir, tmp_path, tmp_path_factory
):
    exe = [sys.executable, "-m", "vvloc.cli"]
    run = lambda *a: subprocess.run([*exe, *a], capture_output=True, text=True)  # noqa: E731
    ck = ["--checkpoint", str(model_dir), "--dataset", str(tiny_world)]
    # the map session among the queries, or a query session twice
    r = run("eval", *ck, "--database", "s0", "--queries", "s0", "--out", str(tmp_path / "e"))
    assert r.returncode == 2 and "the map session 's0' is among the queries" in r.stderr
    r = run("eval", *ck, "--database", "s0", "--queries", "s1,s1", "--out", str(tmp_path / "e"))
    assert r.returncode == 2 and "named more than once" in r.stderr
    loc = ["localize", "--checkpoint", str(model_dir), "--dataset", str(tiny_world)]
    r = run(*loc, "--map", str(map_file), "--session", "s9", "--out", str(tmp_path / "e"))
    assert r.returncode == 2 and "--session: no session 's9' in" in r.stderr, r.stderr
    r = run(*loc, "--map", str(tmp_path / "no.h5"), "--session", "s1", "--out", str(tmp_path / "e"))
    assert r.returncode == 2 and "--map: map file not found" in r.stderr, r.stderr
    r = run("eval", *ck, "--database", "s0", "--queries", "s1,s9", "--out", str(tmp_path / "e"))
    assert r.returncode == 2 and "--queries: no session 's9' in" in r.stderr, r.stderr
    r = run("eval", *ck, "--database", "s9", "--queries", "s1", "--out", str(tmp_path / "e"))
    assert r.returncode == 2 and "--database: no session 's9' in" in r.stderr, r.stderr
    # eval names its options as the command line spells them, not run_evaluation's arguments
    r = run("eval", *ck, "--loop_radius", "nan", "--out", str(tmp_path / "e"))
    assert (
        r.returncode == 2
        and "eval: error: --loop_radius: expected a descriptor distance" in r.stderr
    )
    assert not (tmp_path / "e").exists()
    # an --out that is a file is refused before localizing anything
    blocker = tmp_path / "file.txt"
    blocker.write_text("keep")
    r = run("localize", "--map", str(map_file), *ck, "--session", "s1", "--out", str(blocker))
    assert r.returncode == 2 and "--out:" in r.stderr and "is a file" in r.stderr
    assert blocker.read_text() == "keep"
    r = run("eval", *ck, "--database", "s0", "--queries", "s1", "--out", str(blocker))
    assert r.returncode == 2 and "--out:" in r.stderr and "is a file" in r.stderr
    assert blocker.read_text() == "keep"
    # ... and so is one below a file (localize said so after localizing every frame)
    below = blocker / "sub"
    r = run("localize", "--map", str(map_file), *ck, "--session", "s1", "--out", str(below))
    assert r.returncode == 2 and f"--out: {below} lies below {blocker}" in r.stderr, r.stderr
    # outputs inside the dataset would break it (a report folder among its sessions)
    inside = tiny_world / "sessions" / "s9"
    for cmd in (["eval", *ck, "--database", "s0", "--queries", "s1"],
                ["localize", "--map", str(map_file), *ck, "--session", "s1"]):  # fmt: skip
        r = run(*cmd, "--out", str(inside))
        assert r.returncode == 2 and "lies inside the dataset" in r.stderr, r.stderr
    assert not inside.exists()
    # an empty --out (an unset shell variable) is the working directory: the outputs went
    # there, among whatever was there
    here = tmp_path_factory.mktemp("here")  # not in tmp_path, whose listing is checked below
    for cmd in (["eval", *ck, "--database", "s0", "--queries", "s1"],
                ["localize", "--map", str(map_file), *ck, "--session", "s1"],
                ["loops", "--map", str(map_file), "--checkpoint", str(model_dir)],
                ["demo", "--checkpoint", str(model_dir)]):  # fmt: skip
        for out in ("", ".", str(here.parent)):
            r = subprocess.run([*exe, *cmd, "--out", out], capture_output=True, text=True,
                               cwd=here)  # fmt: skip
            assert r.returncode == 2, (cmd[0], out, r.stderr)
            assert "is the working directory or a folder above it" in r.stderr, r.stderr
    assert not list(here.iterdir())
    # the demo checks its checkpoint and its --out before rendering minutes of world
    r = run("demo", "--out", str(tmp_path / "d"), "--checkpoint", str(tmp_path / "nothing"))
    assert r.returncode == 2 and "--checkpoint:" in r.stderr and "rendering" not in r.stdout
    # every command names the option a bad checkpoint came from, not the library's argument
    r = run("eval", "--checkpoint", str(tmp_path / "nothing"), "--dataset", str(tiny_world),
            "--database", "s0", "--queries", "s1", "--out", str(tmp_path / "e"))  # fmt: skip
    assert r.returncode == 2 and f"--checkpoint: {tmp_path / 'nothing'} does not exist" in r.stderr
    r = run("loops", "--map", str(map_file), "--checkpoint", str(tiny_world), "--out",
            str(tmp_path / "l"))  # fmt: skip
    assert r.returncode == 2 and "--checkpoint: " in r.stderr
    assert "config.json not found" in r.stderr
    # a NaN --radius passed typer's max=2 (NaN > 2 is false)
    r = run("loops", "--map", str(map_file), "--checkpoint", str(model_dir), "--radius", "nan",
            "--out", str(tmp_path / "l"))  # fmt: skip
    assert (
        r.returncode == 2 and "loops: error: --radius: expected a descriptor distance" in r.stderr
    )
    assert not (tmp_path / "l").exists() and not (tmp_path / "e").exists()
    r = run("demo", "--out", str(blocker))
    assert r.returncode == 2 and "--out:" in r.stderr and "rendering" not in r.stdout
    # ... and never replaces a dataset it did not render
    mine = tmp_path / "d2"
    shutil.copytree(tiny_world, mine / "data")
    rig = json.loads((mine / "data" / "rig.json").read_text())
    rig["meta"] = {"source": "a user's own drives"}  # not a parking world vvloc sim rendered
    (mine / "data" / "rig.json").write_text(json.dumps(rig))
    r = run("demo", "--out", str(mine), "--frames", "10")
    assert r.returncode == 2 and "holds a dataset the demo did not render" in r.stderr
    assert sorted(p.name for p in (mine / "data" / "sessions").iterdir()) == sorted(
        p.name for p in (tiny_world / "sessions").iterdir()
    )
    # a parking world vvloc sim rendered, with sessions beyond the demo's: not the demo's
    rig["meta"] = {"generator": "vvloc.sim", "scene": "parking", "seed": 5}
    (mine / "data" / "rig.json").write_text(json.dumps(rig))
    shutil.copytree(mine / "data" / "sessions" / "s0", mine / "data" / "sessions" / "s7")
    r = run("demo", "--out", str(mine), "--frames", "10")
    assert r.returncode == 2 and "holds a dataset the demo did not render" in r.stderr
    assert (mine / "data" / "sessions" / "s7").is_dir()
    # --overwrite replaces a dataset, never another folder
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "todo.txt").write_text("mine")
    r = run("sim", "--out", str(notes), "--sessions", "1", "--frames", "2", "--overwrite")
    assert r.returncode == 2 and "not a vvloc dataset" in r.stderr
    assert (notes / "todo.txt").read_text() == "mine"
    r = run("sim", "--out", str(blocker), "--sessions", "1", "--frames", "2", "--overwrite")
    assert r.returncode == 2 and "is a file" in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "d2",
        "file.txt",
        "notes",
    ]  # no .partial-*
    # malformed YAML and a --resume with nothing to resume: one line, exit 2
    bad = tmp_path / "bad.yaml"
    bad.write_text("dataset: [unclosed\n")
    r = run("train", "--config", str(bad), "--out", str(tmp_path / "t"))
    assert r.returncode == 2 and "not valid YAML" in r.stderr and "Traceback" not in r.stderr
    good = tmp_path / "good.yaml"
    good.write_text(f"dataset: {tiny_world}\nstage1_epochs: 1\nstage2_epochs: 0\n")
    r = run("train", "--config", str(good), "--out", str(tmp_path / "t"), "--resume")
    assert r.returncode == 2 and "no run to resume" in r.stderr
    r = run("train", "--config", str(good), "--out", str(tmp_path / "t"), "--device", "gpu")
    assert r.returncode == 2 and "--device" in r.stderr and not (tmp_path / "t").exists()
    r = run("train", "--config", str(good), "--out", str(blocker))
    assert r.returncode == 2 and "--out:" in r.stderr and "is a file" in r.stderr
    assert blocker.read_text() == "keep"


def test_report_and_localize_folders_never_replace_files_they_did_not_write(tmp_path):
    from vvloc.commands.localize import HEADER, OUTPUTS, _check_localize_folder
    from vvloc.localize.evaluation import check_report_folder

    for check in (check_report_folder, _check_localize_folder):
        check(tmp_path / "new")  # missing or empty: fine
        check(tmp_path)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "report.md").write_text("my analysis")
    (mine / "map.h5").write_text("my map")
    with pytest.raises(FileExistsError, match=r"holds map.h5, report.md, which no earlier vvloc"):
        check_report_folder(mine)
    (mine / "report.json").write_text('{"notes": "mine"}')  # a JSON, not a vvloc report's
    with pytest.raises(FileExistsError, match="which no earlier vvloc eval report wrote"):
        check_report_folder(mine)
    # an earlier report is replaced whole
    (mine / "report.json").write_text('{"meta": {}, "global_localization": {}}')
    check_report_folder(mine)
    # localize never replaces the report's queries.csv, and replaces its own outputs
    (mine / "queries.csv").write_text("# vvloc evaluation per query\n")
    with pytest.raises(
        FileExistsError, match=r"holds queries.csv, which no earlier vvloc localize"
    ):
        _check_localize_folder(mine)
    loc = tmp_path / "loc"
    loc.mkdir()
    for name in OUTPUTS:
        (loc / name).write_text("x")
    (loc / "queries.csv").write_text(HEADER + "\n")
    _check_localize_folder(loc)


def test_map_build_replaces_only_a_map_and_never_writes_into_the_dataset(tmp_path, monkeypatch):
    from pathlib import Path

    from vvloc.commands._util import check_out_folder
    from vvloc.commands.mapping import check_map_out
    from vvloc.localize import MapDatabase

    data = tmp_path / "data"
    (data / "sessions" / "s0").mkdir(parents=True)
    (data / "rig.json").write_text("{}")
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    n = 3
    old = MapDatabase.from_arrays(
        poses=np.zeros((n, 3)), timestamps=np.arange(n) * 1.0, sessions="s0",
        global_descriptors=np.eye(n, 8), local_descriptors=np.ones((n, 4, 2)),
        model_config={"a": 1}, grid_size=0.6,
    ).save(tmp_path / "old.h5")  # fmt: skip
    check_map_out(tmp_path / "new.h5", overwrite=False, dataset=data)
    check_map_out(old, overwrite=True, dataset=data)  # an earlier map: replaced with --overwrite
    with pytest.raises(FileExistsError, match=r"^--out: .*old.h5 exists; pass --overwrite"):
        check_map_out(old, overwrite=False, dataset=data)
    # a user's file, or the dataset's own files, were replaced by --overwrite
    for target in (notes, data / "rig.json"):
        with pytest.raises((FileExistsError, ValueError), match=r"^--out: "):
            check_map_out(target, overwrite=True, dataset=data)
    with pytest.raises(FileExistsError, match="is not a vvloc map; --overwrite replaces only"):
        check_map_out(notes, overwrite=True, dataset=data)
    with pytest.raises(ValueError, match="lies inside the dataset"):
        check_map_out(data / "map.h5", overwrite=False, dataset=data)
    with pytest.raises(IsADirectoryError, match=r"^--out: "):
        check_map_out(tmp_path, overwrite=True, dataset=data)
    with pytest.raises(ValueError, match=r"^--out: expected the path of a map file"):
        check_map_out(Path(""), overwrite=False, dataset=data)
    check_map_out(tmp_path / "nowhere" / "m.h5", overwrite=False, dataset=data)  # made later
    assert not (tmp_path / "nowhere").exists()
    with pytest.raises(NotADirectoryError, match=r"^--out: .*notes.txt is a file, not a folder"):
        check_map_out(notes / "sub" / "m.h5", overwrite=False, dataset=data)
    with pytest.raises(ValueError, match=r"^--out: /dev/null is not a regular file"):
        check_map_out(Path("/dev/null"), overwrite=True, dataset=data)
    assert notes.read_text() == "mine" and (data / "rig.json").read_text() == "{}"
    # a folder that cannot be written is said before any work (root ignores mode bits, so the
    # check is faked; a read-only mount was found after every frame was localized)
    monkeypatch.setattr("os.access", lambda p, mode: False)
    with pytest.raises(PermissionError, match=r"^--out: the folder .* is not writable"):
        check_map_out(tmp_path / "m.h5", overwrite=False, dataset=data)
    with pytest.raises(PermissionError, match=r"^--out: .*, the folder .*loc is to be made in, is"):
        check_out_folder(tmp_path / "loc")


def test_eval_localize_and_demo_refuse_a_folder_of_files_they_did_not_write(
    tiny_world, map_file, model_dir, tmp_path
):
    from vvloc.localize.evaluation import run_evaluation

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "report.md").write_text("my analysis")
    (mine / "queries.csv").write_text("# vvloc evaluation per query\n")
    before = {p.name: p.read_bytes() for p in mine.iterdir()}
    with pytest.raises(FileExistsError, match="no earlier vvloc eval report"):
        run_evaluation(model_dir, tiny_world, "s0", ["s1"], mine, every=5)
    exe = [sys.executable, "-m", "vvloc.cli"]
    run = lambda *a: subprocess.run([*exe, *a], capture_output=True, text=True)  # noqa: E731
    r = run("localize", "--map", str(map_file), "--dataset", str(tiny_world), "--session", "s2",
            "--checkpoint", str(model_dir), "--out", str(mine))  # fmt: skip
    assert r.returncode == 2 and "which no earlier vvloc localize wrote" in r.stderr, r.stderr
    r = run("demo", "--out", str(mine), "--frames", "10")
    assert r.returncode == 2 and "no earlier vvloc eval report" in r.stderr, r.stderr
    assert f"--out: {mine} holds" in r.stderr  # the option, as the command line spells it
    assert "rendering" not in r.stdout and not (mine / "data").exists()
    r = run("eval", "--checkpoint", str(model_dir), "--dataset", str(tiny_world),
            "--out", str(mine))  # fmt: skip
    assert r.returncode == 2 and f"--out: {mine} holds queries.csv, report.md" in r.stderr, r.stderr
    assert {p.name: p.read_bytes() for p in mine.iterdir()} == before


def test_cli_version_and_quiet_logs(tmp_path):
    exe = [sys.executable, "-m", "vvloc.cli"]
    r = subprocess.run([*exe, "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.startswith("vvloc ")
    import io
    import os
    import warnings

    from tqdm import tqdm

    from vvloc.cli import _quiet_when_logged

    before = warnings.formatwarning, warnings.showwarning
    try:
        _quiet_when_logged()  # pytest's stderr is not a terminal
        assert os.environ.get("TQDM_MININTERVAL") == "30"
        assert warnings.formatwarning("x", UserWarning, "f.py", 1) == "vvloc: warning: x\n"
        # a warning while a progress bar is drawn starts a line of its own (it was glued to
        # the bar's: "map:   0%|          | 0/40 [...]vvloc: warning: ...")
        log = io.StringIO()
        bar = tqdm(total=4, desc="map", file=log, mininterval=0)
        bar.update(1)
        warnings.showwarning(UserWarning("2 frames blank"), UserWarning, "f.py", 1, file=log)
        bar.close()
        lines = log.getvalue().split("\n")
        assert "vvloc: warning: 2 frames blank" in lines, lines
        quiet = io.StringIO()  # no bar: the warning alone, as before
        warnings.showwarning(UserWarning("y"), UserWarning, "f.py", 1, file=quiet)
        assert quiet.getvalue() == "vvloc: warning: y\n"
    finally:
        warnings.formatwarning, warnings.showwarning = before
        os.environ.pop("TQDM_MININTERVAL", None)


def test_trained_on_reads_the_training_record(tmp_path, monkeypatch):
    from vvloc.localize.evaluation import trained_on

    monkeypatch.chdir(tmp_path)
    record = {
        "runs": [
            {"config": {"dataset": "data/lot", "train_sessions": ["s0", "s1", "s5"]}},
            {
                "config": {
                    "dataset": "data/lot",
                    "train_sessions": ["s0"],
                    "extra_datasets": [{"dataset": "./data/garage"}],  # every session
                }
            },
        ]
    }
    assert trained_on(record, "data/lot", ["s3", "s5", "s1"]) == ["s5", "s1"]
    assert trained_on(record, tmp_path / "data" / "lot" / "", ["s2"]) == []
    assert trained_on(record, "data/garage", ["s7", "s8"]) == ["s7", "s8"]
    assert trained_on(record, "data/lot-test", ["s1"]) == []  # another dataset
    assert trained_on({}, "data/lot", ["s1"]) == []  # no record (an earlier vvloc's weights)
    assert trained_on({"runs": [{"recorded": False}]}, "data/lot", ["s1"]) == []
    # a run records where it ran: its relative dataset is found from any working directory
    # (the record's cwd), as well as from the one it names relative to
    ran = {"runs": [{"cwd": str(tmp_path), "config": {"dataset": "lot", "train_sessions": ["s1"]}}]}
    assert trained_on(ran, tmp_path / "lot", ["s1", "s2"]) == ["s1"]
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert trained_on(ran, tmp_path / "lot", ["s1", "s2"]) == ["s1"]
    assert trained_on(ran, "lot", ["s1"]) == ["s1"]  # elsewhere/lot, as the config's text reads
    assert trained_on(ran, tmp_path / "other", ["s1"]) == []


def test_trained_on_knows_a_copy_or_a_conversion_of_a_trained_session(tmp_path):
    """A trained session in another folder: a copy (found by its frames, the run's
    session_digests) or a `vvloc convert` output that kept fewer frames (found by the folder it
    was converted from). Both escaped the check, which compared folders alone."""
    from vvloc.data import Camera, DatasetWriter, convert_dataset
    from vvloc.localize.evaluation import trained_on
    from vvloc.provenance import rendered_plan, session_digest

    cam = Camera("front", 8, 6, np.array([[4.0, 0, 3.5], [0, 4, 2.5], [0, 0, 1]]), FORWARD)
    lot = tmp_path / "lot"
    with DatasetWriter(lot, [cam]) as w:
        for name in ("s0", "s1"):
            s = w.add_session(name)
            for k in range(4):
                s.add(k, (float(k), float(name[1:]), 0.0), np.zeros((1, 3, 6, 8), np.uint8))
    s1 = open_dataset(lot).session("s1")
    run = {"config": {"dataset": str(lot), "train_sessions": ["s1"]}}
    recorded = {**run, "session_digests": [session_digest(s1.timestamps, s1.poses, s1.floors)]}
    copy = tmp_path / "copy"
    shutil.copytree(lot, copy)
    assert trained_on({"runs": [run]}, copy, ["s0", "s1"]) == []  # a record of before 2026-12-06
    assert trained_on({"runs": [recorded]}, copy, ["s0", "s1"]) == ["s1"]
    thinned = convert_dataset(copy, tmp_path / "thinned", every=2, progress=False)
    assert trained_on({"runs": [run]}, thinned, ["s0", "s1"]) == []  # converted from the copy
    assert trained_on({"runs": [recorded]}, thinned, ["s0", "s1"]) == ["s1"]  # the copy's frames
    again = convert_dataset(lot, tmp_path / "once", every=2, progress=False)
    twice = convert_dataset(again, tmp_path / "twice", image_size=(4, 3), progress=False)
    assert trained_on({"runs": [run]}, again, ["s0", "s1"]) == ["s1"]
    assert trained_on({"runs": [run]}, twice, ["s0", "s1"]) == ["s1"]
    # trained on a conversion: its source and a sibling conversion hold the same drives
    on_conversion = {"config": {"dataset": str(again), "train_sessions": ["s1"]}}
    sibling = convert_dataset(lot, tmp_path / "sibling", every=3, progress=False)
    assert trained_on({"runs": [on_conversion]}, lot, ["s0", "s1"]) == ["s1"]
    assert trained_on({"runs": [on_conversion]}, sibling, ["s0", "s1"]) == ["s1"]
    assert trained_on({"runs": [on_conversion]}, copy, ["s0", "s1"]) == []  # no lineage shared
    # a run on a conversion of some sessions, without train_sessions, trained those alone:
    # another conversion of the same source (the test dates of one raw folder) is held out
    train_part = convert_dataset(lot, tmp_path / "train-part", sessions=["s1"], progress=False)
    test_part = convert_dataset(lot, tmp_path / "test-part", sessions=["s0"], progress=False)
    on_part = {"config": {"dataset": str(train_part)}}
    assert trained_on({"runs": [on_part]}, test_part, ["s0"]) == []
    assert trained_on({"runs": [on_part]}, lot, ["s0", "s1"]) == ["s1"]
    # a rendered session's digest holds its plan: the same drive under another light differs
    for folder, lighting in ((lot, "day"), (copy, "day"), (tmp_path / "relit", "night")):
        if not folder.exists():
            shutil.copytree(lot, folder)
        plan = json.dumps({"lighting": lighting, "seed": 7})
        (folder / "sessions" / "s1" / "session.json").write_text(plan)
    planned = {
        **run,
        "session_digests": [
            session_digest(s1.timestamps, s1.poses, s1.floors, {"lighting": "day", "seed": 7})
        ],
    }
    assert rendered_plan(lot, "s1") == {"lighting": "day", "seed": 7}
    assert trained_on({"runs": [planned]}, copy, ["s1"]) == ["s1"]
    assert trained_on({"runs": [planned]}, tmp_path / "relit", ["s1"]) == []


def _fake_render(root, sessions, lighting=None, **world):
    """rig.json meta and session.json files as ``vvloc sim`` writes them, without images."""
    from dataclasses import asdict

    from vvloc.sim.simulate import session_plan

    meta = {"generator": "vvloc.sim", "scene": "parking", "seed": 0} | world
    root.mkdir(parents=True)
    (root / "rig.json").write_text(json.dumps({"cameras": [], "meta": meta}))
    for spec in session_plan(meta["scene"], sessions, meta["seed"], lighting):
        (root / "sessions" / spec.name).mkdir(parents=True)
        (root / "sessions" / spec.name / "session.json").write_text(json.dumps(asdict(spec)))


def test_trained_on_knows_a_trained_session_rendered_again_elsewhere(tmp_path, monkeypatch):
    from vvloc.localize.evaluation import trained_on

    monkeypatch.chdir(tmp_path)
    sim = {"scene": "parking", "sessions": 20, "frames": 300, "seed": 0}
    garage = {"scene": "garage", "floors": 2, "sessions": 6, "frames": 300, "seed": 0}
    record = {
        "runs": [
            {
                "config": {
                    "dataset": "data/lot",
                    "sim": sim,
                    "train_sessions": ["s0", "s1", "s2", "s5"],
                    "extra_datasets": [{"dataset": "data/garage", "sim": garage}],
                }
            }
        ]
    }
    # the README's `vvloc sim --sessions 3` into another folder: the same drives of one world
    _fake_render(tmp_path / "mine", 6)
    assert trained_on(record, "mine", ["s1", "s3", "s4", "s5"]) == ["s1", "s5"]
    # another world seed, another scene, tilted queries, other lighting: not the same sessions
    _fake_render(tmp_path / "seed1", 3, seed=1)
    _fake_render(tmp_path / "pillars", 3, scene="garage", floors=2, floor_marking="pillars")
    _fake_render(tmp_path / "tilted", 3, max_roll=5.0)
    _fake_render(tmp_path / "day", 3, lighting=["day"])
    for other in ("seed1", "pillars", "tilted", "day"):
        assert trained_on(record, other, ["s1", "s2"]) == [], other
    # the garage source trained every session of its world (no train_sessions)
    _fake_render(tmp_path / "walls", 3, scene="garage", floors=2)
    assert trained_on(record, "walls", ["s1", "s2"]) == ["s1", "s2"]
    # a dataset that vvloc sim did not render, or without session.json, is judged by path only
    (tmp_path / "mine" / "sessions" / "s1" / "session.json").unlink()
    assert trained_on(record, "mine", ["s1", "s5"]) == ["s5"]
    assert trained_on(record, tmp_path / "nowhere", ["s1"]) == []


def test_a_failed_evaluation_leaves_no_folder_it_made(tiny_world, model_dir, tmp_path, monkeypatch):
    import vvloc.localize.evaluation as evaluation

    def broken(*args: object, **kwargs: object) -> None:
        raise ValueError("a frame could not be read")

    monkeypatch.setattr(evaluation.Localizer, "localize_batch", broken)
    out = tmp_path / "new" / "eval"
    with pytest.raises(ValueError, match="could not be read"):
        evaluation.run_evaluation(model_dir, tiny_world, "s0", ["s1"], out, progress=False)
    assert not (tmp_path / "new").exists()  # both folders it made, left empty, are gone
    mine = tmp_path / "mine"
    mine.mkdir()
    with pytest.raises(ValueError, match="could not be read"):
        evaluation.run_evaluation(model_dir, tiny_world, "s0", ["s1"], mine, progress=False)
    assert mine.is_dir() and not any(mine.iterdir())  # the user's folder stays


def test_cli_localize_names_the_session_of_another_rig(tiny_world, model_dir, map_file, tmp_path):
    exe = [sys.executable, "-m", "vvloc.cli"]
    run = lambda *a: subprocess.run([*exe, *a], capture_output=True, text=True)  # noqa: E731
    three = ",".join(c.name for c in open_dataset(tiny_world).cameras[:3])
    r = run("convert", "--src", str(tiny_world), "--out", str(tmp_path / "t3"), "--cameras",
            three, "--sessions", "s1")  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = run("localize", "--map", str(map_file), "--checkpoint", str(model_dir), "--dataset",
            str(tmp_path / "t3"), "--session", "s1", "--out", str(tmp_path / "l"))  # fmt: skip
    assert r.returncode == 0, r.stderr
    # it named the library's argument, frames[0]
    said = f"vvloc: warning: --session s1 of --dataset {tmp_path / 't3'}: from another rig"
    assert said in r.stderr and r.stderr.count("from another rig") == 1, r.stderr
    assert "found themselves" not in r.stderr  # s1 is no map session
    # the map's own session: each frame finds itself at cost ~0 (vvloc eval refuses it)
    r = run("localize", "--map", str(map_file), "--checkpoint", str(model_dir), "--dataset",
            str(tiny_world), "--session", "s0", "--out", str(tmp_path / "self"))  # fmt: skip
    assert r.returncode == 0, r.stderr
    n = len(open_dataset(tiny_world).session("s0"))
    said = f"vvloc: warning: --session s0: {n} of {n} frames found themselves in the map"
    assert said in r.stderr, r.stderr
    # a session of the map's name and times in another world (here: another rig's copy,
    # whose frames are not the map's) is a fair test, not a warning
    r = run("convert", "--src", str(tiny_world), "--out", str(tmp_path / "t3s0"), "--cameras",
            three, "--sessions", "s0")  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = run("localize", "--map", str(map_file), "--checkpoint", str(model_dir), "--dataset",
            str(tmp_path / "t3s0"), "--session", "s0", "--out", str(tmp_path / "l3"))  # fmt: skip
    assert r.returncode == 0 and "found themselves" not in r.stderr, r.stderr


def test_cli_names_more_options_before_any_work(tiny_world, model_dir, map_file, tmp_path):
    exe = [sys.executable, "-m", "vvloc.cli"]
    run = lambda *a: subprocess.run([*exe, *a], capture_output=True, text=True)  # noqa: E731
    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    empty = world / "sessions" / "sE"
    shutil.copytree(world / "sessions" / "s0", empty)
    poses = empty / "poses.csv"
    poses.write_text(poses.read_text().splitlines()[0] + "\n")  # the header alone: no frames
    build = ["map", "build", "--checkpoint", str(model_dir), "--out", str(tmp_path / "m.h5")]
    # an empty session was left out of the map without a word
    r = run(*build, "--dataset", str(world), "--sessions", "s0,sE")
    assert r.returncode == 2 and "--sessions: session 'sE'" in r.stderr and "no frames" in r.stderr
    r = run(*build, "--dataset", str(world), "--sessions", "")
    assert r.returncode == 2 and "--sessions: expected at least one" in r.stderr, r.stderr
    r = run(*build, "--dataset", str(tmp_path / "nope"), "--sessions", "s0")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--dataset: " in r.stderr, r.stderr
    assert not (tmp_path / "m.h5").exists()
    # a dangling symbolic link as --out was found after localizing every frame
    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "nowhere")
    r = run("localize", "--map", str(tmp_path / "m.h5"), "--checkpoint", str(model_dir),
            "--dataset", str(world), "--session", "s1", "--out", str(dangling))  # fmt: skip
    assert r.returncode == 2 and "--out: " in r.stderr and "symbolic link" in r.stderr, r.stderr
    # 100 000 pixels square: killed for memory without a word
    r = run("convert", "--src", str(world), "--out", str(tmp_path / "c"), "--width", "100000",
            "--height", "100000")  # fmt: skip
    assert r.returncode == 2 and "--width/--height: expected sides of at most 16384" in r.stderr
    assert not (tmp_path / "c").exists()
    r = run("demo", "--out", str(tmp_path / "d"), "--seed", "-1")
    assert r.returncode == 2 and "rendering" not in r.stdout and "--seed" in r.stderr
    r = run("localize", "--map", str(tmp_path / "m.h5"), "--checkpoint", str(model_dir),
            "--dataset", str(world), "--session", "s1", "--out", str(tmp_path / "l"),
            "--threads", "3000000000")  # fmt: skip
    assert r.returncode == 2 and "--threads" in r.stderr and "Overflow" not in r.stderr
    # ints past int64 are named by the option they came from, not the library's argument
    huge = "100000000000000000000"
    r = run("sim", "--out", str(tmp_path / "s"), "--seed", huge)
    assert r.returncode == 2 and "error: --seed: expected an int <=" in r.stderr, r.stderr
    assert not (tmp_path / "s").exists()
    r = run("loops", "--map", str(map_file), "--checkpoint", str(model_dir), "--out",
            str(tmp_path / "l"), "--window", huge)  # fmt: skip
    assert r.returncode == 2 and "error: --window: expected an int <=" in r.stderr, r.stderr
    # a sequence window longer than any session confirms nothing: said, not a silent 0
    r = run("loops", "--map", str(map_file), "--checkpoint", str(model_dir), "--out",
            str(tmp_path / "l"), "--sequence", "1000")  # fmt: skip
    assert r.returncode == 0 and "half-window 1000 needs 2001 keyframes" in r.stderr, r.stderr
    # "," names no session: every session was converted
    r = run("convert", "--src", str(world), "--out", str(tmp_path / "c"), "--sessions", ",")
    assert r.returncode == 2 and "--sessions: expected at least one session name" in r.stderr
    assert not (tmp_path / "c").exists()
    # --threshold 0 accepts nothing: said before the map is built, not after every query
    r = run("calibrate", "--checkpoint", str(model_dir), "--dataset", str(world), "--database",
            "s0", "--queries", "s1", "--threshold", "0")  # fmt: skip
    assert r.returncode == 2 and "--threshold: 0 accepts no answer" in r.stderr, r.stderr
    assert not (model_dir / "calibration.json").exists()
    # a symbolic link that loops: Path.resolve's RuntimeError exited 1, and sim rendered first
    loop = tmp_path / "loop"
    loop.symlink_to(tmp_path / "loop2")
    (tmp_path / "loop2").symlink_to(loop)
    said = "loop is a symbolic link that loops"
    r = run("eval", "--checkpoint", str(model_dir), "--dataset", str(loop), "--database", "s0",
            "--queries", "s1", "--out", str(tmp_path / "e"))  # fmt: skip
    assert r.returncode == 2 and f"--dataset: {tmp_path}/{said}" in r.stderr, r.stderr
    r = run("sim", "--out", str(loop), "--sessions", "1", "--frames", "2")
    assert r.returncode == 2 and said in r.stderr and "frame/s" not in r.stderr, r.stderr
    r = run("map", "build", "--checkpoint", str(model_dir), "--dataset", str(world),
            "--sessions", "s0", "--out", str(loop))  # fmt: skip
    assert r.returncode == 2 and f"--out: {tmp_path}/{said}" in r.stderr, r.stderr
