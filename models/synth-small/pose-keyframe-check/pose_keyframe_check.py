"""AOE/APE of the committed parking reports over the queries whose pose was built on a true
revisit (the keyframe ``metric_row``, chosen before the pose), beside the reports' rows over
the queries whose snapped top-1 is a true revisit (chosen with the pose).

    python models/synth-small/pose-keyframe-check/pose_keyframe_check.py data/synth-parking-96

The argument is any parking dataset of ``vvloc sim`` with seed 0 and 300 keyframes a session:
its map session s0 is the reports' (``data/synth-parking-110``'s s0 is the same drive); the
script checks that by counting the reports' true top-1s again from the map poses.
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np

from vvloc import evaluate
from vvloc.data import open_dataset

HERE = Path(__file__).parent
REPORTS = ("report-test96-local", "report-fresh-local")


def main() -> None:
    db = open_dataset(sys.argv[1]).session("s0")
    for name in REPORTS:
        folder = HERE.parent / name
        lines = [line for line in open(folder / "queries.csv") if not line.startswith("#")]
        rows = list(csv.DictReader(lines))
        gt = np.array([[float(r["gt_x"]), float(r["gt_y"])] for r in rows])
        yaw_err = np.array([float(r["yaw_err_deg"]) for r in rows])
        pos_err = np.array([float(r["pos_err_m"]) for r in rows])
        top1 = np.array([r["top1_correct"] == "1" for r in rows])
        metric_row = np.array([int(r["metric_row"]) for r in rows])
        map_row = np.array([int(r["map_row"]) for r in rows])
        kept = np.linalg.norm(db.poses[None, :, :2] - gt[:, None], axis=2).min(1) <= 2.0
        again = (np.linalg.norm(db.poses[map_row, :2] - gt, axis=1) <= 2.0) & kept
        if not np.array_equal(again, top1 & kept):
            sys.exit(f"{name}: the map poses do not give the report's true top-1s: another map")
        basis = (np.linalg.norm(db.poses[metric_row, :2] - gt, axis=1) <= 2.0) & kept
        report = json.loads((folder / "report.json").read_text())
        print(f"{name}: {int(kept.sum())} kept queries")
        for label, sel in (
            ("top-1 true revisit (report)", top1 & kept),
            ("pose's keyframe", basis),
        ):
            aoe = evaluate.error_percentiles(yaw_err[sel], (25, 50, 95))
            ape = evaluate.error_percentiles(pos_err[sel], (25, 50, 95))
            print(
                f"  {label:28s} n={int(sel.sum()):3d}  AOE@25/50/95 "
                + " / ".join(f"{v:.3f}" for v in aoe)
                + " deg  APE@25/50/95 "
                + " / ".join(f"{v:.3f}" for v in ape)
                + " m"
            )
        ml = report["pose_accuracy"]["VVLoc-ML"]["true_revisit"]
        print(
            f"  report.json true_revisit: n={ml['count']} AOE@50 {ml['AOE@50']:.3f} "
            f"APE@50 {ml['APE@50']:.3f}"
        )


if __name__ == "__main__":
    main()
