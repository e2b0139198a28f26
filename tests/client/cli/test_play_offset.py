"""Players replaying one clip stand apart: `play --offset X,Z` moves every streamed pose
by exactly X,Z metres and nothing else, and the demo gives each of its players a spot
of its own."""

from __future__ import annotations

import asyncio
import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from posecast.client.bench import demo
from posecast.client.builtin import builtin_motion_path
from posecast.client.cli import _parser
from posecast.client.session.player import PlayerStats
from posecast.client.sources import OffsetSource, PoseSource, open_source

CLIP = f"bvh:{builtin_motion_path()}"


def test_an_offset_moves_positions_by_exactly_x_z_and_keeps_rotations() -> None:
    plain, moved = open_source(CLIP), open_source(CLIP, offset=(1.5, -2.25))
    assert isinstance(moved, OffsetSource)
    shift = np.array([1.5, 0.0, -2.25])
    pairs = [(plain.calibration(), moved.calibration())]
    pairs += [(plain.read(), moved.read()) for _ in range(20)]  # type: ignore[misc]
    for a, b in pairs:
        assert a is not None and b is not None and a.roles == b.roles
        np.testing.assert_array_equal(b.positions, a.positions + shift)
        np.testing.assert_array_equal(b.rotations, a.rotations)


def test_no_offset_is_the_source_itself() -> None:
    assert not isinstance(open_source(CLIP), OffsetSource)


def test_the_offset_leaves_the_wrapped_samples_alone() -> None:
    inner = open_source(CLIP)
    before = inner.calibration().poses.copy()
    OffsetSource(inner, (3.0, 4.0)).calibration()
    np.testing.assert_array_equal(inner.calibration().poses, before)


def test_play_parses_the_offset() -> None:
    base = ["play", "--server", "ws://127.0.0.1:1", "--room", "r"]
    assert _parser().parse_args(base).offset == (0.0, 0.0)
    assert _parser().parse_args([*base, "--offset", "-1.5,2"]).offset == (-1.5, 2.0)


def test_the_demo_players_stand_apart(monkeypatch: pytest.MonkeyPatch) -> None:
    spots: list[tuple[float, float]] = []

    async def fake_player(url: str, room: str, name: str, source: PoseSource,
                          **_: object) -> PlayerStats:
        hip = source.calibration()
        i = hip.roles.index("hip")
        spots.append((float(hip.positions[i, 0]), float(hip.positions[i, 2])))
        return PlayerStats()

    monkeypatch.setattr(demo, "run_player", fake_player)
    asyncio.run(demo.run_players("ws://unused", 6, 0.1, Path(builtin_motion_path())))
    assert len(spots) == 6
    # every pair at least a metre apart: their bodies and name labels do not merge
    for a, b in itertools.combinations(spots, 2):
        assert math.dist(a, b) >= 1.0, (a, b)
