"""Success judging: the learned classifier (on frames whose outcome is visible, and end
to end on a LeRobot dataset recorded by the simulator with both outcomes), human labels
from a CSV, and an external callable judge."""

import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from imac_data.build.from_episodes import ingest_episodes
from imac_data.core.cameras import load_calibration
from imac_data.core.rig import Rig
from imac_data.core.robot import aloha
from imac_data.core.robot.model import RobotModel
from imac_data.dataset.ingest import IngestOptions
from imac_data.errors import InputError
from imac_data.sources.sim.recorder import SimConfig, record_dataset
from imac_model.evaluate.success import (
    CallableJudge,
    CsvJudge,
    EpisodeFrames,
    SuccessClassifier,
    SuccessClassifierConfig,
    dataset_success_labels,
    episode_frames,
    evaluate_judge,
    fit_classifier,
    split_episodes,
    train_success_classifier,
)

CAMS = ("observation.images.cam_high", "observation.images.cam_left_wrist", "observation.images.cam_right_wrist")


@pytest.fixture(scope="module")
def sim_dataset(tmp_path_factory):
    """Four full scripted transfer_cube episodes with policy noise 0.5 (seeds 4-7: two
    failures, then two successes, as the simulator judges them), through the builder's
    ingest stage into a LeRobot dataset with its ``imac/success`` column."""
    src = tmp_path_factory.mktemp("sim")
    record_dataset(SimConfig(num_episodes=4, width=64, height=48, noise=0.5, seed=4, with_depth=False), src,
                   progress=False)
    root = tmp_path_factory.mktemp("ds") / "succ"
    return ingest_episodes(sorted(src.glob("episode_*.hdf5")), rig=Rig(RobotModel(aloha.robot_config()), load_calibration(src / "calibration.json")),
                           repo_id="local/succ", root=root,
                           options=IngestOptions(fps=25, task="transfer the cube", source="policy"), progress=False)


def synthetic_episodes(n, rng):
    """Textured frames; a success shows a bright square near a fixed place in the head view."""
    episodes, labels = [], []
    for i in range(n):
        success = i % 2 == 0
        frames = {c: torch.from_numpy(rng.random((3, 3, 48, 64), dtype=np.float32) * 0.6) for c in CAMS[:2]}
        if success:
            y, x = 10 + rng.integers(-3, 4), 40 + rng.integers(-3, 4)
            frames[CAMS[0]][:, :, y:y + 10, x:x + 10] = 1.0
        episodes.append(EpisodeFrames(i, frames))
        labels.append(success)
    return episodes, labels


def test_classifier_learns_a_visible_outcome():
    rng = np.random.default_rng(0)
    episodes, labels = synthetic_episodes(32, rng)
    train_ids, heldout_ids = split_episodes(dict(enumerate(labels)), 0.25, seed=0)
    assert set(train_ids).isdisjoint(heldout_ids) and len(heldout_ids) == 8
    config = SuccessClassifierConfig(cameras=CAMS[:2], last_frames=3, epochs=60, image_size=(24, 32))
    clf = fit_classifier(config, [episodes[i] for i in train_ids], [labels[i] for i in train_ids])
    report = evaluate_judge(clf, [episodes[i] for i in heldout_ids], [labels[i] for i in heldout_ids])
    assert report["accuracy"] == 1.0 and report["majority_baseline"] == 0.5
    assert report["confusion"] == {"true_positive": 4, "true_negative": 4, "false_positive": 0, "false_negative": 0}


def test_classifier_trained_on_a_built_dataset(sim_dataset, tmp_path):
    labels = dataset_success_labels(sim_dataset)
    assert labels == {0: False, 1: False, 2: True, 3: True}, "the recorder's outcomes for seeds 4-7 changed"
    config = SuccessClassifierConfig(cameras=CAMS, last_frames=4, epochs=40)
    clf, report = train_success_classifier(sim_dataset, config)
    train, heldout = report["train"], report["heldout"]
    # stratified, disjoint, covering every labelled episode
    assert set(train["episodes"]).isdisjoint(heldout["episodes"])
    assert sorted(train["episodes"] + heldout["episodes"]) == [0, 1, 2, 3]
    for part in (train, heldout):
        truth = [labels[e] for e in part["episodes"]]
        assert sorted(truth) == [False, True]
        assert part["accuracy"] == np.mean(np.array(part["predicted"]) == np.array(truth))
    assert report["frames"] == "real (recorded)" and report["unlabelled_episodes"] == 0
    # saved and loaded back: same probabilities
    real = episode_frames(sim_dataset, [0, 1, 2, 3], CAMS, last=4)
    loaded = SuccessClassifier.load(clf.save(tmp_path / "clf"))
    np.testing.assert_allclose(loaded.probabilities(real), clf.probabilities(real), rtol=1e-6)
    # generated frames (any tensors under the same camera keys, any length) go through the same judge
    generated = [EpisodeFrames(10 + e.episode_index, {c: e.frames[c].flip(-1)[:2] for c in CAMS}) for e in real]
    result = evaluate_judge(loaded, generated, [labels[e.episode_index] for e in real])
    assert result["n"] == 4 and result["episodes"] == [10, 11, 12, 13]
    with pytest.raises(InputError, match="no frames for camera"):
        loaded.judge([EpisodeFrames(0, {CAMS[0]: real[0].frames[CAMS[0]]})])


def test_episode_frames_are_the_last_frames_of_each_episode_or_those_asked_for(sim_dataset):
    eps = episode_frames(sim_dataset, [1, 3], CAMS[:1], last=2)
    ends = sim_dataset.meta.episodes["dataset_to_index"]
    for ep in eps:
        last = ends[ep.episode_index] - 1
        frames = ep.frames[CAMS[0]]
        assert frames.shape == (2, 3, 48, 64)
        torch.testing.assert_close(frames[1], sim_dataset[last][CAMS[0]], rtol=0, atol=0)
        torch.testing.assert_close(frames[0], sim_dataset[last - 1][CAMS[0]], rtol=0, atol=0)
        assert ep.task == sim_dataset[last]["task"]
    starts = sim_dataset.meta.episodes["dataset_from_index"]
    for ep in episode_frames(sim_dataset, [1, 3], CAMS[:1], at=[4, 0, 2]):  # chosen frames, in the order asked
        for k, i in enumerate([4, 0, 2]):
            torch.testing.assert_close(ep.frames[CAMS[0]][k], sim_dataset[starts[ep.episode_index] + i][CAMS[0]],
                                       rtol=0, atol=0)
    length = int(sim_dataset.meta.episodes["length"][1])
    with pytest.raises(InputError, match=f"episode 1 has {length} frames, so no frame {length}"):
        episode_frames(sim_dataset, [1], CAMS[:1], at=[0, length])
    with pytest.raises(InputError, match=r"episodes \[9\] are not in the dataset"):
        episode_frames(sim_dataset, [9], CAMS[:1])
    with pytest.raises(InputError, match="not video features"):
        episode_frames(sim_dataset, [0], ["observation.images.nope"])


def test_labels_column_required(sim_dataset, tmp_path):
    root = tmp_path / "nolabels"
    shutil.copytree(sim_dataset.root, root)
    for f in (root / "meta" / "episodes").rglob("*.parquet"):
        pq.write_table(pq.read_table(f).drop(["imac/success"]), f)
    with pytest.raises(InputError, match="no 'imac/success' column"):
        dataset_success_labels(LeRobotDataset("local/succ", root=root))


def test_too_few_labelled_episodes():
    with pytest.raises(InputError, match="at least 2 labelled episodes of each outcome"):
        split_episodes({0: True, 1: False, 2: False}, 0.25, 0)


def test_csv_judge(tmp_path):
    path = tmp_path / "labels.csv"
    path.write_text("episode_index,success,notes\n0,1,ok\n1, false ,dropped\n2,Yes,\n3,failure,\n")
    judge = CsvJudge.from_csv(path, known_episodes=range(4))
    episodes = [EpisodeFrames(i, {}) for i in (3, 0, 2, 1)]
    assert judge.judge(episodes).tolist() == [False, True, True, False]
    with pytest.raises(InputError, match=r"names episodes the dataset does not have: \[3\]"):
        CsvJudge.from_csv(path, known_episodes=range(3))
    with pytest.raises(InputError, match=r"no label for episodes \[7\]"):
        judge.judge([EpisodeFrames(7, {})])
    for text, message in (("episode,success\n0,1\n", "missing column 'episode_index'"),
                          ("episode_index,success\n0,maybe\n", r"labels.csv:2: success 'maybe'"),
                          ("episode_index,success\n0,1\n0,0\n", r"labels.csv:3: episode 0 is labelled twice"),
                          ("episode_index,success\nx,1\n", "is not an integer"),
                          ("episode_index,success\n", "no labels")):
        path.write_text(text)
        with pytest.raises(InputError, match=message):
            CsvJudge.from_csv(path)


def test_callable_judge():
    episodes = [EpisodeFrames(i, {"cam": torch.full((1, 3, 4, 4), i / 4)}) for i in range(4)]
    by_brightness = CallableJudge(lambda ep: float(ep.frames["cam"].mean()), threshold=0.4, name="bright")
    assert by_brightness.judge(episodes).tolist() == [False, False, True, True]
    assert CallableJudge(lambda ep: ep.episode_index == 1).judge(episodes).tolist() == [False, True, False, False]
    with pytest.raises(InputError, match="returned 'yes'"):
        CallableJudge(lambda ep: "yes").judge(episodes)
    with pytest.raises(InputError, match="must be callable"):
        CallableJudge(42)
