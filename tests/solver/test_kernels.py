"""Compiled kernels: the joint-limit clamp's shortcut never changes a result."""

from __future__ import annotations

import numpy as np

from posecast.solver.kernels import clamped, clamped_exactly, composed, surely_within, swing_twist
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import build_rig


def test_the_clamp_shortcut_only_skips_joints_the_exact_test_leaves_alone() -> None:
    """``surely_within`` spares the atan2 calls of joints within their limits; it must
    say so only when the exact test agrees, down to the last bit, also for deviations
    exactly on a limit, an ulp either side, and locked axes."""
    rig = build_rig(load_makehuman().skeleton)
    rng = np.random.default_rng(7)
    movable = np.nonzero(rig.movable)[0]
    skipped = 0
    for _ in range(20000):
        j = int(rng.choice(movable))
        pre, post = tuple(rig.pre[j]), tuple(rig.post[j])
        lo, hi = tuple(rig.lo[j]), tuple(rig.hi[j])
        d = rng.uniform(rig.lo[j], rig.hi[j])
        pick = rng.integers(0, 4, 3)
        d = np.where(pick == 0, rig.lo[j], np.where(pick == 1, rig.hi[j], d))
        d = d * (1.0 + rng.choice([0.0, 1e-16, -1e-16, 1e-13, -1e-13], 3))
        q = composed(pre, post, float(d[0]), float(d[1]), float(d[2]))
        q = tuple(float(v) * float(rng.choice([1.0, -1.0, 1.3])) for v in q)
        st = swing_twist(q, pre, post)
        exact = clamped_exactly(q, pre, post, lo, hi, st)
        if surely_within(st, lo, hi):
            skipped += 1
            assert exact == (False, q)
        assert clamped(q, pre, post, lo, hi) == exact
    assert skipped > 1000  # the shortcut is taken
