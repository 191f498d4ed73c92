#!/usr/bin/env bash
# The loop edges and localize answers of models/synth-small on a small parking set, against the
# ground truth (README, "pinned to (0, 0)"). Run from the repository root after `make develop`:
#   bash models/synth-small/loop-edge-check/run.sh [WORK_DIR]   (about 5 min on 2 cores)
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
work=${1:-runs/loop-edge-check}
ck=models/synth-small
py=${PYTHON:-.venv/bin/python}
vvloc=${VVLOC:-.venv/bin/vvloc}
mkdir -p "$work"
[ -d "$work/data" ] || "$vvloc" sim --scene parking --sessions 2 --frames 40 --seed 0 --out "$work/data"
"$vvloc" map build --checkpoint $ck --dataset "$work/data" --sessions s0,s1 --out "$work/map.h5" --overwrite
"$vvloc" map build --checkpoint $ck --dataset "$work/data" --sessions s0 --out "$work/map-s0.h5" --overwrite
"$vvloc" loops --map "$work/map.h5" --out "$work/loops" --checkpoint $ck
"$vvloc" loops --map "$work/map.h5" --out "$work/loops-seq0" --sequence 0 --checkpoint $ck
"$vvloc" localize --map "$work/map-s0.h5" --dataset "$work/data" --session s1 --out "$work/loc" --checkpoint $ck --no_snap --threads 1
{
  echo "## vvloc loops, defaults (sequence check on)"; "$py" "$here/edge_errors.py" "$work/loops"
  echo; echo "## vvloc loops --sequence 0 (single keyframes)"; "$py" "$here/edge_errors.py" "$work/loops-seq0"
  echo; echo "## the --sequence 0 pairs verified in both directions"
  "$py" "$here/both_dirs.py" "$work/map.h5" "$work/loops-seq0" $ck
  echo; echo "## vvloc localize --no_snap: s1's 40 frames against a map of s0"
  "$py" "$here/pinned_queries.py" "$work/data" s0 s1 "$work/loc"
} | tee "$work/output.txt"
