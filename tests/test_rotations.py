"""Property-based tests for solver.rotations (quaternions stored x, y, z, w)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from solver import rotations as rot

SETTINGS = settings(max_examples=200, deadline=None)
# batch tests check up to 6 elements per example, so fewer examples cover as many rotations
BATCH_SETTINGS = settings(max_examples=50, deadline=None)

TOL = 1e-9
TOL_SINGULAR = 1e-7  # trig near singularities (180 degrees, antiparallel vectors)

AXES = np.eye(3)
AXIS_NAMES = "xyz"
PI = math.pi

# --------------------------------------------------------------------------- strategies

_coord = st.floats(-2.0, 2.0, allow_nan=False, allow_infinity=False, allow_subnormal=False)


def _nonzero(min_norm: float):
    return lambda x: np.linalg.norm(x) > min_norm


raw_quats = st.tuples(_coord, _coord, _coord, _coord).map(np.array).filter(_nonzero(1e-3))
unit_quats = raw_quats.map(lambda q: q / np.linalg.norm(q))
unit_vecs = (
    st.tuples(_coord, _coord, _coord).map(np.array).filter(_nonzero(1e-3))
    .map(lambda v: v / np.linalg.norm(v))
)
vecs = st.tuples(_coord, _coord, _coord).map(np.array)
angles = st.floats(-PI, PI, allow_nan=False, allow_subnormal=False)
fractions = st.floats(0.0, 1.0, allow_nan=False)
axis_index = st.integers(0, 2)


def batches(elements, min_size: int = 1, max_size: int = 6, width: int = 4):
    return st.lists(elements, min_size=min_size, max_size=max_size).map(
        lambda xs: np.stack(xs) if xs else np.empty((0, width))
    )


def half_turns():
    """Rotations of exactly 180 degrees (w = 0) about a random axis."""
    return unit_vecs.map(lambda a: np.append(a, 0.0))


def near_half_turns():
    """Rotations within 1e-3 rad of 180 degrees, including exactly 180."""
    eps = st.one_of(st.just(0.0), st.floats(1e-12, 1e-3), st.floats(-1e-3, -1e-12))
    return st.tuples(unit_vecs, eps).map(lambda ae: rot.from_axis_angle(ae[0], PI - ae[1]))


any_quats = st.one_of(unit_quats, half_turns(), near_half_turns())

# --------------------------------------------------------------------------- helpers


def each(f, *arrays):
    """f applied to one element of each array at a time, results stacked."""
    return np.stack([f(*xs) for xs in zip(*arrays, strict=True)])


def sign_free_err(p, q) -> float:
    """Max abs difference between quaternions p and q, treating q and -q as equal
    (element-wise over batches)."""
    p = np.asarray(p)
    q = np.asarray(q)
    plus = np.max(np.abs(p - q), axis=-1)
    minus = np.max(np.abs(p + q), axis=-1)
    return float(np.max(np.minimum(plus, minus)))


def assert_same_rotation(p, q, tol: float = TOL) -> None:
    err = sign_free_err(p, q)
    assert err < tol, f"{p} vs {q}: err {err}"


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
@given(raw_quats, st.floats(1e-3, 1e3))
def test_normalize_unit_and_scale_invariant(q, k):
    n = rot.normalize(q)
    assert abs(np.linalg.norm(n) - 1.0) < TOL
    np.testing.assert_allclose(rot.normalize(k * q), n, atol=TOL)
    np.testing.assert_allclose(rot.normalize(n), n, atol=1e-15)


def test_normalize_zero_is_finite():
    out = rot.normalize(np.zeros((2, 4)))
    assert np.all(np.isfinite(out))
    np.testing.assert_array_equal(out, 0.0)


@SETTINGS
@given(any_quats)
def test_canonical(q):
    c = rot.canonical(q)
    assert c[3] >= 0.0
    assert_same_rotation(c, q, 0.0 + 1e-300)
    np.testing.assert_array_equal(rot.canonical(c), c)
    np.testing.assert_array_equal(rot.canonical(-q)[3] >= 0.0, True)


@SETTINGS
@given(unit_quats, unit_quats)
def test_conjugate_involution_and_antihomomorphism(a, b):
    np.testing.assert_array_equal(rot.conjugate(rot.conjugate(a)), a)
    np.testing.assert_allclose(
        rot.conjugate(rot.mul(a, b)), rot.mul(rot.conjugate(b), rot.conjugate(a)), atol=TOL
    )
    assert rot.inverse is rot.conjugate


def test_identity_shapes():
    np.testing.assert_array_equal(rot.identity(), rot.IDENTITY)
    ids = rot.identity((2, 3))
    assert ids.shape == (2, 3, 4)
    np.testing.assert_array_equal(ids, np.broadcast_to(rot.IDENTITY, (2, 3, 4)))


# --------------------------------------------------------------------------- group axioms


@SETTINGS
@given(unit_quats, unit_quats, unit_quats)
def test_mul_associative(a, b, c):
    np.testing.assert_allclose(rot.mul(rot.mul(a, b), c), rot.mul(a, rot.mul(b, c)), atol=TOL)


@SETTINGS
@given(any_quats, unit_quats)
def test_mul_identity_inverse_norm(q, b):
    # identity
    np.testing.assert_allclose(rot.mul(q, rot.IDENTITY), q, atol=1e-15)
    np.testing.assert_allclose(rot.mul(rot.IDENTITY, q), q, atol=1e-15)
    # inverse, up to sign (double cover)
    assert_same_rotation(rot.mul(q, rot.conjugate(q)), rot.IDENTITY)
    assert_same_rotation(rot.mul(rot.conjugate(q), q), rot.IDENTITY)
    assert_same_rotation(rot.mul(q, -rot.conjugate(q)), rot.IDENTITY)
    # norm preserved
    assert abs(np.linalg.norm(rot.mul(q, b)) - 1.0) < TOL
    assert abs(np.linalg.norm(rot.mul(b, q)) - 1.0) < TOL


def test_mul_known_products():
    # i*j = k, j*k = i, k*i = j, i*i = -1 in x, y, z, w order
    i, j, k = (np.append(AXES[n], 0.0) for n in range(3))
    np.testing.assert_array_equal(rot.mul(i, j), k)
    np.testing.assert_array_equal(rot.mul(j, k), i)
    np.testing.assert_array_equal(rot.mul(k, i), j)
    np.testing.assert_array_equal(rot.mul(i, i), -rot.IDENTITY)


# --------------------------------------------------------------------------- rotate / matrices


@SETTINGS
@given(any_quats, vecs)
def test_rotate_matches_matrix(q, v):
    np.testing.assert_allclose(rot.rotate(q, v), rot.to_matrix(q) @ v, atol=TOL)
    np.testing.assert_allclose(rot.rotate(-q, v), rot.rotate(q, v), atol=TOL)
    np.testing.assert_allclose(rot.rotate(rot.conjugate(q), rot.rotate(q, v)), v, atol=TOL)


@SETTINGS
@given(unit_quats, unit_quats, vecs)
def test_rotate_composition_order(a, b, v):
    """mul(a, b) applies b first, then a."""
    np.testing.assert_allclose(
        rot.rotate(rot.mul(a, b), v), rot.rotate(a, rot.rotate(b, v)), atol=TOL
    )
    np.testing.assert_allclose(
        rot.to_matrix(rot.mul(a, b)), rot.to_matrix(a) @ rot.to_matrix(b), atol=TOL
    )


@SETTINGS
@given(any_quats, vecs, vecs)
def test_rotate_is_isometry(q, u, v):
    ru, rv = rot.rotate(q, u), rot.rotate(q, v)
    assert abs(np.linalg.norm(ru) - np.linalg.norm(u)) < TOL
    assert abs(ru @ rv - u @ v) < TOL
    # orientation preserving: rotation commutes with the cross product
    np.testing.assert_allclose(np.cross(ru, rv), rot.rotate(q, np.cross(u, v)), atol=TOL)


@SETTINGS
@given(any_quats)
def test_to_matrix_orthonormal(q):
    m = rot.to_matrix(q)
    assert m.shape == (3, 3)
    np.testing.assert_allclose(m @ m.T, np.eye(3), atol=TOL)
    np.testing.assert_allclose(m.T @ m, np.eye(3), atol=TOL)
    assert abs(np.linalg.det(m) - 1.0) < TOL
    np.testing.assert_allclose(rot.to_matrix(rot.conjugate(q)), m.T, atol=TOL)


def test_to_matrix_known():
    q = rot.from_axis_angle([0.0, 0.0, 1.0], PI / 2)
    np.testing.assert_allclose(rot.to_matrix(q), rot_z(PI / 2), atol=1e-15)
    np.testing.assert_allclose(rot.rotate(q, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-15)


@SETTINGS
@given(any_quats)
@example(np.array([1.0, 0.0, 0.0, 0.0]))
@example(np.array([0.0, 1.0, 0.0, 0.0]))
@example(np.array([0.0, 0.0, 1.0, 0.0]))
@example(np.array([0.0, 0.0, 0.0, 1.0]))
@example(np.array([0.0, 0.0, 0.0, -1.0]))
@example(np.array([0.6, 0.8, 0.0, 0.0]))
@example(np.array([1.0, 1.0, 1.0, 0.0]) / math.sqrt(3.0))
@example(np.array([1.0, -1.0, 1.0, 1e-9]) / math.sqrt(3.0))
def test_from_matrix_roundtrip(q):
    back = rot.from_matrix(rot.to_matrix(q))
    assert back.shape == (4,)
    assert back[3] >= 0.0
    assert abs(np.linalg.norm(back) - 1.0) < TOL
    assert_same_rotation(back, q, TOL)
    assert rot.angle_between(back, q) < 1e-6
    np.testing.assert_allclose(rot.to_matrix(back), rot.to_matrix(q), atol=TOL)


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("theta", [PI, -PI, PI - 1e-9, PI - 1e-6, PI + 1e-9, PI / 2, 0.0])
def test_from_matrix_half_turn_about_axis(axis, theta):
    m = HAND[AXIS_NAMES[axis]](theta)
    q = rot.from_matrix(m)
    assert_same_rotation(q, rot.from_axis_angle(AXES[axis], theta), TOL)
    np.testing.assert_allclose(rot.to_matrix(q), m, atol=TOL)


def test_from_matrix_half_turn_random_axes():
    rng = np.random.default_rng(0)
    axes_ = rng.normal(size=(64, 3))
    axes_ /= np.linalg.norm(axes_, axis=-1, keepdims=True)
    for theta in (PI, PI - 1e-8, -PI + 1e-8):
        q = rot.from_axis_angle(axes_, np.full(64, theta))
        back = rot.from_matrix(rot.to_matrix(q))
        assert back.shape == (64, 4)
        assert_same_rotation(back, q, TOL)
        assert np.all(rot.angle_between(back, q) < 1e-6)


@BATCH_SETTINGS
@given(batches(any_quats, 0, 6))
def test_from_matrix_batch_matches_single(qs):
    ms = rot.to_matrix(qs)
    batch = rot.from_matrix(ms)
    assert batch.shape == qs.shape
    if len(qs):
        np.testing.assert_array_equal(batch, each(rot.from_matrix, ms))
    # extra leading axes survive
    if len(qs):
        nested = rot.from_matrix(ms[None, :, None])
        assert nested.shape == (1, len(qs), 1, 4)
        np.testing.assert_array_equal(nested[0, :, 0], batch)


# --------------------------------------------------------------------------- axis-angle, exp/log


@SETTINGS
@given(unit_vecs, angles, vecs)
def test_from_axis_angle(axis, theta, v):
    q = rot.from_axis_angle(axis, theta)
    assert abs(np.linalg.norm(q) - 1.0) < TOL
    assert abs(rot.angle(q) - abs(theta)) < TOL_SINGULAR
    np.testing.assert_allclose(rot.rotate(q, axis), axis, atol=TOL)  # axis is fixed
    # Rodrigues' formula
    expected = (
        v * math.cos(theta)
        + np.cross(axis, v) * math.sin(theta)
        + axis * (axis @ v) * (1.0 - math.cos(theta))
    )
    np.testing.assert_allclose(rot.rotate(q, v), expected, atol=TOL)
    # the axis need not be unit
    np.testing.assert_allclose(rot.from_axis_angle(3.5 * axis, theta), q, atol=TOL)
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
    np.testing.assert_allclose(rot.to_rotvec(q), rv, atol=TOL)
    assert abs(rot.angle(q) - theta) < TOL_SINGULAR


@SETTINGS
@given(any_quats)
def test_log_then_exp(q):
    rv = rot.to_rotvec(q)
    assert np.linalg.norm(rv) <= PI + 1e-12
    assert abs(np.linalg.norm(rv) - rot.angle(q)) < TOL
    assert_same_rotation(rot.from_rotvec(rv), q, TOL)
    # double cover: q and -q give one rotation vector (at exactly pi, rv and -rv are equal)
    assert_same_rotation(rot.from_rotvec(rot.to_rotvec(-q)), q, TOL)
    if abs(q[3]) > 1e-6:
        np.testing.assert_allclose(rot.to_rotvec(-q), rv, atol=TOL)


@SETTINGS
@given(unit_vecs, st.floats(PI + 1e-6, 3 * PI))
def test_from_rotvec_beyond_pi(axis, theta):
    """|rv| > pi is the same rotation as the shorter one the other way round."""
    q = rot.from_rotvec(axis * theta)
    assert_same_rotation(q, rot.from_rotvec(axis * (theta - 2 * PI)))
    assert abs(np.linalg.norm(q) - 1.0) < TOL


@pytest.mark.parametrize("theta", [0.0, 1e-300, 1e-200, 1e-15, 1e-12, 1e-10, 9.99e-9, 1e-8,
                                   1.001e-8, 1e-6, 1e-4])
def test_rotvec_tiny_angles(theta):
    axis = np.array([2.0, -3.0, 6.0]) / 7.0
    rv = axis * theta
    q = rot.from_rotvec(rv)
    assert np.all(np.isfinite(q))
    k = 0.5 if theta == 0.0 else math.sin(0.5 * theta) / theta
    np.testing.assert_allclose(q[:3], k * rv, rtol=1e-12, atol=0.0)
    assert abs(q[3] - math.cos(0.5 * theta)) < 1e-15
    back = rot.to_rotvec(q)
    assert np.all(np.isfinite(back))
    np.testing.assert_allclose(back, rv, rtol=1e-9, atol=1e-300)
    # and from a (slightly non-unit) quaternion built by hand
    np.testing.assert_allclose(rot.to_rotvec(np.append(0.5 * rv, 1.0)), rv, rtol=1e-9,
                               atol=1e-300)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_to_rotvec_half_turn(axis):
    q = np.append(AXES[axis], 0.0)
    np.testing.assert_allclose(np.abs(rot.to_rotvec(q)), PI * AXES[axis], atol=1e-15)
    np.testing.assert_allclose(np.abs(rot.to_rotvec(-q)), PI * AXES[axis], atol=1e-15)


# --------------------------------------------------------------------------- angles


@SETTINGS
@given(any_quats, any_quats)
def test_angle_between_metric(a, b):
    ab = rot.angle_between(a, b)
    assert 0.0 <= ab <= PI
    assert abs(ab - rot.angle_between(b, a)) < TOL_SINGULAR
    assert abs(ab - rot.angle_between(-a, b)) < TOL_SINGULAR
    assert abs(ab - rot.angle_between(a, -b)) < TOL_SINGULAR
    assert rot.angle_between(a, a) < TOL_SINGULAR
    assert rot.angle_between(a, -a) < TOL_SINGULAR  # double cover


@SETTINGS
@given(unit_quats, unit_quats, unit_quats)
def test_angle_between_invariance_and_triangle(a, b, c):
    ab = rot.angle_between(a, b)
    # bi-invariant metric on SO(3)
    assert abs(rot.angle_between(rot.mul(c, a), rot.mul(c, b)) - ab) < TOL_SINGULAR
    assert abs(rot.angle_between(rot.mul(a, c), rot.mul(b, c)) - ab) < TOL_SINGULAR
    assert rot.angle_between(a, c) <= ab + rot.angle_between(b, c) + TOL_SINGULAR


@SETTINGS
@given(unit_vecs, angles, unit_quats)
def test_angle_between_known(axis, theta, a):
    b = rot.mul(a, rot.from_axis_angle(axis, theta))
    assert abs(rot.angle_between(a, b) - abs(theta)) < TOL_SINGULAR


@SETTINGS
@given(unit_quats)
def test_angle_matches_trace(q):
    tr = np.trace(rot.to_matrix(q))
    expected = math.acos(min(1.0, max(-1.0, 0.5 * (tr - 1.0))))
    assert abs(rot.angle(q) - expected) < 1e-6  # acos is ill-conditioned near 0 and pi
    assert abs(rot.angle(q) - rot.angle(-q)) < 1e-15
    assert abs(rot.angle(q) - rot.angle(7.0 * q)) < TOL  # scale invariant


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
    tol = _between_tol(u, v) if tol is None else tol
    q = rot.between(u, v)
    un = u / np.linalg.norm(u, axis=-1, keepdims=True)
    vn = v / np.linalg.norm(v, axis=-1, keepdims=True)
    assert np.all(np.abs(np.linalg.norm(q, axis=-1) - 1.0) < TOL)
    moved = rot.rotate(q, un)
    np.testing.assert_allclose(moved, np.broadcast_to(vn, moved.shape), atol=tol)
    return q


@SETTINGS
@given(unit_vecs, unit_vecs, st.floats(0.1, 10.0), st.floats(0.1, 10.0))
@example(np.array([1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 2.98023223876953e-08]), 1.0, 1.0)
@example(np.array([0.0, 0.0, -1.0]), np.array([0.0, 1e-08, 1.0]), 1.0, 1.0)
@example(np.array([0.0, 0.6, 0.8]), np.array([0.0, -0.6, -0.8]), 2.0, 0.5)
def test_between_rotates_u_onto_v(u, v, su, sv):
    q = _assert_between(su * u, sv * v)
    tol = _between_tol(u, v)
    # shortest arc: the angle is the one between u and v, the axis is perpendicular to both
    assert abs(rot.angle(q) - math.acos(np.clip(u @ v, -1.0, 1.0))) < 1e-6
    assert abs(q[:3] @ u) < tol
    assert abs(q[:3] @ v) < tol
    assert_same_rotation(q, rot.between(u, v))


@SETTINGS
@given(unit_vecs)
@example(np.array([1.0, 0.0, 0.0]))
@example(np.array([-1.0, 0.0, 0.0]))
@example(np.array([0.0, 1.0, 0.0]))
@example(np.array([0.0, 0.0, -1.0]))
@example(np.array([1.0, 1.1e-6, 0.0]) / math.hypot(1.0, 1.1e-6))
@example(np.array([1.0, 0.0, 0.9e-6]) / math.hypot(1.0, 0.9e-6))
def test_between_same_and_opposite(u):
    assert_same_rotation(rot.between(u, u), rot.IDENTITY)
    q = _assert_between(u, -u)
    assert abs(rot.angle(q) - PI) < TOL
    assert abs(q[:3] @ u) < TOL  # a half turn about an axis perpendicular to u


@SETTINGS
@given(unit_vecs, unit_vecs, st.sampled_from([1e-4, 1e-6, 1e-7, 5e-8, 3e-8, 1e-8, 1e-9, 1e-11]))
def test_between_nearly_opposite(u, w, eps):
    """v a hair away from -u: must still land on v, not on -u."""
    perp = w - (w @ u) * u
    if np.linalg.norm(perp) < 1e-3:
        perp = np.cross(u, AXES[np.argmin(np.abs(u))])
    perp /= np.linalg.norm(perp)
    v = -math.cos(eps) * u + math.sin(eps) * perp
    _assert_between(u, v, TOL_SINGULAR)


@SETTINGS
@given(unit_vecs, unit_vecs, st.sampled_from([1e-4, 1e-7, 1e-10]))
def test_between_nearly_same(u, w, eps):
    perp = np.cross(u, w)
    if np.linalg.norm(perp) < 1e-3:
        perp = np.cross(u, AXES[np.argmin(np.abs(u))])
    perp /= np.linalg.norm(perp)
    v = math.cos(eps) * u + math.sin(eps) * perp
    q = _assert_between(u, v, TOL)
    assert abs(rot.angle(q) - eps) < TOL_SINGULAR


@BATCH_SETTINGS
@given(batches(unit_vecs), batches(unit_vecs))
def test_between_batch_with_opposites(us, vs):
    n = min(len(us), len(vs))
    us, vs = us[:n].copy(), vs[:n].copy()
    vs[::2] = -us[::2]  # mix antiparallel pairs into the batch
    vs[1::3] = us[1::3]  # and identical ones
    q = _assert_between(us, vs)
    np.testing.assert_allclose(q, each(rot.between, us, vs), atol=TOL)


@BATCH_SETTINGS
@given(unit_vecs, batches(unit_vecs))
def test_between_broadcast_single_against_batch(u, vs):
    vs = np.concatenate([vs, -u[None], u[None]])  # include v = -u and v = u
    q = _assert_between(u, vs)
    assert q.shape == (len(vs), 4)
    q2 = _assert_between(vs, u)
    assert q2.shape == (len(vs), 4)
    np.testing.assert_allclose(q, each(lambda v: rot.between(u, v), vs), atol=TOL)
    np.testing.assert_allclose(q2, each(lambda v: rot.between(v, u), vs), atol=TOL)


# --------------------------------------------------------------------------- Euler angles

ORDERS = ["xyz", "xzy", "yxz", "yzx", "zxy", "zyx", "xyx", "zxz", "yzy"]


@SETTINGS
@given(st.tuples(angles, angles, angles), st.sampled_from(ORDERS))
def test_from_euler_is_intrinsic_composition(a, order):
    q = rot.from_euler(np.array(a), order)
    expected = rot.IDENTITY
    for name, theta in zip(order, a, strict=True):
        expected = rot.mul(expected, rot.from_axis_angle(AXES["xyz".index(name)], theta))
    np.testing.assert_allclose(q, expected, atol=TOL)
    m = HAND[order[0]](a[0]) @ HAND[order[1]](a[1]) @ HAND[order[2]](a[2])
    np.testing.assert_allclose(rot.to_matrix(q), m, atol=TOL)
    np.testing.assert_allclose(rot.from_euler(np.array(a), order.upper()), q, atol=0.0)


@SETTINGS
@given(angles, angles, angles, vecs)
def test_from_euler_zxy_hand_matrices(z, x, y, v):
    """BVH "Zrotation Xrotation Yrotation": R = Rz @ Rx @ Ry."""
    q = rot.from_euler([z, x, y], "zxy")
    m = rot_z(z) @ rot_x(x) @ rot_y(y)
    np.testing.assert_allclose(rot.to_matrix(q), m, atol=TOL)
    np.testing.assert_allclose(rot.rotate(q, v), m @ v, atol=TOL)


@SETTINGS
@given(angles, angles, angles, vecs)
def test_from_euler_zyx_hand_matrices(z, y, x, v):
    q = rot.from_euler([z, y, x], "zyx")
    m = rot_z(z) @ rot_y(y) @ rot_x(x)
    np.testing.assert_allclose(rot.to_matrix(q), m, atol=TOL)
    np.testing.assert_allclose(rot.rotate(q, v), m @ v, atol=TOL)


def test_from_euler_single_axis():
    np.testing.assert_allclose(rot.from_euler([0.3, 0.0, 0.0], "zxy"),
                               rot.from_axis_angle([0, 0, 1], 0.3), atol=1e-15)
    np.testing.assert_allclose(rot.from_euler([0.0, 0.0, 0.0], "xyz"), rot.IDENTITY, atol=0.0)


@BATCH_SETTINGS
@given(batches(st.tuples(angles, angles, angles).map(np.array)), st.sampled_from(ORDERS))
def test_from_euler_batch(a, order):
    q = rot.from_euler(a, order)
    assert q.shape == (len(a), 4)
    np.testing.assert_allclose(q, each(lambda x: rot.from_euler(x, order), a), atol=1e-15)


# --------------------------------------------------------------------------- slerp


@SETTINGS
@given(unit_quats, any_quats)
def test_slerp_endpoints(a, b):
    np.testing.assert_allclose(rot.slerp(a, b, 0.0), a, atol=TOL)
    assert_same_rotation(rot.slerp(a, b, 1.0), b, TOL)
    assert_same_rotation(rot.slerp(a, a, 0.37), a, TOL)
    assert_same_rotation(rot.slerp(a, -a, 0.37), a, TOL)  # same rotation: no motion


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
        np.testing.assert_allclose(
            rot.to_rotvec(rot.mul(rot.conjugate(a), q)) / t,
            rot.to_rotvec(rot.mul(rot.conjugate(a), b)),
            atol=1e-6 / t,
        )


@SETTINGS
@given(unit_quats, unit_quats, fractions)
def test_slerp_short_path_and_symmetry(a, b, t):
    if a @ b > 0:
        b = -b  # force dot(a, b) < 0: the interpolation must take the short arc
    q = rot.slerp(a, b, t)
    total = rot.angle_between(a, b)
    assert total <= PI
    assert abs(rot.angle_between(a, q) - t * total) < TOL_SINGULAR
    assert_same_rotation(q, rot.slerp(a, -b, t), TOL)
    assert_same_rotation(q, rot.slerp(b, a, 1.0 - t), TOL_SINGULAR)


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
    np.testing.assert_allclose(q, each(rot.slerp, a, b, t), atol=1e-15)
    # one t for the whole batch, and many t for a single pair
    q1 = rot.slerp(a, b, t[0])
    np.testing.assert_allclose(q1, each(lambda x, y: rot.slerp(x, y, t[0]), a, b), atol=1e-15)
    qt = rot.slerp(a[0], b[0], t)
    assert qt.shape == (n, 4)
    np.testing.assert_allclose(qt, each(lambda s: rot.slerp(a[0], b[0], s), t), atol=1e-15)


# --------------------------------------------------------------------------- swing / twist


def _check_swing_twist(q, axis: int, tol: float = TOL):
    swing, twist = rot.swing_twist(q, axis)
    assert swing.shape == (*np.shape(q)[:-1], 3)
    assert np.all(np.abs(swing[..., axis]) < tol)  # swing is perpendicular to the twist axis
    assert np.all(np.abs(twist) <= PI + 1e-12)
    assert np.all(np.linalg.norm(swing, axis=-1) <= PI + 1e-12)
    rebuilt = rot.mul(rot.from_rotvec(swing), rot.from_axis_angle(AXES[axis], twist))
    assert_same_rotation(rebuilt, q, tol)
    return swing, twist


@SETTINGS
@given(any_quats, axis_index)
def test_swing_twist_recomposes(q, axis):
    _check_swing_twist(q, axis)
    s2, t2 = rot.swing_twist(-q, axis)  # double cover gives the same split
    s1, t1 = rot.swing_twist(q, axis)
    # (at exactly 180 degrees, +-pi twist and +-pi swing vectors are one rotation)
    assert_same_rotation(rot.from_rotvec(s2), rot.from_rotvec(s1), TOL)
    assert min(abs(t2 - t1), 2 * PI - abs(t2 - t1)) < TOL
    if abs(q[3]) > 1e-6:
        np.testing.assert_allclose(s2, s1, atol=TOL)
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
    np.testing.assert_allclose(swing, swing_rv, atol=1e-8)
    # twist of +-pi is one rotation
    assert min(abs(tw - twist), 2 * PI - abs(tw - twist)) < 1e-8


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_swing_twist_pure_cases(axis):
    # pure twist
    q = rot.from_axis_angle(AXES[axis], 1.2)
    swing, twist = _check_swing_twist(q, axis)
    np.testing.assert_allclose(swing, 0.0, atol=1e-15)
    assert abs(twist - 1.2) < 1e-12
    # pure swing of 180 degrees: twist undefined, taken as zero
    other = AXES[(axis + 1) % 3]
    q = rot.from_axis_angle(other, PI)
    swing, twist = _check_swing_twist(q, axis)
    assert twist == 0.0
    np.testing.assert_allclose(np.abs(swing), PI * other, atol=1e-12)
    # identity
    swing, twist = _check_swing_twist(rot.IDENTITY, axis)
    np.testing.assert_array_equal(swing, 0.0)
    assert twist == 0.0


@BATCH_SETTINGS
@given(batches(any_quats), axis_index)
def test_swing_twist_batch(qs, axis):
    swing, twist = _check_swing_twist(qs, axis)
    assert twist.shape == (len(qs),)
    np.testing.assert_allclose(swing, each(lambda q: rot.swing_twist(q, axis)[0], qs),
                               atol=1e-15)
    np.testing.assert_allclose(twist, each(lambda q: rot.swing_twist(q, axis)[1], qs),
                               atol=1e-15)


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
        assert len(batch) == n
        np.testing.assert_allclose(batch, each(f, *args), atol=1e-15, err_msg=f.__name__)


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
        np.testing.assert_allclose(batch, single, atol=1e-15)


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
