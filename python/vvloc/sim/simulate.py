"""Simulate a whole dataset: a world, a rig, sessions of keyframes, written in the vvloc format."""

from __future__ import annotations

import inspect
import logging
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from vvloc._checks import finite_float, positive_int
from vvloc.data.frame import Camera, euler_to_matrix
from vvloc.data.vvloc_format import DatasetWriter
from vvloc.sim.render import PRESETS, Renderer
from vvloc.sim.rig import make_rig
from vvloc.sim.sequences import Drive, drive_keyframes, sample_loop
from vvloc.sim.world import World, garage_world, parking_world

log = logging.getLogger("vvloc.sim")

SCENES = ("parking", "garage")
PARKING_LIGHTING = ("day", "dusk", "night", "rain", "fog")
GARAGE_LIGHTING = ("garage", "garage_dim")
OFFSETS = (0.0, 1.5, -1.5)
T0_US = 1_600_000_000_000_000  # first session's start, microseconds
SESSION_GAP_US = 86_400_000_000  # one day between sessions
MAX_TILT = 30.0  # degrees: the largest roll or pitch bound simulate_dataset takes


@dataclass(frozen=True)
class SessionSpec:
    """How one simulated session differs from the mapping session ``s0``: its ``lighting``
    preset's name, lateral ``offset`` (metres, + = left of the route's direction), ``reverse``d
    direction, the share ``change_fraction`` in [0, 1] of bays whose parked car changes, and the
    ``seed`` of those changes and of the drive's wobble."""

    name: str
    lighting: str
    offset: float
    reverse: bool
    change_fraction: float
    seed: int


def session_plan(
    scene: str, sessions: int, seed: int = 0, lighting: Sequence[str] | None = None
) -> list[SessionSpec]:
    """The sessions' specs: ``s0`` maps (first lighting, centred, forward, base cars); query
    session i cycles lateral offsets (0, +1.5, −1.5 m), direction (reversed when i mod 4 ∈ {2, 3})
    and lighting, and moves 15 % of the parked cars."""
    if scene not in SCENES:  # another name took the garage's lighting without a word
        raise ValueError(f"scene: expected one of {SCENES}, got {scene!r}")
    if sessions < 1:
        raise ValueError(f"sessions: expected >= 1, got {sessions}")
    if isinstance(lighting, str):  # one preset would cycle through its letters
        raise TypeError(f"lighting: expected a list of preset names, got the str {lighting!r}")
    cycle = (
        tuple(lighting)
        if lighting
        else (PARKING_LIGHTING if scene == "parking" else GARAGE_LIGHTING)
    )
    unknown = [name for name in cycle if name not in PRESETS]
    if unknown:
        raise ValueError(f"lighting: unknown presets {unknown}; known: {sorted(PRESETS)}")
    return [
        SessionSpec(
            name=f"s{i}",
            lighting=cycle[i % len(cycle)],
            offset=OFFSETS[i % len(OFFSETS)],
            reverse=i % 4 in (2, 3),
            change_fraction=0.0 if i == 0 else 0.15,
            seed=int(np.random.default_rng([seed, 100 + i]).integers(2**31)),
        )
        for i in range(sessions)
    ]


#: The most storeys ``vvloc sim --scene garage`` builds (each is a full level of the garage).
MAX_FLOORS = 16


def build_world(scene: str, seed: int = 0, floors: int = 2, floor_marking: str = "walls") -> World:
    """The world of ``scene`` ("parking" or "garage" with ``floors`` storeys marked as
    ``floor_marking`` says, see :func:`vvloc.sim.world.garage_world`)."""
    if scene == "parking":
        if floor_marking != "walls":
            raise ValueError("floor_marking: only the garage scene has floors to mark")
        return parking_world(seed)
    if scene == "garage":
        return garage_world(seed, floors=floors, floor_marking=floor_marking)
    raise ValueError(f"scene: expected one of {SCENES}, got {scene!r}")


def tilted_rig(
    rig: Sequence[Camera], rng: np.random.Generator, bounds_deg: np.ndarray
) -> np.ndarray:
    """(M, 4, 4) camera → level-ego transforms of ``rig`` on a vehicle tilted about its ego
    origin (the ground point under it) by a roll and a pitch drawn uniformly within
    ``bounds_deg`` = (roll, pitch) degrees: R = Ry(pitch)·Rx(roll) (ZYX order, yaw 0) applied
    to every camera."""
    roll, pitch = np.radians(rng.uniform(-1.0, 1.0, 2) * bounds_deg)
    T = euler_to_matrix(0.0, 0.0, 0.0, float(roll), float(pitch), 0.0)
    return np.stack([T @ c.cam_to_ego for c in rig])


def simulate_dataset(
    out: str | os.PathLike[str],
    *,
    scene: str = "parking",
    sessions: int = 3,
    frames: int = 600,
    floors: int | None = None,
    floor_marking: str = "walls",
    seed: int = 0,
    cameras: int = 4,
    width: int = 160,
    height: int = 96,
    texture_strength: float = 1.0,
    lighting: Sequence[str] | None = None,
    max_roll: float = 0.0,
    max_pitch: float = 0.0,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Render a synthetic dataset into ``out`` (vvloc format) and return its path.

    Each session drives the world's loop(s) for ``frames`` keyframes (garage: split across the
    floors, each floor driving its own copy of the loop), see :func:`session_plan`. Everything is
    a function of ``seed``. The dataset appears atomically: on error nothing is left behind.
    ``width``, ``height``: each camera's image size, pixels; ``cameras``: how many (a ring).
    ``floors`` (garage only; default 2, at most 16): storeys; the parking lot has one level,
    and a number given for it is refused rather than ignored.
    ``floor_marking`` (garage only): ``"walls"`` or ``"pillars"``, see
    :func:`vvloc.sim.world.garage_world`; recorded in ``rig.json``'s ``meta``.
    ``max_roll``, ``max_pitch`` (degrees, 0 to 30; default 0: level): tilt the vehicle of every
    query session (s1, s2, ...) by a roll and a pitch drawn uniformly within these bounds for
    each keyframe, about the ground point under it, as a Segway or a car on uneven ground
    tilts; the mapping session s0 stays level. Each frame's cameras are rendered where the
    tilt puts them and written as that frame's own extrinsics (``cam_to_ego.csv``, the level
    ego frame's, as the NCLT and RobotCar readers give them); the pose stays (x, y, yaw).
    """
    o = _checked_options(
        scene=scene,
        sessions=sessions,
        frames=frames,
        floors=floors,
        floor_marking=floor_marking,
        seed=seed,
        cameras=cameras,
        width=width,
        height=height,
        texture_strength=texture_strength,
        lighting=lighting,
        max_roll=max_roll,
        max_pitch=max_pitch,
    )
    scene, sessions, frames, seed = o.scene, o.sessions, o.frames, o.seed
    plan, rig, world, tilt_bounds = o.plan, o.rig, o.world, o.tilt_bounds
    texture_strength = o.texture_strength
    loops = [sample_loop(r) for r in world.routes]
    meta = {
        "scene": scene,
        "seed": seed,
        "floors": len(world.floor_z),
        "floor_marking": floor_marking,
        "texture_strength": texture_strength,
        "generator": "vvloc.sim",
    }
    tilting = bool(tilt_bounds.any())
    if tilting:  # recorded only when used: a level dataset's rig.json is as before
        meta["max_roll"], meta["max_pitch"] = float(max_roll), float(max_pitch)
    renderer = Renderer(rig, texture_strength=texture_strength)
    total = sessions * frames
    bar = None  # opened once the writer accepted --out (a refusal prints no empty bar)
    try:
        with DatasetWriter(out, rig, overwrite=overwrite, meta=meta) as writer:
            bar = tqdm(total=total, desc=f"vvloc sim {scene}", unit="frame", disable=not progress)
            for k, spec in enumerate(plan):
                verts, idx = world.mesh(spec.change_fraction, spec.seed)
                renderer.set_mesh(verts, idx, world.lights, world.light_colors, world.light_floors)
                sw = writer.add_session(spec.name, meta=asdict(spec))
                drive = Drive(spec.offset, spec.reverse, seed=spec.seed)
                nf = len(loops)
                counts = [frames // nf + (1 if f < frames % nf else 0) for f in range(nf)]
                t_base = 0.0
                tilts = np.random.default_rng([seed, 300 + k]) if tilting and k > 0 else None
                for f, (loop, n) in enumerate(zip(loops, counts, strict=True)):
                    if n == 0:
                        continue
                    poses, times = drive_keyframes(loop, drive, n)
                    z = float(world.floor_z[f]) + 0.0  # no -0.0 in the CSV
                    for j in range(n):
                        ts = T0_US + k * SESSION_GAP_US + round((t_base + times[j]) * 1e6)
                        own = None if tilts is None else tilted_rig(rig, tilts, tilt_bounds)
                        images = renderer.render(
                            poses[j], z, spec.lighting, frame_index=j, floor=f, cam_to_ego=own
                        )
                        sw.add(ts, poses[j], images, z=z, floor=f, cam_to_ego=own)
                        bar.update(1)
                    t_base += float(times[-1]) + 60.0  # a minute on the ramp to the next floor
                log.info("session %s: %d frames, %s", spec.name, sw.count, spec.lighting)
    finally:
        if bar is not None:
            bar.close()
        renderer.release()
    return Path(out)


@dataclass(frozen=True)
class _Options:
    """:func:`simulate_dataset`'s options, checked, and what they build before any rendering."""

    scene: str
    sessions: int
    frames: int
    seed: int
    texture_strength: float
    tilt_bounds: np.ndarray  # (2,) float64 degrees: max roll, max pitch
    plan: list[SessionSpec]
    rig: list[Camera]
    world: World


def check_options(**options: object) -> None:
    """Refuse bad :func:`simulate_dataset` keyword arguments (all but ``out``) before anything
    is rendered or said: the ``ValueError``/``TypeError`` that :func:`simulate_dataset` would
    raise, naming the argument. ``overwrite`` and ``progress`` are not checked here."""
    params = inspect.signature(simulate_dataset).parameters
    known = [p for p in params if p != "out"]
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise TypeError(f"unknown simulate_dataset arguments {unknown} (known: {known})")
    checked = [p for p in known if p not in ("overwrite", "progress")]
    given = {p: options.get(p, params[p].default) for p in checked}  # its defaults, not copies
    _checked_options(**given)  # type: ignore[arg-type]  # checked inside


def _checked_options(
    *,
    scene: str,
    sessions: int,
    frames: int,
    floors: int | None,
    floor_marking: str,
    seed: int,
    cameras: int,
    width: int,
    height: int,
    texture_strength: float,
    lighting: Sequence[str] | None,
    max_roll: float,
    max_pitch: float,
) -> _Options:
    """The checks of :func:`simulate_dataset` (every argument given: the defaults are its
    own), and the session plan, rig and world they lead to."""
    if scene == "parking" and floors is not None:
        raise ValueError("floors: only the garage scene has floors (the parking lot has one level)")
    if floors is None:
        floors = 2
    sessions, frames, floors = (
        positive_int(v, key)
        for key, v in (("sessions", sessions), ("frames", frames), ("floors", floors))
    )
    if scene == "garage" and floors > MAX_FLOORS:  # the parking lot has one level
        raise ValueError(f"floors: expected at most {MAX_FLOORS} storeys, got {floors}")
    if scene == "garage" and frames < floors:  # each floor drives its share of the frames
        raise ValueError(
            f"frames: expected at least one frame per floor ({floors}) a session, got {frames}"
        )
    seed = positive_int(seed, "seed", 0)
    cameras = positive_int(cameras, "cameras")  # as this function names it (make_rig: num_cameras)
    texture_strength = finite_float(texture_strength, "texture_strength")  # a plain float
    if texture_strength < 0:
        raise ValueError(f"texture_strength: expected a value >= 0, got {texture_strength}")
    for key, v in (("max_roll", max_roll), ("max_pitch", max_pitch)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= MAX_TILT:
            raise ValueError(f"{key}: expected degrees within [0, {MAX_TILT:g}], got {v!r}")
    tilt_bounds = np.array([max_roll, max_pitch], dtype=np.float64)
    plan = session_plan(scene, sessions, seed, lighting)
    rig = make_rig(cameras, width, height)
    world = build_world(scene, seed, floors, floor_marking)
    return _Options(scene, sessions, frames, seed, texture_strength, tilt_bounds, plan, rig, world)
