"""The `posecast` command: parses arguments and calls library functions (thin on purpose,
so that tests call the same functions)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

from posecast import __version__
from posecast.client import arguments as arg
from posecast.client.jit import CompileNotice, warm_kernels
from posecast.protocol.validation import ROOM_NAME_RULE
from posecast.server.limits import ServerLimits
from posecast.solver.ik import DEFAULT_SOLVER, SOLVERS, SolverOptions
from posecast.solver.motion import VIVE_DEVICES  # view --marker's joints
from posecast.solver.prediction import KINDS as PREDICTORS
from posecast.solver.tracking.devices import DEFAULT_SET, PRESETS

if TYPE_CHECKING:
    import ssl

    from posecast.client.connection import SessionError
    from posecast.client.player import Player
    from posecast.client.spectator import Spectator
    from posecast.client.viewer import ViewerStats
    from posecast.server.auth import JoinTokens

STOPPED = ("Ctrl-C (SIGINT) or SIGTERM stops it cleanly: it prints its summary and exits "
           "with status 130 (143 for SIGTERM), as a shell reports a signal.")


def _limit(text: str) -> str:
    """One NAME=VALUE of ``serve --limit``, checked against ServerLimits' fields. Limits
    that go together (avatars_per_room >= players_per_room) are checked together in
    _serve: one at a time, raising both (in a config file's [limits] too) would fail."""
    try:
        ServerLimits(players_per_room=1, avatars_per_room=2**62).with_text([text])
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def _redis_url(text: str) -> str:
    from posecast.server.cluster import check_redis_url

    try:
        return check_redis_url(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _secret_file(text: str) -> Path:
    """A file holding a join-token secret (server.auth): readable, 32 bytes or more."""
    from posecast.server.auth import SecretError, read_secret_file

    try:
        read_secret_file(Path(text))
    except SecretError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return Path(text)


# client.bench_hostile.ATTACKS, without importing it (and websockets) for every command
_HOSTILE_ATTACKS = ("calibrate-flood", "bad-messages", "big-frames", "poison-time",
                    "poison-calibration", "hello-strings", "reconnect-calibrate",
                    "join-leave")
# client.bench_fanout.BUDGET_MS, likewise
_FANOUT_BUDGET_MS = 25.0


def _addresses(text: str) -> list[str]:
    """``serve --trusted-proxies``: comma-separated IP addresses."""
    from posecast.server.address_budgets import normalized_ip

    values = [v.strip() for v in text.split(",") if v.strip()]
    try:
        return [normalized_ip(v) for v in values] if values else [normalized_ip(text)]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"not IP addresses: {err}") from None


def _origins(text: str) -> list[str]:
    """``serve --origins``: comma-separated scheme://host[:port] values."""
    from posecast.server.tls import check_origin

    try:
        return [check_origin(v.strip()) for v in text.split(",") if v.strip()] or [
            check_origin(text)]
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _positive_ints(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected numbers separated by commas, got {text!r}") from None
    if not values or any(v <= 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected positive numbers, got {text!r}")
    return values


def _parser() -> argparse.ArgumentParser:
    p = arg.Parser(prog="posecast", description=(
        "Stream full-body VR poses: calibrate, solve and score avatars from Vive trackers."),
        epilog="posecast COMMAND --help shows the options of a command.")
    p.add_argument("--version", action="version", version=f"posecast {__version__}")
    p.add_argument("--log-level", choices=arg.LOG_LEVELS, default=None,
                   help="diagnostics on stderr from this level up (default: info for serve, "
                        "warning for the others); may also follow the command")
    p.set_defaults(show_help=p.print_help)
    # not required: a bare `posecast` (or `posecast bench`) prints its help
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    ev = sub.add_parser("eval", help="reconstruct recordings (Vive .csv or .bvh) and score them")
    ev.add_argument("files", nargs="*", type=arg.existing_file, metavar="FILE",
                    help="recordings; none: the built-in CMU motion clip")
    ev.add_argument("--solver", choices=SOLVERS, default=DEFAULT_SOLVER,
                    help="the inverse kinematics solver")
    ev.add_argument("--max-iterations", type=_positive_ints, default=None,
                    help="iteration limit per chain; several (5,10,30) compare them")
    ev.add_argument("--calibration", choices=("fit", "uniform"), default="fit",
                    help="bone lengths fitted to the T-pose, or the paper's one uniform scale")
    ev.add_argument("--smoothing", type=arg.fraction, default=0.0,
                    help="SLERP smoothing, weight of the previous frame in [0, 1)")
    ev.add_argument("--delay-ms", type=arg.non_negative_float, default=None, metavar="D",
                    help="score what a viewer shows D ms after each capture, against the "
                         "recording at that instant (adds jitter_m_s3: mean jerk shown)")
    ev.add_argument("--predict", action="store_true",
                    help="with --delay-ms: carry each pose forward by D ms first (motion "
                         "prediction, as view --mode predict does)")
    ev.add_argument("--predictor", choices=PREDICTORS, default="posecast",
                    help="posecast's predictor, or a baseline to compare: constant velocity, "
                         "SlimeVR's averaged deltas")
    ev.add_argument("--predict-on", choices=("joints", "trackers"), default="joints",
                    help="predict the solved joint rotations (the viewer's way) or the "
                         "trackers before the solve (the server's)")
    ev.add_argument("--map", type=arg.existing_file, default=None, metavar="FILE",
                    help="BVH joint name -> role (.json or .toml) for rigs whose names and "
                         "shape are not recognised, e.g. {\"Bone_7\": \"forearm_l\"}")
    ev.add_argument("--devices", type=arg.devices, default=DEFAULT_SET, metavar="SET",
                    help="the devices that drive the avatar: 3 (head and hands), 4 (+ hip), "
                         "6 (+ feet), 10 (+ elbows and knees) or a comma list of roles; the "
                         "others are scored as held out (default: 6)")
    ev.add_argument("--dropouts", type=arg.dropouts, default=None,
                    metavar="RATE[,max=S][,seed=N]",
                    help="lose each driving device but the head at random, RATE times a "
                         "minute for 0.05 to S s (default 2); adds dropout_frames and "
                         "dropout_error_mm")
    ev.add_argument("--naive", action="store_true",
                    help="the naive baseline for body parts without a device: pelvis "
                         "straight under the head, legs straight down, feet on the floor")
    ev.add_argument("--cross-validate", action="store_true",
                    help="leave one clip out: score each Vive recording with the calibration "
                         "constants fitted on the others (at least two recordings)")
    ev.add_argument("--cross-validate-body", action="store_true",
                    help="leave one clip out: score each clip (mocap or Vive) at 3 and 4 "
                         "points with the body model's constants chosen on the others")
    ev.add_argument("--json", action="store_true", help="print one JSON document")

    sub.add_parser("warm", help="compile the solver kernels now, into numba's on-disk cache "
                   "(make setup runs it; other commands compile what they lack on first use)")

    sv = sub.add_parser("serve", help="host sessions: the websockets server")
    sv.add_argument("--config", type=arg.existing_file, default=None, metavar="FILE.toml",
                    help="take any of these options from a TOML file (keys: the option "
                         "names, e.g. port = 8765, busy_poll = true, a [limits] table); "
                         "flags given here override it; deploy/posecast.toml lists them all")
    sv.add_argument("--host", default="127.0.0.1",
                    help="address to listen on (0.0.0.0 for every interface)")
    sv.add_argument("--port", type=arg.port, default=8765,
                    help="port to listen on (0: any free one)")
    sv.add_argument("--solver", choices=SOLVERS, default=DEFAULT_SOLVER,
                    help="the inverse kinematics solver")
    sv.add_argument("--busy-poll", action="store_true",
                    help="never sleep: poll, and keep the frame path warm between bursts "
                         "(lower latency; takes a whole core, give it one)")
    sv.add_argument("--no-helper", dest="helper", action="store_false",
                    help="with --busy-poll on some cores only (taskset), a helper thread "
                         "spins on the others and takes part of each batch; this turns "
                         "it off")
    sv.add_argument("--secret-file", type=_secret_file, default=None, metavar="FILE",
                    help="admit only join tokens signed with the secret in FILE (posecast "
                         "token mints them); default: the secret in $POSECAST_SECRET, and "
                         "without either anyone joins any room")
    defaults = ServerLimits()
    sv.add_argument("--limit", action="append", default=[], type=_limit, metavar="NAME=VALUE",
                    help="override one of the server's limits (repeat for more; "
                         "docs/architecture.md, \"Limits\", says why each); names and "
                         "defaults: " + ", ".join(f"{name}={value}" for name, value
                                                  in vars(defaults).items()))

    sv.add_argument("--certfile", type=arg.existing_file, default=None,
                    help="serve wss:// (TLS 1.2+) with this PEM certificate (then any "
                         "intermediates); needs --keyfile")
    sv.add_argument("--keyfile", type=arg.existing_file, default=None,
                    help="the certificate's private key, PEM, unencrypted")
    sv.add_argument("--origins", type=_origins, default=None,
                    metavar="https://HOST[:PORT],...",
                    help="browser pages allowed to connect (their Origin header); a "
                         "client that sends no Origin, as play and view, is always let "
                         "in (default: every origin)")
    sv.add_argument("--trusted-proxies", type=_addresses, default=None,
                    metavar="ADDRESS,...",
                    help="reverse proxies in front (e.g. 127.0.0.1 for nginx on this "
                         "machine): a connection from one counts as the client its "
                         "X-Forwarded-For names, for every per-address limit and in the "
                         "log (default: none; behind a proxy without it, every client "
                         "shares the proxy's limits)")
    sv.add_argument("--redis", type=_redis_url, default=None, metavar="redis://HOST:PORT",
                    help="one of many server processes (on one machine or many) sharing "
                         "rooms through this Redis: a room is solved by one of them, its "
                         "spectators may join any (docs/architecture.md, \"Many "
                         "processes\")")
    sv.add_argument("--public-url", type=arg.server_url, default=None,
                    metavar="ws://HOST:PORT",
                    help="with --redis: where players reach this process, when other "
                         "processes send them here (default: ws://HOST:PORT as it "
                         "listens; behind a proxy, the proxy's URL for it)")

    pl = sub.add_parser("play", help="join a session as a tracked player",
                        description="Join a room as a player and stream your tracked poses. "
                        + STOPPED)
    pl.add_argument("--server", required=True, type=arg.server_url,
                    help="the server, ws://HOST:PORT (wss:// for TLS); several of one "
                         "service comma-separated, tried in turn (serve --redis)")
    pl.add_argument("--cafile", type=arg.ca_file, default=None,
                    help="PEM CA certificates to trust for a wss:// server (a private "
                         "CA); default: the system's trust store")
    pl.add_argument("--room", required=True, type=arg.room,
                    help="the room to join (made on first join); " + ROOM_NAME_RULE)
    pl.add_argument("--source", default="openvr", type=arg.source,
                    help="where the poses come from: openvr | vive:FILE | bvh:FILE")
    pl.add_argument("--name", default="player", type=arg.display_name,
                    help="the name shown above your avatar")
    pl.add_argument("--token", default=None, type=arg.token,
                    help="your join token from the host (posecast token), for a server "
                         "with a secret")
    pl.add_argument("--no-reconnect", dest="reconnect", action="store_false",
                    help="end when the connection is lost (by default: reconnect with "
                         "backoff and resume the avatar, still calibrated)")
    pl.add_argument("--devices", type=_devices_or_roles_file, default=None, metavar="SET",
                    help="the devices to stream, of those the source has: 3 (head and "
                         "hands), 4 (+ hip), 6 (+ feet), 10 (+ elbows and knees) or a "
                         "comma list of roles (default: every device the source has)")
    pl.add_argument("--dropouts", type=arg.dropouts, default=None, metavar="RATE[,max=S]"
                    "[,seed=N]",
                    help="lose each device but the head at random, RATE times a minute "
                         "for 0.05 to S s (default 2), as a tracker hidden from the base "
                         "stations is: to try what the room sees")
    pl.add_argument("--roles", type=arg.existing_file, default=None, metavar="FILE.toml",
                    help="TOML file mapping tracker serial numbers to roles (openvr)")
    pl.add_argument("--loop", action="store_true", help="replay a recording forever")
    pl.add_argument("--offset", type=arg.offset, default=(0.0, 0.0), metavar="X,Z",
                    help="move every pose sideways by X,Z metres, so that players replaying "
                         "one clip stand apart (default: 0,0)")
    pl.add_argument("--seconds", type=arg.positive_float, default=None,
                    help="stop after this many seconds (default: when the source ends)")
    pl.add_argument("--record", type=arg.new_file, default=None, metavar="FILE",
                    help="also keep the raw device poses in FILE, a Vive recording "
                         "(docs/vive-format.md) that posecast eval and --source vive:FILE "
                         "read; frame 0 is the calibration T-pose")
    pl.add_argument("--calibrate-in", type=arg.non_negative_float, default=None,
                    help="seconds to get into the T-pose before calibrating "
                         "(default: 3 for openvr, 0 for recordings); press Enter to "
                         "recalibrate while playing")

    vw = sub.add_parser("view", help="watch a room: skinned avatars in a window, or to PNGs",
                        description="Watch a room: every avatar skinned, in a window or "
                        "(--headless) to PNG files. " + STOPPED)
    vw.add_argument("--server", required=True, type=arg.server_url,
                    help="the server, ws://HOST:PORT (wss:// for TLS); several of one "
                         "service comma-separated, tried in turn (serve --redis)")
    vw.add_argument("--cafile", type=arg.ca_file, default=None,
                    help="PEM CA certificates to trust for a wss:// server (a private "
                         "CA); default: the system's trust store")
    vw.add_argument("--room", required=True, type=arg.room,
                    help="the room to watch; " + ROOM_NAME_RULE)
    vw.add_argument("--headless", action="store_true",
                    help="no window: render through EGL to PNG files in --out")
    vw.add_argument("--frames", type=arg.positive_int, default=None,
                    help="stop after this many frames that show a player (default: 100 "
                         "headless; a window until it is closed)")
    vw.add_argument("--out", type=arg.out_dir, default=Path("frames"),
                    help="PNG folder (headless), made if missing")
    vw.add_argument("--size", type=arg.size, default="1280x720", help="WIDTHxHEIGHT in pixels")
    vw.add_argument("--fps", type=arg.positive_float, default=30.0,
                    help="frames drawn per second")
    vw.add_argument("--mode", choices=("interpolate", "zero-buffer", "predict"),
                    default="interpolate",
                    help="interpolate: render slightly behind, SLERP between frames; "
                         "zero-buffer: the newest frame, least latency; predict: the "
                         "newest frame carried forward by its capture-to-render latency")
    vw.add_argument("--view", choices=("orbit", "first-person", "mirror"), default="orbit",
                    help="the camera: around everyone, at a player's eyes, or facing them")
    vw.add_argument("--screenshot", type=arg.out_file, default=None,
                    help="window: save the last frame shown as a PNG")
    vw.add_argument("--token", default=None, type=arg.token,
                    help="your join token from the host (posecast token), for a server "
                         "with a secret")
    vw.add_argument("--no-reconnect", dest="reconnect", action="store_false",
                    help="end when the connection is lost (by default: reconnect with "
                         "backoff to the same room)")
    vw.add_argument("--max-rate", type=arg.rate_hz, default=None,
                    help="ask the server for at most this many batches per second")
    vw.add_argument("--json", action="store_true",
                    help="print the summary as one JSON document")
    vw.add_argument("--marker", nargs="?", const="right_hand", default=None,
                    choices=VIVE_DEVICES, metavar="JOINT",
                    help="draw a high-contrast marker on this joint of every avatar, for "
                         "posecast latency-video to follow in a video of tracker and "
                         "screen (alone: right_hand; JOINT: " + ", ".join(VIVE_DEVICES)
                         + ")")

    rc = sub.add_parser("record", help="record a room's skeletons and avatar frames to a file",
                        description="Record a room as its spectators receive it: every "
                        "skeleton and avatar frame, with their timestamps, to a new .pcrec "
                        "file (docs/recording-format.md) that posecast replay and export "
                        "read. " + STOPPED)
    rc.add_argument("--server", required=True, type=arg.server_url,
                    help="the server, ws://HOST:PORT (wss:// for TLS); several of one "
                         "service comma-separated, tried in turn (serve --redis)")
    rc.add_argument("--room", required=True, type=arg.room,
                    help="the room to record; " + ROOM_NAME_RULE)
    rc.add_argument("--out", required=True, type=arg.new_file, metavar="FILE",
                    help="the recording to make (never written over)")
    rc.add_argument("--seconds", type=arg.positive_float, default=None,
                    help="stop after this many seconds (default: until Ctrl-C)")
    rc.add_argument("--cafile", type=arg.ca_file, default=None,
                    help="PEM CA certificates to trust for a wss:// server (a private "
                         "CA); default: the system's trust store")
    rc.add_argument("--token", default=None, type=arg.token,
                    help="a spectator's join token (posecast token), for a server with a "
                         "secret")
    rc.add_argument("--no-reconnect", dest="reconnect", action="store_false",
                    help="end when the connection is lost (by default: reconnect with "
                         "backoff and go on recording)")

    rp = sub.add_parser("replay", help="play a recording back into a room",
                        description="Play a recording (posecast record) back into a room "
                        "at its original timing: its avatars join the room and move as "
                        "they did, for every spectator there. " + STOPPED)
    rp.add_argument("file", type=arg.existing_file, metavar="FILE", help="a .pcrec recording")
    rp.add_argument("--server", required=True, type=arg.server_url,
                    help="the server, ws://HOST:PORT (wss:// for TLS); several of one "
                         "service comma-separated, tried in turn (serve --redis)")
    rp.add_argument("--room", required=True, type=arg.room,
                    help="the room to play into; " + ROOM_NAME_RULE)
    rp.add_argument("--speed", type=arg.positive_float, default=1.0,
                    help="play this many times faster than recorded")
    rp.add_argument("--loop", action="store_true", help="start again at the end, forever")
    rp.add_argument("--cafile", type=arg.ca_file, default=None,
                    help="PEM CA certificates to trust for a wss:// server (a private "
                         "CA); default: the system's trust store")
    rp.add_argument("--token", default=None, type=arg.token,
                    help="a player's join token (posecast token --role player), for a "
                         "server with a secret")

    ex = sub.add_parser("export", help="a recording as one BVH file per avatar",
                        description="Write each avatar of a recording (posecast record) as "
                        "a BVH file: its calibrated skeleton as the hierarchy (centimetres), "
                        "its poses resampled to one rate as the motion; Blender, three.js "
                        "and posecast eval read them. An avatar recalibrated during the "
                        "recording gets a second file.")
    ex.add_argument("file", type=arg.existing_file, metavar="FILE", help="a .pcrec recording")
    ex.add_argument("--bvh", required=True, type=arg.out_dir, metavar="DIR",
                    help="the folder to write into, made if missing (files of the same "
                         "names are replaced)")
    ex.add_argument("--fps", type=arg.rate_hz, default=None,
                    help="the frame rate of the files (default: the recording's own, the "
                         "median rate rounded)")

    vm = sub.add_parser("vmc", help="send one avatar of a room to a VMC receiver (VSeeFace, "
                        "VNyan, Warudo, Unity)",
                        description="Send one avatar of a room to a VMC protocol receiver "
                        "(OSC over UDP: VSeeFace, VNyan, Warudo, Unity with EVMC4U) as it "
                        "moves: root, the Unity humanoid bones, OK and time, one bundle a "
                        "frame. " + STOPPED)
    vm.add_argument("--server", required=True, type=arg.server_url,
                    help="the server, ws://HOST:PORT (wss:// for TLS); several of one "
                         "service comma-separated, tried in turn (serve --redis)")
    vm.add_argument("--room", required=True, type=arg.room,
                    help="the room to take the avatar from; " + ROOM_NAME_RULE)
    vm.add_argument("--avatar", default=None, type=arg.display_name, metavar="NAME",
                    help="the avatar's name (default: the room's first avatar)")
    vm.add_argument("--to", default="127.0.0.1:39539", type=arg.vmc_target,
                    metavar="HOST:PORT", help="the VMC receiver (39539: the protocol's port)")
    vm.add_argument("--rate", type=arg.rate_hz, default=60.0,
                    help="bundles per second at most (receivers choke above 200)")
    vm.add_argument("--seconds", type=arg.positive_float, default=None,
                    help="stop after this many seconds (default: until Ctrl-C)")
    vm.add_argument("--cafile", type=arg.ca_file, default=None,
                    help="PEM CA certificates to trust for a wss:// server (a private "
                         "CA); default: the system's trust store")
    vm.add_argument("--token", default=None, type=arg.token,
                    help="a spectator's join token (posecast token), for a server with a "
                         "secret")

    tk = sub.add_parser("token", help="print a join token for a server with a secret",
                        description="Print a join token (a JWT signed with the server's "
                        "secret) for one room and role; only the token goes to stdout, so "
                        "that TOKEN=$(posecast token ...) works.")
    tk.add_argument("--secret-file", type=_secret_file, default=None, metavar="FILE",
                    help="the server's secret (as serve --secret-file); default: "
                         "$POSECAST_SECRET")
    tk.add_argument("--room", required=True, type=arg.room,
                    help="the room it admits to; " + ROOM_NAME_RULE)
    tk.add_argument("--role", required=True, choices=("player", "spectator"),
                    help="what it admits as")
    tk.add_argument("--ttl", type=arg.duration, default="2h",
                    help="how long it stays valid: 90s, 15m, 2h, 7d or seconds")
    tk.add_argument("--name", type=arg.display_name, default=None,
                    help="admit only this display name (default: any)")

    dm = sub.add_parser("demo", help="a whole session on this machine, with latency table")
    dm.add_argument("--render", type=arg.out_dir, default=None,
                    help="also run a headless viewer writing PNG frames to this folder")
    dm.add_argument("--render-mode", choices=("interpolate", "zero-buffer"),
                    default="interpolate", help="the viewer's snapshot mode (with --render)")
    dm.add_argument("--players", type=arg.count, default=4,
                    help="players replaying the built-in walk, each standing apart")
    dm.add_argument("--spectators", type=arg.count, default=2, help="headless spectators")
    dm.add_argument("--seconds", type=arg.positive_float, default=10.0,
                    help="how long the players stream")
    dm.add_argument("--solver", choices=SOLVERS, default=DEFAULT_SOLVER,
                    help="the inverse kinematics solver")
    dm.add_argument("--no-busy-poll", dest="busy_poll", action="store_false",
                    help="the server sleeps between bursts (by default it busy-polls "
                         "when it has a core of its own)")
    dm.add_argument("--no-helper", dest="helper", action="store_false",
                    help="the server solves alone (by default, busy polling, a helper "
                         "thread spins on the clients' core and takes part of each batch)")
    dm.add_argument("--network", type=arg.network, default=None, metavar="SPEC",
                    help="put an emulated link between every client and the server, "
                         "each direction delayed: DELAY[+-JITTER][,stall=HOLD/EVERY]"
                         "[,seed=N], e.g. 40ms+-10ms or 40ms+-10ms,stall=200ms/5s "
                         "(default: loopback)")
    dm.add_argument("--limit", action="append", default=[], type=_limit, metavar="NAME=VALUE",
                    help="override one of the server's limits, as serve --limit does")
    dm.add_argument("--servers", type=arg.positive_int, default=1, metavar="N",
                    help="run N server processes sharing the room through a Redis the demo "
                         "starts (serve --redis; needs redis-server): the players on the "
                         "first, the spectators spread over all; the latency table gains "
                         "the relay hop")
    dm.add_argument("--devices", action="append", type=_device_set, default=None,
                    metavar="SET",
                    help="the players' tracker set: 3 (head and hands), 4 (+ hip), 6 (+ "
                         "feet, the default), 10 (+ elbows and knees) or a comma list of "
                         "roles; repeat it for a room of several, taken in turn")
    dm.add_argument("--dropouts", type=arg.dropouts, default=None,
                    metavar="RATE[,max=S][,seed=N]",
                    help="every player loses each device but the head at random, RATE "
                         "times a minute for 0.05 to S s (default 2)")
    dm.add_argument("--json", action="store_true", help="print one JSON document")

    lv = sub.add_parser("latency-video", help="end-to-end latency from a video of the "
                        "tracker and the screen (the paper's section 3.2)",
                        description="Measure end-to-end latency from a video that films the "
                        "tracker swinging and the screen showing its avatar (view --marker "
                        "draws a marker to follow): both boxes are followed with OpenCV, "
                        "the turns of their horizontal motion paired, and the mean frame "
                        "difference turned into ms; a cross-correlation estimate is shown "
                        "beside it. docs/latency-video.md says how to film.")
    lv.add_argument("video", type=arg.existing_file, metavar="VIDEO",
                    help="the video (a phone's slow motion, 240 fps, is best)")
    lv.add_argument("--tracker-box", type=arg.box, default=None, metavar="X,Y,W,H",
                    help="the real tracker (or a marker on it) in the first frame, pixels")
    lv.add_argument("--avatar-box", type=arg.box, default=None, metavar="X,Y,W,H",
                    help="the avatar's marker on the screen in the first frame, pixels")
    lv.add_argument("--select", action="store_true",
                    help="draw both boxes on the first frame (needs a display and an "
                         "OpenCV with a GUI)")
    lv.add_argument("--tracker", choices=("kcf", "csrt"), default="kcf",
                    help="OpenCV's tracker: KCF as in the paper, CSRT slower and steadier")
    lv.add_argument("--fps", type=arg.positive_float, default=None,
                    help="frames per second of the filming (default: the file's; give it "
                         "for a slow-motion video saved at a playback rate)")
    lv.add_argument("--plot", type=arg.out_file, default=None, metavar="FILE.png",
                    help="draw both traces, their turns and how they were paired")
    lv.add_argument("--json", action="store_true", help="print one JSON document")

    bench = sub.add_parser("bench", help="measure speed")
    bsub = bench.add_subparsers(dest="bench", metavar="WHAT")
    bs = bsub.add_parser("solver", help="microseconds per avatar-frame at several batch sizes")
    bs.add_argument("--solver", choices=SOLVERS, default=DEFAULT_SOLVER,
                    help="the inverse kinematics solver")
    bs.add_argument("--avatars", type=_positive_ints, default=[1, 10, 100],
                    help="batch sizes to measure, comma-separated (default: 1,10,100)")
    bs.add_argument("--max-iterations", type=arg.positive_int, default=None,
                    help="iteration limit per chain (default: the solver's own)")
    bs.add_argument("--seconds", type=arg.positive_float, default=2.0,
                    help="time spent per batch size")
    bs.add_argument("--devices", type=arg.devices, default=DEFAULT_SET, metavar="SET",
                    help="the tracker set the avatars are driven by (as for eval); the "
                         "body model fills the rest")
    bs.add_argument("--json", action="store_true", help="print one JSON document")
    bp = bsub.add_parser("protocol", help="wire sizes, quantization error, codec timings")
    bp.add_argument("--json", action="store_true", help="print one JSON document")
    br = bsub.add_parser("render", help="ms per frame of the viewer (software GL here)")
    br.add_argument("--avatars", type=arg.positive_int, default=16, help="avatars drawn")
    br.add_argument("--size", type=arg.size, default="1280x720", help="WIDTHxHEIGHT in pixels")
    br.add_argument("--frames", type=arg.positive_int, default=120, help="frames to draw")
    br.add_argument("--out", type=arg.out_file, default=None, help="save the last frame as PNG")
    br.add_argument("--json", action="store_true", help="print one JSON document")
    bv = bsub.add_parser("server", help="players and spectators one server sustains")
    bv.add_argument("--counts", type=_positive_ints, default=[4, 8, 16, 24, 32, 48, 64],
                    help="players (= spectators) to try, in order "
                         "(default: 4,8,16,24,32,48,64)")
    bv.add_argument("--seconds", type=arg.positive_float, default=4.0,
                    help="length of each step")
    bv.add_argument("--no-helper", dest="helper", action="store_false",
                    help="the server solves alone (see demo --no-helper)")
    bv.add_argument("--json", action="store_true", help="print one JSON document")
    bf = bsub.add_parser("fanout", help="spectators one server process serves, and several "
                         "together through Redis (serve --redis; needs redis-server)")
    bf.add_argument("--processes", type=_positive_ints, default=[1, 2],
                    help="numbers of server processes to measure, comma-separated "
                         "(default: 1,2)")
    bf.add_argument("--players", type=arg.positive_int, default=4,
                    help="players at 90 Hz in the room (on the first process)")
    bf.add_argument("--start", type=arg.positive_int, default=200,
                    help="spectators of the first step (then x1.5 until one fails, "
                         "then halving the gap)")
    bf.add_argument("--max", type=arg.positive_int, default=20000,
                    help="spectators not to go beyond (default: 20000)")
    bf.add_argument("--budget-ms", type=arg.positive_float, default=_FANOUT_BUDGET_MS,
                    help="p99 capture to spectator each process must keep besides losing "
                         f"at most 1%% of the frames (default: {_FANOUT_BUDGET_MS:g})")
    bf.add_argument("--seconds", type=arg.positive_float, default=4.0,
                    help="length of each step's measurement")
    bf.add_argument("--repeat", type=arg.positive_int, default=1,
                    help="whole runs, reporting each count's median and the median of "
                         "the runs' ratios (a run takes ~5 min)")
    bf.add_argument("--json", action="store_true", help="print one JSON document")
    bu = bsub.add_parser("startup", help="seconds the first commands take after set-up "
                         "(--version, serve until listening, eval of the built-in clip)")
    bu.add_argument("--runs", type=arg.positive_int, default=5,
                    help="fresh processes per command")
    bu.add_argument("--json", action="store_true", help="print one JSON document")
    bk = bsub.add_parser("soak", help="the server's RSS, open files and rates over minutes "
                         "of players and spectators, as a table and a plot")
    bk.add_argument("--minutes", type=arg.positive_float, required=True,
                    help="how long the players stream")
    bk.add_argument("--players", type=arg.positive_int, default=8,
                    help="players replaying the built-in walk at 90 Hz")
    bk.add_argument("--spectators", type=arg.count, default=8, help="headless spectators")
    bk.add_argument("--interval", type=arg.positive_float, default=None,
                    help="seconds between samples (default: 5, less for short runs)")
    bk.add_argument("--plot", type=arg.out_file, default=None, metavar="FILE.png",
                    help="also draw RSS, open files and rates over time to this PNG")
    bk.add_argument("--json", action="store_true", help="print one JSON document")
    bpr = bsub.add_parser("prediction", help="error a viewer's delay adds, with and without "
                          "motion prediction (D = 0, 25, 50, 100 ms; a minute or two)")
    bpr.add_argument("files", nargs="*", type=arg.existing_file, metavar="FILE",
                     help="Vive .csv and .bvh recordings (default: ../shared/data/vive/*.csv "
                          "and ../shared/data/mocap/*.bvh)")
    bpr.add_argument("--json", action="store_true", help="print one JSON document")
    bh = bsub.add_parser("hostile", help="what one hostile client costs everyone else "
                         "(issues 14 and 27's attacks, figures beside their targets)")
    bh.add_argument("--attack", required=True, choices=_HOSTILE_ATTACKS,
                    help="calibrate-flood, bad-messages and big-frames run in another room "
                         "than the bystanders; poison-time, poison-calibration, "
                         "hello-strings, reconnect-calibrate and join-leave in theirs")
    bh.add_argument("--seconds", type=arg.positive_float, default=10.0,
                    help="how long the attacker attacks")
    bh.add_argument("--json", action="store_true", help="print one JSON document")
    for child in arg.subparsers(p):  # the global options may follow the command too
        child.add_argument("--log-level", choices=arg.LOG_LEVELS, default=argparse.SUPPRESS,
                           help="as posecast --log-level")
        child.set_defaults(show_help=child.print_help)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if getattr(args, "config", None) is not None:  # the file's values become defaults
        args = _with_config(parser, args, argv)
    if args.command is None or (args.command == "bench" and args.bench is None):
        args.show_help()
        return 0
    _configure_logging(args.command, args.log_level)
    notice = CompileNotice().install()  # a command that must compile kernels says so
    try:
        return _command(args, notice)
    except KeyboardInterrupt:  # Ctrl-C where no command handles it (e.g. while compiling)
        print(f"posecast {args.command}: interrupted", file=sys.stderr)
        return 130
    finally:  # process-wide: tests call main() many times, each with its own stderr
        notice.close()
        notice.uninstall()


def _with_config(parser: argparse.ArgumentParser, args: argparse.Namespace,
                 argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line parsed again over ``--config``'s values; a bad file is one line
    naming its line and key, exit 2, as a bad flag."""
    from posecast.client.config_file import ConfigError, apply_config

    command = next(child for child in arg.subparsers(parser)
                   if child.prog == f"{parser.prog} {args.command}")
    try:
        apply_config(parser, command, args.config)
    except ConfigError as err:
        command.error(f"--config {err}")
    return parser.parse_args(argv)


def _configure_logging(command: str, level_name: str | None) -> None:
    """Diagnostics go through logging to stderr: from info up for serve (its log of who
    joins and leaves), from warning up for the others, whose results go to stdout."""
    level = getattr(logging, (level_name or ("info" if command == "serve" else "warning"))
                    .upper())
    logging.basicConfig(format="%(asctime)s %(levelname)s %(name)s: %(message)s"
                        if command == "serve" else
                        f"posecast {command}: %(levelname)s: %(message)s")
    logging.getLogger().setLevel(level)
    # websockets' own "connection open/closed" lines name nobody: ours do (server.app)
    logging.getLogger("websockets").setLevel(logging.DEBUG if level <= logging.DEBUG
                                             else logging.WARNING)
    logging.getLogger("numba").setLevel(logging.WARNING)  # its debug output is the compiler's


def _eval_flags_given(args: argparse.Namespace, *more: tuple[str, bool]) -> list[str]:
    """The options of eval given that the cross-validations do not take."""
    return [flag for flag, on in (
        ("--delay-ms", args.delay_ms is not None), ("--predict", args.predict),
        ("--map", args.map is not None), ("--dropouts", args.dropouts is not None),
        ("--naive", args.naive),
        ("--devices", set(args.devices) != set(PRESETS[DEFAULT_SET])), *more) if on]


def _command(args: argparse.Namespace, notice: CompileNotice) -> int:
    if args.command == "warm":
        print(f"kernels ready in {warm_kernels(notice):.1f} s")
        return 0
    if args.command in ("demo", "bench"):  # before their processes start, each would compile
        warm_kernels(notice)
    if args.command == "eval" and args.cross_validate_body:
        from posecast.client.crossval_body_command import run_cross_validate_body

        return run_cross_validate_body(
            args.files, args.solver, args.max_iterations, args.json,
            given=_eval_flags_given(args, ("--smoothing", args.smoothing != 0.0),
                                    ("--cross-validate", args.cross_validate)))
    if args.command == "eval" and args.cross_validate:
        from posecast.client.crossval_command import run_cross_validate

        return run_cross_validate(args.files, args.solver, args.max_iterations,
                                  args.calibration, args.smoothing, args.json,
                                  given=_eval_flags_given(args))
    if args.command == "eval":
        from posecast.client.eval_command import run_eval

        return run_eval(args.files, args.solver, args.max_iterations, args.calibration,
                        args.smoothing, args.json, delay_ms=args.delay_ms,
                        predict=args.predict, predictor=args.predictor,
                        predict_on=args.predict_on, joint_map=args.map,
                        devices=args.devices, dropouts=args.dropouts, naive=args.naive)
    if args.command == "token":
        return _token(args)
    if args.command == "latency-video":
        from posecast.client.latency_video import run_latency_video

        return run_latency_video(args.video, args.tracker_box, args.avatar_box,
                                 tracker=args.tracker, select=args.select, fps=args.fps,
                                 plot=args.plot, as_json=args.json)
    if args.command == "record":
        from posecast.client.connection import SessionError
        from posecast.client.record_command import run_record

        if (status := _cafile_without_tls("record", args)) is not None:
            return status
        try:
            return run_record(args.server, args.room, args.out, args.seconds, args.token,
                              args.cafile, args.reconnect)
        except SessionError as err:
            return _fail("record", _session_words(err))
        except OSError as err:  # the file (made since the arguments were checked)
            return _fail("record", f"{args.out}: {err.strerror or err}")
    if args.command == "replay":
        from posecast.client.connection import SessionError
        from posecast.client.record_command import run_replay

        if (status := _cafile_without_tls("replay", args)) is not None:
            return status
        try:
            return run_replay(args.file, args.server, args.room, args.speed, args.loop,
                              args.token, args.cafile)
        except SessionError as err:
            return _fail("replay", _session_words(err))
    if args.command == "export":
        from posecast.client.export_command import run_export

        return run_export(args.file, args.bvh, args.fps)
    if args.command == "vmc":
        from posecast.client.connection import SessionError
        from posecast.client.vmc import VmcError
        from posecast.client.vmc_command import run_vmc_command

        if (status := _cafile_without_tls("vmc", args)) is not None:
            return status
        host, port = args.to
        try:
            return run_vmc_command(args.server, args.room, args.avatar, host, port,
                                   args.seconds, args.rate, args.token, args.cafile)
        except SessionError as err:
            return _fail("vmc", _session_words(err))
        except VmcError as err:
            return _fail("vmc", err)
    if args.command == "serve":
        return _serve(args)
    if args.command == "play":
        return _play(args)
    if args.command == "demo":
        return _demo(args)
    if args.command == "view":
        return _view(args)
    if args.command == "bench" and args.bench == "solver":
        from posecast.client.bench import bench_solver, format_solver_table

        result = bench_solver(args.solver, args.avatars,
                              SolverOptions(max_iterations=args.max_iterations), args.seconds,
                              args.devices)
        print(json.dumps(result) if args.json else format_solver_table(result))
        return 0
    if args.command == "bench" and args.bench == "protocol":
        from posecast.client.bench_protocol import bench_protocol, format_protocol_table

        doc = bench_protocol()
        print(json.dumps(doc) if args.json else format_protocol_table(doc))
        return 0
    if args.command == "bench" and args.bench == "render":
        from posecast.client.viewer.bench import bench_render, format_render_table

        width, height = args.size
        result = bench_render(args.avatars, width, height, args.frames, out=args.out)
        print(json.dumps(result) if args.json else format_render_table(result))
        return 0
    if args.command == "bench" and args.bench == "server":
        from posecast.client.bench_server import bench_server, format_server_table

        result = bench_server(args.counts, args.seconds,
                              helper=None if args.helper else False)
        print(json.dumps(result) if args.json else format_server_table(result))
        return 0
    if args.command == "bench" and args.bench == "soak":
        from posecast.client.bench_soak import bench_soak, format_soak_table, plot_soak

        doc = bench_soak(args.minutes, args.players, args.spectators, args.interval)
        if args.plot is not None:
            plot_soak(doc, args.plot)
        print(json.dumps(doc) if args.json else format_soak_table(doc))
        return 0
    if args.command == "bench" and args.bench == "prediction":
        from posecast.client.bench_prediction import (
            bench_prediction,
            format_prediction_table,
            main_files,
        )

        files = main_files(args.files)
        if files is None:
            return 2
        doc = bench_prediction(files)
        print(json.dumps(doc) if args.json else format_prediction_table(doc))
        return 0
    if args.command == "bench" and args.bench == "hostile":
        from posecast.client.bench_hostile import bench_hostile, format_hostile_table

        doc = bench_hostile(args.attack, args.seconds)
        print(json.dumps(doc) if args.json else format_hostile_table(doc))
        return 0
    if args.command == "bench" and args.bench == "fanout":
        return _bench_fanout(args)
    if args.command == "bench" and args.bench == "startup":
        from posecast.client.bench_startup import bench_startup, format_startup_table

        doc = bench_startup(args.runs)
        print(json.dumps(doc) if args.json else format_startup_table(doc))
        return 0
    return 2


def _bench_fanout(args: argparse.Namespace) -> int:
    from posecast.client.bench_fanout import bench_fanout, format_fanout_table, format_step
    from posecast.client.redis_process import RedisMissingError

    try:  # a line per step as it ends: a whole run takes minutes
        doc = bench_fanout(args.processes, args.players, args.start, args.seconds,
                           args.budget_ms, args.max, args.repeat,
                           progress=lambda step: print(format_step(step), file=sys.stderr,
                                                       flush=True))
    except RedisMissingError as err:
        return _fail("bench fanout", err)
    except RuntimeError as err:  # spectators that could not join, a server that died
        return _fail("bench fanout", err)
    print(json.dumps(doc) if args.json else format_fanout_table(doc))
    return 0


def _view(args: argparse.Namespace) -> int:
    from posecast.client.connection import SessionError
    from posecast.client.console import view_summary
    from posecast.client.viewer import GLUnavailableError, NoDisplayError

    if (status := _cafile_without_tls("view", args)) is not None:
        return status
    watched: list[Spectator] = []
    try:
        stats, signum = asyncio.run(_view_live(args, watched))
    except (NoDisplayError, GLUnavailableError) as err:
        return _fail("view", err)
    except SessionError as err:
        return _fail("view", _session_words(err))
    spectator = watched[0].stats if watched else None
    if args.json:
        print(json.dumps(stats.as_json() if stats is not None else {}))
    else:
        for line in view_summary(stats, spectator, args.out if args.headless else None):
            print(line)
    return 128 + signum if signum else 0


async def _view_live(args: argparse.Namespace, watched: list[Spectator]
                     ) -> tuple[ViewerStats | None, int]:
    """The viewer, with a word on stderr about where it joined and whom it waits for,
    until its frames are done, its window closes or a signal stops it."""
    from posecast.client.connection import Reconnect, stop_task
    from posecast.client.console import StatusLine, report_spectator, run_until_signal
    from posecast.client.viewer import Mode, ViewMode, run_headless_viewer, run_window_viewer

    status = StatusLine("posecast view")
    stop = asyncio.Event()
    reporters: list[asyncio.Task[None]] = []

    def on_spectator(spectator: Spectator) -> None:
        if args.reconnect:  # a word on stderr when the session is lost and when it is back
            spectator.reconnect = Reconnect(say=status.say)
        watched.append(spectator)
        reporters.append(asyncio.create_task(report_spectator(spectator, status)))

    width, height = args.size
    mode, view = Mode(args.mode), ViewMode(args.view)
    run = (run_headless_viewer(args.server, args.room, args.frames or 100, args.out, width,
                               height, interval_ms=1000.0 / args.fps, mode=mode, view=view,
                               max_rate_hz=args.max_rate, token=args.token,
                               cafile=args.cafile, stop=stop,
                               on_spectator=on_spectator, marker=args.marker)
           if args.headless else
           run_window_viewer(args.server, args.room, width, height, fps=args.fps, mode=mode,
                             view=view, max_rate_hz=args.max_rate, frames=args.frames,
                             screenshot=args.screenshot, token=args.token,
                             cafile=args.cafile, stop=stop,
                             on_spectator=on_spectator, marker=args.marker))
    try:
        return await run_until_signal(run, stop)
    finally:
        for task in reporters:
            await stop_task(task)
        status.clear()


def _fail(command: str, message: object) -> int:
    print(f"posecast {command}: {message}", file=sys.stderr)
    return 1


def _session_words(err: SessionError) -> str:
    """'cannot reach URL: why' when no websocket opened; else the session's own line
    (the server's reason when it refused the join)."""
    return str(err) if err.reached else f"cannot reach {err.url}: {err.reason}"


def _join_tokens(secret_file: Path | None) -> JoinTokens | None:
    """Tokens with the secret of --secret-file, else of $POSECAST_SECRET, else None;
    SecretError (one line) if that secret is unreadable or too short."""
    from posecast.server.auth import JoinTokens, load_secret

    secret = load_secret(secret_file, os.environ)
    return JoinTokens(secret) if secret is not None else None


def _token(args: argparse.Namespace) -> int:
    from posecast.server.auth import SECRET_ENV, SecretError

    try:
        tokens = _join_tokens(args.secret_file)
    except SecretError as err:
        return _usage("token", str(err))
    if tokens is None:
        return _usage("token", f"needs the server's secret: --secret-file FILE, or "
                      f"${SECRET_ENV}")
    try:
        print(tokens.mint(args.room, args.role, args.ttl, args.name))
    except ValueError as err:
        return _usage("token", str(err))
    return 0


def _usage(command: str, message: str) -> int:
    """A bad command line found after parsing: one line, as argparse's, status 2."""
    print(f"posecast {command}: {message} (see posecast {command} --help)", file=sys.stderr)
    return 2


def _serve(args: argparse.Namespace) -> int:
    from posecast.server.app import Session, install_fast_loop, run_server
    from posecast.server.auth import SecretError

    try:
        tokens = _join_tokens(args.secret_file)
    except SecretError as err:  # $POSECAST_SECRET too short (a file is checked on parsing)
        return _usage("serve", str(err))

    try:
        limits = ServerLimits().with_text(args.limit)
    except ValueError as err:  # limits that do not go together (see _limit)
        print(f"posecast serve: {err} (--limit, or [limits] in --config; see posecast serve "
              "--help)", file=sys.stderr)
        raise SystemExit(2) from None  # a usage error, as argparse ends one
    try:  # before the solver warms up: a bad certificate is told at once
        tls = _server_tls(args)
    except ValueError as err:
        print(f"posecast serve: {err} (see posecast serve --help)", file=sys.stderr)
        return 2
    if args.public_url is not None and args.redis is None:
        return _usage("serve", "--public-url is for --redis: where other processes send "
                               "this one's players")
    install_fast_loop()
    cluster = None
    if args.redis is not None:
        from posecast.server.cluster import Cluster
        cluster = Cluster(args.redis, args.public_url or "")
    session = Session(tokens=tokens, solver=args.solver, busy=args.busy_poll,
                      helper=None if args.helper else False,
                      limits=limits, cluster=cluster,
                      trusted_proxies=args.trusted_proxies or ())
    from posecast.server.cluster import ClusterError
    try:
        asyncio.run(run_server(args.host, args.port, session, handle_signals=True,
                               tls=tls, origins=args.origins))
    except ClusterError as err:
        return _fail("serve", f"{err} (is redis-server running there?)")
    except OSError as err:
        return _fail("serve", f"cannot listen on {args.host}:{args.port}: {err.strerror}")
    print(json.dumps(session.metrics.as_json()))
    return 0


def _server_tls(args: argparse.Namespace) -> ssl.SSLContext | None:
    """serve's TLS context from --certfile and --keyfile (None: neither); ValueError
    in one line (server.tls.TLSConfigError) if they cannot serve."""
    from posecast.server.tls import server_tls_context

    if args.certfile is None and args.keyfile is None:
        return None
    if args.certfile is None or args.keyfile is None:
        given, missing = (("--certfile", "--keyfile") if args.keyfile is None
                          else ("--keyfile", "--certfile"))
        raise ValueError(f"{given} needs {missing} too")
    return server_tls_context(args.certfile, args.keyfile)


def _cafile_without_tls(command: str, args: argparse.Namespace) -> int | None:
    """Status 2 if --cafile came with a ws:// URL, where it would silently do nothing."""
    if args.cafile is None or urlsplit(args.server).scheme == "wss":
        return None
    print(f"posecast {command}: --cafile is for wss:// servers, but --server is "
          f"{args.server!r} (see posecast {command} --help)", file=sys.stderr)
    return 2


def _device_set(text: str) -> str:
    """A tracker set as given (checked now; ``run_demo`` reads it)."""
    arg.devices(text)
    return text


def _devices_or_roles_file(text: str) -> tuple[str, ...] | Path:
    """``play --devices``: a tracker set, or (as before 2026-11) a roles TOML file."""
    if text.lower().endswith(".toml"):
        return arg.existing_file(text)
    return arg.devices(text)


def _play(args: argparse.Namespace) -> int:
    from posecast.client.connection import SessionError
    from posecast.client.console import player_summary
    from posecast.client.player import Player
    from posecast.client.sources import open_source
    from posecast.client.sources.base import SourceError
    from posecast.solver.readers.errors import FormatError

    if (status := _cafile_without_tls("play", args)) is not None:
        return status
    if isinstance(args.devices, Path):  # the old spelling of --roles FILE.toml
        print(f"posecast play: --devices {args.devices} is a roles file: say --roles "
              f"{args.devices} (--devices now names a tracker set)", file=sys.stderr)
        args.roles, args.devices = args.devices, None
    try:
        source = open_source(args.source, args.roles, loop=args.loop, offset=args.offset)
    except (SourceError, FormatError) as err:
        return _fail("play", err)
    if args.devices is not None or args.dropouts is not None:
        from posecast.client.sources.tracker_set import TrackerSetSource
        source = TrackerSetSource(source, args.devices, args.dropouts)
    recording = None
    if args.record is not None:
        from posecast.client.sources.recording_source import RecordingSource
        try:
            source = recording = RecordingSource(source, args.record)
        except OSError as err:
            source.close()
            return _fail("play", f"--record {args.record}: {err.strerror or err}")
    delay = args.calibrate_in if args.calibrate_in is not None else (
        3.0 if args.source == "openvr" else 0.0)
    try:
        player = Player(args.server, args.room, args.name, source, token=args.token,
                        cafile=args.cafile)
        signum = asyncio.run(_play_live(player, delay, args.seconds, args.source,
                                        args.reconnect))
    except SessionError as err:
        return _fail("play", _session_words(err))
    finally:
        source.close()
    print(player_summary(player.stats))
    if recording is not None:
        print(f"kept {recording.frames} frames in {recording.path}"
              + (f" ({recording.skipped} left out: a device of the first frame was "
                 "missing)" if recording.skipped else ""))
    return 128 + signum if signum else 0


async def _play_live(player: Player, delay: float, seconds: float | None,
                     source: str, reconnect: bool = True) -> int:
    """Stream with a word on stderr about where it joined and a progress line, until
    the source or the time ends or a signal stops it (its number is returned)."""
    from posecast.client.connection import Reconnect, stop_task
    from posecast.client.console import StatusLine, report_player, run_until_signal

    status = StatusLine("posecast play")
    if reconnect:  # a word on stderr when the session is lost and when it is back
        player.reconnect = Reconnect(say=status.say)
    stop = asyncio.Event()
    reporter = asyncio.create_task(report_player(player, status, source))
    try:
        _, signum = await run_until_signal(_calibrate_and_stream(player, delay, seconds, stop),
                                           stop)
    finally:
        await stop_task(reporter)
        status.clear()
    return signum


async def _calibrate_and_stream(player: Player, delay: float, seconds: float | None,
                                stop: asyncio.Event) -> None:
    """Count the player into the T-pose, then stream; Enter on a terminal recalibrates."""
    for left in range(math.ceil(delay), 0, -1):
        print(f"stand in a T-pose, arms out sideways: calibrating in {left} s", flush=True)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), min(1.0, delay - (left - 1)))
        if stop.is_set():
            return
    loop = asyncio.get_running_loop()
    interactive = sys.stdin.isatty()
    if interactive:
        def recalibrate() -> None:
            sys.stdin.readline()
            print("recalibrating: hold the T-pose", flush=True)
            player.recalibrate()
        loop.add_reader(sys.stdin.fileno(), recalibrate)
    try:
        await player.run(seconds, stop)
    finally:
        if interactive:
            loop.remove_reader(sys.stdin.fileno())


def _demo(args: argparse.Namespace) -> int:
    from posecast.client.demo import DemoError, run_demo
    from posecast.client.latency import format_latency_table
    from posecast.client.redis_process import RedisMissingError

    try:
        limits = ServerLimits().with_text(args.limit)
    except ValueError as err:  # limits that do not go together (see _limit)
        print(f"posecast demo: {err} (--limit)", file=sys.stderr)
        raise SystemExit(2) from None
    try:
        result = run_demo(args.players, args.spectators, args.seconds, solver=args.solver,
                          render=args.render, render_mode=args.render_mode,
                          busy=None if args.busy_poll else False,
                          helper=None if args.helper else False, network=args.network,
                          limits=limits, servers=args.servers, devices=args.devices,
                          dropouts=args.dropouts)
    except RedisMissingError as err:
        print(f"posecast demo: --servers {args.servers}: {err}", file=sys.stderr)
        return 1
    except DemoError as err:  # e.g. a link whose stalls make the server refuse frames
        print(f"posecast demo: {err}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(result.as_json()))
    else:
        print(result.format_counts())
        print(format_latency_table(result.latency.summary(), result.latency.counts()))
        print(result.format_display_error())
    return 0


if __name__ == "__main__":
    sys.exit(main())
