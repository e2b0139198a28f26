"""The moderngl renderer: every avatar skinned on the GPU, a floor grid, offscreen or on screen.

Linear blend skinning runs in the vertex shader (the paper skinned on the CPU): each
vertex carries four joint indices and weights, and the avatar's joint matrices (see
``skinning.joint_matrices``: FK on the avatar's own bone lengths, the mesh fitted to them)
are a uniform array, written once per avatar; one draw call per avatar. The same shader
source, compiled with a transform-feedback output instead of a fragment stage, returns the
skinned vertex positions (``skinned_positions``), which tests compare with the numpy
reference ``skinning.skin``.

Level of detail (``lod.py``): each avatar is drawn with the coarsest mesh whose detail
still shows at its size on screen, within a per-frame triangle budget, and not at all
when it is outside the view. That is what keeps 16 avatars at 1280x720 within a frame
on a software rasterizer (llvmpipe), whose cost is per triangle. For the same reason the
avatars are lit per vertex (one varying and a trivial fragment shader: ~35% faster on
llvmpipe than per-pixel lighting), joint matrices are sent as their three affine rows,
and back faces are culled (the mesh's winding is consistent).

Contexts: ``Renderer.standalone`` makes a headless EGL context (Mesa llvmpipe works; no
display, no GPU needed); a window passes its own context and screen framebuffer.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import moderngl
import numpy as np
from numpy.typing import NDArray

from posecast.client.viewer.camera import Camera, OrbitCamera
from posecast.client.viewer.lod import DEFAULT_CELLS, build_lods, choose_levels, default_budget
from posecast.client.viewer.skinning import Array, FittedAvatar, pose_matrices, template_avatar
from posecast.solver import rotations as R
from posecast.solver.readers.gltf import SkinnedMesh, load_makehuman

# distinct, readable avatar colours (linear-ish RGB), cycled by avatar id
PALETTE: tuple[tuple[float, float, float], ...] = (
    (0.90, 0.45, 0.25), (0.25, 0.60, 0.90), (0.45, 0.80, 0.35), (0.85, 0.35, 0.70),
    (0.95, 0.80, 0.30), (0.35, 0.85, 0.80), (0.65, 0.50, 0.90), (0.90, 0.55, 0.55),
)
BACKGROUND = (0.11, 0.12, 0.15)
GL_CLIP_DISTANCE0 = 0x3000  # not among moderngl's flags: enabled with enable_direct
LABEL_ABOVE_HEAD_M = 0.12

_SKIN_GLSL = """
in vec3 in_position;
in vec3 in_normal;
in uvec4 in_joints;
in vec4 in_weights;
// each joint's matrix as its top three rows (an affine map): 12 floats, not 16
uniform vec4 u_joints[3 * NUM_JOINTS];

mat4 skin_matrix() {
    uvec4 i = in_joints * 3u;
    vec4 w = in_weights;
    vec4 r0 = w.x * u_joints[i.x] + w.y * u_joints[i.y] + w.z * u_joints[i.z]
            + w.w * u_joints[i.w];
    vec4 r1 = w.x * u_joints[i.x + 1u] + w.y * u_joints[i.y + 1u] + w.z * u_joints[i.z + 1u]
            + w.w * u_joints[i.w + 1u];
    vec4 r2 = w.x * u_joints[i.x + 2u] + w.y * u_joints[i.y + 2u] + w.z * u_joints[i.z + 2u]
            + w.w * u_joints[i.w + 2u];
    return transpose(mat4(r0, r1, r2, vec4(0.0, 0.0, 0.0, 1.0)));
}
"""

_AVATAR_VS = """
#version 330
SKIN
uniform mat4 u_view_projection;
uniform vec3 u_color;
uniform vec3 u_eye;
uniform vec4 u_clip;  // a world plane: the half-space where dot(u_clip, p) < 0 is cut
out vec3 v_color;
const vec3 LIGHT = vec3(0.3578, 0.8050, 0.4472);  // normalize(0.4, 0.9, 0.5)
void main() {
    mat4 m = skin_matrix();
    vec4 world = m * vec4(in_position, 1.0);
    // lit per vertex (Gouraud): one varying instead of two, and a trivial fragment
    // shader; the software rasterizer's cost is per triangle and per varying
    vec3 n = normalize(mat3(m) * in_normal);
    vec3 to_eye = normalize(u_eye - world.xyz);
    float key = max(dot(n, LIGHT), 0.0);
    float sky = 0.5 + 0.5 * n.y;  // hemisphere ambient: brighter from above
    float rim = pow(1.0 - max(dot(n, to_eye), 0.0), 3.0);
    v_color = u_color * (0.25 + 0.25 * sky + 0.6 * key) + 0.15 * rim;
    gl_ClipDistance[0] = dot(u_clip, world);
    gl_Position = u_view_projection * world;
}
"""

_AVATAR_FS = """
#version 330
in vec3 v_color;
out vec4 f_color;
void main() {
    f_color = vec4(v_color, 1.0);
}
"""

_FEEDBACK_VS = """
#version 330
SKIN
out vec3 out_position;
void main() {
    out_position = (skin_matrix() * vec4(in_position, 1.0)).xyz;
}
"""

_GRID_VS = """
#version 330
in vec3 in_position;
in vec3 in_color;
uniform mat4 u_view_projection;
uniform vec4 u_clip;
out vec3 v_color;
out vec3 v_world;
void main() {
    v_color = in_color;
    v_world = in_position;
    gl_ClipDistance[0] = dot(u_clip, vec4(in_position, 1.0));
    gl_Position = u_view_projection * vec4(in_position, 1.0);
}
"""

_GRID_FS = """
#version 330
in vec3 v_color;
in vec3 v_world;
uniform vec3 u_eye;
uniform vec3 u_background;
out vec4 f_color;
void main() {
    float fade = clamp(length(v_world - u_eye) / 25.0, 0.0, 1.0);  // fog into the distance
    f_color = vec4(mix(v_color, u_background, fade), 1.0);
}
"""


def avatar_color(avatar_id: int) -> tuple[float, float, float]:
    return PALETTE[avatar_id % len(PALETTE)]


@dataclass
class AvatarDraw:
    """One avatar to draw: its fitted skeleton and a pose in the avatar's joint order."""

    avatar: FittedAvatar
    rotations: Array  # (J, 4) local rotations, x y z w
    root: Array  # (3,) root joint position
    color: tuple[float, float, float] | None = None  # None: avatar_color(id)
    hide_head: bool = False  # first person: do not draw one's own head


@dataclass
class PosedScene:
    """A frame's avatars after FK: what drawing, labels and tests need."""

    draws: list[AvatarDraw]
    matrices: Array  # (B, J, 4, 4) skinning matrices
    global_rot: Array  # (B, J, 4) mesh joint order
    global_pos: Array  # (B, J, 3)
    # per avatar, after render: the level of detail drawn (0 full), -1 outside the view
    lod: list[int] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.draws)


class GLUnavailableError(RuntimeError):
    """No OpenGL context could be made (no EGL/Mesa libraries, no display)."""


def create_headless_context() -> moderngl.Context:
    """An offscreen OpenGL 3.3+ context through EGL (works with Mesa llvmpipe)."""
    try:
        # moderngl's stub types **settings as dicts; backend is a string
        return moderngl.create_standalone_context(backend="egl")  # type: ignore[arg-type]
    except Exception as err:  # glcontext raises plain Exceptions with the EGL error
        raise GLUnavailableError(
            f"cannot create a headless OpenGL context through EGL ({err}); on Debian/Ubuntu "
            f"install libegl1 libgl1 libgl1-mesa-dri") from err


class Renderer:
    """Draws avatars and a floor grid with GPU skinning.

    ``target`` is the framebuffer drawn into: by default an offscreen one of
    ``width`` x ``height`` (read it with ``read``); a window passes its screen
    (``ctx.detect_framebuffer()``). ``triangle_budget``: None picks one for the GL
    renderer (``lod.default_budget``). One renderer per context and thread.
    """

    def __init__(self, ctx: moderngl.Context, width: int, height: int,
                 mesh: SkinnedMesh | None = None, target: moderngl.Framebuffer | None = None,
                 triangle_budget: int | None = None,
                 lod_cells: Sequence[float] = DEFAULT_CELLS) -> None:
        self.ctx = ctx
        self.mesh = mesh or load_makehuman()
        self.width, self.height = int(width), int(height)
        # triangles per frame (see lod.py; 0: always full meshes); None: by the renderer
        self.triangle_budget = (default_budget(str(ctx.info.get("GL_RENDERER", "")))
                                if triangle_budget is None else int(triangle_budget))
        J = self.mesh.skeleton.num_joints
        skin = _SKIN_GLSL.replace("NUM_JOINTS", str(J))
        self._avatar_prog = ctx.program(vertex_shader=_AVATAR_VS.replace("SKIN", skin),
                                        fragment_shader=_AVATAR_FS)
        self._feedback_prog = ctx.program(vertex_shader=_FEEDBACK_VS.replace("SKIN", skin),
                                          varyings=("out_position",))
        self._grid_prog = ctx.program(vertex_shader=_GRID_VS, fragment_shader=_GRID_FS)
        self._lods = build_lods(self.mesh, lod_cells)
        self._vbo, self._jbo = self._upload_vertices()
        self._index_buffers: list[moderngl.Buffer] = []
        self._levels = [self._vertex_array(self._avatar_prog, ix) for ix in self._lods.levels]
        self._feedback = self._vertex_array(self._feedback_prog, None)
        self._grid, self._grid_vertices = self._make_grid()
        self._own_target = target is None
        if target is None:
            self._color_rb = ctx.renderbuffer((self.width, self.height), 4)
            self._depth_rb = ctx.depth_renderbuffer((self.width, self.height))
            target = ctx.framebuffer(color_attachments=[self._color_rb],
                                     depth_attachment=self._depth_rb)
        self.target = target
        self.head_joint = self.mesh.skeleton.index("head")
        self._head_tip = self.mesh.skeleton.tips[self.head_joint]
        # every joint below the head (none in this rig, but a rig may have eyes, jaw ...)
        parents = self.mesh.skeleton.parents
        hidden = [self.head_joint]
        for j in range(self.head_joint + 1, len(parents)):
            if parents[j] in hidden:
                hidden.append(j)
        self._head_joints = np.array(hidden)

    @classmethod
    def standalone(cls, width: int = 1280, height: int = 720,
                   mesh: SkinnedMesh | None = None,
                   triangle_budget: int | None = None) -> Renderer:
        """A renderer with its own headless EGL context (raises GLUnavailableError)."""
        return cls(create_headless_context(), width, height, mesh,
                   triangle_budget=triangle_budget)

    @property
    def lod_triangles(self) -> list[int]:
        """Triangles of each level of detail (level 0: the full mesh)."""
        return self._lods.triangles

    # ------------------------------------------------------------------ set-up
    def _upload_vertices(self) -> tuple[moderngl.Buffer, moderngl.Buffer]:
        """Vertex attributes in the LOD's vertex order (Morton: better vertex reuse)."""
        m, order = self.mesh, self._lods.vertex_order
        vertices = np.concatenate([m.positions[order], m.normals[order], m.weights[order]],
                                  axis=1)
        vbo = self.ctx.buffer(np.ascontiguousarray(vertices, dtype="f4").tobytes())
        jbo = self.ctx.buffer(np.ascontiguousarray(m.joints[order], dtype="u4").tobytes())
        return vbo, jbo

    def _vertex_array(self, prog: moderngl.Program,
                      indices: NDArray[np.uint32] | None) -> moderngl.VertexArray:
        vbo, jbo = self._vbo, self._jbo
        content: list[tuple[Any, ...]]
        if "in_normal" in prog:
            content = [(vbo, "3f 3f 4f", "in_position", "in_normal", "in_weights")]
        else:  # the feedback program has no normals: skip their 12 bytes
            content = [(vbo, "3f 12x 4f", "in_position", "in_weights")]
        content.append((jbo, "4u", "in_joints"))
        if indices is None:
            return self.ctx.vertex_array(prog, content)
        ibo = self.ctx.buffer(np.ascontiguousarray(indices, dtype="u4").tobytes())
        self._index_buffers.append(ibo)
        return self.ctx.vertex_array(prog, content, index_buffer=ibo, index_element_size=4)

    def _make_grid(self, half: float = 10.0, step: float = 0.5) -> tuple[moderngl.VertexArray,
                                                                          int]:
        lines = []
        ticks = np.arange(-half, half + 1e-9, step)
        for t in ticks:
            major = abs(t - round(t)) < 1e-9
            c = (0.42, 0.44, 0.50) if major else (0.26, 0.27, 0.31)
            cx = (0.75, 0.30, 0.30) if abs(t) < 1e-9 else c  # the x axis (z = 0) in red
            cz = (0.30, 0.40, 0.80) if abs(t) < 1e-9 else c  # the z axis (x = 0) in blue
            lines += [(-half, 0, t, *cx), (half, 0, t, *cx), (t, 0, -half, *cz),
                      (t, 0, half, *cz)]
        data = np.array(lines, dtype="f4")
        vbo = self.ctx.buffer(data.tobytes())
        vao = self.ctx.vertex_array(self._grid_prog, [(vbo, "3f 3f", "in_position",
                                                       "in_color")])
        return vao, len(data)

    # ------------------------------------------------------------------ per frame
    def pose(self, draws: Sequence[AvatarDraw]) -> PosedScene:
        """FK and skinning matrices of every avatar, in one batched call."""
        draws = list(draws)
        if not draws:
            J = self.mesh.skeleton.num_joints
            return PosedScene([], np.empty((0, J, 4, 4)), np.empty((0, J, 4)),
                              np.empty((0, J, 3)))
        matrices, gq, gp = pose_matrices([d.avatar for d in draws], self.mesh,
                                         [d.rotations for d in draws],
                                         [d.root for d in draws])
        posed = PosedScene(draws, matrices, gq, gp)
        hidden = [b for b, d in enumerate(draws) if d.hide_head]
        # the head collapsed onto its joint: M = [0 | p] @ IB
        return self.without_heads(posed, hidden) if hidden else posed

    def head_tops(self, scene: PosedScene) -> Array:
        """Where each avatar's name label goes: a little above the crown, (B, 3)."""
        h = self.head_joint
        tips = np.stack([d.avatar.fit[h] @ self._head_tip for d in scene.draws]) \
            if scene.draws else np.empty((0, 3))
        top = scene.global_pos[:, h] + R.rotate(scene.global_rot[:, h], tips)
        top[:, 1] += LABEL_ABOVE_HEAD_M
        return top

    def _choose_levels(self, scene: PosedScene, camera: Camera,
                       size: tuple[int, int]) -> list[int]:
        """A level of detail per avatar (-1: outside the view, not drawn)."""
        if not scene.draws:
            return []
        width, height = size
        top = self.head_tops(scene)
        bottom = top.copy()
        bottom[:, 1] = scene.global_pos[:, :, 1].min(axis=1)  # the lowest joint's height
        pt, front_t = camera.project(top, width, height)
        pb, front_b = camera.project(bottom, width, height)
        # an avatar partly behind the camera is as close as can be: the finest level
        height_px = np.where(front_t & front_b, np.linalg.norm(pt - pb, axis=1), 1e9)
        # a sphere around the body's joints: not drawn when wholly outside the view
        lo, hi = scene.global_pos.min(axis=1), scene.global_pos.max(axis=1)
        visible = camera.spheres_visible(0.5 * (lo + hi),
                                         0.5 * np.linalg.norm(hi - lo, axis=1) + 0.3)
        shown = np.nonzero(visible)[0]
        levels = [-1] * len(scene)
        if self.triangle_budget > 0:  # the budget is shared by the avatars in view
            chosen = choose_levels(height_px[shown].tolist(), self._lods,
                                   self.triangle_budget)
        else:
            chosen = [0] * len(shown)
        for b, k in zip(shown, chosen, strict=True):
            levels[int(b)] = k
        return levels

    def render(self, scene: PosedScene, camera: Camera, grid: bool = True, *,
               target: moderngl.Framebuffer | None = None,
               size: tuple[int, int] | None = None,
               clip_plane: Array | None = None) -> None:
        """Draw the scene into ``target`` (default: the renderer's own, at its size; does
        not wait for the GPU). ``clip_plane`` (a, b, c, d): cut everything where
        a x + b y + c z + d < 0 (a mirror's reflected pass cuts what is behind it)."""
        ctx = self.ctx
        width, height = size or (self.width, self.height)
        (target or self.target).use()
        ctx.viewport = (0, 0, width, height)
        ctx.clear(*BACKGROUND, 1.0, depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.enable(moderngl.CULL_FACE)
        clip = (0.0, 0.0, 0.0, 1.0) if clip_plane is None else tuple(
            float(x) for x in clip_plane)
        if clip_plane is not None:
            ctx.enable_direct(GL_CLIP_DISTANCE0)
        ctx.front_face = "cw" if camera.mirrored else "ccw"
        vp = _gl_matrix(camera.view_projection)
        eye = tuple(float(x) for x in camera.eye)
        if grid:
            uniform(self._grid_prog, "u_view_projection").write(vp)
            uniform(self._grid_prog, "u_eye").value = eye
            uniform(self._grid_prog, "u_background").value = BACKGROUND
            uniform(self._grid_prog, "u_clip").value = clip
            self._grid.render(moderngl.LINES, vertices=self._grid_vertices)
        prog = self._avatar_prog
        uniform(prog, "u_view_projection").write(vp)
        uniform(prog, "u_eye").value = eye
        uniform(prog, "u_clip").value = clip
        scene.lod = self._choose_levels(scene, camera, (width, height))
        joints = uniform(prog, "u_joints")
        color = uniform(prog, "u_color")
        for b, d in enumerate(scene.draws):
            if scene.lod[b] < 0:
                continue
            joints.write(_gl_matrices(scene.matrices[b]))
            color.value = d.color or avatar_color(d.avatar.info.avatar_id)
            self._levels[scene.lod[b]].render(moderngl.TRIANGLES)
        if clip_plane is not None:
            ctx.disable_direct(GL_CLIP_DISTANCE0)
        ctx.front_face = "ccw"

    def without_heads(self, scene: PosedScene, hidden: Sequence[int]) -> PosedScene:
        """A copy of ``scene`` whose avatars at indices ``hidden`` have no head (the
        first-person camera sits inside it); ``scene`` itself is unchanged, for a mirror
        that shows the head."""
        matrices = scene.matrices.copy()
        for b in hidden:
            matrices[b, self._head_joints, :3, :3] = 0.0
            matrices[b, self._head_joints, :3, 3] = scene.global_pos[b, self._head_joints]
        return PosedScene(scene.draws, matrices, scene.global_rot, scene.global_pos)

    def warm_up(self) -> None:
        """Draw every level of detail once and wait: the driver compiles its shader
        variants on first use (~0.2 s on llvmpipe), which would otherwise stall the
        first real frame while frames queue up on the socket."""
        J = self.mesh.skeleton.num_joints
        avatar = template_avatar(self.mesh)
        draw = AvatarDraw(avatar, np.tile([0.0, 0.0, 0.0, 1.0], (J, 1)),
                          self.mesh.skeleton.offsets[0].copy())
        scene = self.pose([draw])
        camera = OrbitCamera(distance=3.0).camera(self.width / self.height)
        budget = self.triangle_budget
        try:
            for level in range(len(self._levels)):  # cheapest to most detailed
                self.triangle_budget = sum(self.lod_triangles[level:level + 1])
                self.render(scene, camera)
        finally:
            self.triangle_budget = budget
        self.ctx.finish()

    def read(self) -> NDArray[np.uint8]:
        """The target's pixels, (height, width, 3) uint8, top row first; waits for the GPU."""
        raw = self.target.read(components=3, alignment=1)
        return np.frombuffer(raw, np.uint8).reshape(self.height, self.width, 3)[::-1]

    def render_image(self, draws: Sequence[AvatarDraw], camera: Camera,
                     grid: bool = True) -> tuple[NDArray[np.uint8], PosedScene]:
        """Pose, draw and read back in one call."""
        scene = self.pose(draws)
        self.render(scene, camera, grid)
        return self.read(), scene

    # ------------------------------------------------------------------ checks
    def skinned_positions(self, matrices: Array) -> NDArray[np.float32]:
        """The vertex shader's skinned positions (V, 3) for joint ``matrices`` (J, 4, 4),
        read back through transform feedback."""
        V = self.mesh.num_vertices
        out = self.ctx.buffer(reserve=V * 3 * 4)
        try:
            # a draw needs a complete framebuffer bound, even with rasterization off (a
            # surfaceless EGL context has none of its own)
            self.target.use()
            uniform(self._feedback_prog, "u_joints").write(_gl_matrices(matrices))
            self._feedback.transform(out, moderngl.POINTS, vertices=V)
            uploaded = np.frombuffer(out.read(), np.float32).reshape(V, 3)
            result = np.empty((V, 3), np.float32)
            result[self._lods.vertex_order] = uploaded  # back to the mesh's vertex order
            return result
        finally:
            out.release()

    def release(self) -> None:
        for vao in (*self._levels, self._feedback):
            vao.release()
        for buf in (self._vbo, self._jbo, *self._index_buffers):
            buf.release()
        self._grid.release()
        for prog in (self._avatar_prog, self._feedback_prog, self._grid_prog):
            prog.release()
        if self._own_target:
            self.target.release()
            self._color_rb.release()
            self._depth_rb.release()


def uniform(prog: moderngl.Program, name: str) -> moderngl.Uniform:
    """A program's uniform by name (typed: ``prog[name]`` may be any member)."""
    member = prog[name]
    if not isinstance(member, moderngl.Uniform):
        raise TypeError(f"{name!r} is not a uniform of this program")
    return member


def _gl_matrix(m: Array) -> bytes:
    """A (4, 4) row-major numpy matrix as GLSL's column-major mat4 bytes."""
    return np.ascontiguousarray(m.T, dtype="f4").tobytes()


def _gl_matrices(m: Array) -> bytes:
    """Joint matrices (J, 4, 4) as the shader's rows: the top three rows of each."""
    return np.ascontiguousarray(m[..., :3, :], dtype="f4").tobytes()
