# One target per stage; DATASET picks the profile (default: the built-in synthetic world).
#   make heatmaps DATASET=msc DATA_ROOT=/data/msc-rad4r/URBAN_D0
#   make evaluate DATASET=astyx DATA_ROOT=../shared/data/astyx_hires2019/dataset_astyx_hires2019
# DATASET and CACHE default to $PIPELINE_DATASET and $PIPELINE_CACHE, as the pipeline's options do
# (DATA_ROOT left empty lets the pipeline take $PIPELINE_DATA_ROOT or the cache's recorded root).
DATASET ?= $(or $(PIPELINE_DATASET),synthetic)
DATA_ROOT ?=
CACHE ?= $(or $(PIPELINE_CACHE),cache)
WORKERS ?=
ARGS ?=
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
PIPELINE := $(BIN)/pipeline
STAGES := calibrate heatmaps patches train synthesize export evaluate
# quoted: a folder name with spaces stays one argument (ARGS is left to the shell: several options)
q = '$(subst ','\'',$(1))'
RUN_OPTS = --dataset $(call q,$(DATASET)) --cache $(call q,$(CACHE)) $(if $(WORKERS),--workers $(WORKERS)) $(if $(DATA_ROOT),--data-root $(call q,$(DATA_ROOT))) $(ARGS)

.PHONY: help setup demo demo-large test bench soak status clean-cache $(STAGES)

$(BIN)/.installed: pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $@

setup: $(BIN)/.installed  ## create .venv and install the package with pinned dependencies

demo: setup  ## run the whole pipeline on the built-in synthetic world
	$(PIPELINE) run evaluate --dataset synthetic --cache $(call q,$(CACHE)) $(if $(WORKERS),--workers $(WORKERS)) $(ARGS)
	$(PIPELINE) run export --dataset synthetic --cache $(call q,$(CACHE)) $(if $(WORKERS),--workers $(WORKERS)) $(ARGS)
	@echo "report:  $(CACHE)/synthetic/evaluate/report.md"
	@echo "figures: $(CACHE)/synthetic/evaluate/figures/"
	@echo "export:  $(CACHE)/synthetic/export/"

# Dis-Net settings measured best on the 720- and 1200-frame worlds (docs/EXPERIMENTS.md, "Averaged weights ..."
# and "Refitting the count ..."): the speed also shapes the map, the count loss leaves the backbone
# alone, averaged weights, the best epoch picked by the map's val L_KL, brightness/contrast jitter,
# and the number branch refitted on the chosen backbone, starting from the mean count at the ego speed.
LARGE_SETTINGS := --set disnet.speed_map=true --set train.count_grad_scale=0 --set train.ema_decay=0.99 \
	--set train.select_on=kl --set train.jitter=0.3 --set train.count_refit_epochs=50 \
	--set disnet.speed_count_prior=true

demo-large: setup  ## the demo on a 2400-frame world, 12 epochs (about 70 minutes on 2 cores): the fidelity figures
	$(MAKE) demo CACHE=cache-large ARGS="--set dataset.world_frames=2400 --set train.epochs=12 $(LARGE_SETTINGS) $(ARGS)"

# the suite in TEST_WORKERS processes (pytest-xdist), each test file's tests in one of them (its
# module fixtures made once); TEST_WORKERS=1: in this process
TEST_WORKERS ?= 2

test: setup  ## the test suite (about 5 minutes on 2 cores)
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -p no:cacheprovider $(if $(filter-out 1,$(TEST_WORKERS)),-n $(TEST_WORKERS) --dist loadfile) tests

bench: setup  ## speed benchmarks: one line per benchmark ending in the measured ratio
	@for f in tests/benchmarks/bench_*.py; do OMP_NUM_THREADS=1 $(BIN)/python $$f || exit 1; done

soak: setup  ## long crash-resume soak: SIGKILL stages at random moments, compare with a clean run
	$(BIN)/python -m tests.soak --kills 30

help:  ## this list of targets and the variables they take
	@awk -F':.*## ' '/^[a-z-]+:.*## / {printf "  make %-12s %s\n", $$1, $$2}' $(firstword $(MAKEFILE_LIST))
	@echo "  make STAGE        pipeline run STAGE, one target per stage: $(STAGES)"
	@echo "variables: DATASET=$(DATASET) DATA_ROOT=$(DATA_ROOT) CACHE=$(CACHE) WORKERS=$(WORKERS) ARGS=$(ARGS)"

status: setup  ## pipeline status for DATASET and CACHE
	$(PIPELINE) status --dataset $(call q,$(DATASET)) --cache $(call q,$(CACHE)) $(if $(DATA_ROOT),--data-root $(call q,$(DATA_ROOT)))

$(STAGES): setup
	$(PIPELINE) run $@ $(RUN_OPTS)

# refuses an empty CACHE or a DATASET that is no single folder name: `rm -rf cache/` (DATASET=)
# would delete every dataset's cache, and `rm -rf /` (CACHE= DATASET=) worse
clean-cache:  ## delete CACHE/DATASET
	@case $(call q,$(strip $(DATASET))) in ''|.|..|*/*) echo "clean-cache: DATASET='$(DATASET)' is no dataset name: nothing deleted" >&2; exit 2;; esac
	@case $(call q,$(strip $(CACHE))) in '') echo "clean-cache: CACHE is empty: nothing deleted" >&2; exit 2;; esac
	rm -rf $(call q,$(CACHE)/$(DATASET))
