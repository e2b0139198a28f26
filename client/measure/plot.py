"""Line charts as PNG with Pillow, for bench reports (`posecast bench soak --plot`).

Pillow, not matplotlib: Pillow is a dependency already (the viewer writes PNGs with it),
and a few panels of lines with labelled axes need ~100 lines here; matplotlib would add
a ~40 MB dependency (and its font cache on first use) for one optional bench output.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from PIL import Image, ImageDraw, ImageFont

COLORS = ((31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189))
WIDTH, PANEL_HEIGHT = 960, 300
MARGIN_LEFT, MARGIN_RIGHT, MARGIN_TOP, MARGIN_BOTTOM = 80, 20, 34, 44


@dataclass
class Series:
    name: str
    xs: Sequence[float]
    ys: Sequence[float]


@dataclass
class Panel:
    title: str
    y_label: str
    series: list[Series] = field(default_factory=list)
    # the least y range shown: a flat RSS should look flat, not zoomed into its noise
    min_span: float = 0.0


def nice_ticks(low: float, high: float, count: int = 5) -> list[float]:
    """About ``count`` round tick values (1, 2 or 5 x 10^k apart) covering [low, high]."""
    if not (math.isfinite(low) and math.isfinite(high)):
        return [0.0]
    if high <= low:
        high = low + 1.0
    raw = (high - low) / count
    base = 10.0 ** math.floor(math.log10(raw))
    step = next(m * base for m in (1, 2, 5, 10) if m * base >= raw)
    first = math.floor(low / step) * step
    ticks = []
    k = 0
    while first + k * step <= high + step * 1e-9:
        ticks.append(round(first + k * step, 10))
        k += 1
    if ticks[-1] < high:
        ticks.append(round(first + k * step, 10))
    return ticks


def _label(value: float) -> str:
    return f"{value:.6g}"


def line_chart(path: Path, panels: list[Panel], x_label: str) -> None:
    """``panels`` stacked vertically, sharing the x axis; written to ``path`` as PNG."""
    image = Image.new("RGB", (WIDTH, PANEL_HEIGHT * len(panels)), "white")
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default()
    all_x = [x for p in panels for s in p.series for x in s.xs if math.isfinite(x)]
    x_ticks = nice_ticks(min(all_x, default=0.0), max(all_x, default=1.0))
    x0, x1 = x_ticks[0], x_ticks[-1]
    for i, panel in enumerate(panels):
        top = i * PANEL_HEIGHT + MARGIN_TOP
        bottom = (i + 1) * PANEL_HEIGHT - MARGIN_BOTTOM
        left, right = MARGIN_LEFT, WIDTH - MARGIN_RIGHT
        ys = [y for s in panel.series for y in s.ys if math.isfinite(y)]
        low = min(ys, default=0.0)
        high = max(ys, default=1.0)
        span = max(panel.min_span, 1e-9)
        if high - low < span:  # a flat line: in the middle of a visible range
            middle = (low + high) / 2
            low, high = middle - max(span / 2, 1.0), middle + max(span / 2, 1.0)
        y_ticks = nice_ticks(low, high)
        y0, y1 = y_ticks[0], y_ticks[-1]

        def px(x: float, left: int = left, right: int = right) -> float:
            return left + (x - x0) / (x1 - x0) * (right - left)

        def py(y: float, top: int = top, bottom: int = bottom,
               y0: float = y0, y1: float = y1) -> float:
            return bottom - (y - y0) / (y1 - y0) * (bottom - top)

        for y in y_ticks:  # grid and labels
            draw.line([(left, py(y)), (right, py(y))], fill=(225, 225, 225))
            draw.text((left - 6, py(y)), _label(y), fill="black", font=font, anchor="rm")
        for x in x_ticks:
            draw.line([(px(x), bottom), (px(x), bottom + 4)], fill="black")
            draw.text((px(x), bottom + 6), _label(x), fill="black", font=font, anchor="mt")
        draw.rectangle([left, top, right, bottom], outline="black")
        draw.text((left, top - 6), f"{panel.title} ({panel.y_label})", fill="black",
                  font=font, anchor="lb")
        draw.text(((left + right) / 2, bottom + 22), x_label, fill="black", font=font,
                  anchor="mt")
        legend_x = right
        for k, series in enumerate(panel.series):
            color = COLORS[k % len(COLORS)]
            points = [(px(x), py(y)) for x, y in zip(series.xs, series.ys, strict=True)
                      if math.isfinite(x) and math.isfinite(y)]
            if len(points) > 1:
                draw.line(points, fill=color, width=2)
            elif points:
                (x, y), = points
                draw.ellipse([x - 2, y - 2, x + 2, y + 2], fill=color)
            legend_x -= int(draw.textlength(series.name, font=font)) + 30
            draw.line([(legend_x, top - 10), (legend_x + 16, top - 10)], fill=color, width=2)
            draw.text((legend_x + 20, top - 10), series.name, fill="black", font=font,
                      anchor="lm")
    image.save(path)
