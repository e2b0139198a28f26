"""A batch shared with a helper thread (``solver.ik.shared``, ``server.helper``): the
same poses as the server alone, the helper taking part where a core is free, and an
avatar the helper holds and never finishes taken over by the caller."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest
from numba import njit

from posecast.server.app import Session
from posecast.server.avatars import AvatarSolver
from posecast.solver.atomics import atomic_load
from posecast.solver.ik.shared import (
    CLAIM,
    FIELD,
    MAX_BATCH,
    _claim,
    new_control,
    solve_analytic_shared,
)
from posecast.solver.motion import ViveRecording
from posecast.solver.tracking.layout import ND, STATE_SIZE

N = 8


def poses(rec: ViveRecording, frame: int) -> np.ndarray:
    return np.concatenate([rec.positions[frame], rec.rotations[frame]], axis=1)


def stage_with_losses(solver: AvatarSolver, rec: ViveRecording, a: int, f: int) -> None:
    """Avatar a's frame f, some avatars losing their last devices for a while (the feet
    here): the solve's fill carries them on, whichever thread makes it."""
    keep = len(rec.devices) - 2 if a % 3 == 1 and (f // 10) % 2 else len(rec.devices)
    solver.stage(a, rec.devices[:keep], poses(rec, f + 25 * a)[:keep], f / 90)


@pytest.fixture(scope="module")
def session() -> Session:
    return Session()


def _calibrated(session: Session, rec: ViveRecording, cores: tuple[int, ...]) -> AvatarSolver:
    solver = AvatarSolver(session.rig, helper_cores=cores)
    for a in range(N):
        solver.calibrate(a, rec.devices, rec.positions[0], rec.rotations[0])
    return solver


def test_a_helper_gives_the_same_poses_and_takes_part(session: Session,
                                                     recording: ViveRecording) -> None:
    everywhere = tuple(range(os.cpu_count() or 1))

    def rounds() -> int:
        """59 batches with the helper and without: the same poses. Returns the avatars
        the helper solved."""
        helped, alone = (_calibrated(session, recording, c) for c in (everywhere, ()))
        try:
            for f in range(1, 60):
                for solver in (helped, alone):
                    for a in range(N):
                        stage_with_losses(solver, recording, a, f)
                order = list(range(N)) if f % 2 else [5, 0, 7, 2, 1, 6, 3, 4]  # any rows
                h, a = helped.solve_staged(order), alone.solve_staged(order)
                np.testing.assert_array_equal(h.rotations, a.rotations)
                np.testing.assert_array_equal(h.root, a.root)
                np.testing.assert_array_equal(h.iterations, a.iterations)
                # the helper's fills are copied in: the tracking carries on alike
                for name in ("state", "targets", "weights", "filled"):
                    np.testing.assert_array_equal(getattr(helped.tracking, name),
                                                  getattr(alone.tracking, name))
            helper = helped.helper()
            assert helper is not None
        finally:
            helped.close()
        return helper.handed

    handed = rounds()
    if len(everywhere) >= 2:  # a core free for it while this thread solved: it takes
        # part (on a loaded machine its core may come only in a later round)
        deadline = time.monotonic() + 60
        while handed == 0 and time.monotonic() < deadline:
            handed = rounds()
        assert handed > 0


def test_the_shared_code_without_a_thread_gives_the_same_poses(
        session: Session, recording: ViveRecording) -> None:
    """The warm path's twin (``server.busy``) solves through the helper's compiled code
    with no helper thread: it solves every avatar itself, the poses of a plain solve."""
    threads = threading.active_count()
    shared, plain = AvatarSolver(session.rig, shared=True), AvatarSolver(session.rig)
    for solver in (shared, plain):
        for a in range(N):
            solver.calibrate(a, recording.devices, recording.positions[0],
                             recording.rotations[0])
    for f in range(1, 30):
        for solver in (shared, plain):
            for a in range(N):
                stage_with_losses(solver, recording, a, f)
        order = [5, 0, 7, 2, 1, 6, 3, 4] if f % 2 else [3]
        s, p = shared.solve_staged(order), plain.solve_staged(order)
        np.testing.assert_array_equal(s.rotations, p.rotations)
        np.testing.assert_array_equal(s.root, p.root)
        np.testing.assert_array_equal(s.iterations, p.iterations)
    helper = shared.helper()
    assert helper is not None and helper.handed == 0  # the shared path, all its own
    assert threading.active_count() == threads  # and no thread started for it
    shared.close()


@njit(nogil=True)
def _take_one_and_vanish(control: np.ndarray) -> int:
    """A helper that claims an avatar of the next batch and never finishes it."""
    while (atomic_load(control, CLAIM) >> FIELD) & MAX_BATCH == 0:
        pass
    i, _ = _claim(control)
    return i


def test_an_avatar_the_helper_never_finishes_is_taken_over(session: Session,
                                                          recording: ViveRecording) -> None:
    J = session.rig.skeleton.num_joints
    warm = new_control()
    warm[CLAIM] = 1 << FIELD  # a batch of one: compiled now, not while the batch runs
    assert _take_one_and_vanish(warm) == 0

    def attempt() -> int:
        """One batch with a helper that claims an avatar and vanishes: the caller solves
        all eight. Returns the avatar it held (-1: it came after the caller took all,
        which a loaded machine may make it do)."""
        ref = _calibrated(session, recording, ())
        shared = _calibrated(session, recording, ())
        for solver in (ref, shared):
            for a in range(N):
                solver.stage(a, recording.devices, poses(recording, 40 + 25 * a))
        expected = ref.solve_staged(list(range(N)))
        # the shared batch's arrays, with no helper thread: one that vanishes instead
        control, rows = new_control(), np.zeros(N, dtype=np.int64)
        own = (np.zeros(N, dtype=np.int64), np.empty((N, J, 4)), np.empty((N, 3)),
               np.zeros(N, dtype=np.int64), np.empty((N, STATE_SIZE)),
               np.empty((N, ND, 7)), np.empty((N, ND)), np.zeros(N, dtype=np.bool_))
        args = shared._analytic_args()
        rows[:N] = np.arange(N)
        taken: list[int] = []
        thief = threading.Thread(target=lambda: taken.append(_take_one_and_vanish(control)))
        thief.start()
        time.sleep(0.05)  # spinning, waiting for the batch
        handed = solve_analytic_shared(control, rows, N, *own, *args)
        thief.join(60)  # it returns once the batch is posted, whether it got one or not
        assert taken and -1 <= taken[0] < N
        assert handed == 0  # never handed over, and the caller solved all eight
        np.testing.assert_array_equal(shared._rotations[:N], expected.rotations)
        np.testing.assert_array_equal(shared._roots[:N], expected.root)
        # the caller filled every avatar's targets, the one it took over too
        np.testing.assert_array_equal(shared.tracking.state, ref.tracking.state)
        assert shared.tracking.filled[:N].all()
        return taken[0]

    deadline = time.monotonic() + 60
    held = attempt()
    while held < 0 and time.monotonic() < deadline:
        held = attempt()
    assert held >= 0  # it held one avatar in some attempt, and the caller took it over


def test_the_helper_restarts_over_the_grown_arrays(session: Session,
                                                   recording: ViveRecording) -> None:
    """Arrays that grow (a player joins a full solver) get a new helper at once, over
    the new arrays; the poses stay those of the server alone."""
    everywhere = tuple(range(os.cpu_count() or 1))
    helped = AvatarSolver(session.rig, capacity=2, helper_cores=everywhere)
    alone = AvatarSolver(session.rig, capacity=2)
    try:
        first = helped.helper()
        for solver in (helped, alone):
            for a in range(3):  # the third grows the arrays
                solver.calibrate(a, recording.devices, recording.positions[0],
                                 recording.rotations[0])
        assert helped.helper() is not None and helped.helper() is not first
        for f in range(1, 10):
            for solver in (helped, alone):
                for a in range(3):
                    solver.stage(a, recording.devices, poses(recording, f + 30 * a))
            h, a_ = helped.solve_staged([0, 1, 2]), alone.solve_staged([0, 1, 2])
            np.testing.assert_array_equal(h.rotations, a_.rotations)
    finally:
        helped.close()
