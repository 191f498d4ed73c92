"""The package imports, reports its version and build, and manages its thread pool."""

import os
import subprocess
import sys

import pytest

import vvloc
from vvloc import _core


def test_version_matches_extension():
    assert vvloc.__version__ == _core.__version__
    assert vvloc.__version__.count(".") == 2


def test_build_profile_is_exposed():
    assert _core.build_profile in ("release", "debug")


def test_set_and_get_num_threads_roundtrip():
    before = vvloc.get_num_threads()
    try:
        vvloc.set_num_threads(1)
        assert vvloc.get_num_threads() == 1
        vvloc.set_num_threads(2)
        assert vvloc.get_num_threads() == 2
    finally:
        vvloc.set_num_threads(before)


@pytest.mark.parametrize("bad", [0, -3])
def test_set_num_threads_rejects_non_positive(bad):
    with pytest.raises(ValueError, match="n"):
        vvloc.set_num_threads(bad)


@pytest.mark.parametrize("bad", [1.5, "2", True])
def test_set_num_threads_rejects_non_int(bad):
    with pytest.raises(TypeError, match="n"):
        vvloc.set_num_threads(bad)


def test_env_var_sets_default_threads():
    code = "import vvloc; print(vvloc.get_num_threads())"
    env = {**os.environ, "VVLOC_NUM_THREADS": "3"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "3"
