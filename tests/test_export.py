"""Exports: loop-closure CSV, g2o pose graphs and TUM trajectories (content and round trips)."""

from __future__ import annotations

import dataclasses
import io
import itertools
import math
import os
from pathlib import Path

import numpy as np
import pytest

from vvloc.localize import (
    LoopClosures,
    information_from_sigmas,
    read_g2o,
    read_loop_csv,
    read_tum,
    write_g2o,
    write_loop_csv,
    write_tum,
)
from vvloc.localize.export import (
    DEFAULT_LOOP_SIGMAS,
    DEFAULT_ODOMETRY_SIGMAS,
    g2o_text,
    loop_csv_text,
    relative_pose,
    tum_text,
    wrap_angle,
)


def se2(p: np.ndarray) -> np.ndarray:
    c, s = math.cos(p[2]), math.sin(p[2])
    return np.array([[c, -s, p[0]], [s, c, p[1]], [0.0, 0.0, 1.0]])


def loops_fixture() -> LoopClosures:
    return LoopClosures(
        i=np.array([100, 103, 107, 101]),
        j=np.array([108, 110, 102, 111]),
        relative_poses=np.array(
            [[1.5, -0.25, 0.1], [-3.0, 2.0, math.pi], [0.1, 0.2, -3.0], [7.0, 0.0, 4.0]]
        ),
        costs=np.array([0.31, 0.52, 0.9, 0.12]),
        accepted=np.array([True, True, False, True]),
    )


# ---------------------------------------------------------------------------------------------
# SE(2) helpers


def test_relative_pose_follows_design_convention() -> None:
    # The target is 1 m north of a source that faces north: 1 m straight ahead (x forward).
    xi = relative_pose([1.0, 2.0, math.pi / 2], [1.0, 3.0, math.pi])
    np.testing.assert_allclose(xi, [1.0, 0.0, math.pi / 2], atol=1e-12)
    # ...and 1 m east of it is 1 m to the right (y left ⇒ y = -1).
    xi = relative_pose([1.0, 2.0, math.pi / 2], [2.0, 2.0, math.pi / 2])
    np.testing.assert_allclose(xi, [0.0, -1.0, 0.0], atol=1e-12)
    # T_world_t = T_world_s · ξ for random poses.
    rng = np.random.default_rng(0)
    for _ in range(10):
        s, t = rng.uniform(-5, 5, 3), rng.uniform(-5, 5, 3)
        np.testing.assert_allclose(se2(s) @ se2(relative_pose(s, t)), se2(t), atol=1e-12)


def test_wrap_angle_range() -> None:
    a = np.array([-math.pi, math.pi, 3 * math.pi, -3 * math.pi / 2, 0.0, 7.0])
    w = wrap_angle(a)
    assert (w > -math.pi).all() and (w <= math.pi).all()
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
    assert w[0] == math.pi and w[1] == math.pi


# ---------------------------------------------------------------------------------------------
# Loop-closure CSV


def test_loop_csv_content_and_round_trip(tmp_path: Path) -> None:
    loops = loops_fixture()
    path = write_loop_csv(tmp_path / "loops.csv", loops, comments=["threshold: 0.75"])
    lines = path.read_text().splitlines()
    comments = [ln for ln in lines if ln.startswith("#")]
    data = [ln for ln in lines if not ln.startswith("#")]
    assert lines[: len(comments)] == comments  # the header comes first
    text = "\n".join(comments)
    assert "xi_{i->j}" in text and "x forward, y left" in text and "radians" in text
    assert comments[-1] == "# threshold: 0.75"
    assert data[0] == "i,j,x,y,yaw,yaw_deg,cost,accepted"
    assert len(data) == 1 + len(loops)
    first = data[1].split(",")
    assert first[:2] == ["100", "108"] and first[-1] == "1"
    assert float(first[4]) == 0.1 and float(first[5]) == math.degrees(0.1)
    assert data[3].split(",")[-1] == "0"
    # yaw was wrapped to (-pi, pi] on construction: 4.0 rad → 4.0 - 2 pi
    assert float(data[4].split(",")[4]) == pytest.approx(4.0 - 2 * math.pi, abs=1e-15)

    back = read_loop_csv(path)
    for name in ("i", "j", "relative_poses", "costs", "accepted"):
        np.testing.assert_array_equal(getattr(back, name), getattr(loops, name))


PROVENANCE = (
    "model config 0123456789abcdef",
    "model weights " + "ab" * 32,
    "search SearchConfig(half_range=3.0, step=0.6, fine_samples=32, stages=4, shrink=0.5, seed=0)",
)


def test_loop_provenance_is_written_and_read_back_and_kept_by_select(tmp_path: Path) -> None:
    # the model and search settings a pair's pose came from travel with the loops: in the
    # file as comment lines after the conventions, before the caller's comments
    base = loops_fixture()
    assert base.provenance == ()
    loops = LoopClosures(
        base.i, base.j, base.relative_poses, base.costs, base.accepted, list(PROVENANCE)
    )
    assert loops.provenance == PROVENANCE  # a tuple, whatever iterable was given
    # the same lines in another order, or repeated, are the same provenance
    shuffled = [PROVENANCE[2], PROVENANCE[0], PROVENANCE[1], PROVENANCE[0]]
    assert dataclasses.replace(loops, provenance=shuffled).provenance == PROVENANCE
    assert loops.select([2, 0]).provenance == PROVENANCE
    path = write_loop_csv(tmp_path / "l.csv", loops, comments=["map m.h5"])
    lines = path.read_text().splitlines()
    at = [lines.index(f"# {line}") for line in PROVENANCE]
    assert at == sorted(at) and at[-1] + 1 == lines.index("# map m.h5")
    assert read_loop_csv(path).provenance == PROVENANCE
    assert read_loop_csv(write_loop_csv(tmp_path / "b.csv", base)).provenance == ()
    # a comment that reads back as provenance would pass for the loops' own
    with pytest.raises(ValueError, match=r"^comments: 'model weights 00' reads as a provenance"):
        write_loop_csv(tmp_path / "c.csv", base, comments=["map m.h5", "model weights 00"])
    with pytest.raises(ValueError, match=r"^comments: 'model weights 00' reads as a provenance"):
        write_loop_csv(tmp_path / "c.csv", base, comments=(c for c in ["model weights 00"]))
    assert not (tmp_path / "c.csv").exists()
    # a user's comment that is no provenance line, or one after the header, is not taken
    text = path.read_text().replace("# map m.h5", "# model config of the week: v2")
    text += "# model weights " + "cd" * 32 + "\n"
    path.write_text(text)
    assert read_loop_csv(path).provenance == PROVENANCE


def test_loop_csv_refuses_a_loop_from_a_keyframe_to_itself_naming_the_line(tmp_path: Path) -> None:
    one = LoopClosures(i=[0], j=[1], relative_poses=[[0, 0, 0]], costs=[0.1], accepted=[True])
    path = write_loop_csv(tmp_path / "l.csv", one)
    lines = path.read_text().splitlines()
    lines[-1] = "0,0," + lines[-1].split(",", 2)[2]
    path.write_text("\n".join(lines) + "\n")
    want = rf"l.csv:{len(lines)}: malformed loop-closure row: i, j: .* got 0 twice"
    with pytest.raises(ValueError, match=want):
        read_loop_csv(path)


def test_loop_csv_with_no_loops(tmp_path: Path) -> None:
    empty = LoopClosures(i=[], j=[], relative_poses=np.zeros((0, 3)), costs=[], accepted=[])
    back = read_loop_csv(write_loop_csv(tmp_path / "l.csv", empty))
    assert len(back) == 0 and back.relative_poses.shape == (0, 3)


@pytest.mark.parametrize(
    ("kwargs", "exc", "match"),
    [
        ({"i": [[1]]}, ValueError, "i: expected shape"),
        ({"j": [1, 2]}, ValueError, "j: expected shape"),
        ({"relative_poses": np.zeros((1, 2))}, ValueError, "relative_poses"),
        ({"costs": [np.nan]}, ValueError, "costs.*non-finite"),
        ({"accepted": [1]}, TypeError, "accepted.*bool"),
        ({"i": [0.5]}, TypeError, "i: expected an integer"),
        ({"j": np.array([2**63 + 5], np.uint64)}, ValueError, "j: ids beyond int64"),
        # an edge from a vertex to itself: write_g2o wrote what read_g2o refuses
        ({"j": [0]}, ValueError, r"i, j: a loop joins two keyframes, got keyframe 0 to itself"),
        ({"provenance": "model config ab"}, TypeError, "provenance: .*got one str"),
        ({"provenance": 3}, TypeError, "provenance: expected an iterable of str lines, got int"),
        ({"provenance": [b"model config ab"]}, TypeError, "provenance: expected str lines"),
        ({"provenance": ["model config ab\nx"]}, ValueError, "provenance: expected lines"),
        ({"provenance": ["threshold 0.75"]}, ValueError, "got 'threshold 0.75'"),
        # a line break the CSV's comments split at: the line was lost on the way back
        ({"provenance": ["search SearchConfig(a\rb)"]}, ValueError, "provenance: expected"),
        ({"provenance": ["search SearchConfig(a\u2028b)"]}, ValueError, "provenance: expected"),
    ],
)
def test_loop_closures_validate(kwargs: dict, exc: type, match: str) -> None:
    args = {"i": [0], "j": [1], "relative_poses": [[0, 0, 0]], "costs": [0.1], "accepted": [True]}
    with pytest.raises(exc, match=match):
        LoopClosures(**{**args, **kwargs})


def test_information_from_sigmas_refuses_what_is_no_information_matrix() -> None:
    np.testing.assert_allclose(information_from_sigmas(0.5, 0.25, 2.0), np.diag([4, 16, 0.25]))
    # 1e-200 gave inf entries, 1e200 a zero one (a singular matrix), each with only a warning
    for sigmas in ((1e-200, 0.1, 0.05), (0.1, 1e200, 0.05)):
        with pytest.raises(ValueError, match=r"sigmas: 1/sigma\^2 must be a finite float > 0"):
            information_from_sigmas(*sigmas)
    with pytest.raises(ValueError, match=r"sigmas: standard deviations must be > 0"):
        information_from_sigmas(0.1, 0.0, 0.05)
    with pytest.raises(TypeError, match=r"^sigma_x: expected a float, got ndarray"):
        information_from_sigmas(np.array([0.1, 0.2]), 0.1, 0.05)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^sigma_yaw: expected a finite value"):
        information_from_sigmas(0.1, 0.1, np.inf)


# ---------------------------------------------------------------------------------------------
# g2o


def graph_inputs() -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray]:
    rng = np.random.default_rng(3)
    n = 12
    poses = np.column_stack([rng.uniform(-20, 20, (n, 2)), rng.uniform(-math.pi, math.pi, n)])
    ids = np.arange(100, 100 + n)
    sessions = ["a"] * 6 + ["b"] * 6
    seq = np.array([0, 2, 1, 3, 4, 5, 0, 1, 2, 3, 4, 5])  # rows 1 and 2 swapped in time
    return poses, ids, sessions, seq


def test_g2o_round_trip(tmp_path: Path) -> None:
    poses, ids, sessions, seq = graph_inputs()
    loops = loops_fixture()
    rng = np.random.default_rng(4)
    a = rng.normal(size=(len(loops), 3, 3))
    loop_info = a @ np.swapaxes(a, 1, 2) + 3 * np.eye(3)  # per-loop SPD information
    odo_info = information_from_sigmas(0.1, 0.2, 0.01)
    path = write_g2o(
        tmp_path / "graph.g2o",
        poses,
        loops,
        ids=ids,
        sessions=sessions,
        seq=seq,
        odometry_information=odo_info,
        loop_information=loop_info,
    )
    g = read_g2o(path)
    np.testing.assert_array_equal(g.vertex_ids, ids)
    np.testing.assert_array_equal(g.vertex_poses, poses)  # exact: shortest round-trip repr

    # Odometry edges: consecutive keyframes of each session in seq order; then accepted loops.
    rows = [0, 2, 1, 3, 4, 5]
    odo_rows = list(itertools.pairwise(rows)) + [(r, r + 1) for r in range(6, 11)]
    keep = np.flatnonzero(loops.accepted)
    want_edges = [(ids[a], ids[b]) for a, b in odo_rows] + [(loops.i[k], loops.j[k]) for k in keep]
    np.testing.assert_array_equal(g.edges, want_edges)
    n_odo = len(odo_rows)
    for e, (a, b) in enumerate(odo_rows):
        np.testing.assert_allclose(
            se2(poses[a]) @ se2(g.measurements[e]), se2(poses[b]), atol=1e-12
        )
        np.testing.assert_array_equal(g.information[e], odo_info)
    np.testing.assert_array_equal(g.measurements[n_odo:], loops.relative_poses[keep])
    np.testing.assert_array_equal(g.information[n_odo:], loop_info[keep])


def test_g2o_file_has_only_vertex_and_edge_lines_and_default_information(tmp_path: Path) -> None:
    poses, *_ = graph_inputs()
    loops = loops_fixture()
    path = write_g2o(tmp_path / "g.g2o", poses, loops, ids=np.arange(100, 112), only_accepted=False)
    lines = path.read_text().splitlines()
    assert all(ln.split()[0] in ("VERTEX_SE2", "EDGE_SE2") for ln in lines)
    assert all(len(ln.split()) == (5 if ln.startswith("VERTEX") else 12) for ln in lines)
    g = read_g2o(path)
    assert len(g.edges) == 11 + len(loops)  # one session by default; all loops kept
    np.testing.assert_allclose(g.information[0], information_from_sigmas(*DEFAULT_ODOMETRY_SIGMAS))
    np.testing.assert_allclose(g.information[-1], information_from_sigmas(*DEFAULT_LOOP_SIGMAS))
    assert np.diag(g.information[-1]).tolist() == pytest.approx(
        [1 / 0.5**2, 1 / 0.5**2, 1 / math.radians(2.0) ** 2]
    )


def test_read_g2o_skips_comments_and_other_tags(tmp_path: Path) -> None:
    path = tmp_path / "other.g2o"
    path.write_text(
        "# a comment\n\nVERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0.5\nFIX 0\n"
        "EDGE_SE2 0 1 1 0 0.5 10 1 2 20 3 30\n"
    )
    g = read_g2o(path)
    assert g.vertex_ids.tolist() == [0, 1] and g.edges.tolist() == [[0, 1]]
    np.testing.assert_array_equal(g.information[0], [[10, 1, 2], [1, 20, 3], [2, 3, 30]])
    # a file of other lines alone read as an empty graph without a word (a 3D graph, a TUM
    # trajectory); an empty one, or one of comments, is an empty graph
    for name, text, tags in [
        ("3d.g2o", "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nFIX 0\n", "'VERTEX_SE3:QUAT', 'FIX'"),
        ("poses.tum", "# vvloc trajectory\n0.5 1 2 0 0 0 0 1\n", "'0.5'"),
        ("loops.csv", "i,j,x\n1,2,3\n3,4,5\n", "'i,j,x', '1,2,3', '3,4,5'"),
    ]:
        (tmp_path / name).write_text(text)
        with pytest.raises(ValueError, match=rf"{name}: no VERTEX_SE2 or EDGE_SE2 line, only "
                           rf"lines tagged {tags}: not a 2D g2o"):  # fmt: skip
            read_g2o(tmp_path / name)
    (tmp_path / "empty.g2o").write_text("# nothing yet\n\n")
    assert len(read_g2o(tmp_path / "empty.g2o").vertex_ids) == 0


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("VERTEX_SE2 0 0 0\n", ":1: malformed.*VERTEX_SE2"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 1 1\n", ":2: .*repeated"),
        ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0\n", ":1: .*EDGE_SE2"),
        ("VERTEX_SE2 0 x 0 0\n", ":1: malformed"),
        ("VERTEX_SE2 0 0 nan 0\n", ":1: malformed g2o line: y: non-finite value"),
        ("EDGE_SE2 0 1 1 0 0 1 0 0 inf 0 1\n", ":1: malformed g2o line: I22: non-finite value"),
        # an id past int64 was an OverflowError naming no file; past g2o's ints or negative
        ("VERTEX_SE2 99999999999999999999 0 0 0\n", ":1: .*id: 9+ does not fit in a 64-bit"),
        ("VERTEX_SE2 2147483648 0 0 0\n", r":1: .*id: g2o vertex ids lie in \[0, 2147483647\]"),
        ("VERTEX_SE2 -1 0 0 0\n", r":1: .*id: g2o vertex ids lie in \[0, "),
        # numbers C does not read as Python does (1_0 read as 10)
        ("VERTEX_SE2 0 1_0 2 3\n", ":1: .*x: expected a number, got '1_0'"),
        (
            "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1_0 1 0 0 1 0 0 1 0 1\n",
            ":3: .*j: expected an integer",
        ),
        # what write_g2o refuses: self-edges, indefinite information, edges to no vertex
        ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 0 1 0 0 1 0 0 1 0 1\n", ":2: .*from vertex 0 to itself"),
        (
            "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 -1 0 0 -1 0 -1\n",
            ":3: .*not positive definite",
        ),
        (
            "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 5 1 0 0 1 0 0 1 0 1\n",
            ":2: EDGE_SE2 0 5 joins vertex 5, which no VERTEX_SE2 line defines",
        ),
    ],
)
def test_read_g2o_refuses_malformed_lines(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.g2o"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        read_g2o(path)


def test_readers_skip_a_byte_order_mark(tmp_path: Path) -> None:
    # a BOM hid the first line's tag: vertex 0 vanished and its edge still read
    g2o = tmp_path / "bom.g2o"
    g2o.write_text(
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n",
        encoding="utf-8-sig",
    )
    assert read_g2o(g2o).vertex_ids.tolist() == [0, 1]
    tum = tmp_path / "bom.tum"
    tum.write_text("0.5 1 2 0 0 0 0 1\n", encoding="utf-8-sig")
    assert read_tum(tum)[0].tolist() == [0.5]
    loops = LoopClosures(i=[3], j=[4], relative_poses=[[1.0, 0, 0]], costs=[0.2], accepted=[True])
    csv_path = tmp_path / "bom.csv"
    csv_path.write_text(loop_csv_text(loops), encoding="utf-8-sig")
    assert read_loop_csv(csv_path).i.tolist() == [3]


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "no header line"),
        ("# only comments\n", "no header line"),
        ("a,b,c\n", r":1: the header lacks columns \['i', 'j'"),
        ("i,j,x,y,yaw,cost,accepted,i\n1,2,0,0,0,0.1,1,7\n", r":1: .*columns \['i'\] more than"),
        ("i,j,x,y,yaw,cost,accepted\n1,2,0,0,0,0.1,1,EXTRA\n", ":2: .*header's 7 fields, got 8"),
        ("i,j,x,y,yaw,cost,accepted\n1.5,2,0,0,0,0.1,1\n", ":2: .*i: expected an integer"),
        ("i,j,x,y,yaw,cost,accepted\n1,2,0,0,0,0.1,yes\n", ":2: .*accepted: expected 1, 0"),
        ("i,j,x,y,yaw,cost,accepted\n1,2,1_000.5,0,0,0.1,1\n", ":2: .*x: expected a number"),
        ("i,j,x,y,yaw,cost,accepted\n1,99999999999999999999,0,0,0,0.1,1\n", ":2: .*j: .*64-bit"),
        ("# c\ni,j,x,y,yaw,cost,accepted\n\n1,2,0,0,nan,0.1,1\n", ":4: .*yaw: non-finite"),
    ],
)
def test_read_loop_csv_refuses_what_its_writer_never_writes(
    tmp_path: Path, text: str, match: str
) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        read_loop_csv(path)


def test_write_g2o_validates(tmp_path: Path) -> None:
    poses, ids, *_ = graph_inputs()
    loops = loops_fixture()
    out = tmp_path / "g.g2o"
    with pytest.raises(
        ValueError, match=r"loops\.i: ids \[100, 101, 103, 107\] are not vertex ids"
    ):
        write_g2o(out, poses, loops)  # default ids 0..11 hold no loop ids
    with pytest.raises(ValueError, match="symmetric"):
        write_g2o(out, poses, loops, ids=ids, loop_information=np.triu(np.ones((3, 3))))
    with pytest.raises(ValueError, match="positive definite"):
        write_g2o(out, poses, ids=ids, odometry_information=-np.eye(3))
    with pytest.raises(ValueError, match=r"ids.*unique"):
        write_g2o(out, poses, ids=np.zeros(12, np.int64))
    with pytest.raises(ValueError, match="sessions"):
        write_g2o(out, poses, sessions=["a"] * 3)
    with pytest.raises(ValueError, match="poses"):
        write_g2o(out, poses[:, :2])
    with pytest.raises(ValueError, match=r"ids: g2o vertex ids must lie in \[0, 2147483647\]"):
        write_g2o(out, poses, ids=np.arange(-1, 11))  # g2o refuses negative vertex ids
    with pytest.raises(ValueError, match=r"ids: .* got 0\.\.2147483648"):
        write_g2o(out, poses, ids=np.r_[np.arange(11), 2**31])  # g2o's ids are C ints
    with pytest.raises(TypeError, match="only_accepted: expected a bool, got str"):
        write_g2o(out, poses, loops, ids=ids, only_accepted="no")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"sessions: labels must be hashable.*list at row 0"):
        write_g2o(out, poses, sessions=[["a"]] * 12)
    assert os.listdir(tmp_path) == []


def test_write_g2o_wraps_vertex_theta(tmp_path: Path) -> None:
    poses = np.array([[0.0, 0.0, 4.0], [1.0, 0.0, -4.0], [2.0, 0.0, math.pi], [3.0, 0.0, 0.5]])
    g = read_g2o(write_g2o(tmp_path / "g.g2o", poses))
    np.testing.assert_allclose(
        g.vertex_poses[:, 2],
        [4.0 - 2 * math.pi, 2 * math.pi - 4.0, math.pi, 0.5],
        rtol=0,
        atol=1e-15,
    )
    assert g.vertex_poses[2, 2] == math.pi and g.vertex_poses[3, 2] == 0.5  # in range: exact
    # the odometry edges are the same as for the unwrapped poses (relative poses wrap anyway)
    np.testing.assert_allclose(g.measurements, relative_pose(poses[:-1], poses[1:]), atol=1e-12)


# ---------------------------------------------------------------------------------------------
# TUM


def test_tum_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    n = 20
    t = 1.7e9 + np.sort(rng.uniform(0, 100, n))
    yaw = np.concatenate([[math.pi, -math.pi + 1e-9, 0.0], rng.uniform(-math.pi, math.pi, n - 3)])
    poses = np.column_stack([rng.uniform(-100, 100, (n, 2)), yaw])
    z = rng.uniform(0, 2, n)
    path = write_tum(tmp_path / "traj.txt", t, poses, z=z, comments=["session: s1"])
    lines = path.read_text().splitlines()
    assert lines[0].startswith("# vvloc trajectory, TUM format: timestamp tx ty tz qx qy qz qw")
    assert "# session: s1" in lines
    table = np.loadtxt(path, comments="#")  # plain TUM readers skip the '#' header
    assert table.shape == (n, 8)
    np.testing.assert_array_equal(table[:, 0], t)
    np.testing.assert_array_equal(table[:, 3], z)
    np.testing.assert_allclose(np.linalg.norm(table[:, 4:], axis=1), 1.0, atol=1e-15)
    np.testing.assert_array_equal(table[:, 4:6], 0.0)

    assert not any(ln.startswith("# tz = 0") for ln in lines)  # z was given
    t2, poses2 = read_tum(path)
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_array_equal(poses2[:, :2], poses[:, :2])
    dyaw = wrap_angle(poses2[:, 2] - poses[:, 2])
    np.testing.assert_allclose(dyaw, 0.0, atol=1e-12)
    assert (poses2[:, 2] > -math.pi).all() and (poses2[:, 2] <= math.pi).all()


def test_read_tum_heading_of_a_tilted_rotation(tmp_path: Path) -> None:
    # Rotation = yaw 0.7 about z, then a small roll about the vehicle x axis: heading is 0.7.
    yaw, roll = 0.7, 0.2
    qz = np.array([0, 0, math.sin(yaw / 2), math.cos(yaw / 2)])
    qr = np.array([math.sin(roll / 2), 0, 0, math.cos(roll / 2)])
    x1, y1, z1, w1 = qz
    x2, y2, z2, w2 = qr
    q = [
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
    ]
    path = tmp_path / "t.txt"
    path.write_text("0.0 1 2 3 " + " ".join(repr(float(v)) for v in q) + "\n")
    _, poses = read_tum(path)
    assert poses[0].tolist() == pytest.approx([1.0, 2.0, yaw], abs=1e-12)


def test_tum_validation_leaves_no_file(tmp_path: Path) -> None:
    out = tmp_path / "traj.txt"
    out.write_text("old\n")
    with pytest.raises(ValueError, match="poses"):
        write_tum(out, [0.0, 1.0], np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"timestamps.*non-finite"):
        write_tum(out, [0.0, np.inf], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="z"):
        write_tum(out, [0.0, 1.0], np.zeros((2, 3)), z=[1.0, 2.0, 3.0])
    assert out.read_text() == "old\n" and os.listdir(tmp_path) == ["traj.txt"]
    bad = tmp_path / "bad.txt"
    bad.write_text("0 1 2 3 0 0 0\n")
    with pytest.raises(ValueError, match=r"bad\.txt:1: expected 8 fields"):
        read_tum(bad)
    for value in ("nan", "inf", "-inf"):  # refused as the writer refuses them
        bad.write_text(f"# header\n0 1 2 0 0 0 0 1\n1 {value} 2 0 0 0 0 1\n")
        with pytest.raises(ValueError, match=r"bad\.txt:3: malformed TUM line: tx: non-finite"):
            read_tum(bad)


def test_tum_planar_header_and_wrapped_yaw(tmp_path: Path) -> None:
    poses = np.array([[1.0, 2.0, 3 * math.pi / 2], [0.0, 0.0, 0.25]])
    path = write_tum(tmp_path / "traj.txt", [0.0, 1.0], poses)
    lines = path.read_text().splitlines()
    # no height given: the header says tz is 0 because the poses are 3-DoF
    assert any(ln.startswith("# tz = 0: the poses are 3-DoF") for ln in lines)
    table = np.loadtxt(path, comments="#")
    np.testing.assert_array_equal(table[:, 3], 0.0)
    # 3π/2 is written as −π/2: qw = cos(−π/4) > 0, qz = sin(−π/4) < 0
    np.testing.assert_allclose(table[0, 6:], [-math.sqrt(0.5), math.sqrt(0.5)], atol=1e-15)
    np.testing.assert_array_equal(table[1, 6:], [math.sin(0.125), math.cos(0.125)])


def test_write_tum_comments_must_be_lines(tmp_path: Path) -> None:
    with pytest.raises(TypeError, match="comments: expected an iterable of str lines, got int"):
        write_tum(tmp_path / "t.txt", [0.0], [[0.0, 0.0, 0.0]], comments=5)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="comments: expected str lines, got int"):
        write_tum(tmp_path / "t.txt", [0.0], [[0.0, 0.0, 0.0]], comments=[5])  # type: ignore[list-item]
    assert os.listdir(tmp_path) == []
    # one str is one comment (not one line per character)
    path = write_tum(tmp_path / "t.txt", [0.0], [[0.0, 0.0, 0.0]], comments="session: s1")
    assert path.read_text().splitlines().count("# session: s1") == 1
    path = write_loop_csv(tmp_path / "l.csv", loops_fixture(), comments="threshold: 0.75")
    assert path.read_text().splitlines().count("# threshold: 0.75") == 1


def test_text_functions_are_what_the_writers_write(tmp_path: Path) -> None:
    """The CLIs write several files as one change from loop_csv_text, g2o_text and tum_text:
    each text is byte for byte the file its writer writes."""
    loops = loops_fixture()
    poses = np.array([[float(i), 0.5 * i, 0.3 * i - 2.0] for i in range(12)])
    ids = np.arange(100, 112)
    sessions = ["a"] * 6 + ["b"] * 6
    comments = ["map session 'a' of m.h5"]
    write_loop_csv(tmp_path / "l.csv", loops, comments=comments)
    assert (tmp_path / "l.csv").read_bytes() == loop_csv_text(loops, comments=comments).encode()
    write_g2o(tmp_path / "g.g2o", poses, loops, ids=ids, sessions=sessions)
    text = g2o_text(poses, loops, ids=ids, sessions=sessions)
    assert (tmp_path / "g.g2o").read_bytes() == text.encode()
    assert text.count("VERTEX_SE2") == 12 and text.count("EDGE_SE2") == 10 + 3  # 3 accepted
    stamps = np.arange(12) * 0.1
    write_tum(tmp_path / "t.tum", stamps, poses, comments=comments)
    assert (tmp_path / "t.tum").read_bytes() == tum_text(stamps, poses, comments=comments).encode()


def test_csv_rows_quote_fields_that_hold_commas() -> None:
    import csv

    from vvloc._io import csv_row

    line = csv_row(3, "day,1", 'say "hi"', 0.5)
    assert line == '3,"day,1","say ""hi""",0.5'
    assert next(csv.reader([line])) == ["3", "day,1", 'say "hi"', "0.5"]
    # a line break in a field is quoted too (it was written bare, splitting the row), and no
    # line end is added
    line = csv_row("s0", "day\n1", "a\rb", 3)
    assert line == 's0,"day\n1","a\rb",3'
    assert next(csv.reader(io.StringIO(line, newline=""))) == ["s0", "day\n1", "a\rb", "3"]


def test_keyframe_csv_maps_vertex_ids_to_sessions_and_times() -> None:
    from vvloc.localize.export import keyframe_csv_text

    poses = np.array([[1.0, 2.0, 3 * math.pi / 2], [0.5, 0.0, 0.1]])
    text = keyframe_csv_text(
        [7, 9], ["day,1", "s2"], [0, 4], [1.7e9 + 0.123456, 2.5], [0, -1], poses
    )
    rows = [r for r in text.splitlines() if not r.startswith("#")]
    assert rows[0] == "id,session,seq,timestamp,floor,x,y,yaw"
    assert rows[1].startswith('7,"day,1",0,1700000000.123456,0,1.0,2.0,')  # quoted, µs kept
    assert float(rows[1].rsplit(",", 1)[1]) == pytest.approx(-math.pi / 2)  # wrapped
    with pytest.raises(ValueError, match="sessions: expected 2 session names"):
        keyframe_csv_text([7, 9], ["s1"], [0, 1], [0.0, 1.0], [0, 0], poses)
    with pytest.raises(TypeError, match="ids: expected an integer array"):
        keyframe_csv_text([7.0, 9.0], ["a", "b"], [0, 1], [0.0, 1.0], [0, 0], poses)


def test_keyframe_csv_reads_back_what_it_wrote(tmp_path) -> None:
    from vvloc.localize import read_keyframe_csv
    from vvloc.localize.export import keyframe_csv_text

    # a timestamp whose float is a hair below its microsecond: int() lost one, round() not
    us = np.array([1_700_000_001_602_780, 2_500_000])
    assert int(us[0] * 1e-6 * 1e6) != us[0]  # 1700000001.6027799 s
    poses = np.array([[1.0, 2.0, -math.pi / 2], [0.5, 0.0, 0.1]])
    path = tmp_path / "keyframes.csv"
    path.write_text(keyframe_csv_text([7, 9], ["day,1", "s2"], [0, 4], us * 1e-6, [0, -1], poses))
    table = read_keyframe_csv(path)
    assert table.ids.tolist() == [7, 9] and table.sessions == ("day,1", "s2")
    assert table.seq.tolist() == [0, 4] and table.floors.tolist() == [0, -1]
    assert table.timestamps_us.tolist() == us.tolist()
    np.testing.assert_allclose(table.poses, poses, atol=1e-9)
    rows = path.read_text().splitlines()
    for bad, match in (
        ([*rows[:-1], "9,s2,4,2.5,one,0.5,0.0,0.1"], r":\d+: malformed keyframe row: floor"),
        ([*rows[:-1], "9,s2,4"], r"malformed keyframe row: expected the header's 8 fields"),
        ([r for r in rows if not r.startswith("id,")], r"the header lacks columns"),
        (["# nothing"], r"no header line \(columns id, session, seq"),
    ):
        path.write_text("\n".join(bad) + "\n")
        with pytest.raises(ValueError, match=match):
            read_keyframe_csv(path)


def test_a_selection_of_loop_closures_or_candidates_is_checked_and_named():
    from vvloc.localize.loops import LoopCandidates

    lc = LoopClosures(np.array([0, 2]), np.array([1, 3]), np.zeros((2, 3)), np.array([0.3, 0.9]),
                      np.array([True, False]))  # fmt: skip
    assert lc.select(np.array([False, True])).i.tolist() == [2]
    assert lc.select([1, 1, 0]).i.tolist() == [2, 2, 0] and len(lc.select([])) == 0
    with pytest.raises(ValueError, match=r"^mask: expected a bool mask \(2,\), got shape \(3,\)"):
        lc.select([True, False, True])
    with pytest.raises(ValueError, match=r"^mask: expected indices in \[0, 2\), got 0\.\.5"):
        lc.select([0, 5])
    with pytest.raises(TypeError, match=r"^mask: expected a bool mask \(2,\) or int indices"):
        lc.select([0.0])
    cand = LoopCandidates(np.array([0, 1]), np.array([2, 3]), np.array([0.05, 0.2]))
    assert cand.within(0.1).i.tolist() == [0] and len(cand.within(np.inf).i) == 2
    with pytest.raises(ValueError, match=r"^radius: expected a number, got nan"):
        cand.within(np.nan)  # kept nothing
    with pytest.raises(ValueError, match=r"^keep: expected a bool mask \(2,\)"):
        cand.subset(np.array([True]))


def test_text_readers_name_files_they_cannot_read(tmp_path):
    import csv as csv_module

    path = tmp_path / "t.tum"
    path.write_bytes(b"# caf\xe9\n0 1 2 0 0 0 0 1\n")  # Latin-1 in a comment
    for reader in (read_tum, read_g2o, read_loop_csv):
        with pytest.raises(ValueError, match=r"t\.tum: not UTF-8 text"):  # UnicodeDecodeError
            reader(path)
    fifo = tmp_path / "pipe.g2o"
    os.mkfifo(fifo)
    for reader in (read_tum, read_g2o, read_loop_csv):
        with pytest.raises(ValueError, match=r"pipe\.g2o: not a regular file"):  # blocked
            reader(fifo)
    loops = tmp_path / "loops.csv"
    big = "x" * (csv_module.field_size_limit() + 10)
    loops.write_text(f"i,j,x,y,yaw,yaw_deg,cost,accepted\n0,1,0,0,0,0,0.5,{big}\n")
    with pytest.raises(ValueError, match=r"loops\.csv:2: malformed loop-closure row: not a CSV"):
        read_loop_csv(loops)  # _csv.Error, no file or line


def test_tum_quaternions_at_the_ends_of_float_range_give_their_yaw(tmp_path):
    path = tmp_path / "q.tum"
    # (0, 0, s, s) is a 90° yaw at any scale: at 1e308 its norm overflowed (read as 0°), at
    # 1e-170 it underflowed ("zero quaternion")
    path.write_text("0 1 2 0 0 0 1e308 1e308\n1 1 2 0 0 0 1e-170 1e-170\n")
    _, poses = read_tum(path)
    np.testing.assert_allclose(poses[:, 2], [np.pi / 2, np.pi / 2], atol=1e-12)
    path.write_text("0 1 2 0 0 0 0 0\n")
    with pytest.raises(ValueError, match=r"zero quaternion at data row 1"):
        read_tum(path)
