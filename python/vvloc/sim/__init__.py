"""Procedural multi-camera synthetic worlds rendered headless (moderngl + EGL + Mesa llvmpipe).

``simulate_dataset(out, scene="parking" | "garage", ...)`` writes a vvloc-format dataset;
:class:`Renderer` renders one frame of a rig at a pose; :func:`make_rig` builds 4/5/6-camera
rigs; :func:`parking_world` / :func:`garage_world` build the scenes. Frames follow DESIGN.md §3.
"""

from __future__ import annotations

from vvloc.sim.render import PRESETS, Lighting, Renderer, egl_status, projection_from_K
from vvloc.sim.rig import make_rig
from vvloc.sim.sequences import Drive, drive_keyframes, sample_loop
from vvloc.sim.simulate import SCENES, SessionSpec, build_world, session_plan, simulate_dataset
from vvloc.sim.world import World, garage_world, parking_world

__all__ = [
    "PRESETS",
    "SCENES",
    "Drive",
    "Lighting",
    "Renderer",
    "SessionSpec",
    "World",
    "build_world",
    "drive_keyframes",
    "egl_status",
    "garage_world",
    "make_rig",
    "parking_world",
    "projection_from_K",
    "sample_loop",
    "session_plan",
    "simulate_dataset",
]
