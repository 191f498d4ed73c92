"""Compare this run's training logs with the committed model's, field by field, epoch by epoch
as far as this run went (times and the device left out): ``python compare_logs.py`` from this folder. Prints each differing field with
both values, then a summary."""

import json
import math
from pathlib import Path

HERE = Path(__file__).parent
COMMITTED = {
    "synth-small": "train_log-step1.jsonl",
    "synth-small-head": "train_log-head.jsonl",
    "synth-small-ft": "train_log-ft.jsonl",
    "synth-small-ft-head": "train_log.jsonl",
    "synth-small-local": "train_log-local.jsonl",
}


def flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(flat(v, f"{prefix}{k}."))
        elif not any(s in k for s in ("seconds", "device", "time")):
            out[prefix + k] = v
    return out


fields = differing = 0
for run, committed in COMMITTED.items():
    mine = [flat(json.loads(line)) for line in open(HERE / f"log-{run}.jsonl")]
    theirs = [flat(json.loads(line)) for line in open(HERE.parent / committed)]
    # step 1 stops early after epoch 22 (patience); the committed run went on to epoch 29
    assert len(mine) <= len(theirs), run
    for a, b in zip(mine, theirs):
        for key in sorted(set(a) | set(b)):
            fields += 1
            x, y = a.get(key), b.get(key)
            if x == y:
                continue
            differing += 1
            if isinstance(x, float) and isinstance(y, float):
                note = f"relative {abs(x - y) / abs(y):.1e}"
            elif x is None and isinstance(y, float) and not math.isfinite(y):
                note = "null now, non-finite then (JSON of today's logs)"
            else:
                note = "other"
            print(f"{run} epoch {a.get('epoch')}: {key}: {x!r} vs {y!r} ({note})")
print(f"{differing} of {fields} logged values differ")
