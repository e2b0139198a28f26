"""Property-based tests for solver.rotations (quaternions stored x, y, z, w).

Identities are checked with absolute tolerances only (no relative slack): TOL for
well-conditioned maths, TOL_SINGULAR where trigonometry is ill-conditioned (180-degree
rotations, nearly antiparallel vectors).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from posecast.solver import rotations as rot

SETTINGS = settings(max_examples=200, deadline=None)
# batch tests check up to 6 elements per example, so fewer examples cover as many rotations
BATCH_SETTINGS = settings(max_examples=50, deadline=None)

TOL = 1e-9
TOL_SINGULAR = 1e-7
EXACT = 1e-15  # batch against single: the same arithmetic, element by element

AXES = np.eye(3)
PI = math.pi

# --------------------------------------------------------------------------- strategies

_coord = st.floats(-2.0, 2.0, allow_nan=False, allow_infinity=False, allow_subnormal=False)


def _norm_above(min_norm: float):
    return lambda x: np.linalg.norm(x) > min_norm


def _unit(x):
    return x / np.linalg.norm(x)


raw_quats = st.tuples(_coord, _coord, _coord, _coord).map(np.array).filter(_norm_above(1e-3))
unit_quats = raw_quats.map(_unit)
vecs = st.tuples(_coord, _coord, _coord).map(np.array)
unit_vecs = vecs.filter(_norm_above(1e-3)).map(_unit)
angles = st.floats(-PI, PI, allow_nan=False, allow_subnormal=False)
fractions = st.floats(0.0, 1.0, allow_nan=False)
axis_index = st.integers(0, 2)

# exactly 180 degrees (w = 0) about a random axis
half_turns = unit_vecs.map(lambda a: np.append(a, 0.0))
# within 1e-3 rad of 180 degrees, either side
near_half_turns = st.tuples(
    unit_vecs, st.one_of(st.floats(1e-12, 1e-3), st.floats(-1e-3, -1e-12))
).map(lambda ae: rot.from_axis_angle(ae[0], PI - ae[1]))
any_quats = st.one_of(unit_quats, half_turns, near_half_turns)


def batches(elements, min_size: int = 1, max_size: int = 6, width: int = 4):
    return st.lists(elements, min_size=min_size, max_size=max_size).map(
        lambda xs: np.stack(xs) if xs else np.empty((0, width))
    )


# --------------------------------------------------------------------------- helpers


def assert_close(actual, expected, atol: float = TOL) -> None:
    """Max absolute difference <= atol (NaN fails); expected broadcasts to actual."""
    actual = np.asarray(actual, dtype=np.float64)
    expected = np.asarray(expected, dtype=np.float64)
    assert np.broadcast_shapes(actual.shape, expected.shape) == actual.shape
    err = np.max(np.abs(actual - expected), initial=0.0)
    assert err <= atol, f"max abs error {err:.3g} > {atol:.0g}\n{actual}\nvs\n{expected}"


def assert_same_rotation(p, q, atol: float = TOL) -> None:
    """Quaternions equal up to sign (q and -q are one rotation), element-wise over batches."""
    p = np.asarray(p)
    q = np.asarray(q)
    err = np.minimum(np.max(np.abs(p - q), axis=-1), np.max(np.abs(p + q), axis=-1))
    assert np.max(err) <= atol, f"{p} vs {q}: error {np.max(err):.3g}"


def angle_diff(a, b):
    """Distance between two angles modulo 2 pi (a twist of pi equals one of -pi)."""
    d = abs(a - b) % (2 * PI)
    return min(d, 2 * PI - d)


def each(f, *arrays):
    """f applied to one element of each array at a time, results stacked."""
    return np.stack([f(*xs) for xs in zip(*arrays, strict=True)])


def rot_x(a: float):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


HAND = {"x": rot_x, "y": rot_y, "z": rot_z}

# --------------------------------------------------------------------------- basics


@SETTINGS
@given(raw_quats, st.floats(1e-3, 1e3), any_quats)
def test_normalize_canonical_conjugate(raw, k, q):
    n = rot.normalize(raw)
    assert abs(np.linalg.norm(n) - 1.0) < TOL
    assert_close(rot.normalize(k * raw), n)
    assert_close(rot.normalize(n), n, EXACT)

    c = rot.canonical(q)
    assert c[3] >= 0.0
    assert_same_rotation(c, q, 0.0)
    np.testing.assert_array_equal(rot.canonical(c), c)
    assert rot.canonical(-q)[3] >= 0.0

    np.testing.assert_array_equal(rot.conjugate(rot.conjugate(q)), q)
    np.testing.assert_array_equal(rot.conjugate(q), [-q[0], -q[1], -q[2], q[3]])
    assert rot.inverse is rot.conjugate


def test_normalize_zero_is_finite():
    np.testing.assert_array_equal(rot.normalize(np.zeros((2, 4))), 0.0)


def test_identity_shapes():
    np.testing.assert_array_equal(rot.identity(), rot.IDENTITY)
    ids = rot.identity((2, 3))
    assert ids.shape == (2, 3, 4)
    np.testing.assert_array_equal(ids, np.broadcast_to(rot.IDENTITY, (2, 3, 4)))


# --------------------------------------------------------------------------- group axioms


@SETTINGS
@given(any_quats, unit_quats, unit_quats)
def test_mul_group_axioms(a, b, c):
    # associativity
    assert_close(rot.mul(rot.mul(a, b), c), rot.mul(a, rot.mul(b, c)))
    # identity
    assert_close(rot.mul(a, rot.IDENTITY), a, EXACT)
    assert_close(rot.mul(rot.IDENTITY, a), a, EXACT)
    # inverse, up to sign (double cover)
    assert_same_rotation(rot.mul(a, rot.conjugate(a)), rot.IDENTITY)
    assert_same_rotation(rot.mul(rot.conjugate(a), a), rot.IDENTITY)
    assert_same_rotation(rot.mul(a, -rot.conjugate(a)), rot.IDENTITY)
    # norm preserved
    assert abs(np.linalg.norm(rot.mul(a, b)) - 1.0) < TOL
    assert abs(np.linalg.norm(rot.mul(b, a)) - 1.0) < TOL
    # (ab)* = b* a*
    assert_close(rot.conjugate(rot.mul(a, b)), rot.mul(rot.conjugate(b), rot.conjugate(a)))


def test_mul_known_products():
    # i*j = k, j*k = i, k*i = j, i*i = -1 in x, y, z, w order
    i, j, k = (np.append(AXES[n], 0.0) for n in range(3))
    np.testing.assert_array_equal(rot.mul(i, j), k)
    np.testing.assert_array_equal(rot.mul(j, k), i)
    np.testing.assert_array_equal(rot.mul(k, i), j)
    np.testing.assert_array_equal(rot.mul(i, i), -rot.IDENTITY)


# --------------------------------------------------------------------------- rotate / matrices


@SETTINGS
@given(any_quats, vecs, vecs)
def test_rotate_matrix_and_isometry(q, u, v):
    m = rot.to_matrix(q)
    assert m.shape == (3, 3)
    # rotate is R(q) @ v, for q and -q alike, and the conjugate undoes it
    ru, rv = rot.rotate(q, u), rot.rotate(q, v)
    assert_close(rv, m @ v)
    assert_close(rot.rotate(-q, v), rv)
    assert_close(rot.rotate(rot.conjugate(q), rv), v)
    # lengths, dot products and handedness are preserved
    assert abs(np.linalg.norm(ru) - np.linalg.norm(u)) < TOL
    assert abs(ru @ rv - u @ v) < TOL
    assert_close(np.cross(ru, rv), rot.rotate(q, np.cross(u, v)))
    # R is orthonormal with det +1, and R(q*) = R(q)^T
    assert_close(m @ m.T, np.eye(3))
    assert_close(m.T @ m, np.eye(3))
    assert abs(np.linalg.det(m) - 1.0) < TOL
    assert_close(rot.to_matrix(rot.conjugate(q)), m.T)


@SETTINGS
@given(unit_quats, any_quats, vecs)
def test_rotate_composition_order(a, b, v):
    """mul(a, b) applies b first, then a."""
    ab = rot.mul(a, b)
    assert_close(rot.rotate(ab, v), rot.rotate(a, rot.rotate(b, v)))
    assert_close(rot.to_matrix(ab), rot.to_matrix(a) @ rot.to_matrix(b))


def test_to_matrix_known():
    q = rot.from_axis_angle([0.0, 0.0, 1.0], PI / 2)
    assert_close(rot.to_matrix(q), rot_z(PI / 2), EXACT)
    assert_close(rot.rotate(q, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], EXACT)


@SETTINGS
@given(any_quats)
@example(np.array([1.0, 0.0, 0.0, 0.0]))
@example(np.array([0.0, 1.0, 0.0, 0.0]))
@example(np.array([0.0, 0.0, 1.0, 0.0]))
@example(np.array([0.0, 0.0, 0.0, 1.0]))
@example(np.array([0.0, 0.0, 0.0, -1.0]))
@example(np.array([0.6, 0.8, 0.0, 0.0]))
@example(np.array([1.0, 1.0, 1.0, 0.0]) / math.sqrt(3.0))
@example(_unit(np.array([1.0, -1.0, 1.0, 1e-9])))
@example(_unit(np.array([1e-9, 1e-9, 1.0, -1e-9])))
def test_from_matrix_roundtrip(q):
    back = rot.from_matrix(rot.to_matrix(q))
    assert back.shape == (4,)
    assert back[3] >= 0.0
    assert abs(np.linalg.norm(back) - 1.0) < TOL
    assert_same_rotation(back, q)
    assert rot.angle_between(back, q) < 1e-6
    assert_close(rot.to_matrix(back), rot.to_matrix(q))


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("theta", [PI, -PI, PI - 1e-9, PI - 1e-6, PI + 1e-9, PI / 2, 0.0])
def test_from_matrix_half_turn_about_axis(axis, theta):
    m = HAND["xyz"[axis]](theta)
    q = rot.from_matrix(m)
    assert_same_rotation(q, rot.from_axis_angle(AXES[axis], theta))
    assert_close(rot.to_matrix(q), m)


def test_from_matrix_half_turn_random_axes():
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(64, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    for theta in (PI, PI - 1e-8, -PI + 1e-8):
        q = rot.from_axis_angle(axes, np.full(64, theta))
        back = rot.from_matrix(rot.to_matrix(q))
        assert back.shape == (64, 4)
        assert_same_rotation(back, q)
        assert np.all(rot.angle_between(back, q) < 1e-6)


@BATCH_SETTINGS
@given(batches(any_quats, 0, 6))
def test_from_matrix_batch_matches_single(qs):
    ms = rot.to_matrix(qs)
    batch = rot.from_matrix(ms)
    assert batch.shape == qs.shape
    if len(qs):
        np.testing.assert_array_equal(batch, each(rot.from_matrix, ms))
        nested = rot.from_matrix(ms[None, :, None])  # extra leading axes survive
        assert nested.shape == (1, len(qs), 1, 4)
        np.testing.assert_array_equal(nested[0, :, 0], batch)


# --------------------------------------------------------------------------- axis-angle, exp/log


@SETTINGS
@given(unit_vecs, angles, vecs)
def test_from_axis_angle(axis, theta, v):
    q = rot.from_axis_angle(axis, theta)
    assert abs(np.linalg.norm(q) - 1.0) < TOL
    assert abs(rot.angle(q) - abs(theta)) < TOL_SINGULAR
    assert_close(rot.rotate(q, axis), axis)  # the axis is fixed
    # Rodrigues' formula
    c, s = math.cos(theta), math.sin(theta)
    assert_close(rot.rotate(q, v), v * c + np.cross(axis, v) * s + axis * (axis @ v) * (1 - c))
    # the axis need not be unit; the rotation vector is axis * angle
    assert_close(rot.from_axis_angle(3.5 * axis, theta), q)
    assert_same_rotation(rot.from_rotvec(axis * theta), q)


@SETTINGS
@given(unit_vecs, st.floats(0.0, PI - 1e-6))
@example(np.array([1.0, 0.0, 0.0]), 0.0)
@example(np.array([0.0, 1.0, 0.0]), 1e-10)
@example(np.array([0.0, 0.0, 1.0]), 1e-8)
@example(np.array([0.6, 0.0, 0.8]), PI - 1e-6)
def test_rotvec_roundtrip(axis, theta):
    rv = axis * theta
    q = rot.from_rotvec(rv)
    assert abs(np.linalg.norm(q) - 1.0) < TOL
    assert q[3] >= 0.0
    assert_close(rot.to_rotvec(q), rv)
    assert abs(rot.angle(q) - theta) < TOL_SINGULAR
    # exp(-rv) is the inverse; |rv| beyond pi wraps round to the same rotation
    assert_close(rot.from_rotvec(-rv), rot.conjugate(q))
    assert_same_rotation(rot.from_rotvec(axis * (theta + 2 * PI)), q)
    assert_same_rotation(rot.from_rotvec(axis * (theta - 2 * PI)), q)


@SETTINGS
@given(any_quats)
def test_log_then_exp(q):
    rv = rot.to_rotvec(q)
    assert np.linalg.norm(rv) <= PI + 1e-12
    assert abs(np.linalg.norm(rv) - rot.angle(q)) < TOL
    assert_same_rotation(rot.from_rotvec(rv), q)
    # double cover: q and -q give one rotation vector (at exactly pi, rv and -rv are equal)
    assert_same_rotation(rot.from_rotvec(rot.to_rotvec(-q)), q)
    if abs(q[3]) > 1e-6:
        assert_close(rot.to_rotvec(-q), rv)


@pytest.mark.parametrize("theta", [0.0, 1e-300, 1e-200, 1e-15, 1e-12, 1e-10, 9.99e-9, 1e-8,
                                   1.001e-8, 1e-6, 1e-4])
def test_rotvec_tiny_angles(theta):
    axis = np.array([2.0, -3.0, 6.0]) / 7.0
    rv = axis * theta
    q = rot.from_rotvec(rv)
    assert np.all(np.isfinite(q))
    k = 0.5 if theta == 0.0 else math.sin(0.5 * theta) / theta
    np.testing.assert_allclose(q[:3], k * rv, rtol=1e-12, atol=0.0)
    assert abs(q[3] - math.cos(0.5 * theta)) < EXACT
    back = rot.to_rotvec(q)
    assert np.all(np.isfinite(back))
    np.testing.assert_allclose(back, rv, rtol=1e-9, atol=1e-300)
    # and from a (slightly non-unit) quaternion built by hand
    np.testing.assert_allclose(rot.to_rotvec(np.append(0.5 * rv, 1.0)), rv, rtol=1e-9,
                               atol=1e-300)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_to_rotvec_half_turn(axis):
    q = np.append(AXES[axis], 0.0)
    assert_close(np.abs(rot.to_rotvec(q)), PI * AXES[axis], EXACT)
    assert_close(np.abs(rot.to_rotvec(-q)), PI * AXES[axis], EXACT)


# --------------------------------------------------------------------------- angles


@SETTINGS
@given(any_quats, any_quats, unit_quats)
def test_angle_between_is_a_metric(a, b, c):
    ab = rot.angle_between(a, b)
    assert 0.0 <= ab <= PI
    assert abs(ab - rot.angle_between(b, a)) < TOL_SINGULAR  # symmetric
    assert abs(ab - rot.angle_between(-a, b)) < TOL_SINGULAR  # double cover
    assert abs(ab - rot.angle_between(a, -b)) < TOL_SINGULAR
    assert rot.angle_between(a, a) < TOL_SINGULAR
    assert rot.angle_between(a, -a) < TOL_SINGULAR
    # bi-invariant
    assert abs(rot.angle_between(rot.mul(c, a), rot.mul(c, b)) - ab) < TOL_SINGULAR
    assert abs(rot.angle_between(rot.mul(a, c), rot.mul(b, c)) - ab) < TOL_SINGULAR
    # triangle inequality
    assert rot.angle_between(a, c) <= ab + rot.angle_between(b, c) + TOL_SINGULAR


@SETTINGS
@given(unit_vecs, angles, unit_quats)
def test_angle_known(axis, theta, a):
    b = rot.mul(a, rot.from_axis_angle(axis, theta))
    assert abs(rot.angle_between(a, b) - abs(theta)) < TOL_SINGULAR
    # the angle agrees with the trace of the matrix: tr R = 1 + 2 cos(angle)
    cos = 0.5 * (np.trace(rot.to_matrix(b)) - 1.0)
    assert abs(rot.angle(b) - math.acos(min(1.0, max(-1.0, cos)))) < 1e-6  # acos: ill-cond.
    assert rot.angle(b) == rot.angle(-b)
    assert abs(rot.angle(b) - rot.angle(7.0 * b)) < TOL  # scale invariant


# --------------------------------------------------------------------------- between


def _between_tol(u, v) -> float:
    """Nearly antiparallel inputs are ill-conditioned: the shortest-arc axis u x v is only
    good to ~eps/|u x v|, the fallback axis misses v by |u x v|; both are ~sqrt(eps) at worst."""
    un = u / np.linalg.norm(u, axis=-1, keepdims=True)
    vn = v / np.linalg.norm(v, axis=-1, keepdims=True)
    d = np.sum(un * vn, axis=-1)
    sin = np.linalg.norm(np.cross(un, vn), axis=-1)
    return TOL_SINGULAR if np.any((d < 0.0) & (sin < 1e-5)) else TOL


def _assert_between(u, v, tol: float | None = None):
    """between(u, v) is a unit quaternion rotating direction u onto direction v."""
    tol = _between_tol(u, v) if tol is None else tol
    q = rot.between(u, v)
    un = u / np.linalg.norm(u, axis=-1, keepdims=True)
    vn = v / np.linalg.norm(v, axis=-1, keepdims=True)
    assert np.all(np.abs(np.linalg.norm(q, axis=-1) - 1.0) < TOL)
    moved = rot.rotate(q, un)
    assert_close(moved, np.broadcast_to(vn, moved.shape), tol)
    return q


@SETTINGS
@given(unit_vecs, unit_vecs, st.floats(0.1, 10.0), st.floats(0.1, 10.0))
@example(np.array([1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 2.98023223876953e-08]), 1.0, 1.0)
@example(np.array([0.0, 0.0, -1.0]), np.array([0.0, 1e-08, 1.0]), 1.0, 1.0)
@example(np.array([0.0, 0.6, 0.8]), np.array([0.0, -0.6, -0.8]), 2.0, 0.5)
@example(np.array([0.0, 0.0, -1.0]), _unit(np.array([0.0, 5.960464477539063e-08, 1.5])), 1.0, 3.0)
def test_between_rotates_u_onto_v(u, v, su, sv):
    q = _assert_between(su * u, sv * v)
    tol = _between_tol(u, v)
    # shortest arc: the angle is the one between u and v, the axis is perpendicular to both
    assert abs(rot.angle(q) - math.acos(np.clip(u @ v, -1.0, 1.0))) < 1e-6
    assert abs(q[:3] @ u) < tol
    assert abs(q[:3] @ v) < tol
    assert_same_rotation(q, rot.between(u, v), tol)  # lengths do not matter


@SETTINGS
@given(unit_vecs)
@example(np.array([1.0, 0.0, 0.0]))
@example(np.array([-1.0, 0.0, 0.0]))
@example(np.array([0.0, 1.0, 0.0]))
@example(np.array([0.0, 0.0, -1.0]))
@example(_unit(np.array([1.0, 1.1e-6, 0.0])))
@example(_unit(np.array([1.0, 0.0, 0.9e-6])))
def test_between_same_and_opposite(u):
    assert_same_rotation(rot.between(u, u), rot.IDENTITY)
    q = _assert_between(u, -u)
    assert abs(rot.angle(q) - PI) < TOL
    assert abs(q[:3] @ u) < TOL  # a half turn about an axis perpendicular to u


@SETTINGS
@given(unit_vecs, unit_vecs, st.sampled_from([1.0, -1.0]),
       st.sampled_from([1e-4, 1e-6, 1e-7, 5e-8, 3e-8, 1e-8, 1e-9, 1e-11]))
def test_between_nearly_parallel(u, w, sign, eps):
    """v a hair away from u or -u: must land on v, not on +-u."""
    perp = np.cross(u, w)
    if np.linalg.norm(perp) < 1e-3:
        perp = np.cross(u, AXES[np.argmin(np.abs(u))])
    perp /= np.linalg.norm(perp)
    v = sign * math.cos(eps) * u + math.sin(eps) * perp
    q = _assert_between(u, v, TOL if sign > 0 else TOL_SINGULAR)
    expected = eps if sign > 0 else PI - eps
    assert abs(rot.angle(q) - expected) < TOL_SINGULAR


@BATCH_SETTINGS
@given(batches(unit_vecs), batches(unit_vecs))
def test_between_batch_with_opposites(us, vs):
    n = min(len(us), len(vs))
    us, vs = us[:n].copy(), vs[:n].copy()
    vs[::2] = -us[::2]  # mix antiparallel pairs into the batch
    vs[1::3] = us[1::3]  # and identical ones
    q = _assert_between(us, vs)
    assert_close(q, each(rot.between, us, vs), EXACT)


@BATCH_SETTINGS
@given(unit_vecs, batches(unit_vecs))
def test_between_broadcast_single_against_batch(u, vs):
    vs = np.concatenate([vs, -u[None], u[None]])  # include v = -u and v = u
    q = _assert_between(u, vs)
    assert q.shape == (len(vs), 4)
    q2 = _assert_between(vs, u)
    assert q2.shape == (len(vs), 4)
    assert_close(q, each(lambda v: rot.between(u, v), vs), EXACT)
    assert_close(q2, each(lambda v: rot.between(v, u), vs), EXACT)


# --------------------------------------------------------------------------- Euler angles

ORDERS = ["xyz", "xzy", "yxz", "yzx", "zxy", "zyx", "xyx", "zxz", "yzy"]


@SETTINGS
@given(st.tuples(angles, angles, angles), st.sampled_from(ORDERS))
def test_from_euler_is_intrinsic_composition(a, order):
    q = rot.from_euler(np.array(a), order)
    expected = rot.IDENTITY
    for name, theta in zip(order, a, strict=True):
        expected = rot.mul(expected, rot.from_axis_angle(AXES["xyz".index(name)], theta))
    assert_close(q, expected)
    m = HAND[order[0]](a[0]) @ HAND[order[1]](a[1]) @ HAND[order[2]](a[2])
    assert_close(rot.to_matrix(q), m)
    np.testing.assert_array_equal(rot.from_euler(np.array(a), order.upper()), q)


@SETTINGS
@given(angles, angles, angles, vecs, st.sampled_from(["zxy", "zyx"]))
def test_from_euler_hand_matrices(a0, a1, a2, v, order):
    """BVH "Zrotation Xrotation Yrotation" is R = Rz @ Rx @ Ry; "zyx" is Rz @ Ry @ Rx."""
    m = {
        "zxy": rot_z(a0) @ rot_x(a1) @ rot_y(a2),
        "zyx": rot_z(a0) @ rot_y(a1) @ rot_x(a2),
    }[order]
    q = rot.from_euler([a0, a1, a2], order)
    assert_close(rot.to_matrix(q), m)
    assert_close(rot.rotate(q, v), m @ v)


def test_from_euler_single_axis():
    assert_close(rot.from_euler([0.3, 0.0, 0.0], "zxy"), rot.from_axis_angle([0, 0, 1], 0.3),
                 EXACT)
    np.testing.assert_array_equal(rot.from_euler([0.0, 0.0, 0.0], "xyz"), rot.IDENTITY)


@BATCH_SETTINGS
@given(batches(st.tuples(angles, angles, angles).map(np.array)), st.sampled_from(ORDERS))
def test_from_euler_batch(a, order):
    q = rot.from_euler(a, order)
    assert q.shape == (len(a), 4)
    assert_close(q, each(lambda x: rot.from_euler(x, order), a), EXACT)


# --------------------------------------------------------------------------- slerp


@SETTINGS
@given(unit_quats, any_quats, fractions)
@example(np.array([0.0, 0.0, 1.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]), 0.5)  # tie: dot = 0
def test_slerp_endpoints_and_short_path(a, b, t):
    assert_close(rot.slerp(a, b, 0.0), a)
    assert_same_rotation(rot.slerp(a, b, 1.0), b)
    assert_same_rotation(rot.slerp(a, a, t), a)
    assert_same_rotation(rot.slerp(a, -a, t), a)  # one rotation: no motion
    # force dot(a, b) < 0: the interpolation must still take the short arc
    if a @ b > 0:
        b = -b
    q = rot.slerp(a, b, t)
    total = rot.angle_between(a, b)
    assert abs(rot.angle_between(a, q) - t * total) < TOL_SINGULAR
    # at dot(a, b) = 0 the rotations are 180 degrees apart: both arcs are equally short and
    # either is right, so the sign-independence below only holds away from that tie
    if abs(a @ b) > 1e-6:
        assert_same_rotation(q, rot.slerp(a, -b, t))
        assert_same_rotation(q, rot.slerp(b, a, 1.0 - t), TOL_SINGULAR)


@SETTINGS
@given(unit_quats, unit_quats, fractions)
def test_slerp_constant_angular_velocity(a, b, t):
    q = rot.slerp(a, b, t)
    assert abs(np.linalg.norm(q) - 1.0) < TOL
    total = rot.angle_between(a, b)
    assert abs(rot.angle_between(a, q) - t * total) < TOL_SINGULAR
    assert abs(rot.angle_between(q, b) - (1.0 - t) * total) < TOL_SINGULAR
    # on the geodesic: a single fixed axis from a
    if total > 1e-3 and t > 1e-3:
        assert_close(rot.to_rotvec(rot.mul(rot.conjugate(a), q)) / t,
                     rot.to_rotvec(rot.mul(rot.conjugate(a), b)), 1e-6 / t)


@SETTINGS
@given(unit_quats, st.sampled_from([0.0, 1e-15, 1e-12, 1e-9, 1e-7, 1e-5]), unit_vecs,
       fractions)
def test_slerp_nearly_equal(a, eps, axis, t):
    b = rot.mul(a, rot.from_axis_angle(axis, eps))
    q = rot.slerp(a, b, t)
    assert np.all(np.isfinite(q))
    assert abs(np.linalg.norm(q) - 1.0) < TOL
    assert rot.angle_between(a, q) <= eps + TOL


@BATCH_SETTINGS
@given(batches(unit_quats), batches(unit_quats), batches(fractions))
def test_slerp_batch(a, b, t):
    n = min(len(a), len(b), len(t))
    a, b, t = a[:n], b[:n], t[:n]
    q = rot.slerp(a, b, t)
    assert q.shape == (n, 4)
    assert_close(q, each(rot.slerp, a, b, t), EXACT)
    # one t for the whole batch, and many t for a single pair
    assert_close(rot.slerp(a, b, t[0]), each(lambda x, y: rot.slerp(x, y, t[0]), a, b), EXACT)
    qt = rot.slerp(a[0], b[0], t)
    assert qt.shape == (n, 4)
    assert_close(qt, each(lambda s: rot.slerp(a[0], b[0], s), t), EXACT)


# --------------------------------------------------------------------------- swing / twist


def _check_swing_twist(q, axis: int):
    """q == swing * twist (up to sign), swing perpendicular to the twist axis."""
    swing, twist = rot.swing_twist(q, axis)
    assert swing.shape == (*np.shape(q)[:-1], 3)
    assert np.all(np.abs(swing[..., axis]) < TOL)
    assert np.all(np.abs(twist) <= PI + 1e-12)
    assert np.all(np.linalg.norm(swing, axis=-1) <= PI + 1e-12)
    rebuilt = rot.mul(rot.from_rotvec(swing), rot.from_axis_angle(AXES[axis], twist))
    assert_same_rotation(rebuilt, q)
    return swing, twist


@SETTINGS
@given(any_quats, axis_index)
def test_swing_twist_recomposes(q, axis):
    s1, t1 = _check_swing_twist(q, axis)
    s2, t2 = rot.swing_twist(-q, axis)  # double cover gives the same split
    # (at exactly 180 degrees, +-pi twists and +-pi swing vectors are one rotation)
    assert_same_rotation(rot.from_rotvec(s2), rot.from_rotvec(s1))
    assert angle_diff(t2, t1) < TOL
    if abs(q[3]) > 1e-6:
        assert_close(s2, s1)
        assert abs(t2 - t1) < TOL


@SETTINGS
@given(axis_index, angles, unit_vecs, st.floats(0.0, PI - 1e-3))
def test_swing_twist_recovers_parts(axis, twist, direction, swing_angle):
    """Build q = swing * twist explicitly and get both parts back."""
    perp = direction.copy()
    perp[axis] = 0.0
    if np.linalg.norm(perp) < 1e-3:
        perp = AXES[(axis + 1) % 3]
    perp /= np.linalg.norm(perp)
    swing_rv = perp * swing_angle
    q = rot.mul(rot.from_rotvec(swing_rv), rot.from_axis_angle(AXES[axis], twist))
    swing, tw = _check_swing_twist(q, axis)
    assert_close(swing, swing_rv, 1e-8)
    assert angle_diff(tw, twist) < 1e-8


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_swing_twist_pure_cases(axis):
    # pure twist
    swing, twist = _check_swing_twist(rot.from_axis_angle(AXES[axis], 1.2), axis)
    assert_close(swing, 0.0, EXACT)
    assert abs(twist - 1.2) < 1e-12
    # pure swing of 180 degrees: twist undefined, taken as zero
    other = AXES[(axis + 1) % 3]
    swing, twist = _check_swing_twist(rot.from_axis_angle(other, PI), axis)
    assert twist == 0.0
    assert_close(np.abs(swing), PI * other, 1e-12)
    # identity
    swing, twist = _check_swing_twist(rot.IDENTITY, axis)
    np.testing.assert_array_equal(swing, 0.0)
    assert twist == 0.0


@BATCH_SETTINGS
@given(batches(any_quats), axis_index)
def test_swing_twist_batch(qs, axis):
    swing, twist = _check_swing_twist(qs, axis)
    assert twist.shape == (len(qs),)
    assert_close(swing, each(lambda q: rot.swing_twist(q, axis)[0], qs), EXACT)
    assert_close(twist, each(lambda q: rot.swing_twist(q, axis)[1], qs), EXACT)


# --------------------------------------------------------------------------- broadcasting


@BATCH_SETTINGS
@given(batches(any_quats), batches(any_quats), batches(vecs))
def test_broadcasting_batch_matches_single(qa, qb, vs):
    n = min(len(qa), len(qb), len(vs))
    qa, qb, vs = qa[:n], qb[:n], vs[:n]
    for f, args in [
        (rot.mul, (qa, qb)),
        (rot.rotate, (qa, vs)),
        (rot.to_matrix, (qa,)),
        (rot.to_rotvec, (qa,)),
        (rot.from_rotvec, (vs,)),
        (rot.from_axis_angle, (vs, vs[:, 0])),
        (rot.angle, (qa,)),
        (rot.angle_between, (qa, qb)),
        (rot.normalize, (qa,)),
        (rot.canonical, (qa,)),
        (rot.conjugate, (qa,)),
    ]:
        batch = f(*args)
        assert len(batch) == n, f.__name__
        assert_close(batch, each(f, *args), EXACT)


@BATCH_SETTINGS
@given(any_quats, batches(any_quats), batches(vecs))
def test_broadcasting_single_against_batch(q, qs, vs):
    for batch, single in [
        (rot.mul(q, qs), each(lambda p: rot.mul(q, p), qs)),
        (rot.mul(qs, q), each(lambda p: rot.mul(p, q), qs)),
        (rot.rotate(q, vs), each(lambda v: rot.rotate(q, v), vs)),
        (rot.rotate(qs[:1], vs), each(lambda v: rot.rotate(qs[0], v), vs)),  # (1,4) vs (N,3)
        (rot.angle_between(q, qs), each(lambda p: rot.angle_between(q, p), qs)),
        (rot.slerp(q, qs, 0.3), each(lambda p: rot.slerp(q, p, 0.3), qs)),
    ]:
        assert_close(batch, single, EXACT)


def test_broadcasting_grid_shapes():
    rng = np.random.default_rng(1)
    q = rot.normalize(rng.normal(size=(2, 3, 4)))
    v = rng.normal(size=(2, 3, 3))
    assert rot.mul(q, q).shape == (2, 3, 4)
    assert rot.rotate(q, v).shape == (2, 3, 3)
    assert rot.to_matrix(q).shape == (2, 3, 3, 3)
    assert rot.from_matrix(rot.to_matrix(q)).shape == (2, 3, 4)
    assert rot.to_rotvec(q).shape == (2, 3, 3)
    assert rot.from_rotvec(v).shape == (2, 3, 4)
    assert rot.angle(q).shape == (2, 3)
    assert rot.between(v, v[::-1]).shape == (2, 3, 4)
    assert rot.from_euler(v, "zxy").shape == (2, 3, 4)
    assert rot.slerp(q, q[::-1], 0.5).shape == (2, 3, 4)
    swing, twist = rot.swing_twist(q, 2)
    assert swing.shape == (2, 3, 3)
    assert twist.shape == (2, 3)
    # a (1, 3, 4) batch against a (2, 1, 4) batch
    assert rot.mul(q[:1], q[:, :1]).shape == (2, 3, 4)
    assert rot.rotate(q[:1], v[:, :1]).shape == (2, 3, 3)
