"""The `posecast` command line's parser: every command, option and help text, and the
argument types only it uses."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from posecast import __version__
from posecast.client.cli import arguments as arg

# constants only: the parser is built before any command's libraries load, so that
# --version and --help answer at once (numpy, numba and pydantic take ~1 s)
from posecast.protocol.sizes import ROOM_NAME_RULE
from posecast.server.limits import ServerLimits
from posecast.solver.choices import (
    DEFAULT_SOLVER,
    PREDICTORS,
    SOLVERS,
    VIVE_DEVICES,  # view --marker's joints
)
from posecast.solver.tracking.devices import DEFAULT_SET

if TYPE_CHECKING:

    pass


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


def _positive_list(text: str, kind: type[float]) -> list[float]:
    """Comma-separated positive finite numbers of ``kind`` (int or float)."""
    try:
        values = [kind(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected numbers separated by commas, got {text!r}") from None
    if not values or not all(0 < v < float("inf") for v in values):
        raise argparse.ArgumentTypeError(f"expected positive numbers, got {text!r}")
    return values


def _positive_ints(text: str) -> list[int]:
    return [int(v) for v in _positive_list(text, int)]


def _positive_floats(text: str) -> list[float]:
    return _positive_list(text, float)


def _device_set(text: str) -> str:
    """A tracker set as given (checked now; ``run_demo`` reads it)."""
    arg.devices(text)
    return text


def _devices_or_roles_file(text: str) -> tuple[str, ...] | Path:
    """``play --devices``: a tracker set, or (as before 2026-11) a roles TOML file."""
    if text.lower().endswith(".toml"):
        return arg.existing_file(text)
    return arg.devices(text)


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
    hmd = pl.add_mutually_exclusive_group()
    hmd.add_argument("--hmd", action="store_true",
                     help="see the room in your headset (SteamVR): your own body, solved "
                          "here from the compositor's poses, in first person and in a "
                          "mirror, and everyone else in the room")
    hmd.add_argument("--hmd-out", type=arg.out_dir, default=None, metavar="DIR",
                     help="without SteamVR: what both eyes would see, side by side, as PNG "
                          "files in DIR (made if missing); the source's head stands in "
                          "for the headset")
    pl.add_argument("--hmd-frames", type=arg.positive_int, default=None, metavar="N",
                    help="with --hmd or --hmd-out: stop after N headset frames")
    pl.add_argument("--hmd-scale", type=arg.positive_float, default=1.0, metavar="F",
                    help="with --hmd-out: each eye at F times a Vive's recommended "
                         "1512x1680 (default 1)")
    pl.add_argument("--mirror", type=arg.non_negative_float, default=2.0, metavar="M",
                    help="with --hmd or --hmd-out: a mirror M metres before where you "
                         "calibrate (default 2; 0: none)")

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
    dm.add_argument("--browser", nargs="?", const="interpolate", default=None,
                    choices=("interpolate", "zero-buffer", "predict"), metavar="MODE",
                    help="one more spectator: the browser page in headless Chromium, in "
                         "this playout mode (interpolate, zero-buffer or predict; default "
                         "the page's, interpolate); its display error is measured beside "
                         "the desktop viewer's")
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
    bpg = bsub.add_parser("page", help="ms a frame the browser page's playout takes to "
                          "sample and pose the avatars, per mode (headless Chromium)")
    bpg.add_argument("--avatars", type=arg.positive_int, default=16,
                     help="players walking in the room, each drawn")
    bpg.add_argument("--frames", type=arg.positive_int, default=20,
                     help="frames a mode's turn is the median of (Chromium draws a few a "
                          "second on the CPU)")
    bpg.add_argument("--turns", type=arg.positive_int, default=3,
                     help="alternated turns of the three modes")
    bpg.add_argument("--json", action="store_true", help="print one JSON document")
    bhs = bsub.add_parser("headset", help="ms from a headset frame's poses to its submission "
                          "(play --hmd's frame loop) at a Vive's eye size and fractions")
    bhs.add_argument("--scales", type=_positive_floats, default=[1.0, 0.5], metavar="F,...",
                     help="eye sizes as fractions of a Vive's 1512x1680 (default: 1,0.5)")
    bhs.add_argument("--frames", type=arg.positive_int, default=120,
                     help="frames measured at each size (after 10 to warm up)")
    bhs.add_argument("--others", type=arg.count, default=3,
                     help="other players in the room, drawn in every frame")
    bhs.add_argument("--json", action="store_true", help="print one JSON document")
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
