# The two commands of the README: `make demo` (main job) and `make test`.
# Both set up whatever is missing first (system packages, .venv, editable install).
PY := .venv/bin/python
export MUJOCO_GL ?= egl

.PHONY: setup demo test bench experiment da3 clean

setup:
	@bash scripts/setup.sh

demo: setup
	$(PY) -m imac_data.build --repo local/aloha_sim_transfer_cube --overwrite

test: setup
	$(PY) -m pytest -q

bench: setup
	$(PY) -m benchmarks.run

# The small-scale comparison of docs/experiment (about 60-90 minutes on an idle 2-core machine; resumable:
# every stage is cached under runs/experiment).
experiment: setup
	$(PY) -m imac_model.experiment --work runs/experiment --docs docs/experiment

# Depth Anything 3's code (no weights): scripts/setup.sh installs it; this re-runs that install.
da3: setup
	$(PY) -c "from imac_data.depth_sources import DA3_INSTALL; print(DA3_INSTALL)" | sed 's|^pip|$(PY) -m pip|' | sh

clean:
	rm -rf .venv .pytest_cache build *.egg-info
