"""Faults a user can make, tried as a user would: each gets a clear error, the source is
never modified, and nothing half-written is left behind."""

import hashlib
import shutil
from pathlib import Path

import pytest
import yaml

from imac_data.build import main
from imac_data.recipes import RECIPES_DIR
from imac_data.simulate import SimConfig, record_dataset


@pytest.fixture(scope="module")
def sim_src(tmp_path_factory):
    """Tiny simulated episodes: 2 episodes, 120x160, a few frames."""
    out = tmp_path_factory.mktemp("faults_sim")
    record_dataset(SimConfig(num_episodes=2, width=160, height=120, max_steps=12), out, progress=False)
    return out


def tree_digest(path: Path) -> dict[str, str]:
    """sha256 of every file under ``path`` (relative name -> digest)."""
    return {str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(path.rglob("*")) if p.is_file()}


def recipe_file(where: Path, **augment) -> Path:
    data = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    data["augment"] = {"height": 60, "width": 80, "contact_chunk": 4, **augment}
    path = where / "recipe.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def copy_source(sim_src: Path, dst: Path) -> Path:
    shutil.copytree(sim_src, dst)
    return dst


@pytest.mark.parametrize("layout", ["root_is_source", "root_inside_source", "root_contains_source"])
def test_overwrite_never_deletes_the_source(sim_src, tmp_path, capsys, layout):
    """--overwrite with --root equal to, inside or containing the source directory is refused
    before any work, and the raw episodes and calibration stay byte-identical."""
    if layout == "root_contains_source":
        root = tmp_path / "out"
        src = copy_source(sim_src, root / "episodes")
    else:
        src = copy_source(sim_src, tmp_path / "episodes")
        root = src if layout == "root_is_source" else src / "built"
    recipe = recipe_file(tmp_path)
    before = tree_digest(src)
    listing = sorted(p.name for p in tmp_path.iterdir())
    rc = main(["--repo", "local/x", "--recipe", str(recipe), "--source", str(src), "--root", str(root),
               "--overwrite", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2
    assert str(src) in err and "source episodes" in err
    assert tree_digest(src) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == listing  # nothing new next to the output


def test_overwrite_never_deletes_the_calibration(sim_src, tmp_path, capsys):
    """A calibration file kept inside the output directory is an input too."""
    src = copy_source(sim_src, tmp_path / "episodes")
    root = tmp_path / "out"
    root.mkdir()
    calib = root / "calibration.json"
    shutil.copy(src / "calibration.json", calib)
    data = yaml.safe_load(recipe_file(tmp_path).read_text())
    data["cameras"] = {"calibration": str(calib)}
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text(yaml.safe_dump(data))
    digest = hashlib.sha256(calib.read_bytes()).hexdigest()
    rc = main(["--repo", "local/x", "--recipe", str(recipe), "--source", str(src), "--root", str(root),
               "--overwrite", "--no-progress"])
    assert rc == 2
    assert "calibration" in capsys.readouterr().err
    assert hashlib.sha256(calib.read_bytes()).hexdigest() == digest


def test_augment_refuses_a_dataset_inside_its_raw_episodes(sim_src, tmp_path, capsys):
    from imac_data.augment import main as augment_main

    src = copy_source(sim_src, tmp_path / "episodes")
    before = tree_digest(src)
    rc = augment_main(["--repo", "local/x", "--root", str(src), "--recipe", str(recipe_file(tmp_path)),
                       "--source", str(src), "--no-progress"])
    assert rc == 2
    assert "raw episodes" in capsys.readouterr().err
    assert tree_digest(src) == before
