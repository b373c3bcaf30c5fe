"""The build CLI and recipes: a real build from recorded episodes, and bad input."""

import json
import shutil
from pathlib import Path

import pytest
import torch
import yaml
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from imac_data.cli import main as imac_main
from imac_data.core.contact.images import JET_LUT, colorize
from imac_data.core.robot import aloha
from imac_data.dataset.output import staging_dir
from imac_data.errors import InputError
from imac_data.metadata import dataset_info, imac_block
from imac_data.recipes import RECIPES_DIR, load_recipe, parse_recipe
from imac_data.sources.sim.recorder import SimConfig, record_dataset


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    record_dataset(SimConfig(num_episodes=2, width=80, height=64, max_steps=20), out, progress=False)
    return out


def write_recipe(tmp_path, **changes) -> Path:
    """The shipped sim recipe, with the added streams at the tiny episodes' size."""
    data = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    data["augment"] = {"height": 64, "width": 80, "contact_chunk": 4}
    for dotted, value in changes.items():
        node = data
        *parents, leaf = dotted.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_shipped_recipes_parse():
    for path in RECIPES_DIR.glob("*.yaml"):
        load_recipe(path)


def test_cli_builds_a_loadable_dataset(sim_dir, tmp_path, capsys):
    root = tmp_path / "out"
    rc = imac_main(["build", "--repo", "local/tiny", "--recipe", str(write_recipe(tmp_path)), "--source", str(sim_dir),
               "--root", str(root), "--no-progress"])
    assert rc == 0
    out, err = capsys.readouterr()
    assert "built local/tiny: 2 episodes" in out
    assert "[build] stage" in err and "total" in err  # --no-progress hides the bars, not the stage timings
    ds = LeRobotDataset("local/tiny", root=root, delta_timestamps={
        "action": [0.0, 0.04], "control.motion.cam_high": [0.04, 0.08], "control.contact_s2g.cam_left_wrist": [0.04]})
    assert ds.meta.total_episodes == 2
    item = ds[0]
    assert item["action"].shape == (2, 14)
    assert item["control.motion.cam_high"].shape == (2, 3, 64, 80)
    assert item["control.contact_s2g.cam_left_wrist"].shape == (3, 64, 80)  # LeRobot squeezes one timestamp
    for cam in ("cam_high", "cam_left_wrist", "cam_right_wrist"):
        for key in (f"observation.depth.{cam}", f"control.motion.{cam}", f"control.contact_r2s.{cam}",
                    f"control.contact_s2g.{cam}"):
            assert key in ds.meta.video_keys
    assert tuple(ds.meta.features["control.contact_cap"]["shape"]) == (2,)
    info = imac_block(ds.meta)
    assert info["contact"]["chunk_size"] == 4 and info["depth"]["codec"]["lam"] == -500
    assert (root / "README.md").read_text().startswith("# local/tiny")
    # the output is complete: rebuilding without --overwrite is refused, with it succeeds
    assert imac_main(["build", "--repo", "local/tiny", "--recipe", str(write_recipe(tmp_path)), "--source", str(sim_dir),
                 "--root", str(root), "--no-progress"]) == 2
    assert "already exists" in capsys.readouterr().err
    assert imac_main(["build", "--repo", "local/tiny", "--recipe", str(write_recipe(tmp_path)), "--source", str(sim_dir),
                 "--root", str(root), "--no-progress", "--overwrite", "--episodes", "1"]) == 0
    assert LeRobotDataset("local/tiny", root=root).meta.total_episodes == 1


@pytest.mark.parametrize("changes, message", [
    ({"source.episodes": "two"}, r"recipe.yaml: source\.episodes: expected an integer"),
    ({"source.sim.noise": 2.0}, r"recipe.yaml: source\.sim\.noise: must be in \[0, 1\]"),
    ({"robot.platform": "ur5"}, r"robot\.platform: unknown platform 'ur5'"),
    ({"source.colour": "red"}, r"source: unknown field\(s\) \['colour'\]"),
    ({"fps": 12.5}, r"recipe.yaml: fps: must be a positive whole number .* got 12.5"),
    ({"augment.contact_cap": float("inf")}, r"augment.contact_cap: must be a finite number of metres > 0, got inf"),
    ({"augment.renderer": "vulkan"}, r"augment.renderer: must be one of \['open3d', 'opengl'\], got 'vulkan'"),
    ({"source.type": "aloha_hdf5"}, r"source\.path: required"),
])
def test_invalid_recipe_fields(tmp_path, changes, message, capsys):
    recipe = write_recipe(tmp_path, **changes)
    with pytest.raises(InputError, match=message):
        load_recipe(recipe)
    root = tmp_path / "out"
    assert imac_main(["build", "--repo", "local/x", "--recipe", str(recipe), "--root", str(root)]) == 2
    assert "error:" in capsys.readouterr().err
    assert not root.exists() and not staging_dir(root).exists()


def test_cli_bad_input_exits_nonzero_and_writes_nothing(sim_dir, tmp_path, capsys):
    root = tmp_path / "out"
    assert imac_main(["build", "--repo", "local/definitely_not_a_recipe", "--root", str(root)]) == 2
    assert "unknown recipe" in capsys.readouterr().err
    assert imac_main(["build", "--repo", "local/x", "--recipe", str(write_recipe(tmp_path)), "--root", str(root),
                 "--source", str(tmp_path / "missing")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert not root.exists() and not staging_dir(root).exists()


def test_a_device_this_machine_lacks_is_refused_in_one_line_before_any_work(sim_dir, tmp_path, capsys):
    """--device cuda on a machine without CUDA (CI's): one line that says so and how to build anyway."""
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA: --device cuda is accepted here")
    root = tmp_path / "out"
    for device, message in (("cuda", "--device cuda: torch sees no CUDA device on this machine (build without "
                                     "--device to use the CPU path)"),
                            ("tpu", "--device must be cpu, cuda or cuda:N, got 'tpu'")):
        assert imac_main(["build", "--repo", "local/x", "--recipe", str(write_recipe(tmp_path)), "--root", str(root),
                          "--source", str(sim_dir), "--device", device, "--no-progress"]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err
    assert not root.exists() and not staging_dir(root).exists()
    assert imac_main(["augment", "--repo", "local/x", "--root", str(root), "--recipe", str(write_recipe(tmp_path)),
                      "--source", str(sim_dir), "--device", "cuda", "--no-progress"]) == 2
    assert "--device cuda: torch sees no CUDA device" in capsys.readouterr().err


def custom_robot_recipe(tmp_path, sim_dir, urdf_text: str) -> Path:
    """A recipe for the ALOHA episodes that brings its own URDF (as a real user's would)."""
    config = aloha.robot_config()
    urdf = tmp_path / "robot.urdf"
    urdf.write_text(urdf_text)
    joint_map = []
    for entry in config.joint_map:
        if isinstance(entry, str):
            joint_map.append(entry)
        else:
            joint_map.append({"gripper": entry.joint, "scale": entry.scale, "offset": entry.offset})
    data = {
        "name": "custom", "task": "t", "fps": 25,
        "robot": {"urdf": str(urdf), "joint_map": joint_map, "gripper_links": list(config.gripper_links),
                  "package_dirs": {k: str(v) for k, v in dict(config.package_dirs).items()}},
        "cameras": {"calibration": str(sim_dir / "calibration.json")},
        "source": {"type": "aloha_hdf5", "path": str(sim_dir)},
        "augment": {"height": 64, "width": 80, "contact_chunk": 4},
    }
    path = tmp_path / "custom.yaml"
    path.write_text(yaml.safe_dump(data))
    parse_recipe(data, str(path))
    return path


def test_custom_urdf_recipe_builds(sim_dir, tmp_path):
    text = aloha.robot_config().urdf_path.read_text()
    recipe = custom_robot_recipe(tmp_path, sim_dir, text)
    root = tmp_path / "out"
    assert imac_main(["build", "--repo", "local/custom", "--recipe", str(recipe), "--root", str(root), "--no-progress"]) == 0
    assert LeRobotDataset("local/custom", root=root).meta.total_frames > 0


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace('name="vx300s_left/elbow"', 'name="vx300s_left/elbow_joint"'), "vx300s_left/elbow"),
    (lambda t: t.replace("vx300s_6_wrist.stl", "vx300s_6_wrist_MISSING.stl"), "vx300s_6_wrist_MISSING.stl"),
])
def test_robot_errors_name_the_joint_or_mesh_and_write_nothing(sim_dir, tmp_path, capsys, edit, message):
    text = edit(aloha.robot_config().urdf_path.read_text())
    recipe = custom_robot_recipe(tmp_path, sim_dir, text)
    root = tmp_path / "out"
    assert imac_main(["build", "--repo", "local/custom", "--recipe", str(recipe), "--root", str(root)]) == 2
    assert message in capsys.readouterr().err
    assert not root.exists() and not staging_dir(root).exists()
    assert sorted(p.name for p in sim_dir.iterdir()) == sorted(
        ["calibration.json", "episode_0.hdf5", "episode_1.hdf5"])


def test_source_is_never_modified(sim_dir, tmp_path):
    src = tmp_path / "src"
    shutil.copytree(sim_dir, src)
    before = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in src.iterdir()}
    assert imac_main(["build", "--repo", "local/x", "--recipe", str(write_recipe(tmp_path)), "--source", str(src),
                 "--root", str(tmp_path / "out"), "--no-progress"]) == 0
    assert {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in src.iterdir()} == before


PAPER_TASKS = ("banana_basket", "green_bowl_pink_plate", "box_ears", "chips_pour", "sweep_trash", "fold_shirt",
               "tape_box", "panda_plate")


@pytest.mark.parametrize("name", PAPER_TASKS)
def test_paper_recipes_say_what_is_missing(name, tmp_path, capsys, monkeypatch):
    for var in ("IMAC_COBOT_MAGIC_URDF", "IMAC_COBOT_MAGIC_MESHES", "IMAC_COBOT_MAGIC_CALIBRATION", "IMAC_DATA_ROOT"):
        monkeypatch.delenv(var, raising=False)
    root = tmp_path / "out"
    assert imac_main(["build", "--repo", f"local/{name}", "--root", str(root)]) == 2
    err = capsys.readouterr().err
    for var in ("IMAC_COBOT_MAGIC_URDF", "IMAC_COBOT_MAGIC_CALIBRATION", "IMAC_DATA_ROOT"):
        assert var in err
    assert not root.exists()
    # with the variables set to places that do not exist, the message names the paths
    monkeypatch.setenv("IMAC_COBOT_MAGIC_URDF", str(tmp_path / "rig.urdf"))
    monkeypatch.setenv("IMAC_COBOT_MAGIC_MESHES", str(tmp_path))
    monkeypatch.setenv("IMAC_COBOT_MAGIC_CALIBRATION", str(tmp_path / "calib.json"))
    monkeypatch.setenv("IMAC_DATA_ROOT", str(tmp_path / "data"))
    assert imac_main(["build", "--repo", f"local/{name}", "--root", str(root)]) == 2
    err = capsys.readouterr().err
    assert f"not found at {tmp_path / 'rig.urdf'}" in err
    assert f"not found at {tmp_path / 'data' / name}" in err
    recipe = load_recipe(RECIPES_DIR / f"{name}.yaml")
    assert recipe.fps == 30 and recipe.source.type == "aloha_hdf5"


def dataset_files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def reference_build(sim_dir, tmp_path_factory):
    """An uninterrupted local build in this process (1 worker)."""
    tmp = tmp_path_factory.mktemp("ref")
    root = tmp / "out"
    assert imac_main(["build", "--repo", "local/tiny", "--recipe", str(write_recipe(tmp)), "--source", str(sim_dir),
                 "--root", str(root), "--no-progress", "--workers", "1"]) == 0
    return root


def test_ray_build_is_identical_to_local_build(sim_dir, tmp_path, reference_build):
    root = tmp_path / "out"
    assert imac_main(["build", "--repo", "local/tiny", "--recipe", str(write_recipe(tmp_path)), "--source", str(sim_dir),
                 "--root", str(root), "--no-progress", "--executor", "ray", "--workers", "2"]) == 0
    assert dataset_files(root) == dataset_files(reference_build)


def test_killed_build_resumes_to_the_same_dataset(sim_dir, tmp_path, reference_build):
    """SIGKILL while the build runs (after its first episode's shard is complete), rerun:
    the result equals an uninterrupted build."""
    import os
    import signal
    import subprocess
    import sys
    import time

    root = tmp_path / "out"
    shards = tmp_path / ".out.staging" / "shards"
    cmd = [sys.executable, "-m", "imac_data.build", "--repo", "local/tiny", "--recipe", str(write_recipe(tmp_path)),
           "--source", str(sim_dir), "--root", str(root), "--no-progress", "--workers", "1"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and not (shards / "episode_000000" / "meta" / "info.json").is_file():
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert (shards / "episode_000000").is_dir(), "the build never finished its first episode"
    assert not root.exists()
    assert subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE).returncode == 0
    assert dataset_files(root) == dataset_files(reference_build)
    assert not (tmp_path / ".out.staging").exists()


def test_resume_key_follows_the_robot_description(sim_dir, tmp_path):
    """Shards of a killed build are reused only for the same robot: an edited mesh (its
    sha256 in the rig's info block, which the key hashes) starts the staging over."""
    from imac_data.build.from_episodes import build_key
    from imac_data.core.rig import Rig

    recipe = load_recipe(write_recipe(tmp_path))
    paths, calibration = sorted(sim_dir.glob("episode_*.hdf5")), sim_dir / "calibration.json"
    block = Rig.from_recipe(recipe, calibration).to_info()
    key = build_key(recipe, paths, calibration, "local/tiny", block)
    assert key == build_key(recipe, paths, calibration, "local/tiny", json.loads(json.dumps(block)))
    files = block["robot"]["description"]["files"]
    edited = json.loads(json.dumps(block))
    edited["robot"]["description"]["files"][next(iter(files))] = "0" * 64
    assert build_key(recipe, paths, calibration, "local/tiny", edited) != key


def test_hub_card_is_what_lerobot_uploads(reference_build):
    """Everything up to the upload: LeRobot's own card builder renders our description
    (the upload itself needs a token and network, which tests do not have)."""
    from lerobot.datasets.utils import create_lerobot_dataset_card

    from imac_data.dataset.card import hub_card_kwargs

    recipe = load_recipe(RECIPES_DIR / "aloha_sim_transfer_cube.yaml")
    kwargs = hub_card_kwargs(reference_build, "local/tiny", recipe)
    ds = LeRobotDataset("local/tiny", root=reference_build)
    card = create_lerobot_dataset_card(dataset_info=ds.meta.info, repo_id="local/tiny", **kwargs)
    text = str(card)
    assert "control.contact_s2g.cam_left_wrist" in text and "delta_timestamps" in text
    assert "imac" in card.data.tags and card.data.license == "apache-2.0"
    ws = dataset_info(reference_build)["imac"]["workspace"]
    assert ws["source"].startswith("robot reach") and ws["depth_range"] == [0.0, 3.736]  # the contact crop
    assert f"world box min `{json.dumps(ws['min'])}`, max `{json.dumps(ws['max'])}` m" in text
    assert "depth lies in\n[0.0, 3.736) m" in text


def decoded_streams(root: Path) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Every control stream of the tiny build at ``root`` decoded by LeRobot, ``{key: uint8 (T, H, W, 3)}``,
    and the frames' contact caps ``(T, 2)`` (r2s, s2g) in metres."""
    ds = LeRobotDataset("local/tiny", root=root)
    keys = [k for k in ds.meta.video_keys if k.startswith("control.")]
    items = [ds[i] for i in range(len(ds))]
    frames = {k: (torch.stack([it[k] for it in items]).permute(0, 2, 3, 1) * 255).round().to(torch.uint8) for k in keys}
    return frames, torch.stack([it["control.contact_cap"] for it in items]).double()


def contact_bounds(rgb: torch.Tensor, cap: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distances a contact image's colours can stand for: ``(lo, hi)`` metres per pixel of ``rgb``
    ``(T, H, W, 3)`` painted with ``cap`` ``(T,)``, from the colour map's definition (level
    ``floor(256 (1 - d / cap))``, clipped to 0..255; docs/dataset-format.md); NaN where nothing is painted."""
    code = (rgb.long() * torch.tensor([65536, 256, 1])).sum(-1)
    first, last = torch.full_like(code, -1), torch.full_like(code, -1)  # a few neighbouring levels share a colour
    for i, c in enumerate((torch.as_tensor(JET_LUT).long() * torch.tensor([65536, 256, 1])).sum(-1).tolist()):
        first[(code == c) & (first < 0)] = i
        last[code == c] = i
    painted = code != 0
    assert bool((first[painted] >= 0).all()), "a painted pixel's colour is not in the colour map"
    c = cap.reshape(-1, 1, 1)
    lo, hi = (255 - last) / 256.0 * c, (256 - first) / 256.0 * c
    hi = torch.where(first == 0, torch.full_like(hi, float("inf")), hi)  # at or beyond the cap
    return lo.masked_fill(~painted, float("nan")), hi.masked_fill(~painted, float("nan"))


def test_contact_bounds_hold_every_painted_distance_and_no_more():
    """The helper above against the painter: distances coloured by ``colorize`` fall within the bounds read
    back from their colours, and the bounds are one level wide below the cap (four where ``jet`` repeats
    (0, 0, 255), levels 29-32)."""
    cap = torch.tensor([0.05, 0.3], dtype=torch.float64)
    d = torch.rand(2, 64, 80, dtype=torch.float64) * cap.reshape(-1, 1, 1) * 1.2
    d[:, 0, :3] = torch.tensor([0.0, float("inf"), float("nan")], dtype=torch.float64)
    lo, hi = contact_bounds(colorize(d, cap.reshape(-1, 1, 1)), cap)
    painted = ~torch.isnan(d)
    assert bool(torch.isnan(lo[~painted]).all()) and bool((lo[painted] <= d[painted]).all())
    assert bool((d[painted] <= hi[painted]).all())
    width = ((hi - lo) / cap.reshape(-1, 1, 1))[painted & (d < cap.reshape(-1, 1, 1) * 255 / 256)] * 256
    assert float(width.max()) <= 4 + 1e-9 and float((width <= 1 + 1e-9).float().mean()) > 0.97


def assert_builds_agree(a_root: Path, b_root: Path, *, iou: float, grey_share: float, contact_share: float) -> None:
    """Two builds of the same episodes by two renderers or devices: the camera and depth videos byte for byte;
    the motion images' robot masks at IoU >= ``iou`` and their colours within one grey level on ``grey_share``
    of the robot's pixels; each contact stream painted on the same pixels at IoU >= ``iou``, and where both
    paint, the two distances within the build's certified tolerance (``max(1 mm, 3 % d)``: each is within it
    of the exact distance) on ``contact_share`` of the pixels, read from the colours and the caps."""
    files_a, files_b = dataset_files(a_root), dataset_files(b_root)
    for prefix in ("videos/observation.images.", "videos/observation.depth."):
        files = {p: b for p, b in files_a.items() if p.startswith(prefix)}
        assert files and files == {p: b for p, b in files_b.items() if p.startswith(prefix)}, prefix
    (a, cap_a), (b, cap_b) = decoded_streams(a_root), decoded_streams(b_root)
    assert a.keys() == b.keys()
    for k in a:
        ma, mb = a[k].amax(-1) > 0, b[k].amax(-1) > 0  # black is no robot / no value
        overlap = float((ma & mb).sum() / (ma | mb).sum())
        if k.startswith("control.motion."):
            grey = (a[k].int() - b[k].int()).abs().amax(-1)[ma & mb]
            print(f"{k}: IoU {overlap:.5f}, grey > 1 on {int((grey > 1).sum())} of {grey.numel()} pixels")
            assert overlap >= iou and float((grey <= 1).float().mean()) >= grey_share, k
            continue
        s = 0 if k.startswith("control.contact_r2s.") else 1
        (lo_a, hi_a), (lo_b, hi_b) = contact_bounds(a[k], cap_a[:, s]), contact_bounds(b[k], cap_b[:, s])
        both = ma & mb
        gap = (torch.maximum(lo_a, lo_b) - torch.minimum(hi_a, hi_b)).clamp(min=0)[both]
        within = gap <= torch.clamp(0.03 * torch.minimum(hi_a, hi_b)[both], min=1e-3)
        print(f"{k}: painted IoU {overlap:.5f}, caps {cap_a[:, s].max():.4f} / {cap_b[:, s].max():.4f} m, "
              f"outside the tolerance on {int((~within).sum())} of {within.numel()} pixels")
        assert overlap >= iou and float(within.float().mean()) >= contact_share, k


def test_the_opengl_renderer_builds_what_the_ray_caster_builds(sim_dir, tmp_path, reference_build):
    """``augment.renderer: opengl`` (two workers, so each process makes its own EGL context) against the
    reference build's Open3D ray casting, decoded from the datasets (:func:`assert_builds_agree`): the robot
    masks at IoU >= 0.999 and their colours within one grey level on 99.5 % of the robot's pixels; contact
    within the certified tolerance on 99 % of the pixels both paint. Issue 65's tolerances (0.9999, 99.9 %)
    hold at the demo's size (``tests/test_render.py``); at 64x80 the pixels on a silhouette, where the two
    may pick another triangle, are a larger share (9 of 8,616 in the head view). The dataset records the
    renderer."""
    root = tmp_path / "out"
    assert imac_main(["build", "--repo", "local/tiny", "--recipe", str(write_recipe(tmp_path, **{
        "augment.renderer": "opengl"})), "--source", str(sim_dir), "--root", str(root), "--no-progress",
        "--workers", "2"]) == 0
    assert imac_block(dataset_info(root))["augment"]["renderer"] == "opengl"
    assert_builds_agree(reference_build, root, iou=0.999, grey_share=0.995, contact_share=0.99)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device: `imac build --device cuda` is refused "
                    "here (test_a_device_this_machine_lacks_is_refused_in_one_line_before_any_work); its rasteriser "
                    "and brute-force contact are checked on the CPU in test_render.py and test_benchmarks.py")
def test_the_gpu_build_builds_what_the_cpu_build_builds(sim_dir, tmp_path, reference_build):
    """``imac build --device cuda`` (the torch rasteriser and brute-force contact on the GPU) against the CPU
    build, with the tolerances of the OpenGL renderer's test above (the same silhouette pixels at 64x80)."""
    root = tmp_path / "out"
    assert imac_main(["build", "--repo", "local/tiny", "--recipe", str(write_recipe(tmp_path)), "--source",
                      str(sim_dir), "--root", str(root), "--no-progress", "--device", "cuda"]) == 0
    assert_builds_agree(reference_build, root, iou=0.999, grey_share=0.995, contact_share=0.99)
