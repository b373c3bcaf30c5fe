# The two commands of the README: `make demo` (main job) and `make test`.
# Both set up whatever is missing first (system packages, .venv, editable install).
# PYTHON picks the interpreter (default: python3), VENV the environment (default: .venv): scripts/setup.sh.
VENV ?= .venv
PY := $(VENV)/bin/python
export MUJOCO_GL ?= egl

.PHONY: setup demo test bench experiment ranking ranking-checkpoints da3 clean

setup:
	@bash scripts/setup.sh

demo: setup
	$(PY) -m imac_data.build --repo local/aloha_sim_transfer_cube --overwrite

# Lint first (ruff, pinned in the dev extra; its settings and the vendored LeRobot files it skips are in
# pyproject.toml), then the suite on TEST_PROCESSES processes (pytest-xdist), a test file each at a time:
# a file's module fixtures are built once (docs/verification.md, "The test suite").
TEST_PROCESSES ?= 2
test: setup
	$(PY) -m ruff check .
	$(PY) -m pytest -q -n $(TEST_PROCESSES) --dist loadfile

# The data layer's benchmark (benchmarks/results/latest.{json,md}), then the model and evaluation
# benchmarks, each printing its own figures (JSON beside latest.json where the script writes one).
# latest.md also builds the same episodes with BENCH_BASELINE's command line: the build-speed issue's start.
BENCH_BASELINE ?= 4e5e2e9
bench: setup
	$(PY) -m benchmarks.run --baseline $(BENCH_BASELINE)
	$(PY) -m benchmarks.model_train --json benchmarks/results/model_train.json
	$(PY) -m benchmarks.model_rollout --json benchmarks/results/model_rollout.json
	$(PY) -m benchmarks.model_plan --json benchmarks/results/model_plan.json
	$(PY) -m benchmarks.evaluate_closed_loop --json benchmarks/results/evaluate_closed_loop.json
	$(PY) -m benchmarks.evaluate_video_metrics --samples 2
	$(PY) -m benchmarks.evaluate_statistics --markdown benchmarks/results/evaluate_statistics.md
	$(PY) -m benchmarks.evaluate_success
	$(PY) -m benchmarks.panda_vs_pybullet --json benchmarks/results/panda_vs_pybullet.json
	$(PY) -m benchmarks.calibration_refine --seeds 1 --methods gradient --cues sim,edges

# The small-scale comparison of docs/experiment (about 60-90 minutes on an idle 2-core machine; resumable:
# every stage is cached under runs/experiment).
experiment: setup
	$(PY) -m imac_model experiment --work runs/experiment --docs docs/experiment

# Policy ranking in simulation (docs/ranking.md): does the world model rank policies as MuJoCo does?
# About 5.3 CPU-hours at today's defaults (the protocol allows 8); stops early (exit 4) if motion+contact fails the early gate; resumable, every stage cached
# under runs/ranking (spread it over days if need be).
ranking: setup
	$(PY) -m imac_model ranking --work runs/ranking --docs docs/ranking

# Ranking policy checkpoints (docs/ranking.md, "Ranking checkpoints"): ACT trained with lerobot-train on the
# project's own dataset, then the checkpoint preset (graded scripted policies, three ACT checkpoints and the best
# under graded action noise, 100 starts, motion+contact from 3 training seeds). About 16 CPU-hours in all (18 as first run on 2026-12-02, with two discarded ACT runs and a stopped build: docs/ranking.md, "Budget");
# both commands resume where they stopped, so spread it over days.
ranking-checkpoints: setup
	$(PY) -m benchmarks.lerobot_policy --work runs/lerobot_act
	$(PY) -m imac_model ranking --preset checkpoints --work runs/checkpoints --docs docs/ranking

# Depth Anything 3's code (no weights): scripts/setup.sh installs it; this re-runs that install.
da3: setup
	$(PY) -c "from imac_data.sources.da3 import DA3_INSTALL; print(DA3_INSTALL)" | sed 's|^pip|$(PY) -m pip|' | sh

clean:
	rm -rf .venv .venv312 .pytest_cache build *.egg-info
