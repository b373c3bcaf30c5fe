"""The GPU machine's entry point: ``python scripts/gpu_train.py RUNS_FILE OUT [--runs NAME ...]``.

That machine has Python, torch and numpy and nothing else of ours: PyYAML and safetensors travel as
wheels in a ``wheels/`` folder beside the runs file and are put on the path here when missing (no
environment variable is read). Then :mod:`imac_model.training.runs` trains every run of the file."""

import importlib.util
import sys
import tempfile
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _wheels(runs_file: Path) -> None:
    if all(importlib.util.find_spec(m) for m in ("yaml", "safetensors")):
        return
    site = Path(tempfile.mkdtemp(prefix="imac_wheels_"))
    wheels = sorted((runs_file.parent / "wheels").glob("*.whl"))
    if not wheels:
        sys.exit(f"gpu_train: this Python lacks PyYAML or safetensors, and {runs_file.parent / 'wheels'} has no "
                 "wheels of them (docs/ranking.md, \"The GPU preset\")")
    for wheel in wheels:
        zipfile.ZipFile(wheel).extractall(site)
    sys.path.insert(0, str(site))


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit("usage: python scripts/gpu_train.py RUNS_FILE OUT [--runs NAME ...]")
    _wheels(Path(sys.argv[1]))
    sys.path.insert(0, str(ROOT))
    from imac_model.training.runs import main

    raise SystemExit(main(sys.argv[1:]))
