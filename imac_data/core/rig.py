"""The rig: one robot with its cameras and controller, and what is derived from them.

A :class:`Rig` holds the robot (URDF, joint map, batched FK), the calibrated cameras (view
order = the dataset's), the controller map phi, the workspace crop of the contact streams,
and, built on first use in each process, the renderer and the gripper surface samples. It
comes from a recipe (:meth:`Rig.from_recipe`) or from a built dataset alone
(:meth:`Rig.from_info`), which give the same rig. After construction it is tensors in,
tensors out, so the world model calls the same functions online as the build offline::

    rig = Rig.from_info(ds.meta)
    q = rig.frame_configurations(state, action)                  # or rig.rollout(q_t, actions)
    views = rig.robot_views(q, resolution=(240, 320))            # rgb, mask, depth, poses, gripper points
    chunk = rig.contact(ref_depth, q_ref, q_future)              # both contact streams of one chunk"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import torch

from imac_data.core.cameras import Camera, camera_from_dict, load_calibration
from imac_data.core.contact.clouds import DEFAULT_DILATE_PX, DEFAULT_GRIPPER_SPACING, GripperSurface, scene_cloud
from imac_data.core.contact.images import ContactChunk, contact_chunk
from imac_data.core.contact.workspace import Workspace, as_workspace, resolve_workspace, saturation_depth
from imac_data.core.depth import DepthCodec
from imac_data.core.metric_depth import resize_depth
from imac_data.core.motion import Controller, frame_configurations, rollout
from imac_data.core.render import BACKENDS, check_device, make_renderer
from imac_data.core.robot.description import check_description, description_manifest
from imac_data.core.robot.lerobot_units import LEROBOT_ARMS, read_calibration
from imac_data.core.robot.model import RobotConfig, RobotModel
from imac_data.core.robot.platforms import platform as get_platform
from imac_data.core.scene_warp import DEFAULT_FILL, splat
from imac_data.errors import InputError
from imac_data.layout import INFO, URDF_NAME, description_dir
from imac_data.metadata import RIG_KEYS, dataset_root, imac_block, imac_block_path

__all__ = ["Rig", "RobotViews", "DEFAULT_GRIPPER_SPACING", "RIG_KEYS"]


@dataclass
class RobotViews:
    """The robot seen from every camera at N configurations (views in the rig's order).

    ``rgb (N, V, H, W, 3)`` uint8 (motion image), ``mask (N, V, H, W)`` bool, ``depth
    (N, V, H, W)`` float32 robot z-depth (0 = no robot), ``link_id (N, V, H, W)`` int16
    (index into ``rig.renderer.link_names``, -1 = none), ``T_world_cam (N, V, 4, 4)``
    camera-to-world (OpenCV; wrist cameras posed by FK), ``gripper_points (N, M, 3)``."""

    rgb: torch.Tensor | None
    mask: torch.Tensor
    depth: torch.Tensor
    link_id: torch.Tensor
    T_world_cam: torch.Tensor
    gripper_points: torch.Tensor | None

    def rows(self, lo: int, hi: int) -> RobotViews:
        """Configurations ``lo .. hi - 1`` of a batched render (e.g. one chunk's)."""
        return RobotViews(*(None if x is None else x[lo:hi] for x in
                            (self.rgb, self.mask, self.depth, self.link_id, self.T_world_cam, self.gripper_points)))


@dataclass(eq=False)
class Rig:
    """Robot + cameras + controller (+ renderer and gripper surface, built on first use)."""

    robot: RobotModel
    cameras: dict[str, Camera]
    controller: Controller = field(default_factory=Controller)
    state_names: tuple[str, ...] | None = None
    gripper_spacing: float = DEFAULT_GRIPPER_SPACING
    threads: int = 0  # renderer (Embree) and contact threads; 0 = all cores
    workspace: Workspace | None = None  # the contact streams' scene crop; None = none
    device: str = "cpu"  # cpu: Open3D ray casting, KD-trees; cuda[:N]: the torch rasteriser, brute force there
    cpu_renderer: str = "open3d"  # the renderer backend on the CPU (render.BACKENDS): open3d or opengl

    def __post_init__(self) -> None:
        if not self.cameras:
            raise InputError(f"rig of robot {self.robot.name!r}: no cameras")
        self.cameras = dict(self.cameras)
        links = set(self.robot.link_names)
        for name, cam in self.cameras.items():
            if cam.is_mounted and cam.link not in links:
                raise InputError(f"camera {name!r} is mounted on link {cam.link!r}, which robot "
                                 f"{self.robot.name!r} does not have")
        self.controller.validate(self.robot.dof)
        if self.state_names is not None:
            self.state_names = tuple(self.state_names)
            if len(self.state_names) != self.robot.dof:
                raise InputError(f"rig: {len(self.state_names)} state names for a {self.robot.dof}-D joint vector")
        if not (math.isfinite(self.gripper_spacing) and self.gripper_spacing > 0):
            raise InputError(f"rig: gripper spacing must be > 0 metres, got {self.gripper_spacing}")
        self.workspace = as_workspace(self.workspace)
        self.device = check_device(self.device)
        if self.cpu_renderer not in BACKENDS:
            raise InputError(f"rig: unknown renderer {self.cpu_renderer!r}; available: {sorted(BACKENDS)}")
        self._renderer = None
        self._gripper = None

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_recipe(cls, recipe, calibration: str | Path | Mapping[str, Camera] | None = None, *,
                    robot: RobotModel | None = None) -> Rig:
        """The rig a recipe describes. ``calibration``: a calibration file or cameras
        (default: the recipe's ``cameras.calibration``); ``robot``: the recipe's robot if
        already loaded (:meth:`robot_from_recipe`). The workspace is the recipe's
        ``augment.contact_workspace``, defaults filled in (:func:`~imac_data.core.contact.workspace.resolve_workspace`)."""
        if calibration is None:
            path = recipe.resolve_path(recipe.cameras.calibration)
            if path is None:
                raise InputError(f"{recipe.file or 'recipe'}: cameras.calibration: no calibration given")
            calibration = path
        cameras = load_calibration(calibration) if isinstance(calibration, (str, Path)) else dict(calibration)
        robot = robot if robot is not None else cls.robot_from_recipe(recipe)
        a = recipe.augment
        workspace = resolve_workspace(a.contact_workspace, robot, saturation_depth(DepthCodec.preset(a.depth_codec)))
        r = recipe.robot
        if r.platform is not None:
            # a simulated platform's source is the simulator itself (source.type = the platform)
            task = recipe.source.sim.task if recipe.source.type == r.platform else None
            return cls.from_platform(r.platform, cameras, robot=robot, task=task, workspace=workspace)
        controller = Controller()
        if r.controller is not None:
            from dataclasses import asdict

            controller = Controller.from_dict(asdict(r.controller), where=f"{recipe.file}: robot.controller")
        return cls(robot, cameras, controller, workspace=workspace)

    @classmethod
    def from_platform(cls, platform: str, cameras: Mapping[str, Camera], *, robot: RobotModel | None = None,
                      task: str | None = None, workspace: Workspace | None = None) -> Rig:
        """A registered rig by name (:data:`~imac_data.core.robot.platforms.PLATFORMS`) with the
        given cameras; ``task``: the simulated scene whose actuators the controller follows."""
        entry = get_platform(platform)
        robot = robot if robot is not None else RobotModel(entry.robot())
        return cls(robot, dict(cameras), entry.controller(task), state_names=entry.state_names, workspace=workspace)

    @staticmethod
    def robot_from_recipe(recipe) -> RobotModel:
        """The recipe's robot alone (URDF, joint map; checked against each other), e.g. to
        fail on a bad URDF before any work starts."""
        r = recipe.robot
        if r.platform is not None:
            entry = get_platform(r.platform, f"{recipe.file}: robot.platform")
            options = {}
            if entry.lerobot_arm is not None:  # the recipe's LeRobot units (checked by the recipe's validation)
                path = recipe.resolve_path(r.calibration)
                arm = LEROBOT_ARMS[entry.lerobot_arm]
                options = {"units": r.units,
                           "calibration": None if path is None else read_calibration(path, (*arm.body, arm.gripper))}
            return RobotModel(entry.robot(**options))
        urdf = recipe.resolve_path(r.urdf)
        if not urdf.is_file():
            raise InputError(f"{recipe.file}: robot.urdf: file not found: {urdf}")
        joint_map = RobotConfig.parse_joint_map(r.joint_map_entries(), f"{recipe.file}: robot.joint_map")
        return RobotModel(RobotConfig(name=recipe.name, urdf_path=urdf, joint_map=joint_map,
                                      gripper_links=r.gripper_links,
                                      package_dirs={k: recipe.resolve_path(v) for k, v in r.package_dirs.items()}))

    @classmethod
    def from_info(cls, meta, root: str | Path | None = None, *, check_files: bool = True) -> Rig:
        """The rig of a built dataset: ``meta`` is ``ds.meta``, the dataset's root or its
        :func:`~imac_data.metadata.dataset_info` dict (:mod:`imac_data.metadata`); ``root``, the directory that holds
        ``meta/imac/robot/``, is needed with a dict only."""
        root = root if root is not None else dataset_root(meta)
        if root is None:
            raise InputError("Rig.from_info: a meta/info.json dict needs the dataset's root (root=...), where the "
                             "robot description meta/imac/robot/ is; or pass ds.meta or the root alone")
        where = f"{root}/{INFO}" if isinstance(meta, Mapping) else str(imac_block_path(root))  # a dict: info.json's
        block = imac_block(meta, require=("robot",), where=where)
        return cls.from_block(block, description_dir(root), check_files=check_files, where=f"{where} imac")

    @classmethod
    def from_dataset(cls, root: str | Path) -> Rig:
        """:meth:`from_info` of the dataset at ``root``."""
        return cls.from_info(Path(root))

    @classmethod
    def from_block(cls, block: Mapping, description_dir: str | Path, *, check_files: bool = True,
                   where: str = "imac block") -> Rig:
        """A rig from the ``imac`` block's rig keys and a packaged robot description directory."""
        missing = [k for k in ("robot", "cameras", "controller") if k not in block]
        if missing:
            raise InputError(f"{where}: missing key(s) {missing}")
        rb = block["robot"]
        for key in ("name", "joint_map", "description"):
            if key not in rb:
                raise InputError(f"{where}.robot: missing key {key!r}")
        description_dir = Path(description_dir)
        if check_files:
            check_description(description_dir, rb["description"], where=f"{where}.robot.description")
        config = RobotConfig(name=rb["name"], urdf_path=description_dir / URDF_NAME,
                             joint_map=RobotConfig.parse_joint_map(rb["joint_map"], f"{where}.robot.joint_map"),
                             gripper_links=tuple(rb.get("gripper_links", ())))
        cameras = {n: camera_from_dict(n, c, f"{where}.cameras.{n}") for n, c in block["cameras"].items()}
        surface = block.get("gripper_surface", {})
        # schema 1 datasets have no workspace: their contact streams were not cropped
        workspace = Workspace.from_dict(block.get("workspace"), f"{where}.workspace")
        return cls(RobotModel(config), cameras, Controller.from_dict(block["controller"], f"{where}.controller"),
                   state_names=rb.get("state_names"),
                   gripper_spacing=float(surface.get("spacing", DEFAULT_GRIPPER_SPACING)), workspace=workspace)

    def to_info(self) -> dict:
        """The rig's part of ``info["imac"]`` (:data:`RIG_KEYS`), JSON-ready."""
        config = self.robot.config
        return {
            "robot": {"name": config.name, "joint_map": config.joint_map_dict(),
                      "gripper_links": list(config.gripper_links),
                      "state_names": None if self.state_names is None else list(self.state_names),
                      "description": description_manifest(self.robot)},
            "cameras": {name: cam.to_dict() for name, cam in self.cameras.items()},
            "controller": self.controller.to_dict(),
            "gripper_surface": {"links": list(config.gripper_links), "spacing": self.gripper_spacing, "seed": 0},
            "workspace": None if self.workspace is None else self.workspace.to_dict(),
        }

    def with_image_sizes(self, sizes: Mapping[str, tuple[int, int]]) -> Rig:
        """The same rig with each camera's calibration rescaled to the recorded image size
        ``(height, width)`` (same aspect ratio; K follows, :meth:`Camera.rescaled`)."""
        cams = {name: cam.for_images(*sizes.get(name, (cam.height, cam.width)))
                for name, cam in self.cameras.items()}
        rig = Rig(self.robot, cams, self.controller, self.state_names, self.gripper_spacing, self.threads,
                  self.workspace, self.device, self.cpu_renderer)
        rig._renderer, rig._gripper = self._renderer, self._gripper
        return rig

    def for_views(self, views) -> Rig:
        """The same rig with the cameras ``views`` alone, in that order (a model's views)."""
        missing = [v for v in views if v not in self.cameras]
        if missing:
            raise InputError(f"rig: no camera(s) {missing} (has {self.names})")
        return Rig(self.robot, {v: self.cameras[v] for v in views}, self.controller, self.state_names,
                   self.gripper_spacing, self.threads, self.workspace, self.device, self.cpu_renderer)

    # ------------------------------------------------------------------ parts

    @property
    def names(self) -> list[str]:
        """View order (the order of ``cameras``: head, left wrist, right wrist)."""
        return list(self.cameras)

    @property
    def dof(self) -> int:
        return self.robot.dof

    @property
    def renderer(self):
        if self._renderer is None:
            self._renderer = (make_renderer(self.robot, self.cpu_renderer, nthreads=self.threads)
                              if self.device == "cpu" else make_renderer(self.robot, "torch", device=self.device))
        return self._renderer

    def use_cpu_renderer(self, backend: str) -> None:
        """Render with ``backend`` on the CPU from now on (a recipe's ``augment.renderer``)."""
        if backend not in BACKENDS:
            raise InputError(f"rig: unknown renderer {backend!r}; available: {sorted(BACKENDS)}")
        if backend != self.cpu_renderer:
            self.cpu_renderer, self._renderer = backend, None

    @property
    def gripper(self):
        """Surface samples of the gripper links (:class:`~imac_data.core.contact.clouds.GripperSurface`)."""
        if self._gripper is None:
            self._gripper = GripperSurface(self.robot, spacing=self.gripper_spacing)
        return self._gripper

    def set_threads(self, threads: int) -> None:
        """Threads for the renderer's ray casting and the contact queries (0 = all cores)."""
        self.threads = int(threads)
        if self._renderer is not None and hasattr(self._renderer, "nthreads"):
            self._renderer.nthreads = self.threads

    def stream_cameras(self, resolution: tuple[int, int] | None = None) -> dict[str, Camera]:
        """The cameras at ``resolution`` ``(H, W)`` (K rescaled with :meth:`Camera.rescaled`)."""
        if resolution is None:
            return dict(self.cameras)
        try:
            h, w = (int(x) for x in resolution)
        except (TypeError, ValueError):
            raise InputError(f"rig: resolution must be (height, width), got {resolution!r}") from None
        if h <= 0 or w <= 0:
            raise InputError(f"rig: resolution must be positive, got {resolution!r}")
        return {n: (c if (c.height, c.width) == (h, w) else c.rescaled(w, h)) for n, c in self.cameras.items()}

    def intrinsics(self, resolution: tuple[int, int] | None = None, device=None) -> torch.Tensor:
        """``K (V, 3, 3)`` float32 at ``resolution``."""
        cams = self.stream_cameras(resolution)
        return torch.stack([torch.as_tensor(c.K, dtype=torch.float32, device=device) for c in cams.values()])

    # ------------------------------------------------------------------ kinematics

    def link_poses(self, q) -> dict[str, torch.Tensor]:
        """World pose ``(*B, 4, 4)`` of every link at joint vectors ``q (*B, D)``."""
        return self.robot.link_poses(q)

    def camera_poses(self, q=None, *, link_poses=None, dtype=torch.float32) -> torch.Tensor:
        """Camera-to-world poses ``(*B, V, 4, 4)`` at joint vectors ``q (*B, D)`` (or FK link
        poses); fixed cameras broadcast, mounted ones follow their link."""
        if link_poses is None:
            link_poses = self.link_poses(torch.as_tensor(q, dtype=dtype))
        ref = next(iter(link_poses.values()))
        batch = tuple(ref.shape[:-2])
        return torch.stack([c.pose(link_poses, batch_shape=batch, dtype=ref.dtype, device=ref.device)
                            for c in self.cameras.values()], dim=-3)

    def frame_configurations(self, state, action=None, *, source: str = "action"):
        """The configuration each frame's motion image shows (:func:`imac_data.core.motion.frame_configurations`)."""
        return frame_configurations(state, action, source=source, controller=self.controller)

    def rollout(self, q_t, actions):
        """phi: configurations ``(*B, K, D)`` after each of ``actions (*B, K, D)`` from ``q_t (*B, D)``."""
        return rollout(q_t, actions, self.controller)

    # ------------------------------------------------------------------ rendering

    def robot_views(self, q=None, *, link_poses=None, resolution: tuple[int, int] | None = None,
                    gripper: bool = True) -> RobotViews:
        """Render the robot at joint vectors ``q (N, D)`` (or FK ``link_poses``) into every
        camera at ``resolution`` (default: each camera's size)."""
        if link_poses is None:
            q = torch.as_tensor(q, dtype=torch.float32)
            if q.ndim != 2:
                raise InputError(f"robot_views: joint vectors must be (N, D), got shape {tuple(q.shape)}")
            link_poses = self.link_poses(q)
        cams = self.stream_cameras(resolution)
        views = self.renderer.render(cameras=cams, link_poses=link_poses)
        names = list(cams)
        ref = next(iter(link_poses.values()))
        batch = tuple(ref.shape[:-2])

        def stack(attr):
            return torch.stack([getattr(views[n], attr) for n in names], dim=len(batch))

        poses = torch.stack([cams[n].pose(link_poses, batch_shape=batch) for n in names], dim=len(batch))
        return RobotViews(rgb=stack("rgb"), mask=stack("mask"), depth=stack("depth"), link_id=stack("link_id"),
                          T_world_cam=poses, gripper_points=self.gripper.points(link_poses) if gripper else None)

    # ------------------------------------------------------------------ contact

    def contact(self, ref_depth, q_ref, q_future, **options):
        """Both contact streams of one chunk, from depth: ``ref_depth (V, H, W)`` metres at the
        reference (sensed, or a world model's prediction), the reference state ``q_ref (D,)``
        (robot mask and camera poses) and the configurations to draw ``q_future (S, D)``.
        With a leading batch axis (``(B, V, H, W)``, ``(B, D)``, ``(B, S, D)``) every tensor
        of the result gets one too. The robot is rendered at the depth's ``(H, W)``, then
        :meth:`contact_images` paints the streams; ``options`` are its own.
        """
        ref_depth = torch.as_tensor(ref_depth)
        q_ref = torch.as_tensor(q_ref, dtype=torch.float32)
        q_future = torch.as_tensor(q_future, dtype=torch.float32)
        V = len(self.cameras)
        if ref_depth.ndim == 4:
            if q_ref.ndim != 2 or q_future.ndim != 3 or not (len(ref_depth) == len(q_ref) == len(q_future)):
                raise InputError(f"contact: batched inputs must be (B, V, H, W), (B, D), (B, S, D); got "
                                 f"{tuple(ref_depth.shape)}, {tuple(q_ref.shape)}, {tuple(q_future.shape)}")
            parts = [self.contact(ref_depth[b], q_ref[b], q_future[b], **options) for b in range(len(ref_depth))]
            return ContactChunk(*(torch.stack([getattr(p, k) for p in parts])
                                  for k in ("r2s", "s2g", "r2s_rgb", "s2g_rgb", "caps")))
        if ref_depth.ndim != 3 or ref_depth.shape[0] != V:
            raise InputError(f"contact: reference depth must be (V, H, W) with V = {V} views {self.names}, "
                             f"got {tuple(ref_depth.shape)}")
        if q_ref.ndim != 1 or q_future.ndim != 2:
            raise InputError(f"contact: q_ref must be (D,) and q_future (S, D), got {tuple(q_ref.shape)}, "
                             f"{tuple(q_future.shape)}")
        hw = tuple(ref_depth.shape[-2:])
        seen = self.robot_views(q_ref[None], resolution=hw, gripper=False)
        drawn = self.robot_views(q_future, resolution=hw)
        return self.contact_images(ref_depth, seen, drawn, **options)

    def contact_images(self, ref_depth, seen: RobotViews, drawn: RobotViews, *, threads: int | None = None,
                       device=None, **options) -> ContactChunk:
        """Both contact streams of one chunk from its renders and its reference depth: the one
        function the build (:mod:`imac_data.augment.pipeline`), the world model's rollout
        (``imac_model.pipelines.online_controls``) and :meth:`contact` call, so that offline and
        online controls are the same function of the same inputs.

        ``ref_depth (V, h, w)`` metres at the reference (resized nearest-pixel to the renders'
        size); ``seen``: the robot rendered at the reference's measured state (one configuration:
        its mask is removed from the scene, its camera poses place it); ``drawn``: the robot at the
        chunk's S configurations (robot depth, camera poses, gripper points). ``threads``: the
        nearest-neighbour and painting threads (None: every core; the result is the same).
        ``options``: :func:`~imac_data.core.contact.images.contact_chunk` (cap, percentile,
        dilate_px, allow_empty_scene, ...); the scene is cropped to the rig's workspace unless
        ``workspace`` is given (None = no crop). Returns a :class:`~imac_data.core.contact.images.ContactChunk`.
        """
        hw = tuple(drawn.depth.shape[-2:])
        ref_depth = torch.as_tensor(ref_depth)
        if tuple(ref_depth.shape[-2:]) != hw:
            ref_depth = resize_depth(ref_depth, hw, name="reference depth")
        device = torch.device(device) if device is not None else ref_depth.device
        options.setdefault("workspace", self.workspace)
        if threads is not None:
            options.update(workers=threads, parallel=threads)

        def on(x):
            return None if x is None else x.to(device)

        return contact_chunk(on(ref_depth.to(torch.float32)), on(self.intrinsics(hw)), on(seen.T_world_cam[0]),
                             on(seen.mask[0]), on(drawn.depth), on(drawn.T_world_cam), on(drawn.gripper_points),
                             device=device, **options)

    def scene_warp(self, ref_rgb, ref_depth, seen: RobotViews, poses, *, dilate_px: int = DEFAULT_DILATE_PX,
                   fill: int = DEFAULT_FILL) -> torch.Tensor:
        """The scene-warp images of one chunk, uint8 ``(S, V, h, w, 3)``: the reference RGB
        ``(V, h, w, 3)`` uint8 and depth ``(V, h, w)`` metres, the robot (``seen``'s mask, grown by
        ``dilate_px``) removed and cropped to the rig's workspace, splatted into every camera at
        ``poses (S, V, 4, 4)`` (:meth:`camera_poses` of the chunk's configurations); black where
        no scene lands (:func:`~imac_data.core.scene_warp.splat`)."""
        ref_rgb = torch.as_tensor(ref_rgb)
        hw = tuple(ref_rgb.shape[1:3])
        ref_depth = torch.as_tensor(ref_depth, dtype=torch.float32)
        if tuple(ref_depth.shape[-2:]) != hw:
            ref_depth = resize_depth(ref_depth, hw, name="reference depth")
        if tuple(seen.mask.shape[-2:]) != hw:
            raise InputError(f"scene warp: the robot was rendered at {tuple(seen.mask.shape[-2:])}, the reference "
                             f"images are {hw}")
        K = self.intrinsics(hw)
        cloud = scene_cloud(ref_depth, K, seen.T_world_cam[0].float(), seen.mask[0], dilate_px=dilate_px,
                            workspace=self.workspace)
        colours = ref_rgb.reshape(-1, ref_rgb.shape[-1]).index_select(0, cloud.flat)
        images, _ = splat(cloud.points, colours, K, torch.as_tensor(poses, dtype=torch.float32), hw,
                          source_view=cloud.flat // (hw[0] * hw[1]), fill=fill)
        return images

    def __repr__(self) -> str:
        return (f"Rig(robot={self.robot.name!r}, dof={self.dof}, cameras={self.names}, "
                f"controller={self.controller.mode!r})")

