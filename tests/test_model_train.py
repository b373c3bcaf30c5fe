"""imac_model on a real dataset built by imac_data.build.hdf5: chunks against LeRobot's own loader,
the training and sampling CLIs, exact resume, and bad input."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from safetensors.torch import load_file

from imac_data.cli import main as imac_main
from imac_data.metadata import dataset_info
from imac_data.recipes import RECIPES_DIR
from imac_data.sources.sim.recorder import SimConfig, record_dataset
from imac_model.cli import main as model_main
from imac_model.config import DataConfig, load_run_config
from imac_model.data.chunks import ChunkDataset, open_metadata, resolve_layout
from imac_model.training import train as train_cli
from imac_model.training.log import read_log

ROOT = Path(__file__).resolve().parents[1]
CHUNK = 4
VIEWS = ("cam_high", "cam_left_wrist", "cam_right_wrist")
TINY = ["--set", "backbone.small.dim=32", "--set", "backbone.small.depth=1", "--set", "backbone.small.heads=2",
        "--set", "train.batch_size=2", "--set", "train.eval_batches=1", "--set", "train.log_every=1",
        "--set", "data.view_height=32", "--set", "train.warmup_steps=2", "--set", "data.held_out_episodes=[1]"]


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("chunk_cache")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """Two short simulated episodes (22 and 21 frames) built with the real builder, contact chunk 4."""
    tmp = tmp_path_factory.mktemp("model_ds")
    sim = tmp / "sim"
    record_dataset(SimConfig(num_episodes=2, width=80, height=64, max_steps=44), sim, progress=False)
    recipe = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    recipe["augment"] = {"height": 64, "width": 80, "contact_chunk": CHUNK}
    (tmp / "recipe.yaml").write_text(yaml.safe_dump(recipe))
    root = tmp / "ds"
    assert imac_main(["build", "--repo", "local/model_tiny", "--recipe", str(tmp / "recipe.yaml"), "--source", str(sim),
                       "--root", str(root), "--no-progress", "--workers", "1"]) == 0
    return root


def run_args(dataset, out, *extra):
    return ["--dataset", "local/model_tiny", "--root", str(dataset), "--output-dir", str(out), "--no-progress",
            *TINY, *extra]


def test_chunks_are_lerobots_frames_in_the_mosaic(dataset):
    """Every field of an item against LeRobot's own loader (no delta_timestamps) at the
    dataset's resolution: reference rule, layout, controls of the future frames, padding."""
    data = DataConfig(dataset="local/model_tiny", root=str(dataset), view_height=64)
    meta = open_metadata(data)
    layout = resolve_layout(dataset_info(meta), data, ("motion", "contact_s2g", "contact_r2s"), spatial_multiple=8,
                            temporal_factor=1, mode="motion+contact")
    assert layout.views == VIEWS and layout.view_hw == (64, 80) and layout.chunk == CHUNK
    chunks = ChunkDataset("local/model_tiny", layout, root=dataset, cache="none")
    plain = LeRobotDataset("local/model_tiny", root=dataset)
    lengths = [int(n) for n in plain.meta.episodes["length"]]
    starts = [int(s) for s in plain.meta.episodes["dataset_from_index"]]
    assert len(chunks) == sum(len(range(0, n - 1, CHUNK)) for n in lengths)
    h, w = 64, 80
    for i in (1, len(chunks.episode_chunks(0)) - 1):  # a middle chunk and the (padded) last one of episode 0
        item = chunks[i]
        _, episode, ref = chunks.index[i]
        assert episode == 0 and ref == i * CHUNK
        for k in (0, 1, CHUNK):
            frame = min(ref + k, lengths[0] - 1)  # LeRobot pads with the episode's last frame
            row = plain[starts[0] + frame]
            got = item["reference"] if k == 0 else item["future"][k - 1]
            for v, cam in enumerate(VIEWS):
                rgb = (row[f"observation.images.{cam}"] * 255).round().byte()
                depth = (row[f"observation.depth.{cam}"] * 255).round().byte()
                assert torch.equal(got[:, :h, v * w:(v + 1) * w], rgb)
                assert torch.equal(got[:, h:, v * w:(v + 1) * w], depth)
                if k > 0:
                    motion = (row[f"control.motion.{cam}"] * 255).round().byte()
                    assert torch.equal(item["control.motion"][k - 1][:, :h, v * w:(v + 1) * w], motion)
                    assert torch.equal(item["control.motion"][k - 1][:, h:, v * w:(v + 1) * w], motion)
            if k < CHUNK:
                torch.testing.assert_close(item["actions"][k], plain[starts[0] + frame]["action"])
        valid = [ref + k < lengths[0] for k in range(1, CHUNK + 1)]
        assert item["future_valid"].tolist() == valid
        assert bool(item["success"]) == bool(plain.meta.episodes["imac/success"][0])
    assert not all(chunks[len(chunks.episode_chunks(0)) - 1]["future_valid"])  # the last chunk is padded


def test_decoding_in_a_worker_after_the_parent_read_the_videos(dataset):
    """LeRobot caches one open video file per path; a forked worker that read through the parent's would move
    the file offset they share and garble both ("Invalid data found when processing input"). The oracle: the
    items this process decodes alone, before and after three worker preloads."""
    data = DataConfig(dataset="local/model_tiny", root=str(dataset), view_height=64)
    layout = resolve_layout(dataset_info(open_metadata(data)), data, ("motion",), spatial_multiple=8,
                            temporal_factor=1, mode="motion")
    alone = ChunkDataset("local/model_tiny", layout, root=dataset, cache="none")
    truth = [alone[i] for i in range(len(alone))]  # the parent now holds every video open
    for _ in range(3):
        preloaded = ChunkDataset("local/model_tiny", layout, root=dataset, cache="memory")
        preloaded.preload(num_workers=1, progress=False)
        for i in (len(alone) - 1, 0, len(alone) // 2):  # the parent reads again, out of order
            assert torch.equal(alone[i]["future"], truth[i]["future"])
        for i, item in enumerate(truth):
            for key in ("reference", "future", "control.motion"):
                assert torch.equal(preloaded[i][key], item[key]), (i, key)


def test_a_batch_carries_each_chunks_episode_first_frame(dataset):
    """``ChunkBatch.first_frame`` against LeRobot's own loader: frame 0 of each chunk's episode."""
    data = DataConfig(dataset="local/model_tiny", root=str(dataset), view_height=64)
    layout = resolve_layout(dataset_info(open_metadata(data)), data, (), spatial_multiple=8, temporal_factor=1,
                            mode="none")
    chunks = ChunkDataset("local/model_tiny", layout, root=dataset, cache="none")
    plain = LeRobotDataset("local/model_tiny", root=dataset)
    starts = [int(s) for s in plain.meta.episodes["dataset_from_index"]]
    picks = [chunks.episode_chunks(1)[2], chunks.episode_chunks(0)[3], chunks.episode_chunks(1)[0]]
    batch = chunks.batch(picks)
    h, w = 64, 80
    for b, i in enumerate(picks):
        row = plain[starts[chunks.index[i][1]]]
        got = (batch.first_frame[b] * 255).round().byte()
        for v, cam in enumerate(VIEWS):
            assert torch.equal(got[:, :h, v * w:(v + 1) * w], (row[f"observation.images.{cam}"] * 255).round().byte())
            assert torch.equal(got[:, h:, v * w:(v + 1) * w], (row[f"observation.depth.{cam}"] * 255).round().byte())
    assert not torch.equal(batch.first_frame[0], batch.first_frame[1])


@pytest.fixture(scope="module")
def trained(dataset, cache_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "run"
    rc = model_main(["train", *run_args(dataset, out, "--set", "train.max_steps=4", "--set", "train.checkpoint_every=2",
                                        "--set", "train.eval_every=2", "--set", f"data.cache_dir={cache_dir}")])
    assert rc == 0
    return out


def test_training_logs_held_out_loss_and_checkpoints(trained):
    rows = [json.loads(line) for line in (trained / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [0, 1, 2, 3, 4]
    assert all("heldout_loss" in r for r in rows if r["step"] in (0, 2, 4))
    assert (trained / "log.csv").read_text().splitlines()[0].startswith("step,loss,heldout_loss")
    last = trained / "checkpoints" / "step_000004"
    for name in ("model.json", "config.yaml", "model.safetensors", "ema.safetensors", "trainer_state.pt"):
        assert (last / name).is_file(), name
    # the saved config loads back and is the run's
    run = load_run_config(last / "config.yaml")
    assert run.train.max_steps == 4 and run.data.held_out_episodes == (1,)


def test_resume_equals_an_uninterrupted_run(dataset, trained, tmp_path):
    out = tmp_path / "resumed"
    run = load_run_config(trained / "config.yaml").replace(**{"train.output_dir": str(out)})
    assert len(list(Path(run.data.cache_dir).glob("chunks-*.pt"))) == 2  # train and held-out chunks, reused
    first = train_cli.train(run, progress=False, stop_after_steps=2)
    assert first.step == 2 and first.stopped == "interrupted"
    second = train_cli.train(run, progress=False)
    assert second.step == 4
    for name in ("model.safetensors", "ema.safetensors"):
        a = load_file(trained / "checkpoints" / "step_000004" / name)
        b = load_file(out / "checkpoints" / "step_000004" / name)
        assert a.keys() == b.keys()
        for k in a:
            assert torch.equal(a[k], b[k]), (name, k)
    loss = lambda d: [r.get("loss") for r in map(json.loads, (d / "log.jsonl").read_text().splitlines())]  # noqa: E731
    assert loss(out) == loss(trained)
    # not vacuous: another seed trains to other weights
    other = tmp_path / "other"
    train_cli.train(run.replace(**{"train.output_dir": str(other), "train.seed": 1}), progress=False)
    a = load_file(trained / "checkpoints" / "step_000004" / "model.safetensors")
    c = load_file(other / "checkpoints" / "step_000004" / "model.safetensors")
    assert any(not torch.equal(a[k], c[k]) for k in a)


def test_sample_cli_writes_the_mosaic_video(trained, tmp_path, capsys):
    import av

    out, png = tmp_path / "s.mp4", tmp_path / "s.png"
    assert model_main(["sample", "--checkpoint", str(trained), "--episode", "1", "--chunk", "1", "--out", str(out),
                            "--png", str(png), "--steps", "2", "--scale", "1"]) == 0
    assert "pixel MSE vs recorded" in capsys.readouterr().out
    with av.open(str(out)) as f:
        frames = [fr.to_ndarray(format="rgb24") for fr in f.decode(video=0)]
    assert len(frames) == CHUNK
    # generated | recorded | controls (three streams, one row each): 2 mosaics of 64x120 + 120 wide
    assert frames[0].shape == (96, 3 * 120, 3)
    assert png.is_file()


def _copy_without(dataset: Path, dst: Path, prefix: str) -> Path:
    shutil.copytree(dataset, dst)
    info = json.loads((dst / "meta" / "info.json").read_text())
    info["features"] = {k: v for k, v in info["features"].items() if not k.startswith(prefix)}
    (dst / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    return dst


@pytest.mark.parametrize("extra, message", [
    (["--set", "data.chunk=8"], "data.chunk: 8 future frames per chunk, but the dataset's contact chunk is 4"),
    (["--set", "data.view_height=30"], "data.view_height: 30 cannot be patchified"),
    (["--set", "backbone.kind=wan", "--set", "data.view_height=24"],
     "data.view_height: 24 cannot be patchified: the mosaic height 2 x 24 must be a multiple of 32"),
    (["--set", "backbone.kind=wan"], "no view width near the cameras' aspect 1.25 patchifies at height 32; use "
                                     "view_height 80 or 128"),
    (["--set", "train.lrr=1"], "train: unknown field(s) ['lrr']"),
    (["--set", "data.held_out_episodes=[7]"], "data.held_out_episodes: [7] do not exist"),
    (["--root", "/nonexistent/imac_dataset"], "at /nonexistent/imac_dataset (there is no meta/info.json there, so "
                                              "LeRobot tried the hub)"),
])
def test_bad_runs_fail_before_training_and_write_nothing(dataset, tmp_path, capsys, extra, message):
    out = tmp_path / "run"
    assert model_main(["train", *run_args(dataset, out, *extra)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_a_dataset_without_the_modes_streams_is_refused(dataset, tmp_path, capsys):
    no_contact = _copy_without(dataset, tmp_path / "no_contact", "control.contact_")
    out = tmp_path / "run"
    args = ["--dataset", "local/x", "--root", str(no_contact), "--output-dir", str(out), *TINY]
    assert model_main(["train", *args, "--mode", "motion+contact"]) == 2
    err = capsys.readouterr().err
    assert "lacks streams that conditioning mode 'motion+contact' needs" in err
    assert "control.contact_s2g.cam_high" in err and "control.contact_r2s.cam_right_wrist" in err
    assert not out.exists()
    # the motion mode only needs what is there
    meta = open_metadata(DataConfig(dataset="local/x", root=str(no_contact)))
    resolve_layout(dataset_info(meta), DataConfig(view_height=32), ("motion",), spatial_multiple=8, temporal_factor=1)


def test_unreadable_checkpoints_are_named(trained, tmp_path, capsys):
    bad = tmp_path / "ckpt"
    shutil.copytree(trained / "checkpoints" / "step_000004", bad)
    weights = bad / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:1000])
    assert model_main(["sample", "--checkpoint", str(bad), "--episode", "0"]) == 2
    assert f"{weights}: unreadable weights" in capsys.readouterr().err
    (bad / "model.json").write_text("{not json")
    assert model_main(["sample", "--checkpoint", str(bad), "--episode", "0"]) == 2
    assert "model.json" in capsys.readouterr().err
    assert model_main(["sample", "--checkpoint", str(tmp_path / "nope"), "--episode", "0"]) == 2
    assert "checkpoint not found" in capsys.readouterr().err
    # weights of another model
    other = tmp_path / "other"
    shutil.copytree(trained / "checkpoints" / "step_000004", other)
    spec = json.loads((other / "model.json").read_text())
    spec["backbone"]["small"]["dim"] = 64
    spec["backbone"]["small"]["heads"] = 4
    (other / "model.json").write_text(json.dumps(spec))
    assert model_main(["sample", "--checkpoint", str(other), "--episode", "0"]) == 2
    assert "do not fit the model" in capsys.readouterr().err
    # resuming into a directory whose checkpoints are of another model is refused
    run = load_run_config(trained / "config.yaml").replace(**{"backbone.small.dim": 64, "backbone.small.heads": 4})
    from imac_data.errors import InputError

    with pytest.raises(InputError, match="holds checkpoints of another model"):
        train_cli.train(run, progress=False)


def test_data_parallel_on_the_cpu_trains_one_run_over_both_processes(dataset, tmp_path):
    """torchrun on a machine without a GPU: two gloo processes train one run of the global batch (not two copies
    writing one directory): one log whose rows count both processes and their CPU time, and the held-out losses of
    one process trained on the same batches."""
    one, two = tmp_path / "one", tmp_path / "two"
    args = ["--set", "train.max_steps=4", "--set", "train.eval_every=2", "--set", "train.cpu_threads=1"]
    assert model_main(["train", *run_args(dataset, one, *args)]) == 0
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    env.pop("CUDA_VISIBLE_DEVICES", None)
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                           "-m", "imac_model", "train", *run_args(dataset, two, *args)], env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    a, b = read_log(one), read_log(two)
    assert [r["step"] for r in b] == [r["step"] for r in a] == [0, 1, 2, 3, 4]  # one log, not one per process
    assert [r.get("processes") for r in a[1:]] == [1] * 4 and [r.get("processes") for r in b[1:]] == [2] * 4
    held = [(x["heldout_loss"], y["heldout_loss"]) for x, y in zip(a, b) if "heldout_loss" in x]
    assert len(held) == 3 and all(abs(x - y) <= 2e-3 * abs(x) for x, y in held), held


def test_the_ema_follows_the_weights_to_the_device_the_runtime_moves_them_to():
    """The trainer makes the EMA before the runtime moves the model to its device (a GPU); the first update
    must then move the shadow, not mix devices (the loan of 2026-12-04 stopped at its first step so). The
    "meta" device stands in for the GPU: a real move with no data. On one device, the update is the average."""
    from imac_model.training.train import EMA

    model = torch.nn.Linear(3, 2)
    ema = EMA(model, decay=0.9)
    before = {k: v.clone() for k, v in ema.state().items()}
    with torch.no_grad():
        model.weight.add_(1.0)
    ema.update(model, step=0)  # d = min(0.9, 1 / 10)
    assert torch.allclose(ema.state()["weight"], 0.1 * before["weight"] + 0.9 * model.weight)
    ema.update(model.to("meta"), step=1)
    assert {v.device.type for v in ema.state().values()} == {"meta"}
