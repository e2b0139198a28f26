"""``posecast export FILE --bvh DIR``: one BVH file per avatar of a recording (a second
file for an avatar that was recalibrated: its skeleton changed), resampled to one rate."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np

from posecast.client.interop.recording import AvatarTake, avatar_takes, read_recording
from posecast.client.skeletons import skeleton_of
from posecast.solver.bvh_export import export_bvh
from posecast.solver.readers.errors import FormatError

_UNSAFE = re.compile(r"[^A-Za-z0-9_-]+")


def run_export(path: Path, out_dir: Path, fps: float | None) -> int:
    """Write the BVH files and say what each holds; the exit status."""
    try:
        rec = read_recording(path)
    except FormatError as err:
        print(f"posecast export: {err}", file=sys.stderr)
        return 1
    if rec.warning is not None:
        print(f"posecast export: warning: {rec.warning}", file=sys.stderr)
    takes = avatar_takes(rec)
    if not takes:
        print(f"posecast export: {path}: the recording holds no avatar-frames",
              file=sys.stderr)
        return 1
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        for take, name in zip(takes, file_names(takes), strict=True):
            target = out_dir / name
            done = export_bvh(target, skeleton_of(take.info), np.array(take.times),
                              np.array(take.roots), np.array(take.rotations), fps)
            seconds = (done.frames - 1) / done.fps
            print(f"{done.path}: {take.info.display_name!r}, {done.frames} frames at "
                  f"{done.fps:g} fps ({seconds:.1f} s), {take.info.num_joints} joints")
    except OSError as err:
        print(f"posecast export: {err.filename or out_dir}: {err.strerror or err}",
              file=sys.stderr)
        return 1
    except ValueError as err:  # a take the writer refuses (e.g. one frame at one instant)
        print(f"posecast export: {path}: {err}", file=sys.stderr)
        return 1
    return 0


def file_names(takes: list[AvatarTake]) -> list[str]:
    """A file name per take from its avatar's name, made safe and unique ("ann.bvh",
    "ann-2.bvh" for a second take or a second avatar of that name)."""
    out: list[str] = []
    for take in takes:
        stem = _UNSAFE.sub("_", take.info.display_name).strip("_") or "avatar"
        name, k = f"{stem}.bvh", 1
        while name in out:
            k += 1
            name = f"{stem}-{k}.bvh"
        out.append(name)
    return out
