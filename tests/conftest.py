"""Shared fixtures: a tiny rendered synthetic world (needs headless EGL)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


def _require_egl() -> None:
    from vvloc.sim import egl_status

    ok, why = egl_status()
    if not ok:
        msg = (
            "headless EGL unavailable (apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri "
            f"libgl1): {why}"
        )
        if os.environ.get("VVLOC_REQUIRE_EGL") == "1":
            pytest.fail(f"VVLOC_REQUIRE_EGL=1 but {msg}")
        pytest.skip(msg)


@pytest.fixture(scope="module")
def egl() -> None:
    """Skip (or fail under VVLOC_REQUIRE_EGL=1) when headless EGL is unavailable."""
    _require_egl()


@pytest.fixture
def one_torch_thread():
    """Run a test with one torch thread (2 contended cores make torch's default threads slow)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def tiny_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3-session, 40-keyframe parking-lot dataset (vvloc format), rendered once per run."""
    _require_egl()
    from vvloc.sim import simulate_dataset

    root = tmp_path_factory.mktemp("world") / "tiny"
    simulate_dataset(root, scene="parking", sessions=3, frames=40, seed=0, progress=False)
    return root
