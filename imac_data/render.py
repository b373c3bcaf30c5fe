"""Motion images: the robot rendered from its URDF + forward kinematics into camera views.

Interface
---------
:class:`Renderer` is the small interface callers use (the world model online, the
dataset builder offline, the QA overlay)::

    views = renderer.render(q, cameras)            # q (*B, D) dataset joint vectors
    views["cam_high"].rgb    # (*B, H, W, 3) uint8  URDF colours, Lambertian shading, black background
    views["cam_high"].mask   # (*B, H, W)    bool   robot pixels
    views["cam_high"].depth  # (*B, H, W)    float32 robot z-depth in metres, 0 = no robot
    views["cam_high"].link_id  # (*B, H, W)  int16  index into renderer.link_names, -1 = background

Fixed cameras use their constant pose, mounted (wrist) cameras the pose of their link
from FK at the same configuration. ``resolution=(H, W)`` renders every view at that
size, rescaling K with :meth:`Camera.rescaled` (the one place K follows a resize).
A backend implements :meth:`Renderer.render_link_poses` only; validation, FK and
resizing live in the base class, so a GPU rasteriser can be added without
touching callers. :func:`make_renderer` picks a backend by name.

The CPU backend: :class:`RaycastRenderer`
-----------------------------------------
Open3D's ``RaycastingScene`` (Embree) on the CPU: no display, no GPU. Rebuilding
its BVH for the posed robot every frame costs more than casting all three views
(about 25-80 ms for the 60k-triangle ALOHA rig on 2 cores, most of the frame), so
we never rebuild it. Instead the scene is built **once**, with every link's
visual meshes in that *link's own frame*, each link a separate geometry placed
at its own far-apart offset ("slot"). A camera ray is cast against a link by
expressing it in the link frame (``T_link_cam = T_world_link^-1 T_world_cam``)
and moving it into the link's slot; per pixel the nearest hit over all links
wins (a z-buffer over links, ``scatter_reduce(amin)``). Slots are spaced so
that a ray cannot reach another slot before it has left its own link's reach:
a hit on a foreign geometry id is a miss of the intended link. Rays are only cast
where a link can be: inside the image rectangle its bounding box projects to
(the box is clipped against the near plane first), so the ray count is about
twice the robot's pixel area instead of links x pixels. Everything per ray is
batched torch (no Python loop over links, meshes or views); all frames, views
and links of a chunk go to Embree in one ``cast_rays`` call.

Conventions: pixel centres at integer coordinates, rays through ``K^-1 [u, v, 1]``
(so the hit parameter *is* z-depth). Open3D's own ``create_rays_pinhole`` casts
through ``(u + 0.5, v + 0.5)`` (half-integer centres), half a pixel off from
ours, so we never use it. ``near`` (metres, default 0) starts every ray on the
plane ``z = near`` like an OpenGL near clip plane (used to compare with MuJoCo,
which clips at ``znear * extent``); real cameras do not clip, hence the default.
Faces are two-sided (the first surface hit counts, front or back).
"""

from __future__ import annotations

import abc
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from imac_data.cameras import Camera
from imac_data.errors import InputError
from imac_data.robot import RobotModel

__all__ = ["RenderOutput", "Renderer", "RaycastRenderer", "make_renderer", "BACKENDS"]


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


# ----------------------------------------------------------------------------- CPU ray casting

# The 12 edges of a box given by its 8 corners in itertools.product order (bit i = axis i).
_BOX_EDGES = torch.tensor([(a, a | (1 << ax)) for a in range(8) for ax in range(3) if not a & (1 << ax)])


def _rigid_inverse(T: torch.Tensor) -> torch.Tensor:
    R = T[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = R
    out[..., :3, 3] = -(R @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


class RaycastRenderer(Renderer):
    """CPU renderer: Open3D ``RaycastingScene`` built once with each link in its own frame.

    ``near``: rays start on the plane z = near (metres) in front of each camera; 0 = no
    clipping. ``ambient``: shade = colour * (ambient + (1 - ambient) |cos(normal, ray)|).
    ``max_range``: the largest camera-to-link distance (m) supported (sets the slot
    spacing; float32 resolution of the slots stays far below 0.1 mm).
    ``max_rays``: rays per Embree call; longer batches are cast frame-chunk by chunk.
    ``nthreads``: Embree threads, 0 = all cores.
    """

    def __init__(self, robot: RobotModel, *, near: float = 0.0, ambient: float = 0.3,
                 max_range: float = 10.0, max_rays: int = 2_000_000, nthreads: int = 0):
        super().__init__(robot)
        import open3d as o3d  # heavy import, only for this backend

        self._o3d = o3d
        if not (math.isfinite(near) and near >= 0):
            raise InputError(f"renderer near plane must be finite and >= 0, got {near}")
        self.near = float(near)
        self.ambient = float(ambient)
        self.max_range = float(max_range)
        self.max_rays = int(max_rays)
        self.nthreads = int(nthreads)

        L = len(self.link_names)
        index = {name: i for i, name in enumerate(self.link_names)}
        verts: list[list[np.ndarray]] = [[] for _ in range(L)]
        faces: list[list[np.ndarray]] = [[] for _ in range(L)]
        colours: list[list[np.ndarray]] = [[] for _ in range(L)]
        counts = [0] * L
        for mesh in robot.visual_meshes:
            i = index[mesh.link]
            verts[i].append(np.asarray(mesh.vertices, dtype=np.float64))
            faces[i].append(np.asarray(mesh.faces, dtype=np.int64) + counts[i])
            colours[i].append(np.broadcast_to(np.asarray(mesh.rgba[:3], np.float32), (len(mesh.faces), 3)))
            counts[i] += len(mesh.vertices)
        link_verts = [np.concatenate(v) for v in verts]
        link_faces = [np.concatenate(f) for f in faces]

        lo = np.stack([v.min(0) for v in link_verts])
        hi = np.stack([v.max(0) for v in link_verts])
        corners = np.stack([np.where(np.array([(c >> ax) & 1 for ax in range(3)], bool), hi, lo)
                            for c in range(8)], axis=1)  # (L, 8, 3)
        self._corners = torch.as_tensor(corners, dtype=torch.float64)
        reach = max(float(np.linalg.norm(v, axis=1).max()) for v in link_verts)
        # A ray's path to its own link's hit stays within max_range (+ near plane) of the
        # slot centre, a foreign link lies within `reach` of its own slot centre.
        self.slot_spacing = 2.0 * (self.max_range + reach) + 1.0
        n_axis = max(1, math.ceil(L ** (1 / 3) - 1e-9))
        grid = np.array([(i % n_axis, (i // n_axis) % n_axis, i // (n_axis * n_axis)) for i in range(L)])
        self._slots = torch.as_tensor(grid * self.slot_spacing, dtype=torch.float64)  # (L, 3)

        scene = o3d.t.geometry.RaycastingScene(nthreads=self.nthreads)
        for i in range(L):
            v = (link_verts[i] + self._slots[i].numpy()).astype(np.float32)
            gid = scene.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(link_faces[i].astype(np.uint32)))
            if gid != i:  # pragma: no cover - Open3D numbers geometries in insertion order
                raise RuntimeError(f"Open3D returned geometry id {gid} for link {i}")
        self._scene = scene
        tri_counts = [len(f) for f in link_faces]
        self._tri_offset = torch.as_tensor(np.concatenate([[0], np.cumsum(tri_counts)[:-1]]), dtype=torch.long)
        self._tri_colour = torch.as_tensor(np.concatenate([np.concatenate(c) for c in colours]))  # (F, 3)
        self.num_triangles = int(sum(tri_counts))
        self._grid_cache: dict = {}
        self._warm = False

    # ------------------------------------------------------------------ helpers

    def _pixel_dirs(self, cam: Camera) -> torch.Tensor:
        """``(H*W, 3)`` float64 camera-frame ray directions ``K^-1 [u, v, 1]`` (z == 1)."""
        key = (cam.K.tobytes(), cam.width, cam.height)
        if key not in self._grid_cache:
            v, u = torch.meshgrid(torch.arange(cam.height, dtype=torch.float64),
                                  torch.arange(cam.width, dtype=torch.float64), indexing="ij")
            pix = torch.stack([u, v, torch.ones_like(u)], dim=-1).reshape(-1, 3)
            d = pix @ torch.linalg.inv(torch.as_tensor(cam.K, dtype=torch.float64)).T
            d[:, 2] = 1.0  # exact: K's last row is (0, 0, 1)
            if len(self._grid_cache) > 32:
                self._grid_cache.clear()
            self._grid_cache[key] = d
        return self._grid_cache[key]

    def _rectangles(self, T_cam_link: torch.Tensor, K: torch.Tensor, hw: torch.Tensor) -> torch.Tensor:
        """Pixel rectangles (inclusive ``u0, u1, v0, v1``) that each link's bounding box can
        cover, shape ``(N, V, L, 4)``; empty where ``u1 < u0``.

        The box (corners in the link frame) is clipped against the plane z = zc in
        front of the camera (zc = near, or 0.1 mm) before projecting, so boxes that
        reach behind the camera still give a tight, correct rectangle.
        """
        zc = max(self.near, 1e-4)
        corners = self._corners.to(T_cam_link)  # (L, 8, 3)
        p = (T_cam_link[..., None, :3, :3] @ corners[..., None])[..., 0] + T_cam_link[..., None, :3, 3]  # (N,V,L,8,3)
        a, b = p[..., _BOX_EDGES[:, 0], :], p[..., _BOX_EDGES[:, 1], :]  # (N,V,L,12,3)
        za, zb = a[..., 2], b[..., 2]
        crosses = (za - zc) * (zb - zc) < 0
        s = ((zc - za) / torch.where(crosses, zb - za, torch.ones_like(za))).clamp(0, 1)
        x = a + s[..., None] * (b - a)
        pts = torch.cat([p, x], dim=-2)  # (N,V,L,20,3)
        ok = torch.cat([p[..., 2] >= zc, crosses], dim=-1)
        z = torch.where(ok, pts[..., 2], torch.ones_like(pts[..., 2]))
        Kb = K[None, :, None]  # (1, V, 1, 3, 3)
        uvw = (Kb[..., None, :, :] @ pts[..., None])[..., 0]
        uv = uvw[..., :2] / z[..., None]
        big = torch.finfo(uv.dtype).max
        umin = torch.where(ok, uv[..., 0], big).amin(-1)
        umax = torch.where(ok, uv[..., 0], -big).amax(-1)
        vmin = torch.where(ok, uv[..., 1], big).amin(-1)
        vmax = torch.where(ok, uv[..., 1], -big).amax(-1)
        any_ok = ok.any(-1)
        H = hw[:, 0][None, :, None].to(uv)
        W = hw[:, 1][None, :, None].to(uv)
        # One pixel of margin: the box is conservative anyway, rounding must not be.
        u0 = torch.floor(torch.minimum(umin.clamp(min=-1.0), W)) - 1
        u1 = torch.ceil(torch.minimum(umax.clamp(min=-1.0), W)) + 1
        v0 = torch.floor(torch.minimum(vmin.clamp(min=-1.0), H)) - 1
        v1 = torch.ceil(torch.minimum(vmax.clamp(min=-1.0), H)) + 1
        u0, v0 = u0.clamp(min=0), v0.clamp(min=0)
        u1, v1 = torch.minimum(u1, W - 1), torch.minimum(v1, H - 1)
        rect = torch.stack([u0, u1, v0, v1], dim=-1).long()
        rect[~any_ok] = torch.tensor([0, -1, 0, -1])
        return rect

    # ------------------------------------------------------------------ render

    def render_link_poses(self, link_poses: Mapping[str, torch.Tensor],
                          cameras: Mapping[str, Camera]) -> dict[str, RenderOutput]:
        names = list(cameras)
        cams = [cameras[n] for n in names]
        ref = link_poses[self.link_names[0]]
        batch = tuple(ref.shape[:-2])
        device = ref.device
        N = int(np.prod(batch)) if batch else 1
        T_wl = torch.stack([link_poses[n].reshape(N, 4, 4) for n in self.link_names], dim=1).to(
            "cpu", torch.float64)  # (N, L, 4, 4)
        poses64 = {k: v.reshape(N, 4, 4).to("cpu", torch.float64) for k, v in link_poses.items()}
        T_wc = torch.stack([c.pose(poses64, batch_shape=(N,), dtype=torch.float64) for c in cams], dim=1)
        if not torch.isfinite(T_wc).all():
            raise InputError("render: non-finite camera pose")

        outputs = {n: {"depth": torch.zeros(N, c.height, c.width, dtype=torch.float32),
                       "link": torch.full((N, c.height, c.width), -1, dtype=torch.int16),
                       "rgb": torch.zeros(N, c.height, c.width, 3, dtype=torch.uint8)}
                   for n, c in zip(names, cams)}
        if N:
            K = torch.stack([torch.as_tensor(c.K, dtype=torch.float64) for c in cams])
            hw = torch.tensor([[c.height, c.width] for c in cams])
            dirs = [self._pixel_dirs(c) for c in cams]
            T_cam_link = _rigid_inverse(T_wc)[:, :, None] @ T_wl[:, None]  # (N, V, L, 4, 4)
            rect = self._rectangles(T_cam_link, K, hw)
            area = ((rect[..., 1] - rect[..., 0] + 1).clamp(min=0) * (rect[..., 3] - rect[..., 2] + 1).clamp(min=0))
            rays_per_frame = area.sum(dim=(1, 2))
            start = 0
            while start < N:  # frame chunks of at most max_rays rays (at least one frame)
                stop = start + 1
                total = int(rays_per_frame[start])
                while stop < N and total + int(rays_per_frame[stop]) <= self.max_rays:
                    total += int(rays_per_frame[stop])
                    stop += 1
                self._render_chunk(start, stop, T_cam_link, rect, area, dirs, cams, names, outputs)
                start = stop

        result = {}
        for n, c in zip(names, cams):
            o = outputs[n]
            shape = (*batch, c.height, c.width)
            depth = o["depth"].reshape(shape).to(device)
            result[n] = RenderOutput(rgb=o["rgb"].reshape(*shape, 3).to(device), mask=depth > 0,
                                     depth=depth, link_id=o["link"].reshape(shape).to(device))
        return result

    def _render_chunk(self, start: int, stop: int, T_cam_link: torch.Tensor, rect: torch.Tensor,
                      area: torch.Tensor, dirs: list[torch.Tensor], cams: list[Camera], names: list[str],
                      outputs: dict) -> None:
        n, V, L = stop - start, len(cams), len(self.link_names)
        rect = rect[start:stop].reshape(-1, 4)
        area = area[start:stop].reshape(-1)
        T_lc = _rigid_inverse(T_cam_link[start:stop]).reshape(-1, 4, 4)  # camera in link frame
        keep = torch.nonzero(area > 0)[:, 0]
        if len(keep) == 0:
            return
        rect, area, T_lc = rect[keep], area[keep], T_lc[keep]
        b_idx = keep // (V * L)
        v_idx = (keep // L) % V
        l_idx = keep % L

        dist = T_lc[:, :3, 3].norm(dim=-1)
        if float(dist.max()) > self.max_range:
            i = int(dist.argmax())
            raise InputError(f"camera {names[int(v_idx[i])]!r} is {float(dist[i]):.1f} m from link "
                             f"{self.link_names[int(l_idx[i])]!r}, beyond the renderer's max_range "
                             f"{self.max_range} m (make the renderer with a larger max_range)")

        # Per rectangle: ray direction in the link frame = A @ [u, v, 1] with A = R_lc K^-1.
        # Pixel directions come from the cached grids (exactly what backproject uses).
        widths = torch.tensor([c.width for c in cams])
        hws = torch.tensor([c.width * c.height for c in cams])
        dir_base = torch.cumsum(torch.cat([torch.zeros(1, dtype=torch.long), hws[:-1]]), 0)
        all_dirs = torch.cat(dirs)  # (sum HW, 3) float64
        rid = torch.repeat_interleave(torch.arange(len(keep)), area)
        local = torch.arange(len(rid)) - torch.repeat_interleave(torch.cumsum(area, 0) - area, area)
        rw = (rect[:, 1] - rect[:, 0] + 1)[rid]
        u = rect[rid, 0] + local % rw
        v = rect[rid, 2] + local // rw
        vr = v_idx[rid]
        pix = v * widths[vr] + u
        d_cam = all_dirs[dir_base[vr] + pix].to(torch.float32)
        R = T_lc[:, :3, :3].to(torch.float32)
        d_link = (R[rid] @ d_cam[:, :, None])[:, :, 0]
        origin = (T_lc[:, :3, 3] + self._slots[l_idx]).to(torch.float32)[rid]
        if self.near > 0:
            origin = origin + self.near * d_link
        rays = torch.cat([origin, d_link], dim=1).contiguous()

        o3c = self._o3d.core
        hit = self._scene.cast_rays(o3c.Tensor.from_numpy(rays.numpy()), nthreads=self.nthreads)
        t_hit = torch.from_numpy(hit["t_hit"].numpy())
        gid = torch.from_numpy(hit["geometry_ids"].numpy().astype(np.int64))
        lr = l_idx[rid]
        valid = torch.nonzero((gid == lr) & torch.isfinite(t_hit))[:, 0]
        if len(valid) == 0:
            return
        depth = t_hit[valid] + self.near

        # z-buffer over links: flat output index (frame, view, pixel) -> nearest hit.
        frame_hw = hws.to(torch.long)
        view_base = torch.cumsum(torch.cat([torch.zeros(1, dtype=torch.long), n * frame_hw[:-1]]), 0)
        rv = vr[valid]
        out_idx = view_base[rv] + b_idx[rid[valid]] * frame_hw[rv] + pix[valid]
        size = int(n * frame_hw.sum())
        zbuf = torch.full((size,), math.inf, dtype=torch.float32)
        zbuf.scatter_reduce_(0, out_idx, depth, "amin")
        win = depth == zbuf[out_idx]
        order = torch.arange(len(valid))
        winner = torch.full((size,), -1, dtype=torch.long)
        winner.scatter_reduce_(0, out_idx[win], order[win], "amax")
        px = torch.nonzero(winner >= 0)[:, 0]
        w = winner[px]  # index into `valid`
        ray = valid[w]
        link = lr[ray]
        prim = torch.from_numpy(hit["primitive_ids"].numpy().astype(np.int64))[ray]
        normal = torch.from_numpy(hit["primitive_normals"].numpy())[ray]
        d = d_link[ray]
        cos = (normal * d).sum(-1).abs() / (normal.norm(dim=-1) * d.norm(dim=-1)).clamp(min=1e-12)
        shade = self.ambient + (1.0 - self.ambient) * cos
        colour = self._tri_colour[self._tri_offset[link] + prim] * shade[:, None]
        rgb = (colour * 255.0 + 0.5).clamp(0, 255).to(torch.uint8)

        zflat = torch.zeros(size, dtype=torch.float32)
        zflat[px] = depth[w]
        lflat = torch.full((size,), -1, dtype=torch.int16)
        lflat[px] = link.to(torch.int16)
        cflat = torch.zeros(size, 3, dtype=torch.uint8)
        cflat[px] = rgb
        for k, (name, cam) in enumerate(zip(names, cams)):
            s = slice(int(view_base[k]), int(view_base[k] + n * frame_hw[k]))
            o = outputs[name]
            o["depth"][start:stop] = zflat[s].view(n, cam.height, cam.width)
            o["link"][start:stop] = lflat[s].view(n, cam.height, cam.width)
            o["rgb"][start:stop] = cflat[s].view(n, cam.height, cam.width, 3)


BACKENDS = {"open3d": RaycastRenderer}


def make_renderer(robot: RobotModel, backend: str = "open3d", **options) -> Renderer:
    """A renderer for ``robot`` by backend name (``"open3d"``: CPU ray casting, the default)."""
    if backend not in BACKENDS:
        raise InputError(f"unknown renderer backend {backend!r}; available: {sorted(BACKENDS)}")
    return BACKENDS[backend](robot, **options)
