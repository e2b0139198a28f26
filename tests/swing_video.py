"""Videos for latency-video's tests, made with OpenCV's VideoWriter: what a phone films
when a tracker on a string swings in front of the screen that shows its avatar.

Left: a textured marker (KCF loses a plain square: it has no texture to correlate)
swinging left and right with a wandering period; right: another marker that follows the
same path ``delay`` frames later; pixel noise over everything; 240 fps, MJPG in AVI
(FFmpeg in opencv-python reads and writes it everywhere).

``python tests/swing_video.py OUT.avi DELAY`` writes one and prints its two boxes.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import cv2
import numpy as np

Box = tuple[int, int, int, int]
FPS = 240.0
WIDTH, HEIGHT = 320, 240


def marker(seed: int, cells: int = 6, cell: int = 6) -> np.ndarray:
    """Random black and white cells in a black border, BGR: texture for the trackers."""
    bits = np.random.default_rng(seed).integers(0, 2, (cells, cells)) * 255
    image = np.pad(np.kron(bits, np.ones((cell, cell))), cell).astype(np.uint8)
    return np.repeat(image[:, :, None], 3, axis=2)


def swing(frames: int, fps: float = FPS) -> np.ndarray:
    """Positions in [0, 1] of a swing whose rate wanders between 1 and 2 per second, so
    that no one delay lines the turns up by chance."""
    t = np.arange(frames) / fps
    rate = 1.5 + 0.5 * np.sin(2.0 * np.pi * t / 2.3)
    return 0.5 + 0.5 * np.sin(np.cumsum(2.0 * np.pi * rate / fps))


def write_swing_video(path: Path, delay: int, seconds: float = 3.0, fps: float = FPS,
                      still: bool = False, seed: int = 0,
                      display_hz: float | None = None) -> tuple[Box, Box]:
    """Write the video; return the (tracker, avatar) boxes in its first frame. ``still``:
    neither marker moves (a video without motion). ``display_hz``: the avatar changes only
    at this refresh rate (a 90 Hz screen filmed at 240 fps), which adds to the delay
    half a refresh on average and spreads it."""
    rng = np.random.default_rng(seed)
    frames = int(fps * seconds)
    x = swing(frames + delay, fps) if not still else np.full(frames + delay, 0.5)
    tracker, avatar = marker(1), marker(2)
    size = tracker.shape[0]
    travel = WIDTH // 2 - size - 20
    noise = [rng.normal(0.0, 8.0, (HEIGHT, WIDTH, 1)) for _ in range(16)]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps,
                             (WIDTH, HEIGHT))
    boxes: tuple[Box, Box] | None = None
    try:
        for i in range(delay, frames + delay):
            frame = np.full((HEIGHT, WIDTH, 3), 110.0)
            xt = round(10 + x[i] * travel)
            # the screen shows its newest refresh, of the pose ``delay`` frames before it
            refresh = i if display_hz is None else round(
                math.floor(i / fps * display_hz + 1e-9) * fps / display_hz)
            xa = round(WIDTH // 2 + 10 + x[max(refresh - delay, 0)] * travel)
            frame[60:60 + size, xt:xt + size] = tracker
            frame[140:140 + size, xa:xa + size] = avatar
            writer.write(np.clip(frame + noise[i % len(noise)], 0, 255).astype(np.uint8))
            if boxes is None:
                boxes = (xt, 60, size, size), (xa, 140, size, size)
    finally:
        writer.release()
    assert boxes is not None
    return boxes


if __name__ == "__main__":
    print(write_swing_video(Path(sys.argv[1]), int(sys.argv[2])))
