"""The README is a front door that works: short, every docs page reachable from it, no pointer
outside the repository, its loading example runs as written, and its command lines exist."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import yaml

from imac_data.cli import main as imac_main
from imac_data.recipes import RECIPES_DIR
from imac_data.sources.sim.recorder import SimConfig, record_dataset

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def _links(page: Path) -> list[Path]:
    return [(page.parent / target).resolve() for target in LINK.findall(page.read_text())
            if not target.startswith(("http://", "https://", "mailto:"))]


def test_readme_is_short_and_every_page_is_reachable():
    assert len(README.read_text().split()) <= 1500
    seen, todo = set(), [README]
    while todo:
        page = todo.pop()
        for target in _links(page):
            assert target.exists(), f"{page.relative_to(ROOT)} links to {target} which does not exist"
            if target.suffix == ".md" and target not in seen:
                seen.add(target)
                todo.append(target)
    pages = set((ROOT / "docs").rglob("*.md"))
    assert pages <= seen, f"not reachable from the README: {sorted(p.relative_to(ROOT) for p in pages - seen)}"


def test_nothing_points_outside_the_repository():
    files = [README, *(ROOT / "docs").rglob("*.md"), *(ROOT / "dataset_cards").glob("*"),
             *(p for pkg in ("imac_data", "imac_model") for p in (ROOT / pkg).rglob("*.py"))]
    for f in files:
        text = f.read_text()
        assert "../shared" not in text and "DESIGN.md" not in text, f"{f.relative_to(ROOT)} points outside the repo"


def test_readme_loading_example_runs(tmp_path):
    """The README's Python block, as written, on a small dataset of the demo's repo id."""
    src = tmp_path / "sim"
    record_dataset(SimConfig(num_episodes=1, width=80, height=64, max_steps=20), src, progress=False)
    recipe = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    recipe["augment"] = {"height": 64, "width": 80}
    recipe["source"]["episodes"] = 1
    (tmp_path / "recipe.yaml").write_text(yaml.safe_dump(recipe))
    home = tmp_path / "home"
    root = home / "local" / "aloha_sim_transfer_cube"
    assert imac_main(["build", "--repo", "local/aloha_sim_transfer_cube", "--recipe", str(tmp_path / "recipe.yaml"),
                      "--source", str(src), "--root", str(root), "--no-progress"]) == 0
    block = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)[0]
    check = "\nassert item['control.motion.cam_high'].shape[0] == 8 and views.rgb.shape[0] == q.shape[0] == 8\n"
    env = {**os.environ, "HF_LEROBOT_HOME": str(home)}
    run = subprocess.run([sys.executable, "-c", block + check], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-3000:]


def test_the_command_lines_exist():
    """``imac`` and ``imac-model`` (console scripts) and ``python -m`` forms answer ``--help``."""
    bindir = Path(sys.executable).parent
    for argv in ([str(bindir / "imac"), "--help"], [str(bindir / "imac-model"), "--help"],
                 [sys.executable, "-m", "imac_data", "build", "--help"], [sys.executable, "-m", "imac_data.build", "--help"],
                 [sys.executable, "-m", "imac_model", "evaluate", "closed-loop", "--help"]):
        run = subprocess.run(argv, capture_output=True, text=True, timeout=120)
        assert run.returncode == 0 and "usage:" in run.stdout, (argv, run.stderr[-2000:])
