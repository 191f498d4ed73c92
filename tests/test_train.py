"""The trainer: losses fall on a tiny set, checkpoints and resume, config validation."""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import math
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from PIL import Image

import vvloc.train
import vvloc.train.data
import vvloc.train.steps
import vvloc.train.trainer
from data_helpers import blank_frames
from vvloc.checkpoints import resolve_checkpoint
from vvloc.evaluate import to_jsonable
from vvloc.losses import random_translation_bias
from vvloc.nets import VVLocNet
from vvloc.train import (
    TrainConfig,
    Trainer,
    TripletFrames,
    near_seed,
    train,
    training_losses,
    validation_query_count,
    validation_recall,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _config(root, **kw) -> TrainConfig:
    base = dict(
        dataset=str(root),
        model="small",
        stage1_epochs=1,
        stage2_epochs=1,
        steps_per_epoch=2,
        batch_size=2,
        num_workers=0,
        seed=3,
    )
    base.update(kw)
    return TrainConfig.from_dict(base)


@pytest.mark.parametrize("seed", [0, 1, 7])
def test_the_near_loss_draws_its_offsets_from_a_stream_of_its_own(seed):
    # until 2026-12-05 its seed equalled the translation-bias loss's at seed 0, so every near
    # offset pointed along the bias offset of its pair
    for step in (0, 1, 30, 999):
        bias = random_translation_bias(64, (1.0, 3.0), seed * 1_000_003 + step)
        near = random_translation_bias(64, (0.25, 1.0), near_seed(seed, step))
        cos = (bias * near).sum(1) / (bias.norm(dim=1) * near.norm(dim=1))
        assert (cos.abs() > 0.9999).sum() < 8, (seed, step)  # all 64 under the old seed 0
        assert cos.mean().abs() < 0.4, (seed, step)  # 64 independent directions: |mean| ~ 0.09
    old = random_translation_bias(64, (0.25, 1.0), 0 * 1_000_033 + 30)
    bias = random_translation_bias(64, (1.0, 3.0), 0 * 1_000_003 + 30)
    assert torch.allclose(
        old / old.norm(dim=1, keepdim=True), bias / bias.norm(dim=1, keepdim=True)
    )
    seeds = {near_seed(seed, step) for step in range(2000)}
    assert len(seeds) == 2000 and all(0 <= s < 2**63 for s in seeds)
    assert near_seed(seed, 5) == near_seed(seed, 5) != near_seed(seed + 1, 5)


def test_the_near_losses_are_seeded_by_near_seed(monkeypatch, tiny_world):
    seen = []
    monkeypatch.setattr(
        vvloc.train.steps, "near_translation_loss", lambda *a, **kw: seen.append(kw["seed"])
    )
    cfg = _config(tiny_world, tbias_near_weight=1.0, seed=5)
    vvloc.train.near_losses(None, None, None, None, None, cfg, 17)
    assert seen == [near_seed(5, 17)]


@pytest.mark.parametrize(("rerank_weight", "near_weight"), [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)])
def test_a_few_steps_on_fixed_triplets_lower_every_loss(tiny_world, rerank_weight, near_weight):
    cfg = _config(tiny_world, rerank_weight=rerank_weight, tbias_near_weight=near_weight)
    tr = Trainer(cfg, "unused")
    triplets = tr.sampler.sample_random(2)
    batch = torch.utils.data.default_collate(
        [TripletFrames(tr.sampler, triplets)[k] for k in (0, 1)]
    )
    opt = torch.optim.Adam(tr.model.parameters(), lr=1e-3)
    first = last = None
    for _step in range(25):
        loss, parts, _ = training_losses(tr.model, batch, cfg, stage=2, step=0, device=tr.device)
        opt.zero_grad()
        loss.backward()
        opt.step()
        first = first or parts
        last = parts
    assert first is not None and last is not None
    if rerank_weight == 0:  # off: not built, logged as 0
        assert first.rerank == last.rerank == 0.0
    else:  # on: the untrained interactor does not yet rank the positive first by the margin
        assert first.rerank > 0
    if near_weight == 0:
        assert first.tbias_near == last.tbias_near == 0.0
    else:  # the untrained matcher does not yet rank the truth first by the offset's margin
        assert first.tbias_near > 0
    for name in ("triplet", "hinge", "yaw", "tbias", "rerank", "tbias_near"):
        a, b = getattr(first, name), getattr(last, name)
        if a > 0:
            assert b < a, f"{name} did not fall: {a} -> {b}"
    assert last.total < 0.5 * first.total


def test_fit_writes_checkpoint_log_and_resume_continues_from_the_same_step(tiny_world, tmp_path):
    cfg = _config(tiny_world)
    out = tmp_path / "run"
    t1 = train(cfg, out, progress=False)
    assert t1.epoch == 2 and t1.step == 4
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in log] == [1, 2]
    assert all(np.isfinite(r["loss_total"]) for r in log)
    assert (out / "checkpoint" / "model.safetensors").is_file()
    with pytest.raises(FileExistsError, match="--resume"):
        train(cfg, out, progress=False)
    # Resume a run with more epochs from the same state: it continues at step 4.
    cfg3 = _config(tiny_world, stage1_epochs=2)
    (out / "trainer_state.pt").rename(out / "state_copy.pt")
    (out / "state_copy.pt").rename(out / "trainer_state.pt")
    tr = Trainer(cfg, out)
    assert tr.resume()
    assert (tr.epoch, tr.step) == (2, 4)
    for a, b in zip(tr.model.state_dict().values(), t1.model.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="another config"):
        Trainer(cfg3, out).resume()
    # more joint epochs extend the run
    longer = Trainer(_config(tiny_world, stage2_epochs=2), out)
    assert longer.resume() and longer.epoch == 2
    longer.fit(progress=False)
    assert longer.epoch == 3
    # the run's checkpoint folder deleted: said as such ("directory: ... does not exist")
    kept = tmp_path / "kept"
    (out / "checkpoint").rename(kept)
    with pytest.raises(FileNotFoundError, match=r"trainer_state.pt is here but not its checkpoint"):
        Trainer(_config(tiny_world, stage2_epochs=2), out).resume()
    kept.rename(out / "checkpoint")
    # a truncated or foreign trainer state is refused naming the file (torch said "Ran out of
    # input" or "pickle data was truncated" alone, neither a ValueError nor an OSError)
    state = (out / "trainer_state.pt").read_bytes()
    for damaged, why in (
        (b"", r"the file ends early \(truncated\?\)"),
        (state[: len(state) // 2], "PytorchStreamReader failed reading zip archive"),
        (b"garbage" * 10, r"not a pickle torch wrote \(Unsupported operand"),
        (b"\x80\x02}q\x00(X", r"the file ends early"),  # a cut old-style pickle: struct.error
    ):
        (out / "trainer_state.pt").write_bytes(damaged)
        with pytest.raises(
            ValueError, match=rf"trainer_state.pt: not a readable trainer state \({why}"
        ):
            Trainer(cfg, out).resume()
    torch.save({"weights": 1}, out / "trainer_state.pt")
    with pytest.raises(ValueError, match=r"\(a dict without the run's config\)"):
        Trainer(cfg, out).resume()


def test_resumed_run_equals_uninterrupted_run(tiny_world, tmp_path):
    _assert_resumed_run_equals_uninterrupted(
        _config(tiny_world, stage1_epochs=1, stage2_epochs=1), tmp_path, cut=1
    )


def test_a_run_resumed_inside_its_hard_pool_equals_the_uninterrupted_run(tiny_world, tmp_path):
    # Cut where the next epoch's hard triplets start inside the pool: the position in the pool
    # is part of the resumed state (before it was, models/synth-small's step 1, resumed at epoch
    # 10, took other hard triplets from epoch 11 on than an uninterrupted run).
    cfg = _config(tiny_world, stage1_epochs=3, stage2_epochs=0, steps_per_epoch=3)
    cut_state = _assert_resumed_run_equals_uninterrupted(cfg, tmp_path, cut=2)
    assert cut_state["hard_cursor"] > 0 and len(cut_state["hard"]) > cut_state["hard_cursor"]


class _MakesADirectoryWhenUnpickled:
    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return (os.mkdir, (str(self.path),))


def test_a_trainer_state_is_unpickled_without_running_what_it_names(tmp_path):
    # torch.load(weights_only=False) ran whatever a trainer_state.pt named: a file handed over
    # with a run folder could run code at --resume
    load = vvloc.train.resume.load_trainer_state
    marker = tmp_path / "ran"
    torch.save({"config": {}, "x": _MakesADirectoryWhenUnpickled(marker)}, tmp_path / "evil.pt")
    with pytest.raises(ValueError, match=r"evil.pt: .*names posix\.mkdir, .*could run code"):
        load(tmp_path / "evil.pt")
    assert not marker.exists()
    # what a state holds loads: tensors, numpy arrays and scalars, the generator's state
    rng = np.random.default_rng(3)
    state = {
        "config": {"seed": 3},
        "sampler": {"rng": rng.bit_generator.state, "hard": np.arange(6).reshape(2, 3)},
        "best": {"key": (np.float64(0.5), 0.25)},
        "torch_rng": torch.get_rng_state(),
    }
    torch.save(state, tmp_path / "state.pt")
    back = load(tmp_path / "state.pt")
    assert back["sampler"]["rng"] == rng.bit_generator.state
    assert np.array_equal(back["sampler"]["hard"], state["sampler"]["hard"])
    assert back["best"]["key"] == (0.5, 0.25) and torch.equal(back["torch_rng"], state["torch_rng"])
    # and a state numpy 1 pickled (its arrays' reconstructor lived in numpy.core)
    import zipfile

    with zipfile.ZipFile(tmp_path / "state.pt") as z:
        parts = {i: z.read(i) for i in z.infolist()}
    with zipfile.ZipFile(tmp_path / "numpy1.pt", "w", zipfile.ZIP_STORED) as z:
        for info, data in parts.items():
            if info.filename.endswith("data.pkl"):
                assert b"numpy._core.multiarray" in data
                data = data.replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
            z.writestr(info, data)
    assert np.array_equal(
        load(tmp_path / "numpy1.pt")["sampler"]["hard"], np.arange(6).reshape(2, 3)
    )


def test_a_trainer_state_saved_before_the_pool_position_was_kept_still_resumes(
    tiny_world, tmp_path
):
    cfg = _config(tiny_world, stage1_epochs=2, stage2_epochs=0, steps_per_epoch=3)
    tr = Trainer(cfg, tmp_path / "run")
    tr.run_epoch(progress=False)
    tr.save()
    path = tmp_path / "run" / "trainer_state.pt"
    state = torch.load(path, weights_only=False)
    sampler = state.pop("sampler")  # the layout written before 2026-12-03
    torch.save({**state, "sampler_rng": sampler["rng"], "sampler_hard": sampler["hard"]}, path)
    old = Trainer(cfg, tmp_path / "run")
    assert old.resume()
    restored = old.sampler.state_dict()
    assert restored["rng"] == sampler["rng"] and restored["hard_cursor"] == 0
    assert np.array_equal(restored["hard"], sampler["hard"])


def test_hard_pool_restarts_train_what_a_resume_did_before_the_pool_position_was_kept(
    tiny_world, tmp_path
):
    # models/synth-small's step 1 was resumed after epoch 10 by a trainer that restarted the hard
    # pool at its first triplet; hard_pool_restarts: [11] trains the same without a break
    cfg = _config(tiny_world, stage1_epochs=3, stage2_epochs=0, steps_per_epoch=3)
    old = Trainer(cfg, tmp_path / "old")
    for _ in range(2):
        old.run_epoch(progress=False)
    old.save()
    path = tmp_path / "old" / "trainer_state.pt"
    state = torch.load(path, weights_only=False)
    sampler = state.pop("sampler")  # the layout of then: no position in the pool
    assert sampler["hard_cursor"] > 0 and len(sampler["hard"]) > sampler["hard_cursor"]
    torch.save({**state, "sampler_rng": sampler["rng"], "sampler_hard": sampler["hard"]}, path)
    resumed = train(cfg, tmp_path / "old", resume=True, progress=False)
    restarted_cfg = dataclasses.replace(cfg, hard_pool_restarts=[3])
    restarted = train(restarted_cfg, tmp_path / "new", progress=False)
    plain = train(cfg, tmp_path / "plain", progress=False)
    for a, b in zip(
        resumed.model.state_dict().values(), restarted.model.state_dict().values(), strict=True
    ):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert np.array_equal(resumed.sampler.hard, restarted.sampler.hard)
    # and it is a different run from the uninterrupted one without the restart
    assert not np.array_equal(plain.sampler.hard, restarted.sampler.hard) or any(
        not torch.equal(a, b)
        for a, b in zip(
            plain.model.state_dict().values(), restarted.model.state_dict().values(), strict=True
        )
    )


@pytest.mark.parametrize("value", [[0], [1.5], [True], 3])
def test_bad_hard_pool_restarts_are_refused(value):
    with pytest.raises(ValueError, match="hard_pool_restarts: expected a list of 1-based epochs"):
        TrainConfig.from_dict({"dataset": "x", "hard_pool_restarts": value})


def test_hard_pool_restarts_in_the_head_stage_are_refused():
    # the head stage has no hard pool: a restart there would silently do nothing
    cfg = {"dataset": "x", "stage1_epochs": 2, "stage2_epochs": 3, "head_epochs": 2}
    TrainConfig.from_dict({**cfg, "hard_pool_restarts": [5]})
    with pytest.raises(ValueError, match=r"names an epoch after stages 1-2, which end at epoch 5"):
        TrainConfig.from_dict({**cfg, "hard_pool_restarts": [6]})


def _assert_resumed_run_equals_uninterrupted(cfg: TrainConfig, tmp_path: Path, cut: int) -> dict:
    """A run stopped after ``cut`` epochs and resumed ends with the uninterrupted run's weights
    and hard pool; returns the sampler's state at the cut."""
    full = train(cfg, tmp_path / "full", progress=False)
    part = Trainer(cfg, tmp_path / "part")
    for _ in range(cut):
        part.run_epoch(progress=False)
    part.save()
    cut_state = part.sampler.state_dict()
    resumed = train(cfg, tmp_path / "part", resume=True, progress=False)
    assert resumed.step == full.step
    for a, b in zip(
        resumed.model.state_dict().values(), full.model.state_dict().values(), strict=True
    ):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    assert np.array_equal(resumed.sampler.hard, full.sampler.hard)
    return cut_state


@pytest.mark.parametrize(
    ("key", "value", "match"),
    [
        ("batch_size", 0, "batch_size"),
        ("lr", -1.0, "lr"),
        ("rerank_weight", -1.0, "rerank_weight"),
        ("bogus", 1, "unknown keys"),
        # a misspelt key is told its nearest name, not only the list of sixty
        (
            "stage1_epoch",
            1,
            r"unknown keys \['stage1_epoch'\] \(did you mean 'stage1_epoch' → "
            r"'stage1_epochs'\?\); known: ",
        ),
    ],
)
def test_bad_config_is_refused(key, value, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig.from_dict({"dataset": "x", key: value})


_CONFIGS = Path(__file__).parents[1] / "configs"


@pytest.mark.parametrize(
    "name", sorted(str(p.relative_to(_CONFIGS)) for p in _CONFIGS.rglob("*.yaml"))
)
def test_every_committed_config_is_valid_and_keeps_its_held_out_sessions(name):
    cfg = TrainConfig.from_yaml(Path(__file__).parents[1] / "configs" / name)
    assert cfg.epochs > 0 and cfg.model_config().grid_size > 0
    if cfg.train_sessions is not None:
        # the README's test sessions s3/s4 of the synthetic benchmark are never trained on
        assert not {"s3", "s4"} & set(cfg.train_sessions), name
    for extra in cfg.extra_datasets:
        if "garage" in extra["dataset"]:
            # the garage test's query session (s1 against a map of s0) is never trained on
            assert "s1" not in (extra.get("train_sessions") or ["s1"]), name


def _make_model_steps() -> list[tuple[str, str]]:
    """The (config, run folder) steps of `make model`, read from the Makefile's MODEL_STEPS."""
    text = (Path(__file__).parents[1] / "Makefile").read_text().replace("\\\n", " ")
    value = re.search(r"^MODEL_STEPS = (.*)$", text, re.M)
    assert value is not None
    return [tuple(step.split(":")) for step in value.group(1).split()]


def test_make_model_chains_its_run_folders_and_records_the_committed_model():
    root = Path(__file__).parents[1]
    steps = _make_model_steps()
    later = ["synth-small-head", "synth-small-ft", "synth-small-ft-head", "synth-small-local"]
    assert [c for c, _ in steps][1:] == later
    configs = [TrainConfig.from_yaml(root / "configs" / f"{c}.yaml") for c, _ in steps]
    assert configs[0].init_checkpoint is None
    for (_, prev_out), cfg in zip(steps[:-1], configs[1:], strict=True):
        # each step starts from the previous one's run folder (or its best/ or checkpoint/)
        init = Path(cfg.init_checkpoint)
        assert init == Path("runs", prev_out) or init.parent == Path("runs", prev_out), init
    # the committed model's training record holds these configs, in this order (keys added to
    # TrainConfig since count as their defaults): steps 1-4 as `make model` trained them from a
    # clean clone (the same bytes as the first training of those steps; step 1 stopped early
    # after epoch 22 with best/ at epoch 17), then step 5
    record = json.loads((root / "models" / "synth-small" / "training.json").read_text())
    defaults = dataclasses.asdict(TrainConfig())
    recorded = [{**defaults, **run["config"]} for run in record["runs"]]
    expected = [dataclasses.asdict(cfg) for cfg in configs]
    assert recorded == expected
    assert [p["epochs"] for p in record["runs"][0]["processes"]] == [[0, 22]]
    assert record["runs"][0]["joint_stopped_early"] == 22
    # the first training of step 1 (its log is the card's) ran on to epoch 29 with the same
    # best/: patience 5 stops it after epoch 22
    best = record["runs"][0]["weights_epoch"]
    log = (root / "models" / "synth-small" / "train_log-step1.jsonl").read_text().splitlines()
    scored = [json.loads(line) for line in log if "val" in json.loads(line)]
    later = [r for r in scored if best < r["epoch"] <= best + 5]
    assert len(later) == 5 and all(r["best_epoch"] == best for r in later)


def test_the_default_step_one_is_v3s_plus_the_rerank_loss_only():
    configs = Path(__file__).parents[1] / "configs"
    assert _make_model_steps()[0] == ("synth-small-rerank", "synth-small")
    v3 = dataclasses.asdict(TrainConfig.from_yaml(configs / "synth-small.yaml"))
    step1 = dataclasses.asdict(TrainConfig.from_yaml(configs / "synth-small-rerank.yaml"))
    changed = {k for k in v3 if v3[k] != step1[k]}
    assert changed == {"rerank_weight", "patience", "hard_pool_restarts"}
    assert step1["rerank_weight"] > 0


def test_missing_dataset_without_sim_section_is_a_clear_error(tmp_path):
    cfg = TrainConfig.from_dict({"dataset": str(tmp_path / "nope")})
    with pytest.raises(FileNotFoundError, match="sim"):
        Trainer(cfg, tmp_path / "run")


def test_augmented_triplets_are_deterministic_per_item_and_keep_poses(tiny_world):
    cfg = _config(tiny_world, augment={"prob": 1.0})
    tr = Trainer(cfg, "unused")
    triplets = tr.sampler.sample_random(2)
    plain = TripletFrames(tr.sampler, triplets)
    aug = TripletFrames(tr.sampler, triplets, augment=tr.augment, seed=5)
    a, b, p = aug[1], aug[1], plain[1]
    assert torch.equal(a["images"], b["images"])
    assert not torch.equal(a["images"], p["images"])
    assert torch.equal(a["poses"], p["poses"]) and torch.equal(a["intrinsics"], p["intrinsics"])
    assert not torch.equal(
        TripletFrames(tr.sampler, triplets, tr.augment, 6)[1]["images"], a["images"]
    )


def test_bad_augment_config_is_refused_by_name():
    with pytest.raises(ValueError, match="augment"):
        TrainConfig.from_dict({"dataset": "x", "augment": {"brightness": -1}})
    with pytest.raises(ValueError, match="augment"):
        TrainConfig.from_dict({"dataset": "x", "augment": [1, 2]})


def test_validation_of_the_map_session_against_itself_retrieves_every_frame(tiny_world):
    tr = Trainer(_config(tiny_world), "unused")
    res = validation_recall(tr.model, tr.ds, "s0", ["s0"], every=2, top_k=5)
    assert res["queries"] == 20
    # each query is a map frame: its own global descriptor is nearest (distance 0)
    assert res["r1_retrieval"] == 1.0 and res["r5_retrieval"] == 1.0
    assert 0.0 <= res["r1_reranked"] <= 1.0
    again = validation_recall(tr.model, tr.ds, "s0", ["s0"], every=2, top_k=5)
    assert json.dumps(again) == json.dumps(res)  # deterministic (NaN-safe comparison)


def test_fit_with_val_sessions_keeps_the_best_joint_epoch_and_resume_remembers_it(
    tiny_world, tmp_path
):
    cfg = _config(
        tiny_world, stage2_epochs=2, train_sessions=["s0", "s1"], val_sessions=["s2"], val_every=4
    )
    out = tmp_path / "run"
    tr = train(cfg, out, progress=False)
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert "val" not in log[0]  # stage 1: the local-view head is not trained yet
    scored = [r for r in log if "val" in r]
    assert [r["epoch"] for r in scored] == [2, 3]
    best = max(scored, key=lambda r: (r["val"]["r1_reranked"], r["val"]["r1_retrieval"]))
    assert tr.best is not None and tr.best["epoch"] == best["epoch"] == log[-1]["best_epoch"]
    assert (out / "best" / "model.safetensors").is_file()
    # the run folder resolves to best/ for eval, map and localize
    assert resolve_checkpoint(out) == out / "best"
    assert resolve_checkpoint(out / "checkpoint") == out / "checkpoint"
    best_model = VVLocNet.load(out / "best")
    expected = validation_recall(best_model, tr.ds, "s0", ["s2"], every=4)
    for key in ("queries", "r1_retrieval", "r5_retrieval", "r1_reranked"):
        assert expected[key] == best["val"][key], key
    # best/ carries the acceptance calibration measured on the validation sessions
    cal = best_model.calibration
    assert cal["sessions"] == ["s2"] and cal["every"] == 4 and cal["database"] == "s0"
    assert cal["min_distinctiveness"] == expected["calibration"]["min_distinctiveness"]
    assert not (out / "checkpoint" / "calibration.json").exists()
    again = Trainer(cfg, out)
    assert again.resume() and json.dumps(again.best) == json.dumps(tr.best)  # NaN-safe


_REAL_VALIDATE = Trainer.validate


def _scripted_validation(monkeypatch, recalls: list[float] | list[tuple[float, float]]) -> None:
    """Make every validation score the next of ``recalls``: Recall@1 re-ranked (retrieval 0), or
    (re-ranked, retrieval) pairs."""
    scores = iter(recalls)

    def validate(self):
        res = _REAL_VALIDATE(self)
        score = next(scores)
        res["r1_reranked"], res["r1_retrieval"] = score if isinstance(score, tuple) else (score, 0)
        return res

    monkeypatch.setattr(Trainer, "validate", validate)


def test_patience_stops_the_joint_stage_and_the_head_stage_follows(
    tiny_world, tmp_path, monkeypatch
):
    import subprocess
    import sys

    import yaml

    val = dict(train_sessions=["s0", "s1"], val_sessions=["s2"], val_every=4, device="cpu")
    head = dict(head_steps_per_epoch=2, head_batch_size=4, head_negatives=3)
    # joint epochs 2-7 score 0.5, 0.7 (best, epoch 3), 0.6, 0.65, ...: two validated epochs
    # without beating epoch 3 end the joint stage after epoch 5; the head epoch follows as 6
    _scripted_validation(monkeypatch, [0.5, 0.7, 0.6, 0.65, 0.1])
    cfg = _config(tiny_world, stage2_epochs=6, patience=2, head_epochs=1, **head, **val)
    tr = train(cfg, tmp_path / "early", progress=False)
    log = [json.loads(line) for line in (tmp_path / "early" / "log.jsonl").read_text().splitlines()]
    assert [(r["epoch"], r["stage"]) for r in log] == [
        (1, 1),
        (2, 2),
        (3, 2),
        (4, 2),
        (5, 2),
        (6, 3),
    ]
    assert [r.get("joint_stopped_early", False) for r in log] == [False] * 4 + [True, False]
    assert tr.best is not None and tr.best["epoch"] == 3 and tr.joint_stopped == 5
    (run,) = _record(tmp_path / "early" / "checkpoint")["runs"]
    assert (run["epochs"], run["epochs_run"], run["complete"]) == (8, 6, True)
    assert run["joint_stopped_early"] == 5
    # the epochs before the stop are those of a run without patience: the same best/
    _scripted_validation(monkeypatch, [0.5, 0.7, 0.6, 0.65])
    plain = train(_config(tiny_world, stage2_epochs=4, **val), tmp_path / "plain", progress=False)
    assert plain.best is not None and plain.best["epoch"] == 3
    assert (
        VVLocNet.load(tmp_path / "early" / "best").weights_hash()
        == VVLocNet.load(tmp_path / "plain" / "best").weights_hash()
    )
    # a run that stopped early is finished: resuming trains nothing, growing it is refused
    again = train(cfg, tmp_path / "early", resume=True, progress=False)
    assert again.epoch == 6 and again.joint_stopped == 5
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(cfg.to_dict()))
    exe = [sys.executable, "-m", "vvloc.cli", "train", "--config", str(tmp_path / "cfg.yaml")]
    r = subprocess.run([*exe, "--out", str(tmp_path / "early"), "--resume"], capture_output=True)
    assert r.returncode == 0, r.stderr
    assert b"nothing to train: the run had done its 6 epochs;" in r.stdout  # not "trained"
    assert b"the joint stage stopped early after epoch 5 (patience 2)" in r.stdout
    longer = dataclasses.replace(cfg, stage2_epochs=9)
    with pytest.raises(ValueError, match="stopped its joint stage early after epoch 5"):
        train(longer, tmp_path / "early", resume=True, progress=False)


def test_a_run_whose_patience_ran_out_at_its_last_joint_epoch_is_not_extended(
    tiny_world, tmp_path, monkeypatch
):
    # joint epochs 2-4 score 0.7 (best, epoch 2), 0.6, 0.5: at epoch 4 two validated epochs
    # have not beaten best/, so a longer run would have stopped there; extending this one to 6
    # joint epochs is refused like the extension of a run that did stop
    val = dict(train_sessions=["s0", "s1"], val_sessions=["s2"], val_every=4, device="cpu")
    _scripted_validation(monkeypatch, [0.7, 0.6, 0.5])
    cfg = _config(tiny_world, stage2_epochs=3, patience=2, **val)
    tr = train(cfg, tmp_path / "run", progress=False)
    assert tr.joint_stopped is None and tr.epoch == 4
    with pytest.raises(ValueError, match="stopped its joint stage early after epoch 4"):
        train(dataclasses.replace(cfg, stage2_epochs=6), tmp_path / "run", resume=True)
    # with patience left, the extension goes on
    _scripted_validation(monkeypatch, [0.5, 0.6, 0.7, 0.8, 0.9])
    ok = train(cfg, tmp_path / "ok", progress=False)
    more = train(dataclasses.replace(cfg, stage2_epochs=4), tmp_path / "ok", resume=True)
    assert ok.epoch == 4 and more.epoch == 5


def test_patience_that_never_runs_out_changes_nothing(tiny_world, tmp_path, monkeypatch):
    val = dict(train_sessions=["s0", "s1"], val_sessions=["s2"], val_every=4, device="cpu")
    _scripted_validation(monkeypatch, [0.5, 0.6, 0.7])
    tr = train(_config(tiny_world, stage2_epochs=3, patience=1, **val), tmp_path / "a")
    assert tr.joint_stopped is None and tr.epoch == 4 and tr.best["epoch"] == 4
    assert "joint_stopped_early" not in _record(tmp_path / "a" / "checkpoint")["runs"][0]


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"patience": 0, "train_sessions": ["s0"], "val_sessions": ["s1"]}, "patience"),
        ({"patience": 1.5, "train_sessions": ["s0"], "val_sessions": ["s1"]}, "patience"),
        ({"patience": 2}, "needs val_sessions"),
        (
            {"patience": 2, "train_sessions": ["s0"], "val_sessions": ["s1"], "stage2_epochs": 0},
            "stage2_epochs > 0",
        ),
    ],
)
def test_bad_patience_is_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig.from_dict({"dataset": "x", **kw})


def test_bad_select_by_is_refused():
    val = {"dataset": "x", "train_sessions": ["s0"], "val_sessions": ["s1"]}
    with pytest.raises(
        ValueError, match=r"select_by: expected one of \['reranked', 'retrieval', 'last'\]"
    ):
        TrainConfig.from_dict({**val, "select_by": "loss"})
    with pytest.raises(ValueError, match=r"select_by: .* needs val_sessions"):
        TrainConfig.from_dict({"dataset": "x", "select_by": "retrieval"})
    assert TrainConfig.from_dict({**val, "select_by": "retrieval"}).select_by == "retrieval"
    with pytest.raises(ValueError, match=r"select_by: 'last' .*patience"):
        TrainConfig.from_dict({**val, "select_by": "last", "patience": 2, "stage2_epochs": 2})


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"train_sessions": ["s0", "s1"], "val_sessions": ["s1"]}, "overlap"),
        ({"val_sessions": ["s1"]}, "train_sessions is unset"),
        ({"train_sessions": ["s0"], "val_sessions": []}, "non-empty"),
        ({"val_every": 0}, "val_every"),
    ],
)
def test_bad_validation_config_is_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig.from_dict({"dataset": "x", **kw})


def test_extra_datasets_are_rendered_and_sampled_as_their_own_world(tiny_world, tmp_path):
    garage = tmp_path / "garage"
    sim = {"scene": "garage", "sessions": 2, "frames": 8, "floors": 2, "progress": False}
    cfg = _config(
        tiny_world,
        stage1_epochs=1,
        stage2_epochs=0,
        steps_per_epoch=3,
        extra_datasets=[{"dataset": str(garage), "sim": sim}],
        cross_floor_fraction=0.5,
    )
    tr = train(cfg, tmp_path / "run", progress=False)
    assert (garage / "sessions" / "s1").is_dir()  # rendered on first use
    assert tr.sampler.sessions[-2:] == ["garage/s0", "garage/s1"]
    assert set(np.unique(tr.sampler.level_of)) == {0, 1000, 1001}
    with pytest.raises(ValueError, match=r"extra_datasets\[0\]: unknown keys \['bogus'\]"):
        TrainConfig.from_dict({"dataset": "x", "extra_datasets": [{"dataset": "y", "bogus": 1}]})
    with pytest.raises(ValueError, match="cross_floor_fraction"):
        TrainConfig.from_dict({"dataset": "x", "cross_floor_fraction": 2})


def test_a_dataset_rendered_by_another_config_or_missing_val_sessions_are_clear_errors(
    tiny_world, tmp_path
):
    sim = {"scene": "parking", "sessions": 5, "frames": 40, "seed": 0}
    with pytest.raises(ValueError, match=r"lacks sessions \['s3', 's4'\]"):
        Trainer(_config(tiny_world, sim=sim), tmp_path / "run")
    # a dataset of one's own (no rendered world in its rig.json) under a config copied with
    # its sim section: the message says to delete that section, not to move the data away
    own = tmp_path / "own"
    shutil.copytree(tiny_world, own)
    doc = json.loads((own / "rig.json").read_text())
    doc.pop("meta", None)
    (own / "rig.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"not rendered by vvloc sim .* delete the config's sim"):
        Trainer(_config(own, sim=sim), tmp_path / "run")
    # another world than the one recorded in rig.json: refused, naming both
    others = ({"seed": 1}, {"scene": "garage"}, {"scene": "garage", "floor_marking": "pillars"})
    for other in others:
        with pytest.raises(ValueError, match=r"was rendered as .*'scene': 'parking'"):
            Trainer(_config(tiny_world, sim={**sim, "sessions": 3, **other}), tmp_path / "run")
    # ... and another rig, image size or session length than the sim section renders: training
    # used the other data without a word
    for other, said in (
        ({"width": 320}, "'width': 160"),
        ({"cameras": 6}, "'cameras': 4"),
        ({"frames": 999}, "'frames': [40]"),
    ):
        with pytest.raises(
            ValueError, match=rf"^sim: dataset .* rendered with .*{re.escape(said)}"
        ):
            Trainer(_config(tiny_world, sim={**sim, "sessions": 3, **other}), tmp_path / "run")
    with pytest.raises(ValueError, match=r"^sim: unknown keys \['seeed'\]"):  # data there
        Trainer(_config(tiny_world, sim={**sim, "sessions": 3, "seeed": 9}), tmp_path / "run")
    # a TrainConfig built directly is checked as from_dict checks one (val_sessions overlapped
    # the training sessions, and best/ was chosen on them)
    direct = dataclasses.replace(
        _config(tiny_world), train_sessions=["s0", "s1"], val_sessions=["s1"]
    )
    with pytest.raises(ValueError, match=r"val_sessions"):
        Trainer(direct, tmp_path / "run")
    with pytest.raises(TypeError, match=r"^cfg: expected a TrainConfig"):
        Trainer({"dataset": str(tiny_world)}, tmp_path / "run")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"^config: expected a YAML config path or a TrainConfig"):
        vvloc.train.train({"dataset": str(tiny_world)}, tmp_path / "run")  # type: ignore[arg-type]
    assert not (tmp_path / "run").exists()
    # a session name that is wrong, repeated or empty is refused naming its key
    bad = [
        ({"train_sessions": ["s0", "s9"]}, r"train_sessions: \['s9'\] not in .*its sessions: s0"),
        ({"val_sessions": ["s7"]}, r"val_sessions: \['s7'\] not in "),
        ({"val_database": "s8"}, r"val_database: \['s8'\] not in [^(]*; its"),
        ({"train_sessions": ["s0", "s1", "s0"]}, r"train_sessions: \['s0'\] named more than once"),
    ]
    for change, match in bad:
        kw = {"train_sessions": ["s0", "s1"], "val_sessions": ["s2"], **change}
        with pytest.raises(ValueError, match=match):
            Trainer(_config(tiny_world, **kw), "unused")
    # own data without the default map session: the message says the name was a default
    renamed = tmp_path / "renamed"
    shutil.copytree(tiny_world, renamed)
    (renamed / "sessions" / "s0").rename(renamed / "sessions" / "map")
    with pytest.raises(ValueError, match=r"val_database: \['s0'\] .*\(its default: set it"):
        Trainer(_config(renamed, train_sessions=["s1"], val_sessions=["s2"]), "unused")
    empty = tmp_path / "empty"
    shutil.copytree(tiny_world, empty)
    poses = empty / "sessions" / "s1" / "poses.csv"
    poses.write_text(poses.read_text().splitlines()[0] + "\n")
    for cam in (empty / "sessions" / "s1").iterdir():
        if cam.is_dir():
            shutil.rmtree(cam)
            cam.mkdir()
    with pytest.raises(ValueError, match=r"train_sessions: sessions \['s1'\] of .* hold no frames"):
        Trainer(_config(empty, train_sessions=["s0", "s1"]), "unused")


def test_init_checkpoint_starts_from_trained_weights_and_refuses_another_model(
    tiny_world, tmp_path
):
    first = train(_config(tiny_world, stage1_epochs=1, stage2_epochs=0), tmp_path / "a", False)
    tuned = Trainer(_config(tiny_world, init_checkpoint=str(tmp_path / "a")), tmp_path / "b")
    for (name, a), b in zip(
        first.model.state_dict().items(), tuned.model.state_dict().values(), strict=True
    ):
        assert torch.equal(a, b), name
    fresh = Trainer(_config(tiny_world), tmp_path / "c")
    assert not all(
        torch.equal(a, b)
        for a, b in zip(
            fresh.model.state_dict().values(), tuned.model.state_dict().values(), strict=True
        )
    )
    with pytest.raises(ValueError, match=r"init_checkpoint: .* holds model"):
        Trainer(
            _config(
                tiny_world,
                init_checkpoint=str(tmp_path / "a"),
                model_overrides={"num_angles": 30},
            ),
            tmp_path / "d",
        )
    with pytest.raises(FileNotFoundError, match="init_checkpoint"):
        Trainer(_config(tiny_world, init_checkpoint=str(tmp_path / "nope")), tmp_path / "e")
    with pytest.raises(ValueError, match="init_checkpoint"):
        TrainConfig.from_dict({"dataset": "x", "init_checkpoint": 3})


def test_a_garage_rendered_with_another_floor_marking_is_refused(tmp_path):
    from vvloc.train.data import _check_rendered_like

    root = tmp_path / "garage"
    root.mkdir()
    meta = {"scene": "garage", "seed": 0, "floors": 2, "generator": "vvloc.sim"}
    (root / "rig.json").write_text(json.dumps({"meta": meta}))  # before floor_marking existed
    sim = {"scene": "garage", "seed": 0, "floors": 2}
    _check_rendered_like(root, sim)  # an unrecorded marking is the default "walls"
    _check_rendered_like(root, {**sim, "floor_marking": "walls"})
    with pytest.raises(ValueError, match=r"'floor_marking': 'walls'.*'floor_marking': 'pillars'"):
        _check_rendered_like(root, {**sim, "floor_marking": "pillars"})
    with pytest.raises(ValueError, match="'floors': 3"):
        _check_rendered_like(root, {**sim, "floors": 3})
    # a tilting vehicle's dataset is another one than a level vehicle's, both ways
    with pytest.raises(ValueError, match=r"'max_pitch': 0\.0.*'max_pitch': 5\.0"):
        _check_rendered_like(root, {**sim, "max_pitch": 5})
    (root / "rig.json").write_text(json.dumps({"meta": {**meta, "max_roll": 3.0}}))
    _check_rendered_like(root, {**sim, "max_roll": 3})
    with pytest.raises(ValueError, match=r"'max_roll': 3\.0.*'max_roll': 0\.0"):
        _check_rendered_like(root, sim)


NETVLAD_SMALL = {"global_head": "netvlad", "netvlad_clusters": 4, "global_dim": 16}


def _head_only_config(root, base: Path, **kw) -> TrainConfig:
    """A head-stage-only run on the weights of ``base`` (a NetVLAD head unless overridden)."""
    opts = dict(
        init_checkpoint=str(base),
        model_overrides=NETVLAD_SMALL,
        stage1_epochs=0,
        stage2_epochs=0,
        head_epochs=2,
        head_steps_per_epoch=6,
        head_batch_size=4,
        head_negatives=3,
    )
    opts.update(kw)
    return _config(root, **opts)


def test_head_stage_trains_only_the_global_head_and_lowers_its_loss(tiny_world, tmp_path):
    base = train(_config(tiny_world, stage1_epochs=1, stage2_epochs=0), tmp_path / "a", False)
    cfg = _head_only_config(
        tiny_world,
        tmp_path / "a",
        head_epochs=3,
        head_steps_per_epoch=15,
        head_batch_size=8,
        head_lr=1e-2,
    )
    tuned = Trainer(cfg, tmp_path / "b")
    fixed = tuned.sampler.sample_random(64)  # random negatives, the same before and after
    tuned.run_epoch(progress=False)  # caches the BEVs, starts the head from k-means
    with torch.no_grad():
        first = float(tuned.head_losses(tuned.head_cache(), fixed)[0])
    tuned.fit(progress=False)
    with torch.no_grad():
        last = float(tuned.head_losses(tuned.head_cache(), fixed)[0])
    assert last < first
    log = [json.loads(line) for line in (tmp_path / "b" / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in log] == [3, 3]  # fit() ran the remaining two epochs
    before = base.model.state_dict()
    for name, value in tuned.model.state_dict().items():
        if not name.startswith("global_head."):
            assert torch.equal(value, before[name]), name  # the encoder and decoder are frozen
    saved = VVLocNet.load(tmp_path / "b" / "checkpoint")
    assert saved.config.global_head == "netvlad" and saved.global_dim == 16


def test_head_stage_k_means_start_and_resume_continue_identically(tiny_world, tmp_path):
    from vvloc.nets import ModelConfig
    from vvloc.nets.heads import NetVLADHead

    cfg = ModelConfig.small()
    cfg.netvlad_clusters = 3
    head = NetVLADHead(cfg)
    cells = torch.cat([torch.eye(64)[k].repeat(20, 1) * (k + 1) for k in (0, 5, 9)])
    noise = torch.rand(cells.shape, generator=torch.Generator().manual_seed(0))
    head.init_from_features(cells + 0.01 * noise)
    found = sorted(int(i) for i in head.centroids.argmax(dim=1))
    assert found == [0, 5, 9]
    with pytest.raises(ValueError, match="cells: expected at least 3"):
        head.init_from_features(torch.rand(2, 64))

    base = tmp_path / "base"
    train(_config(tiny_world, stage1_epochs=1, stage2_epochs=0), base, progress=False)
    # stopped after the first head epoch (the k-means start), resumed for the second: the
    # resumed run must not restart the head from k-means
    _assert_resumed_run_equals_uninterrupted(_head_only_config(tiny_world, base), tmp_path, cut=1)


def test_the_k_means_start_replaces_only_an_untrained_head(tiny_world, tmp_path, monkeypatch):
    from vvloc.nets.heads import NetVLADHead

    calls = []
    real = NetVLADHead.init_from_features
    monkeypatch.setattr(
        NetVLADHead,
        "init_from_features",
        lambda self, *a, **k: calls.append(1) or real(self, *a, **k),
    )
    kw = dict(head_epochs=2, head_steps_per_epoch=3, head_batch_size=4, head_negatives=3)
    base = tmp_path / "base"
    train(_config(tiny_world, stage1_epochs=1, stage2_epochs=0), base, progress=False)
    train(_head_only_config(tiny_world, base, **kw), tmp_path / "a", progress=False)
    assert len(calls) == 1  # the new head starts from k-means once, not every head epoch
    # a NetVLAD head trained in stage 1 is refined, never reset
    train(
        _config(tiny_world, model_overrides=NETVLAD_SMALL, stage1_epochs=1, stage2_epochs=0, **kw),
        tmp_path / "b",
        progress=False,
    )
    assert len(calls) == 1


def test_mined_negatives_are_never_positives_and_are_the_nearest(tiny_world, tmp_path):
    base = tmp_path / "base"
    train(_config(tiny_world, stage1_epochs=1, stage2_epochs=0), base, progress=False)
    twin = tmp_path / "twin"  # the same places once more, as a second world
    shutil.copytree(tiny_world, twin)
    cfg = _head_only_config(
        tiny_world,
        base,
        model_overrides={},
        head_epochs=1,
        head_negatives=1,
        # a second world lies 10⁶ m away in z: precision must hold
        extra_datasets=[{"dataset": str(twin)}],
    )
    tr = Trainer(cfg, tmp_path / "a")
    g = tr._head_descriptors(tr.head_cache())
    anchors = tr.sampler.anchors[:: max(1, len(tr.sampler.anchors) // 40)]
    neg = tr._mined_negatives(g, anchors)
    pos = tr.sampler.positions
    gap = np.linalg.norm(pos[neg] - pos[anchors], axis=1)
    assert (gap > cfg.neg_radius).all()
    # with head_negatives = 1 the pick is the nearest non-positive in descriptor space
    for a, n in zip(anchors, neg, strict=True):
        far = np.linalg.norm(pos - pos[a], axis=1) > cfg.neg_radius
        sims = (g @ g[a]).numpy()
        assert sims[n] == pytest.approx(sims[far].max())


def _local_only_config(root, base: Path, **kw) -> TrainConfig:
    """A local-stage-only run on the weights of ``base``, the near translation loss on."""
    opts = dict(
        init_checkpoint=str(base),
        stage1_epochs=0,
        stage2_epochs=0,
        local_epochs=2,
        local_steps_per_epoch=4,
        local_batch_size=4,
        tbias_near_weight=1.0,
        tbias_near_zero=0.5,
    )
    opts.update(kw)
    return _config(root, **opts)


def test_local_stage_trains_only_the_decoder_and_interactor_and_lowers_its_losses(
    tiny_world, tmp_path
):
    base = train(_config(tiny_world, stage1_epochs=1, stage2_epochs=0), tmp_path / "a", False)
    cfg = _local_only_config(
        tiny_world, tmp_path / "a", local_epochs=3, local_steps_per_epoch=10, local_lr=1e-3
    )
    tuned = Trainer(cfg, tmp_path / "b")
    fixed = tuned.sampler.sample_random(16)[:, :2]
    tuned.run_epoch(progress=False)  # caches the BEVs
    bevs, poses = tuned.local_cache()
    assert bevs.dtype == torch.float16 and bevs.shape[0] == len(tuned.sampler) == len(poses)
    with torch.no_grad():
        first = [float(x) for x in tuned.local_losses(bevs, poses, fixed, step=0)]
    tuned.fit(progress=False)
    with torch.no_grad():
        last = [float(x) for x in tuned.local_losses(bevs, poses, fixed, step=0)]
    assert last[0] < first[0]
    log = [json.loads(line) for line in (tmp_path / "b" / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in log] == [4, 4]  # fit() ran the remaining two epochs
    assert all(r["loss_tbias_near"] > 0 for r in log)
    before = base.model.state_dict()
    changed = set()
    for name, value in tuned.model.state_dict().items():
        if torch.equal(value, before[name]):
            continue
        changed.add(name.split(".")[0])
    assert changed == {"decoder", "interactor"}  # the encoder and the global head are frozen


def test_local_stage_resume_continues_identically(tiny_world, tmp_path):
    base = tmp_path / "base"
    train(_config(tiny_world, stage1_epochs=1, stage2_epochs=0), base, progress=False)
    _assert_resumed_run_equals_uninterrupted(_local_only_config(tiny_world, base), tmp_path, cut=1)


def test_frames_without_image_content_are_left_out_of_training(tiny_world, tmp_path, caplog):
    # a covered rig's frames look alike wherever they were: their triplets cannot be learnt and
    # stayed in the hard pool for good
    root = tmp_path / "world"
    shutil.copytree(tiny_world, root)
    blank = range(0, 40, 2)
    blank_frames(root, "s1", blank)
    cfg = _config(
        root,
        stage1_epochs=2,
        stage2_epochs=0,
        steps_per_epoch=6,
        head_epochs=1,
        head_steps_per_epoch=2,
        head_batch_size=4,
        head_negatives=3,
        local_epochs=1,
        local_steps_per_epoch=1,
        local_batch_size=2,
    )
    tr = Trainer(cfg, tmp_path / "run")
    where = {("s1", i) for i in blank}
    gids = np.array([g for g in range(len(tr.sampler)) if tr.sampler.locate(g) in where])
    assert len(gids) == len(blank)
    with caplog.at_level("WARNING", logger="vvloc.train"):
        record = tr.run_epoch(progress=False)
    found = tr.sampler.excluded
    assert 0 < len(found) < len(blank) and np.isin(found, gids).all()  # those drawn
    assert record["blank_triplets"] > 0
    assert re.search(
        rf"left {len(found)} training frames? without image content \(every camera's picture "
        r"flat\) out of training from now on: s1:\d+",
        caplog.text,
    )
    assert not np.isin(tr.sampler.hard, gids).any()
    tr.run_epoch(progress=False)
    assert np.isin(found, tr.sampler.excluded).all()
    saved = tr.sampler.excluded
    tr.save()
    tr.run_epoch(progress=False)  # the head stage's cache finds every one of them
    assert np.array_equal(tr.sampler.excluded, gids)
    anchors = tr.sampler.sample_random(50)[:, 0]
    assert not np.isin(anchors, gids).any()
    g = tr._head_descriptors(tr.head_cache())
    g[torch.from_numpy(gids)] = g[int(anchors[0])].clone()  # the anchor's look-alikes
    mined = tr._mined_negatives(g, np.full(50, anchors[0]))
    assert not np.isin(mined, gids).any()
    tr.run_epoch(progress=False)  # the local stage's: no new one
    assert np.array_equal(tr.sampler.excluded, gids)
    # the trainer state carries them: a resumed run leaves them out of its first draw
    resumed = Trainer(cfg, tmp_path / "run")
    assert resumed.resume()
    assert np.array_equal(resumed.sampler.excluded, saved)


def test_an_epoch_of_triplets_without_image_content_trains_no_step_and_says_so(
    tiny_world, tmp_path, caplog
):
    root = tmp_path / "world"
    shutil.copytree(tiny_world, root)
    for name in ("s1", "s2"):  # every positive lies in another session: every triplet blank
        blank_frames(root, name, range(40))
    tr = Trainer(_config(root, stage1_epochs=2, stage2_epochs=0), tmp_path / "run")
    before = [p.detach().clone() for p in tr.model.parameters()]
    with caplog.at_level("WARNING", logger="vvloc.train"):
        record = tr.run_epoch(progress=False)  # no torch warning of a schedule without a step
    assert record["step"] == 0 and record["blank_triplets"] == 4
    assert math.isnan(record["loss_total"]) and math.isnan(record["violated_share"])
    assert "epoch 1 trained no step: each of its 4 triplets held a frame without image content" in (
        caplog.text
    )
    assert all(torch.equal(a, b) for a, b in zip(before, tr.model.parameters(), strict=True))
    tr.save()
    tr._log_record(record)  # null, not a perfect epoch
    logged = json.loads((tmp_path / "run" / "log.jsonl").read_text().splitlines()[0])
    assert logged["loss_total"] is None and logged["violated_share"] is None
    # once every blank frame is found, nothing is left to train on: said so, by its cause
    every = [g for g in range(len(tr.sampler)) if tr.sampler.locate(g)[0] != "s0"]
    with pytest.raises(
        ValueError,
        match=r"^training frames without image content \(every camera's picture flat\) leave "
        r"nothing to train on once left out: exclude: no anchor would be left \(sessions "
        r"\['s0', 's1', 's2'\]; 80 of 120 frames excluded\); the checkpoint in .* keeps the "
        r"last finished epoch$",
    ):
        tr._exclude_blank(np.array(every))


def test_a_run_whose_epoch_trains_no_step_goes_on_and_keeps_its_exclusions(tiny_world, tmp_path):
    # fit() took the epoch's nan losses for a diverged run: FloatingPointError, nothing saved
    # (the exclusions neither), and every retry drew the same epoch and failed the same way
    root = tmp_path / "world"
    shutil.copytree(tiny_world, root)
    for name in ("s1", "s2"):
        blank_frames(root, name, range(40))
    cfg = _config(root, stage1_epochs=1, stage2_epochs=0)
    train(cfg, tmp_path / "run", progress=False)
    (logged,) = [json.loads(x) for x in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert logged["step"] == 0 and logged["blank_triplets"] == 4
    assert logged["loss_total"] is None
    resumed = Trainer(cfg, tmp_path / "run")
    assert resumed.resume() and resumed.epoch == 1 and len(resumed.sampler.excluded) > 0


def test_best_is_written_after_the_state_and_mended_by_resume(tiny_world, tmp_path, monkeypatch):
    # best/ was swapped in before the state: a stop between the two left best/ with weights of
    # an epoch the resumed run trained again, and kept them when the rerun scored lower
    val = dict(train_sessions=["s0", "s1"], val_sessions=["s2"], val_every=4, device="cpu")
    cfg = _config(tiny_world, stage1_epochs=2, stage2_epochs=0, **val)
    tr = Trainer(cfg, tmp_path / "run")

    def stop(self):  # the process stops after the state, before best/
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(Trainer, "_save_best", stop)
        with pytest.raises(KeyboardInterrupt):
            tr.fit(progress=False)
    assert not (tmp_path / "run" / "best").exists()
    resumed = Trainer(cfg, tmp_path / "run")
    assert resumed.resume() and resumed.epoch == 1 and resumed.best["epoch"] == 1
    best = VVLocNet.load(tmp_path / "run" / "best")  # written from the state's weights
    assert best.weights_hash() == resumed.model.weights_hash()
    assert best.training_record["runs"][-1]["weights_epoch"] == 1
    assert best.calibration["sessions"] == ["s2"]
    # with the record the stopped process would have written: its process only
    checkpoint = _record(tmp_path / "run" / "checkpoint")["runs"][-1]["processes"]
    assert best.training_record["runs"][-1]["processes"] == checkpoint


def test_resume_mends_best_from_the_state_or_says_why_it_cannot(tiny_world, tmp_path, caplog):
    val = dict(train_sessions=["s0", "s1"], val_sessions=["s2"], val_every=4, device="cpu")
    cfg = _config(tiny_world, stage1_epochs=3, stage2_epochs=0, **val)
    tr = Trainer(cfg, tmp_path / "run")
    tr.run_epoch(progress=False)
    tr.best = {"epoch": 1, "val": tr.validate()}
    tr.save()
    tr._save_best()
    best = tmp_path / "run" / "best"
    record = best / "training.json"

    def claim(epoch):  # best/ as a process of before 2026-12-07 could leave it
        doc = json.loads(record.read_text())
        doc["runs"][-1]["weights_epoch"] = epoch
        record.write_text(json.dumps(doc))

    # the state's epoch is its best: best/ is written again from the state's weights
    claim(2)
    assert Trainer(cfg, tmp_path / "run").resume()
    assert _record(best)["runs"][-1]["weights_epoch"] == 1
    # an unreadable record: best/ as it is
    record.write_text("{")
    assert Trainer(cfg, tmp_path / "run").resume()
    assert record.read_text() == "{"
    # the state's best is an earlier epoch, whose weights are gone: said, and left for an
    # epoch that beats it
    tr = Trainer(cfg, tmp_path / "run")
    assert tr.resume()
    tr._save_best()  # a readable record again
    tr.run_epoch(progress=False)
    tr.save()  # epoch 2, best still epoch 1
    claim(3)
    before = (best / "model.safetensors").read_bytes()
    with caplog.at_level("WARNING", logger="vvloc.train"):
        assert Trainer(cfg, tmp_path / "run").resume()
    assert "holds epoch 3's weights, the run's state names epoch 1 as its best" in caplog.text
    assert (best / "model.safetensors").read_bytes() == before


def test_weight_decay_is_every_stages(tiny_world, tmp_path):
    tr = Trainer(_config(tiny_world, weight_decay=0.1), tmp_path / "run")
    for opt in (tr.optimizer, tr.head_optimizer, tr.local_optimizer):
        assert opt.param_groups[0]["weight_decay"] == 0.1


def test_a_run_resumes_after_its_init_checkpoint_is_gone(tiny_world, tmp_path):
    base = tmp_path / "base"
    train(_config(tiny_world, stage1_epochs=1, stage2_epochs=0), base, progress=False)
    cfg = _local_only_config(tiny_world, base)
    full = train(cfg, tmp_path / "full", progress=False)
    part = Trainer(cfg, tmp_path / "part")
    part.run_epoch(progress=False)
    part.save()
    base.rename(tmp_path / "moved")  # e.g. the run folder was copied to another machine
    with pytest.raises(FileNotFoundError, match="init_checkpoint: no checkpoint"):
        Trainer(cfg, tmp_path / "fresh")  # a new run needs it
    stray = Trainer(cfg, tmp_path / "part")  # no resume: it would train without the weights
    with pytest.raises(FileNotFoundError, match="init_checkpoint: no checkpoint"):
        stray.fit(progress=False)
    with pytest.raises(FileNotFoundError, match="init_checkpoint: no checkpoint"):
        stray.run_epoch(progress=False)
    with pytest.raises(FileNotFoundError, match="init_checkpoint: no checkpoint"):
        stray.save()  # it would write a random initialisation over the run's checkpoint
    resumed = train(cfg, tmp_path / "part", resume=True, progress=False)
    for a, b in zip(
        resumed.model.state_dict().values(), full.model.state_dict().values(), strict=True
    ):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    record = _record(tmp_path / "part" / "checkpoint")["runs"]
    expected = _record(tmp_path / "full" / "checkpoint")["runs"]
    assert len(record) == len(expected) == 2  # the base run's record is kept
    assert record[0] == expected[0]
    assert record[1]["init_weights_hash"] == expected[1]["init_weights_hash"] is not None


def test_the_local_stage_follows_the_head_stage(tiny_world):
    cfg = _config(tiny_world, stage2_epochs=2, head_epochs=1, local_epochs=2)
    tr = Trainer(cfg, "unused")
    assert [tr.stage_of(e) for e in range(cfg.epochs)] == [1, 2, 2, 3, 4, 4]
    assert tr.total_epochs == cfg.epochs == 6


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"stage1_epochs": 0, "stage2_epochs": 0, "local_epochs": 1}, "local_epochs: .*needs"),
        ({"local_lr": 0.0}, "local_lr"),
        ({"local_batch_size": 0}, "local_batch_size"),
        ({"tbias_near_weight": -1.0}, "tbias_near_weight"),
        ({"tbias_near_range": [1.0, 0.5]}, "tbias_near_range"),
        ({"tbias_near_range": [0.0, 0.5]}, "tbias_near_range"),
        ({"tbias_near_range": 0.5}, "tbias_near_range"),
        ({"tbias_near_zero": 2.0}, "tbias_near_zero"),
    ],
)
def test_bad_local_stage_config_is_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig.from_dict({"dataset": "x", **kw})


def test_a_head_stage_alone_without_a_trained_encoder_is_refused():
    with pytest.raises(ValueError, match=r"head_epochs: .*needs init_checkpoint"):
        TrainConfig.from_dict(
            {"dataset": "x", "stage1_epochs": 0, "stage2_epochs": 0, "head_epochs": 1}
        )


def test_a_new_global_head_without_a_head_stage_is_refused(tiny_world, tmp_path):
    train(_config(tiny_world, stage1_epochs=1, stage2_epochs=0), tmp_path / "a", False)
    with pytest.raises(ValueError, match="set head_epochs > 0"):
        Trainer(
            _config(
                tiny_world,
                init_checkpoint=str(tmp_path / "a"),
                model_overrides={"global_head": "netvlad"},
            ),
            tmp_path / "b",
        )


def test_loop_validation_counts_every_admissible_pair_and_the_cross_floor_ones(tmp_path):
    from vvloc.data import open_dataset
    from vvloc.sim import simulate_dataset
    from vvloc.train import loop_validation

    garage = tmp_path / "garage"
    simulate_dataset(garage, scene="garage", sessions=2, frames=16, floors=2, progress=False)
    ds = open_dataset(garage)
    model = VVLocNet(TrainConfig().model_config()).eval()
    # a radius beyond any distance of unit descriptors (≤ 2) accepts every admissible pair
    res = loop_validation(model, ds, ["s0", "s1"], radius=2.5, window=2)
    fl = np.concatenate([ds.session(s).floors for s in ("s0", "s1")])
    sess = np.repeat([0, 1], 16)
    seq = np.tile(np.arange(16), 2)
    i, j = np.triu_indices(32, 1)
    admissible = ~((sess[i] == sess[j]) & (np.abs(seq[i] - seq[j]) <= 2))
    assert res["frames"] == 32
    assert res["accepted"] == int(admissible.sum())
    assert res["cross_floor"] == int((admissible & (fl[i] != fl[j])).sum()) > 0
    assert res["cfer"] == pytest.approx(res["cross_floor"] / res["accepted"])
    tight = loop_validation(model, ds, ["s0", "s1"], radius=1e-6, window=2)
    assert tight["accepted"] == 0 and tight["cross_floor"] == 0
    # with the sequence check (±1) a pair needs both neighbours of each keyframe: the pairs with
    # a session's first or last keyframe drop; for the others driving the same way is complete
    seq1 = loop_validation(model, ds, ["s0", "s1"], radius=2.5, window=2, sequence=1)
    inner = admissible & (seq[i] % 15 != 0) & (seq[j] % 15 != 0)
    assert seq1["accepted"] == int(inner.sum()) > 0


def test_best_epoch_has_the_fewest_cross_floor_loops_then_the_highest_recall():
    key = Trainer.selection_key
    plain = {"r1_reranked": 0.8, "r1_retrieval": 0.7}
    assert key(plain) > key({"r1_reranked": 0.8, "r1_retrieval": 0.6})
    two = {**plain, "loops": [{"cross_floor": 1}, {"cross_floor": 1}]}
    one = {
        "r1_reranked": 0.7,
        "r1_retrieval": 0.5,
        "loops": [{"cross_floor": 0}, {"cross_floor": 1}],
    }
    assert key(one) > key(two)  # a cross-floor loop closure weighs more than recall
    assert key({**one, "r1_reranked": 0.75}) > key(one)
    # select_by: retrieval first, re-ranked breaks ties; loops still come first
    assert key(plain, "retrieval") > key({"r1_reranked": 0.9, "r1_retrieval": 0.6}, "retrieval")
    assert key(plain, "retrieval") > key({"r1_reranked": 0.7, "r1_retrieval": 0.7}, "retrieval")
    assert key(one, "retrieval") > key(two, "retrieval")
    with pytest.raises(ValueError, match="by: expected one of"):
        key(plain, "loops")


def test_select_by_retrieval_keeps_the_epoch_that_retrieves_best(tiny_world, tmp_path, monkeypatch):
    val = dict(train_sessions=["s0", "s1"], val_sessions=["s2"], val_every=4, device="cpu")
    # (re-ranked, retrieval) of the joint epochs 2-4: re-ranking prefers epoch 2, retrieval
    # ties epochs 3 and 4 and re-ranking breaks the tie for epoch 4
    scores = [(0.9, 0.1), (0.5, 0.6), (0.6, 0.6)]
    _scripted_validation(monkeypatch, scores)
    cfg = _config(tiny_world, stage2_epochs=3, select_by="retrieval", **val)
    assert train(cfg, tmp_path / "retrieval", progress=False).best["epoch"] == 4
    _scripted_validation(monkeypatch, scores)
    plain = _config(tiny_world, stage2_epochs=3, **val)
    assert plain.select_by == "reranked"
    assert train(plain, tmp_path / "reranked", progress=False).best["epoch"] == 2
    _scripted_validation(monkeypatch, scores)
    last = _config(tiny_world, stage2_epochs=3, select_by="last", **val)
    assert train(last, tmp_path / "last", progress=False).best["epoch"] == 4  # the worst retriever


def test_sessions_and_datasets_of_extra_datasets_and_val_loops_are_refused_by_key(
    tiny_world, tmp_path
):
    # they said "no session 's99' in ..." or "no such dataset folder" without the config's key
    base = {"train_sessions": ["s0", "s1"], "val_sessions": ["s2"]}
    twin = tmp_path / "twin"
    shutil.copytree(tiny_world, twin)
    for kw, said in (
        ({"extra_datasets": [{"dataset": str(tmp_path / "none")}]},
         r"^extra_datasets\[0\]\.dataset: .*none does not exist and extra_datasets\[0\] has no"),
        ({"extra_datasets": [{"dataset": str(twin), "train_sessions": ["s1", "s99"]}]},
         r"^extra_datasets\[0\]\.train_sessions: \['s99'\] not in .*; its sessions: s0, s1, s2"),
        ({"val_loops": [{"dataset": str(tmp_path / "none"), "sessions": ["s2"]}]},
         r"^val_loops\[0\]\.dataset: .*none: no such dataset folder"),
        ({"val_loops": [{"dataset": str(tiny_world), "sessions": ["s2", "s99"]}]},
         r"^val_loops\[0\]\.sessions: \['s99'\] not in .*; its sessions: s0, s1, s2"),
    ):  # fmt: skip
        with pytest.raises((ValueError, FileNotFoundError), match=said):
            Trainer(_config(tiny_world, **base, **kw), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_a_raw_nclt_or_robotcar_folder_is_refused_by_key_naming_vvloc_convert(tiny_world, tmp_path):
    # read with no reader options, a raw folder trained at its native image size (NCLT's
    # 1232 x 1616), on every frame, with the ego origin left above the ground
    nclt, oxford = tmp_path / "nclt", tmp_path / "oxford"
    (nclt / "2012-01-08" / "lb3").mkdir(parents=True)
    (nclt / "cam_params").mkdir()
    (oxford / "2014-05-19-13-20-57" / "gps").mkdir(parents=True)
    (oxford / "2014-05-19-13-20-57" / "gps" / "ins.csv").write_text("timestamp\n")
    base = {"train_sessions": ["s0", "s1"], "val_sessions": ["s2"]}
    for kw, said in (
        ({"dataset": str(nclt), "sim": None}, r"^dataset: .*nclt is an NCLT raw folder; "),
        ({"extra_datasets": [{"dataset": str(oxford)}]},
         r"^extra_datasets\[0\]\.dataset: .*oxford is an Oxford RobotCar raw folder; "),
        ({"val_loops": [{"dataset": str(nclt), "sessions": ["s2"]}]},
         r"^val_loops\[0\]\.dataset: .*nclt is an NCLT raw folder; "),
    ):  # fmt: skip
        with pytest.raises(ValueError, match=said + r".*vvloc convert --src "):
            Trainer(_config(tiny_world, **{**base, **kw}), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_an_extra_dataset_of_the_rig_s_cameras_in_another_order_is_refused(tiny_world, tmp_path):
    # it trained: a batch stacks images slot by slot, so each slot's camera embedding learnt two
    # cameras (the README asks for the same rig; another mounting is recorded, not refused)
    twin = tmp_path / "twin"
    shutil.copytree(tiny_world, twin)
    rig = json.loads((twin / "rig.json").read_text())
    rig["cameras"] = rig["cameras"][::-1]
    (twin / "rig.json").write_text(json.dumps(rig))
    said = (
        r"^extra_datasets\[0\]\.dataset: .*twin holds the cameras of .* in another order "
        r"\(right,rear,left,front against front,left,rear,right\): .* vvloc convert --cameras "
        r"front,left,rear,right$"
    )
    with pytest.raises(ValueError, match=said):
        Trainer(_config(tiny_world, extra_datasets=[{"dataset": str(twin)}]), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_bad_val_loops_are_refused_by_name():
    base = {"dataset": "x", "train_sessions": ["s0"], "val_sessions": ["s1"]}
    with pytest.raises(ValueError, match=r"val_loops: needs val_sessions"):
        TrainConfig.from_dict({"dataset": "x", "val_loops": [{"dataset": "g", "sessions": ["s5"]}]})
    with pytest.raises(ValueError, match=r"val_loops\[0\]: expected a mapping"):
        TrainConfig.from_dict({**base, "val_loops": [{"dataset": "g"}]})
    with pytest.raises(ValueError, match=r"val_loops\[0\]: unknown keys \['bogus'\]"):
        TrainConfig.from_dict(
            {**base, "val_loops": [{"dataset": "g", "sessions": ["s5"], "bogus": 1}]}
        )
    with pytest.raises(ValueError, match=r"val_loops\[0\]\.sequence"):
        TrainConfig.from_dict(
            {**base, "val_loops": [{"dataset": "g", "sessions": ["s5"], "sequence": -1}]}
        )
    with pytest.raises(ValueError, match=r"val_loops\[0\]\.radius"):
        TrainConfig.from_dict(
            {**base, "val_loops": [{"dataset": "g", "sessions": ["s5"], "radius": 0}]}
        )
    with pytest.raises(ValueError, match=r"val_loops\[0\]\.sessions: must not be trained on"):
        TrainConfig.from_dict(
            {
                **base,
                "extra_datasets": [{"dataset": "g", "train_sessions": ["s0", "s5"]}],
                "val_loops": [{"dataset": "./g/", "sessions": ["s5"]}],  # g, spelt otherwise
            }
        )


def test_validation_and_extra_datasets_cannot_hold_what_trains():
    base = {"dataset": "data/x", "train_sessions": ["s0", "s1"], "val_sessions": ["s2"]}
    TrainConfig.from_dict(base)
    # the map session among the validation queries, or a query twice: inflated recall
    with pytest.raises(ValueError, match=r"val_sessions: the map session 's2' is among"):
        TrainConfig.from_dict({**base, "val_database": "s2"})
    with pytest.raises(ValueError, match=r"val_sessions: sessions named more than once"):
        TrainConfig.from_dict({**base, "val_sessions": ["s2", "s2"]})
    # the training dataset again as an extra one: it would train val_sessions as another world
    for spelt in ("data/x", "./data/x", "data/x/", "data/../data/x"):
        with pytest.raises(ValueError, match=r"extra_datasets\[0\]\.dataset: .* training dataset"):
            TrainConfig.from_dict({**base, "extra_datasets": [{"dataset": spelt}]})
    twice = [{"dataset": "data/g"}, {"dataset": "./data/g", "train_sessions": ["s1"]}]
    with pytest.raises(ValueError, match=r"extra_datasets\[1\]\.dataset: .* listed twice"):
        TrainConfig.from_dict({**base, "extra_datasets": twice})


def test_fit_with_val_loops_logs_them_and_selects_by_them(tiny_world, tmp_path):
    loops = [{"dataset": str(tiny_world), "sessions": ["s2"], "radius": 0.5, "window": 2}]
    cfg = _config(
        tiny_world,
        stage1_epochs=2,
        stage2_epochs=0,
        train_sessions=["s0", "s1"],
        val_sessions=["s2"],
        val_every=4,
        val_loops=loops,
    )
    tr = train(cfg, tmp_path / "run", progress=False)
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    for rec in log:
        (entry,) = rec["val"]["loops"]
        assert entry["frames"] == 40 and entry["cross_floor"] == 0  # one floor
        assert entry["dataset"] == str(tiny_world)
    best = max(log, key=lambda r: Trainer.selection_key(r["val"]))
    assert tr.best is not None and tr.best["epoch"] == best["epoch"]
    with pytest.raises(ValueError, match=r"val_loops\[0\]\.sessions: must not be trained on"):
        _config(
            tiny_world,
            train_sessions=["s0", "s1"],
            val_sessions=["s2"],
            val_loops=[{"dataset": str(tiny_world), "sessions": ["s1"]}],
        )


def _record(path: Path) -> dict:
    return json.loads((path / "training.json").read_text())


def test_every_checkpoint_records_the_runs_that_produced_it(tiny_world, tmp_path, monkeypatch):
    from vvloc.data import open_dataset
    from vvloc.provenance import (
        cpu_model,
        hardware,
        libraries,
        rendered_plan,
        session_digest,
        summarize,
    )

    cfg_a = _config(tiny_world, stage1_epochs=1, stage2_epochs=0, device="cpu")
    first = train(cfg_a, tmp_path / "a", progress=False)
    rec_a = _record(tmp_path / "a" / "checkpoint")
    assert rec_a["format"] == "vvloc.training" and rec_a["version"] == 1
    assert rec_a["weights_hash"] == first.model.weights_hash()
    (run,) = rec_a["runs"]
    assert (run["epochs_run"], run["epochs"], run["weights_epoch"]) == (1, 1, 1)
    assert run["complete"] and run["init_weights_hash"] is None and run["seconds"] > 0
    assert run["config"] == first.cfg.to_dict() and run["out"] == str(tmp_path / "a")
    assert run["cwd"] == os.getcwd()  # what its relative paths are relative to
    # the cameras it trained on, which maps from another rig are checked against
    ds = open_dataset(tiny_world)
    assert run["rigs"] == [[c.to_json() for c in ds.cameras]]
    # the frames of each session it trained on (all three), which eval knows in a copy
    want = sorted(
        session_digest(s.timestamps, s.poses, s.floors, rendered_plan(tiny_world, name))
        for name, s in zip(ds.sessions, map(ds.session, ds.sessions), strict=True)
    )
    assert run["session_digests"] == want and len(set(want)) == 3
    (proc,) = run["processes"]
    assert proc["hardware"] == hardware() and proc["device"] == "cpu"
    assert proc["device_name"] is None and proc["torch_threads"] == torch.get_num_threads()
    assert proc["epochs"] == [0, 1] and proc["seconds"] == run["seconds"]
    # what a retraining must match to give these bytes: processor, kernels, library versions
    assert proc["cpu"] == cpu_model() and proc["libraries"] == libraries()
    assert proc["torch_cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert proc["libraries"]["numpy"] == np.__version__
    # loading keeps the record, saving elsewhere keeps it with the weights
    loaded = VVLocNet.load(tmp_path / "a" / "checkpoint")
    assert loaded.training_record == {"runs": rec_a["runs"]}
    assert [[c.to_json() for c in r] for r in loaded.training_rigs] == run["rigs"]
    assert _record(loaded.save(tmp_path / "copy")) == rec_a
    # a run from that checkpoint carries its record first, then its own run; best/ is kept at
    # the first validated epoch (2 of 3) here
    monkeypatch.setattr(Trainer, "selection_key", staticmethod(lambda val, by="reranked": (0.0,)))
    cfg_b = _config(
        tiny_world,
        stage2_epochs=2,
        init_checkpoint=str(tmp_path / "a"),
        train_sessions=["s0", "s1"],
        val_sessions=["s2"],
        val_every=4,
        device="cpu",
    )
    tr = train(cfg_b, tmp_path / "b", progress=False)
    assert tr.best is not None and tr.best["epoch"] == 2
    rec_b = _record(tmp_path / "b" / "checkpoint")
    assert rec_b["runs"][0] == run
    mine = rec_b["runs"][1]
    assert mine["init_weights_hash"] == first.model.weights_hash()
    assert (mine["epochs_run"], mine["weights_epoch"], mine["complete"]) == (3, 3, True)
    # best/: its weights' epoch, and the whole run's time (to produce and to select them)
    best = _record(tmp_path / "b" / "best")
    assert best["weights_hash"] == VVLocNet.load(tmp_path / "b" / "best").weights_hash()
    assert best["runs"][1] == {**mine, "weights_epoch": 2}
    assert summarize(best).startswith(f"cpu on {hardware()}; 2 runs, ")
    # resuming a finished run trains nothing and leaves every record as it was
    before = [(tmp_path / "b" / d / "training.json").read_text() for d in ("best", "checkpoint")]
    train(cfg_b, tmp_path / "b", resume=True, progress=False)
    after = [(tmp_path / "b" / d / "training.json").read_text() for d in ("best", "checkpoint")]
    assert after == before
    # ... unless its last process stopped before it brought best/ up: then best/ is brought up
    # from the processes that trained (the resuming one trained nothing and is not added)
    stopped = {**best, "runs": [run, {**mine, "weights_epoch": 2, "complete": False}]}
    (tmp_path / "b" / "best" / "training.json").write_text(json.dumps(stopped))
    train(cfg_b, tmp_path / "b", resume=True, progress=False)
    assert _record(tmp_path / "b" / "best") == best


def test_training_time_adds_up_over_resumed_processes(tiny_world, tmp_path):
    from vvloc.provenance import summarize

    out = tmp_path / "run"
    train(_config(tiny_world, stage2_epochs=0, device="cpu"), out, progress=False)
    (p1,) = _record(out / "checkpoint")["runs"][0]["processes"]
    assert p1["epochs"] == [0, 1] and p1["seconds"] > 0
    # extended by a joint epoch in a second process: both processes are in the record
    train(_config(tiny_world, stage2_epochs=1, device="cpu"), out, resume=True, progress=False)
    (run,) = _record(out / "checkpoint")["runs"]
    first, second = run["processes"]
    assert first == p1 and second["epochs"] == [1, 2] and second["seconds"] > 0
    assert run["seconds"] == pytest.approx(first["seconds"] + second["seconds"], abs=0.11)
    assert run["complete"] and run["epochs_run"] == 2
    # a checkpoint of an earlier vvloc has no record, so no measured time: the record says so
    (out / "checkpoint" / "training.json").unlink()
    again = Trainer(_config(tiny_world, stage2_epochs=1, device="cpu"), out)
    assert again.resume()
    (old,) = again.record_for(2)["runs"]
    assert old["processes"][0] == {"epochs": [0, 2], "seconds": None} and old["seconds"] is None
    assert summarize({"runs": [old]}).endswith("1 run, time not measured for 1 run")
    # an init checkpoint without a record (saved outside a run, or by an earlier vvloc) is
    # named, not invented
    init = str(out / "checkpoint")
    cfg = _config(tiny_world, stage2_epochs=0, init_checkpoint=init, device="cpu")
    runs = Trainer(cfg, tmp_path / "x").record_for(0)["runs"]
    assert runs[0] == {
        "recorded": False,
        "checkpoint": init,
        "weights_hash": VVLocNet.load(init).weights_hash(),
    }
    assert re.search(
        r"; 1 run, \d+\.\d min, after an init checkpoint without a record \(1 run unfinished\)$",
        summarize({"runs": runs}),
    )


def test_a_bad_training_record_is_ignored_with_a_warning_and_never_blocks_the_weights(
    tiny_world, tmp_path
):
    train(_config(tiny_world, stage1_epochs=1, stage2_epochs=0), tmp_path / "a", False)
    record = (tmp_path / "a" / "checkpoint" / "training.json").read_text()
    other = tmp_path / "other"
    torch.manual_seed(1)
    VVLocNet(TrainConfig.from_dict({"dataset": "x", "model": "small"}).model_config()).save(other)
    assert not (other / "training.json").exists()
    bad = {
        record: "describes other weights",
        json.dumps({"format": "vvloc.training", "version": 9}): "expected format",
        "{": "not JSON",
    }
    for text, match in bad.items():
        (other / "training.json").write_text(text)
        with pytest.warns(UserWarning, match=match):
            assert VVLocNet.load(other).training_record == {}
    model = VVLocNet.load(tmp_path / "a" / "checkpoint")
    model.training_record = {"runs": "all of them"}
    with pytest.raises(TypeError, match="training_record"):
        model.save(tmp_path / "never")
    assert not (tmp_path / "never").exists()


def test_a_new_run_never_replaces_what_its_folder_holds(tiny_world, tmp_path):
    from vvloc.train import check_run_folder, train

    cfg = _config(tiny_world, stage1_epochs=1, stage2_epochs=0)
    # a folder with a user's checkpoint/ and notes but no trainer_state.pt: refused, kept
    work = tmp_path / "work"
    (work / "checkpoint").mkdir(parents=True)
    (work / "checkpoint" / "weights.pt").write_text("mine")
    (work / "train_config.yaml").write_text("my notes")
    with pytest.raises(FileExistsError, match=r"is not empty \(checkpoint, train_config.yaml\)"):
        train(cfg, work, progress=False)
    assert (work / "checkpoint" / "weights.pt").read_text() == "mine"
    assert (work / "train_config.yaml").read_text() == "my notes"
    assert sorted(p.name for p in work.iterdir()) == ["checkpoint", "train_config.yaml"]
    # a run folder inside the dataset would read as a session: refused before any work
    for inside in (tiny_world / "sessions", tiny_world):
        with pytest.raises(ValueError, match="lies inside the dataset"):
            train(cfg, inside, progress=False)
    assert sorted(p.name for p in (tiny_world / "sessions").iterdir()) == ["s0", "s1", "s2"]
    # a finished run needs --resume; a new or empty folder trains
    train(cfg, tmp_path / "run", progress=False)
    with pytest.raises(FileExistsError, match="already holds a training run"):
        check_run_folder(cfg, tmp_path / "run", resume=False)
    check_run_folder(cfg, tmp_path / "run", resume=True)
    (tmp_path / "empty").mkdir()
    check_run_folder(cfg, tmp_path / "empty", resume=False)
    # a run of this config stopped before its first trainer_state.pt: a new run starts it again
    stopped = tmp_path / "stopped"
    shutil.copytree(tmp_path / "run", stopped)
    (stopped / "trainer_state.pt").unlink()
    (stopped / "log.jsonl").unlink()
    (stopped / ".checkpoint.partial-0123456789ab").mkdir()
    (stopped / ".trainer_state.pt.0123456789ab.tmp").write_bytes(b"half")
    check_run_folder(cfg, stopped, resume=False)
    train(cfg, stopped, progress=False)
    assert (stopped / "trainer_state.pt").is_file()
    # ... but not one of another config, nor a run whose log says it finished epochs
    other = dataclasses.replace(cfg, seed=cfg.seed + 1)
    (stopped / "trainer_state.pt").unlink()
    with pytest.raises(
        FileExistsError, match=r"not empty \(\.trainer_state\S* checkpoint, log.jsonl, train_config"
    ):
        check_run_folder(other, stopped, resume=False)
    with pytest.raises(FileExistsError, match=r"not empty \(log.jsonl\)"):
        check_run_folder(cfg, stopped, resume=False)


def test_cli_train_says_what_the_weights_were_trained_on(tiny_world, tmp_path):
    import subprocess
    import sys

    import yaml

    from vvloc.provenance import hardware

    cfg = _config(tiny_world, stage1_epochs=1, stage2_epochs=0, device="cpu").to_dict()
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    exe = [sys.executable, "-m", "vvloc.cli", "train", "--config", str(tmp_path / "cfg.yaml")]
    exe += ["--out", str(tmp_path / "run")]
    r = subprocess.run(exe, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert f"trained on: cpu on {hardware()}; 1 run, " in r.stdout
    assert "trained 1 epoch; latest checkpoint" in r.stdout
    # the captured log's progress shows real counts with the losses, and keeps the epoch's
    # last line (a bar refreshed by its losses printed 0/N at every step)
    counts = [
        (int(m[1]), int(m[2]))
        for line in r.stderr.replace("\r", "\n").splitlines()
        if (m := re.search(r"\| (\d+)/(\d+) \[.*loss=", line))
    ]
    assert counts and all(done > 0 for done, _ in counts), r.stderr
    assert counts[-1][0] == counts[-1][1], r.stderr
    # with each loss of its stage (stage 1: the global ones; yaw and tbias join in stage 2)
    shown = [line for line in r.stderr.replace("\r", "\n").splitlines() if "loss=" in line]
    assert any("tri=" in line and "hinge=" in line for line in shown), r.stderr
    assert not any("yaw=" in line for line in shown), r.stderr
    # a finished run of an earlier vvloc (no record), resumed: it says so, and exits cleanly
    (tmp_path / "run" / "checkpoint" / "training.json").unlink()
    r = subprocess.run([*exe, "--resume"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "trained on: no training record for these weights" in r.stdout
    assert "nothing to train: the run had done its 1 epoch;" in r.stdout
    # a longer run resumed says which epochs this call trained
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump({**cfg, "stage2_epochs": 1}))
    r = subprocess.run([*exe, "--resume"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "trained epoch 2 (resumed after epoch 1); latest checkpoint" in r.stdout


def test_the_smoke_config_trains_end_to_end(egl, tmp_path):
    """configs/smoke.yaml, the README's check of the training pipeline: it renders its data,
    trains both stages, validates and writes best/ with a calibration."""
    cfg = TrainConfig.from_yaml(_CONFIGS / "smoke.yaml")
    cfg = TrainConfig.from_dict({**cfg.to_dict(), "dataset": str(tmp_path / "data")})
    train(cfg, tmp_path / "run", progress=False)
    best = tmp_path / "run" / "best"
    model = VVLocNet.load(best)
    assert model.calibration["sessions"] == ["s2"]
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [(rec["epoch"], rec["stage"]) for rec in log] == [(1, 1), (2, 2)]


def test_resume_survives_a_stop_between_the_checkpoint_and_state_writes(
    tiny_world, tmp_path, caplog
):
    cfg = _config(tiny_world, stage1_epochs=2, stage2_epochs=0, steps_per_epoch=2)
    out = tmp_path / "run"
    tr = Trainer(cfg, out)
    tr.run_epoch(progress=False)
    tr.save()  # epoch 1: checkpoint/ and trainer_state.pt agree
    state1 = torch.load(out / "trainer_state.pt", weights_only=False)
    tr.run_epoch(progress=False)
    tr._save_model(tr.checkpoint_dir, tr.epoch)  # epoch 2's weights written, then a stop
    resumed = Trainer(cfg, out)
    with caplog.at_level("WARNING", logger="vvloc.train"):
        assert resumed.resume()
    assert "other weights than the trainer state" in caplog.text
    assert resumed.epoch == 1  # the state's epoch, with the state's own weights
    for k, v in resumed.model.state_dict().items():
        assert torch.equal(v, state1["model"][k])


def test_a_checkpoint_folder_is_swapped_in_whole_and_a_stop_inside_the_swap_is_undone(
    tiny_world, tmp_path, monkeypatch
):
    cfg = _config(tiny_world, stage1_epochs=3, stage2_epochs=0, steps_per_epoch=2)
    out = tmp_path / "run"
    tr = Trainer(cfg, out)
    tr.run_epoch(progress=False)
    tr.save()
    first = VVLocNet.load(out / "checkpoint").weights_hash()
    # a stop while the next epoch's folder is written: checkpoint/ stays epoch 1's, whole
    tr.run_epoch(progress=False)
    real_save = VVLocNet.save

    def stop_after_the_weights(self, directory):
        Path(directory).mkdir(parents=True, exist_ok=True)
        (Path(directory) / "model.safetensors").write_bytes(b"half")
        raise KeyboardInterrupt

    monkeypatch.setattr(VVLocNet, "save", stop_after_the_weights)
    with pytest.raises(KeyboardInterrupt):
        tr.save()
    monkeypatch.setattr(VVLocNet, "save", real_save)
    assert VVLocNet.load(out / "checkpoint").weights_hash() == first
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []
    # a stop between the two renames: the previous folder waits under a hidden name, and a
    # resume puts it back
    (out / "checkpoint").rename(out / ".checkpoint.old-0123456789ab")
    (out / ".checkpoint.partial-ba9876543210").mkdir()
    resumed = Trainer(cfg, out)
    assert resumed.resume() and resumed.epoch == 1
    assert VVLocNet.load(out / "checkpoint").weights_hash() == first
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []


def test_resume_refuses_other_data_and_names_a_differing_key(tiny_world, tmp_path):
    cfg = _config(tiny_world, stage1_epochs=2, stage2_epochs=0, steps_per_epoch=2)
    out = tmp_path / "run"
    tr = Trainer(cfg, out)
    tr.run_epoch(progress=False)
    tr.save()
    # how the run executes may change on resume ...
    assert Trainer(
        _config(tiny_world, stage1_epochs=2, stage2_epochs=0, steps_per_epoch=2, num_workers=1), out
    ).resume()
    # ... what it trains may not, and the message says which key
    said = (
        r"another config \(differing: batch_size; batch_size: 2 in the run, 3 now\); use a new "
        r"--out directory or the same config \(a resume may change num_workers, threads, device"
    )
    with pytest.raises(ValueError, match=said):
        Trainer(
            _config(tiny_world, stage1_epochs=2, stage2_epochs=0, steps_per_epoch=2, batch_size=3),
            out,
        ).resume()
    state = torch.load(out / "trainer_state.pt", weights_only=False)
    torch.save({**state, "data": "0" * 64}, out / "trainer_state.pt")
    with pytest.raises(ValueError, match="the training data changed"):
        Trainer(cfg, out).resume()


def test_resume_takes_the_run_s_dataset_moved_or_named_otherwise(tiny_world, tmp_path, caplog):
    """A dataset folder written as another path, or moved or copied, is the run's when its
    sessions and rig are (it used to be refused as 'another config (differing: dataset)')."""
    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    kw = dict(stage1_epochs=2, stage2_epochs=0, steps_per_epoch=2)
    out = tmp_path / "run"
    tr = Trainer(_config(world, **kw), out)
    tr.run_epoch(progress=False)
    tr.save()
    link = tmp_path / "link"
    link.symlink_to(world)
    with caplog.at_level("WARNING", logger="vvloc.train"):
        resumed = Trainer(_config(link, **kw), out)  # the same folder: nothing to say
        assert resumed.resume() and resumed.epoch == 1
    assert "other dataset folders" not in caplog.text
    copy = tmp_path / "copy"
    shutil.copytree(world, copy)
    with caplog.at_level("WARNING", logger="vvloc.train"):
        assert Trainer(_config(copy, **kw), out).resume()
    assert f"other dataset folders (dataset: {str(world)!r} -> {str(copy)!r})" in caplog.text
    # the same drives with other images (another light, another recording) are not the run's
    relit = tmp_path / "relit"
    shutil.copytree(world, relit)
    first = sorted((relit / "sessions" / "s0" / "front").iterdir())[0]
    with Image.open(first) as img:
        Image.new(img.mode, img.size).save(first)
    with pytest.raises(ValueError, match=r"other dataset folders .*their images differ"):
        Trainer(_config(relit, **kw), out).resume()
    # a state saved before the images were sampled cannot tell
    state = torch.load(out / "trainer_state.pt", weights_only=False)
    torch.save({k: v for k, v in state.items() if k != "images"}, out / "trainer_state.pt")
    with pytest.raises(ValueError, match=r"before the trainer sampled the images it reads"):
        Trainer(_config(copy, **kw), out).resume()
    assert Trainer(_config(world, **kw), out).resume()  # its own folder still resumes
    torch.save(state, out / "trainer_state.pt")
    # a copy whose rig differs is not the run's data, nor one whose poses differ
    rig = json.loads((copy / "rig.json").read_text())
    rig["cameras"][0]["K"][0][0] *= 1.01
    (copy / "rig.json").write_text(json.dumps(rig))
    with pytest.raises(ValueError, match=r"other dataset folders \(dataset: .*the rig"):
        Trainer(_config(copy, **kw), out).resume()
    poses = copy / "sessions" / "s0" / "poses.csv"
    rows = poses.read_text().splitlines()
    first = rows[1].split(",")
    first[1] = str(float(first[1]) + 5.0)
    poses.write_text("\n".join([rows[0], ",".join(first), *rows[2:]]) + "\n")
    with pytest.raises(ValueError, match=r"data changed .*names other dataset folders, dataset"):
        Trainer(_config(copy, **kw), out).resume()


def test_resume_takes_a_renamed_extra_dataset(tiny_world, tmp_path, caplog):
    """An extra dataset's sessions are labelled by its folder's name in the data fingerprint:
    a renamed folder is the run's under its former labels (it read as 'data changed')."""
    world, twin = tmp_path / "world", tmp_path / "twin"
    shutil.copytree(tiny_world, world)
    shutil.copytree(tiny_world, twin)
    kw = dict(stage1_epochs=2, stage2_epochs=0, steps_per_epoch=2)
    out = tmp_path / "run"
    tr = Trainer(_config(world, extra_datasets=[{"dataset": str(twin)}], **kw), out)
    tr.run_epoch(progress=False)
    tr.save()
    renamed = tmp_path / "twin-moved"
    twin.rename(renamed)
    with caplog.at_level("WARNING", logger="vvloc.train"):
        resumed = Trainer(_config(world, extra_datasets=[{"dataset": str(renamed)}], **kw), out)
        assert resumed.resume() and resumed.epoch == 1
    assert f"extra_datasets[0].dataset: {str(twin)!r} -> {str(renamed)!r}" in caplog.text


def test_resume_fingerprints_only_the_sessions_the_run_reads(tiny_world, tmp_path):
    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    cfg = _config(
        world,
        stage1_epochs=2,
        stage2_epochs=0,
        steps_per_epoch=2,
        train_sessions=["s0", "s1"],
        val_sessions=["s2"],
    )
    out = tmp_path / "run"
    tr = Trainer(cfg, out)
    tr.run_epoch(progress=False)
    tr.save()
    saved = torch.load(out / "trainer_state.pt", weights_only=False)["data"]
    assert saved.startswith("v2:")
    assert [label for label, _ in tr._read_sessions()] == ["s0", "s1", "val:s0", "val:s2"]
    # a session another run will use, added to the folder, leaves this run resumable
    shutil.copytree(world / "sessions" / "s2", world / "sessions" / "s9")
    resumed = Trainer(cfg, out)
    assert resumed.resume() and resumed.epoch == 1
    assert resumed.data_fingerprint() == saved
    # a state written before 2026-12-06 (every session of the folder hashed) says why
    state = torch.load(out / "trainer_state.pt", weights_only=False)
    legacy = resumed._legacy_data_fingerprint()
    torch.save({**state, "data": legacy}, out / "trainer_state.pt")
    assert Trainer(cfg, out).resume()  # the folder as it was when that state was written
    shutil.rmtree(world / "sessions" / "s9")
    with pytest.raises(ValueError, match="a session added since counts too"):
        Trainer(cfg, out).resume()
    # a validation session's poses are read: changing them is refused
    torch.save(state, out / "trainer_state.pt")
    poses = world / "sessions" / "s2" / "poses.csv"
    rows = poses.read_text().splitlines()
    head, first = rows[0], rows[1].split(",")
    first[1] = str(float(first[1]) + 5.0)
    poses.write_text("\n".join([head, ",".join(first), *rows[2:]]) + "\n")
    with pytest.raises(ValueError, match="the training data changed"):
        Trainer(cfg, out).resume()


def test_a_non_finite_loss_stops_before_the_step(tiny_world, tmp_path, monkeypatch):
    import vvloc.train.trainer as train_module

    cfg = _config(tiny_world, stage1_epochs=2, stage2_epochs=0, steps_per_epoch=2)
    out = tmp_path / "run"
    tr = Trainer(cfg, out)
    tr.run_epoch(progress=False)
    tr.save()
    good = {k: v.clone() for k, v in tr.model.state_dict().items()}
    real = train_module.training_losses

    def nan_loss(*args, **kwargs):
        loss, parts, correct = real(*args, **kwargs)
        return loss * float("nan"), dataclasses.replace(parts, total=float("nan")), correct

    monkeypatch.setattr(train_module, "training_losses", nan_loss)
    with pytest.raises(FloatingPointError, match=r"non-finite loss .*keeps the last finished"):
        tr.run_epoch(progress=False)
    for k, v in tr.model.state_dict().items():  # no step was taken with it
        assert torch.equal(v, good[k])


def test_a_non_finite_epoch_is_not_saved_and_resume_continues_from_the_last_good_one(
    tiny_world, tmp_path, monkeypatch
):
    cfg = _config(tiny_world, stage1_epochs=3, stage2_epochs=0, steps_per_epoch=2)
    out = tmp_path / "run"
    tr = Trainer(cfg, out)
    real_epoch = Trainer.run_epoch
    calls = {"n": 0}

    def second_epoch_nan(self, progress=True):  # a head or local stage has no per-step check
        rec = real_epoch(self, progress=progress)
        calls["n"] += 1
        if calls["n"] == 2:
            rec["loss_total"] = float("nan")
        return rec

    monkeypatch.setattr(Trainer, "run_epoch", second_epoch_nan)
    with pytest.raises(FloatingPointError, match=r"nothing of this epoch was saved \(--resume"):
        tr.fit(progress=False)
    state = torch.load(out / "trainer_state.pt", weights_only=False)
    assert state["epoch"] == 1  # the last good epoch
    assert [json.loads(x)["epoch"] for x in (out / "log.jsonl").read_text().splitlines()] == [1]
    monkeypatch.setattr(Trainer, "run_epoch", real_epoch)
    again = Trainer(cfg, out)
    assert again.resume() and again.epoch == 1


def test_a_log_line_lost_between_the_save_and_its_write_is_written_on_resume(tiny_world, tmp_path):
    cfg = _config(tiny_world, stage1_epochs=3, stage2_epochs=0, steps_per_epoch=2)
    out = tmp_path / "run"
    tr = Trainer(cfg, out)
    rec = tr.run_epoch(progress=False)
    tr.save(record=rec)
    tr._log_record(rec)
    rec = tr.run_epoch(progress=False)
    tr.save(record=rec)  # epoch 2 saved, then a stop before its log line
    resumed = train(cfg, out, resume=True, progress=False)
    assert resumed.epoch == 3
    epochs = [json.loads(x)["epoch"] for x in (out / "log.jsonl").read_text().splitlines()]
    assert epochs == [1, 2, 3]
    # a finished run resumed again writes nothing twice
    train(cfg, out, resume=True, progress=False)
    assert len((out / "log.jsonl").read_text().splitlines()) == 3


def test_a_torn_last_log_line_is_cut_off_and_written_whole_on_resume(tiny_world, tmp_path):
    cfg = _config(tiny_world, stage1_epochs=2, stage2_epochs=0, steps_per_epoch=2)
    out = tmp_path / "run"
    tr = Trainer(cfg, out)
    rec = tr.run_epoch(progress=False)
    tr.save(record=rec)
    line = json.dumps(to_jsonable(rec), allow_nan=False)
    (out / "log.jsonl").write_text(line[: len(line) // 2])  # killed while appending
    train(cfg, out, resume=True, progress=False)
    lines = (out / "log.jsonl").read_text().splitlines()
    assert [json.loads(x)["epoch"] for x in lines] == [1, 2]  # every line valid JSON


@pytest.mark.parametrize(
    ("key", "value", "match"),
    [
        ("yaw_weight", -1.0, "yaw_weight: expected a finite number >= 0"),
        ("tbias_weight", float("inf"), "tbias_weight: expected a finite number >= 0"),
        ("yaw_gamma", -40.0, "yaw_gamma: expected a finite number > 0"),
        ("grad_clip", float("nan"), "grad_clip: expected a finite number >= 0"),
        ("triplet_margin", float("nan"), "triplet_margin: expected a finite number >= 0"),
        ("threads", -1, "threads: expected an int >= 1"),
        ("seed", 2**45, r"seed: expected < 2\*\*32"),
        (
            "extra_datasets",
            [{"dataset": "y", "train_sessions": "s0"}],
            r"extra_datasets\[0\]\.train_sessions: expected a list",
        ),
        (
            "extra_datasets",
            [{"dataset": "y", "anchor_share": "0.5"}],
            r"extra_datasets\[0\]\.anchor_share: expected a share in \(0, 1\)",
        ),
        ("lr", float("inf"), "lr: expected a finite number > 0"),
        ("local_lr", float("nan"), "local_lr: expected a finite number > 0"),
        ("weight_decay", -0.1, "weight_decay: expected a finite number >= 0"),
        ("hard_fraction", 1.5, r"hard_fraction: expected a value in \[0, 1\]"),
        ("hard_fraction", float("nan"), r"hard_fraction: expected a value in \[0, 1\]"),
        ("revisit_gap", -1, "revisit_gap: expected an int >= 0"),
        ("yaw_theta_p", 2.0, "yaw_theta_p, yaw_theta_n: expected finite"),
        ("yaw_theta_n", float("inf"), "yaw_theta_p, yaw_theta_n: expected finite"),
        ("train_sessions", [], "train_sessions: expected a non-empty list"),
        ("model_overrides", {"grid_sise": 64}, r"model, model_overrides: .*grid_sise"),
        ("model", "tiny", "model, model_overrides: model: expected 'small'"),
        # beyond float's or int64's range: named, not math.isfinite's OverflowError
        ("seed", 10**400, r"seed: expected an int, got 1000.* \(out of range\)"),
        ("lr", 10**400, r"lr: expected a number, got 1000.* \(out of range\)"),
        # checked up front, not by Trainer() or after a trained epoch
        ("extra_datasets", [{"dataset": 5}], r"extra_datasets\[0\]\.dataset: expected a folder"),
        ("neg_radius", float("inf"), r"pos_radius, neg_radius: expected 0 < .* < inf metres"),
        # an int where no int goes is not "out of range"
        ("val_database", 0, r"val_database: expected a str .*got 0$"),
    ],
)
def test_config_values_that_would_train_something_else_are_refused(key, value, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig.from_dict({"dataset": "x", key: value})
    TrainConfig.from_dict({"dataset": "x", "grad_clip": 0.0})  # no clipping: allowed


@pytest.mark.parametrize("raw", [None, "lr", ["dataset", "x"]])
def test_a_config_that_is_no_mapping_is_said_to_be_one(raw):
    with pytest.raises(TypeError, match=r"^config: expected a mapping of keys"):
        TrainConfig.from_dict(raw)  # type: ignore[arg-type]


def test_config_yaml_with_a_key_twice_or_a_key_that_is_no_name_is_refused(tmp_path):
    (tmp_path / "twice.yaml").write_text("lr: 1.0e-4\nlr: 1.0e-2\n")
    with pytest.raises(ValueError, match="found the key 'lr' twice"):
        TrainConfig.from_yaml(tmp_path / "twice.yaml")
    (tmp_path / "nested.yaml").write_text("dataset: x\nsim: {seed: 1, seed: 2}\n")
    with pytest.raises(ValueError, match="found the key 'seed' twice"):
        TrainConfig.from_yaml(tmp_path / "nested.yaml")
    (tmp_path / "int.yaml").write_text("dataset: x\n1: 2\n")
    with pytest.raises(ValueError, match=r"keys must be names, got \[1\]"):
        TrainConfig.from_yaml(tmp_path / "int.yaml")


def test_val_loops_entries_are_checked_before_training(tmp_path):
    base = {"dataset": "x", "train_sessions": ["s0"], "val_sessions": ["s1"], "val_database": "s0"}
    for entry, match in (
        ({"radius": float("nan")}, r"val_loops\[0\]\.radius: expected a finite number > 0"),
        ({"radius": float("inf")}, r"val_loops\[0\]\.radius: expected a finite number > 0"),
        ({"radius": 10**400}, r"val_loops\[0\]\.radius: expected a finite number > 0"),
        ({"dataset": 7}, r"val_loops\[0\]\.dataset: expected a folder path"),
    ):
        loops = [{"dataset": "x2", "sessions": ["s2"], **entry}]
        with pytest.raises(ValueError, match=match):
            TrainConfig.from_dict({**base, "val_loops": loops})


def test_yaml_merge_keys_work_as_in_the_safe_loader(tmp_path):
    (tmp_path / "c.yaml").write_text(
        "dataset: x\nextra_datasets:\n"
        "  - <<: {dataset: y, train_sessions: [s1]}\n    train_sessions: [s0]\n"
    )
    cfg = TrainConfig.from_yaml(tmp_path / "c.yaml")
    assert cfg.extra_datasets == [{"dataset": "y", "train_sessions": ["s0"]}]  # own key wins
    (tmp_path / "c.yaml").write_text(
        "dataset: x\nextra_datasets:\n  - <<: {dataset: y}\n"
        "    train_sessions: [s0]\n    train_sessions: [s1]\n"
    )
    with pytest.raises(ValueError, match="found the key 'train_sessions' twice"):
        TrainConfig.from_yaml(tmp_path / "c.yaml")


def test_a_rig_of_more_cameras_than_the_model_holds_is_refused_by_trainer(tiny_world):
    cfg = _config(tiny_world, model_overrides={"max_cameras": 2})
    with pytest.raises(
        ValueError, match=r"model_overrides.max_cameras: .* for 2 cameras, .* has 4"
    ):
        Trainer(cfg, "unused")


def test_a_config_that_is_a_folder_or_missing_is_named_by_the_cli(tmp_path):
    from typer.testing import CliRunner

    from vvloc.cli import app

    for config, words in ((tmp_path, "is a folder; expected a YAML config file"),
                          (tmp_path / "nope.yaml", "config file not found")):  # fmt: skip
        result = CliRunner().invoke(
            app, ["train", "--config", str(config), "--out", str(tmp_path / "run")]
        )
        assert result.exit_code == 2 and "vvloc train: error: --config: " in result.output
        assert words in result.output and not (tmp_path / "run").exists()


def test_an_empty_or_undecodable_config_file_is_refused(tmp_path):
    # an empty file (or comments alone) started a full run of every default
    for text in ("", "# just a comment\n"):
        (tmp_path / "c.yaml").write_text(text)
        with pytest.raises(ValueError, match=r"c.yaml: empty config \(expected a mapping"):
            TrainConfig.from_yaml(tmp_path / "c.yaml")
    (tmp_path / "c.yaml").write_bytes(b"dataset: caf\xe9\n")
    with pytest.raises(ValueError, match=r"c.yaml: not a UTF-8 text file"):
        TrainConfig.from_yaml(tmp_path / "c.yaml")


def test_resume_without_a_run_is_refused_before_the_world_is_rendered(tmp_path, monkeypatch):
    def render(*a, **k):
        raise AssertionError("rendered")

    monkeypatch.setattr(vvloc.train.trainer, "_ensure_dataset", render)
    cfg = TrainConfig.from_dict(
        {"dataset": str(tmp_path / "world"), "sim": {"sessions": 2, "frames": 4}}
    )
    with pytest.raises(FileNotFoundError, match=r"--resume: no run to resume .* drop --resume"):
        vvloc.train.train(cfg, tmp_path / "new", resume=True)
    (tmp_path / "notarun").mkdir()
    (tmp_path / "notarun" / "notes.txt").write_text("mine")
    with pytest.raises(FileNotFoundError, match=r"holds other files: choose another --out"):
        vvloc.train.train(cfg, tmp_path / "notarun", resume=True)
    assert not (tmp_path / "new").exists() and not (tmp_path / "world").exists()
    # a run of this config stopped in its first epoch: its own train_config.yaml, no
    # trainer_state.pt; "the folder holds other files" sent the user elsewhere
    (tmp_path / "stopped").mkdir()
    (tmp_path / "stopped" / "train_config.yaml").write_text(yaml.safe_dump(cfg.to_dict()))
    with pytest.raises(
        FileNotFoundError, match=r"run stopped before its first epoch ended: drop --resume"
    ):
        vvloc.train.train(cfg, tmp_path / "stopped", resume=True)


def test_a_relative_dataset_path_is_named_as_the_working_directory_reads_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(
        FileNotFoundError,
        match=r"^dataset: nowhere does not exist \(.*nowhere: a relative path is taken from the "
        r"working directory, not the config's folder\)",
    ):
        vvloc.train.data._ensure_dataset("nowhere", None)


def test_sessions_a_sim_section_would_not_render_are_refused_before_rendering(
    tmp_path, monkeypatch
):
    def render(*a, **k):
        raise AssertionError("rendered")

    monkeypatch.setattr("vvloc.sim.simulate_dataset", render)
    cfg = TrainConfig.from_dict(
        {
            "dataset": str(tmp_path / "world"),
            "sim": {"sessions": 3, "frames": 4},
            "train_sessions": ["s0", "s1"],
            "val_sessions": ["s5"],
            "val_database": "s2",
        }
    )
    with pytest.raises(
        ValueError,
        match=r"^val_sessions: \['s5'\] not in .*world \(the sessions its sim section would "
        r"render\); its sessions: s0, s1, s2",
    ):
        Trainer(cfg, tmp_path / "run")
    assert not (tmp_path / "world").exists()


def test_extra_datasets_val_loops_and_init_checkpoint_are_checked_before_rendering(
    tmp_path, monkeypatch
):
    # each of these was found only after the main dataset had been rendered
    import functools

    from vvloc.sim import simulate_dataset  # the real one, before it is replaced

    @functools.wraps(simulate_dataset)  # its signature, which the sim section is checked by
    def render(*a, **k):
        raise AssertionError("rendered")

    monkeypatch.setattr("vvloc.sim.simulate_dataset", render)
    have = tmp_path / "have"
    simulate_dataset(have, sessions=2, frames=3, width=32, height=24, progress=False)
    base = {
        "dataset": str(tmp_path / "world"),
        "sim": {"sessions": 3, "frames": 4},
        "train_sessions": ["s0", "s1"],
        "val_sessions": ["s2"],
        "val_database": "s0",
    }
    cases = [
        (
            {"extra_datasets": [{"dataset": str(tmp_path / "nothere")}]},
            FileNotFoundError,
            r"^extra_datasets\[0\]\.dataset: .*nothere does not exist .* no 'sim' section",
        ),
        (
            {"extra_datasets": [{"dataset": str(have), "train_sessions": ["s5"]}]},
            ValueError,
            r"^extra_datasets\[0\]\.train_sessions: \['s5'\] not in",
        ),
        (
            {
                "extra_datasets": [
                    {
                        "dataset": str(tmp_path / "garage"),
                        "sim": {"scene": "garage", "sessions": 2, "frames": 4},
                        "train_sessions": ["s5"],
                    }
                ]
            },
            ValueError,
            r"^extra_datasets\[0\]\.train_sessions: \['s5'\] not in .*garage \(the sessions",
        ),
        (
            {"val_loops": [{"dataset": str(tmp_path / "gone"), "sessions": ["s1"]}]},
            FileNotFoundError,
            r"^val_loops\[0\]\.dataset: ",
        ),
        (
            {"val_loops": [{"dataset": str(have), "sessions": ["s7"]}]},
            ValueError,
            r"^val_loops\[0\]\.sessions: \['s7'\] not in",
        ),
        (
            {"init_checkpoint": str(tmp_path / "runs" / "typo")},
            FileNotFoundError,
            r"^init_checkpoint: no checkpoint \(config.json\) in",
        ),
    ]
    for extra, err, match in cases:
        with pytest.raises(err, match=match):
            Trainer(TrainConfig.from_dict(base | extra), tmp_path / "run")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["have"]
    # a val_loops entry on the dataset the config renders is checked once it is rendered
    ok = base | {"val_loops": [{"dataset": str(tmp_path / "world"), "sessions": ["s2"]}]}
    with pytest.raises(AssertionError, match="rendered"):
        Trainer(TrainConfig.from_dict(ok), tmp_path / "run")


def test_an_interrupted_train_command_says_where_the_run_stands(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from vvloc.cli import app

    (tmp_path / "c.yaml").write_text(yaml.safe_dump({"dataset": str(tmp_path / "d")}))
    out = tmp_path / "run"

    def stopped(cfg, out_dir, resume=False):
        Path(out_dir).mkdir(exist_ok=True)
        if resume:
            (Path(out_dir) / "trainer_state.pt").write_bytes(b"")
        raise KeyboardInterrupt

    monkeypatch.setattr(vvloc.train, "train", stopped)
    args = ["train", "--config", str(tmp_path / "c.yaml"), "--out", str(out)]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 130
    assert "interrupted; no epoch had finished: rerun without --resume" in r.output, r.output
    r = CliRunner().invoke(app, [*args, "--resume"])
    assert r.exit_code == 130 and "rerun with --resume to continue it" in r.output, r.output


def test_config_types_are_checked_by_name():
    base = {"dataset": "x"}
    cases = {
        "weight_decay": ("1e-5", r"weight_decay: expected a number, got '1e-5' \(a number in"),
        # a quoted whole number was told to write 1.0e-5
        "stage1_epochs": ("2", r"stage1_epochs: expected an int, got '2' .*number as 2 or 1000"),
        "batch_size": (2.5, "batch_size: expected an int"),
        "stage2_epochs": (1.7, "stage2_epochs: expected an int"),
        "train_sessions": ("s0", r"train_sessions: expected a list of session names"),
        "num_workers": (True, "num_workers: expected an int"),
        "triplet_margin": (-0.5, "triplet_margin: expected a finite number >= 0"),
        "neg_radius": (1.0, "pos_radius, neg_radius"),
        # infinite weights and margins gave a non-finite loss at the first step
        "rerank_margin": (float("inf"), "rerank_margin: expected a finite number >= 0"),
        "rerank_weight": (float("inf"), "rerank_weight: expected a finite number >= 0"),
        "tbias_near_slope": (float("inf"), "tbias_near_slope: expected a finite number >= 0"),
        "tbias_near_range": ([0.25, float("inf")], r"tbias_near_range: .* finite"),
    }
    for key, (value, match) in cases.items():
        with pytest.raises(ValueError, match=match):
            TrainConfig.from_dict({**base, key: value})
    # no epoch at all trained nothing and named a checkpoint it never wrote
    with pytest.raises(ValueError, match=r"local_epochs: expected at least one epoch, got 0"):
        TrainConfig.from_dict({**base, "stage1_epochs": 0, "stage2_epochs": 0})
    # NCLT's sessions are named by date, which unquoted YAML reads as dates
    import yaml

    for text, key in (
        ("train_sessions: [2012-01-08]", "train_sessions"),
        ("val_database: 2012-01-08", "val_database"),
    ):
        with pytest.raises(ValueError, match=rf"{key}: expected .*quote .*'2012-01-08'"):
            TrainConfig.from_dict({**base, **yaml.safe_load(text)})
    # on/off read as bools; a list key whose entries were all commented out reads as null
    with pytest.raises(ValueError, match=r"val_database: expected a str .*bool: .*'on'"):
        TrainConfig.from_dict({**base, **yaml.safe_load("val_database: on")})
    for key in ("extra_datasets", "val_loops", "hard_pool_restarts"):
        text = f"{key}:\n  # - commented out\n"
        with pytest.raises(ValueError, match=rf"^{key}: expected .*write \[\] for none"):
            TrainConfig.from_dict({**base, **yaml.safe_load(text)})


def test_validation_without_a_query_near_the_map_is_refused(tiny_world, tmp_path, monkeypatch):
    cfg = _config(tiny_world, train_sessions=["s0", "s1"], val_sessions=["s2"], val_database="s0")
    tr = Trainer(cfg, tmp_path / "run")
    assert validation_query_count(tr.ds, "s0", ["s2"], 1) > 0
    tr.ds = _FarAway(tr.ds)  # every pose of s2 moved 500 m away
    with pytest.raises(ValueError, match="val_sessions: no query of"):
        tr.validate()
    # known from the poses alone: the trainer refuses it before any epoch
    real_open = vvloc.train.trainer.open_dataset
    monkeypatch.setattr(vvloc.train.trainer, "open_dataset", lambda root: _FarAway(real_open(root)))
    with pytest.raises(ValueError, match=r"val_sessions: no query of \['s2'\]"):
        Trainer(cfg, tmp_path / "far")
    assert not (tmp_path / "far").exists()


def test_validation_query_count_is_what_validation_scores(tiny_world):
    tr = Trainer(_config(tiny_world), "unused")
    for every in (1, 3):
        res = validation_recall(tr.model, tr.ds, "s0", ["s1", "s2"], every=every, top_k=3)
        assert validation_query_count(tr.ds, "s0", ["s1", "s2"], every) == res["queries"] > 0


class _FarAway:
    """A dataset whose session s2 lies 500 m east of where it was rendered."""

    def __init__(self, ds):
        self._ds = ds
        self.cameras, self.sessions, self.meta = ds.cameras, ds.sessions, ds.meta

    def __getattr__(self, name):  # everything else as the dataset has it
        return getattr(self._ds, name)

    def session(self, name):
        s = self._ds.session(name)
        if name != "s2":
            return s
        moved = copy.copy(s)
        moved.poses = s.poses + np.array([500.0, 0.0, 0.0])
        return moved


def test_log_lines_are_strict_json(tiny_world, tmp_path):
    cfg = _config(tiny_world, train_sessions=["s0", "s1"], val_sessions=["s2"], stage2_epochs=1)
    train(cfg, tmp_path / "run", progress=False)
    for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines():
        # strict parsers (Node's JSON.parse) refuse NaN: the validation's undefined figures
        json.loads(line, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))


def test_worker_processes_load_the_same_batches_as_the_main_process(tiny_world, tmp_path):
    """Frames loaded (and augmented) in forked DataLoader workers train the same weights and
    hard pool as frames loaded in the main process."""
    runs = {}
    for workers in (0, 2):
        cfg = _config(tiny_world, stage2_epochs=0, num_workers=workers, augment={})
        runs[workers] = train(cfg, tmp_path / f"w{workers}", progress=False)
    a, b = runs[0], runs[2]
    for (name, x), y in zip(
        a.model.state_dict().items(), b.model.state_dict().values(), strict=True
    ):
        assert torch.equal(x, y), name
    assert np.array_equal(a.sampler.hard, b.sampler.hard)


def test_a_run_records_each_distinct_rig_of_its_datasets():
    """An extra dataset of another mounting (same camera count and image size, which batches
    need) adds its rig to the record; one of the dataset's rig adds nothing."""
    from types import SimpleNamespace

    from vvloc.data import Camera
    from vvloc.sim.rig import make_rig

    rig = make_rig(4, 32, 24)
    moved = [Camera(c.name, c.width, c.height, c.K, c.cam_to_ego) for c in rig]
    lifted = moved[0].cam_to_ego.copy()
    lifted[2, 3] += 0.5
    moved[0] = Camera(moved[0].name, 32, 24, moved[0].K, lifted)
    sets = [SimpleNamespace(cameras=c) for c in (rig, make_rig(4, 32, 24), moved)]
    rigs = Trainer._rigs(SimpleNamespace(_datasets=sets))  # type: ignore[arg-type]
    assert rigs == [[c.to_json() for c in rig], [c.to_json() for c in moved]]


def test_a_second_process_training_into_a_run_folder_is_refused(tiny_world, tmp_path):
    """A run folder is held by the process training into it (flock on the folder: nothing is
    left behind); another run into it, resumed or not, is refused before any work."""
    from vvloc.train import run_lock

    cfg = _config(tiny_world, stage1_epochs=1, stage2_epochs=0, device="cpu")
    out = tmp_path / "run"
    out.mkdir()
    with run_lock(out):  # as the other process would hold it
        for resume in (False, True):
            with pytest.raises(ValueError, match="another process is training into"):
                train(cfg, out, resume=resume, progress=False)
        assert list(out.iterdir()) == []
    tr = train(cfg, out, progress=False)  # let go: the folder trains
    assert tr.epoch == 1 and not [p for p in out.iterdir() if p.name.endswith(".lock")]


def test_a_group_sigterm_stops_a_run_with_workers_as_sigterm_not_a_crash(tiny_world, tmp_path):
    # systemd, Slurm and `kill -TERM -PGID` signal every process of the group: the data workers
    # died first and the run ended as "DataLoader worker ... is killed by signal" (exit 1, or
    # 143 with a traceback)
    import signal
    import subprocess
    import sys
    import time

    config = tmp_path / "c.yaml"
    config.write_text(
        f"dataset: {tiny_world}\nmodel: small\nstage1_epochs: 3\nstage2_epochs: 0\n"
        "steps_per_epoch: 200\nbatch_size: 1\nnum_workers: 2\nthreads: 1\n"
    )
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "vvloc.cli", "train", "--config", str(config), "--out", str(out)]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children")
        deadline = time.monotonic() + 120
        while len(children.read_text().split()) < 2:  # the two workers run
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.2)
        time.sleep(1.0)  # batches in flight
        os.killpg(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert "Traceback" not in err and "killed by signal" not in err, err[-2000:]


@pytest.mark.parametrize("failure", ["unreadable image", "non-finite loss"])
def test_a_run_with_workers_that_fails_exits_rather_than_hanging(tiny_world, tmp_path, failure):
    # an error a worker raised (the unreadable image) kept the DataLoader's iterator, and so its
    # workers, alive until the interpreter exited, where multiprocessing signalled each worker
    # once and waited for it forever (the workers let a first SIGTERM pass while their parent
    # lives): the message came, the exit not. The non-finite loss, raised in the main process,
    # did not hang; it is here to keep the workers' shut-down on the main process's errors too
    import signal
    import subprocess
    import sys

    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    extra = "lr: 1.0e+8\ngrad_clip: 0\n" if failure == "non-finite loss" else ""
    if failure == "unreadable image":
        for png in (world / "sessions").glob("*/*/*.png"):
            png.write_bytes(png.read_bytes()[:200])
    config = tmp_path / "c.yaml"
    config.write_text(
        f"dataset: {world}\nmodel: small\nstage1_epochs: 1\nstage2_epochs: 0\n"
        f"steps_per_epoch: 3\nbatch_size: 2\nnum_workers: 1\nthreads: 1\n{extra}"
    )
    cmd = [sys.executable, "-m", "vvloc.cli", "train", "--config", str(config), "--out"]
    proc = subprocess.Popen(
        [*cmd, str(tmp_path / "run")], stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    try:
        _, err = proc.communicate(timeout=180)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        pytest.fail(f"vvloc train hung after: {err[-2000:]}")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    if failure == "unreadable image":
        assert proc.returncode == 2, err[-2000:]
        assert "vvloc train: error: " in err and "not a readable image" in err, err[-2000:]
    else:
        assert proc.returncode == 1, err[-2000:]
        assert "vvloc train: failed: epoch 1, step " in err, err[-2000:]
    assert "Traceback" not in err, err[-2000:]


def test_a_non_finite_loss_in_the_first_epoch_is_one_line_saying_nothing_was_saved(
    tiny_world, tmp_path
):
    import subprocess
    import sys

    config = tmp_path / "c.yaml"
    config.write_text(
        f"dataset: {tiny_world}\nmodel: small\nstage1_epochs: 1\nstage2_epochs: 0\n"
        "steps_per_epoch: 3\nbatch_size: 2\nlr: 1.0e+8\ngrad_clip: 0\n"
    )
    cmd = [sys.executable, "-m", "vvloc.cli", "train", "--config", str(config), "--out"]
    r = subprocess.run([*cmd, str(tmp_path / "run")], capture_output=True, text=True)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert "vvloc train: failed: epoch 1, step " in r.stderr
    assert "no epoch had finished: nothing was saved" in r.stderr
    # ... and nothing is left: its train_config.yaml refused a corrected config's run there
    assert not (tmp_path / "run").exists()
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")  # a folder that held something
    r = subprocess.run([*cmd, str(tmp_path / "mine")], capture_output=True, text=True)
    assert r.returncode == 2 and "is not empty (notes.txt)" in r.stderr, r.stderr[-2000:]
    (tmp_path / "empty").mkdir()  # an empty folder stays, empty
    r = subprocess.run([*cmd, str(tmp_path / "empty")], capture_output=True, text=True)
    assert r.returncode == 1 and not list((tmp_path / "empty").iterdir()), r.stderr[-2000:]


def test_a_bad_sim_section_is_named_as_the_configs_key(tmp_path):
    from vvloc.train.data import _ensure_dataset

    world = tmp_path / "world"
    with pytest.raises(ValueError, match=r"^sim: unknown keys \['frame'\] \(known: \["):
        _ensure_dataset(str(world), {"frame": 10})
    with pytest.raises(ValueError, match=r"^extra_datasets\[1\]\.sim: frames: expected"):
        _ensure_dataset(str(world), {"frames": -5}, "extra_datasets[1].")
    assert not world.exists()


@pytest.mark.parametrize(
    ("sim", "error", "said"),
    [
        ({"lighting": ["sunny"]}, ValueError, r"^sim: lighting: unknown presets \['sunny'\]"),
        ({"frames": 0}, ValueError, r"^sim: frames: expected"),
        ({"scene": "garage", "floor_marking": "signs"}, ValueError, r"^sim: floor_marking: "),
        ({"cameras": 0, "progress": False}, ValueError, r"^sim: cameras: expected"),
        ({"max_roll": 45}, ValueError, r"^sim: max_roll: expected degrees"),
        ({"frames": "600"}, TypeError, r"^sim: frames: expected an int >= 1, got str"),
    ],
)
def test_a_bad_sim_value_is_refused_before_rendering_is_announced(
    tmp_path, caplog, sim, error, said
):
    # the "rendering it" warning came first, then the refusal: a user read that the dataset
    # was being rendered
    from vvloc.train.data import _ensure_dataset

    world = tmp_path / "world"
    with caplog.at_level(logging.INFO, logger="vvloc"), pytest.raises(error, match=said):
        _ensure_dataset(str(world), sim)
    assert not [r for r in caplog.records if "rendering it" in r.getMessage()]
    assert not world.exists()


def test_rendering_a_missing_dataset_is_said_at_the_default_level(tmp_path, caplog):
    # a mistyped dataset path beside a leftover sim section trained on a rendered world, said
    # only with -v
    from vvloc.train.data import _ensure_dataset

    world = tmp_path / "mien"
    sim = {"sessions": 1, "frames": 2, "width": 32, "height": 24, "progress": False}
    with caplog.at_level(logging.WARNING, logger="vvloc"):
        _ensure_dataset(str(world), sim)
    said = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert any(
        f"dataset {world} does not exist: rendering it from the config's sim section (parking, 1 "
        "sessions); for a dataset of your own, check the path and delete the sim section" in m
        for m in said
    ), said
    assert (world / "rig.json").is_file()


@pytest.mark.parametrize(
    "error",
    [
        RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 9 GB."),
        torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB"),
        MemoryError(),
    ],
)
def test_running_out_of_memory_names_the_batch_size_and_what_the_run_keeps(
    tiny_world, tmp_path, monkeypatch, error
):
    import vvloc.train.trainer as train_module

    cfg = _config(tiny_world, stage1_epochs=2, stage2_epochs=0, steps_per_epoch=2, batch_size=3)
    out = tmp_path / "run"
    real = train_module.training_losses
    calls = {"n": 0}

    def second_epoch_oom(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > 2:  # epoch 2's first step
            raise error
        return real(*args, **kwargs)

    monkeypatch.setattr(train_module, "training_losses", second_epoch_oom)
    with pytest.raises(MemoryError) as info:
        train(cfg, out, progress=False)
    text = str(info.value)
    assert "out of memory in epoch 2 (stage 1, batch_size 3 on cpu)" in text
    assert "A smaller batch_size needs less" in text
    assert f"The checkpoint in {out / 'checkpoint'} keeps epoch 1, which --resume" in text
    assert info.value.__cause__ is error
    state = torch.load(out / "trainer_state.pt", weights_only=False)
    assert state["epoch"] == 1
    if isinstance(error, RuntimeError):  # the command says it in one line, exit 1
        from typer.testing import CliRunner

        from vvloc.cli import app

        calls["n"] = 0
        (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(cfg.to_dict()))
        args = ["train", "--config", str(tmp_path / "cfg.yaml"), "--out", str(tmp_path / "cli")]
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 1, result.output
        assert "vvloc train: failed: out of memory in epoch 2" in result.output
        assert "Traceback" not in result.output
    monkeypatch.setattr(train_module, "training_losses", real)
    again = Trainer(cfg, out)
    assert again.resume() and again.epoch == 1


def test_out_of_memory_names_each_stages_batch_key(tiny_world):
    cfg = _config(tiny_world, head_epochs=1, local_epochs=1, head_batch_size=4)
    tr = Trainer(cfg, "unused")
    keys = [tr.batch_option(e) for e in range(tr.total_epochs)]
    assert keys == [
        ("batch_size", 2),
        ("batch_size", 2),
        ("head_batch_size", 4),
        ("local_batch_size", 8),
    ]


def test_other_runtime_errors_pass_through_unchanged(tiny_world, tmp_path, monkeypatch):
    import vvloc.train.trainer as train_module

    def broken(*args, **kwargs):
        raise RuntimeError("mat1 and mat2 shapes cannot be multiplied")

    monkeypatch.setattr(train_module, "training_losses", broken)
    with pytest.raises(RuntimeError, match=r"^mat1 and mat2"):
        train(_config(tiny_world), tmp_path / "run", progress=False)
