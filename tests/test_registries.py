"""Extension points are registries: a new platform, source type, depth source or success judge is
its module plus one entry, and nothing else names it.

A toy platform registered here (and only here: no line of the package changes) passes recipe
validation, ``Rig.from_recipe``, ``imac qa overlay`` and a one-episode build. A toy depth source
and a toy judge are picked by name the same way; a toy source type passes recipe validation and
reaches its build. No platform name is spelled out in the packages outside its registry entry
(read from the source with ``ast``).
"""

from __future__ import annotations

import ast
import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from imac_data.build.flow import BUILDS, input_paths
from imac_data.build.from_episodes import build_from_episodes
from imac_data.build.staging import BuildRequest
from imac_data.cli import main as imac_main
from imac_data.core.motion import Controller, GripperActionMap
from imac_data.core.rig import Rig
from imac_data.core.robot import aloha
from imac_data.core.robot.platforms import PLATFORMS, Platform, simulated_platforms
from imac_data.errors import InputError
from imac_data.recipes import (
    HDF5_EPISODES,
    SOURCE_TYPES,
    DepthSection,
    load_recipe,
    missing_inputs,
    parse_recipe,
    source_type,
)
from imac_data.sources.depth import DEPTH_SOURCES, DepthSourceKind, make_depth_source
from imac_data.sources.sim.recorder import SimConfig, record_dataset
from imac_model.evaluate.success import JUDGES, SuccessJudge, load_judge

ROOT = Path(__file__).resolve().parents[1]
TOY = "toy_bimanual"


def toy_robot():
    """The ALOHA arms under another name: a robot the package does not know as a platform."""
    return dataclasses.replace(aloha.robot_config(), name="toy")


def toy_controller(task):
    """Absolute targets, the grippers mapped (no actuator saturation: this toy has no simulator)."""
    return Controller(mode="absolute", grippers=(GripperActionMap(6, scale=1.0), GripperActionMap(13, scale=1.0)))


@pytest.fixture
def toy_platform(monkeypatch):
    monkeypatch.setitem(PLATFORMS, TOY, Platform(robot=toy_robot, controller=toy_controller,
                                                 state_names=tuple(f"q{i}" for i in range(14))))


@pytest.fixture(scope="module")
def episodes(tmp_path_factory):
    """One short recorded episode (64x80) with its calibration, as HDF5 files a user would have."""
    path = tmp_path_factory.mktemp("toy") / "episodes"
    record_dataset(SimConfig(num_episodes=1, width=80, height=64, max_steps=12), path, progress=False)
    return path


def _recipe(tmp_path: Path, episodes: Path) -> Path:
    recipe = {"name": "toy_task", "task": "move the toy", "robot": {"platform": TOY},
              "source": {"type": "aloha_hdf5", "path": str(episodes), "episodes": 1},
              "cameras": {"calibration": str(episodes / "calibration.json")},
              "augment": {"height": 32, "width": 40, "contact_chunk": 4}}
    path = tmp_path / "toy.yaml"
    path.write_text(yaml.safe_dump(recipe))
    return path


def test_a_toy_platform_is_one_entry(toy_platform, episodes, tmp_path, capsys):
    recipe_file = _recipe(tmp_path, episodes)
    recipe = load_recipe(recipe_file)  # recipe validation
    rig = Rig.from_recipe(recipe)
    assert rig.robot.name == "toy" and rig.controller == toy_controller(None)
    assert rig.state_names == tuple(f"q{i}" for i in range(14))
    episode = str(episodes / "episode_0.hdf5")
    calibration = str(episodes / "calibration.json")
    for how in (["--recipe", str(recipe_file)], ["--robot", TOY]):
        out = tmp_path / f"overlay_{how[0][2:]}"
        assert imac_main(["qa", "overlay", episode, "--calibration", calibration, "--out", str(out), "--frames", "0:3",
                          "--source", "action", *how]) == 0
        summary = json.loads((out / "summary.json").read_text())
        assert summary["robot"] == "toy" and summary["num_frames"] == 3
    capsys.readouterr()
    root = tmp_path / "ds"
    assert imac_main(["build", "--repo", "local/toy", "--recipe", str(recipe_file), "--root", str(root),
                      "--no-progress", "--workers", "1"]) == 0
    built = Rig.from_dataset(root)
    assert built.robot.name == "toy" and built.controller == rig.controller and built.state_names == rig.state_names
    assert json.loads((root / "meta" / "info.json").read_text())["total_episodes"] == 1


def test_without_its_entry_the_toy_platform_is_refused(episodes, tmp_path):
    known = re.escape(str(sorted(PLATFORMS)))
    with pytest.raises(InputError, match=rf"robot\.platform: unknown platform '{TOY}'; known: {known}"):
        load_recipe(_recipe(tmp_path, episodes))


class FlatDepth:
    """A toy depth source: every pixel 1 m away."""

    def depth(self, views):
        return {c: np.ones((views.num_frames, cam.height, cam.width), np.float32) for c, cam in views.cameras.items()}

    def describe(self):
        return {"kind": "flat", "from": "1 m everywhere"}


def test_a_toy_depth_source_and_a_toy_judge_are_one_entry(monkeypatch):
    with pytest.raises(InputError, match="depth.source: must be one of"):
        make_depth_source(DepthSection(source="flat"), "r.yaml", 3)
    monkeypatch.setitem(DEPTH_SOURCES, "flat", DepthSourceKind(make=lambda section, recipe_file, n, **_: FlatDepth()))
    assert isinstance(make_depth_source(DepthSection(source="flat"), "r.yaml", 3), FlatDepth)

    class Always(SuccessJudge):
        name = "always"

        def judge(self, episodes):
            return np.ones(len(episodes), dtype=bool)

    with pytest.raises(InputError, match="unknown judge 'always:yes'"):
        load_judge("always:yes")
    monkeypatch.setitem(JUDGES, "always", lambda spec: Always())
    assert isinstance(load_judge("always:yes"), Always)


def test_a_toy_source_type_is_one_entry(monkeypatch, tmp_path):
    recipe = {"name": "x", "task": "t", "robot": {"platform": "aloha_sim"}, "cameras": {"calibration": "c.json"},
              "source": {"type": "toy_hdf5"}}
    known = re.escape(str([*simulated_platforms(), *SOURCE_TYPES]))
    with pytest.raises(InputError, match=rf"r.yaml: source\.type: unknown source type 'toy_hdf5'; known: {known}"):
        parse_recipe(recipe, "r.yaml")
    monkeypatch.setitem(SOURCE_TYPES, "toy_hdf5", dataclasses.replace(HDF5_EPISODES, label="toy"))
    with pytest.raises(InputError, match=r"source\.path: required for source\.type toy_hdf5 \(the directory of HDF5"):
        parse_recipe(recipe, "r.yaml")
    with pytest.raises(InputError, match=r"\['repo_id'\] only apply to source\.type lerobot"):
        parse_recipe({**recipe, "source": {"type": "toy_hdf5", "path": "eps", "repo_id": "a/b"}}, "r.yaml")
    parsed = parse_recipe({**recipe, "source": {"type": "toy_hdf5", "path": "eps"}}, str(tmp_path / "r.yaml"))
    assert BUILDS[source_type(parsed.source.type).build] is build_from_episodes
    assert any(p.startswith("source.path: the directory of HDF5 episodes not found") for p in missing_inputs(parsed))
    assert input_paths(BuildRequest("local/toy", parsed, tmp_path / "out"))["source episodes"] == tmp_path / "eps"


def test_every_source_type_has_a_build():
    assert {kind.build for kind in SOURCE_TYPES.values()} <= set(BUILDS)


def _platform_names_spelled(path: Path) -> list[int]:
    tree = ast.parse(path.read_text())
    return [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Constant) and n.value in PLATFORMS]


def test_no_platform_name_is_spelled_out_outside_its_entry():
    registry = ROOT / "imac_data" / "core" / "robot" / "platforms.py"
    wrong = [f"{p.relative_to(ROOT)}:{line}" for pkg in ("imac_data", "imac_model")
             for p in sorted((ROOT / pkg).rglob("*.py")) if p != registry for line in _platform_names_spelled(p)]
    assert not wrong, "platform names spelled out outside the registry:\n" + "\n".join(wrong)
    assert _platform_names_spelled(registry)  # the check reads the entry itself
