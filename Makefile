# The two commands of the README: `make demo` (main job) and `make test`.
# Both set up whatever is missing first (system packages, .venv, editable install).
PY := .venv/bin/python
export MUJOCO_GL ?= egl

.PHONY: setup demo test bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	$(PY) -m imac_data.build --repo local/aloha_sim_transfer_cube --overwrite

test: setup
	$(PY) -m pytest -q

bench: setup
	$(PY) -m benchmarks.run

clean:
	rm -rf .venv .pytest_cache build *.egg-info
