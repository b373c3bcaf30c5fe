"""LeRobot in one place (``imac_data/lerobot_compat.py``, ``docs/lerobot.md``): no other module
imports LeRobot, and every name the adapter offers resolves on the installed LeRobot, through
the module path that version has."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("imac_data", "imac_model", "benchmarks", "scripts")
# the adapter, and the policy-loading module with LeRobot's policy-side names
ALLOWED = {"imac_data/lerobot_compat.py", "imac_model/evaluate/policies.py"}


def lerobot_imports(path: Path, text: str | None = None) -> list[str]:
    """``file:line module`` for every import of LeRobot in a file: ``import``/``from`` statements
    anywhere in it, and ``import_module("lerobot...")`` / ``__import__("lerobot...")`` calls."""
    tree = ast.parse(path.read_text() if text is None else text)
    found = []
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level:
            names = [node.module or ""]
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if func in ("import_module", "__import__") and isinstance(node.args[0].value, str):
                names = [node.args[0].value]
        found += [f"{path.relative_to(ROOT)}:{node.lineno} {n}" for n in names if n.split(".")[0] == "lerobot"]
    return found


def test_only_the_adapters_import_lerobot():
    files = [p for d in SCANNED for p in sorted((ROOT / d).rglob("*.py"))]
    assert len(files) > 100
    wrong = [hit for p in files if str(p.relative_to(ROOT)) not in ALLOWED for hit in lerobot_imports(p)]
    assert not wrong, "LeRobot imported outside imac_data/lerobot_compat.py:\n" + "\n".join(wrong)
    assert lerobot_imports(ROOT / "imac_model" / "evaluate" / "policies.py") == []  # by name, through import_module


def test_the_scan_catches_each_way_of_importing_lerobot():
    path = ROOT / "imac_data" / "dataset" / "merge.py"
    for line in ("from lerobot.datasets.aggregate import aggregate_datasets",
                 "def f():\n    import lerobot.datasets.utils as u",
                 "import importlib\nx = importlib.import_module('lerobot.datasets.utils')"):
        assert len(lerobot_imports(path, line + "\n" + path.read_text())) == 1, line


def test_every_name_resolves_through_the_path_of_the_installed_version():
    from imac_data import lerobot_compat as lr
    from imac_model.evaluate.policies import LEROBOT_POLICY_NAMES, lerobot_name

    for name in lr.NAMES:
        value, module = lr._find(name)
        assert getattr(lr, name) is value and module in lr.NAMES[name], name
    for name in LEROBOT_POLICY_NAMES:
        assert lerobot_name(name).__name__ == name
    # the riskiest names: private ones of LeRobot's quantile histogram (dataset/videos.py)
    rq = lr.RunningQuantileStats()
    assert rq._num_quantile_bins == 5000 and callable(rq._compute_single_quantile)
    # and the video decoder cache that a DataLoader worker replaces (open_videos_anew)
    video_utils = importlib.import_module("lerobot.datasets.video_utils")
    cache = video_utils._default_decoder_cache
    lr.open_videos_anew()
    assert video_utils._default_decoder_cache is not cache and callable(video_utils._default_decoder_cache.get_decoder)
    video_utils._default_decoder_cache = cache
    if lr.version() == "0.4.4":  # the fallbacks really run: these moved in 0.5.1
        assert lr._find("LeRobotDatasetMetadata")[1] == "lerobot.datasets.lerobot_dataset"
        assert lr._find("convert_dataset")[1] == "lerobot.datasets.v30.convert_dataset_v21_to_v30"
    with pytest.raises(AttributeError):
        lr.NoSuchName  # noqa: B018
