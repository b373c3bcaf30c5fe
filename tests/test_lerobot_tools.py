"""LeRobot's own tools, and our preview, on a dataset built by the real builder.

* ``lerobot-train``: the exact command of the dataset card, for 2 steps on the CPU.
* ``lerobot-dataset-viz --save 1``: its rerun recording holds every stream, frame for frame.
* ``imac qa preview``: the mosaic's tiles match the dataset's videos decoded
  independently with PyAV.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from imac_data.cli import main as imac_main
from imac_data.dataset.card import lerobot_train_command
from imac_data.dataset.videos import read_video_frames
from imac_data.qa.preview import LABEL_PX, ROWS
from imac_data.recipes import RECIPES_DIR
from imac_data.sources.sim.recorder import SimConfig, record_dataset

REPO_ID = "local/tiny"
H, W, T = 64, 80, 10


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A one-episode dataset (10 frames, 64x80) in its own HF_LEROBOT_HOME."""
    tmp = tmp_path_factory.mktemp("tools")
    record_dataset(SimConfig(num_episodes=1, width=W, height=H, max_steps=2 * T), tmp / "sim", progress=False)
    recipe = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    recipe["augment"] = {"height": H, "width": W, "contact_chunk": 4}
    (tmp / "recipe.yaml").write_text(yaml.safe_dump(recipe))
    home = tmp / "lerobot_home"
    root = home / REPO_ID
    assert imac_main(["build", "--repo", REPO_ID, "--recipe", str(tmp / "recipe.yaml"), "--source", str(tmp / "sim"),
                       "--root", str(root), "--episodes", "1", "--no-progress"]) == 0
    return home, root


def _env(home: Path) -> dict:
    bin_dir = str(Path(sys.executable).parent)  # lerobot's console scripts live beside the interpreter
    return {**os.environ, "HF_LEROBOT_HOME": str(home), "PATH": bin_dir + os.pathsep + os.environ.get("PATH", ""),
            "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}


def test_card_lerobot_train_command_trains_two_steps(built, tmp_path):
    home, root = built
    card = (root / "README.md").read_text()
    section = card[card.index("## Train a LeRobot policy on the original cameras"):]
    command = re.search(r"```bash\n(.*?)\n```", section, flags=re.S).group(1)
    info = json.loads((root / "meta" / "info.json").read_text())
    assert command == lerobot_train_command(info, REPO_ID)
    assert "control." not in command and "observation.depth" not in command
    # The card's command as a user would paste it, for 2 steps.
    run = subprocess.run(["bash", "-c", command + " --steps=2 --batch_size=2 --num_workers=0 --log_freq=1 "
                          "--save_checkpoint=false"], cwd=tmp_path, env=_env(home), capture_output=True, text=True,
                         timeout=900)
    out = run.stdout + run.stderr
    assert run.returncode == 0, out[-3000:]
    assert "End of training" in out
    losses = [float(x) for x in re.findall(r"loss:(\d+\.?\d*)", out)]
    assert losses and all(np.isfinite(losses)), out[-2000:]
    assert "num_learnable_params" in out and "'observation.images.cam_high'" in out


def logged_images(rrd: Path) -> dict[str, dict[int, tuple[dict, list]]]:
    """``{entity: {frame_index: (Image:format, Image:buffer)}}`` of a rerun recording. rerun-sdk 0.33
    removed ``rerun.dataframe`` (LeRobot 0.4.4 pins rerun-sdk below 0.27; LeRobot 0.6.1's viz extra
    takes 0.33), so there its chunks are read with ``rerun.experimental.RrdReader``."""
    out: dict[str, dict[int, tuple[dict, list]]] = {}
    try:
        from rerun import dataframe as rr_df
    except ImportError:  # rerun-sdk >= 0.33
        from rerun.experimental import RrdReader

        for chunk in RrdReader(str(rrd)).store().stream():
            rb = chunk.to_record_batch()
            if "Image:buffer" not in rb.schema.names:
                continue
            for f, fmt, buf in zip(rb.column("frame_index").to_pylist(), rb.column("Image:format").to_pylist(),
                                   rb.column("Image:buffer").to_pylist()):
                out.setdefault(chunk.entity_path, {})[f] = (fmt[0], buf[0])
        return out
    recording = rr_df.load_recording(str(rrd))
    entities = {c.entity_path for c in recording.schema().component_columns() if c.component == "Image:buffer"}
    for entity in entities:
        table = recording.view(index="frame_index", contents=entity).select().read_all()
        for f, fmt, buf in zip(table.column("frame_index").to_pylist(), table.column(f"{entity}:Image:format"),
                               table.column(f"{entity}:Image:buffer")):
            out.setdefault(entity, {})[f] = (fmt.as_py()[0], buf.as_py()[0])
    return out


def test_lerobot_dataset_viz_records_every_stream(built, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.scripts.lerobot_dataset_viz import to_hwc_uint8_numpy

    home, root = built
    run = subprocess.run(["lerobot-dataset-viz", "--repo-id", REPO_ID, "--root", str(root), "--episode-index", "0",
                          "--save", "1", "--output-dir", str(tmp_path / "viz"), "--num-workers", "0",
                          "--batch-size", "4"], env=_env(home), capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, (run.stdout + run.stderr)[-3000:]
    images = logged_images(tmp_path / "viz" / "local_tiny_episode_0.rrd")
    ds = LeRobotDataset(REPO_ID, root=root)
    assert len(ds.meta.video_keys) == 15  # 3 cameras x (rgb, depth, motion, r2s, s2g)
    assert {f"/{k}" for k in ds.meta.video_keys} <= set(images)
    for key in ds.meta.video_keys:
        assert sorted(images[f"/{key}"]) == list(range(T)), key
        fmt = images[f"/{key}"][0][0]
        assert (fmt["height"], fmt["width"]) == (H, W), key
    key, k = "control.motion.cam_high", 3
    logged = np.array(images[f"/{key}"][k][1], dtype=np.uint8)
    np.testing.assert_array_equal(logged.reshape(H, W, 3), to_hwc_uint8_numpy(ds[k][key]))


def _source_frames(root: Path, key: str) -> np.ndarray:
    (path,) = sorted((root / "videos" / key).rglob("*.mp4"))  # one episode, one file
    return read_video_frames(path)


def test_preview_mosaic_of_every_stream(built, tmp_path, capsys):
    home, root = built
    out = tmp_path / "preview.mp4"
    assert imac_main(["qa", "preview", str(root), "--episode", "0", "--out", str(out), "--no-progress"]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    video = read_video_frames(out)
    cams = ["cam_high", "cam_left_wrist", "cam_right_wrist"]
    assert video.shape == (T, LABEL_PX + len(ROWS) * (H + LABEL_PX), len(cams) * W, 3)
    for r, (label, prefix) in enumerate(ROWS):
        y = LABEL_PX + r * (H + LABEL_PX) + LABEL_PX
        assert video[:, y - LABEL_PX:y].max() > 200, f"row {label!r} has no label"
        for c, cam in enumerate(cams):
            tile = video[:, y:y + H, c * W:(c + 1) * W].astype(float)
            assert tile.mean() > 5, f"{label} {cam} is black"
            if prefix != "observation.depth.":  # depth is shown decoded and colour-mapped
                err = np.abs(tile - _source_frames(root, prefix + cam)).mean()
                assert err < 6, f"{label} {cam}: mean abs error {err:.1f} against the source video"
    # Bad input: a clear error and nothing written.
    assert imac_main(["qa", "preview", str(root), "--episode", "3", "--out", str(tmp_path / "x.mp4")]) == 2
    assert "episode 3 does not exist" in capsys.readouterr().err
    assert imac_main(["qa", "preview", str(root), "--out", str(root / "x.mp4")]) == 2
    assert "outside the dataset" in capsys.readouterr().err
    assert imac_main(["qa", "preview", str(tmp_path), "--out", str(tmp_path / "y.mp4")]) == 2
    assert "not a LeRobot dataset" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["preview.mp4"]
