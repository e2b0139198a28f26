"""The session's figures in Prometheus' text format, for ``GET /metrics``.

A collector reads ``Session.metrics`` and the rooms when scraped, so the server's frame
path counts plain integers and numpy arrays and never touches prometheus_client. Each
Session has a registry of its own (not the process-wide default): tests run many
servers in one process, and each scrape must show its own server alone.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.process_collector import ProcessCollector
from prometheus_client.registry import Collector

from posecast.protocol import DEVICE_ROLES, ErrorCode
from posecast.server.clock import now

if TYPE_CHECKING:  # the session holds the registry: imported for its type alone
    from posecast.server.app import Session

# the classic text format, which every Prometheus reads (what generate_latest writes)
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

# (Metrics field, help) of each frame counter: avatar-frames, as in the demo's table
FRAME_COUNTERS: tuple[tuple[str, str], ...] = (
    ("frames_received", "Tracker frames received from players."),
    ("frames_solved", "Avatar-frames solved and offered to the room's spectators."),
    ("frames_superseded", "Tracker frames replaced by a newer one of their player "
                          "before being solved."),
    ("frames_discarded", "Tracker frames never solved: their avatar left or "
                         "recalibrated, or the server stopped."),
    ("frames_rejected", "Tracker frames answered with an error."),
    ("frames_unsendable", "Avatar-frames solved but dropped: a spectator would refuse "
                          "the row."),
    ("frames_replayed", "Avatar-frames a replay connection published to the room's "
                        "spectators (posecast replay)."),
    ("frames_relayed", "Avatar-frames another process solved, received through Redis "
                       "for this process's spectators (serve --redis)."),
    ("frames_delivered", "Avatar-frames handed to a spectator's socket, summed over "
                         "spectators."),
    ("frames_dropped", "Avatar-frames never sent to a spectator: a newer one replaced "
                       "them (latest wins), or the spectator left."),
)


class SessionCollector(Collector):
    """Every figure of a session, read at scrape time."""

    def __init__(self, session: Session) -> None:
        self.session = session

    def collect(self) -> Iterator[Metric]:
        s, m = self.session, self.session.metrics
        yield CounterMetricFamily("posecast_connections", "Websocket connections accepted.",
                                  value=m.connections)
        for name, words in FRAME_COUNTERS:
            yield CounterMetricFamily(f"posecast_{name}", words, value=getattr(m, name))
        yield CounterMetricFamily("posecast_batches", "Batches solved (one solve, one "
                                  "message per spectator).", value=m.batches)
        yield CounterMetricFamily("posecast_calibrations", "T-poses taken (calibrations "
                                  "accepted).", value=m.calibrations)
        yield CounterMetricFamily("posecast_internal_errors", "Bugs met while handling "
                                  "a message or a connection (an alert: never expected).",
                                  value=m.internal_errors)
        yield CounterMetricFamily("posecast_writes_merged", "Writes to a spectator's "
                                  "socket that carried several batches (the fan-out ran "
                                  "past a batch's interval).", value=m.writes_merged)
        yield CounterMetricFamily("posecast_rosters", "Roster messages sent to a room's "
                                  "spectators (changes merged per room).", value=m.rosters)
        rejected = CounterMetricFamily("posecast_rejections", "Messages and joins "
                                       "refused with an error, by its code.",
                                       labels=["code"])
        # every code, zeros too: a rate over a series that appears late misses its start
        for code in sorted({*ErrorCode, *m.rejected}):
            rejected.add_metric([str(code)], m.rejected.get(code, 0))
        yield rejected
        devices = (
            ("device_lost_frames", "Tracker frames that lacked one of their avatar's "
             "devices (carried on by the body model, never refused), by role."),
            ("device_losses", "Times one of an avatar's devices was lost (tracked in its "
             "last frame, not in this one), by role."),
            ("devices_mounted", "Devices mounted after their avatar's calibration "
             "(switched on later), by role."))
        for name, words in devices:
            family = CounterMetricFamily(f"posecast_{name}", words, labels=["role"])
            counts = getattr(m, name)
            for role in DEVICE_ROLES:  # zeros too: rates need the series from the start
                family.add_metric([role], counts.get(role, 0))
            yield family
        limited = CounterMetricFamily("posecast_limited", "Refusals and closes by the "
                                      "server limit that made them.", labels=["limit"])
        for limit, n in sorted(m.limited.items()):
            limited.add_metric([limit], n)
        yield limited

        rooms = list(s.rooms.values())
        yield GaugeMetricFamily("posecast_open_connections", "Websocket connections "
                                "open now.", value=s.open_connections)
        yield GaugeMetricFamily("posecast_rooms", "Rooms open now.", value=len(rooms))
        yield GaugeMetricFamily("posecast_players", "Avatars whose player is connected.",
                                value=sum(a.connected for r in rooms
                                          for a in r.avatars.values()))
        yield GaugeMetricFamily("posecast_spectators", "Spectators connected.",
                                value=sum(len(r.spectators) for r in rooms))
        yield GaugeMetricFamily("posecast_uptime_seconds", "Seconds since the session "
                                "started.", value=now() - s.started)

        if s.cluster is not None:  # serve --redis
            yield GaugeMetricFamily("posecast_redis_up", "1 while the link to Redis works "
                                    "(serve --redis).", value=int(s.cluster.up))
            events = CounterMetricFamily(
                "posecast_cluster_events", "serve --redis: envelopes published and relayed, "
                "dropped while Redis was lost, rooms taken over, players redirected, Redis "
                "lost.", labels=["event"])
            for event, n in vars(s.cluster.stats).items():
                events.add_metric([event], n)
            yield events
        yield CounterMetricFamily("posecast_viewer_reports", "Reports of presentation "
                                  "times taken from spectators (ViewerReport).",
                                  value=m.viewer_reports)
        latency = HistogramMetricFamily(
            "posecast_latency_seconds", "Per avatar-frame, on the server's clock: "
            "capture_to_server (captured to its bytes' arrival), solve (arrival to "
            "solved), server (arrival to handed to the sockets), for every frame solved; "
            "capture_to_spectator (to its arrival at a viewer) and capture_to_presented "
            "(to a viewer's screen), for the frames viewers report; pose_to_submit (a "
            "headset viewer's poses to its frame's submission, on its own clock); relay "
            "(another process "
            "published a batch or roster to this one receiving it through Redis).",
            labels=["stage"])
        for histograms in (m.latency, m.viewer_latency, m.headset_latency, m.relay_latency):
            for stage in histograms.stages:
                buckets, total = histograms.cumulative(stage)
                latency.add_metric([stage], buckets, total)
        yield latency
        shown = HistogramMetricFamily(
            "posecast_display_error_meters", "How far the avatars viewers showed were from "
            "the avatars as solved at the same instant: per shown pose a viewer sampled "
            "(ViewerReport.shown), the mean distance over the body's joints, by the "
            "viewer's kind and playout mode.", labels=["viewer", "mode"])
        for key in sorted(m.display_error.by_label):
            buckets, total = m.display_error.cumulative(key)
            shown.add_metric(list(key), buckets, total)
        yield shown
        samples = CounterMetricFamily(
            "posecast_display_samples", "Shown poses viewers sampled: measured; unmeasured "
            "(no solved frames around their instant); skipped (over what a tick "
            "measures).", labels=["outcome"])
        for outcome in ("measured", "unmeasured", "skipped"):
            samples.add_metric([outcome], m.display_samples[outcome])
        yield samples


def session_registry(session: Session) -> CollectorRegistry:
    """A registry of the session's own: its figures and this process's (CPU, memory,
    open files)."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(SessionCollector(session))
    ProcessCollector(registry=registry)
    return registry


def metrics_text(registry: CollectorRegistry) -> bytes:
    return generate_latest(registry)
