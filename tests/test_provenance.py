"""The training record's one-line summary and its validation, on hand-made records."""

from __future__ import annotations

import math

import pytest

from vvloc.provenance import describe_cpuinfo, json_safe, libraries, summarize, validate_record

CPU = {"hardware": "x86_64, 2 cores", "device": "cpu", "device_name": None}
H200 = {"hardware": "x86_64, 16 cores", "device": "cuda", "device_name": "NVIDIA H200"}


def _cam(fx: float = 100.0, w: int = 160) -> dict:
    """A rig.json camera entry: a level camera looking forward from 1.5 m up."""
    to_ego = [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.5], [0, 0, 0, 1.0]]
    K = [[fx, 0.0, w / 2], [0.0, 100.0, 48.0], [0.0, 0.0, 1.0]]
    return {"name": "front", "width": w, "height": 96, "K": K, "cam_to_ego": to_ego}


def _run(seconds: float | None, *procs: dict, **kw) -> dict:
    return {"seconds": seconds, "processes": list(procs or [CPU])} | kw


def test_summary_names_hardware_runs_and_minutes():
    assert summarize(None) == summarize({}) == "no training record for these weights"
    assert summarize({"runs": [_run(90.0)]}) == "cpu on x86_64, 2 cores; 1 run, 1.5 min"
    four = {"runs": [_run(4020.0), _run(252.0), _run(684.0), _run(294.0)]}
    assert summarize(four) == "cpu on x86_64, 2 cores; 4 runs, 87.5 min (67.0 + 4.2 + 11.4 + 4.9)"
    # a run resumed on another machine names both
    mixed = {"runs": [_run(60.0), _run(30.0, CPU, H200)]}
    assert summarize(mixed) == (
        "NVIDIA H200 (cuda) on x86_64, 16 cores and cpu on x86_64, 2 cores; "
        "2 runs, 1.5 min (1.0 + 0.5)"
    )
    partial = {"runs": [{"recorded": False, "weights_hash": "ab"}, _run(60.0, complete=False)]}
    assert summarize(partial) == (
        "cpu on x86_64, 2 cores; 1 run, 1.0 min, after an init checkpoint without a record "
        "(1 run unfinished)"
    )
    unknown = {"runs": [_run(60.0), _run(None)]}
    assert summarize(unknown) == (
        "cpu on x86_64, 2 cores; 2 runs, 1.0 min, time not measured for 1 run"
    )
    assert summarize({"runs": [{"seconds": 6.0}]}) == "unknown hardware; 1 run, 0.1 min"


def test_the_cpu_is_described_by_its_first_processor_and_widest_vector_extension():
    genoa = (
        "processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 17\n"
        "model name\t: AMD EPYC\nflags\t\t: fpu sse2 avx avx2 avx512f avx512bw\n\n"
        "processor\t: 1\nmodel name\t: other\nflags\t\t: sse2\n"
    )
    assert describe_cpuinfo(genoa) == "AMD EPYC, family 25 model 17, avx512"
    avx2 = "model name : Intel(R) Xeon(R) CPU\ncpu family : 6\nmodel : 85\nflags : sse2 avx2\n"
    assert describe_cpuinfo(avx2) == "Intel(R) Xeon(R) CPU, family 6 model 85, avx2"
    # an Arm machine's cpuinfo names no model, family or x86 extension
    arm = "processor : 0\nBogoMIPS : 50.00\nFeatures : fp asimd\n"
    assert describe_cpuinfo(arm) == describe_cpuinfo("")
    assert "," not in describe_cpuinfo("")


def test_libraries_name_the_installed_versions():
    import numpy as np

    versions = libraries()
    assert versions["numpy"] == np.__version__ and set(versions) >= {"numpy", "scipy"}


def test_json_safe_replaces_non_finite_floats_only():
    value = {"a": [1.0, math.nan, (math.inf, 2)], "b": "nan", "c": None, "d": 3}
    assert json_safe(value) == {"a": [1.0, None, [None, 2]], "b": "nan", "c": None, "d": 3}


@pytest.mark.parametrize(
    ("record", "match"),
    [
        ([], "expected a JSON object"),
        ({"format": "other", "version": 1}, "expected format"),
        ({"format": "vvloc.training", "version": 2}, "expected format"),
        ({"format": "vvloc.training", "version": 1, "runs": {}}, "'runs' must be a list"),
        ({"format": "vvloc.training", "version": 1, "runs": [{"processes": 3}]}, "processes"),
        ({"format": "vvloc.training", "version": 1, "runs": [{"seconds": "1"}]}, "'seconds'"),
        ({"format": "vvloc.training", "version": 1, "runs": []}, "'weights_hash'"),
        ({"format": "vvloc.training", "version": 1, "runs": [{"rigs": []}]}, r"runs\[0\].rigs: "),
        ({"format": "vvloc.training", "version": 1, "runs": [{"rigs": [[]]}]}, r"rigs\[0\]: "),
        ({"format": "vvloc.training", "version": 1, "runs": [{"rigs": [[3]]}]}, r"rigs\[0\]: "),
        (
            {"format": "vvloc.training", "version": 1, "runs": [{"rigs": [[{"name": "f"}]]}]},
            r"runs\[0\].rigs\[0\]: camera entry 'f' lacks keys",
        ),
        (
            {
                "format": "vvloc.training",
                "version": 1,
                "runs": [{}, {"rigs": [[_cam()], [_cam(fx=-1.0)]]}],
            },
            r"runs\[1\].rigs\[1\]: camera 'front': K must be a pinhole",
        ),
        (
            {"format": "vvloc.training", "version": 1, "runs": [{"rigs": [[_cam(), _cam(w=80)]]}]},
            r"rigs\[0\]: cameras of more than one image size",
        ),
        (
            {"format": "vvloc.training", "version": 1, "runs": [{"session_digests": ["0" * 15]}]},
            r"runs\[0\].session_digests must be a list of 16 hex digits",
        ),
        (
            {"format": "vvloc.training", "version": 1, "runs": [{"session_digests": "ab"}]},
            r"runs\[0\].session_digests",
        ),
    ],
)
def test_a_malformed_record_is_refused_naming_its_source(record, match):
    with pytest.raises(ValueError, match=f"src.json: .*{match}"):
        validate_record(record, "src.json")


def test_a_record_file_that_is_not_utf8_or_not_json_is_refused_naming_it(tmp_path):
    from vvloc.provenance import read_record

    path = tmp_path / "training.json"
    path.write_bytes(b'{"format": "caf\xe9"}')
    with pytest.raises(ValueError, match=r"training\.json: not a UTF-8 text file"):
        read_record(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match=r"training\.json: not JSON"):
        read_record(path)


def test_a_record_is_checked_before_it_is_written_and_numpy_numbers_are_plain(tmp_path):
    import numpy as np

    from vvloc.provenance import TRAINING_FORMAT, read_record, write_record

    path = tmp_path / "training.json"
    # each wrote a file that read_record then refused
    for args, error, match in (
        ((None, []), TypeError, r"^weights_hash: expected a str"),
        (("h", {"x": 1}), TypeError, r"^runs: expected a list"),
        (("h", [{"seconds": "5"}]), ValueError, r"'seconds' must be a number >= 0 or null"),
        (("h", [{"seconds": -1.0}]), ValueError, r"'seconds' must be a number >= 0 or null"),
    ):
        with pytest.raises(error, match=match):
            write_record(path, *args)
    assert not list(tmp_path.iterdir())
    write_record(
        path, "h", [{"seconds": np.float32(12.0), "steps": np.int64(3)}, {"seconds": math.nan}]
    )
    assert read_record(path)["runs"] == [{"seconds": 12.0, "steps": 3}, {"seconds": None}]
    assert json_safe({"a": np.float64("nan"), "b": [np.bool_(True)]}) == {"a": None, "b": [True]}
    for version in (True, 1.0):  # both equal 1
        with pytest.raises(ValueError, match=r"version"):
            validate_record({"format": TRAINING_FORMAT, "version": version, "runs": []}, "r")
    assert summarize({"format": "x"}) == "unknown hardware; 0 runs"  # was KeyError 'runs'


def test_describe_cpuinfo_names_text_that_is_no_str():
    with pytest.raises(TypeError, match=r"^text: expected the text of /proc/cpuinfo"):
        describe_cpuinfo(None)  # type: ignore[arg-type]


def test_json_nested_past_the_recursion_limit_is_named_as_a_bad_file(tmp_path):
    from vvloc.provenance import read_record
    from vvloc.targets import read_report

    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ValueError, match=r"deep\.json: not JSON"):
        read_record(deep)  # RecursionError
    with pytest.raises(ValueError, match=r"deep\.json: not a vvloc eval report"):
        read_report(deep)


def test_config_and_rig_json_nested_past_the_recursion_limit_are_named(tmp_path):
    from vvloc.data import DatasetFormatError
    from vvloc.data.vvloc_format import read_rig
    from vvloc.nets.model import _json_object

    deep = tmp_path / "rig.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ValueError, match=r"rig\.json: not a JSON file"):
        _json_object(deep)  # config.json, calibration.json: RecursionError
    with pytest.raises(DatasetFormatError, match=r"rig\.json: cannot read rig"):
        read_rig(deep)
