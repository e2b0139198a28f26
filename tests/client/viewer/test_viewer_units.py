"""The viewer's pure parts: mesh fitting, levels of detail, cameras, HUD and label text
(no GL)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from posecast.client.session.spectator import Spectator
from posecast.client.viewer.camera import OrbitCamera, look_at, mirror
from posecast.client.viewer.lod import (
    HARDWARE_BUDGET,
    SOFTWARE_BUDGET,
    build_lods,
    choose_levels,
    default_budget,
)
from posecast.client.viewer.overlay import hud_lines, label_text
from posecast.client.viewer.scene import SpectatorScene
from posecast.client.viewer.skinning import body_scale, fit_matrices, joint_matrices, skin
from posecast.protocol import AvatarBatch, AvatarFrame, AvatarInfo, AvatarRoster, ClockEstimator
from posecast.protocol.roles import DEVICE_ROLES, DeviceRole, role_bits
from posecast.solver import rotations as R
from posecast.solver.readers.gltf import SkinnedMesh, load_makehuman


@pytest.fixture(scope="module")
def mesh() -> SkinnedMesh:
    return load_makehuman()


def test_fit_maps_every_child_offset_onto_the_avatars(mesh: SkinnedMesh) -> None:
    sk = mesh.skeleton
    rng = np.random.default_rng(4)
    offsets = sk.offsets * rng.uniform(0.8, 1.3, (sk.num_joints, 1))  # each bone its own
    fit = fit_matrices(sk, offsets)
    for j in range(1, sk.num_joints):
        p = sk.parents[j]
        mapped = fit[p] @ sk.offsets[j]
        # exact for single children; the least-squares compromise for the pelvis/chest
        tol = 1e-3 if len(sk.children(int(p))) == 1 else 0.35
        assert np.linalg.norm(mapped - offsets[j]) <= tol * np.linalg.norm(offsets[j]) + 1e-9


def test_fit_keeps_the_body_scale_across_a_stretched_bone(mesh: SkinnedMesh) -> None:
    sk = mesh.skeleton
    offsets = sk.offsets.copy()
    forearm = sk.index("hand_l")  # the forearm's end: lowerarm_l's only child
    offsets[forearm] *= 1.5
    fit = fit_matrices(sk, offsets)
    f = fit[sk.index("lowerarm_l")]
    d = sk.offsets[forearm] / np.linalg.norm(sk.offsets[forearm])
    across = np.cross(d, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    assert f @ d == pytest.approx(1.5 * d, abs=2e-3)  # stretched along the bone
    assert f @ across == pytest.approx(across, abs=2e-3)  # not thickened
    assert body_scale(sk.offsets, offsets) == pytest.approx(1.0)


def test_numpy_skinning_of_the_bind_pose_is_the_mesh(mesh: SkinnedMesh) -> None:
    sk = mesh.skeleton
    gq = R.identity((sk.num_joints,))
    gp = sk.rest_positions()
    m = joint_matrices(gq, gp, np.broadcast_to(np.eye(3), (sk.num_joints, 3, 3)),
                       mesh.inverse_bind)
    out = skin(mesh.positions, mesh.joints, mesh.weights, m)
    assert np.abs(out - mesh.positions).max() < 1e-5


def test_levels_of_detail_share_vertices_and_shrink(mesh: SkinnedMesh) -> None:
    lods = build_lods(mesh)
    assert sorted(lods.vertex_order.tolist()) == list(range(mesh.num_vertices))
    tris = lods.triangles
    assert tris[0] == len(mesh.indices) // 3
    assert all(a > b for a, b in itertools.pairwise(tris))
    assert all(int(ix.max()) < mesh.num_vertices for ix in lods.levels)


def test_choose_levels_by_size_then_budget(mesh: SkinnedMesh) -> None:
    lods = build_lods(mesh)
    coarsest = len(lods.cells) - 1
    big, small = 2000.0, 40.0  # pixels tall
    levels = choose_levels([big, small, -1.0], lods, budget=10**9)
    assert levels[0] == 0 and levels[1] > levels[0] and levels[2] == coarsest
    tight = choose_levels([big, big, small], lods, budget=30_000)
    assert sum(lods.triangles[k] for k in tight) <= 30_000
    assert tight[0] == tight[1]  # equals treated alike (to within one step)
    assert choose_levels([big] * 4, lods, budget=1) == [coarsest] * 4


def test_default_budget_by_renderer() -> None:
    assert default_budget("llvmpipe (LLVM 15.0.6, 256 bits)") == SOFTWARE_BUDGET
    assert default_budget("NVIDIA GeForce RTX 3070/PCIe/SSE2") == HARDWARE_BUDGET


def test_orbit_camera_looks_at_its_target() -> None:
    cam = OrbitCamera(yaw=40.0, pitch=20.0, distance=5.0, target=(1.0, 1.0, -2.0))
    c = cam.camera(16 / 9)
    px, front = c.project(np.array([[1.0, 1.0, -2.0]]), 1280, 720)
    assert front[0] and px[0] == pytest.approx([640.0, 360.0], abs=1e-6)
    assert np.linalg.norm(c.eye - np.array([1.0, 1.0, -2.0])) == pytest.approx(5.0)
    behind = 2 * c.eye - np.array([1.0, 1.0, -2.0])  # as far behind the camera
    assert not c.project(behind[None], 1280, 720)[1][0]
    assert not c.spheres_visible(behind[None], np.array([0.5]))[0]
    assert c.spheres_visible(np.array([[1.0, 1.0, -2.0]]), np.array([0.5]))[0]


def test_look_at_straight_down_is_defined() -> None:
    m = look_at(np.array([0.0, 5.0, 0.0]), np.zeros(3))
    assert np.all(np.isfinite(m))


def test_mirror_flips_left_and_right() -> None:
    head_q = R.identity(())  # facing +z, x to the left
    head_p = np.array([0.0, 1.6, 0.0])
    cam = mirror(head_q, head_p, np.array([0.0, 0.06, 0.09]), 4 / 3)
    assert cam.mirrored
    assert cam.eye[2] > 2.0  # behind the mirror, 1.5 m ahead
    right_hand, left_hand = np.array([-0.5, 1.2, 0.0]), np.array([0.5, 1.2, 0.0])
    px, front = cam.project(np.stack([right_hand, left_hand]), 640, 480)
    assert front.all() and px[0, 0] > px[1, 0]


def test_hud_lines_say_mode_rate_count_and_stages() -> None:
    lines = hud_lines({"capture_to_render": {"p50": 12.34, "p99": 20.0},
                       "server": {"p50": 0.2, "p99": 0.5}, "other": {"p50": 1, "p99": 2}},
                      fps=59.7, avatars=3, mode="interpolate", delay_ms=18.2, view="orbit")
    text = "\n".join(lines)
    assert "3 avatars" in lines[0] and "60 fps" in lines[0]
    assert "interpolate (buffer 18 ms)" in lines[0]
    assert "capture_to_render" in text and "12.3" in text and "20.0" in text
    assert "other" not in text
    # stages in the order a pose travels
    assert text.index("server") < text.index("capture_to_render")
    assert "zero-buffer" in hud_lines({}, 30.0, 1, "zero-buffer", None, "mirror")[0]


def avatar(avatar_id: int, name: str, devices: tuple[DeviceRole, ...],
           lost: tuple[str, ...] = ()) -> tuple[AvatarInfo, AvatarFrame]:
    """A one-joint avatar with these devices, and its frame lacking ``lost``."""
    info = AvatarInfo(avatar_id=avatar_id, display_name=name, joint_names=("root",),
                      parents=(-1,), rest_offsets=np.array([[0.0, 1.0, 0.0]]), devices=devices)
    frame = AvatarFrame(avatar_id=avatar_id, seq=1, root=np.array([0.0, 1.0, 0.0]),
                        rotations=np.array([[0.0, 0.0, 0.0, 1.0]]), t_capture=1.0,
                        t_server_receive=1.1, t_solved=1.2, t_sent=1.3, lost=role_bits(lost))
    return info, frame


def test_the_hud_names_each_avatars_lost_devices_and_only_those() -> None:
    three: tuple[DeviceRole, ...] = ("head", "left_hand", "right_hand")
    room = [avatar(1, "player 1", DEVICE_ROLES),
            avatar(2, "player 2", DEVICE_ROLES, lost=("hip", "left_foot")),
            avatar(3, "player 3", three, lost=("right_hand",))]
    lines = hud_lines({}, 90.0, 3, "interpolate", None, "orbit", room)
    assert lines[-2:] == ["player 2 (11 devices): lost hip, left_foot",
                          "player 3 (3 devices): lost right_hand"]
    assert "player 1" not in "\n".join(lines)
    # nothing lost: no device line at all, as before the protocol carried losses
    calm = [avatar(1, "player 1", DEVICE_ROLES), avatar(3, "player 3", three)]
    assert hud_lines({}, 90.0, 2, "interpolate", None, "orbit", calm) == hud_lines(
        {}, 90.0, 2, "interpolate", None, "orbit")
    # an old recording's roster names no devices: the losses alone
    old = [avatar(4, "old", (), lost=("chest",))]
    assert hud_lines({}, 90.0, 1, "zero-buffer", None, "orbit", old)[-1] == "old: lost chest"


def test_a_label_carries_the_lost_devices_under_the_name() -> None:
    assert label_text("player 2", 0) == "player 2"
    assert label_text("player 2", role_bits(["left_foot", "head"])) == \
        "player 2\nlost head, left_foot"


def test_the_scene_gives_each_avatars_newest_losses_to_the_hud(mesh: SkinnedMesh) -> None:
    """From a received batch's lost column to the HUD's line and the label."""
    spectator = Spectator("ws://127.0.0.1:1/", "lab", "viewer")
    sk = mesh.skeleton
    infos = [AvatarInfo(avatar_id=a, display_name=f"player {a}", joint_names=sk.names,
                        parents=tuple(int(p) for p in sk.parents), rest_offsets=sk.offsets,
                        devices=DEVICE_ROLES[:10]) for a in (1, 2)]
    spectator.on_roster(AvatarRoster(avatars=tuple(infos)))
    scene = SpectatorScene(spectator, mesh)
    assert scene.newest() == [] and scene.lost(2) == 0  # no frame yet
    rotations = np.tile([0.0, 0.0, 0.0, 1.0], (2, sk.num_joints, 1))
    batch = AvatarBatch.from_arrays([1, 2], [5, 5], np.zeros((2, 3)), rotations, [1.0, 1.0],
                                    [1.1, 1.1], 1.2, 1.3, lost=[0, role_bits(["left_foot"])])
    spectator.on_batch(batch, 2.0, ClockEstimator())
    assert scene.lost(1) == 0 and scene.lost(2) == role_bits(["left_foot"])
    lines = hud_lines({}, 90.0, 2, "interpolate", None, "orbit", scene.newest())
    assert lines[-1] == "player 2 (10 devices): lost left_foot"
    assert "player 1" not in "\n".join(lines)


def test_a_calibrated_avatar_wears_the_mesh_without_tearing(mesh: SkinnedMesh) -> None:
    """Calibration raises the hips and knees (solver.calibration); the flesh is bound to
    those joints, so at rest the body and legs are the template mesh scaled by the body
    scale, exactly (bound to the template's own hips, the thighs' flesh moved up with the
    raised joints and the skin at the hips tore into sheets)."""
    from posecast.client.builtin import builtin_motion_path
    from posecast.client.sources.bvh_source import BvhSource
    from posecast.client.viewer.skinning import fit_avatar, pose_matrices
    from posecast.protocol import AvatarInfo
    from posecast.solver.calibration import calibrate
    from posecast.solver.rig import build_rig

    sk = mesh.skeleton
    tpose = BvhSource(builtin_motion_path()).calibration()
    cal = calibrate(build_rig(sk), dict(zip(tpose.roles, tpose.positions, strict=True)),
                    dict(zip(tpose.roles, tpose.rotations, strict=True)))
    info = AvatarInfo(avatar_id=1, display_name="walker", joint_names=sk.names,
                      parents=tuple(int(p) for p in sk.parents), rest_offsets=cal.offsets)
    avatar = fit_avatar(mesh, info)
    root = sk.offsets[0]
    m, _, _ = pose_matrices([avatar], mesh, [R.identity((sk.num_joints,))], [root])
    out = skin(mesh.positions, mesh.joints, mesh.weights, m[0])
    arms = [j for j in range(sk.num_joints)
            if any(sk.names[j].startswith(p) for p in (
                "clavicle", "upperarm", "lowerarm", "hand", "thumb", "index", "middle",
                "ring", "pinky"))]
    body = ~(np.isin(mesh.joints, arms) & (mesh.weights > 0)).any(axis=1)
    expected = root + cal.scale * (mesh.positions.astype(np.float64) - root)
    assert body.sum() > mesh.num_vertices // 2  # torso, head and legs
    assert np.abs(out[body] - expected[body]).max() < 1e-4
