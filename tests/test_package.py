"""The package imports, reports its version and build, and manages its thread pool."""

import os
import subprocess
import sys

import numpy as np
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
    assert "VVLOC_NUM_THREADS" not in out.stderr


@pytest.mark.parametrize(
    "value", ["abc", "0", "-3", "2.5", "+2", "2_0", "\uff13", "\x1f3", "3\x1c", "0" * 5000]
)
def test_an_unusable_threads_variable_is_said_not_ignored(value):
    # "+2", "2_0" and a full-width "3" are ints to Python's int() but not to the Rust pool,
    # which used every core while no warning was given; str.strip() takes \x1c-\x1f, which
    # Rust's trim does not
    code = "import vvloc, os; print(vvloc.get_num_threads() == (os.cpu_count() or 1))"
    env = {**os.environ, "VVLOC_NUM_THREADS": value}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "True"  # every core, as if it were unset
    shown = repr(value) if len(value) <= 40 else f"{value[:20]!r}... ({len(value)} characters)"
    assert f"VVLOC_NUM_THREADS={shown} is not an int in [1, 1024]" in out.stderr


@pytest.mark.parametrize("value", ["5000", "99999999999999999999", "9" * 5000, "0" * 4400 + "2000"])
def test_a_threads_variable_above_1024_asks_for_1024(value):
    # twenty digits overflowed the pool's parse, which then used every core; 5000 digits made
    # Python's int() raise at import
    code = "import vvloc; print(vvloc.get_num_threads())"  # reads the count, starts no thread
    env = {**os.environ, "VVLOC_NUM_THREADS": f" {value} "}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "1024"
    assert "is not an int in [1, 1024]; vvloc's kernels use 1024 threads" in out.stderr


@pytest.mark.parametrize("module", ["vvloc", "vvloc.cli"])
def test_import_does_not_load_torch_or_scipy(module):
    """``import vvloc`` and the CLI's ``--help`` stay light: torch and scipy (≈ 1.5 s) load
    only when a kernel's reference backend, a network or a command's work needs them."""
    code = f"import sys, {module}; print(sorted(m for m in ('torch', 'scipy') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_reference_spatial_kernels_load_on_first_use():
    import vvloc.reference as reference

    assert reference.bev_pad.__module__ == "vvloc.reference.spatial"
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        _ = reference.nothing


def _pad_polar_in_child(args: tuple) -> np.ndarray:
    bev, hyps = args
    return vvloc.kernels.pad_polar(bev, hyps, 16, 6, grid_size=0.3)


def test_the_rust_pool_works_in_forked_children_as_in_the_parent():
    """DataLoader workers are forked after the parent built its pool (threads do not survive a
    fork): the child builds its own and gives the parent's results."""
    import multiprocessing

    rng = np.random.default_rng(0)
    bev = rng.normal(size=(12, 10, 4)).astype(np.float32)
    hyps = rng.uniform(-1, 1, size=(9, 2))
    before = vvloc.get_num_threads()
    try:
        vvloc.set_num_threads(2)
        want = _pad_polar_in_child((bev, hyps))  # the parent's pool exists from here on
        ctx = multiprocessing.get_context("fork")
        with ctx.Pool(2) as pool:
            got = pool.map(_pad_polar_in_child, [(bev, hyps)] * 4)
    finally:
        vvloc.set_num_threads(before)
    for g in got:
        np.testing.assert_array_equal(g, want)


def test_a_child_forked_after_the_networks_ran_runs_torch():
    """A Localizer served from forked workers: torch's OpenMP threads do not survive a fork, and
    a child's next parallel torch kernel waited for them for ever (GNU OpenMP)."""
    import torch

    import vvloc.nets  # noqa: F401 (registers the fork handler, as every network user does)
    from fork_helpers import exit_code_or_hang

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        float((torch.rand(4_000_000) * 2).sum())  # a parallel kernel: OpenMP's threads start
        pid = os.fork()
        if pid == 0:  # the child: another parallel-sized kernel
            code = 1
            try:
                float((torch.rand(4_000_000) * 2).sum())
                code = 0 if torch.get_num_threads() == 1 else 3
            finally:
                os._exit(code)
        code = exit_code_or_hang(pid)
        assert code is not None, "the forked child hung in torch's OpenMP"
        assert code == 0
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize(
    "command",
    [
        ["map", "build", "--dataset", "nowhere", "--sessions", "s0", "--out", "m.h5"],
        ["localize", "--map", "m.h5", "--dataset", "nowhere", "--session", "s1", "--out", "o"],
        ["loops", "--map", "m.h5", "--out", "o"],
        ["eval", "--dataset", "nowhere", "--database", "s0", "--queries", "s1", "--out", "o"],
        ["calibrate", "--dataset", "nowhere", "--queries", "s1"],
    ],
)
def test_the_network_commands_set_torchs_threads(command, tmp_path, monkeypatch):
    import torch
    from typer.testing import CliRunner

    from vvloc.cli import app

    monkeypatch.chdir(tmp_path)
    seen = []
    monkeypatch.setattr(torch, "set_num_threads", seen.append)
    args = [*command, "--checkpoint", "nowhere"]
    result = CliRunner().invoke(app, [*args, "--threads", "1"])
    assert seen == [1] and result.exit_code == 2  # then refused: no such dataset or map
    result = CliRunner().invoke(app, args)
    assert seen == [1] and result.exit_code == 2  # not given: torch's default stays
    result = CliRunner().invoke(app, [*args, "--threads", "0"])
    assert result.exit_code == 2 and "--threads" in result.output and seen == [1]


def test_an_error_raised_in_a_dataloader_worker_is_told_in_its_own_words():
    # torch re-raises a worker's exception as the same type, its message "Caught ... in
    # DataLoader worker process N." and the worker's traceback; the CLI prints the worker's
    # message on its line
    from torch.utils.data import DataLoader, Dataset

    from vvloc.commands._util import error_text
    from vvloc.data import DatasetFormatError

    class Broken(Dataset):
        def __len__(self) -> int:
            return 2

        def __getitem__(self, index: int) -> None:
            raise DatasetFormatError("/d/s0/front/1.png: image is 120x72,\nrig.json says 128x72")

    with pytest.raises(DatasetFormatError) as caught:
        list(DataLoader(Broken(), num_workers=1))
    assert str(caught.value).startswith("Caught DatasetFormatError in DataLoader worker")
    assert error_text(caught.value) == (
        "/d/s0/front/1.png: image is 120x72,\nrig.json says 128x72 (in DataLoader worker process 0)"
    )
    plain = DatasetFormatError("/d/rig.json: bad")
    assert error_text(plain) == "/d/rig.json: bad"
    assert error_text(KeyError("s9")) == "s9"


def test_option_names_are_read_as_a_csv_line():
    from vvloc.commands._util import split_names

    assert split_names("s1, s2,,", "--queries") == ["s1", "s2"]
    # a session named with a comma (vvloc convert keeps a source's names) in double quotes
    assert split_names('"day,1", s2', "--sessions") == ["day,1", "s2"]
    assert split_names("", "--sessions") == []
    with pytest.raises(ValueError, match=r"^--sessions: cannot read .* in double quotes"):
        split_names('"day,1', "--sessions")


def test_an_error_naming_a_library_argument_names_the_option_it_came_from():
    from vvloc.commands._util import with_option_name

    text = "window: expected an int <= 9223372036854775807, got 100000000000000000000"
    assert with_option_name(text, ["loops", "--window", "1e20"]).startswith("--window: expected")
    assert with_option_name(text, ["loops", "--window=1e20"]).startswith("--window: expected")
    # not given on the command line: the value came from elsewhere, said as the library says it
    assert with_option_name(text, ["loops", "--radius", "0.2"]) == text
    assert with_option_name("no colon here", ["--window"]) == "no colon here"
    assert with_option_name("two words: x", ["--two words"]) == "two words: x"


@pytest.mark.parametrize(
    "module",
    [
        "vvloc",
        "vvloc.kernels",
        "vvloc.retrieval",
        "vvloc.geometry",
        "vvloc.evaluate",
        "vvloc.losses",
        "vvloc.data",
        "vvloc.nets",
        "vvloc.localize",
        "vvloc.localize.metric",
        "vvloc.localize.loops",
        "vvloc.localize.localizer",
        "vvloc.localize.calibrate",
        "vvloc.localize.mapdb",
        "vvloc.localize.export",
    ],
)
def test_each_public_module_says_what_it_exports_and_holds_it(module):
    import importlib

    mod = importlib.import_module(module)
    names = mod.__all__
    assert names == sorted(set(names), key=names.index)  # listed once each
    missing = [n for n in names if not hasattr(mod, n)]
    assert not missing, missing
    assert not {"np", "torch", "math", "os"} & set(names)  # a star-import brings no modules


def test_the_localizers_search_config_is_importable_where_the_localizer_is():
    import vvloc.localize as loc
    from vvloc.localize.metric import SearchConfig

    assert loc.SearchConfig is SearchConfig  # Localizer(search=SearchConfig(...))


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["sim"], "vvloc sim: error: Missing option '--out'."),
        (["sim", "--out", "x", "--frames", "abc"], "vvloc sim: error: --frames: "),
        (["eval", "--loop_radius", "0.7"], "vvloc eval: error: --loop_radius: expected a "),
        (["map", "info", "--mapp", "x.h5"], "vvloc map info: error: No such option: --mapp"),
        (["nonexistent"], "vvloc: error: No such command 'nonexistent'."),
        # refused before the command has a context: the path comes from the arguments
        (["sim", "--out"], "vvloc sim: error: Option '--out' requires an argument."),
        (["map", "build", "--out"], "vvloc map build: error: Option '--out' requires an"),
        # demo takes --threads like the other commands that run the networks
        (["demo", "--threads", "0"], "vvloc demo: error: --threads: "),
    ],
)
def test_the_parsers_refusals_read_like_the_commands_own(args, said, tmp_path):
    # the parser printed a usage block and "Error: Invalid value for '--x': ..." where the
    # commands' own checks print one line "vvloc <command>: error: --x: ..."
    r = subprocess.run(
        [sys.executable, "-m", "vvloc.cli", *args], capture_output=True, text=True, cwd=tmp_path
    )
    lines = r.stderr.splitlines()
    assert r.returncode == 2 and r.stdout == "", r.stderr
    assert len(lines) == 2 and lines[0].startswith(said), r.stderr
    assert lines[1] == f"Try '{said.split(':')[0]} --help' for help."
    assert "Traceback" not in r.stderr and "Usage:" not in r.stderr


def test_help_version_and_a_bare_group_still_answer_as_before(tmp_path):
    def run(*args: str) -> subprocess.CompletedProcess[str]:
        exe = [sys.executable, "-m", "vvloc.cli", *args]
        return subprocess.run(exe, capture_output=True, text=True, cwd=tmp_path)

    version = run("--version")
    assert (version.returncode, version.stdout) == (0, f"vvloc {vvloc.__version__}\n")
    helped = run("sim", "--help")
    assert helped.returncode == 0 and helped.stdout.startswith("Usage: vvloc sim [OPTIONS]")
    for bare in ([], ["map"]):  # no command: the group's help, exit 2 as the parser gives it
        r = run(*bare)
        assert r.returncode == 2 and r.stderr.startswith("Usage: vvloc"), r.stderr


def test_convert_names_src_when_it_is_no_dataset(tmp_path):
    # it said "/nonexistent: no such dataset folder" without the option, unlike --dataset
    for src, said in ((tmp_path / "none", "no such dataset folder"), (tmp_path, "not a dataset")):
        exe = [sys.executable, "-m", "vvloc.cli", "convert", "--src", str(src)]
        r = subprocess.run([*exe, "--out", str(tmp_path / "out")], capture_output=True, text=True)
        assert r.returncode == 2, r.stderr
        assert r.stderr.startswith(f"vvloc convert: error: --src: {src}: {said}"), r.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("in_pool", [False, True])
def test_a_kernel_panic_comes_to_python_as_a_runtime_error(in_pool):
    # a panic on the calling thread or in a pool thread's item of a parallel loop: a
    # RuntimeError naming it (an ``except Exception`` catches it; a PanicException would not),
    # and the pool still runs kernels afterwards
    with pytest.raises(
        RuntimeError, match=r"^vvloc internal error in a Rust kernel \(a test panic"
    ):
        vvloc._core._panic_for_tests(in_pool)
    a = np.arange(4 * 16 * 8, dtype=np.float32).reshape(4, 16, 8)
    got = vvloc.kernels.estimate_yaw(a, a)  # 4 pairs: in parallel on the pool
    np.testing.assert_allclose(got.cost, 0.0, atol=1e-6)
