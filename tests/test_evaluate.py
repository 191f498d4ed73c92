"""Evaluation metrics, SE(2) helpers, report and plots on hand-made cases."""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path

import numpy as np
import pytest
import torch

from vvloc import evaluate as ev
from vvloc import geometry as geo
from vvloc import viz

DEG = math.pi / 180.0


# ----------------------------------------------------------------------------- geometry


def test_geometry_refuses_what_is_not_real_numbers_by_name():
    # None read as nan, "1" and True as 1.0; complex or huge ints gave numpy's words
    for bad in (None, "1", True, [1j], 10**400):
        with pytest.raises(TypeError, match=r"^angle: expected real numbers"):
            geo.wrap_angle(bad)
    with pytest.raises(TypeError, match=r"^b: expected real numbers \(\.\.\., 3\)"):
        geo.compose([0.0, 0.0, 0.0], [1j, 0, 0])
    with pytest.raises(ValueError, match=r"^a, b: poses of shapes \(2, 3\) and \(3, 3\) do not"):
        geo.compose(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"^pose: expected a rectangular array"):
        geo.inverse([[0.0, 0.0, 0.0], [1.0, 2.0]])
    torch = pytest.importorskip("torch")
    t = torch.tensor([0.0, 0.0, 1.0], requires_grad=True)  # was torch's "Can't call numpy()"
    np.testing.assert_allclose(geo.compose(t, [1.0, 0.0, 0.0]), [math.cos(1), math.sin(1), 1.0])
    assert np.isnan(geo.compose([0.0, 0.0, np.nan], [1.0, 0.0, 0.0])).all()  # NaN passes


def test_wrap_angle_half_open_interval():
    got = geo.wrap_angle([0.0, math.pi, -math.pi, 1.5 * math.pi, -1.5 * math.pi, 7 * math.pi])
    np.testing.assert_allclose(got, [0.0, math.pi, math.pi, -0.5 * math.pi, 0.5 * math.pi, math.pi])
    assert ((got > -math.pi) & (got <= math.pi)).all()
    # the ulp neighbours of ±π and ±3π stay inside (a − π could round to exactly −2π)
    edges = [x for c in (math.pi, -math.pi, 3 * math.pi, -3 * math.pi, -5 * math.pi)
             for x in (math.nextafter(c, -math.inf), c, math.nextafter(c, math.inf))]  # fmt: skip
    got = geo.wrap_angle(edges)
    assert ((got > -math.pi) & (got <= math.pi)).all(), got
    inside = [x for x in edges if -math.pi < x <= math.pi]
    assert list(geo.wrap_angle(inside)) == inside  # bit for bit
    assert isinstance(geo.wrap_angle(1.0), np.float64)


def test_wrap_angle_keeps_the_remainder_of_large_angles():
    # a − 2π·ceil((a − π)/2π) lost it beyond ~1e15 rad (1e16 gave 2.0, 1e17 gave 0.0), where
    # the Rust kernels (f64::rem_euclid) kept it: the two search backends disagreed
    from fractions import Fraction

    two_pi = Fraction(2.0 * math.pi)
    for a in [1e16, 1e17, 3.7e15, 1e300, 2.0**1000 + 2.0**948, 123456789.125, 1e9]:
        for x in (a, -a):
            r = Fraction(x) - two_pi * math.floor(Fraction(x) / two_pi)  # [0, 2π), exact
            want = float(r - two_pi if r > Fraction(math.pi) else r)
            got = geo.wrap_angle(x)
            assert -math.pi < got <= math.pi
            assert got == pytest.approx(want, rel=0, abs=1e-15), x
    assert geo.wrap_angle(1e16) == 2.637242432414304  # vvloc_core::pose::wrap_angle's bits


def test_relative_pose_matches_design_convention():
    # Source faces north at (1, 0); target is 1 m north of it, facing north-west.
    source = np.array([1.0, 0.0, math.pi / 2])
    target = np.array([1.0, 1.0, 3 * math.pi / 4])
    xi = geo.relative(source, target)
    # Target origin is 1 m straight ahead (vehicle +x), yaw difference +45°.
    np.testing.assert_allclose(xi, [1.0, 0.0, math.pi / 4], atol=1e-12)
    np.testing.assert_allclose(geo.compose(source, xi), target, atol=1e-12)


def test_relative_yaw_is_wrapped():
    xi = geo.relative([0.0, 0.0, 179 * DEG], [0.0, 0.0, -179 * DEG])
    np.testing.assert_allclose(xi[2], 2 * DEG, atol=1e-12)


def test_compose_inverse_roundtrip_batched():
    rng = np.random.default_rng(0)
    poses = np.column_stack([rng.normal(size=(20, 2)) * 50, rng.uniform(-np.pi, np.pi, 20)])
    others = np.column_stack([rng.normal(size=(20, 2)) * 50, rng.uniform(-np.pi, np.pi, 20)])
    np.testing.assert_allclose(geo.compose(poses, geo.inverse(poses)), 0.0, atol=1e-9)
    np.testing.assert_allclose(geo.compose(poses, geo.relative(poses, others)), others, atol=1e-9)


def test_geometry_rejects_bad_shapes():
    with pytest.raises(ValueError, match="pose"):
        geo.inverse(np.zeros((4, 2)))


# ----------------------------------------------------------------------------- Recall@N


def _line_map(n: int = 10, spacing: float = 10.0) -> np.ndarray:
    return np.column_stack([np.arange(n) * spacing, np.zeros(n)])


def test_perfect_retrieval_gives_recall_one():
    db = _line_map()
    queries = db + np.array([0.5, 0.5])
    retrieved = np.column_stack([np.arange(10), (np.arange(10) + 1) % 10])
    res = ev.recall_at_n(queries, db, retrieved, top_n=(1, 2))
    assert res.num_kept == res.num_queries == 10
    np.testing.assert_array_equal(res.recall, np.ones((2, 4)))
    assert res.at(1, 2.0) == 1.0


def test_query_without_map_frame_within_2m_is_excluded():
    db = _line_map()
    queries = np.array([[0.0, 1.0], [10.0, 0.0], [45.0, 0.0], [20.0, 2.5]])
    retrieved = np.array([[0], [1], [4], [2]])
    res = ev.recall_at_n(queries, db, retrieved, top_n=(1,))
    # Query 2 is 5 m from any map frame, query 3 is 2.5 m away: both left out.
    np.testing.assert_array_equal(res.kept, [True, True, False, False])
    assert res.num_kept == 2
    np.testing.assert_array_equal(res.recall, np.ones((1, 4)))
    # The excluded query is never "correct", even though its top-1 is within 5 m.
    np.testing.assert_array_equal(res.correct(1, 5.0), [True, True, False, False])


def test_recall_counts_rank_and_radius():
    db = np.array([[0.0, 0.0], [3.0, 0.0], [8.0, 0.0], [100.0, 0.0], [15.0, 0.0]])
    q = np.array([[0.0, 0.0]])
    # Ranked: 100 m, 15 m, 8 m, 3 m, exact.
    res = ev.recall_at_n(q, db, [[3, 4, 2, 1, 0]], top_n=(1, 2, 3, 4, 5))
    expected = {  # (N, radius) -> counted
        (1, 20.0): 0,
        (2, 20.0): 1,
        (2, 10.0): 0,
        (3, 10.0): 1,
        (3, 5.0): 0,
        (4, 5.0): 1,
        (4, 2.0): 0,
        (5, 2.0): 1,
    }
    for (n, r), want in expected.items():
        assert res.at(n, r) == want, (n, r)
    np.testing.assert_array_equal(res.first_hit, [[4, 3, 2, 1]])
    ns, curve = res.curve(5.0)
    np.testing.assert_array_equal(ns, [1, 2, 3, 4, 5])
    np.testing.assert_array_equal(curve, [0, 0, 0, 1, 1])


def test_recall_respects_floors_and_empty_slots():
    db = np.array([[0.0, 0.0], [0.0, 0.0], [50.0, 0.0]])
    db_floors = np.array([0, 1, 1])
    q = np.array([[0.5, 0.0], [50.0, 0.5]])
    q_floors = np.array([1, 0])  # query 1 is on a floor where nothing is near: excluded
    res = ev.recall_at_n(
        q, db, [[0, -1], [2, 1]], query_floors=q_floors, db_floors=db_floors, top_n=(1, 2)
    )
    np.testing.assert_array_equal(res.kept, [True, False])
    # Query 0's top-1 is right above it but on the other floor; slot 2 is empty.
    assert res.at(1, 20.0) == 0.0
    assert res.at(2, 20.0) == 0.0
    res2 = ev.recall_at_n(
        q, db, [[0, 1], [2, 1]], query_floors=q_floors, db_floors=db_floors, top_n=(1, 2)
    )
    assert res2.at(1, 2.0) == 0.0
    assert res2.at(2, 2.0) == 1.0


def test_recall_with_no_kept_query_is_nan_and_summary_is_json():
    res = ev.recall_at_n([[100.0, 0.0]], [[0.0, 0.0]], [[0]], top_n=(1,))
    assert res.num_kept == 0
    assert np.isnan(res.recall).all()
    d = ev.to_jsonable(res)
    assert d["recall"]["1"]["2"] is None
    assert json.loads(json.dumps(d)) == d


@pytest.mark.parametrize(
    ("kwargs", "err", "match"),
    [
        ({"retrieved": [[0, 9]]}, ValueError, "retrieved"),
        ({"retrieved": [[0.0, 1.0]]}, TypeError, "retrieved"),
        ({"query_positions": [[0.0, 0.0, 0.0]]}, ValueError, "query_positions"),
        ({"top_n": (1, 3)}, ValueError, "top_n"),
        ({"radii": (2.0, -1.0)}, ValueError, "radii"),
        # one key of to_dict() and the report: the last value silently won
        ({"radii": (2.0, 2.0000001)}, ValueError, r"^radii: \[2\.0, 2\.0000001\] are one radius"),
        ({"radii": (5.0, 5)}, ValueError, r"^radii: .*labelled \['5'\]"),
        ({"top_n": (1, 1)}, ValueError, r"^top_n: ranks \[1\] listed more than once"),
        ({"query_floors": [0]}, ValueError, "db_floors"),
        ({"db_positions": [[0.0, np.nan], [1.0, 0.0]]}, ValueError, "db_positions"),
    ],
)
def test_recall_rejects_bad_input(kwargs, err, match):
    args = {"query_positions": [[0.0, 0.0]], "db_positions": [[0.0, 0.0], [1.0, 0.0]]}
    args |= {"retrieved": [[0, 1]], "top_n": (1,)}
    args.update(kwargs)
    with pytest.raises(err, match=match):
        ev.recall_at_n(**args)


def test_robustness_tabulates_each_perturbation_in_order():
    db = _line_map(5)
    q = db + np.array([1.0, 0.0])
    good = np.arange(5)[:, None]
    bad = ((np.arange(5) + 2) % 5)[:, None]
    out = ev.evaluate_robustness(q, db, {"none": good, "fog": bad}, top_n=(1,))
    assert list(out) == ["none", "fog"]
    assert out["none"].at(1, 2.0) == 1.0
    assert out["fog"].at(1, 2.0) == 0.0
    assert out["fog"].at(1, 20.0) == pytest.approx(0.6)  # 3 of 5 land 19 m away, 2 wrap 31 m


# ----------------------------------------------------------------------------- AOE / APE


def test_yaw_error_wraps_around():
    yaw, pos = ev.pose_errors([[3.0, 4.0, 179 * DEG]], [[0.0, 0.0, -179 * DEG]])
    np.testing.assert_allclose(yaw, [2.0])
    np.testing.assert_allclose(pos, [5.0])


def test_90_degree_error_lands_in_the_top_percentile():
    gt = np.zeros((4, 3))
    est = np.zeros((4, 3))
    est[:, 2] = np.array([1.0, 2.0, 3.0, 90.0]) * DEG
    est[:, 0] = [0.1, 0.2, 0.3, 10.0]
    acc = ev.pose_accuracy(est, gt, np.ones(4, dtype=bool))
    row = acc["all"]
    assert row["count"] == 4
    assert [row[f"AOE@{p}"] for p in (25, 50, 75)] == pytest.approx([1.0, 2.0, 3.0])
    assert row["AOE@95"] == pytest.approx(90.0)
    assert [row[f"APE@{p}"] for p in (25, 50, 75, 95)] == pytest.approx([0.1, 0.2, 0.3, 10.0])


def test_error_percentiles_inverted_cdf_and_empty():
    np.testing.assert_array_equal(ev.error_percentiles([0, 0, 0, 90], (50, 75, 95)), [0, 0, 90])
    assert np.isnan(ev.error_percentiles([], (50,))).all()
    with pytest.raises(ValueError, match="percentiles"):
        ev.error_percentiles([1.0], (150,))


def test_pose_accuracy_subsets_true_revisit_and_all():
    gt = np.zeros((3, 3))
    est = np.array([[1.0, 0.0, 10 * DEG], [0.0, 2.0, 20 * DEG], [30.0, 0.0, 170 * DEG]])
    correct = np.array([True, True, False])
    kept = np.array([True, True, True])
    acc = ev.pose_accuracy(est, gt, correct, kept=kept, percentiles=(50, 100))
    assert acc["true_revisit"]["count"] == 2
    assert acc["true_revisit"]["AOE@100"] == pytest.approx(20.0)
    assert acc["true_revisit"]["APE@50"] == pytest.approx(1.0)
    assert acc["all"]["count"] == 3
    assert acc["all"]["AOE@100"] == pytest.approx(170.0)
    assert acc["all"]["APE@100"] == pytest.approx(30.0)
    # a query left out (no map frame within the radius) is in the row over every query only
    out = ev.pose_accuracy(est, gt, correct, kept=[True, True, False], percentiles=(50, 100))
    assert out["all"]["count"] == 2 and out["all"]["APE@100"] == pytest.approx(2.0)
    assert out["every_query"]["count"] == 3
    assert out["every_query"]["APE@100"] == pytest.approx(30.0)
    with pytest.raises(TypeError, match="correct"):
        ev.pose_accuracy(est, gt, np.ones(3))
    assert acc["all"]["other_floor"] == 0


def test_recall_against_an_empty_map_with_floors_is_undefined_not_an_error():
    res = ev.recall_at_n(
        [[0.0, 0.0]], np.zeros((0, 2)), [[-1]], top_n=(1,), query_floors=[0], db_floors=[]
    )
    assert res.num_kept == 0 and np.isnan(res.at(1, 2.0))


def test_an_answer_on_another_floor_is_no_accurate_pose():
    # the third query's estimate is perfect in (x, y, yaw) but built on a keyframe of another
    # floor: the "all" row leaves it out and counts it, the true-revisit row never had it
    gt = np.zeros((3, 3))
    est = np.array([[1.0, 0.0, 10 * DEG], [0.0, 2.0, 20 * DEG], [0.0, 0.0, 0.0]])
    same = np.array([True, True, False])
    acc = ev.pose_accuracy(est, gt, [True, True, False], same_floor=same, percentiles=(0, 100))
    assert acc["all"]["count"] == 2 and acc["all"]["other_floor"] == 1
    assert acc["all"]["APE@0"] == pytest.approx(1.0)  # the perfect cross-floor 0 is not in it
    # the row over all queries has it, by its planar error
    assert acc["every_query"]["count"] == 3 and acc["every_query"]["APE@0"] == 0.0
    assert acc["true_revisit"]["count"] == 2
    with pytest.raises(TypeError, match="same_floor"):
        ev.pose_accuracy(est, gt, same, same_floor=np.ones(3))


def test_pose_keyframe_row_is_chosen_without_the_poses_error():
    # four queries built on true revisits; the fourth pose is 5 m off, so snapping reports a
    # far keyframe as its top-1 and the top-1 row leaves it out; the pose-keyframe row keeps it
    gt = np.zeros((4, 3))
    est = np.array([[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.1, 0.1, 0.0], [5.0, 1.0, 0.0]])
    snapped_correct = np.array([True, True, True, False])
    acc = ev.pose_accuracy(
        est, gt, snapped_correct, pose_keyframe_correct=np.ones(4, bool), percentiles=(100,)
    )
    assert list(acc) == ["true_revisit", "pose_keyframe", "all", "every_query"]
    assert acc["true_revisit"]["count"] == 3 and acc["true_revisit"]["APE@100"] < 0.2
    assert acc["pose_keyframe"]["count"] == 4
    assert acc["pose_keyframe"]["APE@100"] == pytest.approx(np.hypot(5.0, 1.0))
    assert "pose_keyframe" not in ev.pose_accuracy(est, gt, snapped_correct)
    text = "\n".join(ev._pose_table({"VVLoc-ML": acc}))
    assert "pose's keyframe a true revisit" in text
    assert "| every query (kept or not, any floor; x-y error) | 4 |" in text


# ----------------------------------------------------------------------------- loop closure


def _tiny_loop_set():
    db = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    q = np.array([[0.0, 1.0], [10.0, 0.5], [50.0, 0.0], [20.0, 1.5]])
    pairs = np.array([[0, 0], [1, 2], [1, 1], [2, 3], [3, 2]])
    dist = np.array([0.1, 0.2, 0.3, 0.4, 0.9])
    return pairs, dist, q, db


def test_precision_recall_f1_on_a_tiny_set():
    curve = ev.loop_closure_curve(*_tiny_loop_set())
    assert curve.num_positive_queries == 3  # query 2 has no map frame within 2 m
    at = curve.at(0.35)
    assert at["accepted"] == 3
    assert at["precision"] == pytest.approx(2 / 3)
    assert at["recall"] == pytest.approx(2 / 3)
    assert at["f1"] == pytest.approx(2 / 3)
    assert np.isnan(at["cfer"])  # no floors given
    s = curve.sweep()
    np.testing.assert_allclose(s["threshold"], [0.1, 0.2, 0.3, 0.4, 0.9])
    np.testing.assert_allclose(s["precision"], [1, 1 / 2, 2 / 3, 1 / 2, 3 / 5])
    np.testing.assert_allclose(s["recall"], [1 / 3, 1 / 3, 2 / 3, 2 / 3, 1])
    np.testing.assert_allclose(s["f1"], [0.5, 0.4, 2 / 3, 4 / 7, 0.75])
    best = curve.best_f1()
    assert best["f1"] == pytest.approx(0.75)
    assert best["threshold"] == pytest.approx(0.9)
    nothing = curve.at(0.05)
    assert nothing["accepted"] == 0 and np.isnan(nothing["precision"])
    assert nothing["recall"] == 0.0
    assert nothing["f1"] == 0.0  # 2TP / (2TP + FP + FN) with TP = FP = 0 < FN (it was nan)


def test_cfer_counts_accepted_pairs_across_floors():
    db = np.array([[0.0, 0.0], [0.0, 0.0]])
    q = np.array([[0.0, 0.5], [0.0, 0.5]])
    pairs = np.array([[0, 0], [0, 1], [1, 1], [1, 0]])
    dist = np.array([0.1, 0.2, 0.3, 0.5])
    curve = ev.loop_closure_curve(pairs, dist, q, db, query_floors=[0, 1], db_floors=[0, 1])
    at = curve.at(0.3)
    assert at["cfer"] == pytest.approx(1 / 3)
    assert at["precision"] == pytest.approx(2 / 3)
    assert at["recall"] == 1.0
    assert curve.at(0.1)["cfer"] == 0.0
    np.testing.assert_allclose(curve.sweep()["cfer"], [0, 1 / 2, 1 / 3, 1 / 2])


def test_operating_point_at_a_fixed_recall():
    curve = ev.loop_closure_curve(*_tiny_loop_set())  # recall 1/3 at 0.1, 2/3 at 0.3, 1 at 0.9
    half = curve.at_recall(0.5)
    assert half["target_recall"] == 0.5 and half["threshold"] == pytest.approx(0.3)
    assert ev.to_jsonable(half) == ev.to_jsonable({"target_recall": 0.5} | curve.at(0.3))
    assert curve.at_recall(1 / 3)["threshold"] == pytest.approx(0.1)  # reached exactly
    assert curve.at_recall(1.0)["accepted"] == 5
    # a detector with every distance doubled has the same operating points at the same recall
    pairs, dist, q, db = _tiny_loop_set()
    scaled = ev.loop_closure_curve(pairs, 2 * dist, q, db)
    assert scaled.at_recall(0.5)["precision"] == half["precision"]
    fl = {"query_floors": [0, 0, 0, 0], "db_floors": [0, 0, 1, 0]}  # pair (1, 2) joins floors
    floors = ev.loop_closure_curve(pairs[:3], dist[:3], q, db, **fl)
    assert floors.at_recall(0.5)["cfer"] == 0.0  # query 0 alone, at 0.1
    assert floors.at_recall(1.0)["cfer"] == pytest.approx(1 / 3)  # query 1 too, at 0.3
    unreached = ev.loop_closure_curve(pairs[:2], dist[:2], q, db, **fl).at_recall(1.0)
    assert unreached["accepted"] == 0 and np.isnan(unreached["cfer"])  # query 1 never detected
    summary = curve.summary(0.35)
    assert [o["target_recall"] for o in summary["at_recall"]] == list(ev.SUMMARY_RECALLS)
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="recall"):
            curve.at_recall(bad)


def test_cross_floor_events_count_runs_of_pairs_once():
    # frames: session 0 (rows 0-3) and session 1 (rows 4-7); floors 0, 0, 1, 0 in each
    pos = np.array([[1.0, 1.0], [3.0, 1.0], [1.0, 1.0], [25.0, 1.0]] * 2)
    floors = np.array([0, 0, 1, 0] * 2)
    sessions = np.repeat([0, 1], 4)
    pairs = np.array(
        [
            [0, 4],  # event A: sessions (0, 1), floor 0, cell (0, 0)
            [1, 4],  # same event (same cell)
            [1, 6],  # joins floors 0 and 1: event A becomes cross-floor
            [4, 0],  # event A again (the session pair is unordered, first keyframe in cell 0, 0)
            [3, 7],  # event B: floor 0, cell (2, 0)
            [0, 1],  # event C: session pair (0, 0)
        ]
    )
    r = ev.cross_floor_events(pairs, pos, floors, sessions)
    assert r["events"] == 3 and r["cross_floor_events"] == 1
    assert r["cfer"] == pytest.approx(1 / 3)
    # no cross-floor event among n: the exact bound 1 - 0.05^(1/n) (rule of three: ≈ 3/n)
    clean = ev.cross_floor_events(pairs[[0, 4, 5]], pos, floors, sessions)
    assert clean["cross_floor_events"] == 0
    assert clean["cfer_upper"] == pytest.approx(1 - 0.05 ** (1 / 3))
    assert r["cfer_upper"] > clean["cfer_upper"]
    bigger = ev.cross_floor_events(pairs, pos, floors, sessions, cell=100.0)
    assert bigger["events"] == 2  # events A and B share a 100 m cell
    none = ev.cross_floor_events(np.zeros((0, 2), np.int64), pos, floors, sessions)
    assert none["events"] == 0 and np.isnan(none["cfer"]) and np.isnan(none["cfer_upper"])


def test_cross_floor_events_rejects_bad_input():
    pos, fl, ses = np.zeros((2, 2)), np.zeros(2, np.int64), np.zeros(2, np.int64)
    with pytest.raises(ValueError, match="pairs"):
        ev.cross_floor_events([[0, 2]], pos, fl, ses)
    with pytest.raises(ValueError, match="floors, sessions"):
        ev.cross_floor_events([[0, 1]], pos, fl[:1], ses)
    with pytest.raises(ValueError, match="confidence"):
        ev.cross_floor_events([[0, 1]], pos, fl, ses, confidence=1.0)
    with pytest.raises(ValueError, match="cell"):
        ev.cross_floor_events([[0, 1]], pos, fl, ses, cell=0.0)
    # cells beyond int64 were cast to one wrapped cell: distinct events merged, with a warning
    far = np.array([[1e300, 0.0], [-1e300, 0.0]])
    with pytest.raises(ValueError, match=r"cell: 1e-10 m cells number more than 2\*\*62"):
        ev.cross_floor_events([[0, 1], [1, 0]], far, fl, np.array([0, 1]), cell=1e-10)


def test_temporal_window_and_causality_define_the_ground_truth():
    pos = np.column_stack([np.r_[np.arange(10.0), 0.5], np.zeros(11)])
    t = np.arange(11.0)
    pairs = np.array([[10, 0], [1, 2]])  # the second pair lies inside the window: ignored
    dist = np.array([0.2, 0.05])
    kw = {"query_times": t, "db_times": t, "time_window": 3.0}
    causal = ev.loop_closure_curve(pairs, dist, pos, pos, causal=True, **kw)
    assert causal.num_positive_queries == 1
    assert causal.distances.tolist() == [0.2]
    at = causal.at(1.0)
    assert at["precision"] == 1.0 and at["recall"] == 1.0
    both = ev.loop_closure_curve(pairs, dist, pos, pos, **kw)
    assert both.num_positive_queries == 4  # frames 0, 1, 2 are revisited later by frame 10
    assert both.at(1.0)["recall"] == pytest.approx(1 / 4)
    summary = ev.to_jsonable(both.summary(1.0))
    assert json.loads(json.dumps(summary)) == summary


def test_a_perfect_self_loop_detector_scores_recall_one():
    # two sessions over five places 20 m apart; the detector lists each revisit once (i < j)
    pos = np.tile(np.arange(5.0)[:, None] * [20.0, 0.0], (2, 1))
    floors, sessions = np.zeros(10, np.int64), np.repeat([0, 1], 5)
    seqs = np.tile(np.arange(5), 2)
    pairs = np.array([[k, k + 5] for k in range(5)])
    curve = ev.self_loop_closure_curve(pairs, np.full(5, 0.05), pos, floors, sessions, seqs, 1)
    assert curve.num_positive_queries == 10  # every frame has a revisit in the other session
    at = curve.at(0.1)
    assert (at["precision"], at["recall"], at["f1"]) == (1.0, 1.0, 1.0)
    # one pair missed: its two frames are not detected, the other eight are
    assert curve.at(0.1) == ev.self_loop_closure_curve(
        pairs[[4, 0, 1, 2, 3]][::-1], np.full(5, 0.05), pos, floors, sessions, seqs, 1
    ).at(0.1)  # (the pairs' order and orientation do not matter)
    four = ev.self_loop_closure_curve(pairs[:4], np.full(4, 0.05), pos, floors, sessions, seqs, 1)
    assert four.at(0.1)["recall"] == pytest.approx(0.8)
    # a pair exactly at the threshold: accepted by the sweep's rule (≤), not by the loop
    # detector's at its radius (strict: <), in the pair counts and the recall alike
    tie = ev.self_loop_closure_curve(
        pairs, np.array([0.05] * 4 + [0.1]), pos, floors, sessions, seqs, 1
    )
    assert (tie.at(0.1)["accepted"], tie.at(0.1)["recall"]) == (5, 1.0)
    strict = tie.at(0.1, strict=True)
    assert (strict["accepted"], strict["recall"]) == (4, pytest.approx(0.8))
    assert tie.summary(0.1, strict=True)["at_threshold"] == strict
    # the one-sided reading (the pair's first frame only) is what causal / query-map data get
    one_sided = ev.loop_closure_curve(pairs, np.full(5, 0.05), pos, pos)
    assert one_sided.at(0.1)["recall"] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="symmetric"):
        ev.loop_closure_curve(pairs[:4], np.full(4, 0.05), pos, pos[:9], symmetric=True)
    # without times a frame is still not its own revisit: three places 50 m apart have none
    far = np.arange(3.0)[:, None] * [50.0, 0.0]
    alone = ev.loop_closure_curve(np.zeros((0, 2), np.int64), np.zeros(0), far, far, symmetric=True)
    assert alone.num_positive_queries == 0


def test_the_summary_keeps_a_thinned_sweep():
    rng = np.random.default_rng(5)
    pos = rng.uniform(0, 50, (400, 2))
    pairs = np.unique(rng.integers(0, 400, (3200, 2)), axis=0)[:3000]  # each pair once
    curve = ev.loop_closure_curve(pairs, rng.random(3000), pos, pos)
    full = curve.sweep()
    summary = curve.summary(0.5)
    thin = summary["sweep"]
    assert len(thin["threshold"]) <= ev.SUMMARY_SWEEP_POINTS + 2 < len(full["threshold"])
    # first and last thresholds kept, the rest a subsequence of the full sweep
    assert thin["threshold"][0] == full["threshold"][0]
    assert thin["threshold"][-1] == full["threshold"][-1]
    idx = np.searchsorted(full["threshold"], thin["threshold"])
    for key in ("precision", "recall", "f1", "cfer"):
        np.testing.assert_array_equal(thin[key], full[key][idx])
    # the best F1 is kept exactly, and no recall gap is wider than a level's step (+ 1 pair)
    assert np.nanmax(thin["f1"]) == np.nanmax(full["f1"])
    step = full["recall"][-1] / (ev.SUMMARY_SWEEP_POINTS // 2 - 1)
    jumps = np.diff(full["recall"]).max()
    assert np.diff(thin["recall"]).max() <= step + jumps + 1e-12
    small = ev.thin_sweep({"a": [1.0, 2.0]}, 256)
    assert small["a"].tolist() == [1.0, 2.0]


def test_loop_closure_rejects_bad_input():
    pairs, dist, q, db = _tiny_loop_set()
    with pytest.raises(ValueError, match="distances"):
        ev.loop_closure_curve(pairs, dist[:2], q, db)
    with pytest.raises(ValueError, match="pairs"):
        ev.loop_closure_curve(pairs + 10, dist, q, db)
    with pytest.raises(ValueError, match="times"):
        ev.loop_closure_curve(pairs, dist, q, db, query_times=np.arange(4.0))
    # a pair listed twice would count twice (precision 3/4 for one true and one false pair)
    listed = np.concatenate([pairs, pairs[:1], pairs[:1]])
    with pytest.raises(
        ValueError, match=r"pairs: each pair is listed once; \(\d+, \d+\) .* 3 times"
    ):
        ev.loop_closure_curve(listed, np.concatenate([dist, dist[:2]]), q, db)


def test_loop_closure_truth_and_positives_agree_at_the_radius():
    # 1.2^2 + 1.6^2 rounds to 4.000...1 while its norm rounds to 2.0: the tree left the query
    # out of the positives while the pair counted as a true loop (recall nan, precision 1)
    q, d = np.array([[5.7, 2.1]]), np.array([[6.9, 3.7]])
    assert np.linalg.norm(q - d) == 2.0
    curve = ev.loop_closure_curve(np.array([[0, 0]]), np.array([0.1]), q, d, radius=2.0)
    at = curve.at(0.2)
    assert at["precision"] == 1.0 and at["recall"] == 1.0


def test_symmetric_loop_closure_refuses_a_pair_listed_twice():
    pos = np.array([[0.0, 0.0], [0.5, 0.0], [50.0, 0.0]])
    pairs = np.array([[0, 1], [1, 0]])
    with pytest.raises(ValueError, match="each pair is listed once"):
        ev.loop_closure_curve(pairs, np.array([0.1, 0.1]), pos, pos, symmetric=True)
    once = ev.loop_closure_curve(pairs[:1], np.array([0.1]), pos, pos, symmetric=True).at(0.2)
    assert once["accepted"] == 1 and once["recall"] == 1.0


def test_loop_closure_without_candidates():
    _, _, q, db = _tiny_loop_set()
    curve = ev.loop_closure_curve(np.zeros((0, 2), np.int64), np.zeros(0), q, db)
    assert curve.sweep()["f1"].size == 0
    assert np.isnan(curve.best_f1()["f1"])


# ----------------------------------------------------------------------------- loop pose


def _loop_pose_case():
    gt = np.zeros((4, 3))
    est = np.zeros((4, 3))
    est[:, 2] = np.array([1.0, 4.0, 6.0, 10.0]) * DEG
    est[:, 0] = [0.5, 1.9, 2.0, 3.0]
    costs = np.array([0.1, 0.5, 0.75, 0.9])
    return est, gt, costs


def test_rr_thresholds_and_means():
    est, gt, costs = _loop_pose_case()
    out = ev.loop_pose_metrics(est, gt, costs)
    a = out["all"]
    assert a["count"] == 4
    assert a["mRRE_deg"] == pytest.approx(5.25)
    assert a["mRTE_m"] == pytest.approx(1.85)
    assert a["RR_rot"] == 0.5  # 6° and 10° fail
    assert a["RR_trans"] == 0.5  # 2.0 m is not < 2 m


def test_confidence_filter_keeps_costs_strictly_below_threshold():
    est, gt, costs = _loop_pose_case()
    c = ev.loop_pose_metrics(est, gt, costs)["confident"]
    assert c["count"] == 2 and c["share"] == 0.5  # the pair at exactly 0.75 is dropped
    assert c["mRRE_deg"] == pytest.approx(2.5)
    assert c["mRTE_m"] == pytest.approx(1.2)
    assert c["RR_rot"] == 1.0 and c["RR_trans"] == 1.0
    assert "confident" not in ev.loop_pose_metrics(est, gt)


def test_cross_floor_loop_pairs_register_nothing():
    # four pairs with perfect poses, the last joining two floors at the same x-y
    est = gt = np.zeros((4, 3))
    costs = np.array([0.1, 0.2, 0.3, 0.4])
    same = np.array([True, True, True, False])
    m = ev.loop_pose_metrics(est, gt, costs, same_floor=same)
    for row in (m["all"], m["confident"]):
        assert row["count"] == 4 and row["cross_floor"] == 1
        assert row["RR_rot"] == 0.75 and row["RR_trans"] == 0.75  # not registered
        assert row["mRRE_deg"] == 0.0 and row["mRTE_m"] == 0.0  # means over one floor
    assert ev.loop_pose_metrics(est, gt, costs)["all"]["RR_rot"] == 1.0  # floors unknown
    curve = ev.confidence_curve(costs, np.zeros(4), np.zeros(4), same_floor=same)
    np.testing.assert_allclose(curve["RR_trans"], [1.0, 1.0, 1.0, 0.75])
    np.testing.assert_allclose(curve["mRTE_m"], 0.0)
    only = ev.confidence_curve([0.1], [3.0], [1.0], same_floor=[False])
    assert np.isnan(only["mRRE_deg"]).all() and only["RR_rot"].tolist() == [0.0]


def test_confidence_curve():
    est, gt, costs = _loop_pose_case()
    rre, rte = ev.relative_pose_errors(est, gt)
    order = [3, 0, 2, 1]  # shuffled input: the curve sorts by cost
    curve = ev.confidence_curve(costs[order], rre[order], rte[order])
    np.testing.assert_allclose(curve["threshold"], costs)
    np.testing.assert_allclose(curve["kept_share"], [0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(curve["mRRE_deg"], [1.0, 2.5, 11 / 3, 5.25])
    np.testing.assert_allclose(curve["RR_trans"], [1.0, 1.0, 2 / 3, 0.5])
    # a signed rotation error would average -30 and 1 to -14.5 and count -30 as registered
    with pytest.raises(ValueError, match=r"rre_deg: expected absolute errors .*-30"):
        ev.confidence_curve([0.1, 0.2], [-30.0, 1.0], [0.5, 0.5])
    with pytest.raises(ValueError, match=r"rte_m: expected absolute errors"):
        ev.confidence_curve([0.1, 0.2], [30.0, 1.0], [0.5, -0.5])


def test_confidence_curve_keeps_tied_costs_together():
    # costs [0.5, 0.5, 0.2]: thresholds 0.2 then 0.5, the two pairs at 0.5 kept at once
    curve = ev.confidence_curve([0.5, 0.5, 0.2], [4.0, 8.0, 1.0], [0.5, 3.0, 0.1])
    np.testing.assert_allclose(curve["threshold"], [0.2, 0.5])
    np.testing.assert_allclose(curve["kept_share"], [1 / 3, 1.0])
    np.testing.assert_allclose(curve["mRRE_deg"], [1.0, 13 / 3])
    np.testing.assert_allclose(curve["RR_rot"], [1.0, 2 / 3])
    np.testing.assert_allclose(curve["RR_trans"], [1.0, 2 / 3])


def test_pose_errors_wrap_yaws_given_outside_the_half_open_interval():
    # 359° against 1°, −719.5° against 1°, 540° against −180°: 2°, 0.5°, 0°
    est = np.radians([[0, 0, 359.0], [0, 0, -719.5], [0, 0, 540.0]])
    gt = np.radians([[0, 0, 1.0], [0, 0, 1.0], [0, 0, -180.0]])
    yaw, pos = ev.pose_errors(est, gt)
    np.testing.assert_allclose(yaw, [2.0, 0.5, 0.0], atol=1e-9)
    np.testing.assert_allclose(pos, 0.0)


def test_pose_accuracy_true_revisit_row_leaves_out_queries_not_kept():
    # a query marked correct but not kept (no map frame within 2 m) stays out of true_revisit
    gt = np.zeros((3, 3))
    est = np.array([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [40.0, 0.0, 0.0]])
    acc = ev.pose_accuracy(est, gt, [True, True, True], kept=[True, True, False])
    assert acc["true_revisit"]["count"] == 2 and acc["true_revisit"]["APE@95"] == 2.0
    assert acc["all"]["count"] == 2 and acc["every_query"]["count"] == 3
    assert acc["every_query"]["APE@95"] == 40.0


def test_loop_closure_curve_flags_are_bools():
    # causal="no" is truthy: it scored as causal=True (no pair) without a word
    pos = np.c_[np.arange(5.0), np.zeros(5)]
    pairs = [[0, 0], [1, 2], [2, 4]]
    for key in ("causal", "symmetric"):
        with pytest.raises(TypeError, match=f"{key}: expected a bool, got str"):
            ev.loop_closure_curve(pairs, [0.1, 0.1, 0.1], pos, pos, **{key: "no"})
    assert (
        ev.loop_closure_curve(pairs, [0.1] * 3, pos, pos, causal=np.bool_(False)).at(1.0)[
            "accepted"
        ]
        == ev.loop_closure_curve(pairs, [0.1] * 3, pos, pos).at(1.0)["accepted"]
    )


def test_relative_pose_errors_consistent_with_geometry():
    src = np.array([[5.0, 5.0, 170 * DEG], [0.0, 0.0, 0.0]])
    tgt = np.array([[6.0, 4.0, -170 * DEG], [3.0, 4.0, 90 * DEG]])
    gt = geo.relative(src, tgt)
    est = gt + np.array([[0.0, 0.0, 0.0], [0.3, -0.4, 0.0]])
    est[0, 2] = geo.wrap_angle(gt[0, 2] + 179 * DEG + 180 * DEG)  # −1° after wrapping
    rre, rte = ev.relative_pose_errors(est, gt)
    np.testing.assert_allclose(rre, [1.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(rte, [0.0, 0.5], atol=1e-12)


# ----------------------------------------------------------------------------- latency, report


def test_latency_summary():
    out = ev.latency_summary({"encoder": [4.0, 1.0, 3.0, 2.0], "retrieval": []})
    assert out["encoder"] == {"count": 4, "mean_ms": 2.5, "median_ms": 2.0, "p95_ms": 4.0}
    assert out["retrieval"]["count"] == 0 and np.isnan(out["retrieval"]["mean_ms"])


def _full_metrics():
    db = _line_map()
    q = db + np.array([0.5, 0.5])
    q[3] = [300.0, 0.0]
    retrieved = np.column_stack([np.arange(10), (np.arange(10) + 1) % 10])
    reranked = retrieved.copy()
    retrieved[0] = [1, 0]
    g = ev.recall_at_n(q, db, retrieved, top_n=(1, 2))
    ml = ev.recall_at_n(q, db, reranked, top_n=(1, 2))
    gt = np.column_stack([q, np.zeros(10)])
    est = gt + np.linspace(0, 0.2, 30).reshape(10, 3)
    est_l, gt_l, costs = _loop_pose_case()
    curve = ev.loop_closure_curve(*_tiny_loop_set())
    return {
        "meta": {"checkpoint": "runs/x", "hardware": "test"},
        "global_localization": {"VVLoc-G": g, "VVLoc-ML": ml},
        "pose_accuracy": {"VVLoc-ML": ev.pose_accuracy(est, gt, ml.correct(), kept=ml.kept)},
        "loop_closure": {"s1": curve.summary(0.35)},
        "loop_pose": {"s1": ev.loop_pose_metrics(est_l, gt_l, costs)},
        "robustness": ev.evaluate_robustness(
            q, db, {"none": reranked, "fog": retrieved}, top_n=(1, 2)
        ),
        "robustness_pose": {"fog": ev.pose_accuracy(est, gt, ml.correct(), kept=ml.kept)},
        "latency": ev.latency_summary({"encoder": [10.0, 12.0], "retrieval": [0.5, 0.7]}),
        "notes": ["hand-made data"],
    }


def test_write_report_markdown_and_json(tmp_path):
    metrics = _full_metrics()
    fig = viz.plot_recall_curves(
        tmp_path / "fig" / "recall.png", {"G": (np.arange(1, 4), [0.5, 0.7, 0.9])}
    )
    md, js = ev.write_report(tmp_path, metrics, figures={"Recall@N": fig})
    assert md.exists() and js.exists()
    data = json.loads(js.read_text())
    assert data == json.loads(
        json.dumps(ev.to_jsonable(metrics) | {"figures": {"Recall@N": "fig/recall.png"}})
    )
    assert data["global_localization"]["VVLoc-G"]["num_kept"] == 9
    assert data["global_localization"]["VVLoc-G"]["recall"]["1"]["2"] == pytest.approx(8 / 9)
    assert data["loop_closure"]["s1"]["at_threshold"]["cfer"] is None
    text = md.read_text()
    for heading in (
        "Global localization",
        "AOE@50% (°)",
        "Precision@2m (%)",
        "mRRE (°), same floor",
        "mRRE and mRTE are means over the n pairs less those across floors",
        "Robustness",
        "Latency per stage",
        "![Recall@N](fig/recall.png)",
    ):
        assert heading in text, heading
    assert "| VVLoc-G | 9/10 | 88.9 | 88.9 | 100.0 | 100.0 | 100.0 |" in text
    assert "| VVLoc-ML | 9/10 | 100.0 |" in text
    # the "kept" column is defined once, under the first recall table, with the keep radius
    assert data["global_localization"]["VVLoc-G"]["eligibility_radius_m"] == 2.0
    assert text.count("*kept*: queries with a map frame within 2 m of their true position") == 1
    assert text.index("*kept*") < text.index("## Metric pose accuracy")
    row = "| s1 | ≤ 0.350 | 3 | 66.7 | 66.7 | 0.667 | – | – | – | – | – / – / – | 0.750 | 0.900 |"
    assert row in text
    # how AOE/APE@p are taken is said under their table
    assert text.count("(the inverted-CDF percentile, no interpolation") == 1
    # events: their CFER, not only its bound (the point estimate was in the JSON alone)
    events = {"events": 87, "cross_floor_events": 5, "cfer": 5 / 87, "cfer_upper": 0.117}
    curve = data["loop_closure"]["s1"] | {"events": events}
    rendered = ev.render_markdown({"loop_closure": {"s1": curve}})
    assert "| CFER (%) | events | CFER, events (%) | CFER 95 % bound, events (%) |" in rendered
    assert "| 87 | 5.75 | 11.70 |" in rendered  # CFER to 0.01 %: 0.26 % is a target
    # the bound's level and the recall targets as the results hold them (95 % was printed)
    other = curve | {"events": events | {"confidence": 0.9}}
    other["at_recall"] = [{"target_recall": 0.3, "cfer": 0.0012}]
    rendered = ev.render_markdown({"loop_closure": {"s1": other}})
    assert "| CFER 90 % bound, events (%) | CFER at Recall@2m 30 % (%) |" in rendered
    assert "| 11.70 | 0.12 |" in rendered
    assert "| s1 | cost < 0.75 | 2 | 0 | 2.50 | 1.20 | 100.0 | 100.0 |" in text
    # the accept rule of each threshold: the row's as it was computed (summary's default ≤,
    # the detector's < with strict), the sweep's ≤
    assert "| name | accepted at distance | accepted |" in text
    assert "| best-F1 threshold (accepted: distance ≤ it) |" in text
    detector = ev.loop_closure_curve(*_tiny_loop_set()).summary(0.35, strict=True)
    strict = ev.render_markdown({"loop_closure": {"s1": detector}})
    assert "| s1 | < 0.350 |" in strict
    old = json.loads(json.dumps(data["loop_closure"]["s1"]))  # a report of before the rule
    old["at_threshold"].pop("strict")
    assert "| s1 | 0.350 |" in ev.render_markdown({"loop_closure": {"s1": old}})
    # the robustness pose rows are named by perturbation
    robust = text[text.index("## Robustness (metric pose accuracy") :]
    assert "| perturbation | queries | n |" in robust
    assert "| fog | top-1 true revisit |" in robust
    assert "| method | queries | n |" in text[: text.index("## Loop closure")]
    assert not list(tmp_path.glob(".*.tmp"))


def test_report_header_says_which_world_and_when_there_is_none():
    rendered = ev.render_markdown({"meta": {"scene": {"scene": "garage", "floors": 2}}})
    assert "- **scene**: scene: garage, floors: 2" in rendered
    own = ev.render_markdown({"meta": {"dataset": "data/mine", "scene": None}})
    assert "- **scene**: – (not rendered by vvloc sim)" in own and "None" not in own
    # the report's scene of a dataset of one's own: its rig.json's meta.scene, as it is (a dict
    # of it printed "scene: scene: mine")
    from vvloc.localize.evaluation import _scene

    assert _scene({"scene": "mine", "seed": 3}) == "mine"
    assert _scene({"operator": "me"}) is None
    sim = {"generator": "vvloc.sim", "scene": "garage", "seed": 0, "floors": 2, "lighting": []}
    assert _scene(sim) == {"scene": "garage", "seed": 0, "floors": 2}
    mine = ev.render_markdown({"meta": {"scene": _scene({"scene": "mine"})}})
    assert "- **scene**: mine\n" in mine


def test_report_and_figure_files_get_the_mode_of_a_plain_open(tmp_path):
    old = os.umask(0o027)
    try:
        md, js = ev.write_report(tmp_path, {"notes": ["x"]})
        fig = viz.plot_recall_curves(tmp_path / "recall.png", {"a": ([1, 5], [0.5, 1.0])})
    finally:
        os.umask(old)
    for p in (md, js, fig):
        assert stat.S_IMODE(p.stat().st_mode) == 0o640, p.name
    assert sorted(q.name for q in tmp_path.iterdir()) == ["recall.png", "report.json", "report.md"]


def test_report_is_deterministic(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for out in (a, b):
        ev.write_report(out, _full_metrics())
        viz.plot_trajectory(
            out / "traj.png", _line_map(), _line_map() + 1.0, np.arange(10) % 2 == 0
        )
    for name in ("report.md", "report.json", "traj.png"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_write_report_rejects_unserialisable(tmp_path):
    with pytest.raises(TypeError, match="JSON"):
        ev.write_report(tmp_path / "out", {"meta": {"x": object()}})
    assert list(tmp_path.iterdir()) == []


def test_write_report_names_what_is_not_its_layout(tmp_path):
    out = tmp_path / "out"
    for metrics, key in (
        ({"global_localization": {"m": 3}}, "global_localization"),
        ({"loop_closure": {"a": 5}}, "loop_closure"),
        ({"pose_accuracy": {"a": [1]}}, "pose_accuracy"),
        ({"latency": [1, 2]}, "latency"),
        ({"notes": 5}, "notes"),
        ({"notes": ["a", 5]}, "notes"),
        ({"meta": [1]}, "meta"),
    ):
        with pytest.raises(TypeError, match=rf"^metrics\['{key}'\]: expected"):
            ev.write_report(out, metrics)
    with pytest.raises(TypeError, match="out_dir: expected a path"):
        ev.write_report(5, {})  # type: ignore[arg-type]
    # "../x" wrote x.md and x.json beside out_dir, not into it
    for stem in ("../x", "a/b", "", "..", "a\\b"):
        with pytest.raises(ValueError, match="stem: expected a plain file name"):
            ev.write_report(out, {}, stem=stem)
    with pytest.raises(TypeError, match="stem: expected a file name"):
        ev.write_report(out, {}, stem=Path("x"))  # type: ignore[arg-type]
    assert list(tmp_path.iterdir()) == []
    md, js = ev.write_report(out, {"notes": "one"}, stem="x.y")
    assert (md.name, js.name, md.parent) == ("x.y.md", "x.y.json", out)


# ----------------------------------------------------------------------------- plots


def test_all_plots_are_written(tmp_path):
    rng = np.random.default_rng(1)
    db = np.column_stack([np.linspace(0, 100, 50), 10 * np.sin(np.linspace(0, 3, 50))])
    q = db[::5] + rng.normal(scale=1.0, size=(10, 2))
    correct = rng.random(10) > 0.3
    kept = np.ones(10, dtype=bool)
    kept[0] = False
    res = ev.recall_at_n(q, db, np.argsort(rng.random((10, 50)), axis=1)[:, :5], top_n=(1, 5))
    loop = ev.loop_closure_curve(*_tiny_loop_set())
    est, gt, costs = _loop_pose_case()
    rre, rte = ev.relative_pose_errors(est, gt)
    hyp = np.stack(np.meshgrid(np.linspace(-3, 3, 7), np.linspace(-3, 3, 7)), -1).reshape(-1, 2)
    paths = [
        viz.plot_recall_curves(
            tmp_path / "recall.png", {"G": res.curve(2.0), "ML": res.curve(5.0)}
        ),
        viz.plot_error_cdfs(tmp_path / "cdf.png", {"ML": rre, "empty": []}, {"ML": rte}),
        viz.plot_precision_recall(tmp_path / "pr.png", {"s1": loop.sweep()}),
        viz.plot_trajectory(
            tmp_path / "traj.png",
            db,
            q,
            correct,
            kept=kept,
            retrieved_positions=db[res.first_hit[:, 0].clip(0)],
        ),
        viz.plot_yaw_cost_curve(
            tmp_path / "yaw.png",
            1 - np.cos(np.linspace(0, 2 * np.pi, 120, endpoint=False) - 1.0),
            estimated_yaw=1.0,
            true_yaw=1.05,
        ),
        viz.plot_translation_costs(
            tmp_path / "trans.svg",
            hyp,
            np.linalg.norm(hyp - [1.0, -0.5], axis=1),
            estimate=[1.0, -0.5],
            truth=[1.1, -0.4],
        ),
        viz.plot_confidence_curve(tmp_path / "conf.pdf", ev.confidence_curve(costs, rre, rte)),
    ]
    for p in paths:
        assert p.exists() and p.stat().st_size > 1000, p
    assert (tmp_path / "recall.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "trans.svg").read_text().lstrip().startswith("<?xml")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in paths)


def test_plots_say_when_nothing_is_left_to_draw_and_svg_is_reproducible(tmp_path, monkeypatch):
    figs = []
    save = viz.save_figure
    monkeypatch.setattr(viz, "save_figure", lambda fig, path: figs.append(fig) or save(fig, path))

    def texts(fig):
        return [t.get_text() for ax in fig.axes for t in ax.texts]

    nan = np.full(5, np.nan)
    viz.plot_recall_curves(tmp_path / "r.png", {"G": (np.arange(1, 6), nan)})
    viz.plot_error_cdfs(tmp_path / "c.png", {"ML": []}, {"ML": [np.nan]})
    viz.plot_precision_recall(
        tmp_path / "p.png", {"s": {"precision": nan, "recall": nan, "f1": nan}}
    )
    viz.plot_confidence_curve(
        tmp_path / "k.png", {"kept_share": [1.0], "mRRE_deg": [0.5], "mRTE_m": [0.2]}
    )
    assert all(any(t.startswith("no data") for t in texts(f)) for f in figs[:3])
    assert figs[3].axes[0].lines[0].get_marker() == "o"  # one verified pair is drawn
    assert not texts(figs[3])
    # pairs verified, every one across floors: the means leave them out, and the plot says so
    viz.plot_confidence_curve(
        tmp_path / "k2.png", {"kept_share": [0.5, 1.0], "mRRE_deg": nan[:2], "mRTE_m": nan[:2]}
    )
    assert texts(figs[-1]) == ["no data: no verified pair on one floor"]
    # Recall@N ticks are whole numbers; the yaw curve covers −180° as well as +180°
    viz.plot_recall_curves(tmp_path / "r2.png", {"G": (np.arange(1, 21), np.linspace(0, 1, 20))})
    ticks = figs[-1].axes[0].get_xticks()
    assert np.allclose(ticks, np.round(ticks))
    for t in (8, 25, 26, 120):  # 2π·60/120 is an ulp below π, 26 puts −180° on a sample
        viz.plot_yaw_cost_curve(tmp_path / "y.png", np.arange(float(t)))
        x = figs[-1].axes[0].lines[0].get_xdata()
        assert x[0] <= -180.0 and x[-1] >= 180.0 and len(x) == t + 2, t
        assert figs[-1].axes[0].get_xlim() == (-180.0, 180.0)
    # the curves of the CDF panel carry their number of queries
    viz.plot_error_cdfs(tmp_path / "c2.png", {"ML, top-1": [1.0, 2.0]}, {"ML, top-1": [0.1]})
    labels = [t.get_text() for t in figs[-1].axes[0].get_legend().get_texts()]
    assert labels == ["ML, top-1 (n = 2)"]
    a = viz.plot_yaw_cost_curve(tmp_path / "a.svg", np.arange(8.0)).read_bytes()
    assert viz.plot_yaw_cost_curve(tmp_path / "b.svg", np.arange(8.0)).read_bytes() == a


def test_plot_rejects_bad_input_without_leaving_files(tmp_path):
    with pytest.raises(ValueError, match="path"):
        viz.plot_yaw_cost_curve(tmp_path / "yaw.jpeg", np.ones(8))
    with pytest.raises(ValueError, match="costs"):
        viz.plot_translation_costs(tmp_path / "t.png", np.zeros((3, 2)), np.zeros(4))
    with pytest.raises(ValueError, match="correct"):
        viz.plot_trajectory(tmp_path / "t.png", np.zeros((3, 2)), np.zeros((2, 2)), [True])
    with pytest.raises(ValueError, match=r"correct: expected shape \(4,\)"):
        viz.plot_trajectory(tmp_path / "t.png", np.zeros((3, 2)), np.zeros((4, 2)), np.eye(2))
    with pytest.raises(TypeError, match="correct: expected bools"):
        viz.plot_trajectory(tmp_path / "t.png", np.zeros((3, 2)), np.zeros((2, 2)), [np.nan, 1])
    with pytest.raises(TypeError, match="kept: expected bools"):
        viz.plot_trajectory(
            tmp_path / "t.png", np.zeros((3, 2)), np.zeros((2, 2)), [1, 0], kept=[2, 0]
        )
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------- vectorised vs literal


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recall_matches_a_literal_loop(seed):
    rng = np.random.default_rng(seed)
    db = rng.uniform(0, 40, size=(30, 2))
    q = rng.uniform(0, 40, size=(25, 2))
    qf, df = rng.integers(0, 2, 25), rng.integers(0, 2, 30)
    retrieved = np.argsort(rng.random((25, 30)), axis=1)[:, :6]
    retrieved[rng.random((25, 6)) < 0.1] = -1
    res = ev.recall_at_n(q, db, retrieved, query_floors=qf, db_floors=df, top_n=(1, 3, 6))
    for i, n in enumerate((1, 3, 6)):
        for j, r in enumerate(ev.DEFAULT_RADII):
            kept = counted = 0
            for a in range(25):
                same = df == qf[a]
                if not (np.linalg.norm(db[same] - q[a], axis=1) <= 2.0).any():
                    continue
                kept += 1
                top = [b for b in retrieved[a, :n] if b >= 0]
                counted += any(np.linalg.norm(db[b] - q[a]) <= r and df[b] == qf[a] for b in top)
            assert res.num_kept == kept
            want = counted / kept if kept else np.nan
            np.testing.assert_allclose(res.recall[i, j], want, equal_nan=True)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_loop_sweep_matches_pointwise_definition(seed):
    rng = np.random.default_rng(seed)
    q = rng.uniform(0, 20, size=(15, 2))
    db = rng.uniform(0, 20, size=(20, 2))
    qf, df = rng.integers(0, 2, 15), rng.integers(0, 2, 20)
    pairs = np.column_stack(np.divmod(rng.choice(15 * 20, 40, replace=False), 20))  # each once
    dist = rng.integers(0, 10, 40) / 10.0  # ties on purpose
    curve = ev.loop_closure_curve(pairs, dist, q, db, query_floors=qf, db_floors=df)
    sweep = curve.sweep()
    positive = {
        a
        for a in range(15)
        for b in range(20)
        if np.linalg.norm(q[a] - db[b]) <= 2 and qf[a] == df[b]
    }
    assert curve.num_positive_queries == len(positive)
    for k, t in enumerate(sweep["threshold"]):
        acc = dist <= t
        true = np.array([np.linalg.norm(q[a] - db[b]) <= 2 and qf[a] == df[b] for a, b in pairs])
        detected = {a for (a, _), ok in zip(pairs[acc], true[acc], strict=True) if ok}
        assert sweep["precision"][k] == pytest.approx(true[acc].mean())
        assert sweep["recall"][k] == pytest.approx(len(detected) / len(positive))
        cross = np.array([qf[a] != df[b] for a, b in pairs[acc]])
        assert sweep["cfer"][k] == pytest.approx(cross.mean())
        at = curve.at(t)
        for key in ("precision", "recall", "f1", "cfer"):
            assert at[key] == pytest.approx(sweep[key][k])


# ----------------------------------------------------------------------------- acceptance


def test_distinctiveness_is_mean_minus_min_per_query():
    got = ev.distinctiveness([[0.4, 0.1, 0.7], [0.3, 0.3, 0.3], [0.5, 0.9, 0.5]])
    np.testing.assert_allclose(got, [0.3, 0.0, 0.13333333333333336], atol=1e-12)
    assert np.all(got >= 0)
    assert ev.distinctiveness([[0.2]]).tolist() == [0.0]
    with pytest.raises(ValueError, match="rerank_costs"):
        ev.distinctiveness(np.zeros((3, 0)))
    with pytest.raises(ValueError, match="non-finite"):
        ev.distinctiveness([[0.1, np.nan]])


def test_calibration_picks_the_lowest_threshold_meeting_the_target_precision():
    score = np.arange(20.0)[::-1]  # 19 … 0, most confident first
    correct = np.array([True] * 12 + [False, True] * 4)
    cal = ev.calibrate_acceptance(score, correct, target_precision=0.9, min_accepted=5)
    # accepting score >= 6 keeps 14 results with 13 right (92.9 %); >= 4 would be 14/16 = 87.5 %
    assert cal["threshold"] == 6.0 and cal["accepted"] == 14
    assert cal["precision"] == pytest.approx(13 / 14) and cal["accepted_share"] == 0.7
    assert cal["base_precision"] == pytest.approx(16 / 20)
    # a target no threshold reaches on enough results accepts nothing
    none = ev.calibrate_acceptance(score, correct, target_precision=1.0, min_accepted=13)
    assert none["threshold"] == math.inf and none["accepted"] == 0
    assert math.isnan(none["precision"])
    # ties: a threshold accepts every result with that score, never half of a tie (the first
    # two results alone would be 100 % right, but the third has the same score)
    tied = ev.calibrate_acceptance(
        [1.0, 1.0, 1.0, 0.0],
        np.array([True, True, False, False]),
        target_precision=0.9,
        min_accepted=1,
    )
    assert tied["threshold"] == math.inf and tied["accepted"] == 0


@pytest.mark.parametrize(
    ("kw", "err", "match"),
    [
        ({"target_precision": 0.0}, ValueError, "target_precision"),
        ({"min_accepted": 0}, ValueError, "min_accepted"),
        ({"min_accepted": 2.5}, TypeError, "min_accepted"),
    ],
)
def test_calibration_rejects_bad_arguments(kw, err, match):
    with pytest.raises(err, match=match):
        ev.calibrate_acceptance([0.1, 0.2], np.array([True, False]), **kw)
    with pytest.raises(TypeError, match="correct"):
        ev.calibrate_acceptance([0.1, 0.2], [1, 0])


def test_recall_top_n_must_be_int_ranks():
    # a float rank was truncated (1.5 → 1) and a str split into digits ("15" → (1, 5))
    q, db = np.zeros((1, 2)), np.zeros((3, 2))
    for bad in ([1.5], "15", [True]):
        with pytest.raises(TypeError, match=r"^top_n: expected a sequence of int ranks"):
            ev.recall_at_n(q, db, [[0, 1, 2]], top_n=bad)
    assert (ev.recall_at_n(q, db, [[0, 1, 2]], top_n=[np.int64(2)]).recall == 1.0).all()
    # the default (1, 5) with K = 3 retrieved: the message said "got (1, 5)" of a top_n the
    # caller never passed
    said = r"got \(1, 5\) \(the default top_n \(1, 5\) needs K >= 5 retrieved per query; "
    with pytest.raises(ValueError, match=said + r"pass top_n=\(1,\) or retrieve more\)$"):
        ev.recall_at_n(q, db, [[0, 1, 2]])
    with pytest.raises(ValueError, match=r"^top_n: expected ranks in 1..K = 3, got \(1, 4\)$"):
        ev.recall_at_n(q, db, [[0, 1, 2]], top_n=(1, 4))


# ----------------------------------------------------------------------------- audit of 2026-12-06


def test_error_percentiles_is_the_exact_inverted_cdf_for_every_percentile():
    # numpy's inverted_cdf rounds p / 100 first: p = 7 of 100 samples gave the 8th smallest
    from fractions import Fraction

    for n in (1, 3, 25, 100, 1000):
        e = np.arange(n, dtype=np.float64)[::-1].copy()  # any order
        for p in (0, 7, 14, 25, 28, 50, 56, 75, 95, 99.9, 100):
            # smallest e with at least p % of the samples <= e, p read as the decimal written
            k = max(math.ceil(Fraction(n) * Fraction(str(p)) / 100), 1)
            assert ev.error_percentiles(e, (p,))[0] == k - 1, (n, p)
    assert ev.error_percentiles(np.arange(100.0), (7,))[0] == 6.0
    assert ev.error_percentiles(np.arange(1000.0), (99.9,))[0] == 998.0


def test_error_percentiles_refuse_a_signed_sample():
    # a signed yaw difference would rank -170 deg below 1 deg: refused, not ranked
    with pytest.raises(ValueError, match=r"errors: expected absolute errors .*1 negative.*-170"):
        ev.error_percentiles([1.0, -170.0, 3.0], (50,))
    np.testing.assert_array_equal(ev.error_percentiles(np.abs([1.0, -170.0, 3.0]), (50,)), [3.0])
    negative = r"samples_ms\['metric'\]: expected durations >= 0 ms, got -0.5"
    with pytest.raises(ValueError, match=negative):
        ev.latency_summary({"metric": [1.0, -0.5]})


def test_error_percentiles_refuse_a_scalar_or_nan_percentile_by_name():
    with pytest.raises(TypeError, match="percentiles: expected a sequence"):
        ev.error_percentiles([1.0, 2.0], 50)
    with pytest.raises(TypeError, match="percentiles: expected a sequence"):
        ev.error_percentiles([1.0, 2.0], "50")
    with pytest.raises(ValueError, match="percentiles: expected a finite value"):
        ev.error_percentiles([1.0, 2.0], [float("nan")])
    with pytest.raises(ValueError, match=r"percentiles: expected values in \[0, 100\]"):
        ev.error_percentiles([1.0, 2.0], [101])


def _two_revisits_one_found() -> ev.LoopClosureCurve:
    q = np.array([[0.0, 0.0], [10.0, 0.0]])
    d = np.array([[0.5, 0.0], [10.5, 0.0]])
    return ev.loop_closure_curve([[0, 0]], [0.3], q, d)  # query 1's revisit never proposed


def test_a_query_whose_revisit_was_never_proposed_is_not_found_at_an_infinite_threshold():
    c = _two_revisits_one_found()
    for strict in (False, True):
        assert c.at(1e9, strict=strict)["recall"] == 0.5
        assert c.at(np.inf, strict=strict)["recall"] == 0.5
        assert c.at(np.inf, strict=strict)["accepted"] == 1
    assert c.sweep()["recall"].max() == 0.5


def test_thresholds_must_be_numbers():
    c = _two_revisits_one_found()
    with pytest.raises(ValueError, match="threshold: expected a number, got nan"):
        c.at(np.nan)
    with pytest.raises(ValueError, match="threshold: expected a number"):
        c.summary(float("nan"))
    for bad in (None, "0.5", True):
        with pytest.raises(TypeError, match="threshold: expected a real number"):
            c.at(bad)
    with pytest.raises(ValueError, match="recall: expected a finite value"):
        c.at_recall(float("nan"))
    with pytest.raises(ValueError, match=r"recall: expected a value in \(0, 1\]"):
        c.at_recall(0.0)
    est = np.zeros((2, 3))
    for bad, err in ((np.nan, ValueError), (None, TypeError), ("0.75", TypeError)):
        with pytest.raises(err, match="cost_threshold"):
            ev.loop_pose_metrics(est, est, [0.1, 0.2], cost_threshold=bad)
    assert (
        ev.loop_pose_metrics(est, est, [0.1, 0.2], cost_threshold=np.inf)["confident"]["count"] == 2
    )
    pos = np.zeros((2, 2))
    for bad, err in (
        (np.nan, ValueError),
        (None, TypeError),
        ("0.9", TypeError),
        (1.0, ValueError),
    ):
        with pytest.raises(err, match="confidence"):
            ev.cross_floor_events([[0, 1]], pos, [0, 0], [0, 1], confidence=bad)
    for bad, err in ((None, TypeError), ("1", TypeError), (np.inf, ValueError), (-1, ValueError)):
        with pytest.raises(err, match="time_window"):
            ev.loop_closure_curve(
                [[0, 0]], [0.3], pos, pos, query_times=[0, 1], db_times=[0, 1], time_window=bad
            )
    for bad, err in ((None, TypeError), ("0.9", TypeError), (np.nan, ValueError)):
        with pytest.raises(err, match="target_precision"):
            ev.calibrate_acceptance([0.1, 0.2], np.array([True, False]), target_precision=bad)


def test_recall_ranks_and_radii_are_checked_where_they_are_read():
    r = ev.recall_at_n(
        np.zeros((1, 2)), np.array([[50.0, 0], [1, 0], [60, 0]]), [[0, 1, 2]], top_n=(1,)
    )
    assert r.at(1, 2.0) == 0.0 and r.at(2, 2.0) == 1.0
    with pytest.raises(TypeError, match="n: expected an int rank"):
        r.at(1.5, 2.0)  # was Recall@2
    with pytest.raises(TypeError, match="radius"):
        r.correct(1, "2")
    with pytest.raises(ValueError, match=r"radius: 3\.0 m is not one of"):
        r.at(1, 3.0)
    with pytest.raises(TypeError, match="radii: expected a sequence"):
        ev.recall_at_n(np.zeros((1, 2)), np.zeros((1, 2)), [[0]], top_n=(1,), radii=2.0)
    with pytest.raises(TypeError, match="top_n: expected a sequence"):
        ev.recall_at_n(np.zeros((1, 2)), np.zeros((1, 2)), [[0]], top_n=1)
    with pytest.raises(ValueError, match=r"retrieved: expected an array of shape .* ragged"):
        ev.recall_at_n(np.zeros((2, 2)), np.zeros((3, 2)), [[0, 1], [2]])


def test_self_loop_closure_curve_checks_its_frame_arrays_by_name():
    pos = np.zeros((3, 2))
    good = dict(floors=[0, 0, 0], sessions=[0, 0, 1], seqs=[0, 1, 0])
    curve = ev.self_loop_closure_curve([[0, 2]], [0.1], pos, window=0, **good)
    assert curve.at(1.0)["true_accepted"] == 1
    for key, bad, err in (
        ("sessions", [0, 0], ValueError),
        ("sessions", ["a", "b", "c"], TypeError),
        ("sessions", [0.5, 0.0, 1.0], TypeError),
        ("seqs", [0.0, np.nan, 1.0], TypeError),
        ("floors", [[0, 0, 0]], ValueError),
    ):
        with pytest.raises(err, match=f"^{key}: expected"):
            ev.self_loop_closure_curve([[0, 2]], [0.1], pos, window=0, **{**good, key: bad})
    for window, err in ((np.nan, TypeError), (-1, ValueError), (1.5, TypeError)):
        with pytest.raises(err, match="window"):
            ev.self_loop_closure_curve([[0, 2]], [0.1], pos, window=window, **good)


def test_self_loop_closure_curve_is_exact_for_any_sequence_numbers():
    # nanosecond stamps or numbers past 2**53: only differences within a session matter, so the
    # temporal neighbours stay neighbours (as floats 2**53 + k rounded into each other)
    pos = np.c_[np.arange(8) * 0.5, np.zeros(8)]
    floors, sessions = np.zeros(8, np.int64), np.repeat([3, 7], 4)
    pairs = np.array([[0, 2], [1, 3], [0, 4], [1, 6], [5, 7]])
    seqs = np.tile(np.arange(4), 2)

    def summary(base: int, window: int) -> dict:
        curve = ev.self_loop_closure_curve(
            pairs, np.full(5, 0.1), pos, floors, sessions, base + seqs, window
        )
        return curve.summary(0.5)

    want = summary(0, 2)
    assert want["at_threshold"]["accepted"] == 2  # the two pairs across sessions
    for base in (2**53, 10**18, -(10**18)):
        assert summary(base, 2) == want
    # one session, a pair two numbers apart under window 1: admissible, a true loop (as floats
    # 10**18 + k, the pair rounded to one time and was dropped as a temporal neighbour)
    one = np.zeros(3, np.int64)
    line = np.c_[np.arange(3) * 0.5, np.zeros(3)]
    for base in (0, 10**18):
        near = ev.self_loop_closure_curve(
            [[0, 2]], [0.1], line, one, one, base + np.arange(3), 1
        ).summary(0.5)
        assert near["at_threshold"]["accepted"] == 1 and near["at_threshold"]["recall"] == 1.0
    # a window wider than any session excludes the same pairs as one just wider than its span
    assert summary(0, 2**62) == summary(0, 4)
    with pytest.raises(ValueError, match="seqs: expected each session's sequence numbers to span"):
        ev.self_loop_closure_curve(
            pairs,
            np.full(5, 0.1),
            pos,
            floors,
            sessions,
            np.array([-(2**62)] * 3 + [2**62] + [0] * 4),
            1,
        )


def test_integer_arguments_beyond_int64_are_refused_not_wrapped():
    # uint64 2**64 - 1 cast to int64 is -1, an empty slot of a retrieval list
    top = np.array([[2**64 - 1, 0]], np.uint64)
    with pytest.raises(ValueError, match="retrieved: expected values that fit int64, got 1844"):
        ev.recall_at_n([[0.0, 0.0]], [[0.0, 0.0], [50.0, 0.0]], top, top_n=(1,))
    ok = ev.recall_at_n(
        [[0.0, 0.0]], [[0.0, 0.0], [50.0, 0.0]], np.array([[0, 1]], np.uint64), top_n=(1,)
    )
    assert ok.first_hit[0, 0] == 0


def test_torch_tensors_are_taken_as_the_kernels_take_them():
    # a tensor that requires grad (a loss's inputs) or in bfloat16 is read, not refused by torch
    yaw = torch.tensor([1.0, 3.0, 2.0], requires_grad=True)
    np.testing.assert_array_equal(ev.error_percentiles(yaw, (50,)), [2.0])
    np.testing.assert_array_equal(ev.error_percentiles(yaw.detach().bfloat16(), (100,)), [3.0])


def test_calibrate_acceptance_of_no_result_accepts_nothing():
    # two empty lists: "correct: expected a bool array of shape (0,), got dtype float64"
    out = ev.calibrate_acceptance([], [])
    assert out["queries"] == 0 and out["threshold"] == math.inf


def test_best_f1_takes_the_lowest_of_equal_f1s():
    # pairs in score order false, true, true, true, false, false, true; 5 positive queries,
    # each true pair detecting another: F1 is exactly 2/3 at thresholds 4 and 7, which
    # 2PR/(P+R) rounded an ulp apart, the later one up (best F1 then reported at 7)
    pattern = [False, True, True, True, False, False, True]
    queries = np.c_[np.arange(5) * 100.0, np.zeros(5)]
    db = [tuple(p) for p in queries]  # a map frame on every query: all 5 are positive
    pairs, detected = [], 0
    for t in pattern:
        qi = detected if t else 0
        detected += t
        db.append((qi * 100.0 + (0.0 if t else 50.0), 0.0))  # on the query, or 50 m off
        pairs.append((qi, len(db) - 1))
    dist = np.arange(1.0, len(pattern) + 1)
    curve = ev.loop_closure_curve(np.array(pairs), dist, queries, np.array(db))
    best = curve.best_f1()
    assert (best["threshold"], best["accepted"]) == (4.0, 4)
    assert (best["precision"], best["recall"]) == (0.75, 0.6)
    assert curve.sweep()["f1"][3] == curve.sweep()["f1"][6]


def test_recall_at_a_radius_close_to_another_reads_its_own_column():
    # np.isclose(2.0, 2.00001) is True: at(1, 2.00001) read the 2 m column
    res = ev.recall_at_n([[0.0, 0.0]], [[2.000005, 0.0], [0.0, 1.0]], [[0]], top_n=(1,),
                         radii=(2.0, 2.00001))  # fmt: skip
    assert (res.at(1, 2.0), res.at(1, 2.00001)) == (0.0, 1.0)
    assert res.at(1, 0.1 + 0.2 + 1.7) == 0.0  # a radius as typed still finds its column


def test_latency_summary_wants_a_mapping():
    with pytest.raises(TypeError, match="samples_ms: expected a mapping"):
        ev.latency_summary([1.0, 2.0])


def test_thin_sweep_refuses_arrays_that_do_not_line_up():
    from vvloc.evaluate import thin_sweep

    with pytest.raises(ValueError, match=r"^sweep: expected arrays of one length, got"):
        thin_sweep({"recall": np.linspace(0, 1, 100), "f1": np.zeros(10)}, 5)  # IndexError
    with pytest.raises(ValueError, match=r"^sweep\['recall'\]: expected a 1-D real array"):
        thin_sweep({"recall": np.ones((3, 2))}, 1)
    with pytest.raises(ValueError, match=r"^sweep\['f1'\]: expected a 1-D real array"):
        thin_sweep({"f1": np.ones(3, complex)}, 1)
    with pytest.raises(ValueError, match=r"^points: expected an int >= 1"):
        thin_sweep({"recall": np.ones(3)}, 0)
    # no recall: thinned by rank (and the best F1) alone
    thin = thin_sweep({"f1": np.r_[np.zeros(99), 1.0], "t": np.arange(100.0)}, 10)
    assert 1.0 in thin["f1"] and len(thin["t"]) <= 12


def test_wrap_angle_gives_nan_for_infinity_without_a_warning():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's 'invalid value' RuntimeWarning was raised
        got = geo.wrap_angle(np.array([np.inf, -np.inf, np.nan, 4.0]))
    assert np.isnan(got[:3]).all() and got[3] == pytest.approx(4.0 - 2 * math.pi)


def test_plots_refuse_percentages_and_signed_errors_naming_them(tmp_path):
    # a recall of 80 (percent) was drawn off the axes: an empty plot with a legend
    with pytest.raises(ValueError, match=r"^curves\['A'\] recall: expected fractions in \[0, 1\]"):
        viz.plot_recall_curves(tmp_path / "r.png", {"A": ([1, 5, 10], [80, 90, 95])})
    with pytest.raises(ValueError, match=r"^errors\['A'\]: expected absolute errors >= 0"):
        viz.plot_error_cdfs(tmp_path / "e.png", {"A": [-10, -5, 5]}, {"A": [1.0]})
    sweep = {"precision": [0.5, 90.0], "recall": [0.1, 0.2], "f1": [0.2, 0.3]}
    with pytest.raises(ValueError, match=r"^curves\['B'\]\['precision'\]: expected fractions"):
        viz.plot_precision_recall(tmp_path / "p.png", {"B": sweep})
    curve = {"kept_share": [0.5, 1.0], "mRRE_deg": [1.0, -2.0], "mRTE_m": [0.1, 0.2]}
    with pytest.raises(ValueError, match=r"^curve\['mRRE_deg'\]: expected absolute errors"):
        viz.plot_confidence_curve(tmp_path / "c.png", curve)
    assert not list(tmp_path.iterdir())
    # NaN (undefined) and fractions draw
    viz.plot_recall_curves(tmp_path / "r.png", {"A": ([1, 5], [float("nan"), 0.9])})
    assert (tmp_path / "r.png").is_file()
