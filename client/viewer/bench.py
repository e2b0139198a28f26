"""``bench_render``: milliseconds per frame of the viewer for N avatars, on this machine.

The poses are the built-in motion as the server would send them: the CMU walk replayed as
trackers (``BvhSource``, as ``posecast demo``'s players do), the MakeHuman avatar
calibrated on its T-pose and solved frame by frame with the solver the server uses
(calibration and IK from ``solver/``, so client/ needs no server import). Each avatar
plays the clip from its own frame, walking in place on a grid so that all stay in view.

A frame is timed as the viewer does it: FK of every avatar, skinning matrices, the draw
(level of detail within the triangle budget), name labels and HUD, and the read-back of
the pixels that completes it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from posecast.client.builtin import builtin_motion_path
from posecast.client.sources.bvh_source import BvhSource
from posecast.client.viewer.camera import OrbitCamera
from posecast.client.viewer.overlay import TextItem, TextOverlay, hud_lines, label_items
from posecast.client.viewer.renderer import AvatarDraw, Renderer, avatar_color
from posecast.client.viewer.skinning import FittedAvatar, fit_avatar
from posecast.protocol import AvatarInfo
from posecast.solver.calibration import calibrate
from posecast.solver.ik import PoseBatch, Solver
from posecast.solver.readers.gltf import SkinnedMesh, load_makehuman
from posecast.solver.rig import build_rig

Array = NDArray[np.float64]
WARMUP_FRAMES = 5
GRID_SPACING_M = 1.4


@dataclass(frozen=True)
class Clip:
    """The built-in motion solved onto the calibrated MakeHuman avatar."""

    info: AvatarInfo  # the calibrated skeleton, as the server sends it
    rotations: Array  # (F, J, 4)
    roots: Array  # (F, 3)


def solve_builtin_clip(mesh: SkinnedMesh | None = None, solver: str = "analytic",
                       motion: Path | None = None) -> Clip:
    """Calibrate on the clip's T-pose and solve every frame (warm-started, as the server)."""
    mesh = mesh or load_makehuman()
    rig = build_rig(mesh.skeleton)
    source = BvhSource(motion or builtin_motion_path())
    tpose = source.calibration()
    cal = calibrate(rig, dict(zip(tpose.roles, tpose.positions, strict=True)),
                    dict(zip(tpose.roles, tpose.rotations, strict=True)))
    roles = tpose.roles
    targets = cal.targets(source.poses[..., :3], source.poses[..., 3:], roles)
    ik = Solver(rig, solver)
    state = PoseBatch(cal.pose[None].copy(), cal.root[None].copy())
    F = targets.shape[0]
    rotations = np.empty((F, *cal.pose.shape))
    roots = np.empty((F, 3))
    for f in range(F):
        ik.solve(targets[f:f + 1], state, cal.offsets[None])
        rotations[f], roots[f] = state.rotations[0], state.root[0]
    sk = mesh.skeleton
    info = AvatarInfo(avatar_id=0, display_name="walker", joint_names=sk.names,
                      parents=tuple(int(p) for p in sk.parents), rest_offsets=cal.offsets)
    return Clip(info, rotations, roots)


def grid_positions(n: int, spacing: float = GRID_SPACING_M) -> Array:
    """n places on the floor (x, 0, z), a near-square grid centred on the origin."""
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols) if n else 0
    i = np.arange(n)
    return np.stack([(i % cols - (cols - 1) / 2) * spacing, np.zeros(n),
                     (i // cols - (rows - 1) / 2) * spacing], axis=1)


def crowd(clip: Clip, mesh: SkinnedMesh, n: int) -> list[FittedAvatar]:
    """n avatars wearing the clip's calibrated skeleton, ids 0..n-1."""
    return [fit_avatar(mesh, clip.info.model_copy(update={"avatar_id": i,
                                                          "display_name": f"player {i + 1}"}))
            for i in range(n)]


def crowd_frame(clip: Clip, avatars: list[FittedAvatar], f: int,
                places: Array) -> list[AvatarDraw]:
    """Frame ``f`` of the crowd: avatar i at clip frame f + 37 i, walking in place."""
    F = clip.rotations.shape[0]
    draws = []
    for i, a in enumerate(avatars):
        k = (f + 37 * i) % F
        root = clip.roots[k].copy()
        root[[0, 2]] = places[i, [0, 2]]  # the pelvis held over its place: in place
        draws.append(AvatarDraw(a, clip.rotations[k], root))
    return draws


def bench_render(avatars: int = 16, width: int = 1280, height: int = 720, frames: int = 60,
                 triangle_budget: int | None = None, overlay: bool = True,
                 out: str | Path | None = None,
                 renderer: Renderer | None = None) -> dict[str, object]:
    """Render ``frames`` frames of ``avatars`` walking avatars; milliseconds per frame.

    ``triangle_budget``: None for the renderer's default (lod.default_budget). ``out``:
    write the last frame there as a PNG. Returns {"avatars", "width", "height",
    "frames", "renderer", "triangle_budget", "frame_ms": {"p50", "p99", "mean"},
    "triangles_per_frame", "levels" (frames drawn at each level of detail)}.
    """
    r = renderer or Renderer.standalone(width, height, triangle_budget=triangle_budget)
    try:
        mesh = r.mesh
        clip = solve_builtin_clip(mesh)
        people = crowd(clip, mesh, avatars)
        places = grid_positions(avatars)
        orbit = OrbitCamera(yaw=25.0, pitch=18.0)
        first = crowd_frame(clip, people, 0, places)
        orbit.frame(r.pose(first).global_pos.reshape(-1, 3))
        camera = orbit.camera(width / height)
        text = TextOverlay(r.ctx) if overlay else None
        names = [a.info.display_name for a in people]
        colors = [avatar_color(a.info.avatar_id) for a in people]
        times = []
        tris = []
        levels: dict[int, int] = {}
        pixels = None
        tri_count = r.lod_triangles
        for f in range(frames + WARMUP_FRAMES):
            draws = crowd_frame(clip, people, f, places)
            t0 = time.perf_counter()
            posed = r.pose(draws)
            r.render(posed, camera)
            if text is not None:
                items = label_items(names, colors, r.head_tops(posed), camera, width, height)
                items.append(TextItem("\n".join(hud_lines({}, 0.0, avatars, "bench", None,
                                                          "orbit")), 10, 10))
                text.draw(items, width, height)
            pixels = r.read()
            dt = time.perf_counter() - t0
            if f >= WARMUP_FRAMES:
                times.append(dt)
                tris.append(sum(tri_count[k] for k in posed.lod if k >= 0))
                for k in posed.lod:
                    levels[k] = levels.get(k, 0) + 1
        if text is not None:
            text.release()
        if out is not None and pixels is not None:
            Image.fromarray(np.ascontiguousarray(pixels), "RGB").save(out)
        ms = np.asarray(times) * 1e3
        return {"avatars": avatars, "width": width, "height": height, "frames": frames,
                "renderer": r.ctx.info.get("GL_RENDERER", "?"),
                "triangle_budget": r.triangle_budget,
                "frame_ms": {"p50": round(float(np.percentile(ms, 50)), 2),
                             "p99": round(float(np.percentile(ms, 99)), 2),
                             "mean": round(float(ms.mean()), 2)},
                "triangles_per_frame": int(np.median(tris)) if tris else 0,
                "levels": {str(k): v for k, v in sorted(levels.items())}}
    finally:
        if renderer is None:
            r.release()
            r.ctx.release()


def format_render_table(result: dict[str, object]) -> str:
    ms = result["frame_ms"]
    assert isinstance(ms, dict)
    return (f"{result['avatars']} avatars at {result['width']}x{result['height']} on "
            f"{result['renderer']}: {ms['p50']:.2f} ms per frame p50, {ms['p99']:.2f} ms p99 "
            f"({result['triangles_per_frame']} triangles, budget {result['triangle_budget']})")


if __name__ == "__main__":  # python -m posecast.client.viewer.bench [avatars] [frames]
    import json
    import sys

    n = int(sys.argv[1]) if len(sys.argv) > 1 else 16
    k = int(sys.argv[2]) if len(sys.argv) > 2 else 60
    res = bench_render(n, frames=k, out=sys.argv[3] if len(sys.argv) > 3 else None)
    print(format_render_table(res))
    print(json.dumps(res))
