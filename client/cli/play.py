"""`posecast play`: join a room as a tracked player and stream a source's poses."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from posecast.client.cli.common import cafile_without_tls, fail, session_words

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from posecast.client.headset.displays import Display, SampleFeed
    from posecast.client.headset.view import HeadsetStats
    from posecast.client.session.player import Player
    from posecast.client.sources.base import DeviceSample, PoseSource

MAX_HMD_SCALE = 4.0  # 6048x6720 an eye: beyond, a typo


def _play(args: argparse.Namespace) -> int:
    from posecast.client.cli.console import headset_summary, player_summary
    from posecast.client.session.connection import SessionError
    from posecast.client.session.player import Player
    from posecast.client.sources import open_source
    from posecast.client.sources.base import SourceError
    from posecast.client.viewer.renderer import GLUnavailableError
    from posecast.solver.readers.errors import FormatError

    if (status := cafile_without_tls("play", args)) is not None:
        return status
    if isinstance(args.devices, Path):  # the old spelling of --roles FILE.toml
        print(f"posecast play: --devices {args.devices} is a roles file: say --roles "
              f"{args.devices} (--devices now names a tracker set)", file=sys.stderr)
        args.roles, args.devices = args.devices, None
    headset = args.hmd or args.hmd_out is not None
    if not headset and (args.hmd_frames is not None or args.hmd_scale != 1.0):
        return fail("play", "--hmd-frames and --hmd-scale are for --hmd or --hmd-out DIR")
    if args.hmd and args.source != "openvr":
        return fail("play", "--hmd shows the body your headset tracks: it needs --source "
                            "openvr (a recording's view: --hmd-out DIR)")
    if args.hmd_scale > MAX_HMD_SCALE:
        return fail("play", f"--hmd-scale {args.hmd_scale:g} is over {MAX_HMD_SCALE:g}")
    raw: PoseSource | None = None  # --hmd: the scene application's OpenVR source
    try:
        if args.hmd:
            from posecast.client.sources.openvr_source import open_scene_source
            raw = open_scene_source(args.roles)
            source = open_source_wrapped(raw, args.offset)
        else:
            source = open_source(args.source, args.roles, loop=args.loop, offset=args.offset)
    except (SourceError, FormatError) as err:
        return fail("play", f"--hmd: {err}" if args.hmd else err)
    if args.devices is not None or args.dropouts is not None:
        from posecast.client.sources.tracker_set import TrackerSetSource
        source = TrackerSetSource(source, args.devices, args.dropouts)
    recording = None
    if args.record is not None:
        from posecast.client.sources.recording_source import RecordingSource
        try:
            source = recording = RecordingSource(source, args.record)
        except OSError as err:
            source.close()
            return fail("play", f"--record {args.record}: {err.strerror or err}")
    delay = args.calibrate_in if args.calibrate_in is not None else (
        3.0 if args.source == "openvr" else 0.0)
    hmd: tuple[Display, SampleFeed | None] | None = None
    headset_stats: list[HeadsetStats] = []
    try:
        if headset:
            hmd = _headset_display(args, raw)
        player = Player(args.server, args.room, args.name, source, token=args.token,
                        cafile=args.cafile)
        signum = asyncio.run(_play_live(player, delay, args.seconds, args.source,
                                        args.reconnect, hmd, args, headset_stats))
    except SessionError as err:
        return fail("play", session_words(err))
    except SourceError as err:
        return fail("play", err)
    except GLUnavailableError as err:
        return fail("play", f"the headset view needs OpenGL: {err}")
    finally:
        source.close()
    print(player_summary(player.stats))
    if headset_stats:
        print(headset_summary(headset_stats[0], args.hmd_out))
    if recording is not None:
        print(f"kept {recording.frames} frames in {recording.path}"
              + (f" ({recording.skipped} left out: a device of the first frame was "
                 "missing)" if recording.skipped else ""))
    return 128 + signum if signum else 0


def open_source_wrapped(raw: PoseSource, offset: tuple[float, float]) -> PoseSource:
    """``raw`` moved by ``offset`` as ``open_source`` would."""
    from posecast.client.sources.base import OffsetSource
    return OffsetSource(raw, offset) if offset != (0.0, 0.0) else raw


def _headset_display(args: argparse.Namespace,
                     raw: PoseSource | None) -> tuple[Display, SampleFeed | None]:
    """SteamVR's compositor (``--hmd``: ``raw`` is the scene application's OpenVR
    source), or PNG files (``--hmd-out``) with a Vive's eyes; SourceError if the
    compositor cannot be had."""
    from posecast.client.headset.displays import FileDisplay, SampleFeed
    from posecast.client.headset.stereo import vive_setup
    from posecast.client.sources.base import SourceError
    if args.hmd_out is not None:
        feed = SampleFeed()
        return FileDisplay(feed, vive_setup().scaled(args.hmd_scale), args.hmd_out), feed
    import openvr

    from posecast.client.headset.compositor import Compositor
    from posecast.client.headset.displays import CompositorDisplay
    from posecast.client.sources.openvr_source import OpenVRSource
    assert isinstance(raw, OpenVRSource)
    try:
        compositor = Compositor(raw.system, openvr.VRCompositor())
    except openvr.error_code.OpenVRError as err:
        raise SourceError(f"SteamVR's compositor is not available ({err})") from None
    return CompositorDisplay(compositor, _body_poses(raw, args.devices)), None


def _body_poses(raw: PoseSource, devices: tuple[str, ...] | None
                ) -> Callable[[NDArray[np.void], float], DeviceSample]:
    """The compositor's poses as the player's devices (``--devices``: the same set as
    it streams)."""
    from posecast.client.sources.base import DeviceSample
    from posecast.client.sources.openvr_source import OpenVRSource
    assert isinstance(raw, OpenVRSource)

    def body(poses: NDArray[np.void], t: float) -> DeviceSample:
        sample = raw.sample_of(poses, t)
        if devices is None:
            return sample
        keep = [i for i, r in enumerate(sample.roles) if r in devices]
        return DeviceSample(t, tuple(sample.roles[i] for i in keep), sample.poses[keep])
    return body


async def _play_live(player: Player, delay: float, seconds: float | None,
                     source: str, reconnect: bool = True,
                     hmd: tuple[Display, SampleFeed | None] | None = None,
                     args: argparse.Namespace | None = None,
                     headset_stats: list[HeadsetStats] | None = None) -> int:
    """Stream with a word on stderr about where it joined and a progress line, until
    the source or the time ends or a signal stops it (its number is returned). With
    ``hmd`` (a display and its feed), the room is drawn into it meanwhile; its stats
    go into ``headset_stats``."""
    from posecast.client.cli.console import StatusLine, report_player, run_until_signal
    from posecast.client.session.connection import Reconnect, stop_task

    status = StatusLine("posecast play")
    say: Callable[[str], None] = status.say
    stop = asyncio.Event()
    reporter = asyncio.create_task(report_player(player, status, source))
    headset: contextlib.AbstractAsyncContextManager[object] = contextlib.nullcontext()
    if hmd is not None:
        from posecast.client.headset.session import Headset
        assert args is not None
        headset = live = Headset(player, hmd[0], hmd[1], stop=stop,
                                 mirror_distance=args.mirror or None,
                                 frames=args.hmd_frames)

        def say(text: str) -> None:  # the terminal's line, and the headset's HUD
            status.say(text)
            live.link.say(text)
    if reconnect:  # a word on stderr when the session is lost and when it is back
        player.reconnect = Reconnect(say=say)
    try:
        async with headset:
            _, signum = await run_until_signal(
                _calibrate_and_stream(player, delay, seconds, stop, say), stop)
    finally:
        await stop_task(reporter)
        status.clear()
        if hmd is not None and headset_stats is not None:
            headset_stats.append(live.stats)
    return signum


async def _calibrate_and_stream(player: Player, delay: float, seconds: float | None,
                                stop: asyncio.Event,
                                say: Callable[[str], None] | None = None) -> None:
    """Count the player into the T-pose, then stream; Enter on a terminal recalibrates.
    ``say``: the countdown there too (a headset's HUD)."""
    for left in range(math.ceil(delay), 0, -1):
        line = f"stand in a T-pose, arms out sideways: calibrating in {left} s"
        print(line, flush=True)
        if say is not None:
            say(line)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), min(1.0, delay - (left - 1)))
        if stop.is_set():
            return
    loop = asyncio.get_running_loop()
    interactive = sys.stdin.isatty()
    if interactive:
        def recalibrate() -> None:
            sys.stdin.readline()
            print("recalibrating: hold the T-pose", flush=True)
            player.recalibrate()
        loop.add_reader(sys.stdin.fileno(), recalibrate)
    try:
        await player.run(seconds, stop)
    finally:
        if interactive:
            loop.remove_reader(sys.stdin.fileno())
