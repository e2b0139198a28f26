"""Pose sources for the player: OpenVR hardware, or a recording replayed in real time.

``open_source`` turns the ``--source`` argument of ``posecast play`` into a source.

Imports protocol/, solver/ and the built-in motion; no other client package (a source
knows nothing of the session it feeds).
"""

from __future__ import annotations

from pathlib import Path

from posecast.client.sources.base import (
    ROLES,
    DeviceSample,
    OffsetSource,
    PoseSource,
    SourceError,
    now,
)

__all__ = ["ROLES", "SPEC_FORMS", "DeviceSample", "OffsetSource", "PoseSource", "SourceError",
           "now", "open_source"]

SPEC_FORMS = ("openvr", "vive:FILE", "bvh:FILE")


def open_source(spec: str, config: Path | None = None, loop: bool = False,
                offset: tuple[float, float] = (0.0, 0.0)) -> PoseSource:
    """The source a spec names: ``openvr`` (live SteamVR devices; ``config``: a TOML file
    of serial-number roles), ``vive:FILE`` (a Vive recording) or ``bvh:FILE`` (simulated
    trackers from motion capture). ``loop`` replays a file source forever; ``offset``
    (x, z metres) moves every pose sideways (``OffsetSource``)."""
    source = _open(spec, config, loop)
    return OffsetSource(source, offset) if offset != (0.0, 0.0) else source


def _open(spec: str, config: Path | None, loop: bool) -> PoseSource:
    kind, sep, path = spec.partition(":")  # only the first colon: "vive:C:\\rec.csv" works
    if kind == "openvr" and not sep:
        # imported here: the native OpenVR library loads only for those who ask for it
        try:
            from posecast.client.sources.openvr_source import OpenVRSource
        except (ImportError, OSError) as err:
            raise SourceError(f"the openvr package cannot load: {err}") from None
        return OpenVRSource(config)
    if kind in ("vive", "bvh") and path:
        if config is not None:
            raise SourceError(f"a config file is for the openvr source, not {kind}:FILE")
        if kind == "vive":
            from posecast.client.sources.vive_source import ViveFileSource
            return ViveFileSource(path, loop=loop)
        from posecast.client.sources.bvh_source import BvhSource
        return BvhSource(path, loop=loop)
    raise SourceError(f"unknown pose source {spec!r}: use one of {', '.join(SPEC_FORMS)}")
