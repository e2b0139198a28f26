"""Everything a person runs: the `posecast` command line and what it drives.

Packages, by concept (docs/architecture.md, "Layout"):
- ``cli``: the parser and one small module per command; each parses and calls library
  code below, so that tests call the same functions.
- ``session``: a connection to a server (clock sync, reconnect, TLS), the player that
  streams a source's poses, the spectator that receives a room.
- ``sources``: where a player's poses come from (OpenVR, recordings, BVH).
- ``viewer`` and ``web``: the desktop viewer (moderngl) and the browser page's sources.
- ``interop``: into and out of other tools (record, replay, BVH export, VMC).
- ``measure``: latency accounting, the video latency tool, display error, plots.
- ``bench``: every benchmark, the demo's harness, the network emulator, the Redis helper.

Directly here: the built-in motion (``builtin``), the skeletons it ships
(``skeletons``), the solver's warm-up (``jit``) and a progress bar (``progress``).
Nothing imports ``cli``, and only ``cli`` imports ``bench``; no package reaches into
another's underscore modules (tests/test_layering.py checks both).
"""
