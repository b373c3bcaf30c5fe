"""Recipes: YAML files that say where the raw data is, which robot and cameras, and how to build.

A recipe is parsed into typed, frozen dataclasses and validated here, at the boundary: an
unknown key, a wrong type or a bad value raises :class:`InputError` naming the file and the
dotted field. Paths are relative to the recipe file unless absolute; ``~`` and environment
variables are expanded. The schema is in ``docs/building.md`` ("Recipes")."""

from __future__ import annotations

import dataclasses
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from imac_data.config import parse_dataclass
from imac_data.core.contact.workspace import WorkspaceSettings
from imac_data.core.depth import DepthCodec
from imac_data.core.depth_map import DepthMapParams
from imac_data.core.motion import Controller
from imac_data.core.robot.aloha import SIM_TASKS
from imac_data.core.robot.lerobot_units import CALIBRATION_HINT, LEROBOT_ARMS, UNITS, convention
from imac_data.core.robot.platforms import PLATFORMS, lerobot_platforms, platform, simulated_platforms
from imac_data.errors import InputError
from imac_data.layout import ACTION, STATE
from imac_data.metadata import imac_block

RECIPES_DIR = Path(__file__).resolve().parent.parent / "recipes"
DEPTH_FORMATS = ("millimetres", "metres", "codec", "lerobot")


@dataclass(frozen=True)
class JointSpec:
    """A joint-vector entry with an affine map: ``q_urdf = offset + scale * value``."""

    joint: str
    scale: float = 1.0
    offset: float = 0.0


@dataclass(frozen=True)
class GripperEntry:
    """The older spelling of :class:`JointSpec` (only grippers could carry a map)."""

    gripper: str  # finger joint driven by this entry
    scale: float
    offset: float = 0.0


@dataclass(frozen=True)
class GripperActionSpec:
    index: int
    scale: float = 1.0
    offset: float = 0.0
    low: float | None = None
    high: float | None = None


@dataclass(frozen=True)
class ControllerSection:
    """``robot.controller``: :class:`imac_data.core.motion.Controller` as a recipe writes it."""

    mode: str = "absolute"
    grippers: tuple[GripperActionSpec, ...] = ()
    absolute_indices: tuple[int, ...] = ()
    delta_grippers: bool = False
    clip_low: tuple[float | None, ...] | None = None
    clip_high: tuple[float | None, ...] | None = None


@dataclass(frozen=True)
class RobotSection:
    platform: str | None = None
    urdf: str | None = None
    joint_map: tuple[str | JointSpec | GripperEntry, ...] | None = None
    gripper_links: tuple[str, ...] = ()
    package_dirs: dict[str, str] = field(default_factory=dict)
    controller: ControllerSection | None = None
    # a platform recorded in LeRobot's units (lerobot_platforms()): the body's units (default: the platform's),
    # and the arm's LeRobot calibration file, which range_m100_100 needs (docs/new-robot.md)
    units: str | None = None
    calibration: str | None = None

    def joint_map_entries(self) -> list:
        """The joint map in :meth:`imac_data.core.robot.model.RobotConfig.parse_joint_map`'s input form."""
        out = []
        for e in self.joint_map or ():
            if isinstance(e, JointSpec):
                out.append({"joint": e.joint, "scale": e.scale, "offset": e.offset})
            elif isinstance(e, GripperEntry):
                out.append({"joint": e.gripper, "scale": e.scale, "offset": e.offset})
            else:
                out.append(e)
        return out


@dataclass(frozen=True)
class CamerasSection:
    calibration: str | None = None


@dataclass(frozen=True)
class SimSection:
    task: str = "transfer_cube"
    noise: float = 0.3
    seed: int = 0
    height: int = 240
    width: int = 320
    frame_stride: int = 2
    segmentation: bool = True  # ground-truth robot masks, for the calibration overlay's IoU


@dataclass(frozen=True)
class EpisodeDefaults:
    source: str = "teleop"
    policy_name: str | None = None
    checkpoint: str | None = None


@dataclass(frozen=True)
class SourceSection:
    type: str
    path: str | None = None
    episodes: int | None = None
    repo_id: str | None = None  # lerobot: a hub dataset, when no path is given
    cameras: dict[str, str] = field(default_factory=dict)  # lerobot: source video key -> camera name
    state_key: str = STATE  # lerobot: joint vectors, one robot.joint_map entry per index
    action_key: str = ACTION
    action_space: str = "joint"  # lerobot: "joint" | "ee" (end-effector actions are refused)
    metadata: str | None = None  # lerobot: CSV or JSON of episode metadata keyed by episode_index
    sim: SimSection = field(default_factory=SimSection)
    episode_defaults: EpisodeDefaults = field(default_factory=EpisodeDefaults)


@dataclass(frozen=True)
class SourceType:
    """A recipe's ``source.type`` read from files: what ``source.path`` is, the build that reads
    it, and what only it takes."""

    build: str  # "episodes": HDF5 episode files (build.from_episodes); "lerobot": a LeRobot dataset (build.from_lerobot)
    label: str  # its name in messages ("a LeRobot source")
    path: str  # what source.path is
    path_hint: str  # what is in it, for a path that is not there
    input_name: str  # the source among a build's inputs
    hub: bool = False  # source.repo_id (a hub dataset) may stand in for source.path
    own_keys: tuple[str, ...] = ()  # source keys only this type reads (set for another type: refused)
    depth_feature: bool = False  # its recorded depth is a named feature (depth.feature), not HDF5 depth


# what the simulator records (a simulated platform's source.type, simulated_platforms()) and ALOHA/AgileX write
HDF5_EPISODES = SourceType(build="episodes", label="HDF5", path="the directory of HDF5 episodes",
                           path_hint="episode_0.hdf5, episode_1.hdf5, ... as the ALOHA/AgileX recorder writes them",
                           input_name="source episodes")

# source.type -> how it is read. A new source type is one entry (and, if no build reads it yet, its build in
# imac_data.build.flow.BUILDS); the simulated platforms are source types too and read as HDF5_EPISODES.
SOURCE_TYPES: dict[str, SourceType] = {
    "aloha_hdf5": HDF5_EPISODES,
    "lerobot": SourceType(build="lerobot", label="LeRobot", path="the LeRobot dataset's root directory",
                          path_hint="the directory holding meta/info.json", input_name="source dataset", hub=True,
                          own_keys=("repo_id", "metadata", "cameras"), depth_feature=True),
}


def source_type(name: str, where: str = "source.type") -> SourceType:
    """How the ``source.type`` ``name`` is read (:class:`InputError` naming ``where`` and the known types)."""
    simulated = simulated_platforms()
    if name in simulated:
        return HDF5_EPISODES
    if name not in SOURCE_TYPES:
        raise InputError(f"{where}: unknown source type {name!r}; known: {list(simulated) + list(SOURCE_TYPES)}")
    return SOURCE_TYPES[name]


@dataclass(frozen=True)
class DepthMapOutput:
    """``augment.lerobot_depth_map``: also write each camera's depth as a LeRobot 0.6 depth map,
    ``observation.depth_map.{cam}`` (12-bit codes of the quantiser below, lossless HEVC)."""

    enabled: bool = False
    depth_min: float = 0.01  # metres at code 0 (LeRobot's defaults)
    depth_max: float = 10.0  # metres at code 4095
    shift: float = 3.5  # metres, log quantisation's offset
    use_log: bool = True  # log (finer near the camera) or linear

    def __post_init__(self) -> None:
        problem = self.params().problem()
        if problem:
            raise InputError(f"augment.lerobot_depth_map: {problem.replace('video.', '')}")

    def params(self) -> DepthMapParams:
        return DepthMapParams(self.depth_min, self.depth_max, self.shift, self.use_log)


CPU_RENDERERS = ("open3d", "opengl")  # render.BACKENDS that a CPU build draws with


@dataclass(frozen=True)
class AugmentSettings:
    """How the control streams are made (the recipe's ``augment`` section; recorded in
    ``info["imac"]["augment"]``)."""

    height: int = 240  # resolution of the added streams
    width: int = 320
    motion_source: str = "action"  # "action" (commanded, through phi) | "state" (measured)
    depth_codec: str = "manipulation"  # DepthCodec preset
    contact_chunk: int = 8  # H: frames per chunk; reference = the chunk's start frame
    contact_cap: float | None = None  # metres; None = the chunk's percentile per stream
    contact_percentile: float = 99.0
    robot_mask_dilate_px: int = 2  # robot removal from the reference depth
    contact_workspace: WorkspaceSettings = field(default_factory=WorkspaceSettings)  # box + depth range
    # a chunk whose reference frame has no scene (no valid depth left, e.g. a depth sensor's
    # first frames): "error" stops the build, "no_contact" builds it without contact
    # (r2s saturated on the robot, s2g black, caps contact.EMPTY_CAP)
    empty_reference_scene: str = "error"
    lerobot_depth_map: DepthMapOutput = field(default_factory=DepthMapOutput)  # off: see docs/lerobot.md
    # the motion images' renderer on the CPU: open3d (ray casting) or opengl (EGL rasterisation, 0.74x the
    # render stage's CPU at 480x640; the same images within the tolerances of docs/building.md); --device cuda: torch
    renderer: str = "open3d"

    def __post_init__(self) -> None:
        if self.height <= 0 or self.width <= 0:
            raise InputError(f"augment: resolution must be positive, got {self.height}x{self.width}")
        if self.motion_source not in ("action", "state"):
            raise InputError(f"augment.motion_source: must be 'action' or 'state', got {self.motion_source!r}")
        if self.contact_chunk < 1:
            raise InputError(f"augment.contact_chunk: must be >= 1, got {self.contact_chunk}")
        if self.contact_cap is not None and not 0 < self.contact_cap < math.inf:
            raise InputError(f"augment.contact_cap: must be a finite number of metres > 0, got {self.contact_cap}")
        if not 0 < self.contact_percentile <= 100:
            raise InputError(f"augment.contact_percentile: must be in (0, 100], got {self.contact_percentile}")
        if self.empty_reference_scene not in ("error", "no_contact"):
            raise InputError(f"augment.empty_reference_scene: must be 'error' or 'no_contact', got "
                             f"{self.empty_reference_scene!r}")
        if self.renderer not in CPU_RENDERERS:
            raise InputError(f"augment.renderer: must be one of {list(CPU_RENDERERS)}, got {self.renderer!r}")
        if self.robot_mask_dilate_px < 0:
            raise InputError(f"augment.robot_mask_dilate_px: must be >= 0, got {self.robot_mask_dilate_px}")
        try:
            DepthCodec.preset(self.depth_codec)
        except InputError as e:
            raise InputError(f"augment.depth_codec: {e}") from None

    @property
    def resolution(self) -> tuple[int, int]:
        return self.height, self.width

    def contact_options(self) -> dict:
        """What these settings fix of :meth:`~imac_data.core.rig.Rig.contact_images`: the build
        passes them, and so does the world model's rollout, from the settings a dataset records."""
        return {"cap": self.contact_cap, "percentile": float(self.contact_percentile),
                "dilate_px": self.robot_mask_dilate_px, "allow_empty_scene": self.empty_reference_scene == "no_contact"}

    @classmethod
    def from_info(cls, meta) -> AugmentSettings:
        """The settings a dataset was built with (``imac.augment`` of its ``imac`` block;
        ``meta``: ``ds.meta``, the root or the dict, :mod:`imac_data.metadata`). A field the
        dataset does not record takes this class's default, except the stream resolution,
        which must be recorded."""
        block = imac_block(meta, require=("augment",))
        where = "meta/info.json imac.augment"
        recorded = block["augment"]
        if not isinstance(recorded, dict) or "height" not in recorded or "width" not in recorded:
            raise InputError(f"{where}: no stream resolution (height, width) recorded")
        try:
            return parse_dataclass(cls, recorded, "imac.augment")
        except InputError as e:
            raise InputError(f"meta/info.json {e}") from None


@dataclass(frozen=True)
class DepthSection:
    """Where the depth streams come from (``depth:``; :mod:`imac_data.sources.depth`)."""

    source: str = "recorded"  # a name in imac_data.sources.depth.DEPTH_SOURCES (checked before a build starts)
    model: str | None = None  # da3: hub id or local weights directory (default DA3-BASE)
    monocular_model: str | None = None  # da3, fewer than 3 posed views: DA3's monocular metric model
    feature: str | None = None  # recorded from a LeRobot source: feature key, "{cam}" = camera name
    # recorded LeRobot feature: millimetres | metres | codec | lerobot (a LeRobot depth map);
    # None: lerobot for a feature flagged as a depth map, else millimetres
    format: str | None = None
    codec: str = "manipulation"  # format codec: the DepthCodec preset the feature was encoded with
    device: str | None = None  # da3: cuda, cpu, ... (default: CUDA when available)
    batch_size: int = 4  # da3: timesteps per forward pass
    process_res: int = 504  # da3: long side the network sees (a multiple of 14)


@dataclass(frozen=True)
class Recipe:
    name: str
    task: str
    robot: RobotSection
    source: SourceSection
    fps: float | None = None
    cameras: CamerasSection = field(default_factory=CamerasSection)
    augment: AugmentSettings = field(default_factory=AugmentSettings)
    depth: DepthSection = field(default_factory=DepthSection)
    file: str = ""  # where the recipe was read from (for messages and relative paths)

    def resolve_path(self, value: str | None) -> Path | None:
        """A recipe path, relative to the recipe file."""
        if value is None:
            return None
        p = Path(os.path.expandvars(os.path.expanduser(value)))
        return p if p.is_absolute() or not self.file else Path(self.file).parent / p


# --------------------------------------------------------------------------- parsing


def _validate(recipe: Recipe) -> None:
    f = recipe.file or "<recipe>"
    r, s = recipe.robot, recipe.source
    if r.platform is None and r.urdf is None:
        raise InputError(f"{f}: robot: give either 'platform' ({sorted(PLATFORMS)}) or 'urdf' + 'joint_map'")
    if r.platform is not None:
        platform(r.platform, f"{f}: robot.platform")
    if r.urdf is not None and not r.joint_map:
        raise InputError(f"{f}: robot.joint_map: required with robot.urdf (one entry per joint-vector index)")
    if r.platform is not None:
        extra = [k for k in ("urdf", "joint_map", "controller") if getattr(r, k) is not None]
        extra += [k for k in ("gripper_links", "package_dirs") if getattr(r, k)]
        if extra:
            raise InputError(f"{f}: robot: platform {r.platform!r} brings its own robot and controller; "
                             f"remove {extra} (or drop 'platform' and describe your robot)")
    _validate_units(r, f)
    if r.controller is not None:
        try:
            Controller.from_dict(dataclasses.asdict(r.controller), where="robot.controller").validate(
                len(r.joint_map or ()))
        except InputError as e:
            raise InputError(f"{f}: {e}") from None
    simulated = simulated_platforms()
    kind = source_type(s.type, f"{f}: source.type")
    if s.type not in simulated and s.path is None and not (kind.hub and s.repo_id is not None):
        if kind.hub:
            raise InputError(f"{f}: source: type {s.type} needs 'path' ({kind.path}) or 'repo_id' (a hub dataset)")
        raise InputError(f"{f}: source.path: required for source.type {s.type} ({kind.path})")
    if s.action_space not in ("joint", "ee"):
        raise InputError(f"{f}: source.action_space: must be 'joint' or 'ee', got {s.action_space!r}")
    unset = SourceSection(type=s.type)  # a key set away from its default is refused if another type owns it
    others = {k: name for name, other in SOURCE_TYPES.items() for k in other.own_keys if k not in kind.own_keys}
    extra = [k for k in others if getattr(s, k) != getattr(unset, k)]
    if extra:
        owners = " or ".join(dict.fromkeys(others[k] for k in extra))
        raise InputError(f"{f}: source: {extra} only apply to source.type {owners}")
    d = recipe.depth
    if d.format is not None and d.format not in DEPTH_FORMATS:
        raise InputError(f"{f}: depth.format: must be one of {DEPTH_FORMATS}, got {d.format!r}")
    if d.feature is not None and (not kind.depth_feature or d.source != "recorded"):
        with_feature = " or ".join(name for name, other in SOURCE_TYPES.items() if other.depth_feature)
        raise InputError(f"{f}: depth.feature: only for depth.source recorded with source.type {with_feature}")
    if kind.depth_feature and d.source == "recorded" and d.feature is None:
        raise InputError(f"{f}: depth.feature: a {kind.label} source has no HDF5 depth; name its depth feature "
                         "(e.g. observation.depth.{cam}), or set depth.source to da3 or none")
    if d.batch_size < 1 or d.process_res < 14 or d.process_res % 14:
        raise InputError(f"{f}: depth: batch_size must be >= 1 and process_res a positive multiple of 14")
    if s.type in simulated and r.platform != s.type:
        raise InputError(f"{f}: source.type {s.type} records the simulated rig: set robot.platform: {s.type}")
    if s.type not in simulated and recipe.cameras.calibration is None:
        raise InputError(f"{f}: cameras.calibration: required for real data (a calibration JSON, see docs/calibration.md)")
    if s.episodes is not None and s.episodes <= 0:
        raise InputError(f"{f}: source.episodes: must be positive, got {s.episodes}")
    if recipe.fps is not None and not (0 < recipe.fps < math.inf and float(recipe.fps).is_integer()):
        raise InputError(f"{f}: fps: must be a positive whole number (LeRobot stores an integer fps), got {recipe.fps}")
    if s.episode_defaults.source not in ("teleop", "policy"):
        raise InputError(f"{f}: source.episode_defaults.source: must be 'teleop' or 'policy'")
    sim = s.sim
    if sim.task not in SIM_TASKS:
        raise InputError(f"{f}: source.sim.task: must be one of {list(SIM_TASKS)}, got {sim.task!r}")
    if not 0.0 <= sim.noise <= 1.0:
        raise InputError(f"{f}: source.sim.noise: must be in [0, 1], got {sim.noise}")
    if sim.height <= 0 or sim.width <= 0 or sim.frame_stride <= 0:
        raise InputError(f"{f}: source.sim: height, width and frame_stride must be positive")


def _validate_units(r: RobotSection, f: str) -> None:
    """``robot.units`` and ``robot.calibration``: options of a platform recorded in LeRobot's units."""
    if r.units is None and r.calibration is None:
        arm = PLATFORMS[r.platform].lerobot_arm if r.platform is not None else None
        if arm is not None and LEROBOT_ARMS[arm].units == "range_m100_100":
            raise InputError(f"{f}: robot.calibration: platform {r.platform!r} records -100..100 by default, which "
                             f"maps to angles only through the arm's calibration file ({CALIBRATION_HINT})")
        return
    given = [k for k in ("units", "calibration") if getattr(r, k) is not None]
    if r.platform is None or PLATFORMS[r.platform].lerobot_arm is None:
        what = f"platform {r.platform!r}" if r.platform is not None else "a robot given by urdf and joint_map"
        raise InputError(f"{f}: robot: {given} are options of a platform recorded in LeRobot's units "
                         f"({list(lerobot_platforms())}), not of {what}; a urdf recipe's joint_map carries its units "
                         "in each entry's scale and offset (imac robot joints URDF --lerobot-robot TYPE "
                         "--lerobot-units UNITS --lerobot-calibration FILE prints them)")
    if r.units is not None and r.units not in UNITS:
        raise InputError(f"{f}: robot.units: one of {list(UNITS)} (the body joints' LeRobot units; the gripper "
                         f"always records 0..100), got {r.units!r}")
    units = r.units or LEROBOT_ARMS[PLATFORMS[r.platform].lerobot_arm].units
    if units == "range_m100_100" and r.calibration is None:
        raise InputError(f"{f}: robot.calibration: required with robot.units range_m100_100: values in -100..100 "
                         f"map to angles only through the arm's calibration file ({CALIBRATION_HINT})")


def joint_units(recipe: Recipe) -> dict | None:
    """The LeRobot units the recipe's joint map takes (:func:`~imac_data.core.robot.lerobot_units.convention`,
    what a build records as ``imac.build.joint_units``), or None: a robot not recorded in LeRobot's units, or one
    whose recipe writes its own joint map."""
    r = recipe.robot
    arm = PLATFORMS[r.platform].lerobot_arm if r.platform is not None else None
    if arm is None:
        return None
    return convention(arm, r.units, recipe.resolve_path(r.calibration))


def parse_recipe(data: dict, file: str = "") -> Recipe:
    where = file or "<recipe>"
    if not isinstance(data, dict):
        raise InputError(f"{where}: a recipe must be a YAML mapping")
    try:
        recipe = parse_dataclass(Recipe, data, "", skip={"file"})  # file: set below, never read
    except InputError as e:
        raise InputError(f"{where}: {e}") from None
    recipe = dataclasses.replace(recipe, file=file)
    _validate(recipe)
    return recipe


def _read_yaml(path: Path) -> dict:
    if not path.is_file():
        raise InputError(f"recipe file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise InputError(f"{path}: invalid YAML ({e})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: a recipe must be a YAML mapping")
    return data


def _merge(base: dict, override: dict) -> dict:
    out = dict(base)
    for key, value in override.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def load_recipe(path: str | Path) -> Recipe:
    """Read and validate a recipe. ``base: <file>`` (relative to the recipe) names a
    platform file whose fields the recipe extends or overrides."""
    path = Path(path)
    data = _read_yaml(path)
    if "base" in data:
        base_file = data.pop("base")
        if not isinstance(base_file, str):
            raise InputError(f"{path}: base: expected a file name, got {base_file!r}")
        base = _read_yaml(path.parent / base_file)
        if "base" in base:
            raise InputError(f"{path.parent / base_file}: a base file cannot have a base itself")
        data = _merge(base, data)
    return parse_recipe(data, str(path))


_ENV = re.compile(r"\$\{?([A-Za-z_][A-Za-z0-9_]*)\}?")


def missing_inputs(recipe: Recipe, source_path: Path | None = None) -> list[str]:
    """Every user-supplied file the recipe needs that is not there, each with how to supply it."""
    problems = []

    def check(field: str, value: str | None, what: str, how: str, is_dir: bool = False) -> None:
        if value is None:
            return
        unset = [v for v in _ENV.findall(value) if v not in os.environ]
        if unset:
            problems.append(f"{field}: {what} -- set the environment variable {unset[0]} ({how}), "
                            f"or write the path into {recipe.file or 'the recipe'}")
            return
        path = recipe.resolve_path(value)
        if not (path.is_dir() if is_dir else path.is_file()):
            problems.append(f"{field}: {what} not found at {path} ({how})")

    r = recipe.robot
    if r.platform is None:
        check("robot.urdf", r.urdf, "the robot's URDF", "your robot description, with its meshes")
        for name, value in r.package_dirs.items():
            check(f"robot.package_dirs.{name}", value, f"the directory of package://{name}/", "where the meshes are",
                  is_dir=True)
    check("robot.calibration", r.calibration, "the arm's LeRobot calibration file", CALIBRATION_HINT)
    check("cameras.calibration", recipe.cameras.calibration, "the camera calibration JSON",
          "format in docs/calibration.md")
    if source_path is None:
        kind = source_type(recipe.source.type)
        check("source.path", recipe.source.path, kind.path, kind.path_hint, is_dir=True)
    check("source.metadata", recipe.source.metadata, "the episode metadata file", "CSV or JSON keyed by episode_index")
    return problems


def find_recipe(name: str) -> Path:
    """``recipes/<name>.yaml`` of this repository."""
    path = RECIPES_DIR / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in RECIPES_DIR.glob("*.yaml"))
        raise InputError(f"unknown recipe {name!r}: no {path}; known recipes: {known} (or pass --recipe PATH)")
    return path
