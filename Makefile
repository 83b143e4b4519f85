# egosim — every target that needs the environment depends on `setup`, so on a fresh clone
# `make dataset` or `make test` is the first and only command.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.stamp-setup
TORCH_VERSION := 2.13.0

# make dataset: INPUT (a video file/folder, frame folder or EgoDex folder; empty = synthetic world)
INPUT ?=
DATA ?= data/dataset
WORKFLOW ?= workflows/dataset.yaml
SET ?=
WORKERS ?=

.PHONY: setup test test-all lint format dataset check train train-ddp bench eval-real clean

setup: $(STAMP)

# Re-runs when pyproject.toml changes. open3d 0.20 needs Debian's libusb-1.0-0: installed here
# when missing (needs root, as on CI and the dev machines).
$(STAMP): pyproject.toml
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
		echo "installing libusb-1.0-0 (needed by open3d)"; \
		(apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >/dev/null || \
		{ echo "could not install libusb-1.0-0: run 'apt-get install libusb-1.0-0' as root"; exit 1; }; \
	fi
	# Debian's chromium: tests/test_report.py opens the HTML dataset report in it, headless
	# (the test skips without it). Not fatal: everything else works without a browser.
	@if ! command -v chromium >/dev/null 2>&1; then \
		echo "installing chromium (headless check of the HTML report)"; \
		(apt-get update -qq && apt-get install -y -qq chromium) >/dev/null || \
		echo "could not install chromium: run 'apt-get install chromium' as root (report test skips)"; \
	fi
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==$(TORCH_VERSION)
	$(BIN)/pip install -q -e ".[dev]"
	# MediaPipe Hands (hands stage backend `mediapipe`): only 0.10.21 ships its models in the wheel.
	# Its declared deps would downgrade numpy to 1.x (breaking pyarrow), add a second OpenCV
	# (opencv-contrib-python) and jax: install it without them, plus the few it really imports.
	# protobuf stays in pyproject's range (>=5.29.6 for foxglove, <6: protobuf 7 breaks Hands()).
	$(BIN)/pip install -q --no-deps mediapipe==0.10.21
	$(BIN)/pip install -q "absl-py>=2,<3" "flatbuffers>=24,<26" "attrs>=19.1" "matplotlib>=3.8,<4" \
		"protobuf>=5.29.6,<6"
	# A TFLite runtime to run MediaPipe's landmark model on chosen regions (tracking through misses:
	# on the real DWM clip 00013 left-hand recall 0.17 -> 1.0, right 0.42 -> 0.96).
	$(BIN)/pip install -q "ai-edge-litert==2.3.0"
	touch $(STAMP)

test: setup
	$(BIN)/python -m pytest -q

# Everything, including the slow end-to-end tests.
test-all: setup
	$(BIN)/python -m pytest -q -m ""

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: setup
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

# Build a dataset (from the synthetic world unless INPUT is given), then check every shard.
dataset: setup
	$(BIN)/egosim run $(WORKFLOW) --out $(DATA) $(if $(INPUT),--input $(INPUT)) \
		$(if $(WORKERS),--workers $(WORKERS)) $(foreach s,$(SET),--set $(s))
	$(BIN)/egosim check $(DATA)

check: setup
	$(BIN)/egosim check $(DATA)

# Train the `tiny` preset on the pack step of $(DATA) (what `make dataset` built): checkpoints,
# metrics, previews and RUN/sample.mp4 in $(RUN). 1000 steps at the pack size 32x56x9 took
# about 6 minutes on this 2-core machine with one torch thread per core (TRAIN_THREADS).
RUN ?= runs/tiny
TRAIN_STEPS ?= 1000
TRAIN_THREADS ?= $(shell nproc)
TRAIN_SET ?=
train: setup
	OMP_NUM_THREADS=$(TRAIN_THREADS) $(BIN)/egosim train --data $(DATA) --preset tiny --out $(RUN) \
		--steps $(TRAIN_STEPS) --set batch_size=2 --set optim.lr=5e-4 \
		--set optim.warmup_steps=50 --set checkpoint_every=500 $(foreach s,$(TRAIN_SET),--set $(s))

# The same training on TRAIN_RANKS processes (torchrun; gloo on CPU, NCCL + FSDP2 on GPUs):
# batch_size=1 per rank on 2 ranks is make train's global batch of 2.
TRAIN_RANKS ?= 2
train-ddp: setup
	OMP_NUM_THREADS=1 $(BIN)/torchrun --standalone --nproc_per_node $(TRAIN_RANKS) \
		-m egosim.pipeline.cli train --data $(DATA) --preset tiny --out $(RUN) \
		--steps $(TRAIN_STEPS) --set batch_size=1 --set optim.lr=5e-4 --set optim.warmup_steps=50 \
		--set checkpoint_every=500 $(foreach s,$(TRAIN_SET),--set $(s))

bench: setup
	$(BIN)/python -m bench.run

# The dataset workflow with default settings on every real video in ../shared/data: clips per
# video, frames posed, focal, metric scale, hand/surface depth ratio, scene render vs the DWM
# ground-truth static video (table, and runs/real/real_video.json). About 15 minutes on 2 cores.
eval-real: setup
	$(BIN)/python -m bench.real_video --out runs/real

clean:
	rm -rf $(VENV) data/dataset bench/results.jsonl
