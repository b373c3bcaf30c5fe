"""Success judging behind one interface: did an episode succeed?

A :class:`SuccessJudge` maps episodes (:class:`EpisodeFrames`: an index, its last frames per
camera, its task) to booleans: :class:`SuccessClassifier` (a small CNN trained on a dataset's own
``imac/success`` labels, held-out accuracy reported beside the majority baseline),
:class:`CsvJudge` (labels scored by people) and :class:`CallableJudge` (any external judge).
Frames are read with LeRobot's own metadata and decoder, only where needed."""

from __future__ import annotations

import csv
import json
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from imac_data import lerobot_compat as lr
from imac_data.core.depth import depth_codec_of
from imac_data.errors import InputError
from imac_data.layout import IMAGE_PREFIX, STATE, SUCCESS_COLUMN, depth_key, video_column
from imac_model.data.depth import decode_depth
from imac_model.evaluate.policies import python_object


@dataclass(frozen=True)
class EpisodeFrames:
    """What a judge sees of one episode, its last K frames (real or generated):
    ``frames[camera]`` ``(K, 3, H, W)`` float in [0, 1]; where asked for, ``depth[camera]``
    ``(K, H, W)`` metres (0 = unknown) under the same camera keys and ``states`` ``(K, D)``."""

    episode_index: int
    frames: Mapping[str, torch.Tensor]
    task: str | None = None
    depth: Mapping[str, torch.Tensor] | None = None
    states: torch.Tensor | None = None


class SuccessJudge(ABC):
    """Judges episodes: one boolean (success) per episode."""

    name: str = "judge"

    @abstractmethod
    def judge(self, episodes: Sequence[EpisodeFrames]) -> np.ndarray:
        """Success (bool) per episode, in order."""


# --------------------------------------------------------------------------- reading datasets


def dataset_success_labels(dataset) -> dict[int, bool | None]:
    """The dataset's own per-episode labels (``imac/success``; None where unknown)."""
    episodes = dataset.meta.episodes
    if SUCCESS_COLUMN not in episodes.column_names:
        raise InputError(f"{dataset.root}: meta/episodes has no {SUCCESS_COLUMN!r} column "
                         "(datasets built by `python -m imac_data.build` have it)")
    return {int(i): (None if s is None else bool(s))
            for i, s in zip(episodes["episode_index"], episodes[SUCCESS_COLUMN])}


def image_cameras(dataset) -> list[str]:
    """The dataset's RGB camera keys (``observation.images.*``)."""
    return [k for k in dataset.meta.camera_keys if k.startswith(IMAGE_PREFIX)]


def episode_frames(dataset, episodes: Iterable[int] | None = None, cameras: Sequence[str] | None = None,
                   last: int = 4, *, geometry: bool = False, at: Sequence[int] | None = None) -> list[EpisodeFrames]:
    """The last ``last`` frames of each episode and camera (or, with ``at``, those frame indices of
    each), decoded by LeRobot's video decoder from the dataset's own files (only these cameras and
    timestamps). With ``geometry``, also each camera's depth in metres (its ``observation.depth.*``
    colour video through the dataset's depth codec) and the states."""
    meta = dataset.meta
    cameras = list(cameras) if cameras is not None else image_cameras(dataset)
    missing = [c for c in cameras if c not in meta.video_keys]
    if missing or not cameras:
        raise InputError(f"{dataset.root}: camera keys {missing or cameras} are not video features of the dataset "
                         f"(it has {meta.video_keys})")
    depth_of = {c: depth_key(c[len(IMAGE_PREFIX):]) for c in cameras}
    codec = None
    if geometry:
        absent = [k for k in depth_of.values() if k not in meta.video_keys] + \
            ([STATE] if STATE not in meta.features else [])
        if absent:
            raise InputError(f"{dataset.root}: judging geometry needs {absent}, which the dataset does not have")
        codec = depth_codec_of(meta)
    if not isinstance(last, int) or last < 1:
        raise InputError(f"last: must be a positive integer, got {last!r}")
    if at is not None and (not at or any(not isinstance(i, int) or i < 0 for i in at)):
        raise InputError(f"at: must be frame indices >= 0, got {at!r}")
    table = meta.episodes
    index_of = {int(e): row for row, e in enumerate(table["episode_index"])}
    wanted = list(index_of) if episodes is None else [int(e) for e in episodes]
    unknown = [e for e in wanted if e not in index_of]
    if unknown:
        raise InputError(f"{dataset.root}: episodes {unknown} are not in the dataset "
                         f"(it has {len(index_of)} episodes)")
    tasks, lengths = table["tasks"], table["length"]
    videos = cameras + ([depth_of[c] for c in cameras] if geometry else [])
    starts = {key: table[video_column(key, "from_timestamp")] for key in videos}

    def decode(ep, row, key, times):
        path = Path(dataset.root) / meta.get_video_file_path(ep, key)
        start = float(starts[key][row])
        return lr.decode_video_frames(path, [start + t for t in times], dataset.tolerance_s, lr.video_backend(dataset))

    out = []
    for ep in wanted:
        row = index_of[ep]
        length = int(lengths[row])
        indices = list(range(max(0, length - last), length)) if at is None else list(at)
        if indices and max(indices) >= length:
            raise InputError(f"{dataset.root}: episode {ep} has {length} frames, so no frame {max(indices)}")
        times = [i / meta.fps for i in indices]
        frames = {cam: decode(ep, row, cam, times) for cam in cameras}
        depth = states = None
        if geometry:
            depth = {cam: decode_depth(decode(ep, row, depth_of[cam], times), codec)[0] for cam in cameras}
            lo = int(table["dataset_from_index"][row])
            states = torch.stack([torch.as_tensor(x, dtype=torch.float32)
                                  for x in dataset.hf_dataset.select([lo + i for i in indices])[STATE]])
        task = tasks[row][0] if tasks[row] else None
        out.append(EpisodeFrames(ep, frames, task, depth, states))
    return out


# --------------------------------------------------------------------------- the learned classifier


@dataclass(frozen=True)
class SuccessClassifierConfig:
    """The classifier's input and training. Saved beside its weights."""

    cameras: tuple[str, ...]
    last_frames: int = 4  # frames per episode, from its end
    image_size: tuple[int, int] = (48, 64)  # (H, W) each camera is resized to
    width: int = 16  # channels of the first convolution
    epochs: int = 150
    lr: float = 3e-3
    weight_decay: float = 1e-4
    heldout_fraction: float = 0.25
    seed: int = 0
    threshold: float = 0.5
    threads: int = 1  # torch threads while training/predicting: the tiny CNN only loses to synchronisation with more

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", tuple(self.cameras))
        object.__setattr__(self, "image_size", tuple(int(x) for x in self.image_size))
        if not self.cameras:
            raise InputError("SuccessClassifierConfig.cameras: at least one camera key")
        for name in ("last_frames", "width", "epochs", "threads"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise InputError(f"SuccessClassifierConfig.{name}: must be a positive integer (got {v!r})")
        if len(self.image_size) != 2 or min(self.image_size) < 8:
            raise InputError(f"SuccessClassifierConfig.image_size: (H, W), each >= 8 (got {self.image_size!r})")
        if not 0.0 < self.heldout_fraction < 1.0:
            raise InputError(f"SuccessClassifierConfig.heldout_fraction: must be in (0, 1) "
                             f"(got {self.heldout_fraction!r})")
        if not 0.0 < self.threshold < 1.0:
            raise InputError(f"SuccessClassifierConfig.threshold: must be in (0, 1) (got {self.threshold!r})")
        if not self.lr > 0 or self.weight_decay < 0:
            raise InputError("SuccessClassifierConfig: lr must be > 0 and weight_decay >= 0")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping) -> SuccessClassifierConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise InputError(f"success classifier config: unknown field(s) {unknown}")
        return cls(**dict(data))


@contextmanager
def _torch_threads(n: int):
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


class _TinyCNN(nn.Module):
    """Three stride-2 convolutions, a coarse spatial pool (where things are matters:
    the object in the gripper vs on the table) and a linear read-out."""

    def __init__(self, in_channels: int, width: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(in_channels, 1, 1))
        self.register_buffer("std", torch.ones(in_channels, 1, 1))
        self.features = nn.Sequential(
            nn.Conv2d(in_channels, width, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(width, 2 * width, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(2 * width, 2 * width, 3, stride=2, padding=1), nn.ReLU(),
            nn.AdaptiveAvgPool2d((3, 4)), nn.Flatten(),
        )
        self.head = nn.Linear(2 * width * 12, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features((x - self.mean) / self.std)).squeeze(-1)


class SuccessClassifier(SuccessJudge):
    """A trained success classifier (see the module docstring); ``save``/``load`` a directory."""

    name = "classifier"

    def __init__(self, config: SuccessClassifierConfig, net: _TinyCNN | None = None):
        self.config = config
        self.net = net or _TinyCNN(3 * len(config.cameras), config.width)
        self.net.eval()

    def inputs(self, episodes: Sequence[EpisodeFrames]) -> tuple[torch.Tensor, torch.Tensor]:
        """``(frames, owner)``: one channel-stacked, resized image per (episode, frame),
        and the position of its episode in ``episodes``."""
        images, owner = [], []
        for i, ep in enumerate(episodes):
            missing = [c for c in self.config.cameras if c not in ep.frames]
            if missing:
                raise InputError(f"episode {ep.episode_index}: no frames for camera(s) {missing} "
                                 f"(the classifier was trained on {list(self.config.cameras)})")
            views = []
            for cam in self.config.cameras:
                f = torch.as_tensor(ep.frames[cam]).float()
                if f.ndim != 4 or f.shape[1] != 3:
                    raise InputError(f"episode {ep.episode_index}, {cam}: expected (K, 3, H, W) frames, "
                                     f"got {tuple(f.shape)}")
                f = f[-self.config.last_frames:]
                views.append(F.interpolate(f, size=self.config.image_size, mode="bilinear", antialias=True,
                                           align_corners=False))
            k = min(v.shape[0] for v in views)
            images.append(torch.cat([v[-k:] for v in views], dim=1))
            owner += [i] * k
        return torch.cat(images), torch.tensor(owner)

    @torch.no_grad()
    def probabilities(self, episodes: Sequence[EpisodeFrames]) -> np.ndarray:
        """Success probability per episode: the mean over its frames."""
        if not episodes:
            return np.zeros(0)
        x, owner = self.inputs(episodes)
        with _torch_threads(self.config.threads):
            p = torch.sigmoid(self.net(x)).double()
        sums = torch.zeros(len(episodes), dtype=torch.float64).index_add_(0, owner, p)
        counts = torch.bincount(owner, minlength=len(episodes)).double()
        return (sums / counts).numpy()

    def judge(self, episodes: Sequence[EpisodeFrames]) -> np.ndarray:
        return self.probabilities(episodes) >= self.config.threshold

    def save(self, directory: str | Path) -> Path:
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        (directory / "config.json").write_text(json.dumps(self.config.to_dict(), indent=2))
        torch.save(self.net.state_dict(), directory / "model.pt")
        return directory

    @classmethod
    def load(cls, directory: str | Path) -> SuccessClassifier:
        directory = Path(directory)
        for name in ("config.json", "model.pt"):
            if not (directory / name).is_file():
                raise InputError(f"{directory}: not a saved success classifier (no {name})")
        config = SuccessClassifierConfig.from_dict(json.loads((directory / "config.json").read_text()))
        clf = cls(config)
        clf.net.load_state_dict(torch.load(directory / "model.pt", map_location="cpu", weights_only=True))
        clf.net.eval()
        return clf


def split_episodes(labels: Mapping[int, bool], heldout_fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """Stratified train / held-out split of labelled episodes: each outcome contributes
    ``round(fraction * count)`` held-out episodes, at least one, leaving at least one
    for training."""
    counts = {o: sum(1 for v in labels.values() if v == o) for o in (True, False)}
    if min(counts.values()) < 2:
        raise InputError(f"the success classifier needs at least 2 labelled episodes of each outcome for a held-out "
                         f"split; got {counts[True]} successes and {counts[False]} failures")
    rng = np.random.default_rng(seed)
    train, heldout = [], []
    for outcome in (True, False):
        eps = np.array(sorted(e for e, v in labels.items() if v == outcome))
        rng.shuffle(eps)
        k = min(len(eps) - 1, max(1, round(heldout_fraction * len(eps))))
        heldout += eps[:k].tolist()
        train += eps[k:].tolist()
    return sorted(train), sorted(heldout)


def fit_classifier(config: SuccessClassifierConfig, episodes: Sequence[EpisodeFrames],
                   labels: Sequence[bool]) -> SuccessClassifier:
    """Train a fresh classifier on ``episodes`` (full batch, Adam, class-balanced loss)."""
    torch.manual_seed(config.seed)
    clf = SuccessClassifier(config)
    x, owner = clf.inputs(episodes)
    y = torch.tensor([float(labels[i]) for i in owner.tolist()])
    pos = float(y.sum())
    if pos == 0 or pos == len(y):
        raise InputError("training episodes must include both successes and failures")
    net = clf.net
    net.mean.copy_(x.mean((0, 2, 3)).reshape(-1, 1, 1))
    net.std.copy_(x.std((0, 2, 3)).clamp_min(1e-3).reshape(-1, 1, 1))
    loss_fn = nn.BCEWithLogitsLoss(pos_weight=torch.tensor((len(y) - pos) / pos))
    opt = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    net.train()
    with _torch_threads(config.threads):
        for _ in range(config.epochs):
            opt.zero_grad()
            loss = loss_fn(net(x), y)
            loss.backward()
            opt.step()
    net.eval()
    return clf


def evaluate_judge(judge: SuccessJudge, episodes: Sequence[EpisodeFrames], labels: Sequence[bool]) -> dict:
    """Accuracy of ``judge`` on labelled episodes (real or generated): accuracy,
    balanced accuracy, the majority-class baseline and the confusion counts."""
    if len(labels) != len(episodes) or len(labels) == 0:
        raise InputError(f"labels: {len(labels)} labels for {len(episodes)} episodes")
    return {**verdict_scores(judge.judge(episodes), labels), "episodes": [int(e.episode_index) for e in episodes]}


def verdict_scores(predicted: Sequence[bool], labels: Sequence[bool]) -> dict:
    """Verdicts against labels: accuracy, balanced accuracy (the mean recall of the outcomes
    present: a judge that always says the majority outcome scores 0.5), the majority-class
    baseline and the confusion counts."""
    pred, y = np.asarray(predicted, dtype=bool), np.asarray(labels, dtype=bool)
    if len(y) != len(pred) or len(y) == 0:
        raise InputError(f"labels: {len(y)} labels for {len(pred)} verdicts")
    tp, tn = int(np.sum(pred & y)), int(np.sum(~pred & ~y))
    fp, fn = int(np.sum(pred & ~y)), int(np.sum(~pred & y))
    recalls = [r for r in (tp / (tp + fn) if tp + fn else None, tn / (tn + fp) if tn + fp else None) if r is not None]
    return {
        "n": int(len(y)),
        "accuracy": (tp + tn) / len(y),
        "balanced_accuracy": float(np.mean(recalls)),
        "majority_baseline": max(y.mean(), 1 - y.mean()).item(),
        "confusion": {"true_positive": tp, "true_negative": tn, "false_positive": fp, "false_negative": fn},
        "predicted": pred.tolist(),
    }


def train_success_classifier(dataset, config: SuccessClassifierConfig | None = None, *,
                             cameras: Sequence[str] | None = None) -> tuple[SuccessClassifier, dict]:
    """Train on ``dataset``'s own labelled episodes; returns the classifier and a report
    with the split and the training and held-out accuracies (on real frames)."""
    if config is None:
        config = SuccessClassifierConfig(cameras=tuple(cameras) if cameras else tuple(image_cameras(dataset)))
    all_labels = dataset_success_labels(dataset)
    labels = {e: s for e, s in all_labels.items() if s is not None}
    unlabelled = len(all_labels) - len(labels)
    train_ids, heldout_ids = split_episodes(labels, config.heldout_fraction, config.seed)
    frames = {ep.episode_index: ep for ep in episode_frames(dataset, train_ids + heldout_ids, config.cameras,
                                                            config.last_frames)}
    train_eps = [frames[e] for e in train_ids]
    heldout_eps = [frames[e] for e in heldout_ids]
    clf = fit_classifier(config, train_eps, [labels[e] for e in train_ids])
    report = {
        "dataset": str(dataset.root),
        "config": config.to_dict(),
        "unlabelled_episodes": unlabelled,
        "train": evaluate_judge(clf, train_eps, [labels[e] for e in train_ids]),
        "heldout": evaluate_judge(clf, heldout_eps, [labels[e] for e in heldout_ids]),
        "frames": "real (recorded)",
    }
    return clf, report


# --------------------------------------------------------------------------- human and external judges


_TRUE = {"1", "true", "yes", "y", "success", "t"}
_FALSE = {"0", "false", "no", "n", "failure", "fail", "f"}


class CsvJudge(SuccessJudge):
    """Success labels scored by people, from a CSV with columns ``episode_index`` and
    ``success`` (1/0, true/false, yes/no, success/failure); other columns are ignored."""

    name = "csv"

    def __init__(self, labels: Mapping[int, bool], source: str = "labels"):
        self.labels = dict(labels)
        self.source = source

    @classmethod
    def from_csv(cls, path: str | Path, known_episodes: Iterable[int] | None = None) -> CsvJudge:
        """Read ``path``; with ``known_episodes`` (e.g. the dataset's episode indices),
        refuse a CSV that names any other episode."""
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: labels CSV not found")
        labels: dict[int, bool] = {}
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            columns = [c.strip() for c in (reader.fieldnames or [])]
            for col in ("episode_index", "success"):
                if col not in columns:
                    raise InputError(f"{path}: missing column {col!r} (columns: {columns})")
            for line, row in enumerate(reader, start=2):
                row = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
                try:
                    ep = int(row["episode_index"])
                except ValueError:
                    raise InputError(f"{path}:{line}: episode_index {row['episode_index']!r} is not an integer") \
                        from None
                value = row["success"].lower()
                if value not in _TRUE | _FALSE:
                    raise InputError(f"{path}:{line}: success {row['success']!r} is not one of "
                                     "1/0, true/false, yes/no, success/failure")
                if ep in labels:
                    raise InputError(f"{path}:{line}: episode {ep} is labelled twice")
                labels[ep] = value in _TRUE
        if not labels:
            raise InputError(f"{path}: no labels")
        if known_episodes is not None:
            known = {int(e) for e in known_episodes}
            unknown = sorted(set(labels) - known)
            if unknown:
                raise InputError(f"{path}: names episodes the dataset does not have: {unknown} "
                                 f"(the dataset has {len(known)} episodes"
                                 + (f", indices {min(known)}..{max(known)})" if known else ")"))
        return cls(labels, str(path))

    def judge(self, episodes: Sequence[EpisodeFrames]) -> np.ndarray:
        missing = [e.episode_index for e in episodes if e.episode_index not in self.labels]
        if missing:
            raise InputError(f"{self.source}: no label for episodes {missing}")
        return np.array([self.labels[e.episode_index] for e in episodes], dtype=bool)


class CallableJudge(SuccessJudge):
    """An external judge: ``fn(EpisodeFrames) -> bool or probability`` (>= threshold is success)."""

    name = "external"

    def __init__(self, fn: Callable[[EpisodeFrames], bool | float], threshold: float = 0.5, name: str = "external"):
        if not callable(fn):
            raise InputError(f"external judge must be callable, got {type(fn).__name__}")
        self.fn = fn
        self.threshold = threshold
        self.name = name

    def judge(self, episodes: Sequence[EpisodeFrames]) -> np.ndarray:
        out = []
        for ep in episodes:
            v = self.fn(ep)
            if isinstance(v, (bool, np.bool_)):
                out.append(bool(v))
            elif isinstance(v, (int, float, np.integer, np.floating)) and np.isfinite(v):
                out.append(float(v) >= self.threshold)
            else:
                raise InputError(f"external judge {self.name!r} returned {v!r} for episode {ep.episode_index}; "
                                 "expected a bool or a finite probability")
        return np.array(out, dtype=bool)


def _python_judge(spec: str) -> SuccessJudge:
    obj = python_object(spec, "judge")
    return obj if isinstance(obj, SuccessJudge) else CallableJudge(obj, name=spec[len("python:"):])


# The judges a command line names, ``KIND:ARGUMENT`` -> a judge made from the whole spec. A new judge
# is its class (a SuccessJudge) and one entry here.
JUDGES: dict[str, Callable[[str], SuccessJudge]] = {
    "classifier": lambda spec: SuccessClassifier.load(spec[len("classifier:"):]),  # classifier:DIR
    "python": _python_judge,  # python:MODULE:NAME
}


def load_judge(spec: str) -> SuccessJudge:
    """A judge from a command-line spec (:data:`JUDGES`): ``classifier:DIR`` (a saved
    :class:`SuccessClassifier`) or ``python:MODULE:NAME`` (a :class:`SuccessJudge`, a class making
    one, or a function ``EpisodeFrames -> bool or probability``)."""
    kind = spec.split(":", 1)[0]
    if ":" not in spec or kind not in JUDGES:
        raise InputError(f"unknown judge {spec!r}: use " + " or ".join(f"{k}:..." for k in JUDGES)
                         + " (classifier:DIR, python:MODULE:NAME)")
    return JUDGES[kind](spec)
