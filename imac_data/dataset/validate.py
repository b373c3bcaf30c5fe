"""Checks of a dataset built by imac: the build's final check of its staged dataset, and
``imac validate ROOT [--full]``.

Each check is a function ``(ctx) -> [problem, ...]`` in :data:`CHECKS`, run in order (a check
whose prerequisite failed is skipped, saying so): ``metadata``, ``frame_counts``,
``imac_block``, ``rig``, ``joint_units``, ``calibration``, ``caps``, ``decode``, ``depth``
(``docs/building.md``, "Checking a dataset"). Video frames are sampled per episode unless ``full``."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from imac_data import lerobot_compat as lr
from imac_data.core.cameras import camera_from_dict, rigid_problem
from imac_data.core.depth import depth_codec_of, walk_distance
from imac_data.core.depth_map import PIX_FMT as DEPTH_MAP_PIX_FMT
from imac_data.core.depth_map import params_of_feature
from imac_data.core.rig import Rig
from imac_data.core.robot.lerobot_units import value_problems
from imac_data.dataset.info import RIG_KEYS, STREAM_KEYS, imac_block, read_info
from imac_data.dataset.streams import episode_files
from imac_data.dataset.videos import read_video_frames
from imac_data.errors import InputError
from imac_data.layout import (
    CAP_KEY,
    DEPTH_MAP_PREFIX,
    DEPTH_PREFIX,
    IMAC_INFO,
    IMAGE_PREFIX,
    POSE_PREFIX,
    STATE,
    info_path,
    is_added_stream,
    video_column,
)
from imac_data.metadata import imac_block_path, unchecked_imac_block
from imac_data.sources.lerobot_episodes import count_decodable_frames, stream_pix_fmt

__all__ = ["validate_dataset", "Report", "CHECKS"]

RIGID_TOL = 1e-4  # rotation orthonormality and det, camera poses stored as float32


@dataclass
class Report:
    """Problems per check (an empty list = passed; a missing check = not run)."""

    root: Path
    full: bool
    results: dict[str, list[str]] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not any(self.results.values()) and not self.skipped

    @property
    def problems(self) -> list[str]:
        return [f"{check}: {p}" for check, ps in self.results.items() for p in ps]

    def format(self) -> str:
        lines = [f"{self.root}: {'OK' if self.ok else 'INVALID'} ({'every frame' if self.full else 'sampled frames'})"]
        for check, ps in self.results.items():
            lines.append(f"  {'ok  ' if not ps else 'FAIL'} {check}" + ("" if not ps else f": {len(ps)} problem(s)"))
            lines += [f"         - {p}" for p in ps[:20]] + ([f"         ... {len(ps) - 20} more"] if len(ps) > 20 else [])
        for check, why in self.skipped.items():
            lines.append(f"  skip {check}: {why}")
        return "\n".join(lines)

    def raise_if_invalid(self) -> None:
        if not self.ok:
            raise InputError(f"dataset {self.root} failed validation:\n{self.format()}")


class _Context:
    def __init__(self, root: Path, full: bool, sample: int):
        self.root, self.full, self.sample = root, full, sample
        self.info: dict | None = None
        self._dataset = None
        self._lengths: dict[int, int] | None = None
        self._episodes = None
        self.decoded_depth: dict[tuple[int, str], np.ndarray] = {}  # sampled depth frames, for check_depth

    @property
    def features(self) -> dict:
        return self.info["features"]

    @property
    def episodes(self):
        """``meta/episodes`` as one pyarrow table."""
        if self._episodes is None:
            import pyarrow as pa
            import pyarrow.parquet as pq

            self._episodes = pa.concat_tables([pq.read_table(f) for f in episode_files(self.root)],
                                              promote_options="default")
        return self._episodes

    @property
    def lengths(self) -> dict[int, int]:
        if self._lengths is None:
            t = self.episodes
            self._lengths = dict(zip(t.column("episode_index").to_pylist(), t.column("length").to_pylist()))
        return self._lengths

    def data_column(self, key: str) -> tuple[np.ndarray, np.ndarray]:
        """``(episode_index, values)`` of a data column over every data file."""
        import pyarrow.parquet as pq

        eps, vals = [], []
        for f in sorted((self.root / "data").rglob("*.parquet")):
            t = pq.read_table(f, columns=["episode_index", key])
            eps.append(t.column("episode_index").to_numpy())
            vals.append(np.asarray(t.column(key).to_pylist(), dtype=np.float64))
        return np.concatenate(eps), np.concatenate(vals)

    @property
    def dataset(self):
        if self._dataset is None:
            self._dataset = lr.LeRobotDataset(f"local/{self.root.name}", root=self.root)
        return self._dataset

    def sample_indices(self) -> list[int]:
        """Global frame indices: first, last and evenly between, per episode."""
        t = self.episodes
        out = []
        for lo, hi in zip(t.column("dataset_from_index").to_pylist(), t.column("dataset_to_index").to_pylist()):
            out += np.unique(np.linspace(lo, hi - 1, min(self.sample, hi - lo)).astype(int)).tolist()
        return out

    def video_keys(self, prefix: str = "") -> list[str]:
        return [k for k, f in self.features.items() if f.get("dtype") == "video" and k.startswith(prefix)]


# ----------------------------------------------------------------------------- checks


def check_metadata(ctx: _Context) -> list[str]:
    ctx.info = read_info(ctx.root)
    problems = []
    if ctx.info.get("codebase_version") != "v3.0":
        return [f"dataset format {ctx.info.get('codebase_version')!r}; expected LeRobot v3.0"]
    n = int(ctx.info.get("total_episodes", -1))
    idx = sorted(ctx.lengths)
    if idx != list(range(n)):
        problems.append(f"meta/episodes lists episodes {idx[:10]}{'...' if len(idx) > 10 else ''}, info.json "
                        f"says {n}")
    total = sum(ctx.lengths.values())
    if total != ctx.info.get("total_frames"):
        problems.append(f"episode lengths sum to {total} frames, info.json total_frames is "
                        f"{ctx.info.get('total_frames')}")
    if any(v <= 0 for v in ctx.lengths.values()):
        problems.append(f"episode(s) with no frames: {[e for e, v in ctx.lengths.items() if v <= 0]}")
    return problems


def check_frame_counts(ctx: _Context) -> list[str]:
    problems = []
    eps, _ = ctx.data_column("frame_index")
    rows = np.bincount(eps, minlength=len(ctx.lengths))
    for ep, n in ctx.lengths.items():
        if rows[ep] != n:
            problems.append(f"episode {ep}: {rows[ep]} rows in data/, length {n}")
    fps = float(ctx.info["fps"])
    t = ctx.episodes
    for key in ctx.video_keys():
        cols = [video_column(key, c) for c in ("from_timestamp", "to_timestamp")]
        if any(c not in t.column_names for c in cols):
            problems.append(f"{key}: meta/episodes has no {cols[0]} / {cols[1]} columns")
            continue
        span = np.asarray(t.column(cols[1]).to_pylist()) - np.asarray(t.column(cols[0]).to_pylist())
        for ep, s in zip(t.column("episode_index").to_pylist(), span):
            if round(s * fps) != ctx.lengths[ep]:
                problems.append(f"{key}: episode {ep} spans {round(s * fps)} frames in its video, length "
                                f"{ctx.lengths[ep]}")
    if ctx.full:
        problems += _count_video_frames(ctx)
    return problems


def _video_files(ctx: _Context, key: str) -> dict[Path, int]:
    """Each video file of ``key`` -> the frames its episodes claim."""
    t = ctx.episodes
    path = ctx.info.get("video_path")
    out: dict[Path, int] = {}
    for ep, c, f in zip(t.column("episode_index").to_pylist(), t.column(video_column(key, "chunk_index")).to_pylist(),
                        t.column(video_column(key, "file_index")).to_pylist()):
        p = ctx.root / path.format(video_key=key, chunk_index=c, file_index=f)
        out[p] = out.get(p, 0) + ctx.lengths[ep]
    return out


def _count_video_frames(ctx: _Context) -> list[str]:
    problems = []
    for key in ctx.video_keys():
        for path, want in _video_files(ctx, key).items():
            if not path.is_file():
                problems.append(f"{key}: {path.relative_to(ctx.root)} is missing")
                continue
            got, error = count_decodable_frames(path)
            if error:
                problems.append(f"{key}: {path.relative_to(ctx.root)} does not decode after frame {got} ({error})")
                continue
            if got != want:
                problems.append(f"{key}: {path.relative_to(ctx.root)} holds {got} frames, its episodes {want}")
    return problems


def check_imac_block(ctx: _Context) -> list[str]:
    streams = any(is_added_stream(k) for k in ctx.features)
    if streams and "imac" not in ctx.info:
        return [f"{ctx.root} has imac's streams but no 'imac' block ({IMAC_INFO}): a tool that writes a new dataset "
                "left it out (LeRobot's merge_datasets, add_features, remove_feature: docs/lerobot.md); put it back "
                f"from the dataset it was made from: imac validate {ctx.root} --restore-imac-from ORIGINAL"]
    try:
        imac_block(ctx.info, str(imac_block_path(ctx.root)), require=RIG_KEYS + (STREAM_KEYS if streams else ()))
    except InputError as e:
        return [str(e)]
    return []


def check_rig(ctx: _Context) -> list[str]:
    try:
        rig = Rig.from_info(ctx.info, ctx.root)
    except InputError as e:
        return [str(e)]
    cams = set(rig.names)
    have = {k.split(".", 2)[2] for k in ctx.video_keys(IMAGE_PREFIX)}
    return [] if not have or cams == have else [f"calibrated cameras {sorted(cams)} differ from the dataset's "
                                                   f"cameras {sorted(have)}"]


def check_joint_units(ctx: _Context) -> list[str]:
    """The recorded joint states against the LeRobot units the dataset says its joint map took (``imac.joint_units``,
    absent: nothing to check): values those units cannot record mean the joint map reads them wrongly."""
    units = unchecked_imac_block(ctx.info).get("joint_units")
    if not units:
        return []
    if STATE not in ctx.features:
        return [f"imac.joint_units: the dataset has no {STATE} to check"]
    _, states = ctx.data_column(STATE)
    if not len(states):
        return []
    return [f"{STATE} {p} (imac.joint_units: body {units.get('body')}, gripper {units.get('gripper')}; the joint map "
            "reads the recording in other units than it was made in)"
            for p in value_problems(units, states.min(axis=0), states.max(axis=0))]


def check_calibration(ctx: _Context) -> list[str]:
    problems = []
    for name, c in unchecked_imac_block(ctx.info).get("cameras", {}).items():
        try:  # the calibration checks of the build's input (fx, fy, principal point, rigid pose)
            camera_from_dict(name, c, f"imac.cameras.{name}")
        except InputError as e:
            problems.append(str(e))
            continue
        why = rigid_problem(c.get("T_world_cam", c.get("T_link_cam")), RIGID_TOL)  # stricter: written by us
        if why:
            problems.append(f"camera {name!r}: pose {why}")
    for key in [k for k in ctx.features if k.startswith(POSE_PREFIX)]:
        _, poses = ctx.data_column(key)
        why = rigid_problem(poses if ctx.full else poses[:: max(1, len(poses) // 64)], RIGID_TOL)
        if why:
            problems.append(f"{key}: {why}")
    return problems


def check_caps(ctx: _Context) -> list[str]:
    key = CAP_KEY
    if key not in ctx.features:
        return []
    _, caps = ctx.data_column(key)
    bad = ~(np.isfinite(caps) & (caps > 0))
    return [] if not bad.any() else [f"{key}: {int(bad.any(axis=-1).sum())} frame(s) with caps that are not "
                                     f"finite and > 0 (first {caps[bad.any(axis=-1)][0].tolist()})"]


def check_decode(ctx: _Context) -> list[str]:
    problems = []
    keys = ctx.video_keys()
    for i in ctx.sample_indices():
        try:
            item = ctx.dataset[int(i)]
        except Exception as e:  # noqa: BLE001 - the loader's error is the finding
            problems.append(f"frame {i}: LeRobotDataset cannot load it ({type(e).__name__}: {e})")
            continue
        for key in keys:
            h, w, c = ctx.features[key]["shape"]
            # a depth map: (1, H, W) millimetres from LeRobot 0.6, grey (3, H, W) from 0.4.4, which has no depth maps
            shapes = [(c, h, w), (3, h, w)] if key.startswith(DEPTH_MAP_PREFIX) else [(3, h, w)]
            if key not in item or tuple(item[key].shape) not in shapes:
                problems.append(f"frame {i}: {key} did not decode to {' or '.join(map(str, shapes))}")
            elif key.startswith(DEPTH_PREFIX):
                ctx.decoded_depth[(int(i), key)] = np.asarray(item[key])
    return problems


def _lossless(encoding: dict) -> bool:
    return encoding.get("qp") == 0 and encoding.get("pix_fmt") in ("rgb24", "gbrp")


def check_depth_maps(ctx: _Context) -> list[str]:
    """LeRobot depth maps: a quantiser LeRobot reads as written, and gray12le files (all of them
    with ``full``, else each feature's first)."""
    problems = []
    for key in ctx.video_keys(DEPTH_MAP_PREFIX):
        try:
            params_of_feature(ctx.features[key], f"info.json feature {key!r}")
        except InputError as e:
            problems.append(str(e))
        files = list(_video_files(ctx, key))
        for path in files if ctx.full else files[:1]:
            got = stream_pix_fmt(path) if path.is_file() else "missing"
            if got != DEPTH_MAP_PIX_FMT:
                problems.append(f"{key}: {path.relative_to(ctx.root)} is {got}, not {DEPTH_MAP_PIX_FMT}")
    return problems


def check_depth(ctx: _Context) -> list[str]:
    keys = ctx.video_keys(DEPTH_PREFIX)
    if not keys:
        return check_depth_maps(ctx)
    try:
        codec = depth_codec_of(ctx.info)
    except InputError as e:
        return [str(e)]
    lossless = _lossless(imac_block(ctx.info, "info.json", require=("depth",))["depth"].get("encoding", {}))
    problems = []

    def judge(where: str, rgb) -> None:
        dist = np.asarray(walk_distance(rgb, channel_axis=-3 if rgb.shape[-3] == 3 else -1), dtype=np.float64)
        off = dist.max() if lossless else np.quantile(dist, 0.99)
        if off > (2.0 / 255 if lossless else 0.15):
            problems.append(f"{where}: colours are off the depth codec's walk by up to {off * 255:.1f}/255 "
                            f"({'lossless' if lossless else 'lossy'} stream): not depth frames, or damaged")
            return
        d = np.asarray(codec.decode(rgb, channel_axis=-3 if rgb.shape[-3] == 3 else -1), dtype=np.float64)
        if not np.isfinite(d).all() or d.min() < 0 or d.max() > codec.max_depth * (1 + 1e-6):
            problems.append(f"{where}: decodes outside the codec's range [0, {codec.max_depth:.3f}] m")

    if ctx.full:
        for key in keys:
            for path in _video_files(ctx, key):
                if path.is_file():
                    judge(f"{key} {path.relative_to(ctx.root)}", read_video_frames(path))
    else:
        if not ctx.decoded_depth:  # run on its own (--check depth): decode the samples here
            check_decode(ctx)
        for (i, key), frame in ctx.decoded_depth.items():  # the frames check_decode decoded
            judge(f"frame {i} {key}", frame)
    return problems + check_depth_maps(ctx)


CHECKS: list[tuple[str, Callable[[_Context], list[str]]]] = [
    ("metadata", check_metadata),
    ("frame_counts", check_frame_counts),
    ("imac_block", check_imac_block),
    ("rig", check_rig),
    ("joint_units", check_joint_units),
    ("calibration", check_calibration),
    ("caps", check_caps),
    ("decode", check_decode),
    ("depth", check_depth),
]
_NEEDS = {"frame_counts": "metadata", "imac_block": "metadata", "rig": "imac_block", "joint_units": "imac_block",
          "calibration": "imac_block",
          "caps": "metadata", "decode": "frame_counts", "depth": "decode"}


def validate_dataset(root: str | Path, *, full: bool = False, sample: int = 4,
                     checks: list[str] | None = None) -> Report:
    """Run the checks (all, or the named ones) on the dataset at ``root``; returns the
    :class:`Report` (``report.ok``; ``report.raise_if_invalid()``)."""
    root = Path(root)
    report = Report(root=root, full=full)
    if not info_path(root).is_file():
        report.results["metadata"] = [f"{root} is not a LeRobot dataset (no meta/info.json)"]
        return report
    ctx = _Context(root, full, sample)
    names = [n for n, _ in CHECKS]
    unknown = sorted(set(checks or ()) - set(names))
    if unknown:
        raise InputError(f"unknown check(s) {unknown}; known: {names}")
    for name, fn in CHECKS:
        if checks is not None and name not in checks and name != "metadata":
            continue
        need = _NEEDS.get(name)
        while need is not None and need not in report.results and need != "metadata":
            need = _NEEDS.get(need)
        if need is not None and report.results.get(need):
            report.skipped[name] = f"needs {need}, which failed"
            continue
        try:
            report.results[name] = fn(ctx)
        except InputError as e:
            report.results[name] = [str(e)]
        except (OSError, ValueError, KeyError, json.JSONDecodeError) as e:
            report.results[name] = [f"{type(e).__name__}: {e}"]
    return report
