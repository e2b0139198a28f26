"""The built-in motion shipped with posecast (a CMU clip; credit in assets/CREDITS.md)."""

from __future__ import annotations

from pathlib import Path

ASSETS = Path(__file__).resolve().parent / "assets"


def builtin_motion_path() -> Path:
    return ASSETS / "cmu_02_01_walk.bvh"
