"""A triangle rasteriser in torch: the motion images on any torch device (CPU or CUDA).

:class:`RasterRenderer` draws what :class:`~imac_data.core.render.RaycastRenderer` casts, with the same
sampling (a pixel is its centre's ray) and the same shading, so either can build a dataset. Per view and
batch of frames it

1. puts every vertex in the camera frame (one matmul per link pose);
2. bounds every triangle's projection (its part in front of the near plane) by the pixel centres it can
   cover, and lists those (triangle, pixel) candidates;
3. tests each candidate's ray against its triangle in homogeneous form: with ``M`` the triangle's
   camera-frame vertices as columns and ``d = K^-1 [u, v, 1]``, ``w = adj(M) d`` are its barycentric
   coordinates scaled by ``det(M) / t``, so the ray hits iff every ``w`` has the sign of ``det(M)``,
   at z-depth ``t = det(M) / sum(w)``;
4. keeps the nearest hit per pixel (one ``scatter_reduce`` of depth and triangle packed in an int64)
   and shades it: ``colour * (ambient + (1 - ambient) |cos(normal, ray)|)``.

Nothing is per-pixel Python; the work is elementwise over candidates, which a GPU does in bulk
(docs/dataset-format.md, "How the robot is rendered").
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch

from imac_data.core.cameras import Camera
from imac_data.core.render.base import Renderer, RenderOutput, check_device, rigid_inverse
from imac_data.core.robot.model import RobotModel
from imac_data.errors import InputError

__all__ = ["RasterRenderer"]

_LOW31 = (1 << 31) - 1
_EMPTY = torch.iinfo(torch.int64).max


class RasterRenderer(Renderer):
    """Renderer that rasterises the posed links' triangles with torch on ``device``.

    ``near``: geometry in front of the plane z = near (metres) is drawn, 0 = everything in front of the
    camera. ``ambient``: as :class:`~imac_data.core.render.RaycastRenderer`. ``max_candidates``: (triangle,
    pixel) tests at a time, more are split by frames (about 100 bytes each); ``group_elements``: frames at
    a time times triangles, for the per-triangle bounds (about 100 bytes each). ``nthreads`` is taken for
    the other backend's sake and unused (torch's own threads apply).
    """

    def __init__(self, robot: RobotModel, *, near: float = 0.0, ambient: float = 0.3,
                 device: str | torch.device = "cpu", max_candidates: int | None = None,
                 group_elements: int | None = None, nthreads: int = 0):
        super().__init__(robot)
        for name, value, ok in (("near", near, near >= 0), ("ambient", ambient, 0 <= ambient <= 1)):
            if not (math.isfinite(value) and ok):
                raise InputError(f"renderer {name} out of range: {value}")
        self.near = float(near)
        self.ambient = float(ambient)
        self.device = torch.device(device)
        if self.device.type == "cuda":
            check_device(str(device))
        on_gpu = self.device.type == "cuda"
        self.max_candidates = int(max_candidates or (1 << 25 if on_gpu else 1 << 20))
        self.group_elements = int(group_elements or (1 << 24 if on_gpu else 1 << 20))

        index = {name: i for i, name in enumerate(self.link_names)}
        per_link = [[] for _ in self.link_names]  # vertices sorted by link: one matmul per link moves them
        for mesh in robot.visual_meshes:
            per_link[index[mesh.link]].append(mesh)
        verts, faces, colours, count = [], [], [], 0
        self._link_spans = []
        for meshes in per_link:
            first = count
            for mesh in meshes:
                verts.append(np.asarray(mesh.vertices, np.float64))
                faces.append(np.asarray(mesh.faces, np.int64) + count)
                colours.append(np.broadcast_to(np.asarray(mesh.rgba[:3], np.float32), (len(mesh.faces), 3)))
                count += len(mesh.vertices)
            self._link_spans.append((first, count))
        if not verts:
            raise InputError(f"robot {robot.config.name!r} ({robot.config.urdf_path}) has no visual geometry to render")
        v, f = np.concatenate(verts), np.concatenate(faces)
        vertex_link = np.repeat(np.arange(len(per_link)), [b - a for a, b in self._link_spans])
        normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        dev = self.device
        self._vertices = torch.as_tensor(v, dtype=torch.float32, device=dev)
        self._faces = torch.as_tensor(f, device=dev)
        self._face_link = torch.as_tensor(vertex_link[f[:, 0]], device=dev)
        self._normals = torch.as_tensor(normal, dtype=torch.float32, device=dev)
        self._colours = torch.as_tensor(255.0 * np.concatenate(colours), dtype=torch.float32, device=dev)
        self.num_triangles = len(f)

    # ------------------------------------------------------------------ render

    def render_link_poses(self, link_poses: Mapping[str, torch.Tensor],
                          cameras: Mapping[str, Camera]) -> dict[str, RenderOutput]:
        ref = link_poses[self.link_names[0]]
        batch, out_device = tuple(ref.shape[:-2]), ref.device
        N = math.prod(batch)

        def pose(name):
            return link_poses[name].detach().reshape(N, 4, 4).to(self.device, torch.float64)

        T_wl = torch.stack([pose(n) for n in self.link_names], dim=1)  # (N, L, 4, 4)
        result = {}
        for name, cam in cameras.items():
            if cam.is_mounted:
                mount = T_wl[:, self.link_names.index(cam.link)] if cam.link in self.link_names else pose(cam.link)
                T_wc = mount @ torch.as_tensor(cam.T_link_cam, dtype=torch.float64, device=self.device)
            else:
                T_wc = torch.as_tensor(cam.T_world_cam, dtype=torch.float64, device=self.device).expand(N, 4, 4)
            if not torch.isfinite(T_wc).all():
                raise InputError("render: non-finite camera pose")
            T_cl = rigid_inverse(T_wc)[:, None] @ T_wl  # (N, L, 4, 4) link -> camera
            H, W = cam.height, cam.width
            rgb = torch.zeros((N, H, W, 3), dtype=torch.uint8, device=self.device)
            depth = torch.zeros((N, H, W), dtype=torch.float32, device=self.device)
            link = torch.full((N, H, W), -1, dtype=torch.int16, device=self.device)
            step = max(1, self.group_elements // self.num_triangles)
            for lo in range(0, N, step):
                hi = min(N, lo + step)
                self._draw(T_cl[lo:hi], cam, rgb[lo:hi], depth[lo:hi], link[lo:hi])
            shape = (*batch, H, W)
            out = RenderOutput(rgb=rgb.reshape(*shape, 3), mask=(link >= 0).reshape(shape),
                               depth=depth.reshape(shape), link_id=link.reshape(shape))
            result[name] = RenderOutput(*(x.to(out_device) for x in (out.rgb, out.mask, out.depth, out.link_id)))
        return result

    # ------------------------------------------------------------------ helpers

    def _camera_frame(self, T_cl: torch.Tensor) -> torch.Tensor:
        """Vertices in the camera frame ``(n, V, 3)`` float32 from link->camera poses ``(n, L, 4, 4)``."""
        T = T_cl.to(torch.float32)
        p = torch.empty((T.shape[0], len(self._vertices), 3), dtype=torch.float32, device=self.device)
        for li, (a, b) in enumerate(self._link_spans):
            if b > a:
                torch.add(self._vertices[a:b] @ T[:, li, :3, :3].transpose(-1, -2), T[:, li, None, :3, 3], out=p[:, a:b])
        return p

    def _bounds(self, p: torch.Tensor, cam: Camera) -> tuple[torch.Tensor, ...]:
        """Per (frame, triangle) of vertices ``p`` (camera frame): the first pixel column and row its part in
        front of the near plane can cover, how many columns and rows (0 = none), and its projection as a
        convex polygon of 4 corners ``(n, F, 4, 2)`` (a triangle repeats its last corner; a triangle partly
        behind the plane is clipped by it first)."""
        zc = max(self.near, 1e-5)
        K = torch.as_tensor(cam.K, dtype=torch.float32, device=self.device)

        def project(x):
            z = torch.where(x[..., 2] >= zc, x[..., 2], torch.ones_like(x[..., 2]))
            return torch.stack([(K[0, 0] * x[..., 0] + K[0, 1] * x[..., 1]) / z + K[0, 2],
                                K[1, 1] * x[..., 1] / z + K[1, 2]], -1)

        front = p[..., 2] >= zc
        corners = project(p)[:, self._faces]  # (n, F, 3, 2)
        poly = torch.cat([corners, corners[:, :, 2:]], dim=2)
        n_front = front[:, self._faces].sum(-1)
        part = torch.nonzero((n_front > 0) & (n_front < 3), as_tuple=True)
        if len(part[0]):  # partly behind: walk the edges, keeping front corners and where edges cross z = zc
            tri = p[part[0][:, None], self._faces[part[1]]]  # (m, 3, 3)
            a, b = tri, tri.roll(-1, dims=1)
            s = (zc - a[..., 2]) / (b[..., 2] - a[..., 2])
            crossing = a + s[..., None] * (b - a)
            walk = torch.stack([tri, crossing], dim=2).reshape(-1, 6, 3)  # corner 0, edge 01, corner 1, ...
            keep = torch.stack([a[..., 2] >= zc, (a[..., 2] - zc) * (b[..., 2] - zc) < 0], dim=2).reshape(-1, 6)
            slot = torch.arange(6, device=self.device)
            order = torch.argsort(slot + 6 * (~keep).to(torch.int64), dim=1)[:, :4]  # kept slots first, in order
            order[:, 3] = torch.where(keep.sum(1) == 4, order[:, 3], order[:, 2])  # a triangle: repeat its last
            poly[part] = project(walk.gather(1, order[..., None].expand(-1, -1, 3)))
        lo, hi = poly.amin(2), poly.amax(2)
        lo[n_front == 0], hi[n_front == 0] = 1.0, 0.0  # wholly behind: empty
        size = torch.tensor([cam.width, cam.height], dtype=torch.float32, device=self.device)
        first = lo.clamp(min=0.0).minimum(size).ceil()
        last = hi.minimum(size - 1).clamp(min=-1.0).floor()
        span = (last - first + 1).clamp(min=0).to(torch.int64)
        first = first.to(torch.int64)
        return first[..., 0], first[..., 1], span[..., 0], span[..., 1], poly

    def _spans(self, u0, v0, cols, rows, poly) -> tuple[torch.Tensor, ...]:
        """Row by row of each polygon's bounds (rows of ``u0`` ...), the columns between where the row's
        centre line meets its edges, rounded outwards with 1e-3 px to spare for float rounding (the hit test
        decides). Returns per line: its polygon, row, first column and number of columns."""
        dev = self.device
        line_of = torch.repeat_interleave(torch.arange(len(u0), device=dev), rows)
        y = v0[line_of] + torch.arange(len(line_of), device=dev) - (torch.cumsum(rows, 0) - rows)[line_of]
        a = poly[line_of]  # (m, 4, 2)
        b = a.roll(-1, dims=1)
        yf = y.to(torch.float32)[:, None]
        dv = b[..., 1] - a[..., 1]
        t = ((yf - a[..., 1]) / torch.where(dv == 0, torch.ones_like(dv), dv)).clamp(0.0, 1.0)
        x = a[..., 0] + t * (b[..., 0] - a[..., 0])
        eps = 1e-3
        meets = (yf >= torch.minimum(a[..., 1], b[..., 1]) - eps) & (yf <= torch.maximum(a[..., 1], b[..., 1]) + eps)
        inf = torch.tensor(float("inf"), device=dev)
        left = torch.where(meets, x, inf).amin(1)
        right = torch.where(meets, x, -inf).amax(1)
        first, last = u0[line_of], u0[line_of] + cols[line_of] - 1
        c0 = (left - eps).ceil().clamp(min=-1, max=1 << 30).to(torch.int64).maximum(first)
        c1 = (right + eps).floor().clamp(min=-2, max=1 << 30).to(torch.int64).minimum(last)
        return line_of, y, c0, (c1 - c0 + 1).clamp(min=0)

    def _draw(self, T_cl: torch.Tensor, cam: Camera, rgb: torch.Tensor, depth: torch.Tensor,
              link: torch.Tensor) -> None:
        """Rasterise frames ``T_cl`` (n, L, 4, 4) of one camera into the output slices."""
        n, H, W = T_cl.shape[0], cam.height, cam.width
        p = self._camera_frame(T_cl)
        u0, v0, cols, rows, poly = self._bounds(p, cam)
        ft = torch.nonzero((cols * rows).reshape(-1), as_tuple=True)[0]  # every (frame, triangle) in view
        if len(ft) == 0:
            return
        line_of, y, c0, width = self._spans(u0.reshape(-1)[ft], v0.reshape(-1)[ft], cols.reshape(-1)[ft],
                                            rows.reshape(-1)[ft], poly.reshape(-1, 4, 2)[ft])
        total = int(width.sum())
        if total > self.max_candidates and n > 1:  # too many tests at once: half the frames at a time
            h = n // 2
            for lo, hi in ((0, h), (h, n)):
                self._draw(T_cl[lo:hi], cam, rgb[lo:hi], depth[lo:hi], link[lo:hi])
            return
        cand_line = torch.repeat_interleave(torch.arange(len(line_of), device=self.device), width)
        px = c0[cand_line] + torch.arange(total, device=self.device) - (torch.cumsum(width, 0) - width)[cand_line]
        owner, py = line_of[cand_line], y[cand_line]  # each candidate's row of ft, and its pixel
        if len(owner) == 0:
            return
        frame, face = ft // self.num_triangles, ft % self.num_triangles

        # adj(M): rows are cross products of the columns; det(M) = p0 . (p1 x p2)
        tri = p[frame[:, None], self._faces[face]]  # (m, 3, 3): corner, xyz
        p0, p1, p2 = tri[:, 0].double(), tri[:, 1].double(), tri[:, 2].double()
        adj = torch.stack([torch.linalg.cross(p1, p2), torch.linalg.cross(p2, p0), torch.linalg.cross(p0, p1)], 1)
        det = (p0 * adj[:, 0]).sum(-1)
        Kinv = torch.as_tensor(np.linalg.inv(cam.K), dtype=torch.float64, device=self.device)
        E = (adj @ Kinv).to(torch.float32)  # (m, 3, 3): w = E [u, v, 1]
        sign = torch.sign(det).to(torch.float32)
        uf, vf = px.to(torch.float32), py.to(torch.float32)
        Eo = E[owner] * sign[owner, None, None]
        w = Eo[..., 0] * uf[:, None] + Eo[..., 1] * vf[:, None] + Eo[..., 2]  # (total, 3), >= 0 inside
        s = w.sum(-1)
        t = det.abs().to(torch.float32)[owner] / s
        hit = (w >= 0).all(-1) & (s > 0) & (t >= self.near) & torch.isfinite(t)
        idx = torch.nonzero(hit, as_tuple=True)[0]
        if len(idx) == 0:
            return
        # nearest hit per pixel: positive float32 depths order as their bit patterns
        pix = (frame[owner[idx]] * H + py[idx]) * W + px[idx]
        key = (t[idx].view(torch.int32).to(torch.int64) << 31) | owner[idx]
        best = torch.full((n * H * W,), _EMPTY, dtype=torch.int64, device=self.device)
        best.scatter_reduce_(0, pix, key, reduce="amin")
        drawn = torch.nonzero(best != _EMPTY, as_tuple=True)[0]
        win = best[drawn] & _LOW31  # the winning candidate's (frame, triangle) row
        zbits = (best[drawn] >> 31).to(torch.int32)
        f_win, face_win = frame[win], face[win]

        # shade: |cos| between the face normal (camera frame) and the pixel's ray
        lk = self._face_link[face_win]
        R = T_cl[f_win, lk, :3, :3].to(torch.float32)
        nrm = (R @ self._normals[face_win][:, :, None])[..., 0]
        yy, xx = (drawn % (H * W)) // W, drawn % W
        ray = (Kinv.to(torch.float32) @ torch.stack([xx.to(torch.float32), yy.to(torch.float32),
                                                      torch.ones_like(xx, dtype=torch.float32)], 0)).T
        cos = (nrm * ray).sum(-1).abs() / (ray * ray).sum(-1).sqrt()
        colour = self._colours[face_win] * (self.ambient + (1.0 - self.ambient) * cos)[:, None] + 0.5
        rgb.view(-1, 3)[drawn] = colour.to(torch.uint8)
        depth.view(-1)[drawn] = zbits.view(torch.float32)
        link.view(-1)[drawn] = lk.to(torch.int16)
