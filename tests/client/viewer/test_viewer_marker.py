"""`posecast view --marker`: the latency-video marker lands on the projected joint, in
the renderer and in a headless viewer watching a real player over a real socket."""

from __future__ import annotations

import asyncio
import gc
import json
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import VIEW_H, VIEW_W, serving
from PIL import Image
from swing_video import marker, swing

from posecast.client.builtin import builtin_motion_path
from posecast.client.cli import _parser
from posecast.client.session.player import run_player
from posecast.client.sources.bvh_source import BvhSource
from posecast.client.viewer.bench import Clip
from posecast.client.viewer.camera import OrbitCamera
from posecast.client.viewer.headless import HeadlessStats, run_headless_viewer
from posecast.client.viewer.marker import (
    CELLS,
    MARKER_JOINTS,
    MarkerOverlay,
    marker_centres,
    marker_image,
    marker_size,
)
from posecast.client.viewer.renderer import AvatarDraw, Renderer
from posecast.client.viewer.skinning import fit_avatar, template_avatar
from posecast.server.app import Session

W, H = VIEW_W, VIEW_H




def find_marker(image: np.ndarray) -> tuple[float, tuple[float, float]]:
    """(match score, centre in pixels) of the best match of the marker in ``image``."""
    size = marker_size(image.shape[0])
    template = np.ascontiguousarray(marker_image(size)[:, :, :3])
    scores = cv2.matchTemplate(np.ascontiguousarray(image), template, cv2.TM_CCOEFF_NORMED)
    _, best, _, (x, y) = cv2.minMaxLoc(scores)
    return float(best), (x + size / 2.0, y + size / 2.0)


def test_the_pattern_is_textured_and_sized_to_the_frame() -> None:
    size = marker_size(720)
    assert size == 720 // 8 // CELLS * CELLS and size % CELLS == 0
    image = marker_image(size)
    assert image.shape == (size, size, 4) and (image[:, :, 3] == 255).all()
    gray = image[:, :, 0]
    assert set(np.unique(gray)) == {0, 255}
    cell = size // CELLS
    assert (gray[0] == 255).all() and (gray[cell + 1, cell:-cell] == 0).all()  # quiet, border
    inner = gray[2 * cell:-2 * cell, 2 * cell:-2 * cell]
    assert 0.3 < (inner == 255).mean() < 0.7  # half the bits white: texture to follow
    assert not np.array_equal(inner, inner[:, ::-1]) and not np.array_equal(inner, inner.T)


@pytest.mark.parametrize(("joint", "frame"), [("right_hand", 0), ("right_hand", 90),
                                              ("left_foot", 40), ("head", 120)])
def test_marker_is_drawn_where_the_joint_projects(renderer: Renderer, clip: Clip,
                                                  joint: str, frame: int) -> None:
    m = renderer.mesh
    posed = renderer.pose([AvatarDraw(fit_avatar(m, clip.info), clip.rotations[frame],
                                      clip.roots[frame])])
    centre = posed.global_pos[0].mean(axis=0)
    camera = OrbitCamera(yaw=30.0, pitch=10.0, distance=3.0,
                         target=(float(centre[0]), float(centre[1]), float(centre[2]))
                         ).camera(W / H)
    renderer.render(posed, camera)
    without = renderer.read().copy()
    index = m.skeleton.index(MARKER_JOINTS[joint])
    centres = marker_centres(posed, index, camera, W, H)
    assert len(centres) == 1
    overlay = MarkerOverlay(renderer.ctx)
    try:
        overlay.draw(centres, W, H)
    finally:
        overlay.release()
    score, found = find_marker(renderer.read())
    assert score > 0.99
    assert abs(found[0] - centres[0][0]) <= 1.0 and abs(found[1] - centres[0][1]) <= 1.0
    assert find_marker(without)[0] < 0.8  # the avatar alone does not look like it


def test_headless_viewer_draws_the_marker_on_a_live_player(egl: None,
                                                           tmp_path: Path) -> None:
    async def main() -> HeadlessStats:
        async with serving(Session()) as url:
            source = BvhSource(builtin_motion_path(), loop=True, rate_hz=90.0)
            stop = asyncio.Event()
            player = asyncio.create_task(run_player(url, "marked", "swinger", source,
                                                    stop=stop))
            try:
                return await asyncio.wait_for(run_headless_viewer(
                    url, "marked", 4, tmp_path, W, H, interval_ms=50.0, timeout=60.0,
                    marker="right_hand"), 120)
            finally:
                stop.set()
                await asyncio.wait_for(player, 10)

    stats = asyncio.run(main())
    assert stats.frames == 4
    for path in sorted(tmp_path.glob("frame_*.png")):
        score, _ = find_marker(np.asarray(Image.open(path).convert("RGB")))
        assert score > 0.95, path


def test_latency_video_follows_the_rendered_marker(egl: None, tmp_path: Path) -> None:
    """Film posecast itself, synthetically: on the left a textured tracker swinging, on
    the right the viewer's frames (the avatar carried by the same swing, --marker on its
    right hand) rendered at 90 Hz and showing each pose 10 camera frames late. KCF must
    follow the rendered marker, and the tool find 10 frames plus the 90 Hz hold (1.125
    on average with swing_video's refresh times)."""
    delay, fps, hz, frames = 10, 240.0, 90.0, 720
    x = swing(frames + delay)
    # a context of its own, made current as it is made: other tests' contexts (the live
    # viewer's) may have been current in this thread, and collected ones may release
    gc.collect()
    renderer = Renderer.standalone(W, H)
    m = renderer.mesh
    avatar = template_avatar(m)
    rest = np.tile([0.0, 0.0, 0.0, 1.0], (m.skeleton.num_joints, 1))
    root0 = m.skeleton.offsets[0]
    camera = OrbitCamera(yaw=0.0, pitch=5.0, distance=3.0,
                         target=(float(root0[0]), 1.0, float(root0[2]))).camera(W / H)
    hand = m.skeleton.index(MARKER_JOINTS["right_hand"])
    overlay = MarkerOverlay(renderer.ctx)
    tracker = marker(1)
    size = tracker.shape[0]
    path = tmp_path / "posecast_filmed.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (2 * W, H))
    boxes: list[str] = []
    shown, shown_refresh = np.zeros((H, W, 3), np.uint8), -1
    try:
        for i in range(delay, frames + delay):
            refresh = round(math.floor(i / fps * hz + 1e-9) * fps / hz)
            if refresh != shown_refresh:  # the screen draws a new frame
                root = root0 + np.array([1.2 * x[max(refresh - delay, 0)] - 0.6, 0.0, 0.0])
                posed = renderer.pose([AvatarDraw(avatar, rest, root)])
                renderer.render(posed, camera)
                centres = marker_centres(posed, hand, camera, W, H)
                overlay.draw(centres, W, H)
                shown, shown_refresh = renderer.read()[:, :, ::-1].copy(), refresh  # BGR
            left = np.full((H, W, 3), 110, np.uint8)
            xt = round(10 + x[i] * (W - size - 20))
            left[100:100 + size, xt:xt + size] = tracker
            writer.write(np.hstack([left, shown]))
            if not boxes:
                side = marker_size(H)
                cx, cy = centres[0]
                boxes = [f"{xt},100,{size},{size}",
                         f"{W + round(cx - side / 2)},{round(cy - side / 2)},{side},{side}"]
    finally:
        writer.release()
        overlay.release()
        renderer.release()
        renderer.ctx.release()
    result = subprocess.run([sys.executable, "-m", "posecast.client.cli", "latency-video",
                             str(path), "--tracker-box", boxes[0], "--avatar-box", boxes[1],
                             "--json"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    doc = json.loads(result.stdout)
    assert doc["lost_frames"] == {"tracker": 0, "avatar": 0}
    assert abs(doc["frames"] - (delay + 1.125)) <= 1.0, doc
    assert abs(doc["xcorr_frames"] - (delay + 1.125)) <= 1.0, doc


def test_marker_option_defaults_to_the_right_hand() -> None:
    base = ["view", "--server", "ws://127.0.0.1:8765", "--room", "r"]
    assert _parser().parse_args(base).marker is None
    assert _parser().parse_args([*base, "--marker"]).marker == "right_hand"
    assert _parser().parse_args([*base, "--marker", "left_foot"]).marker == "left_foot"
    assert set(MARKER_JOINTS) >= {"head", "hip", "left_hand", "right_hand"}
