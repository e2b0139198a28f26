"""The viewer's GPU skinning and rendering, headless through EGL (Mesa llvmpipe in CI).

Skipped, with the reason, only where no EGL context can be made (libegl1, libgl1 or
libgl1-mesa-dri missing)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import VIEW_H, VIEW_W

from posecast.client.viewer.bench import Clip
from posecast.client.viewer.camera import OrbitCamera, first_person, mirror
from posecast.client.viewer.renderer import BACKGROUND, AvatarDraw, Renderer
from posecast.client.viewer.skinning import (
    FittedAvatar,
    SkeletonMismatchError,
    bind_offsets,
    fit_avatar,
    skin,
    template_avatar,
)
from posecast.protocol import AvatarInfo
from posecast.solver import rotations as R
from posecast.solver.readers.gltf import SkinnedMesh, load_makehuman

W, H = VIEW_W, VIEW_H




@pytest.fixture(scope="module")
def mesh() -> SkinnedMesh:
    return load_makehuman()


def rest(mesh: SkinnedMesh) -> tuple[np.ndarray, np.ndarray]:
    J = mesh.skeleton.num_joints
    return np.tile([0.0, 0.0, 0.0, 1.0], (J, 1)), mesh.skeleton.offsets[0].copy()


def rescaled(mesh: SkinnedMesh, body: float, arms: float) -> FittedAvatar:
    """The template re-boned as calibration does: body scaled, arms scaled apart."""
    sk = mesh.skeleton
    bind = bind_offsets(sk)
    offsets = bind * body
    for name in ("lowerarm_l", "hand_l", "lowerarm_r", "hand_r"):  # upper arm, forearm
        offsets[sk.index(name)] = bind[sk.index(name)] * arms
    return template_avatar(mesh, offsets=offsets)


def skinned(renderer: Renderer, draw: AvatarDraw) -> tuple[np.ndarray, np.ndarray]:
    """(GPU transform feedback, numpy reference) skinned positions of one avatar."""
    m = renderer.mesh
    matrices = renderer.pose([draw]).matrices[0]
    return (renderer.skinned_positions(matrices),
            skin(m.positions, m.joints, m.weights, matrices))


def test_gpu_skinning_equals_numpy_reference(renderer: Renderer, clip: Clip) -> None:
    m = renderer.mesh
    avatar = fit_avatar(m, clip.info)  # calibrated: body and arms scaled, mesh fitted
    for f in (0, 100, 250):
        gpu, ref = skinned(renderer, AvatarDraw(avatar, clip.rotations[f], clip.roots[f]))
        assert gpu.shape == ref.shape == (m.num_vertices, 3)
        err = np.abs(gpu.astype(np.float64) - ref).max()
        assert err <= 1e-4, f"frame {f}: GPU and numpy skinning differ by {err * 1e3:.3f} mm"
        moved = np.linalg.norm(ref - m.positions, axis=1).max()
        assert moved > 0.1  # a walking pose, not the bind pose


def test_gpu_skinning_of_a_random_pose_with_stretched_bones(renderer: Renderer,
                                                            mesh: SkinnedMesh) -> None:
    rng = np.random.default_rng(3)
    J = mesh.skeleton.num_joints
    rot = R.from_rotvec(rng.normal(0.0, 0.5, (J, 3)))
    avatar = rescaled(mesh, 1.1, 1.25)
    gpu, ref = skinned(renderer, AvatarDraw(avatar, rot, np.array([0.3, 0.9, -1.0])))
    assert np.abs(gpu.astype(np.float64) - ref).max() <= 1e-4


def test_uniformly_scaled_avatar_is_the_scaled_mesh(renderer: Renderer,
                                                    mesh: SkinnedMesh) -> None:
    """The fit maps each bone's flesh with its bone: a uniformly larger skeleton wears a
    uniformly larger mesh, exactly."""
    s = 1.15
    avatar = template_avatar(mesh, offsets=bind_offsets(mesh.skeleton) * s)
    q, root = rest(mesh)
    gpu, ref = skinned(renderer, AvatarDraw(avatar, q, root))
    expected = root + s * (mesh.positions.astype(np.float64) - root)
    assert np.abs(ref - expected).max() < 1e-5
    assert np.abs(gpu - expected).max() < 1e-4


def test_longer_arms_stretch_the_arms_only(renderer: Renderer, mesh: SkinnedMesh) -> None:
    q, root = rest(mesh)
    plain, _ = skinned(renderer, AvatarDraw(template_avatar(mesh), q, root))
    long_arms, _ = skinned(renderer, AvatarDraw(rescaled(mesh, 1.0, 1.3), q, root))
    sk = mesh.skeleton
    arm = [sk.index(n) for n in ("upperarm_l", "lowerarm_l", "hand_l", "upperarm_r",
                                 "lowerarm_r", "hand_r")]
    arm += [j for j in range(sk.num_joints) if sk.parents[j] in arm or any(
        sk.names[j].startswith(f) for f in ("index", "middle", "ring", "pinky", "thumb"))]
    on_arm = np.isin(mesh.joints, arm) & (mesh.weights > 0)
    untouched = ~on_arm.any(axis=1)
    moved = np.linalg.norm(long_arms - plain, axis=1)
    assert moved[untouched].max() < 1e-5  # legs, torso, head: as they were
    hand = mesh.joints[:, 0] == sk.index("hand_l")  # dominated by the hand
    # upper arm and forearm grew by 30%: the hand moves out by 30% of the arm's length
    rest_pos = sk.rest_positions()
    arm_length = np.linalg.norm(rest_pos[sk.index("hand_l")] - rest_pos[sk.index("upperarm_l")])
    assert np.median(moved[hand]) == pytest.approx(0.3 * arm_length, rel=0.05)


def test_rotating_one_arm_moves_that_arm_and_nothing_else(renderer: Renderer,
                                                          mesh: SkinnedMesh) -> None:
    sk = mesh.skeleton
    avatar = template_avatar(mesh)
    q, root = rest(mesh)
    before, _ = skinned(renderer, AvatarDraw(avatar, q, root))
    shoulder = sk.index("upperarm_l")
    q2 = q.copy()
    q2[shoulder] = R.from_axis_angle(np.array([0.0, 0.0, 1.0]), np.radians(50.0))
    after, _ = skinned(renderer, AvatarDraw(avatar, q2, root))
    chain = {shoulder}
    for j in range(shoulder + 1, sk.num_joints):  # the arm: the shoulder and below
        if int(sk.parents[j]) in chain:
            chain.add(j)
    weight_on_arm = np.where(np.isin(mesh.joints, sorted(chain)), mesh.weights, 0.0).sum(1)
    moved = np.linalg.norm(after - before, axis=1)
    assert moved[weight_on_arm == 0.0].max() < 1e-6, "a vertex off the arm moved"
    assert moved[weight_on_arm > 0.5].min() > 1e-3, "an arm vertex did not move"
    hand = mesh.joints[:, 0] == sk.index("hand_l")
    assert moved[hand].mean() > 0.2  # the hand swings by tens of centimetres


def body_joints(mesh: SkinnedMesh) -> list[int]:
    """Joints inside the body's flesh: all but the floor-level root and the fingers
    (a finger is thinner than a pixel at this distance)."""
    fingers = ("index", "middle", "ring", "pinky", "thumb")
    return [j for j, n in enumerate(mesh.skeleton.names)
            if n != "Root" and not n.startswith(fingers)]


def covered(image: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Per pixel position: does it differ from the background colour?"""
    bg = np.round(np.asarray(BACKGROUND) * 255)
    x = np.clip(px[:, 0].astype(int), 0, image.shape[1] - 1)
    y = np.clip(px[:, 1].astype(int), 0, image.shape[0] - 1)
    return np.abs(image[y, x].astype(int) - bg).max(axis=1) > 8


@pytest.mark.parametrize("frame", [0, 60, 180])
def test_silhouette_covers_the_projected_joints(renderer: Renderer, clip: Clip,
                                                frame: int) -> None:
    m = renderer.mesh
    avatar = fit_avatar(m, clip.info)
    draw = AvatarDraw(avatar, clip.rotations[frame], clip.roots[frame])
    posed = renderer.pose([draw])
    centre = posed.global_pos[0].mean(axis=0)
    camera = OrbitCamera(yaw=35.0, pitch=10.0, distance=2.6,
                         target=(float(centre[0]), float(centre[1]), float(centre[2]))
                         ).camera(W / H)
    renderer.render(posed, camera, grid=False)
    image = renderer.read()
    joints = body_joints(m)
    px, front = camera.project(posed.global_pos[0, joints], W, H)
    assert front.all() and (px >= 0).all() and (px[:, 0] < W).all() and (px[:, 1] < H).all()
    hit = covered(image, px)
    missing = [m.skeleton.names[j] for j, ok in zip(joints, hit, strict=True) if not ok]
    assert not missing, f"joints not covered by the silhouette: {missing}"
    # and the silhouette is a body, not the whole frame
    assert 0.02 < covered(image, np.argwhere(np.ones((H, W)))[:, ::-1] + 0.5).mean() < 0.5


def test_empty_scene_is_background_and_grid(renderer: Renderer) -> None:
    camera = OrbitCamera(pitch=10.0, distance=3.0).camera(W / H)  # horizon at row ~150
    every_pixel = np.argwhere(np.ones((H, W)))[:, ::-1] + 0.5
    renderer.render(renderer.pose([]), camera, grid=False)
    assert not covered(renderer.read(), every_pixel).any()
    renderer.render(renderer.pose([]), camera)
    grid = covered(renderer.read(), every_pixel).reshape(H, W)
    assert 0.01 < grid[H // 2:].mean() < 0.5  # floor lines below the horizon
    assert not grid[:H // 4].any()  # none in the sky


def test_mirror_shows_the_right_hand_on_the_right(renderer: Renderer, clip: Clip) -> None:
    m = renderer.mesh
    avatar = fit_avatar(m, clip.info)
    posed = renderer.pose([AvatarDraw(avatar, clip.rotations[0], clip.roots[0])])
    h = renderer.head_joint
    camera = mirror(posed.global_rot[0, h], posed.global_pos[0, h], avatar.eye, W / H)
    renderer.render(posed, camera)
    image = renderer.read()
    sk = m.skeleton
    hands = posed.global_pos[0, [sk.index("hand_r"), sk.index("hand_l")]]
    px, front = camera.project(hands, W, H)
    assert front.all()
    assert px[0, 0] > px[1, 0], "in a mirror the right hand is on the image's right"
    body = posed.global_pos[0, body_joints(m)]
    assert covered(image, camera.project(body, W, H)[0]).mean() > 0.9


def test_first_person_sees_from_the_eyes_without_the_head(renderer: Renderer,
                                                          clip: Clip) -> None:
    m = renderer.mesh
    avatar = fit_avatar(m, clip.info)
    draw = AvatarDraw(avatar, clip.rotations[0], clip.roots[0], hide_head=True)
    posed = renderer.pose([draw])
    h = renderer.head_joint
    q, p = posed.global_rot[0, h], posed.global_pos[0, h]
    camera = first_person(q, p, avatar.eye, W / H)
    assert 0.05 < np.linalg.norm(camera.eye - p) < 0.15  # at the eyes, just off the joint
    gpu = renderer.skinned_positions(posed.matrices[0])
    on_head = m.joints[:, 0] == h
    assert np.abs(gpu[on_head] - p).max(axis=1).min() < 1e-4  # head collapsed on its joint
    # looking down from the eyes, the feet are below the image centre
    renderer.render(posed, camera)
    foot = posed.global_pos[0, m.skeleton.index("foot_l")]
    assert camera.project(foot[None], W, H)[0][0, 1] > H / 2 or \
        not camera.project(foot[None], W, H)[1][0]


def test_level_of_detail_follows_size_and_budget(renderer: Renderer, mesh: SkinnedMesh) -> None:
    q, root = rest(mesh)
    near = AvatarDraw(template_avatar(mesh, 0), q, root)
    far = AvatarDraw(template_avatar(mesh, 1), q, root + np.array([0.0, 0.0, -40.0]))
    behind = AvatarDraw(template_avatar(mesh, 2), q, root + np.array([0.0, 0.0, 40.0]))
    camera = OrbitCamera(yaw=0.0, pitch=0.0, distance=2.5, target=(0, 0.9, 0)).camera(W / H)
    scene = renderer.pose([near, far, behind])
    renderer.render(scene, camera)
    assert scene.lod[0] < scene.lod[1]  # the far one is coarser
    assert scene.lod[2] == -1  # behind the camera: not drawn
    budget = renderer.triangle_budget
    try:
        renderer.triangle_budget = 1
        renderer.render(scene, camera)
        coarsest = len(renderer.lod_triangles) - 1
        assert scene.lod[:2] == [coarsest, coarsest]
    finally:
        renderer.triangle_budget = budget


def test_an_avatar_of_another_rig_is_refused(mesh: SkinnedMesh) -> None:
    info = AvatarInfo(avatar_id=3, display_name="bvh person", joint_names=("Hips", "Spine"),
                      parents=(-1, 0), rest_offsets=np.zeros((2, 3)))
    with pytest.raises(SkeletonMismatchError, match="lacks the mesh joints"):
        fit_avatar(mesh, info)


def test_avatar_in_another_joint_order_is_matched_by_name(renderer: Renderer,
                                                          mesh: SkinnedMesh,
                                                          clip: Clip) -> None:
    """A server may list joints in another (parents-first) order: names decide."""
    sk = mesh.skeleton
    # swap two sibling subtrees' order: thigh_r's chain before thigh_l's
    order = list(range(sk.num_joints))
    left = [sk.index(n) for n in ("thigh_l", "calf_l", "foot_l", "ball_l")]
    right = [sk.index(n) for n in ("thigh_r", "calf_r", "foot_r", "ball_r")]
    for i, k in zip(left, right, strict=True):
        order[i], order[k] = order[k], order[i]
    inverse = np.argsort(order)
    parents = tuple(int(inverse[p]) if p >= 0 else -1 for p in sk.parents[order])
    info = AvatarInfo(avatar_id=0, display_name="shuffled",
                      joint_names=tuple(sk.names[j] for j in order), parents=parents,
                      rest_offsets=np.asarray(clip.info.rest_offsets)[order])
    shuffled = fit_avatar(mesh, info)
    same = fit_avatar(mesh, clip.info)
    got, _ = skinned(renderer, AvatarDraw(shuffled, clip.rotations[30][order], clip.roots[30]))
    want, _ = skinned(renderer, AvatarDraw(same, clip.rotations[30], clip.roots[30]))
    assert np.abs(got - want).max() < 1e-6
