"""`posecast latency-video --plot`: the picture people check a measurement with.

Top: both smoothed, normalised traces over time, their turns (maxima as upward, minima
as downward triangles) and a line from each tracker turn to the avatar turn it was paired
with. Bottom: the delay of each pair over time, their mean (eq. 15) and the
cross-correlation estimate. A pairing gone wrong (a skipped swing, a box that slipped)
shows as a long slanted line on top and a dot far from the others below.
Drawn with Pillow and ``client.plot``'s ticks, as the other plots (no matplotlib).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from posecast.client.measure.plot import COLORS, nice_ticks
from posecast.solver.video_latency import Peaks, VideoLatency

WIDTH = 1100
TOP_HEIGHT, BOTTOM_HEIGHT = 380, 230
LEFT, RIGHT, TOP, BOTTOM = 70, 20, 46, 44
TRACKER_COLOR, AVATAR_COLOR, PAIR_COLOR = COLORS[0], COLORS[1], (120, 120, 120)
MEAN_COLOR, XCORR_COLOR = COLORS[2], COLORS[3]

Scale = Callable[[float], float]


def _axes(draw: ImageDraw.ImageDraw, font: ImageFont.ImageFont | ImageFont.FreeTypeFont,
          box: tuple[int, int, int, int], x_ticks: list[float], y_ticks: list[float],
          title: str, x_label: str) -> tuple[Scale, Scale]:
    """Frame, grid and tick labels of one panel; the data-to-pixel maps."""
    left, top, right, bottom = box
    x0, x1, y0, y1 = x_ticks[0], x_ticks[-1], y_ticks[0], y_ticks[-1]

    def px(x: float) -> float:
        return left + (x - x0) / (x1 - x0) * (right - left)

    def py(y: float) -> float:
        return bottom - (y - y0) / (y1 - y0) * (bottom - top)

    for y in y_ticks:
        draw.line([(left, py(y)), (right, py(y))], fill=(228, 228, 228))
        draw.text((left - 6, py(y)), f"{y:.6g}", fill="black", font=font, anchor="rm")
    for x in x_ticks:
        draw.line([(px(x), top), (px(x), bottom)], fill=(242, 242, 242))
        draw.line([(px(x), bottom), (px(x), bottom + 4)], fill="black")
        draw.text((px(x), bottom + 6), f"{x:.6g}", fill="black", font=font, anchor="mt")
    draw.rectangle([left, top, right, bottom], outline="black")
    draw.text((left, top - 8), title, fill="black", font=font, anchor="lb")
    draw.text(((left + right) / 2, bottom + 22), x_label, fill="black", font=font, anchor="mt")
    return px, py


def _triangle(draw: ImageDraw.ImageDraw, x: float, y: float, up: bool,
              color: tuple[int, int, int], size: float = 6.0) -> None:
    tip = -size if up else size
    draw.polygon([(x, y + tip), (x - size, y - tip / 2), (x + size, y - tip / 2)],
                 fill=color, outline="black")


def _value_at(trace: np.ndarray, frame: float) -> float:
    return float(np.interp(frame, np.arange(len(trace)), trace))


def plot_latency(result: VideoLatency, path: Path, title: str = "") -> None:
    """Write the two-panel picture of ``result`` to ``path`` (PNG)."""
    image = Image.new("RGB", (WIDTH, TOP_HEIGHT + BOTTOM_HEIGHT), "white")
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default()
    to_ms = 1000.0 / result.fps
    n = len(result.tracker)
    times = np.arange(n) * to_ms
    x_ticks = nice_ticks(0.0, max(float(times[-1]), 1.0), 10)
    low = float(min(result.tracker.min(), result.avatar.min()))
    high = float(max(result.tracker.max(), result.avatar.max()))
    y_ticks = nice_ticks(low, high)
    doc = result.as_json()
    headline = (f"latency {doc['latency_ms']:.1f} ms +- {doc['latency_std_ms']:.1f} "
                f"({doc['peaks']} turns paired), cross-correlation "
                f"{doc['xcorr_latency_ms']:.1f} ms, {result.fps:g} fps")
    px, py = _axes(draw, font, (LEFT, TOP, WIDTH - RIGHT, TOP_HEIGHT - BOTTOM), x_ticks,
                   y_ticks, f"{title}: {headline}" if title else headline, "time (ms)")
    draw.text((LEFT, 12), "horizontal position, smoothed and normalised"
              + (" (avatar mirrored)" if result.mirrored else ""), fill="black", font=font)
    # every trace point is drawn: a few thousand frames make a few thousand segments
    for trace, color in ((result.tracker, TRACKER_COLOR), (result.avatar, AVATAR_COLOR)):
        draw.line([(px(t), py(v)) for t, v in zip(times, trace, strict=True)],
                  fill=color, width=2)
    for t_frame, a_frame in result.pairs:  # a bracket beyond each pair of turns
        yt = py(_value_at(result.tracker, t_frame))
        ya = py(_value_at(result.avatar, a_frame))
        out = -14.0 if _value_at(result.tracker, t_frame) > 0 else 14.0
        bar = (min(yt, ya) if out < 0 else max(yt, ya)) + out
        draw.line([(px(t_frame * to_ms), yt + out / 2), (px(t_frame * to_ms), bar),
                   (px(a_frame * to_ms), bar), (px(a_frame * to_ms), ya + out / 2)],
                  fill=PAIR_COLOR, width=2)
    for peaks, trace, color in ((result.tracker_peaks, result.tracker, TRACKER_COLOR),
                                (result.avatar_peaks, result.avatar, AVATAR_COLOR)):
        _draw_peaks(draw, peaks, trace, color, to_ms, px, py)
    _legend(draw, font, WIDTH - RIGHT, TOP - 20, [("tracker", TRACKER_COLOR),
                                                  ("avatar", AVATAR_COLOR),
                                                  ("paired turns", PAIR_COLOR)])

    lags = [(t * to_ms, (a - t) * to_ms) for t, a in result.pairs]
    mean_ms, xcorr_ms = result.latency_ms, result.xcorr_frames * to_ms
    values = [lag for _, lag in lags] + [mean_ms, xcorr_ms]
    spread = max(max(values) - min(values), 2.0)
    lag_ticks = nice_ticks(min(values) - spread * 0.2, max(values) + spread * 0.2, 4)
    top2 = TOP_HEIGHT + TOP
    qx, qy = _axes(draw, font, (LEFT, top2, WIDTH - RIGHT, TOP_HEIGHT + BOTTOM_HEIGHT
                                - BOTTOM), x_ticks, lag_ticks,
                   "delay of each pair (ms)", "time of the tracker's turn (ms)")
    for value, color in ((mean_ms, MEAN_COLOR), (xcorr_ms, XCORR_COLOR)):
        y = qy(value)
        for x in range(LEFT, WIDTH - RIGHT, 12):  # dashed
            draw.line([(x, y), (min(x + 6, WIDTH - RIGHT), y)], fill=color, width=2)
    for t, lag in lags:
        draw.ellipse([qx(t) - 4, qy(lag) - 4, qx(t) + 4, qy(lag) + 4], fill=PAIR_COLOR,
                     outline="black")
    _legend(draw, font, WIDTH - RIGHT, top2 - 20, [("pair", PAIR_COLOR),
                                                   ("mean of pairs", MEAN_COLOR),
                                                   ("cross-correlation", XCORR_COLOR)])
    image.save(path)


def _draw_peaks(draw: ImageDraw.ImageDraw, peaks: Peaks, trace: np.ndarray,
                color: tuple[int, int, int], to_ms: float, px: Scale, py: Scale) -> None:
    for frame, kind in zip(peaks.frames, peaks.kinds, strict=True):
        value = _value_at(trace, float(frame))
        if math.isfinite(value):
            _triangle(draw, px(float(frame) * to_ms), py(value), kind > 0, color)


def _legend(draw: ImageDraw.ImageDraw, font: ImageFont.ImageFont | ImageFont.FreeTypeFont,
            right: int, y: int, entries: list[tuple[str, tuple[int, int, int]]]) -> None:
    x = right
    for name, color in reversed(entries):
        x -= int(draw.textlength(name, font=font)) + 30
        draw.line([(x, y), (x + 16, y)], fill=color, width=3)
        draw.text((x + 20, y), name, fill="black", font=font, anchor="lm")
