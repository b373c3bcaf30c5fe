"""CPU ray casting of the robot: Open3D's ``RaycastingScene`` built once, every link in its own frame
(``docs/dataset-format.md``, "How the robot is rendered")."""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping

import numpy as np
import torch

from imac_data.core.cameras import Camera
from imac_data.core.render.base import Renderer, RenderOutput, rigid_inverse
from imac_data.core.robot.model import RobotModel
from imac_data.errors import InputError

__all__ = ["RaycastRenderer"]


# The 12 edges of a box given by its 8 corners (corner c has bit i set = max along axis i).
_BOX_EDGES = np.array([(a, a | (1 << ax)) for a in range(8) for ax in range(3) if not a & (1 << ax)])


def _convex_hull(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(n, 3)`` and edges ``(m, 2)`` of the convex hull of a point set; its
    bounding box where the hull is degenerate (flat or collinear geometry)."""
    import trimesh

    try:
        hull = trimesh.convex.convex_hull(vertices)
        if len(hull.vertices) >= 4 and len(hull.edges_unique):
            return np.asarray(hull.vertices, dtype=np.float64), np.asarray(hull.edges_unique, dtype=np.int64)
    except Exception:  # qhull refuses degenerate input
        pass
    lo, hi = vertices.min(0), vertices.max(0)
    bits = np.array([[(c >> ax) & 1 for ax in range(3)] for c in range(8)], dtype=bool)
    return np.where(bits, hi, lo), _BOX_EDGES


class RaycastRenderer(Renderer):
    """CPU renderer: Open3D ``RaycastingScene`` built once with each link in its own frame.

    ``near``: rays start on the plane z = near (metres) in front of each camera; 0 = no
    clipping. ``ambient``: shade = colour * (ambient + (1 - ambient) |cos(normal, ray)|).
    ``max_range``: the largest camera-to-link distance (m) supported (sets the slot
    spacing; float32 resolution of the slots stays far below 0.1 mm).
    ``max_rays``: rays per Embree call; longer batches are cast frame-chunk by chunk.
    ``nthreads``: Embree threads, 0 = all cores.

    Internals are numpy (single-threaded, predictable on a busy 2-core machine) around
    one multi-threaded Embree call per chunk; torch only at the boundary.
    """

    def __init__(self, robot: RobotModel, *, near: float = 0.0, ambient: float = 0.3,
                 max_range: float = 10.0, max_rays: int = 1 << 20, nthreads: int = 0):
        super().__init__(robot)
        import open3d as o3d  # heavy import, only for this backend

        self._o3d = o3d
        for name, value, ok in (("near", near, near >= 0), ("ambient", ambient, 0 <= ambient <= 1),
                                ("max_range", max_range, max_range > 0), ("max_rays", max_rays, max_rays > 0)):
            if not (math.isfinite(value) and ok):
                raise InputError(f"renderer {name} out of range: {value}")
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

        if not link_verts:
            raise InputError(f"robot {robot.config.name!r} ({robot.config.urdf_path}) has no visual geometry to render")
        # Culling volume of each link: the convex hull of its visual vertices (link frame),
        # padded to a common size by repeating a vertex / an edge.
        hulls = [_convex_hull(v) for v in link_verts]
        nv, ne = max(len(h[0]) for h in hulls), max(len(h[1]) for h in hulls)
        self._hull_v = np.stack([np.concatenate([hv, np.repeat(hv[-1:], nv - len(hv), 0)]) for hv, _ in hulls])
        self._hull_e = np.stack([np.concatenate([he, np.repeat(he[-1:], ne - len(he), 0)]) for _, he in hulls])
        reach = max(float(np.linalg.norm(v, axis=1).max()) for v in link_verts)
        # A ray's path to its own link's hit stays within max_range (+ near plane) of the
        # slot centre, a foreign link lies within `reach` of its own slot centre.
        self.slot_spacing = 2.0 * (self.max_range + reach) + 1.0
        n_axis = max(1, math.ceil(L ** (1 / 3) - 1e-9))
        grid = np.array([(i % n_axis, (i // n_axis) % n_axis, i // (n_axis * n_axis)) for i in range(L)])
        # centred on the origin: the smaller the coordinates, the finer float32 resolves them
        self._slots = (grid - (n_axis - 1) / 2) * self.slot_spacing  # (L, 3)

        scene = o3d.t.geometry.RaycastingScene(nthreads=self.nthreads)
        for i in range(L):
            v = (link_verts[i] + self._slots[i]).astype(np.float32)
            gid = scene.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(link_faces[i].astype(np.uint32)))
            if gid != i:  # pragma: no cover - Open3D numbers geometries in insertion order
                raise RuntimeError(f"Open3D returned geometry id {gid} for link {i}")
        # Embree builds the BVH lazily at the first cast: do it now, not in the first render.
        scene.cast_rays(o3d.core.Tensor(np.array([[0, 0, 0, 0, 0, 1]], np.float32)))
        self._scene = scene
        tri_counts = [len(f) for f in link_faces]
        self._tri_offset = np.concatenate([[0], np.cumsum(tri_counts)[:-1]]).astype(np.int64)
        # per-triangle colour, pre-scaled to 0..255
        self._tri_colour = 255.0 * np.concatenate([np.concatenate(c) for c in colours]).astype(np.float32)
        self.num_triangles = int(sum(tri_counts))
        self._rays = np.empty((0, 6), dtype=np.float32)
        self._pix = np.empty(0, dtype=np.int64)
        self._kernel = np.ones((3, 3), np.uint8)
        self._lock = threading.Lock()  # the ray workspace is shared: one render at a time

    # ------------------------------------------------------------------ helpers

    def _footprints(self, T_cam_link: np.ndarray, K: np.ndarray, hw: np.ndarray) -> list[tuple]:
        """Where each link can appear: for every (frame, view, link) whose convex hull reaches
        in front of the camera, ``(frame, view, link, u0, v0, mask, count)`` with ``mask`` a boolean
        ``(h, w)`` block of the image at ``(u0, v0)`` (the hull's silhouette grown by one pixel)
        and ``count`` its number of pixels.

        The hull is clipped against the plane z = zc (the near plane, or 1 mm) before
        projecting: its silhouette is the 2D convex hull of the projected vertices in front
        of the plane and of the points where hull edges cross it, a superset of the link's.
        """
        import cv2

        zc = max(self.near, 1e-3)
        R, t = T_cam_link[..., :3, :3], T_cam_link[..., :3, 3]
        p = self._hull_v @ np.swapaxes(R, -1, -2) + t[..., None, :]  # (N, V, L, P, 3) hull in camera frame
        front = p[..., 2] >= zc
        z = np.where(front, p[..., 2], 1.0)
        fx, fy, cx, cy, skew = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 0, 1]
        shp = (1, -1, 1, 1)
        xn, yn = p[..., 0] / z, p[..., 1] / z
        uv = np.stack([fx.reshape(shp) * xn + skew.reshape(shp) * yn + cx.reshape(shp),
                       fy.reshape(shp) * yn + cy.reshape(shp)], axis=-1)  # (N, V, L, P, 2)
        n_front = front.sum(-1)
        out = []
        for n, v, li in zip(*np.nonzero(n_front)):
            q = uv[n, v, li]
            if n_front[n, v, li] < front.shape[-1]:  # partly behind the plane: add the edge crossings
                q = q[front[n, v, li]]
                e = self._hull_e[li]
                pa, pb = p[n, v, li, e[:, 0]], p[n, v, li, e[:, 1]]
                cross = (pa[:, 2] - zc) * (pb[:, 2] - zc) < 0
                pa, pb = pa[cross], pb[cross]
                x = pa + ((zc - pa[:, 2]) / (pb[:, 2] - pa[:, 2]))[:, None] * (pb - pa)
                q = np.concatenate([q, (x / x[:, 2:]) @ K[v, :2].T])
            H, W = hw[v]
            lo, hi = q.min(0), q.max(0)
            u0, v0 = max(int(np.floor(lo[0])) - 1, 0), max(int(np.floor(lo[1])) - 1, 0)
            u1, v1 = min(int(np.ceil(hi[0])) + 1, W - 1), min(int(np.ceil(hi[1])) + 1, H - 1)
            if u1 < u0 or v1 < v0:
                continue
            mask = np.zeros((v1 - v0 + 1, u1 - u0 + 1), np.uint8)
            poly = cv2.convexHull(np.round((q - (u0, v0)) * 16).astype(np.int32))  # 1/16 px fixed point
            cv2.fillConvexPoly(mask, poly, 1, lineType=cv2.LINE_8, shift=4)
            mask = cv2.dilate(mask, self._kernel)  # one pixel of margin: rounding must stay conservative
            out.append((int(n), int(v), int(li), u0, v0, mask.view(bool), cv2.countNonZero(mask)))
        return out

    def _workspace(self, n: int) -> np.ndarray:
        """A reused ``(n, 6)`` float32 ray buffer. Fresh large allocations are costly here:
        first-touch page faults cost more than the arithmetic that fills them."""
        if self._rays.shape[0] < n:
            self._rays = np.empty((max(n, 2 * self._rays.shape[0]), 6), dtype=np.float32)
        if self._pix.shape[0] < n:
            self._pix = np.empty(max(n, 2 * self._pix.shape[0]), dtype=np.int64)
        return self._rays[:n]

    # ------------------------------------------------------------------ render

    def render_link_poses(self, link_poses: Mapping[str, torch.Tensor],
                          cameras: Mapping[str, Camera]) -> dict[str, RenderOutput]:
        with self._lock:
            return self._render(link_poses, cameras)

    def _render(self, link_poses: Mapping[str, torch.Tensor], cameras: Mapping[str, Camera]) -> dict[str, RenderOutput]:
        names = list(cameras)
        cams = [cameras[n] for n in names]
        ref = link_poses[self.link_names[0]]
        batch = tuple(ref.shape[:-2])
        device = ref.device
        N = math.prod(batch)

        def pose(name):
            return link_poses[name].detach().reshape(N, 4, 4).to("cpu", torch.float64).numpy()

        T_wl = np.stack([pose(n) for n in self.link_names], axis=1)  # (N, L, 4, 4)
        T_wc = np.stack([np.broadcast_to(c.T_world_cam, (N, 4, 4)) if not c.is_mounted
                         else (T_wl[:, self.link_names.index(c.link)] if c.link in self.link_names
                               else pose(c.link)) @ c.T_link_cam for c in cams], axis=1)  # (N, V, 4, 4)
        if not np.isfinite(T_wc).all():
            raise InputError("render: non-finite camera pose")

        # Outputs; depth doubles as the z-buffer while rendering (inf = empty).
        depth = [np.full((N, c.height, c.width), np.inf, dtype=np.float32) for c in cams]
        mask = [np.zeros((N, c.height, c.width), dtype=bool) for c in cams]
        link = [np.full((N, c.height, c.width), -1, dtype=np.int16) for c in cams]
        rgb = [np.zeros((N, c.height, c.width, 3), dtype=np.uint8) for c in cams]
        if N:
            K = np.stack([c.K for c in cams])
            hw = np.array([[c.height, c.width] for c in cams])
            T_cam_link = rigid_inverse(T_wc)[:, :, None] @ T_wl[:, None]  # (N, V, L, 4, 4)
            T_link_cam = rigid_inverse(T_cam_link)
            feet = []
            for i in range(0, N, 16):  # bounded memory for the hull projection
                feet += [(n + i, *rest) for n, *rest in self._footprints(T_cam_link[i:i + 16], K, hw)]
            if feet:
                n, v, li = np.array([f[:3] for f in feet]).T
                dist = np.linalg.norm(T_link_cam[n, v, li, :3, 3], axis=-1)
                if dist.max() > self.max_range:
                    i = int(dist.argmax())
                    raise InputError(f"camera {names[v[i]]!r} is {dist[i]:.1f} m from link "
                                     f"{self.link_names[li[i]]!r} (frame {n[i]}), beyond the renderer's max_range "
                                     f"{self.max_range} m (make the renderer with a larger max_range)")
            # Per (frame, view, link): ray direction in the link frame = A @ [u, v, 1] with
            # A = R_link_cam K^-1 (z component of K^-1 [u, v, 1] is 1, so the hit parameter
            # is camera z-depth); origin = the camera centre in the link frame, in the link's slot.
            A = (T_link_cam[..., :3, :3] @ np.linalg.inv(K)[None, :, None]).astype(np.float32)
            origin = (T_link_cam[..., :3, 3] + self._slots).astype(np.float32)
            counts = np.array([f[6] for f in feet], dtype=np.int64)
            frame_of = np.array([f[0] for f in feet], dtype=np.int64)  # non-decreasing
            per_frame = np.bincount(frame_of, weights=counts, minlength=N)
            first = np.searchsorted(frame_of, np.arange(N + 1))  # feet of frame i: first[i]:first[i+1]
            start = 0
            while start < N:  # chunks of whole frames, at most max_rays rays (at least one frame)
                stop, total = start + 1, per_frame[start]
                while stop < N and total + per_frame[stop] <= self.max_rays:
                    total += per_frame[stop]
                    stop += 1
                i, j = first[start], first[stop]
                if j > i:
                    self._render_chunk(feet[i:j], counts[i:j], A, origin, hw, depth, mask, link, rgb)
                start = stop

        result = {}
        for k, (n, c) in enumerate(zip(names, cams)):
            np.putmask(depth[k], ~mask[k], 0.0)
            shape = (*batch, c.height, c.width)
            out = RenderOutput(rgb=torch.from_numpy(rgb[k]).reshape(*shape, 3),
                               mask=torch.from_numpy(mask[k]).reshape(shape),
                               depth=torch.from_numpy(depth[k]).reshape(shape),
                               link_id=torch.from_numpy(link[k]).reshape(shape))
            if device.type != "cpu":
                out = RenderOutput(*(x.to(device) for x in (out.rgb, out.mask, out.depth, out.link_id)))
            result[n] = out
        return result

    def _render_chunk(self, feet: list[tuple], counts: list[int], A: np.ndarray, origin: np.ndarray,
                      hw: np.ndarray, depth: list[np.ndarray], mask: list[np.ndarray],
                      link: list[np.ndarray], rgb: list[np.ndarray]) -> None:
        """Cast the rays of some footprints (whole frames) in one Embree call and z-buffer them."""
        f0, f1 = feet[0][0], feet[-1][0] + 1
        ends = np.cumsum(counts)
        starts = ends - counts
        total = int(ends[-1]) if len(ends) else 0
        if total == 0:
            return
        rays = self._workspace(total)
        pix = self._pix[:total]
        near = self.near
        # Ray generation, footprint by footprint: pixel (u, v) -> A [u, v, 1] per component
        # (strided 1-D writes; no per-ray gathers of per-footprint data).
        for (n, v, li, u0, v0, foot, _), s, e in zip(feet, starts, ends):
            ys, xs = np.nonzero(foot)
            uu, vv = xs + u0, ys + v0
            W = int(hw[v, 1])
            np.add(vv * W + uu, (n - f0) * int(hw[v, 0]) * W, out=pix[s:e])  # pixel index in frames f0:f1
            uf, vf = uu.astype(np.float32), vv.astype(np.float32)
            a, o = A[n, v, li], origin[n, v, li]
            for k in range(3):
                d = rays[s:e, 3 + k]
                np.multiply(uf, a[k, 0], out=d)
                d += vf * a[k, 1]
                d += a[k, 2]
                if near > 0:
                    np.multiply(d, near, out=rays[s:e, k])
                    rays[s:e, k] += o[k]
                else:
                    rays[s:e, k] = o[k]

        hit = self._scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays), nthreads=self.nthreads)
        t_hit = hit["t_hit"].numpy()
        if near > 0:
            t_hit += near
        gid = hit["geometry_ids"].numpy().view(np.int32)  # INVALID_ID (a miss) reads as -1

        # z-buffer over links, footprint by footprint; a hit on a foreign slot is a miss.
        winner = [np.full((f1 - f0, int(h), int(w)), -1, dtype=np.int32) for h, w in hw]  # ray index
        for (n, v, li, *_), s, e in zip(feet, starts, ends):
            zf, wf = depth[v][f0:f1].reshape(-1), winner[v].reshape(-1)
            idx, t = pix[s:e], t_hit[s:e]
            ok = gid[s:e] == li
            ok &= t < zf[idx]
            sel = np.flatnonzero(ok)
            zf[idx[sel]] = t[sel]
            wf[idx[sel]] = sel + s

        # Shade the winning rays only: Lambertian with the light at the camera.
        prim = hit["primitive_ids"].numpy().view(np.int32)
        normal = hit["primitive_normals"].numpy()  # unit length, link frame
        foot_link = np.array([f[2] for f in feet])
        for k in range(len(depth)):
            wv = winner[k].reshape(-1)
            np.greater_equal(winner[k], 0, out=mask[k][f0:f1])
            px = np.flatnonzero(wv >= 0)
            if len(px) == 0:
                continue
            ray = wv[px]
            lk = foot_link[np.searchsorted(ends, ray, side="right")]
            nr = np.take(normal, ray, axis=0)
            dr = np.take(rays, ray, axis=0)
            dot = nr[:, 0] * dr[:, 3] + nr[:, 1] * dr[:, 4] + nr[:, 2] * dr[:, 5]
            dd = dr[:, 3] * dr[:, 3] + dr[:, 4] * dr[:, 4] + dr[:, 5] * dr[:, 5]
            shade = self.ambient + (1.0 - self.ambient) * (np.abs(dot) / np.sqrt(dd))
            colour = np.take(self._tri_colour, self._tri_offset[lk] + np.take(prim, ray), axis=0)
            colour *= shade[:, None]
            colour += 0.5  # round; values stay in [0, 255.5)
            link[k][f0:f1].reshape(-1)[px] = lk
            out = rgb[k][f0:f1].reshape(-1, 3)
            for c in range(3):
                out[px, c] = colour[:, c]
