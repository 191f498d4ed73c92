"""The small model's targets on the synthetic benchmark, checked against ``vvloc eval`` reports.

The figures are those the training issue asks of a trained small model (the paper's best NCLT
figures), read from the ``report.json`` of three evaluations of one checkpoint (the test of
``models/synth-small/MODEL_CARD.md``, which ``make model-test`` runs):

- ``parking``: ``vvloc eval`` on held-out parking-lot sessions (no ``--loops`` needed):
  Recall@1 (2 m) after metric re-ranking (``VVLoc-ML``) ≥ 80.6 %, its gain over retrieval alone
  (``VVLoc-G``) ≥ +3 points, AOE/APE@50 % ≤ 1.6° / 0.7 m and @25 % ≤ 0.7° / 0.3 m over the
  queries whose top-1 is a true revisit;
- ``pillars`` and ``garage``: ``vvloc eval --loops`` on a 2-floor garage (with floor-marked
  pillars, and the default one whose floors differ only in parked cars and wall signs): CFER ≤
  0.26 % (the share of accepted loop closures that join two floors), for the loop detector with
  its sequence check and for single keyframes, at the report's descriptor threshold, by the
  descriptors alone: the report's rows with the loop detector's floor check
  (``vvloc.localize.loops.floor_consensus``) are not the issue's figures (the check keeps loops
  to the floor numbers the sessions record, the labels CFER is scored against) and are left out;
- the training time recorded with the weights (their ``training.json``, as the report carries
  it) ≤ 90 min (on 2 CPU cores, or the hardware the record names).

Nothing here computes a metric: every value is the report's (:mod:`vvloc.evaluate` defines
them); this module only compares. It imports no torch.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

REPORT_FILE = "report.json"


@dataclass(frozen=True)
class Figure:
    """One target figure. ``number`` is the value in the unit of ``target`` (percent, points,
    degrees, metres or minutes), ``value`` the same as printed; both say "n/a" / None when the
    report lacks it or was not given, and then ``met`` is None."""

    name: str
    target: str  # e.g. ">= 80.6 %"
    value: str  # as printed, e.g. "82.2 %"
    met: bool | None
    detail: str = ""
    number: float | None = None


def read_report(path: str | Path) -> dict[str, Any]:
    """The ``report.json`` of a ``vvloc eval`` report folder (or the file itself)."""
    path = Path(path)
    if path.is_dir():
        path = path / REPORT_FILE
    if not path.is_file():
        raise FileNotFoundError(f"no vvloc eval report at {path}: run vvloc eval --out first")
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:  # too deep nesting
        raise ValueError(f"{path}: not a vvloc eval report (not JSON: {e})") from None
    if not isinstance(report, dict) or not isinstance(report.get("meta"), dict):
        raise ValueError(f"{path}: not a vvloc eval report (no 'meta' object)")
    return report


def _shown(value: float, fmt: str, met: bool, passes: Callable[[float], bool]) -> str:
    """``value`` formatted with ``fmt``, with two more digits where the rounded text would
    pass or fail the target differently from ``value`` itself (80.597 % is "80.597 %" against
    ">= 80.6 %", not a missed "80.6 %")."""
    text = f"{value:{fmt}}"
    if passes(float(text)) != met:
        digits = int(fmt.rstrip("f").split(".")[-1] or 0) + 2
        text = f"{value:{fmt[: fmt.index('.')]}.{digits}f}"
    return text


def _number(value: Any, where: str, high: float = math.inf) -> float:
    """``value`` as a float in [0, ``high``] (NaN kept: undefined), ``ValueError`` naming
    ``where`` otherwise: a share of 90.0 (a percentage) read as 9000 % and met the target."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where}: expected a number, got {value!r:.40}")
    v = float(value)
    if not (math.isnan(v) or 0.0 <= v <= high):
        raise ValueError(f"{where}: expected a value in [0, {high:g}], got {value!r}")
    return v


def _count(value: Any, where: str) -> int:
    """``value`` as an int >= 0, ``ValueError`` naming ``where`` otherwise (2.5, NaN, inf)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{where}: expected a count (an int >= 0), got {value!r:.40}")
    return value


def _at_most(name: str, value: float | None, limit: float, unit: str, fmt: str) -> Figure:
    if value is None or not math.isfinite(value):
        return Figure(name, f"<= {limit:{fmt}}{unit}", "n/a", None)
    met = value <= limit
    shown = _shown(value, fmt, met, lambda v: v <= limit)
    return Figure(name, f"<= {limit:{fmt}}{unit}", f"{shown}{unit}", met, number=value)


def _parking(report: Mapping[str, Any]) -> list[Figure]:
    gl = report.get("global_localization", {})
    try:
        kept = _count(gl["VVLoc-ML"]["num_kept"], "VVLoc-ML num_kept")
        if kept > 0:  # without a kept query (none within 2 m of the map) recall is undefined
            reranked = _number(gl["VVLoc-ML"]["recall"]["1"]["2"], "VVLoc-ML Recall@1 (2 m)", 1)
            retrieval = _number(gl["VVLoc-G"]["recall"]["1"]["2"], "VVLoc-G Recall@1 (2 m)", 1)
    except (KeyError, TypeError) as e:
        raise ValueError(
            f"parking report: no Recall@1 at 2 m for VVLoc-ML and VVLoc-G ({e})"
        ) from e
    recall_name, recall_target = "parking: Recall@1 (2 m) re-ranked", ">= 80.6 %"
    gain_name, gain_target = "parking: gain of re-ranking over retrieval alone", ">= +3.0 points"
    none_kept = "0 kept queries (none has a map keyframe within 2 m)"
    if kept == 0:
        figures = [
            Figure(recall_name, recall_target, "n/a", None, none_kept),
            Figure(gain_name, gain_target, "n/a", None, none_kept),
        ]
    else:
        recall_met = reranked >= 0.806
        gain = reranked - retrieval
        gain_met = gain >= 0.03 - 1e-12
        figures = [
            Figure(
                recall_name,
                recall_target,
                _shown(100 * reranked, ".1f", recall_met, lambda v: v >= 80.6) + " %",
                recall_met,
                f"{kept} kept queries",
                100 * reranked,
            ),
            Figure(
                gain_name,
                gain_target,
                _shown(100 * gain, "+.1f", gain_met, lambda v: v >= 3.0 - 1e-10) + " points",
                gain_met,
                f"retrieval alone {100 * retrieval:.1f} %",
                100 * gain,
            ),
        ]
    pose = report.get("pose_accuracy", {}).get("VVLoc-ML", {}).get("true_revisit", {})
    count = pose.get("count")
    for pct, aoe, ape in ((50, 1.6, 0.7), (25, 0.7, 0.3)):
        for kind, limit, unit in (("AOE", aoe, "°"), ("APE", ape, " m")):
            value = pose.get(f"{kind}@{pct}") if kept else None
            fig = _at_most(
                f"parking: {kind}@{pct} % (true revisits)",
                None if value is None else _number(value, f"pose_accuracy {kind}@{pct}"),
                limit,
                unit,
                ".2f",
            )
            figures.append(replace(fig, detail=f"{count} queries" if kept else none_kept))
    return figures


def _cfer(report: Mapping[str, Any], world: str) -> list[Figure]:
    loops = report.get("loop_closure")
    if not loops:
        raise ValueError(f"{world} report: no loop_closure (evaluate it with vvloc eval --loops)")
    figures = []
    variants = {
        ("sequence-checked" if "sequence" in key else "single keyframes"): entry
        for key, entry in loops.items()
        if "floor consensus" not in key  # not the figure (module docstring)
    }
    for label in ("single keyframes", "sequence-checked"):
        entry = variants.get(label)
        if entry is None:  # e.g. vvloc eval --loop_sequence 0: the figure is not in the report
            missing = "not in the report (vvloc eval --loops with --loop_sequence >= 1)"
            figures.append(Figure(f"{world}: CFER, {label}", "<= 0.26 %", "n/a", None, missing))
            continue
        at = entry["at_threshold"]
        where = f"{world} report: loop_closure[{label}]"
        accepted = _count(at["accepted"], f"{where} accepted")
        cfer = None if at["cfer"] is None else _number(at["cfer"], f"{where} cfer", 1)
        if cfer is not None and math.isnan(cfer):
            cfer = None  # undefined: nothing accepted
        cross = round(cfer * accepted) if accepted and cfer is not None else 0
        value = None if cfer is None else 100.0 * cfer
        fig = _at_most(f"{world}: CFER, {label}", value, 0.26, " %", ".2f")
        precision = at.get("precision")  # None (JSON null) when nothing is accepted
        shown = "n/a" if precision is None else f"{100 * float(precision):.1f} %"
        detail = f"{cross} of {accepted} accepted loops join two floors (threshold "
        detail += f"{at['threshold']:g}, precision@2m {shown})"
        figures.append(replace(fig, detail=detail))
    return figures


def _training_time(report: Mapping[str, Any]) -> Figure:
    # "training": null for weights without a record; a run stored as recorded: false (an
    # init checkpoint that had none) took time nobody measured, so the sum would only be a
    # lower bound
    runs = (report.get("training") or {}).get("runs") or []
    seconds = [r.get("seconds") for r in runs]
    name = "training time"
    if not runs or None in seconds or not all(r.get("recorded", True) for r in runs):
        return Figure(name, "<= 90 min", "n/a", None, "the weights carry no complete record")
    minutes = sum(_number(s, "training seconds") for s in seconds) / 60.0
    return Figure(
        name,
        "<= 90 min",
        f"{minutes:.1f} min",
        minutes <= 90.0,
        str(report.get("meta", {}).get("trained_on", "")),
        minutes,
    )


#: The world each report must be of, as ``vvloc eval`` records it (``meta.scene``, from the
#: dataset's ``rig.json``); reports without it (other data, older reports) are not checked.
WORLDS: dict[str, dict[str, Any]] = {
    "parking": {"scene": "parking"},
    "pillars": {"scene": "garage", "floor_marking": "pillars"},
    "garage": {"scene": "garage", "floor_marking": "walls"},
}


#: The note ``vvloc eval`` writes when the checkpoint's training record lists query sessions
#: (what reports before ``meta.trained_on_queries`` have to tell it).
TRAINED_ON_NOTE = "were trained on** (the checkpoint's training record)"


def _check_held_out(name: str, report: Mapping[str, Any]) -> None:
    """``ValueError`` when the report's queries were trained on: the targets are figures of
    held-out sessions."""
    seen = (report.get("meta") or {}).get("trained_on_queries")
    if seen is None:  # reports before 2026-12-05 say it in a note only
        notes = report.get("notes") or []
        seen = ["(see the report's notes)"] if any(TRAINED_ON_NOTE in str(n) for n in notes) else []
    if seen:
        raise ValueError(
            f"--{name}: the report's query sessions {seen} were trained on (the checkpoint's "
            "training record): the targets are figures of held-out sessions"
        )


def _check_world(name: str, report: Mapping[str, Any]) -> None:
    scene = (report.get("meta") or {}).get("scene")
    if not isinstance(scene, Mapping):
        return
    wrong = {k: scene.get(k) for k, v in WORLDS[name].items() if scene.get(k, v) != v}
    if wrong:
        raise ValueError(
            f"--{name}: the report is of {dict(scene)}, expected a world with {WORLDS[name]}"
        )


def check_targets(
    parking: Mapping[str, Any],
    pillars: Mapping[str, Any] | None = None,
    garage: Mapping[str, Any] | None = None,
) -> list[Figure]:
    """Compare the reports of one checkpoint with the targets (module docstring).

    ``parking``, ``pillars``, ``garage``: parsed ``report.json`` of ``vvloc eval`` (the garages
    evaluated with ``--loops``; either may be None: its CFER is then listed as not evaluated).
    Raises ``ValueError`` when a report lacks its figures or holds them in another shape (a
    hand-edited file), when the reports are of different weights (``meta.model_weights_hash``),
    or when a report's query sessions were trained on (``meta.trained_on_queries``, or the note
    of older reports)."""
    try:
        return _check_targets(parking, pillars, garage)
    except (AttributeError, TypeError) as e:  # a section that is not an object, e.g. a list
        raise ValueError(f"malformed report: a section is not what vvloc eval writes ({e})") from e
    except KeyError as e:  # e.g. a loop-closure entry without its at_threshold
        raise ValueError(f"malformed report: no {e} where vvloc eval writes one") from e


def _check_targets(
    parking: Mapping[str, Any],
    pillars: Mapping[str, Any] | None = None,
    garage: Mapping[str, Any] | None = None,
) -> list[Figure]:
    reports = {"parking": parking, "pillars": pillars, "garage": garage}
    hashes = {
        name: r.get("meta", {}).get("model_weights_hash")
        for name, r in reports.items()
        if r is not None
    }
    if len(set(hashes.values())) > 1:
        raise ValueError(f"the reports are of different weights: {hashes}")
    for name, report in reports.items():
        if report is not None:
            _check_world(name, report)
            _check_held_out(name, report)
    figures = _parking(parking)
    for world, report in (("pillar garage", pillars), ("default garage", garage)):
        if report is None:
            figures.append(Figure(f"{world}: CFER", "<= 0.26 %", "not evaluated", None))
        else:
            figures += _cfer(report, world)
    figures.append(_training_time(parking))
    return figures


def targets_markdown(figures: list[Figure], weights_hash: str | None = None) -> str:
    """A Markdown table of ``figures`` (figure, target, value, met, detail)."""
    lines = []
    if weights_hash:
        lines.append(f"Weights `{weights_hash[:16]}`.\n")
    lines += ["| figure | target | value | | detail |", "|---|---|---|---|---|"]
    for f in figures:
        met = {True: "met", False: "**missed**", None: "n/a"}[f.met]
        lines.append(f"| {f.name} | {f.target} | {f.value} | {met} | {f.detail} |")
    missed = [f.name for f in figures if f.met is False]
    lines.append("")
    lines.append(
        f"{len(missed)} of {len(figures)} figures missed: {'; '.join(missed)}."
        if missed
        else f"Every one of the {len(figures)} figures is met."
        if all(f.met is not None for f in figures)
        else "No figure is missed, but not every figure was evaluated."
    )
    return "\n".join(lines) + "\n"


def figures_json(figures: list[Figure]) -> list[dict[str, Any]]:
    """``figures`` as plain dicts (JSON serialisable)."""
    return [asdict(f) for f in figures]
