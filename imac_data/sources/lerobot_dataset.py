"""An existing LeRobot dataset as the source of a build (``source.type: lerobot``).

The source is a local dataset root (``source.path``) or a hub dataset (``source.repo_id``,
downloaded through LeRobot into the build's staging directory). It is only read:

* a v3.0 dataset is copied file by file into the staging directory, so its camera videos
  land in the output byte-identical;
* a v2.1 dataset is first copied into staging and converted there by LeRobot's own
  converter (``convert_dataset``, with ``push_to_hub=False``); its videos are then the
  converter's (it concatenates the episode files without re-encoding).

The recipe maps the source's camera keys to calibrated camera names (``source.cameras``,
default ``observation.images.<cam> -> <cam>``); mapped cameras are renamed to
``observation.images.<cam>`` (the same files, moved), unmapped camera features are dropped.
``robot.joint_map`` has one entry per index of ``source.state_key`` and
``source.action_key``, each with its affine map to the URDF's units; the actions must be
joint targets, an end-effector action space is refused.

Everything is checked here, before any work, with errors naming the dataset and the key.
"""

from __future__ import annotations

import csv
import json
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from imac_data import lerobot_compat as lr
from imac_data.console import cpu_cores
from imac_data.core.depth_map import depth_marker
from imac_data.errors import InputError
from imac_data.layout import (
    EPISODE_COLUMNS,
    IMAGE_PREFIX,
    POSE_PREFIX,
    STATS_COLUMNS,
    TASKS,
    episodes_dir,
    info_path,
    is_added_stream,
    video_column,
)
from imac_data.sources.hdf5 import parse_success
from imac_data.sources.lerobot_episodes import count_decodable_frames

__all__ = ["SourceDataset", "locate_source", "camera_map", "check_joint_layout",
           "episode_metadata", "cartesian_names"]

# end-effector (Cartesian) action names: x, y and z entries (last name token), or an explicit
# end-effector word; joint names such as "forearm_roll" are not enough on their own
EE_WORD = re.compile(r"(^|[._\-\s])(eef|ee|end_effector|cartesian|tcp)([._\-\s]|$)", re.IGNORECASE)


def cartesian_names(names: list[str]) -> list[str]:
    """The entries of ``names`` that mark an end-effector action vector (empty: joint-like)."""
    last = [re.split(r"[._\-\s]+", n.lower())[-1] for n in names]
    explicit = [n for n in names if EE_WORD.search(n)]
    if explicit:
        return explicit
    if {"x", "y", "z"} <= set(last):
        return [n for n, t in zip(names, last) if t in ("x", "y", "z", "roll", "pitch", "yaw", "qx", "qy", "qz",
                                                        "qw", "rx", "ry", "rz")]
    return []


@dataclass
class SourceDataset:
    """The metadata of a LeRobot v3.0 dataset at ``root`` (``info.json`` and the episodes
    table), read with pyarrow; frames are read by :mod:`imac_data.sources.lerobot_episodes`."""

    root: Path
    info: dict
    episodes: list[dict]  # one row per episode, in index order

    @classmethod
    def open(cls, root: Path) -> SourceDataset:
        import pyarrow.parquet as pq

        root = Path(root)
        info_file = info_path(root)
        if not info_file.is_file():
            raise InputError(f"{root} is not a LeRobot dataset ({info_file} is missing)")
        info = _read_info(info_file)
        version = info.get("codebase_version")
        if version != "v3.0":
            raise InputError(f"{root}: LeRobot dataset version {version!r}; expected v3.0 (v2.1 is converted first)")
        _check_info(info, info_file)
        rows = []
        for f in sorted(episodes_dir(root).rglob("*.parquet")):
            cols = [c for c in pq.read_schema(f).names if not c.startswith(STATS_COLUMNS)]
            rows += pq.read_table(f, columns=cols).to_pylist()
        rows.sort(key=lambda r: r["episode_index"])
        if [r["episode_index"] for r in rows] != list(range(len(rows))) or len(rows) != info["total_episodes"]:
            raise InputError(f"{root}: meta/episodes does not list episodes 0..{info['total_episodes'] - 1} once each")
        return cls(root, info, rows)

    @property
    def features(self) -> dict:
        return self.info["features"]

    def data_file(self, row: dict) -> Path:
        """The parquet file that holds episode ``row``'s frames."""
        return self.root / self.info["data_path"].format(chunk_index=row["data/chunk_index"],
                                                         file_index=row["data/file_index"])

    def video_file(self, key: str, row: dict) -> Path:
        """The video file that holds episode ``row``'s frames of camera feature ``key``."""
        return self.root / self.info["video_path"].format(video_key=key, chunk_index=row[video_column(key, "chunk_index")],
                                                          file_index=row[video_column(key, "file_index")])

    def check_files(self, video_keys: list[str]) -> None:
        """Every file the build reads is there: the tasks table, each episode's data file and
        its video files of ``video_keys`` (LeRobot would try to download a missing one)."""
        tasks = self.root / TASKS
        if not tasks.is_file():
            raise InputError(f"dataset {self.root}: {tasks} is missing")
        for row in self.episodes:
            try:
                files = [self.data_file(row), *(self.video_file(key, row) for key in video_keys)]
            except KeyError as e:
                raise InputError(f"dataset {self.root}: meta/episodes has no column {e} for episode "
                                 f"{row['episode_index']}") from None
            missing = [f for f in files if not f.is_file()]
            if missing:
                raise InputError(f"dataset {self.root}: episode {row['episode_index']} needs {missing[0]}, which is "
                                 "missing")

    def check_videos(self, video_keys: list[str], *, progress: bool = False) -> None:
        """Every frame the episodes use of ``video_keys`` decodes, checked before any work (each
        file decoded once, threads over files: 2-3 % of a build). A damaged or short file is named
        with the episode that needs it; LeRobot would fail only when that frame is loaded."""
        from concurrent.futures import ThreadPoolExecutor

        spans: dict[Path, list[tuple[int, int, int, str]]] = {}  # file -> (first, end, episode, key) per episode
        for row in self.episodes:
            for key in video_keys:
                try:
                    first, end = (round(row[video_column(key, f"{c}_timestamp")] * self.fps) for c in ("from", "to"))
                except KeyError as e:
                    raise InputError(f"dataset {self.root}: meta/episodes has no column {e} for episode "
                                     f"{row['episode_index']}") from None
                spans.setdefault(self.video_file(key, row), []).append((first, end, row["episode_index"], key))
        files = sorted(spans)
        with ThreadPoolExecutor(min(cpu_cores(), len(files) or 1)) as pool:
            counted = list(tqdm(pool.map(count_decodable_frames, files), total=len(files), unit="file",
                                desc="check source videos", disable=not progress))
        for path, (got, error) in zip(files, counted):
            short = [s for s in sorted(spans[path]) if s[1] > got]
            if short:
                first, end, episode, key = short[0]
                why = f"does not decode after frame {got} ({error})" if error else f"holds {got} frames"
                raise InputError(f"dataset {self.root}: {path} ({key}) {why}, but episode {episode} uses its frames "
                                 f"{first}..{end - 1}: the video is damaged or cut short")

    @property
    def fps(self) -> int:
        return int(self.info["fps"])

    @property
    def video_keys(self) -> list[str]:
        return [k for k, f in self.features.items() if f["dtype"] == "video"]

    def is_depth_map(self, key: str) -> bool:
        """Whether feature ``key`` is a LeRobot depth map (any marker; conflicting markers count)."""
        try:
            return bool(depth_marker(self.features[key]))
        except ValueError:
            return True

    def image_hw(self, key: str) -> tuple[int, int]:
        f = self.features[key]
        names = list(f.get("names") or [])
        shape = list(f["shape"])
        if "height" in names and "width" in names:
            return int(shape[names.index("height")]), int(shape[names.index("width")])
        return (int(shape[1]), int(shape[2])) if shape[0] == 3 else (int(shape[0]), int(shape[1]))

    def width(self, key: str, what: str) -> int:
        if key not in self.features:
            raise InputError(f"{self.root}: no feature {key!r} ({what}); its features are {sorted(self.features)}")
        shape = self.features[key]["shape"]
        if len(shape) != 1:
            raise InputError(f"{self.root}: feature {key!r} ({what}) has shape {shape}; expected a vector")
        return int(shape[0])


# ------------------------------------------------------------------------------ locate


def _check_info(info: dict, info_file: Path) -> None:
    """The fields of a v3.0 ``info.json`` that reading a source needs, with their types."""
    for key, kind, what in (("fps", (int, float), "a number"), ("total_episodes", int, "an integer"),
                            ("features", dict, "an object"), ("data_path", str, "a path template"),
                            ("video_path", (str, type(None)), "a path template")):
        if key not in info or isinstance(info[key], bool) or not isinstance(info[key], kind):
            got = f"got {info[key]!r}" if key in info else "it is missing"
            raise InputError(f"{info_file}: '{key}' must be {what}; {got}")
    if not (info["fps"] > 0 and float(info["fps"]).is_integer()):
        raise InputError(f"{info_file}: 'fps' must be a positive whole number, got {info['fps']!r}")


def _read_info(info_file: Path) -> dict:
    try:
        info = json.loads(info_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{info_file}: not valid JSON ({e})") from None
    if not isinstance(info, dict):
        raise InputError(f"{info_file}: expected a JSON object, got {type(info).__name__}")
    return info


def _version(root: Path) -> str | None:
    path = info_path(root)
    return _read_info(path).get("codebase_version") if path.is_file() else None


def _download(repo_id: str, into: Path) -> Path:
    """The hub dataset ``repo_id`` downloaded by LeRobot (v3.0) or, for a v2.1 dataset, by
    the hub client at its v2.1 revision, into ``into`` (a staging directory)."""
    root = into / repo_id
    how = ("download it where there is network access (e.g. `hf download --repo-type dataset "
           f"{repo_id} --local-dir DIR`) and set source.path: DIR")
    try:
        lr.LeRobotDataset(repo_id, root=root)
        return root
    except lr.BackwardCompatibilityError:
        from huggingface_hub import snapshot_download

        try:
            snapshot_download(repo_id, repo_type="dataset", revision="v2.1", local_dir=root)
        except Exception as e:  # noqa: BLE001 - hub/network errors come in many types
            raise InputError(f"source.repo_id {repo_id!r}: cannot download its v2.1 files "
                             f"({type(e).__name__}: {str(e).splitlines()[0][:200]}); {how}") from e
        return root
    except Exception as e:  # noqa: BLE001
        raise InputError(f"source.repo_id {repo_id!r}: LeRobot cannot download it here "
                         f"({type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}); {how}") from e


def _convert_v21(root: Path, staging: Path, repo_id: str) -> tuple[Path, str]:
    """A staged v3.0 copy of the v2.1 dataset at ``root``, converted by LeRobot's converter,
    and the converter's module."""
    base = staging / "v21"
    work = base / repo_id
    if work.exists():
        shutil.rmtree(work)
    shutil.copytree(root, work)
    print(f"[build] converting the v2.1 dataset {root} to v3.0 (LeRobot's converter, on a staged copy)")
    try:
        module = lr.convert_v21(work, repo_id)
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - the converter's own errors
        raise InputError(f"{root}: LeRobot's v2.1 -> v3.0 converter failed ({type(e).__name__}: {e})") from e
    return work, module


def locate_source(path: Path | None, repo_id: str | None, staging: Path) -> tuple[Path, dict]:
    """The v3.0 root to read (the user's own root for v3.0; a staged conversion for v2.1;
    a staged download for a hub dataset) and a description of where it came from."""
    if path is None:
        if repo_id is None:
            raise InputError("source: type lerobot needs 'path' or 'repo_id'")
        root = _download(repo_id, staging / "download")
        where = {"repo_id": repo_id}
    else:
        root = Path(path)
        if not info_path(root).is_file():
            raise InputError(f"source.path {root}: not a LeRobot dataset (no meta/info.json)")
        where = {"path": str(root)}
    version = _version(root)
    where["codebase_version"] = version
    if version == "v2.1":
        root, module = _convert_v21(root, staging, repo_id or f"local/{root.name}")
        where["converted"] = f"v2.1 -> v3.0 by {module}"
    elif version != "v3.0":
        raise InputError(f"{root}: LeRobot dataset version {version!r}; this build reads v3.0 and v2.1")
    return root, where


# ------------------------------------------------------------------------------ checks


def camera_map(src: SourceDataset, mapping: dict[str, str], calibrated: list[str], where: str) -> dict[str, str]:
    """``{source video key: camera name}``, checked against the source and the calibration."""
    videos = [k for k in src.video_keys if not src.is_depth_map(k)]  # colour cameras
    if not mapping:
        mapping = {k: k.removeprefix(IMAGE_PREFIX) for k in videos if k.startswith(IMAGE_PREFIX)}
    for key, cam in mapping.items():
        if key not in src.features:
            raise InputError(f"{where}: source.cameras: dataset {src.root} has no feature {key!r}; its camera "
                             f"features are {videos}")
        if src.is_depth_map(key):
            raise InputError(f"{where}: source.cameras: {key!r} of dataset {src.root} is a depth map, not a colour "
                             "camera; name it in depth.feature instead")
        if key not in videos:
            raise InputError(f"{where}: source.cameras: {key!r} of dataset {src.root} is a "
                             f"{src.features[key]['dtype']} feature, not a camera video")
        if cam not in calibrated:
            raise InputError(f"{where}: source.cameras: {key!r} -> {cam!r}, which the calibration does not "
                             f"describe (it has {calibrated})")
    mapped = list(mapping.values())
    if len(set(mapped)) != len(mapped):
        raise InputError(f"{where}: source.cameras: two source keys map to the same camera ({mapped})")
    unmapped = sorted(set(calibrated) - set(mapped))
    if unmapped:
        raise InputError(f"{where}: the calibration has camera(s) {unmapped} that no source camera maps to; "
                         f"map them in source.cameras (the dataset {src.root} has {videos})")
    clash = [k for k in src.features if is_added_stream(k) or k.startswith(POSE_PREFIX)]
    if clash:
        raise InputError(f"{where}: dataset {src.root} already has imac streams ({clash[:3]}...); "
                         "start from the dataset without them")
    return dict(mapping)


def _names(feature: dict) -> list[str]:
    names = feature.get("names")
    if isinstance(names, dict):  # {"motors": [...]} in some datasets
        names = [n for v in names.values() for n in (v if isinstance(v, list) else [v])]
    return [str(n) for n in names] if isinstance(names, list) else []


def check_joint_layout(src: SourceDataset, state_key: str, action_key: str, action_space: str, dof: int,
                       where: str) -> None:
    """``robot.joint_map`` (``dof`` entries) must cover the state and action vectors index by
    index, and the actions must be joint targets."""
    ee = f"{where}: source.action_space: joint-space actions are required (the motion images render the " \
         "robot at the commanded joint configuration)"
    if action_space == "ee":
        raise InputError(f"{ee}; the recipe declares an end-effector action space. Record joint targets, "
                         "or convert the actions with your robot's inverse kinematics first")
    state_w = src.width(state_key, "source.state_key")
    action_w = src.width(action_key, "source.action_key")
    if dof > state_w:
        raise InputError(f"{where}: robot.joint_map has {dof} entries, wider than {state_key!r} of dataset "
                         f"{src.root} ({state_w} entries: {_names(src.features[state_key]) or 'unnamed'})")
    if dof != state_w:
        raise InputError(f"{where}: robot.joint_map has {dof} entries but {state_key!r} of dataset {src.root} has "
                         f"{state_w}: give one entry per index")
    names = _names(src.features[action_key])
    cartesian = cartesian_names(names)
    if cartesian:
        raise InputError(f"{ee}; {action_key!r} of dataset {src.root} looks like an end-effector pose "
                         f"(entries {cartesian[:6]})")
    if action_w != state_w:
        raise InputError(f"{ee}; {action_key!r} of dataset {src.root} has {action_w} entries but {state_key!r} "
                         f"has {state_w}, so the actions are not joint targets of the same joints")


# ------------------------------------------------------------------------------ metadata

META_FIELDS = {name.removeprefix("imac/"): name for name in EPISODE_COLUMNS}  # metadata field -> column


def episode_metadata(path: Path | None, n: int, defaults) -> list[dict]:
    """Per episode ``imac/source``, ``imac/policy_name``, ``imac/checkpoint``, ``imac/success``:
    from ``path`` (CSV with an ``episode_index`` column, or JSON: a list of objects with
    ``episode_index``, or an object keyed by episode index) over the recipe's defaults."""
    values = (defaults.source, defaults.policy_name, defaults.checkpoint, None)
    rows = [dict(zip(EPISODE_COLUMNS, values)) for _ in range(n)]
    if path is None:
        return rows
    path = Path(path)
    try:
        if path.suffix.lower() == ".csv":
            with path.open(newline="") as fh:
                records = list(csv.DictReader(fh))
        else:
            data = json.loads(path.read_text())
            records = ([{**v, "episode_index": k} for k, v in data.items()] if isinstance(data, dict) else data)
    except (OSError, json.JSONDecodeError, csv.Error) as e:
        raise InputError(f"{path}: cannot read the episode metadata ({e})") from None
    if not isinstance(records, list):
        raise InputError(f"{path}: expected a list of episodes or an object keyed by episode index")
    for i, rec in enumerate(records):
        where = f"{path} entry {i}"
        if not isinstance(rec, dict) or "episode_index" not in rec:
            raise InputError(f"{where}: needs an episode_index")
        unknown = sorted(set(rec) - set(META_FIELDS) - {"episode_index"})
        if unknown:
            raise InputError(f"{where}: unknown field(s) {unknown}; known: episode_index, {sorted(META_FIELDS)}")
        try:
            ep = int(rec["episode_index"])
        except (TypeError, ValueError):
            raise InputError(f"{where}: episode_index must be an integer, got {rec['episode_index']!r}") from None
        if not 0 <= ep < n:
            raise InputError(f"{where}: episode_index {ep} is not an episode of the dataset (0..{n - 1})")
        for name, column in META_FIELDS.items():
            if name not in rec or rec[name] in (None, ""):
                continue
            value = rec[name]
            if name == "success":
                value = parse_success(value, f"{where} (episode {ep})")
            elif name == "source" and value not in ("teleop", "policy"):
                raise InputError(f"{where} (episode {ep}): source must be 'teleop' or 'policy', got {value!r}")
            else:
                value = str(value)
            rows[ep][column] = value
    return rows


def episode_states(root: Path, episodes: list[dict], key: str) -> list[np.ndarray]:
    """``key`` (a vector feature) of every episode, ``(T_e, D)`` float64, from the data files."""
    import pyarrow.parquet as pq

    out: dict[int, list] = {}
    for f in sorted((root / "data").rglob("*.parquet")):
        t = pq.read_table(f, columns=["episode_index", "frame_index", key])
        eps = t.column("episode_index").to_numpy()
        frames = t.column("frame_index").to_numpy()
        values = np.asarray(t.column(key).to_pylist(), dtype=np.float64)
        for ep in np.unique(eps):
            sel = eps == ep
            out.setdefault(int(ep), []).append((frames[sel], values[sel]))
    result = []
    for row in episodes:
        parts = out.get(row["episode_index"], [])
        frames = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, int)
        values = np.concatenate([p[1] for p in parts]) if parts else np.zeros((0, 0))
        if len(frames) != row["length"] or not np.array_equal(np.sort(frames), np.arange(row["length"])):
            raise InputError(f"{root}: episode {row['episode_index']} has {len(frames)} rows of {key!r} in data/, "
                             f"its length is {row['length']}")
        v = values[np.argsort(frames)]
        if not np.isfinite(v).all():
            raise InputError(f"{root}: {key!r} of episode {row['episode_index']} has NaN/inf values")
        result.append(v)
    return result
