"""The browser page as a spectator of `posecast demo --browser`: Debian's Chromium,
headless, driven by playwright in a process of its own, and what it showed read back.

The page records (``&record=1``, client/web/src/recording.js) every frame its playout was
given, with its arrival and clock offset, and every instant it sampled the playout. The
demo replays that through the Python playout, which the parity test
(tests/client/web/test_playout_parity.py) holds equal to the page's, and measures the
display error (``measure_display_error``) at a display's 60 Hz, as the desktop modes' are
(fed what the page received when its network worker received it), and at the page's own
frames. Those are a few a second here, where Chromium draws on the CPU beside the players
and spectators, and fall later after the newest frame than a display's instants do (a
longer prediction: the main thread draws, then takes the queued messages), so their
figure says as much about this machine's renderer as about the page. The page also
records the roots it drew: the replay must give the same (``replay_gap_m``).
"""

from __future__ import annotations

import base64
import contextlib
import multiprocessing as mp
import shutil
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast.client.measure.display_error import (
    Arrival,
    CaptureLog,
    clock_error_ms,
    measure_display_error,
    percentiles,
    replay_playout,
)
from posecast.client.viewer.interpolation import Mode
from posecast.protocol import AvatarFrame
from posecast.solver.rig import Rig

Array = NDArray[np.float64]
CHROMIUM = Path("/usr/bin/chromium")
# the closed network makes Chromium hang on its background requests without these
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync",
                 # WebGL on the CPU (SwiftShader), which newer builds want asked for
                 "--enable-unsafe-swiftshader"]
# small: Chromium draws on the clients' core, with the spectators it is compared with
VIEWPORT = {"width": 640, "height": 360}
START_TIMEOUT_S = 60.0  # a loaded machine starts Chromium and loads the mesh slowly
FRAME_FIELDS = 6  # recording.js: tArrival, offset, avatar id, seq, tCapture, joints
PRESENT_FIELDS = 4  # recording.js: t, offset, frames pushed before, avatars drawn
# the page and the Python playout agree to ~1e-9 (the parity test), and the page's epoch
# seconds (a 2.4e-7 s step) round its times by ~1e-7 m of motion: a root further off means
# the replay is not of what the page did, and its display error would not be either
REPLAY_TOLERANCE_M = 1e-6
NEEDS = ("the browser spectator needs Debian's chromium (apt-get install chromium) and "
         "playwright (pip install -e '.[dev]')")


class BrowserMissingError(RuntimeError):
    """No Chromium or no playwright on this machine: one line that says how to get them."""


class BrowserFailedError(RuntimeError):
    """The page could not join, or did not hand over its recording: one line."""


def find_chromium() -> str:
    """Chromium's path; BrowserMissingError without it or without playwright."""
    path = shutil.which("chromium") or (str(CHROMIUM) if CHROMIUM.exists() else None)
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        path = None
    if path is None:
        raise BrowserMissingError(NEEDS)
    return path


@dataclass
class PageFrames:
    """The frames the page pushed to its playout on one arrival (``Received``)."""

    avatar_ids: NDArray[np.int64]
    joint_counts: NDArray[np.int64]
    frames: list[AvatarFrame]


@dataclass
class PageRecording:
    """What the page recorded, its times moved onto this process' ``perf_counter`` (the
    players' capture clock): ``arrivals`` for ``measure_display_error``; the instants the
    page sampled its playout at, the clock offset it sampled with (NaN: not synced), how
    many arrivals it had been given by then and the roots it drew ({avatar id: xyz})."""

    arrivals: list[Arrival]
    instants: Array
    offsets: Array
    pushed_before: NDArray[np.int64]
    drawn: list[dict[int, Array]]

    @classmethod
    def from_dump(cls, dump: dict[str, Any], wall_minus_perf: float) -> PageRecording:
        """``dump``: the page's (``window.posecastRecording()``); ``wall_minus_perf``:
        time.time() - time.perf_counter() here (the page's clock is the epoch's)."""
        if (dump.get("frameFields"), dump.get("presentFields")) != (FRAME_FIELDS,
                                                                     PRESENT_FIELDS):
            raise ValueError("the page's recording is not laid out as this demo reads it: "
                             "a page of another version (make web)")
        frames = _column(dump["frames"]).reshape(-1, FRAME_FIELDS)
        rotations, roots = _column(dump["rotations"]), _column(dump["roots"]).reshape(-1, 3)
        arrivals: list[Arrival] = []
        start = 0
        for (t, offset, avatar_id, seq, t_capture, joints), root in zip(frames, roots,
                                                                        strict=True):
            count = int(joints)
            frame = AvatarFrame.model_construct(
                avatar_id=int(avatar_id), seq=int(seq), root=root,
                rotations=rotations[4 * start:4 * (start + count)].reshape(count, 4),
                t_capture=float(t_capture), t_server_receive=float(t_capture),
                t_solved=float(t_capture), t_sent=float(t_capture))
            start += count
            # server = page + offset = (page - wall_minus_perf) + (offset + wall_minus_perf)
            arrivals.append(Arrival(
                float(t) - wall_minus_perf,
                None if np.isnan(offset) else float(offset) + wall_minus_perf,
                PageFrames(np.array([frame.avatar_id]), np.array([count]), [frame])))
        presents = _column(dump["presents"]).reshape(-1, PRESENT_FIELDS)
        drawn_rows = _column(dump["drawn"]).reshape(-1, 4)
        drawn: list[dict[int, Array]] = []
        k = 0
        for n in presents[:, 3].astype(int):
            drawn.append({int(r[0]): r[1:] for r in drawn_rows[k:k + n]})
            k += n
        return cls(arrivals, presents[:, 0] - wall_minus_perf,
                   presents[:, 1] + wall_minus_perf, presents[:, 2].astype(np.int64), drawn)

    def replay_gap_m(self, mode: Mode) -> tuple[float, int]:
        """The largest distance between a root the page drew and the Python playout's
        replay of the same instant (metres: ~1e-9 when they agree), over how many."""
        ids = sorted({i for d in self.drawn for i in d})
        if not ids or not self.arrivals:
            return 0.0, 0
        shown = replay_playout(self.arrivals, self.instants, ids, (mode,), self.offsets,
                               self.pushed_before)
        gap, n = 0.0, 0
        for k, drawn in enumerate(self.drawn):
            for i, root in drawn.items():
                if shown.valid[i][k]:
                    gap = max(gap, float(np.abs(shown.roots[mode.value][i][k] - root).max()))
                    n += 1
        return gap, n


def _column(text: str) -> Array:
    return np.frombuffer(base64.b64decode(text), dtype="<f8").astype(np.float64)


def wall_minus_perf() -> float:
    """time.time() - time.perf_counter(), read where the two readings are closest."""
    best, gap = 0.0, np.inf
    for _ in range(20):
        a = time.perf_counter()
        wall = time.time()
        b = time.perf_counter()
        if b - a < gap:
            best, gap = wall - (a + b) / 2, b - a
    return best


class BrowserSpectator:
    """The page at ``url`` (``/?room=R&mode=M&record=1``) in headless Chromium, in a
    process of its own, for the length of a ``with`` block: ``wait_joined`` once it is in
    the room, ``finish`` for its recording and what it said on its console."""

    def __init__(self, url: str) -> None:
        chromium = find_chromium()
        ctx = mp.get_context("spawn")
        self._pipe, child = ctx.Pipe()
        self._process = ctx.Process(target=_browser_process, args=(child, url, chromium),
                                    name="browser-spectator", daemon=True)

    def __enter__(self) -> BrowserSpectator:
        self._process.start()
        return self

    def wait_joined(self) -> None:
        """Block until the page joined its room; BrowserFailedError with why if it cannot."""
        if not self._pipe.poll(START_TIMEOUT_S):
            raise BrowserFailedError(f"the browser page did not join in {START_TIMEOUT_S:g} s")
        said = self._pipe.recv()
        if said != "joined":
            raise BrowserFailedError(f"the browser page did not join: {said}")

    def finish(self) -> dict[str, Any]:
        """{"recording", "errors"}: what the page recorded, its console's errors."""
        self._pipe.send("finish")
        if not self._pipe.poll(START_TIMEOUT_S):
            raise BrowserFailedError("the browser page did not hand over its recording")
        reply: dict[str, Any] | str = self._pipe.recv()
        if isinstance(reply, str):
            raise BrowserFailedError(f"the browser page failed: {reply}")
        return reply

    def __exit__(self, *exc: object) -> None:
        with contextlib.suppress(OSError):
            self._pipe.send("close")
        self._process.join(START_TIMEOUT_S / 2)
        if self._process.is_alive():
            self._process.kill()


def _browser_process(pipe: Connection, url: str, chromium: str) -> None:
    from playwright.sync_api import sync_playwright

    errors: list[str] = []
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport=VIEWPORT)  # type: ignore[arg-type]
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url)
            deadline = time.monotonic() + START_TIMEOUT_S
            while (phase := page.evaluate("() => window.posecast?.phase")) != "joined":
                if errors or phase in ("failed", "ended", "bad room", "bad mode"):
                    raise RuntimeError(f"phase {phase}: {'; '.join(errors)[:300]}")
                if time.monotonic() > deadline:
                    raise RuntimeError(f"still {phase} after {START_TIMEOUT_S:g} s")
                page.wait_for_timeout(50)
            pipe.send("joined")
            while not pipe.poll(0.05):
                page.wait_for_timeout(50)  # lets playwright hear the console meanwhile
            if pipe.recv() != "finish":
                return
            recording = page.evaluate("() => window.posecastRecording()")
            pipe.send({"recording": recording, "errors": errors})
            pipe.poll(START_TIMEOUT_S)  # "close"
            browser.close()
    except Exception as exc:  # said to the demo, which raises it
        with contextlib.suppress(OSError):
            pipe.send(f"{type(exc).__name__}: {exc}")


@dataclass
class PageMeasure:
    """The browser page's display error in its playout mode (mm, one per instant and
    avatar): at a display's 60 Hz as the desktop modes' (``errors_mm``: what it received,
    when its network worker received it) and at the page's own frames (``own_errors_mm``:
    what it drew; a few a second where Chromium draws on the CPU); its frame rate and
    the replay's largest gap to the roots it drew; its console's errors."""

    mode: str
    errors_mm: Array
    own_errors_mm: Array
    presented: int
    fps: float
    replay_gap_m: float
    replay_checked: int
    console_errors: list[str]
    stamps_back: int = 0  # arrivals the page stamped before the one ahead of them
    # the page's clock estimate minus the true server clock (this machine's), its median
    # over the frames: the error of the offset its prediction reckons with
    clock_error_ms: float | None = None  # None: the page's clock never synced

    def as_json(self) -> dict[str, object]:
        return {"mode": self.mode, "own_frames": percentiles(self.own_errors_mm),
                "presented": self.presented, "fps": round(self.fps, 1),
                "replay_gap_m": self.replay_gap_m, "replay_checked": self.replay_checked,
                "console_errors": self.console_errors, "stamps_back": self.stamps_back,
                "clock_error_ms": self.clock_error_ms}

    def describe(self) -> str:
        own = percentiles(self.own_errors_mm)
        agree = ("the replay gives every root it drew" if self.replay_gap_m <= REPLAY_TOLERANCE_M
                 else f"the replay is {self.replay_gap_m * 1e3:.3f} mm off what it drew")
        return (f"at its own {self.presented} frames ({self.fps:.0f} fps, drawn on the CPU) "
                f"p50 {own['p50']:.1f}, p95 {own['p95']:.1f}; {agree}")


def measure_page(page: dict[str, Any], mode: Mode, captures: list[CaptureLog], rig: Rig,
                 solver: str) -> PageMeasure:
    """``page``: ``BrowserSpectator.finish``'s; its display error replayed through the
    Python playout (see the module docstring): at 60 Hz, as the desktop modes', and at
    the page's own instants, as it drew them."""
    recording = PageRecording.from_dump(page["recording"], wall_minus_perf())
    # given at their stamps, in the order of their stamps: as a display's frames would get
    # them (a worker stamps a message when it takes it, so its stamps should already be)
    stamped = sorted(recording.arrivals, key=lambda a: a.t_local)
    at_60hz = measure_display_error(captures, stamped, rig, solver, modes=(mode,))
    own = measure_display_error(captures, recording.arrivals, rig, solver, modes=(mode,),
                                instants=recording.instants,
                                instant_offsets=recording.offsets,
                                pushed_before=recording.pushed_before)
    gap, checked = recording.replay_gap_m(mode)
    t = recording.instants
    fps = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 0.0
    stamps = np.array([a.t_local for a in recording.arrivals])
    return PageMeasure(mode.value, at_60hz.errors_mm.get(mode.value, np.zeros(0)),
                       own.errors_mm.get(mode.value, np.zeros(0)), len(t), fps, gap, checked,
                       list(page.get("errors", [])), int((np.diff(stamps) < 0).sum()),
                       clock_error_ms(recording.arrivals))
