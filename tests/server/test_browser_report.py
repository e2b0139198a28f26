"""ViewerReport: a spectator's presentation times, checked as every message is, and
counted into /metrics' spectator stages; a hostile or buggy report gets one Error and
changes nothing else."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses

import numpy as np
import pytest
from conftest import serving
from stream_decode import decode
from test_http_metrics import TIMEOUT, fresh, histogram, http_get, joined, next_of, samples
from websockets.asyncio.client import ClientConnection

from posecast.protocol import (
    Error,
    ErrorCode,
    Ping,
    ProtocolError,
    ViewerReport,
    decode_client,
    encode,
)
from posecast.protocol.messages import MAX_REPORT_ROWS
from posecast.server.app import Session
from posecast.server.clock import now
from posecast.server.latency import VIEWER_STAGES
from posecast.server.limits import ServerLimits


def report(t_capture: list[float], received_after: float = 0.002,
           presented_after: float = 0.010) -> ViewerReport:
    t = np.asarray(t_capture)
    return ViewerReport(t_capture=t, t_received=t + received_after,
                        t_presented=t + presented_after)


def wire(**columns: object) -> bytes:
    """A viewer_report's msgpack bytes with whatever columns, unchecked."""
    import msgpack

    return msgpack.packb({"type": "viewer_report", **columns}, use_bin_type=True)


def f8(*values: float) -> bytes:
    return np.asarray(values, dtype="<f8").tobytes()


SHOWN = {"avatar_id": 1, "t_presented": 1.0, "root": f8(0.0, 1.0, 0.0),
         "rotations": np.array([0, 0, 0, 32767], "<i2").tobytes()}


# --------------------------------------------------------------------------- the message
def test_a_report_round_trips_within_a_client_message() -> None:
    small = report([1.0, 2.0, 3.0])
    assert decode_client(encode(small)) == small
    # a headset's: its frames' poses-to-submit, with or without avatar-frame rows
    headset = ViewerReport(t_capture=[], t_received=[], t_presented=[],
                           pose_to_submit=[0.004, 0.011])
    back = decode_client(encode(headset))
    assert back == headset and back.pose_to_submit is not None
    assert back.pose_to_submit.tolist() == [0.004, 0.011]
    full = report(list(np.linspace(0.0, 1.0, MAX_REPORT_ROWS)))
    assert len(encode(full)) <= 4096 and decode_client(encode(full)) == full


@pytest.mark.parametrize(("data", "words"), [
    (wire(t_capture=b"", t_received=b"", t_presented=b""), "an empty report"),
    (wire(t_capture=b"", t_received=b"", t_presented=b"", pose_to_submit=b""),
     "an empty report"),
    (wire(t_capture=f8(*range(129)), t_received=f8(*range(129)),
          t_presented=f8(*range(129))), "129 rows; at most 128 allowed"),
    (wire(t_capture=b"", t_received=b"", t_presented=b"", pose_to_submit=f8(0.01, -0.001)),
     "row 1: -0.001 s is not within 0 to 1 s"),
    (wire(t_capture=b"", t_received=b"", t_presented=b"", pose_to_submit=f8(2.0)),
     "row 0: 2.0 s is not within"),
    (wire(t_capture=b"", t_received=b"", t_presented=b"", pose_to_submit=f8(*[0.01] * 129)),
     "pose_to_submit: 129 rows; at most 128"),
    (wire(t_capture=f8(1.0, 2.0), t_received=f8(1.0), t_presented=f8(1.0)),
     "1 rows for 2 t_capture rows"),
    (wire(t_capture=f8(float("nan")), t_received=f8(1.0), t_presented=f8(1.0)),
     "row 0 is nan: times must be finite"),
    (wire(t_capture=f8(1.0), t_received=f8(1.0), t_presented=f8(float("inf"))),
     "row 0 is inf"),
    (wire(t_capture=f8(1.0), t_received=f8(2.0), t_presented=f8(1.5)),
     "row 0: t_presented 1.5 is before t_received 2.0"),
    (wire(t_capture=[1.0], t_received=f8(1.0), t_presented=f8(1.0)),
     "expected packed <f8 bytes, got list"),
    (wire(t_capture=b"1234567", t_received=f8(1.0), t_presented=f8(1.0)),
     "7 bytes is not a whole number"),
    (wire(t_capture=f8(1.0), t_received=f8(1.0)), "t_presented: Field required"),
    (wire(t_capture=f8(1.0), t_received=f8(1.0), t_presented=f8(1.0), extra=1),
     "extra"),
    # shown poses (the server's display error)
    (wire(t_capture=b"", t_received=b"", t_presented=b"", shown=[SHOWN] * 5),
     "at most 4 items"),
    (wire(t_capture=b"", t_received=b"", t_presented=b"",
          shown=[{**SHOWN, "rotations": b"\x00" * 7}]), "7 bytes is not a whole number"),
    (wire(t_capture=b"", t_received=b"", t_presented=b"",
          shown=[{**SHOWN, "rotations": np.array([0, 0, 0, 1000], "<i2").tobytes()}]),
     "unit quaternion"),
    (wire(t_capture=b"", t_received=b"", t_presented=b"",
          shown=[{**SHOWN, "root": f8(0.0, 1e9, 0.0)}]), "shown[0].root: row 0 position"),
    (wire(t_capture=b"", t_received=b"", t_presented=b"", shown=[SHOWN], mode="smooth"),
     "mode"),
])
def test_a_bad_report_is_one_clear_error(data: bytes, words: str) -> None:
    with pytest.raises(ProtocolError) as caught:
        decode_client(data)
    assert caught.value.code == ErrorCode.INVALID
    assert caught.value.message.startswith("viewer_report")
    assert words in caught.value.message


# --------------------------------------------------------------------------- the server
async def error_of(ws: ClientConnection) -> Error:
    msg = await next_of(ws, Error)
    assert isinstance(msg, Error)
    return msg


def test_reports_fill_the_spectator_stages_and_bad_ones_break_nothing() -> None:
    # a bucket that refills only after the test: the rate's cut-off is exact however
    # slowly the machine runs it
    limits = dataclasses.replace(ServerLimits(), reports_per_s=0.001)
    session = Session(fresh(Session()).rig, reconnect_grace=0.0, limits=limits)
    burst = limits.report_burst

    async def scenario() -> None:
        async with serving(session) as url, \
                joined(url, "spectator", "r", "browser") as viewer, \
                joined(url, "spectator", "r", "bystander") as bystander, \
                joined(url, "player", "r", "player") as player:
            t = now()
            # one good report of three frames: 2 ms to the viewer, 10 ms to its screen
            await viewer.send(encode(report([t - 0.003, t - 0.002, t - 0.001])))
            # an hour off the server clock: refused whole, naming column and row
            await viewer.send(encode(report([t - 0.001, t - 3600.0])))
            assert "viewer_report.t_capture[1]" in (await error_of(viewer)).message
            # malformed: the same one Error as any message gets
            await viewer.send(wire(t_capture=f8(t), t_received=f8(t), t_presented=f8(t - 1)))
            assert (await error_of(viewer)).code == ErrorCode.INVALID
            # a player has no presentation times to report
            await player.send(encode(report([t])))
            error = await error_of(player)
            assert error.code == ErrorCode.NOT_ALLOWED and "viewer_report" in error.message
            # over the rate: two reports took from the bucket (the one refused for its
            # times too), so the rest of it and one more
            for _ in range(burst - 1):
                await viewer.send(encode(report([now() - 0.001])))
            assert (await error_of(viewer)).code == ErrorCode.RATE_LIMITED
            # the viewer is still served: a ping answered after all of that
            await viewer.send(encode(Ping(t0=1.0)))
            assert decode(await asyncio.wait_for(viewer.recv(), TIMEOUT)).type == "pong"
            _, _, text = await http_get(url, "/metrics")
            # the bystander heard nothing of it (its room's rosters only)
            heard = []
            with contextlib.suppress(TimeoutError):
                while True:
                    heard.append(decode(await asyncio.wait_for(bystander.recv(), 0.2)).type)
            assert set(heard) <= {"avatar_roster"}
        scraped = samples(text.decode())
        rows = 3 + burst - 2  # the first report's, then one each
        for stage in VIEWER_STAGES:
            buckets, count, _ = histogram(scraped, stage)
            assert count == rows == session.metrics.viewer_latency.count(stage)
            assert buckets[-1] == (float("inf"), rows)
        _, _, presented = histogram(scraped, "capture_to_presented")
        _, _, received = histogram(scraped, "capture_to_spectator")
        assert presented == pytest.approx(0.010 * rows) and received == pytest.approx(
            0.002 * rows)
        # the server's own stages are there still, beside the viewers'
        assert histogram(scraped, "server")[1] == 0
        assert scraped[("posecast_viewer_reports_total", ())] == 1 + burst - 2
        rejections = {code: scraped[("posecast_rejections_total", (("code", code),))]
                      for code in ("invalid", "not_allowed", "rate_limited")}
        assert rejections == {"invalid": 2, "not_allowed": 1, "rate_limited": 1}
        assert session.metrics.limited["reports"] == 1

    asyncio.run(asyncio.wait_for(scenario(), 60))
