"""BVH export: what posecast, Blender's importer and three.js' BVHLoader read back.

The motion is the built-in walk solved onto the calibrated MakeHuman avatar (the
``clip`` fixture: what a spectator receives), written, read back with posecast's own
reader and compared joint by joint after forward kinematics on both.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from posecast.client.viewer.bench import Clip
from posecast.solver import rotations as R
from posecast.solver.bvh_export import bvh_names, bvh_text, depth_first, export_bvh
from posecast.solver.fk import forward_kinematics
from posecast.solver.motion import Motion
from posecast.solver.readers.bvh import read_bvh
from posecast.solver.resample import default_fps, resample
from posecast.solver.skeleton import Skeleton

TOLERANCE_M = 0.5e-3  # the bound on a joint's position after the round trip
THREE_VERSION = "0.187.0"


def skeleton_of(clip: Clip) -> Skeleton:
    info = clip.info
    return Skeleton(info.joint_names, np.array(info.parents), info.rest_offsets)


def positions(skeleton: Skeleton, rotations: np.ndarray, roots: np.ndarray) -> np.ndarray:
    return forward_kinematics(skeleton, rotations, roots)[1]


def read_positions(path: Path, names: tuple[str, ...], scale: float | None = None
                   ) -> tuple[np.ndarray, Motion]:
    """Joint positions (F, J, 3) of a written file, in the order of ``names``."""
    motion = read_bvh(path, scale=scale)
    order = [motion.skeleton.names.index(n) for n in names]
    pos = positions(motion.skeleton, motion.rotations, motion.translations[:, 0])
    return pos[:, order], motion


def reference(times: np.ndarray, rotations: np.ndarray, roots: np.ndarray,
              out_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pose at each of ``out_t``: slerp (root: lerp) between the recorded frames
    that bracket it, one instant at a time."""
    rot_out, root_out = [], []
    for t in out_t:
        i = min(max(int(np.searchsorted(times, t, side="right")) - 1, 0), len(times) - 2)
        u = min(max((t - times[i]) / (times[i + 1] - times[i]), 0.0), 1.0)
        rot_out.append(R.slerp(rotations[i], rotations[i + 1], np.full(len(rotations[i]), u)))
        root_out.append(roots[i] + u * (roots[i + 1] - roots[i]))
    return np.array(rot_out), np.array(root_out)


def motion_columns(path: Path) -> tuple[list[str], np.ndarray]:
    """The joint of each column (position columns of the root included) and the values."""
    lines = path.read_text().splitlines()
    owner: list[str] = []
    joint = ""
    for line in lines:
        words = line.split()
        if words[0] in ("ROOT", "JOINT"):
            joint = words[1]
        elif words[0] == "CHANNELS":
            owner.extend([joint] * int(words[1]))
        elif words[0] == "MOTION":
            break
    start = next(i for i, line in enumerate(lines) if line.startswith("Frame Time:")) + 1
    return owner, np.array([[float(v) for v in line.split()] for line in lines[start:]])


def test_round_trip_of_the_solved_walk_is_exact_to_text_precision(clip: Clip,
                                                                   tmp_path: Path) -> None:
    sk = skeleton_of(clip)
    frames = clip.rotations.shape[0]
    times = 12.5 + np.arange(frames) / 90.0  # a take's instants on the server clock
    done = export_bvh(tmp_path / "walk.bvh", sk, times, clip.roots, clip.rotations)
    assert (done.frames, done.fps) == (frames, 90.0)
    got, motion = read_positions(done.path, done.names)
    want = positions(sk, clip.rotations, clip.roots)
    error = np.linalg.norm(got - want, axis=-1)
    assert error.max() < 1e-6  # 6 decimals of a centimetre: ~1e-8 m, rounding adds up
    assert motion.fps == 90.0 and motion.num_frames == frames
    # the unit was inferred as centimetres: the same as when it is given
    given, _ = read_positions(done.path, done.names, scale=0.01)
    assert np.allclose(given, got, atol=1e-12)


def test_irregular_instants_are_resampled_by_slerp(clip: Clip, tmp_path: Path) -> None:
    """A spectator's recording: 90 Hz with jitter, lost frames, an instant received twice;
    the file has the median rate and each of its frames is the slerp of the two recorded
    frames around its instant."""
    sk = skeleton_of(clip)
    rng = np.random.default_rng(7)
    frames = clip.rotations.shape[0]
    times = np.arange(frames) / 90.0 + rng.uniform(-0.003, 0.003, frames)
    times.sort()
    keep = np.ones(frames, dtype=bool)
    keep[[40, 41, 120, 200, 201, 202]] = False  # lost on the way
    times, rot, roots = times[keep], clip.rotations[keep], clip.roots[keep]
    times[10] = times[9]  # the same instant twice: the later frame is the newer pose
    assert default_fps(times) == 90.0
    for fps in (None, 30.0, 120.0):
        done = export_bvh(tmp_path / f"walk_{fps}.bvh", sk, times, roots, rot, fps=fps)
        rate = 90.0 if fps is None else fps
        out_t = times[0] + np.arange(done.frames) / rate
        assert done.fps == rate and out_t[-1] <= times[-1] + 1e-9
        assert times[-1] - out_t[-1] < 1.0 / rate
        unique = np.append(np.diff(times) > 0, True)
        want_rot, want_root = reference(times[unique], rot[unique], roots[unique], out_t)
        got, _ = read_positions(done.path, done.names)
        error = np.linalg.norm(got - positions(sk, want_rot, want_root), axis=-1)
        assert error.max() < TOLERANCE_M, (fps, error.max())


def turning_walk(clip: Clip) -> tuple[Skeleton, np.ndarray, np.ndarray]:
    """The walk with a body that turns whole turns about the vertical (the root's yaw
    through +-180 deg), an upper arm swept through the Z-X-Y singularity (its X angle
    from 40 to 140 deg, hitting 90 exactly) and a hand twisting one and a half turns."""
    sk = skeleton_of(clip)
    rot = clip.rotations.copy()
    frames = rot.shape[0]
    s = np.linspace(0.0, 1.0, frames)
    yaw = R.from_axis_angle(np.array([0.0, 1.0, 0.0]), 4.0 * np.pi * s)
    rot[:, 0] = R.mul(yaw, rot[:, 0])
    x_sweep = np.radians(40.0 + 100.0 * np.arange(frames) / (frames - 1))
    arm = np.stack([np.radians(30.0) * np.sin(6 * s), x_sweep,
                    np.radians(50.0) * np.cos(4 * s)], axis=-1)
    rot[:, sk.index("upperarm_l")] = R.from_euler(arm, "zxy")
    rot[:, sk.index("hand_r")] = R.from_axis_angle(np.array([0.3, 1.0, 0.2]), 3 * np.pi * s)
    return sk, rot, clip.roots


def test_euler_curves_stay_continuous_through_singularities_and_half_turns(
        clip: Clip, tmp_path: Path) -> None:
    sk, rot, roots = turning_walk(clip)
    frames = rot.shape[0]
    assert frames % 2 == 1  # the sweep's middle frame is the singularity itself
    times = np.arange(frames) / 60.0
    done = export_bvh(tmp_path / "turning.bvh", sk, times, roots, rot)
    got, _ = read_positions(done.path, done.names)
    error = np.linalg.norm(got - positions(sk, rot, roots), axis=-1)
    assert error.max() < TOLERANCE_M
    # no angle's curve jumps: each steps at most a little more than its joint turns
    turn = np.degrees(R.angle_between(rot[1:], rot[:-1])).max(axis=0)  # (J,)
    owner, values = motion_columns(done.path)
    step = np.abs(np.diff(values[:, 3:], axis=0)).max(axis=0)  # after the root's position
    bound = 2.0 * turn[[sk.names.index(n) for n in owner[3:]]] + 1.0
    assert np.all(step < bound), owner[3 + int(np.argmax(step - bound))]
    # whole turns stay whole: the root's yaw runs on past 180 deg instead of wrapping
    root_y = values[:, 5]  # Zrotation Xrotation Yrotation after the 3 positions
    assert np.ptp(root_y) > 600.0


def test_the_file_is_laid_out_as_blender_and_three_js_parse_it(clip: Clip) -> None:
    """Blender's importer reads the hierarchy line by line: 'ROOT|JOINT name', then '{',
    'OFFSET x y z' and 'CHANNELS n ...' on the next lines; 'End Site', '{', 'OFFSET',
    '}'; all three rotation channels of a joint; 'Frames: n' and 'Frame Time: t' alone
    on their lines, then one line of values per frame. three.js expects the same order."""
    sk = skeleton_of(clip)
    text, frames, fps, names = bvh_text(sk, np.arange(5) / 30.0, clip.roots[:5],
                                        clip.rotations[:5])
    lines = [line.split() for line in text.splitlines()]
    assert lines[0] == ["HIERARCHY"]
    joints, end_sites, depth = [], 0, 0
    i = 1
    while lines[i] != ["MOTION"]:
        words = lines[i]
        if words[0] in ("ROOT", "JOINT"):
            assert (words[0] == "ROOT") == (i == 1) and len(words) == 2
            assert lines[i + 1] == ["{"] and lines[i + 2][0] == "OFFSET"
            assert len(lines[i + 2]) == 4 and lines[i + 3][0] == "CHANNELS"
            channels = lines[i + 3][2:]
            assert int(lines[i + 3][1]) == len(channels)
            assert sorted(c for c in channels if c.endswith("rotation")) == [
                "Xrotation", "Yrotation", "Zrotation"]
            assert len(channels) == (6 if i == 1 else 3)
            joints.append(words[1])
            depth += 1
            i += 4
        elif words == ["End", "Site"]:
            assert lines[i + 1] == ["{"] and lines[i + 2][0] == "OFFSET"
            assert lines[i + 3] == ["}"]
            assert np.linalg.norm([float(v) for v in lines[i + 2][1:]]) > 0.99  # cm
            end_sites += 1
            i += 4
        else:
            assert words == ["}"], words
            depth -= 1
            i += 1
    assert depth == 0
    assert joints == [names[j] for j in depth_first(sk)]
    assert end_sites == sum(1 for j in range(sk.num_joints) if not sk.children(j))
    assert lines[i + 1] == ["Frames:", str(frames)]
    assert lines[i + 2][:2] == ["Frame", "Time:"] and len(lines[i + 2]) == 3
    assert 1.0 / float(lines[i + 2][2]) == fps == 30.0  # exactly: Blender's scene rate
    rows = lines[i + 3:]
    assert len(rows) == frames
    assert all(len(r) == 6 + 3 * (len(joints) - 1) for r in rows)
    assert text.endswith("\n") and "\t" in text and "\r" not in text


def test_names_are_sanitised_and_zero_offset_joints_kept(tmp_path: Path) -> None:
    """Names with spaces, braces or three.js' reserved characters, a clash they make, a
    joint at its parent's position (zero offset) and a leaf without a tip."""
    names = ("Hips", "left leg", "left_leg", "mixamorig:Spine", "twist {1}", "Head")
    parents = np.array([-1, 0, 0, 0, 3, 4])
    offsets = np.array([[0, 1.0, 0], [0.1, -0.05, 0], [-0.1, -0.05, 0], [0, 0.2, 0],
                        [0, 0, 0], [0, 0.5, 0]])
    sk = Skeleton(names, parents, offsets)
    assert bvh_names(names) == ("Hips", "left_leg", "left_leg_2", "mixamorig_Spine",
                                "twist_1_", "Head")
    rng = np.random.default_rng(3)
    rot = R.normalize(rng.normal(size=(20, 6, 4)))
    roots = rng.normal(size=(20, 3))
    done = export_bvh(tmp_path / "odd.bvh", sk, np.arange(20) / 10.0, roots, rot,
                      units_per_metre=1.0)
    assert "OFFSET 0.000000 0.000000 0.000000\n" in done.path.read_text().split("twist_1_")[1]
    got, motion = read_positions(done.path, done.names)  # metres, inferred
    assert np.linalg.norm(got - positions(sk, rot, roots), axis=-1).max() < 1e-6
    assert motion.skeleton.names == ("Hips", "left_leg", "left_leg_2", "mixamorig_Spine",
                                     "twist_1_", "Head")


def test_bad_input_is_refused_with_the_reason(clip: Clip, tmp_path: Path) -> None:
    sk = skeleton_of(clip)
    rot, roots = clip.rotations[:4], clip.roots[:4]
    cases = [
        (dict(times=np.array([0.0, 0.1, 0.05, 0.2])), "must not go back: frame 2"),
        (dict(times=np.arange(3) / 30.0), "roots must be (3, 3)"),
        (dict(times=np.arange(4) / 30.0, rotations=rot[:, :10]), "10 joints"),
        (dict(times=np.arange(4) / 30.0, fps=0.0), "fps must be"),
        (dict(times=np.array([0.0, np.nan, 0.2, 0.3])), "times hold a value"),
    ]
    for change, words in cases:
        args = dict(times=np.arange(4) / 30.0, roots=roots, rotations=rot, fps=None)
        args.update(change)
        with pytest.raises(ValueError, match=words.replace("(", r"\(").replace(")", r"\)")):
            export_bvh(tmp_path / "bad.bvh", sk, **args)  # type: ignore[arg-type]
    one = resample(np.array([3.0]), roots[:1], rot[:1])
    assert one.times.tolist() == [3.0] and one.rotations.shape == (1, sk.num_joints, 4)


THREE_SCRIPT = """
import { readFileSync } from 'node:fs';
import * as THREE from 'three';
import { BVHLoader } from 'three/examples/jsm/loaders/BVHLoader.js';
const errors = [];
console.error = (...args) => errors.push(args.join(' '));
console.warn = (...args) => errors.push(args.join(' '));
const [file, timesJson] = process.argv.slice(2);
const result = new BVHLoader().parse(readFileSync(file, 'utf8'));
const bones = result.skeleton.bones.filter((b) => b.name !== 'ENDSITE');
const scene = new THREE.Group();
scene.add(result.skeleton.bones[0]);
const mixer = new THREE.AnimationMixer(scene);
mixer.clipAction(result.clip).play();
const frames = [];
for (const t of JSON.parse(timesJson)) {
  mixer.setTime(t);
  scene.updateMatrixWorld(true);
  frames.push(bones.map((b) => b.getWorldPosition(new THREE.Vector3()).toArray()));
}
console.log(JSON.stringify({ names: bones.map((b) => b.name), frames, errors,
                             tracks: result.clip.tracks.length }));
"""


@pytest.fixture(scope="module")
def three_dir(request: pytest.FixtureRequest) -> Path:
    """A folder with the ``three`` npm package (cached between runs), or a skip."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("node and npm are needed to run three.js' BVHLoader")
    folder = Path(request.config.cache.mkdir(f"three-{THREE_VERSION}"))
    if not (folder / "node_modules" / "three" / "package.json").exists():
        done = subprocess.run(["npm", "install", "--no-audit", "--no-fund", "--silent",
                               "--prefix", str(folder), f"three@{THREE_VERSION}"],
                              capture_output=True, text=True, timeout=300)
        if done.returncode != 0:
            pytest.skip(f"npm could not install three@{THREE_VERSION} (offline?): "
                        f"{done.stderr.strip()[-300:]}")
    (folder / "pose.mjs").write_text(THREE_SCRIPT)
    return folder


def test_three_js_bvhloader_poses_the_skeleton_as_posecast_does(
        clip: Clip, tmp_path: Path, three_dir: Path) -> None:
    sk, rot, roots = turning_walk(clip)
    frames = rot.shape[0]
    done = export_bvh(tmp_path / "turning.bvh", sk, np.arange(frames) / 60.0, roots, rot)
    picks = [0, 1, frames // 2, frames - 2]  # not the last: a looping action wraps there
    run = subprocess.run(["node", str(three_dir / "pose.mjs"), str(done.path),
                          json.dumps([k / done.fps for k in picks])],
                         capture_output=True, text=True, timeout=120, cwd=three_dir)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["errors"] == []
    assert out["names"] == [done.names[j] for j in depth_first(sk)]
    assert out["tracks"] == 2 * sk.num_joints  # a position and a quaternion track each
    got = np.array(out["frames"])[:, np.argsort(depth_first(sk))] / 100.0  # cm
    want = positions(sk, rot[picks], roots[picks])
    assert np.linalg.norm(got - want, axis=-1).max() < TOLERANCE_M
