"""The training record's one-line summary and its validation, on hand-made records."""

from __future__ import annotations

import pytest

from vvloc.provenance import summarize, validate_record


def _run(seconds: float, device: str = "cpu", **kw) -> dict:
    return {"hardware": "x86_64, 2 cores", "device": device, "seconds": seconds} | kw


def test_summary_names_hardware_runs_and_minutes():
    assert summarize(None).startswith("not recorded")
    assert summarize({}).startswith("not recorded")
    one = {"runs": [_run(90.0)]}
    assert summarize(one) == "x86_64, 2 cores (cpu); 1 run, 1.5 min"
    four = {"runs": [_run(4020.0), _run(252.0), _run(684.0), _run(294.0)]}
    assert summarize(four) == "x86_64, 2 cores (cpu); 4 runs, 87.5 min (67.0 + 4.2 + 11.4 + 4.9)"
    mixed = {"runs": [_run(60.0), _run(30.0, "cuda (NVIDIA H200)")]}
    assert summarize(mixed) == (
        "x86_64, 2 cores (cpu); x86_64, 2 cores (cuda (NVIDIA H200)); 2 runs, 1.5 min (1.0 + 0.5)"
    )
    partial = {"runs": [{"recorded": False, "weights_hash": "ab"}, _run(60.0, complete=False)]}
    assert summarize(partial) == (
        "x86_64, 2 cores (cpu); 1 run, 1.0 min, after 1 earlier run not recorded "
        "(a run still in progress)"
    )
    unknown = {"runs": [_run(60.0), {"hardware": "x86_64, 2 cores", "device": "cpu"}]}
    assert summarize(unknown) == (
        "x86_64, 2 cores (cpu); 2 runs, 1.0 min, time not recorded for 1 run"
    )


@pytest.mark.parametrize(
    ("record", "match"),
    [
        ([], "expected a JSON object"),
        ({"format": "other", "version": 1}, "expected format"),
        ({"format": "vvloc.training", "version": 1, "runs": {}}, "'runs' must be a list"),
        ({"format": "vvloc.training", "version": 1, "runs": []}, "'weights_hash'"),
    ],
)
def test_a_malformed_record_is_refused_naming_its_source(record, match):
    with pytest.raises(ValueError, match=f"src.json: {match}"):
        validate_record(record, "src.json")
