"""How much a rendered garage tells its floors apart, whatever the model: an exact analysis.

For a garage dataset written by ``vvloc sim`` this rebuilds its world and session plan (from
``rig.json``'s ``meta``) and asks what *any* loop detector could use to keep two floors apart:

1. Parked cars. Floor f ≥ 1 starts from floor 0's cars with a quarter of the bays toggled;
   every query session toggles 15 % of the bays again. For each pair of keyframes that lie
   within ``--radius`` metres of each other in (x, y) (a true revisit when both are on one floor,
   a look-alike when not) the *layout difference* is the share of the bays in the keyframes'
   BEV squares (±12 m in the ego frame, the small model's BEV) whose state differs: one
   occupied and the other not, or both occupied by cars of different colours.
   The *car-reading detector* shows what the cars allow: it reads every bay in a keyframe's
   BEV square exactly, compares them with each floor's cars as the mapping session ``s0`` saw
   them, and assigns the keyframe to the floor with fewer mismatching bays when it wins by at
   least ``margin`` bays (else it abstains); a pair within the radius is accepted when both of
   its keyframes are assigned to one floor. Its recall and cross-floor error rate (CFER) at each
   margin are an operating point that reading the cars reaches, not a bound on what a detector
   can do (it ignores lighting and viewpoint, which make reading harder, and the wall signs,
   the cars' fixed placement jitter and sequences, which could help).
2. Level signs. The share of keyframes that see a wall level sign of their own floor with its
   digit at least ``--min_px`` pixels tall in some camera (0.9 m digit; occlusion by parked cars
   is ignored, so this is an upper bound).

Usage (from the repository root, on a dataset of ``vvloc sim --scene garage``)::

    .venv/bin/python -m vvloc.sim.floor_cues --dataset data/synth-garage-12 \
        --sessions s0,s1,s6,s7,s8,s9,s10,s11

Prints a Markdown summary; ``--json`` also writes the figures.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from vvloc import geometry
from vvloc.data import Camera, Dataset, open_dataset
from vvloc.data.vvloc_format import rig_meta
from vvloc.sim.simulate import build_world
from vvloc.sim.world import World

BEV_HALF = 12.0  # m: the small model's BEV, 40 cells × 0.6 m
WINDOW = 10  # keyframes: same-session temporal neighbours are not loop candidates
DIGIT_HEIGHT = 0.9  # m


def keyframes(ds: Dataset, sessions: list[str]) -> dict[str, np.ndarray]:
    """The frames of ``sessions`` of ``ds``: ``pose`` (N, 3) world (x, y, yaw) m/rad, ``z`` (N,)
    m, ``floor``, ``session`` (position in ``sessions``) and ``seq`` (N,) int."""
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("pose", "z", "floor", "session", "seq")}
    for k, name in enumerate(sessions):
        s = ds.session(name)
        parts["pose"].append(s.poses)
        parts["z"].append(s.z)
        parts["floor"].append(s.floors)
        parts["session"].append(np.full(len(s), k))
        parts["seq"].append(np.arange(len(s)))
    return {k: np.concatenate(v) for k, v in parts.items()}


def sim_garage(dataset: str) -> tuple[dict[str, Any], World]:
    """``rig.json``'s ``meta`` of a garage dataset written by ``vvloc sim``, and its world
    rebuilt from it; ``ValueError`` for any other dataset."""
    meta = rig_meta(dataset) or {}
    if meta.get("scene") != "garage" or meta.get("generator") != "vvloc.sim":
        raise ValueError(f"dataset: expected a garage of vvloc sim, got meta {meta}")
    return meta, build_world("garage", meta["seed"], meta["floors"], meta["floor_marking"])


def session_specs(dataset: str, sessions: list[str]) -> list[dict[str, Any]]:
    """Each session's ``session.json`` (lighting, change_fraction, seed, ...) as written by
    ``vvloc sim``."""
    root = Path(dataset) / "sessions"
    return [
        json.loads((root / name / "session.json").read_text(encoding="utf-8-sig"))
        for name in sessions
    ]


def bay_states(world: World, specs: list[dict[str, Any]]) -> np.ndarray:
    """(S, B) int64: per session spec (:func:`session_specs`; ``{"change_fraction": 0}`` gives
    the base cars), the state of each of ``world.bays`` (−1 empty, else the car's colour as a
    24-bit RGB number)."""
    out = []
    for spec in specs:
        occ, colors = world.cars(float(spec["change_fraction"]), int(spec.get("seed", 0)))
        key = np.round(colors * 255).astype(np.int64) @ np.array([1 << 16, 1 << 8, 1])
        out.append(np.where(occ, key, -1))
    return np.stack(out)


def ego_xy(poses: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N, K, 2): world points ``xy`` (K, 2) in the ego frames of ``poses`` (N, 3)."""
    points = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)
    return geometry.relative(poses[:, None, :], points[None, :, :])[..., :2]


def bay_centres(world: World) -> np.ndarray:
    """(B/F, 2) world x, y (m) of one floor's bays: every floor has this layout, bay k of floor
    f being ``world.bays[f * B/F + k]``."""
    per_floor = len(world.bays) // len(world.floor_z)
    return np.array([(b.x, b.y) for b in world.bays[:per_floor]])


def visible_bays(world: World, kf: dict[str, np.ndarray]) -> np.ndarray:
    """(N, B/F) bool: bay k of the keyframe's floor has its centre inside the keyframe's BEV
    square (±``BEV_HALF`` m along ego x and y, DESIGN.md §3)."""
    return (np.abs(ego_xy(kf["pose"], bay_centres(world))) <= BEV_HALF).all(axis=-1)


def layout_difference(
    states: np.ndarray,
    kf: dict[str, np.ndarray],
    visible: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    block: int = 20_000,
) -> np.ndarray:
    """(P,) float64 in [0, 1]: for keyframe pairs (a, b) ((P,) rows of ``kf``), the share of the
    bays visible from either (``visible``, :func:`visible_bays`) whose state (``states``,
    :func:`bay_states`, indexed by ``kf["session"]``) differs between a's session and floor and
    b's session and floor (bay k of one floor against bay k of the other)."""
    per_floor = visible.shape[1]
    idx = np.arange(per_floor)
    diff = np.empty(len(a))
    for lo in range(0, len(a), block):
        sa, sb = a[lo : lo + block], b[lo : lo + block]
        st_a = states[kf["session"][sa][:, None], kf["floor"][sa][:, None] * per_floor + idx]
        st_b = states[kf["session"][sb][:, None], kf["floor"][sb][:, None] * per_floor + idx]
        union = visible[sa] | visible[sb]
        diff[lo : lo + block] = ((st_a != st_b) & union).sum(1) / np.maximum(union.sum(1), 1)
    return diff


def sees_sign(
    world: World, kf: dict[str, np.ndarray], cameras: Sequence[Camera], min_px: float
) -> np.ndarray:
    """(N,) bool: a level sign of the keyframe's floor projects into some camera with its digit
    at least ``min_px`` pixels tall (occlusion ignored)."""
    seen = np.zeros(len(kf["z"]), dtype=bool)
    for sx, sy, sz, f in world.level_signs:
        on = kf["floor"] == int(f)
        sign_xy = ego_xy(kf["pose"], np.array([[sx, sy]]))[:, 0]
        ego = np.concatenate([sign_xy, (sz - kf["z"])[:, None]], axis=1)
        for cam in cameras:
            uv, depth = cam.project_ego(ego)
            with np.errstate(divide="ignore", invalid="ignore"):
                px = DIGIT_HEIGHT * cam.K[1, 1] / depth
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0)
            inside &= uv[:, 1] < cam.height
            seen |= on & (depth > 0) & inside & (px >= min_px)
    return seen


def car_reading_detector(
    states: np.ndarray,
    base: np.ndarray,
    kf: dict[str, np.ndarray],
    visible: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    margins: Sequence[int] = (1, 2, 3, 4),
) -> list[dict[str, Any]]:
    """The car-reading detector of the module docstring on keyframe pairs (a, b) ((P,) rows of
    ``kf``, pairs within the revisit radius): ``states`` (S, B) of the keyframes' sessions and
    ``base`` (B,) the mapped cars (:func:`bay_states`), ``visible`` (N, B/F) (:func:`visible_bays`).

    Returns per margin m of ``margins`` (bays): ``accepted`` pairs, ``cross_floor`` among them,
    ``cfer`` (their share, ``nan`` without pairs) and ``recall`` (accepted true revisits / all
    true revisits among the pairs, ``nan`` without true revisits)."""
    per_floor = visible.shape[1]
    floors = states.shape[1] // per_floor
    idx = np.arange(per_floor)
    seen = states[kf["session"][:, None], kf["floor"][:, None] * per_floor + idx]  # (N, B/F)
    mismatch = np.stack(
        [((seen != base[f * per_floor + idx]) & visible).sum(axis=1) for f in range(floors)],
        axis=1,
    )  # (N, F) bays in view that differ from floor f's mapped cars
    ranked = np.sort(mismatch, axis=1)
    floor = np.argmin(mismatch, axis=1)
    lead = ranked[:, 1] - ranked[:, 0] if floors > 1 else np.full(len(floor), per_floor)
    cross = kf["floor"][a] != kf["floor"][b]
    n_true = int((~cross).sum())  # 0: recall is undefined (nan), not 0
    out = []
    for m in margins:
        ok = (lead[a] >= m) & (lead[b] >= m) & (floor[a] == floor[b])
        k = int(ok.sum())
        out.append(
            {
                "margin": int(m),
                "accepted": k,
                "cross_floor": int((ok & cross).sum()),
                "cfer": float((ok & cross).sum() / k) if k else float("nan"),
                "recall": float((ok & ~cross).sum() / n_true) if n_true else float("nan"),
            }
        )
    return out


def analyse(
    dataset: str, sessions: list[str], radius: float = 2.0, min_px: float = 6.0
) -> dict[str, Any]:
    """The figures described in the module docstring, as a JSON-friendly dict: ``pairs`` (count
    and mean layout difference, a share in [0, 1], per kind of keyframe pair),
    ``car_reading_detector`` (:func:`car_reading_detector`) and ``sees_level_sign`` (share of
    keyframes)."""
    ds = open_dataset(dataset)  # a clear error for a missing or malformed dataset
    for name in sessions:
        ds.session(name)  # KeyError naming the known sessions
    meta, world = sim_garage(dataset)
    if not radius > 0 or not min_px > 0:
        raise ValueError(f"radius, min_px: expected > 0, got {radius} and {min_px}")
    specs = session_specs(dataset, sessions)
    kf = keyframes(ds, sessions)
    states = bay_states(world, specs)  # (S, B)
    base = bay_states(world, [{"change_fraction": 0.0}])[0]  # the cars as s0 mapped them
    vis = visible_bays(world, kf)
    pairs = cKDTree(kf["pose"][:, :2]).query_pairs(radius, output_type="ndarray")
    a, b = pairs[:, 0], pairs[:, 1]
    keep = (kf["session"][a] != kf["session"][b]) | (np.abs(kf["seq"][a] - kf["seq"][b]) > WINDOW)
    a, b = a[keep], b[keep]
    cross = kf["floor"][a] != kf["floor"][b]
    same_session = kf["session"][a] == kf["session"][b]
    light = np.array([spec["lighting"] for spec in specs])
    same_light = light[kf["session"][a]] == light[kf["session"][b]]
    diff = layout_difference(states, kf, vis, a, b)
    kinds = {
        "true revisit, one session": ~cross & same_session,
        "true revisit, two sessions, same lighting": ~cross & ~same_session & same_light,
        "true revisit, two sessions, other lighting": ~cross & ~same_session & ~same_light,
        "other floor, one session": cross & same_session,
        "other floor, two sessions": cross & ~same_session,
    }
    summary = {
        k: {"pairs": int(m.sum()), "mean_difference": float(diff[m].mean()) if m.any() else None}
        for k, m in kinds.items()
    }
    detector = car_reading_detector(states, base, kf, vis, a, b)
    seen = {px: float(sees_sign(world, kf, ds.cameras, px).mean()) for px in (min_px, 2 * min_px)}
    return {
        "dataset": dataset,
        "floor_marking": meta["floor_marking"],
        "sessions": sessions,
        "keyframes": len(kf["z"]),
        "pair_radius_m": radius,
        "pairs": summary,
        "car_reading_detector": detector,
        "sees_level_sign": {f"digit >= {px:g} px": v for px, v in seen.items()},
    }


def markdown(r: dict[str, Any]) -> str:
    """The figures of :func:`analyse` as Markdown."""
    lines = [
        f"# Floor cues of {r['dataset']} (floor marking: {r['floor_marking']})",
        "",
        f"{r['keyframes']} keyframes of {', '.join(r['sessions'])}; keyframe pairs within "
        f"{r['pair_radius_m']} m in (x, y), same-session pairs within {WINDOW} keyframes left out.",
        "",
        "| pairs | count | mean layout difference |",
        "|---|---|---|",
    ]
    for k, v in r["pairs"].items():
        m = "—" if v["mean_difference"] is None else f"{100 * v['mean_difference']:.1f} %"
        lines.append(f"| {k} | {v['pairs']} | {m} |")
    lines += [
        "",
        "A detector that reads every bay in view exactly and assigns a keyframe to the floor whose "
        "mapped cars (session s0) it matches better by at least *margin* bays; a pair is accepted "
        "when both keyframes go to one floor (an operating point the cars allow, not a bound):",
        "",
        "| margin (bays) | accepted | across floors | CFER | recall of true revisits |",
        "|---|---|---|---|---|",
    ]
    for o in r["car_reading_detector"]:
        cfer = "–" if o["cfer"] != o["cfer"] else f"{100 * o['cfer']:.2f} %"
        recall = "–" if o["recall"] != o["recall"] else f"{100 * o['recall']:.1f} %"
        lines.append(
            f"| {o['margin']} | {o['accepted']} | {o['cross_floor']} | {cfer} | {recall} |"
        )
    lines += ["", "Keyframes that see a level sign of their floor (occlusion ignored):", ""]
    lines += [f"- {k}: {100 * v:.1f} %" for k, v in r["sees_level_sign"].items()]
    if r["floor_marking"] == "pillars":
        lines += [
            "",
            "Not counted here: this garage's level colour and number on every pillar (the cars "
            "and wall signs above are the same as in the default garage's).",
        ]
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", required=True, help="a garage dataset of vvloc sim")
    p.add_argument("--sessions", required=True, help="comma-separated session names")
    p.add_argument("--radius", type=float, default=2.0, help="revisit radius in (x, y), m")
    p.add_argument("--min_px", type=float, default=6.0, help="legible digit height, pixels")
    p.add_argument("--json", type=Path, help="also write the figures here")
    a = p.parse_args()
    try:
        r = analyse(a.dataset, a.sessions.split(","), a.radius, a.min_px)
    except (KeyError, OSError, ValueError) as e:
        p.exit(2, f"floor_cues: {e}\n")
    print(markdown(r), end="")
    if a.json:
        from vvloc.evaluate import to_jsonable  # NaN (undefined) → null: strict JSON

        a.json.write_text(json.dumps(to_jsonable(r), indent=2, allow_nan=False) + "\n")


if __name__ == "__main__":
    main()
