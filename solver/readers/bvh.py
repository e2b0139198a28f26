"""Reader for BVH motion capture files, with the traps of real exports handled.

A BVH file is a joint hierarchy (``HIERARCHY``: nested ``ROOT``/``JOINT`` blocks with an
``OFFSET``, ``CHANNELS`` and ``End Site`` leaves) followed by ``MOTION``: a frame count, a
frame time and one line of channel values per frame. What this reader makes of it:

- Units: the output is in metres. ``scale`` (metres per file unit) may be given; when it is
  not, it is inferred from the size of the rest-pose skeleton (see ``infer_scale``), never
  from the file name.
- A joint's position channels *replace* its OFFSET for that frame (Bandai gives every joint
  six channels); joints without them use the OFFSET. ``Motion.translations`` holds every
  joint's local translation per frame, the root's being its global position, and the
  skeleton's offsets are the translations of the first motion frame.
- Rotation channels come in any order, per joint; each joint's rotation is the intrinsic
  Euler rotation in the order its channels are written (degrees in the file).
- ``End Site`` blocks are not joints: their offset is the ``tips`` entry of their joint.
- A frame rate within 0.1% of a whole number is that number ("Frame Time: 0.008333" is
  120 fps, not 120.005).
- A first frame that is a bind pose (CMU 01_01's T-pose) sets ``Motion.first_frame`` to 1.

Every problem in the file raises ``FormatError`` with the file and the 1-based line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from posecast.solver import rotations as rot
from posecast.solver.motion import Motion
from posecast.solver.readers.errors import FormatError
from posecast.solver.readers.text import read_lines
from posecast.solver.skeleton import Skeleton

Array = NDArray[np.float64]

CMU_UNIT = 0.056444  # metres per unit of the CMU database's BVH conversions
# candidate file units (metres per unit), tried by infer_scale
UNITS = {"metres": 1.0, "CMU units": CMU_UNIT, "centimetres": 0.01}
NOMINAL_SPAN = 1.7  # metres: the rest-pose span of an adult (about their height)
SPAN_TOLERANCE = 4.0  # an inferred span this many times off nominal means no unit fits
FPS_ROUNDING = 1e-3  # relative distance to a whole fps number that counts as rounding
REST_ZERO_DEG = 1e-3  # a rotation channel this close to zero is "zero" in a bind pose
REST_FRACTION = 0.8  # a bind-pose frame has at least this share of moving channels at zero
MOTION_FRACTION = 0.5  # ... and no later frame has more than this share at zero

POSITIONS = {"Xposition": 0, "Yposition": 1, "Zposition": 2}
ROTATIONS = {"Xrotation": "x", "Yrotation": "y", "Zrotation": "z"}
BRACES = ("{", "}")


@dataclass
class _Joint:
    name: str
    parent: int
    line: int
    offset: list[float] | None = None
    channels: list[str] = field(default_factory=list)
    tip: list[float] | None = None


@dataclass(frozen=True)
class _MotionHeader:
    frames: int
    frame_time: float
    frames_line: int  # 1-based line of "Frames:"
    data_start: int  # 0-based index of the first frame line


class _Cursor:
    """Tokens of the hierarchy with their line numbers; knows which line it is on."""

    def __init__(self, src: str, lines: list[str]) -> None:
        self.src = src
        self.lines = lines
        self.index = -1  # 0-based index of the current line
        self.tokens: list[str] = []
        self.pos = 0

    @property
    def line(self) -> int:
        return max(self.index + 1, 1)  # an empty file's problem is on its line 1

    def error(self, message: str, line: int | None = None) -> FormatError:
        return FormatError(self.src, self.line if line is None else line, message)

    def next(self) -> str | None:
        """The next token, or None at the end of the file."""
        while self.pos >= len(self.tokens):
            self.index += 1
            if self.index >= len(self.lines):
                self.index = len(self.lines) - 1
                return None
            self.tokens = self.lines[self.index].split()
            self.pos = 0
        self.pos += 1
        return self.tokens[self.pos - 1]

    def expect(self, token: str, context: str) -> None:
        found = self.next()
        if found != token:
            shown = "the end of the file" if found is None else repr(found)
            raise self.error(f"expected {token!r} {context}, found {shown}")

    def rest_of_line(self) -> list[str]:
        """The tokens left on the current line, up to a brace (which stays unread)."""
        out: list[str] = []
        while self.pos < len(self.tokens) and self.tokens[self.pos] not in BRACES:
            out.append(self.tokens[self.pos])
            self.pos += 1
        return out

    def numbers(self, keyword: str) -> list[float]:
        tokens = self.rest_of_line()
        if len(tokens) != 3:
            raise self.error(f"expected 3 numbers after {keyword}, found {len(tokens)}: "
                             f"{' '.join(tokens)!r}")
        return [_number(self, t, keyword) for t in tokens]


def read_bvh(path: str | Path, scale: float | None = None) -> Motion:
    """Read a BVH file into a Motion in metres.

    ``scale`` is metres per file unit; None infers it from the skeleton's size
    (``infer_scale``). Raises ``FormatError`` for anything wrong in the file.
    """
    if scale is not None and not (math.isfinite(scale) and scale > 0.0):
        raise ValueError(f"scale must be a positive number of metres per unit, got {scale}")
    src = str(path)
    lines = read_lines(Path(path), src, "utf-8", "UTF-8 text")
    cursor = _Cursor(src, lines)
    joints = _parse_hierarchy(cursor)
    header = _parse_motion_header(cursor)
    data = _parse_frames(src, lines, header, sum(len(j.channels) for j in joints))
    translations, rotations = _animate(joints, data)
    first = _first_motion_frame(joints, data)
    names = tuple(j.name for j in joints)
    parents = np.array([j.parent for j in joints], dtype=np.int32)
    tips = np.array([j.tip or (0.0, 0.0, 0.0) for j in joints], dtype=np.float64)
    unit = scale if scale is not None else infer_scale(src, parents, translations[first], tips)
    translations *= unit
    if not np.all(np.isfinite(translations)):
        raise FormatError(src, None, f"translations overflow at scale {unit}")
    # The skeleton's offsets are the first motion frame's translations, not the OFFSET
    # lines: in the Bandai files every joint's channels below Hips equal its OFFSET, but
    # Hips' channels are the hips' position over the floor, far from its OFFSET.
    skeleton = Skeleton(names, parents, translations[first].copy(), tips * unit)
    return Motion(skeleton=skeleton, rotations=rotations, translations=translations,
                  fps=_fps(header.frame_time), source=src, first_frame=first)


def _number(cursor: _Cursor, token: str, what: str) -> float:
    try:
        value = float(token)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise cursor.error(f"expected a finite number in {what}, found {token!r}")
    return value


# ---------------------------------------------------------------------------- hierarchy

def _parse_hierarchy(cursor: _Cursor) -> list[_Joint]:
    first = cursor.next()
    if first != "HIERARCHY":
        shown = "an empty file" if first is None else repr(first)
        raise cursor.error(f"expected HIERARCHY at the start of a BVH file, found {shown}")
    keyword = cursor.next()
    if keyword != "ROOT":
        shown = "the end of the file" if keyword is None else repr(keyword)
        raise cursor.error(f"expected ROOT after HIERARCHY (a skeleton needs joints), "
                           f"found {shown}")
    joints = [_Joint(_joint_name(cursor, "ROOT"), -1, cursor.line)]
    cursor.expect("{", f"after ROOT {joints[0].name}")
    stack = [0]
    while stack:
        _parse_block_item(cursor, joints, stack)
    if not any(j.channels for j in joints):
        raise cursor.error("the hierarchy declares no CHANNELS: there is nothing to animate",
                           joints[0].line)
    return joints


def _parse_block_item(cursor: _Cursor, joints: list[_Joint], stack: list[int]) -> None:
    """Read one item inside the { } block of the joint on top of the stack."""
    joint = joints[stack[-1]]
    token = cursor.next()
    if token is None:
        raise cursor.error(f"the file ends inside the {{ }} block of joint {joint.name!r} "
                           f"(line {joint.line}): expected '}}'")
    if token == "OFFSET":
        if joint.offset is not None:
            raise cursor.error(f"joint {joint.name!r} has a second OFFSET")
        joint.offset = cursor.numbers("OFFSET")
    elif token == "CHANNELS":
        if joint.channels:
            raise cursor.error(f"joint {joint.name!r} has a second CHANNELS line")
        joint.channels = _channels(cursor)
    elif token == "JOINT":
        _add_joint(cursor, joints, stack)
    elif token == "End":
        _end_site(cursor, joint)
    elif token == "MOTION":
        raise cursor.error(f"MOTION inside the {{ }} block of joint {joint.name!r} (line "
                           f"{joint.line}): a '}}' is missing above")
    elif token == "}":
        if joint.offset is None:
            raise cursor.error(f"joint {joint.name!r} (line {joint.line}) has no OFFSET",
                               joint.line)
        stack.pop()
    else:
        raise cursor.error(f"unknown keyword {token!r} in joint {joint.name!r}: expected "
                           f"OFFSET, CHANNELS, JOINT, End Site or '}}'")


def _joint_name(cursor: _Cursor, keyword: str) -> str:
    name = " ".join(cursor.rest_of_line())
    if not name:
        raise cursor.error(f"expected a joint name after {keyword}, found none")
    return name


def _add_joint(cursor: _Cursor, joints: list[_Joint], stack: list[int]) -> None:
    name = _joint_name(cursor, "JOINT")
    for other in joints:
        if other.name == name:
            raise cursor.error(f"joint name {name!r} is used twice (first on line "
                               f"{other.line}); names must be unique")
    joints.append(_Joint(name, stack[-1], cursor.line))
    cursor.expect("{", f"after JOINT {name}")
    stack.append(len(joints) - 1)


def _channels(cursor: _Cursor) -> list[str]:
    tokens = cursor.rest_of_line()
    if not tokens or not (tokens[0].isascii() and tokens[0].isdigit()):
        shown = repr(tokens[0]) if tokens else "nothing"
        raise cursor.error(f"expected a channel count after CHANNELS, found {shown}")
    count, names = int(tokens[0]), tokens[1:]
    if len(names) != count:
        raise cursor.error(f"CHANNELS declares {count} channels but names {len(names)}")
    if count > 6:
        raise cursor.error(f"expected at most 6 channels (3 positions, 3 rotations), "
                           f"found {count}")
    for name in names:
        if name not in POSITIONS and name not in ROTATIONS:
            raise cursor.error(f"unknown channel {name!r}: expected X/Y/Z position or "
                               f"X/Y/Z rotation (e.g. Xposition, Zrotation)")
    if len(set(names)) != len(names):
        raise cursor.error(f"a channel is listed twice: {' '.join(names)}")
    return names


def _end_site(cursor: _Cursor, joint: _Joint) -> None:
    cursor.expect("Site", "after End")
    if joint.tip is not None:
        raise cursor.error(f"joint {joint.name!r} has a second End Site")
    cursor.expect("{", "after End Site")
    cursor.expect("OFFSET", "inside End Site")
    joint.tip = cursor.numbers("the End Site OFFSET")
    cursor.expect("}", "to close End Site (it holds only an OFFSET)")


# ------------------------------------------------------------------------------- motion

def _parse_motion_header(cursor: _Cursor) -> _MotionHeader:
    token = cursor.next()
    if token != "MOTION":
        if token is None:
            message = "the file has no MOTION section after the hierarchy"
        elif token == "ROOT":
            message = "a second ROOT: only one skeleton per file is supported"
        elif token == "}":
            message = "an extra '}': the ROOT block is already closed; expected MOTION"
        else:
            message = f"expected MOTION after the hierarchy, found {token!r}"
        raise cursor.error(message)
    if cursor.rest_of_line():
        raise cursor.error("expected nothing after MOTION on its line")
    frames = _header_value(cursor, ["Frames:"])
    frames_line = cursor.line
    if not (frames.isascii() and frames.isdigit()) or int(frames) == 0:
        raise cursor.error(f"expected a positive whole number of frames, found {frames!r}")
    text = _header_value(cursor, ["Frame", "Time:"])
    frame_time = _number(cursor, text, "Frame Time")
    if not frame_time > 0.0:
        raise cursor.error(f"expected a Frame Time above 0 seconds, found {text}")
    return _MotionHeader(int(frames), frame_time, frames_line, cursor.index + 1)


def _header_value(cursor: _Cursor, words: list[str]) -> str:
    """The value on the next non-blank line, which must read '<words> <value>'."""
    label = " ".join(words)
    index = cursor.index + 1
    while index < len(cursor.lines) and not cursor.lines[index].strip():
        index += 1
    if index >= len(cursor.lines):
        raise cursor.error(f"the file ends before the '{label}' line of MOTION")
    tokens = cursor.lines[index].split()
    cursor.index, cursor.tokens, cursor.pos = index, tokens, len(tokens)
    if len(tokens) != len(words) + 1 or tokens[:-1] != words:
        raise cursor.error(f"expected '{label} <value>', found {cursor.lines[index]!r}")
    return tokens[-1]


def _parse_frames(src: str, lines: list[str], header: _MotionHeader,
                  width: int) -> Array:
    """The frame lines as an (F, channels) array; the problem on the earliest line raises."""
    first_line = header.data_start + 1
    rows = [line.split() for line in lines[header.data_start:header.data_start
                                           + header.frames]]
    counts = np.fromiter(map(len, rows), dtype=np.int64, count=len(rows))
    bad = np.flatnonzero(counts != width)
    data = _frame_numbers(src, rows[:int(bad[0])] if bad.size else rows, first_line, width)
    if bad.size:
        row = int(bad[0])
        cut = " (the file's last line: it looks cut off)" if row == len(rows) - 1 < (
            header.frames - 1) else ""
        raise FormatError(src, first_line + row,
                          f"frame {row}: expected {width} values (one per channel), "
                          f"found {counts[row]}{cut}")
    if len(rows) < header.frames:
        last = f"line {first_line + len(rows) - 1}" if rows else "none"
        raise FormatError(src, header.frames_line,
                          f"the file is truncated: 'Frames: {header.frames}' declares "
                          f"{header.frames} frames but only {len(rows)} frame lines "
                          f"follow (last: {last})")
    if len(lines) > header.data_start + header.frames:
        raise FormatError(src, first_line + header.frames,
                          f"more frame lines than 'Frames: {header.frames}' (line "
                          f"{header.frames_line}) declares; expected the file to end here")
    return data


def _frame_numbers(src: str, rows: list[list[str]], first_line: int, width: int) -> Array:
    """Convert rows that have the right value count; the first bad number raises."""
    tokens = [t for row in rows for t in row]
    try:
        data = np.fromiter(map(float, tokens), dtype=np.float64, count=len(tokens))
    except ValueError:  # not a number somewhere: find it the slow way
        data = np.full(len(tokens), np.nan)
        for k, token in enumerate(tokens):
            try:
                data[k] = float(token)
            except ValueError:
                break
    data = data.reshape(len(rows), width)
    finite = np.isfinite(data)
    if not finite.all():
        row = int(np.flatnonzero(~finite.all(axis=1))[0])
        col = int(np.flatnonzero(~finite[row])[0])
        raise FormatError(src, first_line + row,
                          f"frame {row}: expected a finite number for channel {col + 1}, "
                          f"found {rows[row][col]!r}")
    return data


def _fps(frame_time: float) -> float:
    fps = 1.0 / frame_time
    whole = round(fps)
    # "Frame Time: 0.008333" is 120.005 fps: a whole rate written with too few digits
    return float(whole) if whole > 0 and abs(fps - whole) <= FPS_ROUNDING * fps else fps


def _animate(joints: list[_Joint], data: Array) -> tuple[Array, Array]:
    """Local translations (F, J, 3) in file units and rotations (F, J, 4) per frame."""
    frames, count = data.shape[0], len(joints)
    offsets = np.array([j.offset for j in joints], dtype=np.float64)
    translations = np.repeat(offsets[None], frames, axis=0)
    rotations = rot.identity((frames, count))
    pos_joint: list[int] = []
    pos_axis: list[int] = []
    pos_col: list[int] = []
    orders: dict[str, tuple[list[int], list[list[int]]]] = {}
    col = 0
    for j, joint in enumerate(joints):
        order, cols = "", []
        for name in joint.channels:
            if name in POSITIONS:  # replaces that axis of the OFFSET, not added to it
                pos_joint.append(j)
                pos_axis.append(POSITIONS[name])
                pos_col.append(col)
            else:
                order += ROTATIONS[name]
                cols.append(col)
            col += 1
        if order:
            group = orders.setdefault(order, ([], []))
            group[0].append(j)
            group[1].append(cols)
    translations[:, pos_joint, pos_axis] = data[:, pos_col]
    # one from_euler call per distinct channel order (CMU 131 mixes ZXY and ZYX)
    for order, (js, col_lists) in orders.items():
        angles = np.radians(data[:, np.array(col_lists)])  # (F, len(js), len(order))
        rotations[:, js] = rot.from_euler(angles, order)
    return translations, rotations


def _first_motion_frame(joints: list[_Joint], data: Array) -> int:
    """1 if frame 0 is a bind pose before the motion (CMU 01_01's T-pose), else 0.

    A bind pose has nearly every rotation channel that moves during the file at exactly
    zero (CMU 01_01: all but the thighs' and upper arms' Z, which hold the T), while no
    later frame comes close. The root's channels and channels constant over the file
    (CMU's fixed LHipJoint) say nothing and are left out.
    """
    cols: list[int] = []
    col = 0
    for j, joint in enumerate(joints):
        for name in joint.channels:
            if j > 0 and name in ROTATIONS:
                cols.append(col)
            col += 1
    if data.shape[0] < 2 or not cols:
        return 0
    angles = data[:, cols]
    moving = np.ptp(angles, axis=0) > REST_ZERO_DEG
    if not moving.any():
        return 0
    zero_share = (np.abs(angles[:, moving]) < REST_ZERO_DEG).mean(axis=1)
    is_rest = zero_share[0] >= REST_FRACTION and zero_share[1:].max() < MOTION_FRACTION
    return 1 if is_rest else 0


def infer_scale(src: str, parents: NDArray[np.int32], offsets: Array, tips: Array) -> float:
    """Metres per file unit, from the order of magnitude of the rest-pose skeleton.

    The rule: pose the skeleton at rest (identity rotations, the first motion frame's
    translations), take its span, the largest distance between two of its joints or End
    Sites, and pick the unit among metres (1), CMU units (0.056444) and centimetres (0.01)
    that makes the span closest to an adult's 1.7 m (closest in ratio). An adult spans
    about 1.5-2.0 m in any rest pose (head to toe, or fingertip to fingertip), so the
    three units are far apart: ~1.7 in metres, ~30 in CMU units, ~170 in centimetres; the
    boundaries fall at ~7 and ~72 file units (measured: CMU files span 25-30 units, Bandai
    184-194 cm). This is the hip-height test made independent of the up axis and of the
    rest pose: CMU's hips stand ~17 units high, Bandai's ~90 cm, a metre file's ~1.
    The root joint is left out: its translation is a global position (Bandai's static
    joint_Root is at the origin, while its Hips may stand anywhere). Joint names are not
    used: rigs with CMU names exist in other units.
    """
    points = _rest_points(parents, offsets, tips)
    span = float(np.max(np.linalg.norm(points[:, None] - points[None], axis=-1)))
    if span > 0.0:
        unit = min(UNITS.values(), key=lambda u: abs(math.log(span * u / NOMINAL_SPAN)))
        if NOMINAL_SPAN / SPAN_TOLERANCE <= span * unit <= NOMINAL_SPAN * SPAN_TOLERANCE:
            return unit
    raise FormatError(src, None, f"cannot infer the length unit: the rest skeleton spans "
                                 f"{span:.4g} file units, which is no adult in "
                                 f"{', '.join(UNITS)}; pass scale= (metres per unit)")


def _rest_points(parents: NDArray[np.int32], offsets: Array, tips: Array) -> Array:
    """Global rest positions of the joints except the root, and of the End Sites."""
    count = len(parents)
    pos = np.zeros((count, 3))
    for j in range(1, count):
        pos[j] = pos[parents[j]] + offsets[j]
    has_tip = np.any(tips != 0.0, axis=1)
    keep = np.arange(count) > 0 if count > 1 else np.ones(count, dtype=bool)
    return np.concatenate([pos[keep], pos[has_tip] + tips[has_tip]])
