"""The browser page's recording as `posecast demo --browser` reads it back
(client/bench/browser.py): its columns in recording.js's layout, its epoch clock moved
onto perf_counter, and the replay of what it was given, which must present the roots the
page drew; a root the page drew otherwise is found. (tests/client/web/test_demo_browser.py
does the same with the real page in Chromium.)"""

from __future__ import annotations

import base64
from typing import Any

import numpy as np
import pytest

from posecast.client.bench.browser import (
    FRAME_FIELDS,
    PRESENT_FIELDS,
    REPLAY_TOLERANCE_M,
    PageRecording,
)
from posecast.client.viewer.interpolation import Interpolator, Mode
from posecast.protocol import AvatarFrame
from posecast.solver import rotations as R

EPOCH = 1.8e9  # the page's clock: seconds since the epoch
WALL_MINUS_PERF = EPOCH - 50.0  # this process' perf_counter read 50 s at the page's EPOCH
OFFSET = 0.25  # the server's clock minus the page's... on top of the epoch
SYNCED_AFTER_S = 0.3
AVATARS = (2, 5)
JOINTS = 4


def _b64(values: list[float]) -> str:
    return base64.b64encode(np.asarray(values, dtype="<f8").tobytes()).decode()


def _page(mode: Mode, seed: int = 3) -> tuple[dict[str, Any], int]:
    """A recording as the page would make it: its own playout (the Python one, which the
    parity test holds equal) fed and sampled on the page's clock. Also how many roots."""
    rng = np.random.default_rng(seed)
    server_minus_page = -EPOCH + 100.0 + OFFSET  # server clock: ~100 s
    arrivals = []
    for a in AVATARS:
        for i in range(120):
            tc = 100.0 + i / 90.0 + a * 1e-3
            arrivals.append((tc - server_minus_page + 0.04 + rng.uniform(-0.01, 0.01), a, i,
                             tc, R.from_rotvec(np.sin(tc + np.arange(JOINTS * 3)
                                                      .reshape(JOINTS, 3))),
                             np.array([np.sin(tc), 0.9, np.cos(tc)])))
    arrivals.sort(key=lambda f: f[0])
    t0 = arrivals[0][0]
    playout = Interpolator(mode=mode)
    frames: list[float] = []
    rotations: list[float] = []
    roots: list[float] = []
    presents: list[float] = []
    drawn: list[float] = []
    pushed = 0
    for k in range(80):
        now = t0 + k / 60.0
        offset = server_minus_page if now > t0 + SYNCED_AFTER_S else None
        # a frame is pushed when its message event runs: sometimes a frame late
        while pushed < len(arrivals) and arrivals[pushed][0] <= now - (0.017 if k % 3 else 0):
            t, a, seq, tc, rot, root = arrivals[pushed]
            playout.push(AvatarFrame.model_construct(
                avatar_id=a, seq=seq, t_capture=tc, rotations=rot, root=root), t)
            frames += [t, np.nan if offset is None else offset, a, seq, tc, JOINTS]
            rotations += rot.ravel().tolist()
            roots += root.tolist()
            pushed += 1
        shown = playout.sample(now, None if offset is None else (lambda x, o=offset: x + o))
        presents += [now, np.nan if offset is None else offset, pushed, len(shown)]
        for a, s in shown.items():
            drawn += [a, *s.root.tolist()]
    dump = {"frameFields": FRAME_FIELDS, "presentFields": PRESENT_FIELDS,
            "frames": _b64(frames), "rotations": _b64(rotations), "roots": _b64(roots),
            "presents": _b64(presents), "drawn": _b64(drawn)}
    return dump, len(drawn) // 4


@pytest.mark.parametrize("mode", list(Mode))
def test_the_replay_of_a_recording_presents_what_the_page_drew(mode: Mode) -> None:
    dump, roots = _page(mode)
    recording = PageRecording.from_dump(dump, WALL_MINUS_PERF)
    # the page's epoch seconds, on perf_counter: ~50 s, as the capture logs' are
    assert 49.0 < recording.instants[0] < 52.0
    assert 49.0 < recording.arrivals[0].t_local < 52.0
    assert recording.pushed_before[-1] == len(recording.arrivals)  # all it was given
    assert (np.diff(recording.pushed_before) >= 0).all()
    gap, checked = recording.replay_gap_m(mode)
    assert checked == roots > 100
    # the page computes on epoch seconds (a 2.4e-7 s step at 1.8e9): ~1e-7 m of rounding
    assert gap <= REPLAY_TOLERANCE_M


def test_a_root_the_page_drew_otherwise_is_found() -> None:
    dump, _ = _page(Mode.PREDICT)
    drawn = np.frombuffer(base64.b64decode(dump["drawn"]), dtype="<f8").copy()
    drawn[-2] += 0.001  # one coordinate of the last root drawn, 1 mm off
    dump["drawn"] = base64.b64encode(drawn.tobytes()).decode()
    gap, _ = PageRecording.from_dump(dump, WALL_MINUS_PERF).replay_gap_m(Mode.PREDICT)
    assert gap == pytest.approx(0.001, abs=1e-9) and gap > REPLAY_TOLERANCE_M


def test_a_recording_of_another_layout_is_refused_in_one_line() -> None:
    dump, _ = _page(Mode.INTERPOLATE)
    with pytest.raises(ValueError, match="a page of another version"):
        PageRecording.from_dump({**dump, "presentFields": 3}, WALL_MINUS_PERF)
