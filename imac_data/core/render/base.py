"""The renderer interface: what every backend of :mod:`imac_data.core.render` returns and checks.

:class:`Renderer` is the interface (the build, the world model online, the overlay)::

    views = renderer.render(q, cameras)            # q (*B, D) dataset joint vectors
    views["cam_high"].rgb    # (*B, H, W, 3) uint8  URDF colours, Lambertian shading, black background
    views["cam_high"].mask   # (*B, H, W)    bool   robot pixels
    views["cam_high"].depth  # (*B, H, W)    float32 robot z-depth in metres, 0 = no robot
    views["cam_high"].link_id  # (*B, H, W)  int16  index into renderer.link_names, -1 = background

A backend implements :meth:`Renderer.render_link_poses` only."""


from __future__ import annotations

import abc
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from imac_data.core.cameras import Camera
from imac_data.core.robot.model import RobotModel
from imac_data.errors import InputError

__all__ = ["RenderOutput", "Renderer", "check_device", "rigid_inverse"]


@dataclass
class RenderOutput:
    """One camera view of a batch of configurations (all tensors share the leading ``*B``)."""

    rgb: torch.Tensor  # (*B, H, W, 3) uint8
    mask: torch.Tensor  # (*B, H, W) bool
    depth: torch.Tensor  # (*B, H, W) float32 z-depth in metres, 0 where mask is False
    link_id: torch.Tensor  # (*B, H, W) int16, index into Renderer.link_names, -1 = background


class Renderer(abc.ABC):
    """Robot renderer interface. Subclasses implement :meth:`render_link_poses`."""

    robot: RobotModel
    link_names: tuple[str, ...]  # links with visual geometry; RenderOutput.link_id indexes this

    def __init__(self, robot: RobotModel):
        self.robot = robot
        seen: dict[str, None] = {}
        for mesh in robot.visual_meshes:
            seen.setdefault(mesh.link, None)
        self.link_names = tuple(seen)

    # ------------------------------------------------------------------ public

    def render(self, q=None, cameras: Mapping[str, Camera] | Sequence[Camera] = (), *,
               resolution: tuple[int, int] | None = None,
               link_poses: Mapping[str, torch.Tensor] | None = None) -> dict[str, RenderOutput]:
        """Render the robot at dataset joint vectors ``q`` ``(*B, D)`` into every camera.

        ``cameras``: name -> :class:`Camera` (or a sequence, keyed by ``Camera.name``).
        ``resolution``: ``(height, width)`` for every view (K rescaled), default each
        camera's own size. ``link_poses`` (link -> ``(*B, 4, 4)``, e.g. from an
        earlier FK call) may be given instead of ``q``. Returns name -> :class:`RenderOutput`.
        Raises :class:`InputError` on a joint vector of the wrong length, non-finite
        joints, or a camera mounted on a link the robot does not have.
        """
        cams = self.prepare_cameras(cameras, resolution)
        if link_poses is None:
            if q is None:
                raise InputError("render: give joint vectors q or link_poses")
            link_poses = self.robot.link_poses(q)  # validates length and finiteness
        else:
            missing = [name for name in self.link_names if name not in link_poses]
            if missing:
                raise InputError(f"render: link_poses lacks link(s) {missing} of robot {self.robot.name!r}")
            for cam in cams.values():
                if cam.is_mounted and cam.link not in link_poses:
                    raise InputError(f"render: link_poses lacks link {cam.link!r}, on which camera "
                                     f"{cam.name!r} is mounted")
            for name in self.link_names:
                if not torch.isfinite(link_poses[name]).all():
                    raise InputError(f"render: non-finite pose of link {name!r}")
        return self.render_link_poses(link_poses, cams)

    def prepare_cameras(self, cameras: Mapping[str, Camera] | Sequence[Camera],
                        resolution: tuple[int, int] | None = None) -> dict[str, Camera]:
        """Validate cameras against the robot (mounted links must exist) and apply ``resolution``."""
        if isinstance(cameras, Camera):
            cameras = [cameras]
        cams = dict(cameras) if isinstance(cameras, Mapping) else {c.name: c for c in cameras}
        if not cams:
            raise InputError("render: no cameras given")
        links = set(self.robot.link_names)
        for name, cam in cams.items():
            if not isinstance(cam, Camera):
                raise InputError(f"render: camera {name!r} is not a Camera (got {type(cam).__name__})")
            if cam.is_mounted and cam.link not in links:
                raise InputError(f"camera {name!r} is mounted on link {cam.link!r}, which robot "
                                 f"{self.robot.name!r} does not have (links: {sorted(links)})")
        if resolution is not None:
            try:
                h, w = (int(x) for x in resolution)
            except (TypeError, ValueError):
                raise InputError(f"render: resolution must be (height, width), got {resolution!r}") from None
            if h <= 0 or w <= 0:
                raise InputError(f"render: resolution must be positive, got {resolution!r}")
            cams = {n: (c if (c.height, c.width) == (h, w) else c.rescaled(w, h)) for n, c in cams.items()}
        return cams

    def links_mask(self, link_id: torch.Tensor, links: Sequence[str]) -> torch.Tensor:
        """Boolean mask of the pixels showing any of ``links`` (e.g. ``robot.gripper_links``)."""
        unknown = [name for name in links if name not in self.link_names]
        if unknown:
            raise InputError(f"links {unknown} have no visual geometry in robot {self.robot.name!r}")
        lut = torch.zeros(len(self.link_names) + 1, dtype=torch.bool, device=link_id.device)
        lut[[self.link_names.index(name) + 1 for name in links]] = True
        return lut[link_id.long() + 1]

    # ------------------------------------------------------------------ backend

    @abc.abstractmethod
    def render_link_poses(self, link_poses: Mapping[str, torch.Tensor],
                          cameras: Mapping[str, Camera]) -> dict[str, RenderOutput]:
        """Render posed links (link -> ``(*B, 4, 4)`` world poses) into validated cameras."""


def rigid_inverse(T):
    """Inverses of rigid 4x4 transforms ``(..., 4, 4)``, numpy or torch (both backends' camera <-> link maps)."""
    R = T[..., :3, :3].swapaxes(-1, -2)
    out = np.zeros_like(T) if isinstance(T, np.ndarray) else torch.zeros_like(T)
    out[..., :3, :3] = R
    out[..., :3, 3] = -(R @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def check_device(device: str) -> str:
    """``device`` of a build (``cpu``, ``cuda`` or ``cuda:N``) if this machine has it, else one clear
    :class:`InputError`. CUDA is asked about without creating a context, so forked workers can still use it."""
    name = str(device)
    if name == "cpu":
        return name
    if not re.fullmatch(r"cuda(:\d+)?", name):
        raise InputError(f"--device must be cpu, cuda or cuda:N, got {name!r}")
    if not torch.cuda.is_available():
        raise InputError(f"--device {name}: torch sees no CUDA device on this machine (build without --device to "
                         "use the CPU path)")
    index = int(name.split(":")[1]) if ":" in name else 0
    if index >= torch.cuda.device_count():
        raise InputError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return name
