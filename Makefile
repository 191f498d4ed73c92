# vvloc: every target bootstraps .venv and builds the Rust extension first.
#   make test    cargo tests of the core crate (release, then debug) + pytest of the package
#   make bench   kernel benchmarks: table on stdout, JSON in bench-results/
#   make lint    cargo fmt/clippy, ruff, mypy of the package and stubtest of the extension
#   make demo    end-to-end demo (see README)
#   make model   the committed small model from scratch (five steps, 46-80 min on 2 cores; the
#                committed bytes on the two AMD EPYC CPUs checked, other weights may come
#                elsewhere: models/synth-small/MODEL_CARD.md)
#   make model-test  the committed model's test on what make model trained (CHECKPOINT=...),
#                against the issue's targets (≈ 8 min, plus ≈ 15-25 min rendering the first time)
#   make model-v3  the recipe of the previous default, models/synth-small-v3 (in a clean runs/)
#   make model-garage  the garage variant models/synth-small-garage from models/synth-small-v1 (≈ 53 min)
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PYTEST_ARGS ?=

.PHONY: venv develop test test-rust test-python bench lint demo model model-v3 model-test model-garage clean

$(VENV)/.deps-stamp: pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -c "import tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; \
	  print('\n'.join(p['dependencies'] + p['optional-dependencies']['dev']))" > $(VENV)/requirements.txt
	$(PY) -m pip install -q -r $(VENV)/requirements.txt
	touch $@

venv: $(VENV)/.deps-stamp

# flock: concurrent builds (several shells, IDE + terminal) must not race on the install.
develop: venv
	flock $(VENV)/.build.lock env VIRTUAL_ENV=$(CURDIR)/$(VENV) PATH=$(CURDIR)/$(VENV)/bin:$$PATH \
	  $(PY) -m maturin develop --release -q

# release (what users run) and debug (integer overflow checks and debug assertions on)
test-rust:
	cargo test -p vvloc-core --release
	cargo test -p vvloc-core

test-python: develop
	@rc=0; $(PY) -m pytest $(PYTEST_ARGS) || rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: that is a failure here" >&2; exit 1; fi; \
	exit $$rc

test: test-rust test-python

bench: develop
	$(PY) benches/run.py

lint: develop
	cargo fmt --all --check
	cargo clippy --workspace --all-targets --release -- -D warnings
	$(PY) -m ruff check python tests benches
	$(PY) -m ruff format --check python tests benches
	$(PY) -m mypy python/vvloc
	$(PY) -m mypy.stubtest vvloc._core

demo: develop
	$(PY) -m vvloc.cli demo

# the five steps of models/synth-small, each config:run folder: stages 1-2 on the parking lot
# with the re-ranking loss (GeM head), the head stage on it (NetVLAD, three worlds), the floor
# fine-tune (stage 2 on three worlds, 6 epochs), the head stage again and the local stage
# (decoder + interactor with the near translation loss); runs/synth-small-local/best/ is the
# model (models/synth-small, byte for byte on the two AMD EPYC CPUs checked). Re-running it
# resumes or skips what a previous run already did; delete runs/synth-small* left from another
# recipe first.
# `make model-v3` runs models/synth-small-v3's recipe: configs/synth-small.yaml (the paper's
# losses only) as step 1. tests/test_train.py holds the chain of run folders to the
# configs' init_checkpoint and to the committed model's training record.
MODEL_STEPS = synth-small-rerank:synth-small synth-small-head:synth-small-head \
  synth-small-ft:synth-small-ft synth-small-ft-head:synth-small-ft-head \
  synth-small-local:synth-small-local
V3_STEPS = synth-small:synth-small $(wordlist 2,4,$(MODEL_STEPS))

model: develop
	for step in $(MODEL_STEPS); do \
	  cfg=$${step%%:*}; out=runs/$${step#*:}; \
	  $(PY) -m vvloc.cli train --config configs/$$cfg.yaml --out $$out \
	    $$(test -e $$out/trainer_state.pt && echo --resume) || exit 1; \
	done

model-v3:
	$(MAKE) model MODEL_STEPS="$(V3_STEPS)"

# the committed model's test (models/synth-small/MODEL_CARD.md, "Against the issue's targets")
# on CHECKPOINT (default: what `make model` trained): renders the three test datasets when they
# are missing (≈ 15-25 min for the three on 2 cores), evaluates (≈ 8 min) into TEST_OUT and prints the
# issue's figures against their targets (`vvloc targets`; TEST_OUT/targets.json)
CHECKPOINT ?= runs/synth-small-local
TEST_OUT ?= runs/model-test
model-test: develop
	test -d data/synth-parking-96 || $(PY) -m vvloc.cli sim --scene parking --sessions 96 \
	  --frames 300 --seed 0 --out data/synth-parking-96
	test -d data/synth-garage-pillars-88 || $(PY) -m vvloc.cli sim --scene garage --floors 2 \
	  --floor_marking pillars --sessions 88 --frames 300 --seed 0 --out data/synth-garage-pillars-88
	test -d data/synth-garage-56 || $(PY) -m vvloc.cli sim --scene garage --floors 2 \
	  --sessions 56 --frames 300 --seed 0 --out data/synth-garage-56
	$(PY) -m vvloc.cli eval --checkpoint $(CHECKPOINT) --dataset data/synth-parking-96 \
	  --database s0 --queries s81,s82,s83,s84,s86,s87,s88,s89,s91,s92,s93,s94 --every 5 \
	  --out $(TEST_OUT)/parking
	$(PY) -m vvloc.cli eval --checkpoint $(CHECKPOINT) --dataset data/synth-garage-pillars-88 \
	  --database s80 --queries s81,s82,s83,s84,s85,s86,s87 --every 60 --loops \
	  --out $(TEST_OUT)/pillars
	$(PY) -m vvloc.cli eval --checkpoint $(CHECKPOINT) --dataset data/synth-garage-56 \
	  --database s48 --queries s49,s50,s51,s52,s53,s54,s55 --every 60 --loops \
	  --out $(TEST_OUT)/garage
	$(PY) -m vvloc.cli targets --parking $(TEST_OUT)/parking --pillars $(TEST_OUT)/pillars \
	  --garage $(TEST_OUT)/garage --out $(TEST_OUT)/targets.json

# the garage variant: two fine-tunes of the committed models/synth-small-v1 (the default model
# until 2026-12-02, the output of the first two steps of v3's recipe: configs/synth-small.yaml
# and -head) and a head stage
model-garage: develop
	for step in ft ft2 ft-head64; do \
	  out=runs/synth-small-garage-$$step; \
	  $(PY) -m vvloc.cli train --config configs/synth-small-garage-$$step.yaml --out $$out \
	    $$(test -e $$out/trainer_state.pt && echo --resume) || exit 1; \
	done

clean:
	rm -rf target $(VENV) bench-results
