"""Shared pytest fixtures.

The real recordings (Vive csv, BVH) are not part of the repository: they live in
``../shared/data`` beside it. Tests that need them ask ``shared_data`` for a path and are
skipped, with the reason, where the data is absent.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


def shared_data_path(path: str) -> Path:
    """``../shared/data/<path>``; skips the calling test when it is absent."""
    full = SHARED_DATA / path
    if not full.exists():
        pytest.skip(f"../shared/data/{path} is absent: the real recordings live beside "
                    f"the project, not in it")
    return full


@pytest.fixture
def shared_data() -> Callable[[str], Path]:
    """``shared_data("vive/kicking.csv")``: the path of a real data file, or a skip."""
    return shared_data_path
