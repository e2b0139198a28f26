"""Text files as numbered lines, for the readers that report errors by file and line."""

from __future__ import annotations

from pathlib import Path

from posecast.solver.readers.errors import FormatError


def read_lines(path: Path, src: str, encoding: str, what: str) -> list[str]:
    """The file's lines without line ends, trailing empty lines dropped. A byte the
    encoding cannot decode is a FormatError at its line ("expected {what}")."""
    data = path.read_bytes()
    try:
        text = data.decode(encoding)
    except UnicodeDecodeError as err:
        line = data.count(b"\n", 0, err.start) + 1
        raise FormatError(src, line, f"expected {what}, found byte "
                                     f"0x{data[err.start]:02x}") from None
    # split on "\n" only (not str.splitlines, which also splits on form feeds and the
    # like) so line numbers match what an editor shows; some exports mix CRLF and LF
    lines = [line.rstrip("\r") for line in text.split("\n")]
    while lines and not lines[-1].strip():
        lines.pop()
    return lines
