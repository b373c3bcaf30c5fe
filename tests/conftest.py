import atexit
import os
import shutil
import tempfile

# Before anything imports `datasets`: LeRobot loads each parquet file with `Dataset.from_parquet`, which keeps an
# Arrow copy under ~/.cache/huggingface/datasets keyed by path and mtime, so every test's new dataset added one to
# the user's home (66 MB a suite, never removed). The suite's copies go to a folder of its own, removed when the
# run ends; one the caller set is kept.
if "HF_DATASETS_CACHE" not in os.environ:
    os.environ["HF_DATASETS_CACHE"] = tempfile.mkdtemp(prefix="imac-tests-hf-datasets-")
    atexit.register(shutil.rmtree, os.environ["HF_DATASETS_CACHE"], ignore_errors=True)

from imac_data.console import cpu_cores, refuse_realtime  # noqa: E402

# Before anything imports mujoco or dm_control: headless EGL rendering (Mesa on the CPU).
os.environ.setdefault("MUJOCO_GL", "egl")
# Each pytest-xdist process, and every process it starts, gets its share of the cores for OpenMP's (and so torch's)
# thread pools: two processes each spinning a pool of both cores made the 2-core suite 13 % slower (694 s, 616 s)
# (docs/verification.md, "The test suite"). A value the caller set is kept.
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _WORKERS > 1:
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, cpu_cores() // _WORKERS)))

# Tests and module fixtures that write with LeRobot's own writer as root would make the test process and SVT-AV1's
# threads real-time, starving the other test process (docs/building.md, "Real-time scheduling left by the AV1
# encoder"): no thread of a test process may; programs it runs get the right back.
refuse_realtime()


# The files that take minutes, collected first: `make test` hands pytest-xdist whole files (--dist loadfile) in
# collection order, so a long file collected late (test_ranking.py, about 8 minutes of one process) became the
# run's tail while the other process sat idle: 1,146 s against 920 s (docs/verification.md, "The test suite").
LONGEST_FIRST = ("test_ranking.py", "test_calibrate_from_nothing.py", "test_so101.py", "test_build.py",
                 "test_faults.py", "test_benchmarks.py", "test_calibrate_time_offset.py", "test_model_scale.py",
                 "test_lerobot_policy.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: a file's own order is kept
