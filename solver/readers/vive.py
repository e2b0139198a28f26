"""Reader for the Vive tracker recordings (format: ``../shared/data/vive/README.md``).

A recording is space-separated text: the header
``tag rawPosX rawPosY rawPosZ rawRotX rawRotY rawRotZ rawRotW scale``, then one line per
device per frame. The devices of a frame always come in the same order and a frame starts
at its ``head`` line; the device sequence is learned from the first frame and every later
frame must repeat it exactly. Positions are metres, rotations unit quaternions x y z w.

The files hold up to ~28,500 lines, so the reader splits every line once and then checks
and converts the whole table with numpy. Every check finds the first bad line, and the
error raised is the one on the earliest line, so line numbers are exact.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from posecast.solver.motion import ViveRecording
from posecast.solver.readers.errors import FormatError
from posecast.solver.readers.text import read_lines

VIVE_FPS = 90.0  # the recordings are replayed at 90 Hz (see the data README)
HEADER = ("tag", "rawPosX", "rawPosY", "rawPosZ", "rawRotX", "rawRotY", "rawRotZ", "rawRotW",
          "scale")
TAGS = {"head": "head", "hip": "hip", "lHand": "left_hand", "rHand": "right_hand",
        "lForeArm": "left_forearm", "rForeArm": "right_forearm", "lFoot": "left_foot",
        "rFoot": "right_foot", "lKnee": "left_knee", "rKnee": "right_knee",
        "chest": "chest"}
FRAME_START = "head"
QUAT_TOLERANCE = 0.05  # |norm - 1| above this is not a rounding error but a broken value
FIRST_BODY_LINE = 2  # row 0 of the table is line 2 of the file (line 1 is the header)

# (row index, tie-break rank, message): the problem on the earliest row wins, and on one
# row the most basic problem (field count before numbers before tags) is reported.
_Problem = tuple[int, int, str]


def read_vive(path: str | Path) -> ViveRecording:
    """Read a Vive recording; raise ``FormatError`` (file, line, what) for any bad input."""
    src = str(path)
    lines = read_lines(Path(path), src, "ascii", "plain ASCII text")
    _check_header(src, lines)
    rows = [line.split() for line in lines[1:]]
    if not rows:
        raise FormatError(src, FIRST_BODY_LINE,
                          "expected device lines after the header, found none: no frames")
    n_ok, problems = _check_field_counts(rows)
    rows = rows[:n_ok]
    tags = np.array([r[0] for r in rows], dtype=str)
    values, value_problem = _parse_values(rows)
    problems += [p for p in (value_problem, _check_quaternions(values)) if p is not None]
    problems += _check_tags(tags)
    first = _first_frame(tags)
    problems += [p for p in (_check_order(tags, first),) if p is not None]
    if problems:
        row, _, message = min(problems)
        raise FormatError(src, row + FIRST_BODY_LINE, message)
    _check_complete(src, tags, first)
    return _recording(src, first, values)


def _check_header(src: str, lines: list[str]) -> None:
    expected = " ".join(HEADER)
    if not lines:
        raise FormatError(src, 1, f"the file is empty: expected the header {expected!r}")
    if tuple(lines[0].split()) != HEADER:
        raise FormatError(src, 1, f"expected the header {expected!r}, found {lines[0]!r}")


def _check_field_counts(rows: list[list[str]]) -> tuple[int, list[_Problem]]:
    """How many leading rows have the right field count, and the first bad row if any."""
    counts = np.fromiter(map(len, rows), dtype=np.int64, count=len(rows))
    bad = np.flatnonzero(counts != len(HEADER))
    if not bad.size:
        return len(rows), []
    row = int(bad[0])
    found = "an empty line" if not rows[row] else f"{counts[row]} fields"
    message = (f"expected {len(HEADER)} space-separated fields "
               f"({' '.join(HEADER)}), found {found}")
    return row, [(row, 0, message)]


def _parse_values(rows: list[list[str]]) -> tuple[NDArray[np.float64], _Problem | None]:
    """The numeric columns as an (N, 8) array, and the first row with a bad number.

    Rows from the first bad one on are dropped from the array, so later checks only see
    numbers that were read correctly."""
    width = len(HEADER) - 1
    tokens = [t for r in rows for t in r[1:]]
    try:
        flat = np.fromiter(map(float, tokens), dtype=np.float64, count=len(tokens))
    except ValueError:  # a token that is not a number: find it the slow way
        return _find_bad_number(rows)
    values = flat.reshape(len(rows), width)
    finite = np.isfinite(values)
    if finite.all():
        return values, None
    row = int(np.flatnonzero(~finite.all(axis=1))[0])
    col = int(np.flatnonzero(~finite[row])[0]) + 1
    return values[:row], (row, 1, _number_message(col, rows[row][col]))


def _find_bad_number(rows: list[list[str]]) -> tuple[NDArray[np.float64], _Problem | None]:
    good: list[list[float]] = []
    for i, row in enumerate(rows):
        parsed: list[float] = []
        for col, token in enumerate(row[1:], start=1):
            try:
                value = float(token)
            except ValueError:
                value = math.nan
            if not math.isfinite(value):
                return np.array(good).reshape(-1, len(HEADER) - 1), (
                    i, 1, _number_message(col, token))
            parsed.append(value)
        good.append(parsed)
    return np.array(good).reshape(-1, len(HEADER) - 1), None


def _number_message(col: int, token: str) -> str:
    return f"expected a finite number for {HEADER[col]} (field {col + 1}), found {token!r}"


def _check_quaternions(values: NDArray[np.float64]) -> _Problem | None:
    norms = np.linalg.norm(values[:, 3:7], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUAT_TOLERANCE)
    if not bad.size:
        return None
    row = int(bad[0])
    return (row, 3, f"expected a unit rotation quaternion (rawRotX..rawRotW), "
                    f"found one of norm {norms[row]:.6g}")


def _check_tags(tags: NDArray[np.str_]) -> list[_Problem]:
    bad = np.flatnonzero(~np.isin(tags, list(TAGS)))
    if not bad.size:
        return []
    row = int(bad[0])
    return [(row, 2, f"expected a device tag ({', '.join(TAGS)}), found {str(tags[row])!r}")]


def _first_frame(tags: NDArray[np.str_]) -> list[str]:
    """The device sequence of the first frame: up to the second ``head`` line."""
    starts = np.flatnonzero(tags == FRAME_START)
    end = int(starts[1]) if starts.size > 1 else len(tags)
    return [str(t) for t in tags[:end]]


def _check_order(tags: NDArray[np.str_], first: list[str]) -> _Problem | None:
    if not tags.size:
        return None
    if first[0] != FRAME_START:
        return (0, 4, f"expected the first device line to be {FRAME_START!r} (a frame "
                      f"starts at its head line), found {first[0]!r}")
    seen: set[str] = set()
    for i, tag in enumerate(first):
        if tag in seen:
            return (i, 4, f"device {tag!r} appears twice in the first frame, which sets "
                          f"the device order: {' '.join(first[:i + 1])}")
        seen.add(tag)
    expected = np.resize(np.array(first), len(tags))  # the first frame, repeated
    bad = np.flatnonzero(tags != expected)
    if not bad.size:
        return None
    row = int(bad[0])
    d = len(first)
    message = (f"device order broken in frame {row // d}: expected {str(expected[row])!r} "
               f"(device {row % d + 1} of {d}: {' '.join(first)}), found {str(tags[row])!r}")
    return (row, 4, message)


def _check_complete(src: str, tags: NDArray[np.str_], first: list[str]) -> None:
    d = len(first)
    have = len(tags) % d
    if have:
        frame = len(tags) // d
        raise FormatError(
            src, len(tags) - 1 + FIRST_BODY_LINE,
            f"the file ends in the middle of a frame: frame {frame} has {have} of its "
            f"{d} devices, expected {first[have]!r} after this line")


def _recording(src: str, first: list[str], values: NDArray[np.float64]) -> ViveRecording:
    d = len(first)
    table = values.reshape(-1, d, values.shape[1])
    quats = table[:, :, 3:7]
    quats = quats / np.linalg.norm(quats, axis=-1, keepdims=True)
    return ViveRecording(
        devices=tuple(TAGS[t] for t in first),
        positions=np.ascontiguousarray(table[:, :, 0:3]),
        rotations=np.ascontiguousarray(quats),
        fps=VIVE_FPS,
        source=src,
    )


# file order of the paper authors' recordings: each hand before its forearm
FILE_ORDER = ("head", "hip", "lHand", "lForeArm", "rHand", "rForeArm", "lFoot", "rFoot",
              "lKnee", "rKnee", "chest")


def file_tags(devices: tuple[str, ...]) -> list[str]:
    """The tags of these devices in the authors' file order; a ValueError for a device
    the format has no tag for."""
    tags = [t for t in FILE_ORDER if TAGS[t] in devices]
    missing = set(devices) - {TAGS[t] for t in tags}
    if missing:
        raise ValueError(f"devices the format has no tag for: {', '.join(sorted(missing))}")
    return tags


def format_vive_frame(tags: list[str], poses: NDArray[np.float64], scale: float = 1.0) -> str:
    """One frame's lines: ``poses`` (D, 7), position | quaternion, one row per tag in
    ``tags`` order; 6 significant digits, as the authors' files have."""
    return "".join(" ".join([tag, *(f"{v:.6g}" for v in (*row, scale))]) + "\n"
                   for tag, row in zip(tags, poses.tolist(), strict=True))


def format_vive(rec: ViveRecording, scale: float = 1.0) -> str:
    """A recording as the text of a Vive recording file (read back by ``read_vive``), its
    devices in the authors' file order."""
    tags = file_tags(rec.devices)
    order = [rec.device(TAGS[t]) for t in tags]
    poses = np.concatenate([rec.positions[:, order], rec.rotations[:, order]], axis=-1)
    return " ".join(HEADER) + "\n" + "".join(
        format_vive_frame(tags, poses[f], scale) for f in range(rec.num_frames))
