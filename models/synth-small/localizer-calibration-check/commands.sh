# The localizer-based calibration of the committed model and its check on the fresh sessions
# (2026-12-04). From the repository root, with data/synth-parking and data/synth-parking-110
# rendered as in MODEL_CARD.md; the calibration goes to a copy of the model.
set -e
PY=.venv/bin/python
$PY -c "from vvloc.nets import VVLocNet; VVLocNet.load('models/synth-small').save('/tmp/calx/model')"
$PY -m vvloc.cli calibrate --checkpoint /tmp/calx/model --dataset data/synth-parking --queries s18,s19 --every 3 --precision 0.9 --overwrite
$PY -m vvloc.cli eval --checkpoint /tmp/calx/model --dataset data/synth-parking-110 --database s0 --queries s96,s97,s98,s99,s101,s102,s103,s104,s106,s107,s108,s109 --every 5 --out /tmp/calx/report-fresh
