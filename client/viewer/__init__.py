"""The viewer: every avatar of a room, skinned on the GPU, in a window or to PNG files.

Modules, in the order a frame uses them:
- ``interpolation``: snapshot buffers; SLERP between frames at an adaptive delay, or
  the newest frame (zero-buffer). Pure.
- ``skinning``: the mesh fitted to each avatar's calibrated skeleton, joint matrices,
  and the numpy reference linear blend skinning. Pure.
- ``camera``: orbit, first-person and mirror cameras. Pure.
- ``lod``: the mesh's levels of detail and the per-frame triangle budget. Pure.
- ``renderer``: moderngl drawing (skinning in the vertex shader, transform-feedback
  read-back of skinned vertices, floor grid), offscreen through EGL or into a window.
- ``overlay``: name labels and the HUD (Pillow text as textures).
- ``scene``/``core``: a running spectator's room turned into frames, with latency
  accounting (``capture_to_render``, ``receive_to_render``).
- ``headless``, ``window``: the two ways to show them; ``bench``: ms per frame.

Entry points (for ``posecast view`` and ``posecast demo --render DIR``):
``run_headless_viewer``, ``render_spectator``, ``HeadlessViewerProcess``,
``run_window_viewer``; ``client.viewer.bench.bench_render``.

Imports protocol/, solver/, client.session (its spectator), client.sources (the clips it
renders in benches) and client.measure (latency accounting); never cli or bench.
"""

from posecast.client.viewer.core import Viewer, ViewerStats
from posecast.client.viewer.headless import (
    HeadlessStats,
    HeadlessViewerProcess,
    ViewerProcessError,
    render_spectator,
    run_headless_viewer,
)
from posecast.client.viewer.interpolation import Interpolator, Mode
from posecast.client.viewer.renderer import GLUnavailableError, Renderer
from posecast.client.viewer.scene import SpectatorScene, ViewerSpectator, ViewMode
from posecast.client.viewer.window import NoDisplayError, check_display, run_window_viewer

__all__ = [
    "GLUnavailableError",
    "HeadlessStats",
    "HeadlessViewerProcess",
    "Interpolator",
    "Mode",
    "NoDisplayError",
    "Renderer",
    "SpectatorScene",
    "ViewMode",
    "Viewer",
    "ViewerProcessError",
    "ViewerSpectator",
    "ViewerStats",
    "check_display",
    "render_spectator",
    "run_headless_viewer",
    "run_window_viewer",
]
