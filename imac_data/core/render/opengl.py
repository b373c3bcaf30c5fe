"""OpenGL rasterisation of the motion images, headless through EGL (Mesa's llvmpipe on a CPU, a GPU's
driver where there is one).

:class:`GLRenderer` draws what :class:`~imac_data.core.render.RaycastRenderer` casts, with the same sampling
(a pixel is its centre's ray) and the same shading, done in the fragment shader. Two colour attachments carry
each pixel's colour and link (a byte each, packed in 32 bits) and its interpolated camera-frame z; a reversed
float depth buffer keeps the nearest surface. A rasteriser's cost follows the triangles rather than the pixels,
so it pays only from 480x640 on: there a build's render stage takes about 0.74 times the ray caster's CPU
(docs/building.md, "Render: a rasteriser instead of ray casting?").

Each process makes its own EGL context (MuJoCo's, ``mujoco.egl``) at its first render; one render at a time."""

from __future__ import annotations

import atexit
import contextlib
import math
import os
import threading
from collections.abc import Mapping

import numpy as np
import torch

from imac_data.core.cameras import Camera
from imac_data.core.render.base import Renderer, RenderOutput, rigid_inverse
from imac_data.core.robot.model import RobotModel
from imac_data.errors import InputError

__all__ = ["GLRenderer"]

_VERTEX = """
#version 330 core
layout(location = 0) in vec3 position;
layout(location = 1) in int link;
uniform mat4 link_to_camera[{links}];
uniform mat3 K;
uniform vec2 size;
uniform float near;
out float z;
flat out int link_of;
void main() {{
    vec3 p = (link_to_camera[link] * vec4(position, 1.0)).xyz;
    z = p.z;
    link_of = link;
    // pixel (u, v) has its centre at integer coordinates, OpenGL's at half integers; row v is window row v
    float uz = K[0][0] * p.x + K[1][0] * p.y + (K[2][0] + 0.5) * p.z;
    float vz = K[1][1] * p.y + (K[2][1] + 0.5) * p.z;
    // reversed z: depth = near / z, in [0, 1] for z >= near (glClipControl zero-to-one)
    gl_Position = vec4(2.0 * uz / size.x - p.z, 2.0 * vz / size.y - p.z, near, p.z);
}}
"""

# The ray caster's shading: colour * (ambient + (1 - ambient) |cos(normal, ray)|), rounded, with the face's
# normal (link frame) and colour from a buffer texture indexed by the triangle; the top byte = link index + 1 (0: no robot).
_FRAGMENT = """
#version 330 core
in float z;
flat in int link_of;
uniform mat4 link_to_camera[{links}];
uniform mat3 K_inverse;
uniform float ambient;
uniform samplerBuffer faces;  // per triangle: normal xyz, then colour rgb (0..255)
layout(location = 0) out uint colour;  // r, g, b, link + 1: a byte each, little-endian
layout(location = 1) out float depth;
void main() {{
    vec3 ray = K_inverse * vec3(gl_FragCoord.xy - 0.5, 1.0);
    vec3 normal = mat3(link_to_camera[link_of]) * texelFetch(faces, 2 * gl_PrimitiveID).xyz;
    float shade = ambient + (1.0 - ambient) * abs(dot(normal, ray)) / length(ray);
    vec3 rgb = texelFetch(faces, 2 * gl_PrimitiveID + 1).xyz * shade + 0.5;
    uvec3 c = uvec3(rgb);
    colour = c.r | (c.g << 8) | (c.b << 16) | (uint(link_of + 1) << 24);
    depth = z;
}}
"""


class GLRenderer(Renderer):
    """Renderer that rasterises the posed links with OpenGL (EGL, no window).

    ``near``, ``ambient``: as :class:`~imac_data.core.render.RaycastRenderer`. ``nthreads``: llvmpipe's
    threads (``LP_NUM_THREADS``), read once per process when EGL starts; 0 = Mesa's default (all cores).
    ``max_frames``: frames drawn into one framebuffer (a layer each) and read back at once.
    """

    def __init__(self, robot: RobotModel, *, near: float = 0.0, ambient: float = 0.3, nthreads: int = 0,
                 max_frames: int = 16):
        super().__init__(robot)
        for name, value, ok in (("near", near, near >= 0), ("ambient", ambient, 0 <= ambient <= 1),
                                ("max_frames", max_frames, max_frames >= 1)):
            if not (math.isfinite(value) and ok):
                raise InputError(f"renderer {name} out of range: {value}")
        if len(self.link_names) > 255:  # the link index travels in one byte
            raise InputError(f"the opengl renderer draws at most 255 links, robot {robot.config.name!r} has "
                             f"{len(self.link_names)}; use the open3d renderer")
        self.max_frames = int(max_frames)
        self.near = float(near)
        self.ambient = float(ambient)
        self.nthreads = int(nthreads)
        index = {name: i for i, name in enumerate(self.link_names)}
        verts, faces, links, normals, colours, count = [], [], [], [], [], 0  # one vertex buffer, links by vertex
        for mesh in robot.visual_meshes:
            v = np.asarray(mesh.vertices, np.float64)
            f = np.asarray(mesh.faces, np.int64)
            n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
            normals.append(n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300))
            verts.append(v)
            faces.append(f + count)
            links.append(np.full(len(v), index[mesh.link], np.int32))
            colours.append(np.broadcast_to(np.asarray(mesh.rgba[:3], np.float32), (len(f), 3)))
            count += len(v)
        if not verts:
            raise InputError(f"robot {robot.config.name!r} ({robot.config.urdf_path}) has no visual geometry to render")
        self._vertices = np.concatenate(verts).astype(np.float32)
        self._faces = np.concatenate(faces).astype(np.uint32)
        self._vertex_link = np.concatenate(links)
        per_face = np.zeros((len(self._faces), 2, 4), np.float32)  # normal, colour: two texels a triangle
        per_face[:, 0, :3] = np.concatenate(normals)
        per_face[:, 1, :3] = 255.0 * np.concatenate(colours)
        self._per_face = per_face
        self.num_triangles = len(self._faces)
        self._gl = None  # this process's context, program, buffers and framebuffers: made at the first render
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ render

    def render_link_poses(self, link_poses: Mapping[str, torch.Tensor],
                          cameras: Mapping[str, Camera]) -> dict[str, RenderOutput]:
        ref = link_poses[self.link_names[0]]
        batch, device = tuple(ref.shape[:-2]), ref.device
        N = math.prod(batch)

        def pose(name):
            return link_poses[name].detach().reshape(N, 4, 4).to("cpu", torch.float64).numpy()

        T_wl = np.stack([pose(n) for n in self.link_names], axis=1)  # (N, L, 4, 4)
        result = {}
        with self._lock, self._current() as gl:
            for name, cam in cameras.items():
                if cam.is_mounted:
                    mount = T_wl[:, self.link_names.index(cam.link)] if cam.link in self.link_names else pose(cam.link)
                    T_wc = mount @ cam.T_link_cam
                else:
                    T_wc = np.broadcast_to(cam.T_world_cam, (N, 4, 4))
                if not np.isfinite(T_wc).all():
                    raise InputError("render: non-finite camera pose")
                T_cl = rigid_inverse(T_wc)[:, None] @ T_wl  # (N, L, 4, 4) link -> camera
                H, W = cam.height, cam.width
                if max(H, W) > gl["max_size"]:
                    raise InputError(f"camera {name!r}: {W}x{H} is larger than this OpenGL's framebuffers "
                                     f"({gl['max_size']} pixels a side); use the open3d renderer")
                step = min(self.max_frames, gl["max_layers"])
                colour = np.empty((N, H, W, 4), np.uint8)
                depth = np.empty((N, H, W), np.float32)
                for lo in range(0, N, step):
                    hi = min(N, lo + step)
                    self._draw(gl, T_cl[lo:hi], cam, colour[lo:hi], depth[lo:hi], step)
                rgb, link = colour[..., :3].copy(), colour[..., 3].astype(np.int16) - 1
                shape = (*batch, H, W)
                out = RenderOutput(rgb=torch.from_numpy(rgb).reshape(*shape, 3),
                                   mask=torch.from_numpy(link >= 0).reshape(shape),
                                   depth=torch.from_numpy(depth).reshape(shape),
                                   link_id=torch.from_numpy(link).reshape(shape))
                if device.type != "cpu":
                    out = RenderOutput(*(x.to(device) for x in (out.rgb, out.mask, out.depth, out.link_id)))
                result[name] = out
        return result

    # ------------------------------------------------------------------ helpers

    @contextlib.contextmanager
    def _current(self):
        """This process's context, current in the calling thread while the block runs (then released, so that
        another thread can take it next)."""
        gl = self._context()
        try:
            yield gl
        finally:
            EGL = gl["EGL"]
            EGL.eglMakeCurrent(gl["display"], EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)

    def _context(self):
        """This process's EGL context, program and buffers, made current in the calling thread."""
        if self._gl is not None and self._gl["pid"] == os.getpid():
            self._gl["context"].make_current()
            return self._gl
        if self.nthreads > 0:  # Mesa reads it when EGL starts: a worker sets it before its first render
            os.environ.setdefault("LP_NUM_THREADS", str(self.nthreads))
        os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
        try:
            import mujoco.egl  # heavy, and needs EGL: only for this backend
            from OpenGL import EGL, GL
        except Exception as e:  # noqa: BLE001 - any failure to load EGL means the same to the user
            raise InputError(f"the opengl renderer needs EGL (libEGL, e.g. Mesa) and PyOpenGL: {e}") from e
        context = mujoco.egl.GLContext(64, 64)  # draws into its own framebuffers, never this surface
        atexit.register(_free, context, os.getpid())  # before interpreter teardown, when EGL can still be called
        context.make_current()
        links = len(self.link_names)
        program = _program(GL, _VERTEX.format(links=links), _FRAGMENT.format(links=links))
        vao = GL.glGenVertexArrays(1)
        GL.glBindVertexArray(vao)
        buffers = GL.glGenBuffers(3)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, buffers[0])
        GL.glBufferData(GL.GL_ARRAY_BUFFER, self._vertices.nbytes, self._vertices, GL.GL_STATIC_DRAW)
        GL.glEnableVertexAttribArray(0)
        GL.glVertexAttribPointer(0, 3, GL.GL_FLOAT, GL.GL_FALSE, 0, None)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, buffers[1])
        GL.glBufferData(GL.GL_ARRAY_BUFFER, self._vertex_link.nbytes, self._vertex_link, GL.GL_STATIC_DRAW)
        GL.glEnableVertexAttribArray(1)
        GL.glVertexAttribIPointer(1, 1, GL.GL_INT, 0, None)
        GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, buffers[2])
        GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, self._faces.nbytes, self._faces, GL.GL_STATIC_DRAW)
        texture, faces = GL.glGenTextures(1), GL.glGenBuffers(1)
        GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, faces)
        GL.glBufferData(GL.GL_TEXTURE_BUFFER, self._per_face.nbytes, self._per_face, GL.GL_STATIC_DRAW)
        GL.glActiveTexture(GL.GL_TEXTURE0)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, texture)
        GL.glTexBuffer(GL.GL_TEXTURE_BUFFER, GL.GL_RGBA32F, faces)
        GL.glUseProgram(program)
        GL.glUniform1i(GL.glGetUniformLocation(program, "faces"), 0)
        GL.glUniform1f(GL.glGetUniformLocation(program, "ambient"), self.ambient)
        GL.glClipControl(GL.GL_LOWER_LEFT, GL.GL_ZERO_TO_ONE)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthFunc(GL.GL_GREATER)
        GL.glDisable(GL.GL_CULL_FACE)
        GL.glDisable(GL.GL_DITHER)
        uniforms = {n: GL.glGetUniformLocation(program, n)
                    for n in ("link_to_camera", "K", "K_inverse", "size", "near")}
        self._gl = {"pid": os.getpid(), "GL": GL, "EGL": EGL, "display": mujoco.egl.EGL_DISPLAY,  # set by the context
                    "context": context, "program": program, "vao": vao, "buffers": (*buffers, faces),
                    "texture": texture, "uniforms": uniforms, "targets": {},
                    "max_size": int(GL.glGetIntegerv(GL.GL_MAX_TEXTURE_SIZE)),
                    "max_layers": int(GL.glGetIntegerv(GL.GL_MAX_ARRAY_TEXTURE_LAYERS))}
        return self._gl

    def _target(self, gl, W: int, H: int, frames: int):
        """A framebuffer for ``frames`` frames of W x H: two array textures, a layer a frame (colour and link,
        z-depth), and one depth buffer. Each frame is drawn at the same window position, so a pixel's value
        does not depend on how the frames are batched."""
        target = gl["targets"].get((W, H, frames))
        if target is not None:
            return target
        GL = gl["GL"]
        fbo = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, fbo)
        GL.glActiveTexture(GL.GL_TEXTURE1)
        layers = GL.glGenTextures(2)
        for texture, fmt in zip(layers, (GL.GL_R32UI, GL.GL_R32F)):
            GL.glBindTexture(GL.GL_TEXTURE_2D_ARRAY, texture)
            GL.glTexStorage3D(GL.GL_TEXTURE_2D_ARRAY, 1, fmt, W, H, frames)
        GL.glActiveTexture(GL.GL_TEXTURE0)
        rbo = GL.glGenRenderbuffers(1)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rbo)
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT32F, W, H)
        GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, rbo)
        for k, texture in enumerate(layers):
            GL.glFramebufferTextureLayer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0 + k, texture, 0, 0)
        GL.glDrawBuffers(2, [GL.GL_COLOR_ATTACHMENT0, GL.GL_COLOR_ATTACHMENT1])
        status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
        if status != GL.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError(f"OpenGL framebuffer of {frames} x {W}x{H} incomplete (status {status:#x})")
        target = gl["targets"][(W, H, frames)] = (fbo, layers, rbo)
        return target

    def _draw(self, gl, T_cl: np.ndarray, cam: Camera, colour: np.ndarray, depth: np.ndarray, frames: int) -> None:
        """Draw frames ``T_cl`` (n <= frames, L, 4, 4) of one camera: RGB and link index + 1 per pixel, and z
        (0: none)."""
        GL, u = gl["GL"], gl["uniforms"]
        n, H, W = T_cl.shape[0], cam.height, cam.width
        fbo, layers, _ = self._target(gl, W, H, frames)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, fbo)
        GL.glViewport(0, 0, W, H)
        GL.glUniformMatrix3fv(u["K"], 1, GL.GL_TRUE, np.asarray(cam.K, np.float32))
        GL.glUniformMatrix3fv(u["K_inverse"], 1, GL.GL_TRUE, np.linalg.inv(cam.K).astype(np.float32))
        GL.glUniform2f(u["size"], float(W), float(H))
        GL.glUniform1f(u["near"], max(self.near, 1e-5))
        T = np.ascontiguousarray(T_cl, dtype=np.float32)
        no_colour, no_depth = np.zeros(4, np.uint32), np.zeros(4, np.float32)
        for i in range(n):
            for k, texture in enumerate(layers):
                GL.glFramebufferTextureLayer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0 + k, texture, 0, i)
            GL.glClearBufferuiv(GL.GL_COLOR, 0, no_colour)
            GL.glClearBufferfv(GL.GL_COLOR, 1, no_depth)
            GL.glClearBufferfv(GL.GL_DEPTH, 0, no_depth[:1])
            GL.glUniformMatrix4fv(u["link_to_camera"], T.shape[1], GL.GL_TRUE, T[i])
            GL.glDrawElements(GL.GL_TRIANGLES, 3 * self.num_triangles, GL.GL_UNSIGNED_INT, None)
        GL.glActiveTexture(GL.GL_TEXTURE1)
        for texture, out, fmt, kind, dtype in ((layers[0], colour, GL.GL_RED_INTEGER, GL.GL_UNSIGNED_INT, np.uint8),
                                               (layers[1], depth, GL.GL_RED, GL.GL_FLOAT, np.float32)):
            GL.glBindTexture(GL.GL_TEXTURE_2D_ARRAY, texture)
            data = np.frombuffer(GL.glGetTexImage(GL.GL_TEXTURE_2D_ARRAY, 0, fmt, kind), dtype)
            out[:] = data.reshape(frames, *out.shape[1:])[:n]
        GL.glActiveTexture(GL.GL_TEXTURE0)


def _free(context, pid: int) -> None:
    if os.getpid() == pid:  # a forked child's copy is not its own to free
        context.free()


def _program(GL, vertex: str, fragment: str):
    """A linked shader program, or a RuntimeError with the driver's log."""
    program = GL.glCreateProgram()
    for kind, source in ((GL.GL_VERTEX_SHADER, vertex), (GL.GL_FRAGMENT_SHADER, fragment)):
        shader = GL.glCreateShader(kind)
        GL.glShaderSource(shader, source)
        GL.glCompileShader(shader)
        if not GL.glGetShaderiv(shader, GL.GL_COMPILE_STATUS):
            raise RuntimeError(f"OpenGL shader does not compile: {GL.glGetShaderInfoLog(shader).decode()}")
        GL.glAttachShader(program, shader)
    GL.glLinkProgram(program)
    if not GL.glGetProgramiv(program, GL.GL_LINK_STATUS):
        raise RuntimeError(f"OpenGL program does not link: {GL.glGetProgramInfoLog(program).decode()}")
    return program
