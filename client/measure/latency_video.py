"""`posecast latency-video`: the paper's video latency tool, the OpenCV side.

Reads a video of the real tracker and of the screen showing its avatar (a phone at 240
fps), follows the two boxes the user gave with OpenCV's KCF tracker (the paper's choice;
CSRT is slower and steadier), and hands the two horizontal traces to the pure analysis in
``solver.video_latency``. KCF and CSRT ship only in opencv-contrib: the dependency is
``opencv-contrib-python-headless`` (no GUI libraries), so ``--select``'s ROI picker works
only where an OpenCV with a GUI is installed and a display is there; otherwise one line
says so.
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast.solver.video_latency import VideoLatency, VideoLatencyError, measure

Box = tuple[int, int, int, int]  # x, y, width, height in pixels; (x, y) the top-left
TRACKERS = ("kcf", "csrt")
MIN_BOX_PX = 8  # a tracker needs some texture inside its box
MAX_LOST = 0.5  # a box lost in more of the frames than this is not followed at all


class VideoError(ValueError):
    """A video that cannot be measured, in one line; ``status`` 2 for a bad command line
    (a box outside the frame), 1 for a video that does not show a latency."""

    def __init__(self, message: str, status: int = 1) -> None:
        super().__init__(message)
        self.status = status


@dataclass
class Traces:
    """Horizontal box centres per frame (NaN where the tracker lost its box)."""

    tracker_x: NDArray[np.float64]
    avatar_x: NDArray[np.float64]
    fps: float
    width: int
    height: int
    tracker: str


def _cv2() -> Any:
    """OpenCV, with FFmpeg's own messages off: a file it cannot read is our one line,
    not also FFmpeg's ("moov atom not found") on stderr."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
    import cv2

    return cv2


def make_tracker(kind: str) -> Any:
    """A fresh OpenCV tracker: KCF or CSRT, from cv2 (OpenCV >= 4.5.1 contrib) or from
    cv2.legacy (older builds)."""
    cv2 = _cv2()
    name = {"kcf": "TrackerKCF_create", "csrt": "TrackerCSRT_create"}[kind]
    for module in (cv2, getattr(cv2, "legacy", None)):
        create = getattr(module, name, None)
        if create is not None:
            return create()
    raise VideoError(f"this OpenCV ({cv2.__version__}) has no {kind.upper()} tracker: it is "
                     "in opencv-contrib-python-headless, which posecast depends on")


def _open(path: Path) -> tuple[Any, float]:
    cv2 = _cv2()
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise VideoError(f"cannot read {path}: not a video OpenCV can decode")
    return capture, float(capture.get(cv2.CAP_PROP_FPS) or 0.0)


def _check_box(option: str, box: Box, width: int, height: int) -> None:
    x, y, w, h = box
    if w < MIN_BOX_PX or h < MIN_BOX_PX:
        raise VideoError(f"{option} {x},{y},{w},{h} is smaller than {MIN_BOX_PX}x{MIN_BOX_PX}"
                         " pixels: draw it around the whole marker", status=2)
    if x < 0 or y < 0 or x + w > width or y + h > height:
        raise VideoError(f"{option} {x},{y},{w},{h} reaches outside the video's "
                         f"{width}x{height} frame", status=2)


def track_video(path: Path, tracker_box: Box, avatar_box: Box, tracker: str = "kcf",
                progress: Callable[[int, int], None] | None = None) -> Traces:
    """Follow both boxes through the video at ``path``; VideoError if it cannot be read,
    a box is outside its frame, or a box is lost in most frames."""
    cv2 = _cv2()
    capture, fps = _open(path)
    try:
        ok, frame = capture.read()
        if not ok or frame is None:
            raise VideoError(f"cannot read {path}: OpenCV opened it but decoded no frame")
        height, width = frame.shape[:2]
        _check_box("--tracker-box", tracker_box, width, height)
        _check_box("--avatar-box", avatar_box, width, height)
        total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        followers = [make_tracker(tracker), make_tracker(tracker)]
        for follower, box in zip(followers, (tracker_box, avatar_box), strict=True):
            follower.init(frame, box)
        xs: list[list[float]] = [[b[0] + b[2] / 2.0] for b in (tracker_box, avatar_box)]
        while True:
            ok, frame = capture.read()
            if not ok or frame is None:
                break
            for follower, x in zip(followers, xs, strict=True):
                found, (bx, _, bw, _) = follower.update(frame)
                x.append(bx + bw / 2.0 if found else math.nan)
            if progress is not None and len(xs[0]) % 60 == 0:
                progress(len(xs[0]), total)
    finally:
        capture.release()
    traces = Traces(np.asarray(xs[0]), np.asarray(xs[1]), fps, width, height, tracker)
    for option, trace in (("--tracker-box", traces.tracker_x),
                          ("--avatar-box", traces.avatar_x)):
        lost = float(np.mean(~np.isfinite(trace)))
        if lost > MAX_LOST:
            raise VideoError(f"{tracker.upper()} lost {option}'s object in {lost:.0%} of the "
                             "frames: box a textured, high-contrast marker tightly (view "
                             "--marker draws one), or try --tracker csrt")
    return traces


def select_boxes(path: Path) -> tuple[Box, Box]:
    """The two boxes drawn by the user on the first frame (OpenCV's ROI picker)."""
    cv2 = _cv2()
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                 or os.environ.get("WAYLAND_DISPLAY")):
        raise VideoError("--select needs a display (no DISPLAY here): give --tracker-box "
                         "and --avatar-box instead", status=2)
    capture, _ = _open(path)
    try:
        ok, frame = capture.read()
    finally:
        capture.release()
    if not ok or frame is None:
        raise VideoError(f"cannot read {path}: OpenCV opened it but decoded no frame")
    boxes = []
    try:
        for what in ("the tracker", "its avatar on the screen"):
            title = f"posecast: box {what}, then Enter"
            x, y, w, h = (int(v) for v in cv2.selectROI(title, frame, showCrosshair=False))
            cv2.destroyWindow(title)
            if w == 0 or h == 0:
                raise VideoError("--select: no box drawn (cancelled)", status=2)
            boxes.append((x, y, w, h))
    except cv2.error:
        raise VideoError("--select needs an OpenCV with a GUI (pip install "
                         "opencv-contrib-python in place of the headless build): give "
                         "--tracker-box and --avatar-box instead", status=2) from None
    return boxes[0], boxes[1]


def format_result(result: VideoLatency, tracker: str) -> str:
    """The human-readable report of a measurement."""
    doc = result.as_json()
    mirrored = " (avatar mirrored)" if result.mirrored else ""
    return "\n".join([
        f"latency (turns, eq. 15)  {doc['latency_ms']:7.1f} ms +- {doc['latency_std_ms']:.1f}"
        f"   = {doc['frames']:.2f} frames at {result.fps:g} fps, {doc['peaks']} turns paired",
        f"latency (x-correlation)  {doc['xcorr_latency_ms']:7.1f} ms"
        f"   = {doc['xcorr_frames']:.2f} frames, r = {doc['xcorr_r']:.3f}",
        f"turns found: tracker {doc['tracker_peaks']}, avatar {doc['avatar_peaks']}"
        f"; tracked with {tracker.upper()}{mirrored}"])


def run_latency_video(video: Path, tracker_box: Box | None, avatar_box: Box | None, *,
                      tracker: str = "kcf", select: bool = False, fps: float | None = None,
                      plot: Path | None = None, as_json: bool = False) -> int:
    """The command: measure, print (a table or JSON), draw ``plot``; the exit status."""
    from posecast.client.progress import ProgressBar

    try:
        if select:
            tracker_box, avatar_box = select_boxes(video)
        if tracker_box is None or avatar_box is None:
            raise VideoError("needs --tracker-box and --avatar-box (or --select where "
                             "there is a display)", status=2)
        bar = ProgressBar(f"tracking {video.name}")
        try:
            traces = track_video(video, tracker_box, avatar_box, tracker, progress=bar)
        finally:
            bar.close()
        result = measure(traces.tracker_x, traces.avatar_x, fps or traces.fps)
    except VideoLatencyError as err:
        return _fail(f"{video}: {err}", 1)
    except VideoError as err:
        return _fail(str(err), err.status)
    if plot is not None:
        from posecast.client.measure.latency_plot import plot_latency

        plot_latency(result, plot, title=f"{video.name}, {tracker.upper()}")
    doc = result.as_json()
    doc.update({"tracker": tracker, "video": str(video), "video_frames": len(traces.tracker_x),
                "lost_frames": {"tracker": int(np.sum(~np.isfinite(traces.tracker_x))),
                                "avatar": int(np.sum(~np.isfinite(traces.avatar_x)))},
                "tracker_box": list(tracker_box), "avatar_box": list(avatar_box)})
    print(json.dumps(doc) if as_json else format_result(result, tracker))
    return 0


def _fail(message: str, status: int) -> int:
    hint = " (see posecast latency-video --help)" if status == 2 else ""
    print(f"posecast latency-video: {message}{hint}", file=sys.stderr)
    return status
