"""Shared pytest fixtures.

The real recordings (Vive csv, BVH) are not part of the repository: they live in
``../shared/data`` beside it. Tests that need them ask ``shared_data`` for a path and are
skipped, with the reason, where the data is absent.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path

import pytest

from posecast.client.viewer.bench import Clip, solve_builtin_clip
from posecast.client.viewer.renderer import GLUnavailableError, Renderer
from posecast.server.app import Session
from posecast.server.serving import run_server
from posecast.solver.motion import ViveRecording
from posecast.solver.readers.vive import read_vive

REPO_ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"
SERVER_TIMEOUT = 10.0  # seconds for a test server to start or to stop


@pytest.fixture(autouse=True)
def _fresh_stream_codings() -> Iterator[None]:
    """Each test's own rosters' codings (tests/stream_decode.py): every server a test
    starts numbers its avatars from 1 again."""
    import stream_decode

    stream_decode.CODINGS.clear()
    stream_decode.CODINGS.plans.clear()
    yield



def shared_data_path(path: str) -> Path:
    """``../shared/data/<path>``; skips the calling test when it is absent."""
    full = SHARED_DATA / path
    if not full.exists():
        pytest.skip(f"../shared/data/{path} is absent: the real recordings live beside "
                    f"the project, not in it")
    return full


@pytest.fixture(scope="session")
def walk_vive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Half a second of the built-in CMU walk as a Vive recording (frame 0 the T-pose),
    made by posecast's own code: the paper authors' recordings stay in ../shared."""
    from posecast.client.builtin import builtin_motion_path
    from posecast.client.sources.bvh_source import tracker_recording
    from posecast.solver.readers.vive import format_vive

    path = tmp_path_factory.mktemp("vive") / "walk_vive.csv"
    path.write_text(format_vive(tracker_recording(builtin_motion_path(), seconds=0.5)))
    return path


@pytest.fixture
def shared_data() -> Callable[[str], Path]:
    """``shared_data("vive/kicking.csv")``: the path of a real data file, or a skip."""
    return shared_data_path


@pytest.fixture(scope="module")
def recording() -> ViveRecording:
    """The walking clip of the Vive recordings: a player's tracker frames."""
    return read_vive(shared_data_path("vive/walking.csv"))


@pytest.fixture(scope="session")
def egl() -> None:
    """Headless OpenGL (EGL; Mesa's llvmpipe without a GPU), or a skip that says why."""
    from posecast.client.viewer.renderer import GLUnavailableError, create_headless_context

    try:
        create_headless_context().release()
    except GLUnavailableError as err:
        pytest.skip(f"no headless OpenGL: {err}")


@contextlib.asynccontextmanager
async def serving(session: Session) -> AsyncIterator[str]:
    """A real server for ``session`` on a free port of 127.0.0.1, for the length of the
    block; yields its URL and shuts it down cleanly after."""
    session.rooms.clear()
    stop = asyncio.Event()
    ready: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    server = asyncio.create_task(run_server("127.0.0.1", 0, session, stop, ready.set_result))
    port = await asyncio.wait_for(ready, SERVER_TIMEOUT)
    try:
        yield f"ws://127.0.0.1:{port}"
    finally:
        stop.set()
        await asyncio.wait_for(server, SERVER_TIMEOUT)


VIEW_W, VIEW_H = 640, 480  # the viewer tests' offscreen frame


@pytest.fixture(scope="module")
def renderer() -> Iterator[Renderer]:
    """A headless renderer of VIEW_W x VIEW_H (skipped without OpenGL), per test module."""
    try:
        r = Renderer.standalone(VIEW_W, VIEW_H)
    except GLUnavailableError as err:
        pytest.skip(f"no headless OpenGL: {err}")
    yield r
    r.release()
    r.ctx.release()


@pytest.fixture(scope="module")
def clip() -> Clip:
    """The built-in walk, solved: skeleton and poses to draw."""
    return solve_builtin_clip()
