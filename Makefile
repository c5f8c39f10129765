# TopoCut — one entry point per stage; `make run` runs the whole pipeline at smoke scale on CPU.
PY      ?= python3
VENV    ?= .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.stamp-setup
ARGS    ?=
TASK    ?= slice
SCALE   ?= smoke
RUN     := $(BIN)/python -m topocut.run scale=$(SCALE) task=$(TASK)

.PHONY: setup run test lint bench simulate mppi teleop pretrain bc eval sweep paper paper-data table2 clean-outputs

setup: $(STAMP)

# torch first, pinned to the CPU build on disk; then the project. Re-runs only when pyproject changes.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "torch==2.13.0"
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $(STAMP)

run: setup
	$(RUN) stage=all logger=csv $(ARGS)

# pytest-xdist: a worker per core, each test file whole on one worker (its module fixtures built once): 25 -> 17 min
# on the 2-core machine when it was measured; on 2026-11-29 the same machine took 40 min, 33 with OMP_NUM_THREADS=1
# and Taichi's kernel cache no longer evicting (topocut.sim.runtime.offline_cache_size); 26:40 on 2026-11-30 with a fresh
# Taichi runtime per test file (tests/conftest.py: its kernels then hit the cache whatever ran before them on the
# worker; 59 min on the run that filled the cache, beside other work); 22:37 on 2026-11-30 (Taichi's source excerpts
# memoised, Lightning imported by the trainings only, the longest files first: tests/conftest.py LONGEST_FIRST, with
# --no-loadscope-reorder, else pytest-xdist orders files by their number of tests); 19:57 on 2026-11-30 (user 42.5 ->
# 37.0 min: the stage runs forked from a server that imported torch, Taichi and Lightning once, tests/stage_runner.py;
# one Taichi thread's scatter a serial loop without atomics, docs/sim.md "Determinism").  TEST_WORKERS=0 runs in one
# process.  OMP_NUM_THREADS=1 and TI_CPU_MAX_NUM_THREADS=1: the stages a test starts as processes train tiny models
# and simulate small scenes, where a second thread beside the other worker only spins (tests/conftest.py's
# one_thread and its single-threaded Taichi do the same inside the workers).
TEST_WORKERS ?= auto
test: setup
	WANDB_MODE=disabled OMP_NUM_THREADS=1 TI_CPU_MAX_NUM_THREADS=1 $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder $(ARGS)

lint: setup
	$(BIN)/ruff check topocut pipelines tests benchmarks

bench: setup
	$(BIN)/python benchmarks/sim_throughput.py --quick
	$(BIN)/python benchmarks/cut_parts.py --device cpu --n-grid 32 --batch 2 --cuts 1
	$(BIN)/python benchmarks/p2g_variants.py --grid 32 --batches 1 4 --steps 20
	$(BIN)/python benchmarks/topology.py --quick
	$(BIN)/python benchmarks/reward.py --batch 16
	$(BIN)/python benchmarks/reward_kernels.py --repeat 1
	$(BIN)/python benchmarks/mppi.py --K 4 --n-grid 32
	$(BIN)/python benchmarks/train.py --steps 3
	$(BIN)/python benchmarks/train_policy.py --blocks 2 --batch 8 --steps 8 32

simulate mppi pretrain bc eval: setup
	$(RUN) stage=$@ $(ARGS)

teleop: setup
	$(RUN) stage=teleop $(ARGS)

# Hydra multirun: 2 tasks x 2 objects on the joblib launcher, shards merged into one dataset version.
sweep: setup
	$(BIN)/python -m topocut.run -m stage=mppi task=slice,stick object=cake,cube hydra/launcher=joblib $(ARGS)
	$(BIN)/python -m topocut.run stage=merge $(ARGS)

# The paper's pipeline at paper scale on one GPU, one command (resumes where a killed run stopped; docs/results.md):
# 1,005 MPPI demonstrations (slice, stick, dice x 5 seen objects), pretraining, 4 learned policies x 3 seeds, and
# the 405-episode evaluation of every policy. `make run` is the same command at smoke scale on the CPU.
# MPS=1 (default): under CUDA's Multi-Process Service when the driver has it and no daemon runs yet (started here,
# stopped after), so that the 16 demonstration / evaluation processes' kernels share the GPU at once instead of
# taking turns: 1.6x the demonstrations per hour of 16 processes without it on one H100 (docs/benchmarks.md).
MPS ?= 1
PAPER_CMD = $(BIN)/python -m topocut.run stage=all scale=paper device=cuda reward=torch trainer=gpu logger=csv $(ARGS)
paper: setup
	@mine=0; if [ "$(MPS)" = 1 ] && command -v nvidia-cuda-mps-control >/dev/null 2>&1 \
	  && ! pgrep -x nvidia-cuda-mps >/dev/null 2>&1; then nvidia-cuda-mps-control -d && mine=1 \
	  && echo "MPS daemon started (MPS=0 runs without it)"; fi; \
	$(PAPER_CMD); rc=$$?; [ $$mine = 1 ] && echo quit | nvidia-cuda-mps-control; exit $$rc

# The same demonstrations as a Hydra multirun (a job per cell: joblib here, submitit on Slurm), merged.
paper-data: setup
	$(BIN)/python -m topocut.run -m scale=paper stage=mppi task=slice,stick,dice \
		object=cake,cube,ditto,ham,potato hydra/launcher=joblib $(ARGS)
	$(BIN)/python -m topocut.run scale=paper stage=merge $(ARGS)

# Paper Table 2: graph model sort x noise x 128/256 points and PointNet, on the latest dataset, then the table.
table2: setup
	$(BIN)/python -m topocut.run -m stage=pretrain scale=$(SCALE) model.sort=false,true model.noise=false,true \
		model.num_points=128,256 hydra/launcher=joblib $(ARGS)
	$(BIN)/python -m topocut.run -m stage=pretrain scale=$(SCALE) model=pointnet model.sort=false,true \
		model.num_points=512 hydra/launcher=joblib $(ARGS)
	$(BIN)/python experiments/table2.py --root $${TOPOCUT_OUTPUTS:-outputs}

clean-outputs:
	rm -rf $${TOPOCUT_OUTPUTS:-outputs}
