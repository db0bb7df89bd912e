"""`kinfly-ground`: the ground station's command line.

  kinfly-ground run     live: LCM keyframes in, signed corrections out, viewer, MAVLink
  kinfly-ground replay  offline: every keyframe of a recorded flight log, with progress

Both end with the outputs in --out (docs/ground.md). Exit status: 0 done, 1 failed while running
(an output could not be written), 2 bad command line or input refused at start."""
from __future__ import annotations

import argparse
import dataclasses
import gc
import math
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from kinfly import ground_status_t

from . import __version__
from ._native import (DEFAULT_PEER_PORT, MAX_VEHICLE_ID, Channel, KeyFileError, PeerLink, Signer,
                      channel_name, ground_subscriptions, load_key_file, parse_channel)
from .command import (KINDS, RESEND_PERIOD_S, AnswerWatch, CommandError, read_waypoints, send,
                      send_until_answered)
from .flight import ACCEPTED, answer, mode_name
from .command import build as build_command
from .export import export, format_ms, print_summary
from .mavlink import MavlinkBridge, MavlinkError, load_signing_key
from .outputs import OutputError, check_writable, memory, read_tum
from .station import Station, StationParams
from .transport import Transport
from .vehicle import percentile
from .viewer import Viewer, ViewerError

DEFAULT_LCM_URL = "udpm://239.255.76.67:7667?ttl=1"  # LCM's default group; ttl 1: one hop (Wi-Fi)
# With unicast peers, multicast stays on this machine (for lcm-logger): the drones' traffic would
# otherwise cross the Wi-Fi twice.
PEER_LCM_URL = "udpm://239.255.76.67:7667?ttl=0"
# The unicast link's counters in summary.json (PeerCounters, firmware/link peer.h).
PEER_COUNTERS = ("sent", "send_failed", "too_large", "received", "foreign", "malformed",
                 "unexpected_channel")
# The ground_status_t at 10 Hz, as the drone's status, and at once (within a turn of the loop,
# 20 ms at most) when a keyframe is done: a drone in lockstep (source.lockstep) waits for that
# word before its next frame's pose, and waited 50 ms a keyframe on average for the next tick.
STATUS_PERIOD_S = 0.1
LINK_TIMEOUT_S = 1.0       # the drone is STALE after this long unheard (as kinfly-fw's default)
PROGRESS_PERIOD_S = 2.0
DRAIN_TIMEOUT_S = 30.0     # at exit, the longest wait for queued keyframes to be fused
# The kernel's receive buffer of the LCM socket holds what arrives while LCM's receive thread
# cannot run (a loaded laptop). A 50 KB keyframe costs about 90 KB of buffer as some 40 chunks
# of a 1500-byte MTU: 4 MB holds two seconds of keyframes at 20 Hz.
RECV_BUFFER_BYTES = 4 << 20
RMEM_MAX = Path("/proc/sys/net/core/rmem_max")
# Messages LCM queues for this process's handler thread, per subscription, before it drops the
# newest: keyframe chunks (some 40 of 1.4 KB a keyframe; 4096 are about 100 keyframes, 6 MB)
# apart from the small messages, which arrive at up to 200 Hz (odometry, ground truth, status),
# so a burst of those never pushes a chunk out. A chunk dropped here would count as lost on the
# link and raise the drone's redundancy.
KEYFRAME_QUEUE_MESSAGES = 4096
SMALL_QUEUE_MESSAGES = 2000


class UsageError(Exception):
    """Bad input found before the station starts (exit status 2)."""


def log(message: str) -> None:
    print(f"kinfly-ground: {message}", file=sys.stderr, flush=True)


# --- arguments -------------------------------------------------------------------------------

def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("out/ground"),
                   help="output directory: mesh.ply, trajectory_onboard.tum, "
                        "trajectory_corrected.tum, session.rrd, summary.json (default out/ground)")
    p.add_argument("--vehicle", type=int, metavar="ID",
                   help=f"the vehicle id to serve, 0..{MAX_VEHICLE_ID} (default: every vehicle, "
                        "one map each, outputs in OUT/vehicle_<id>/)")
    p.add_argument("--save", type=Path, metavar="FILE.rrd",
                   help="where to record the rerun session (default OUT/session.rrd)")
    p.add_argument("--no-record", action="store_true", help="record no .rrd")
    p.add_argument("--viewer", action="store_true", help="spawn the rerun viewer")
    p.add_argument("--ground-truth", type=Path, metavar="FILE.tum",
                   help="ground truth (TUM format, capture clock) to evaluate against; otherwise "
                        "what arrives on KINFLY_<id>_GROUND_TRUTH, if anything")
    d = StationParams()
    p.add_argument("--voxel-size", type=float, default=d.voxel_size_m, metavar="M",
                   help=f"voxel edge of the full-resolution map [m] (default {d.voxel_size_m})")
    p.add_argument("--threads", type=int, default=d.threads,
                   help=f"fusion threads (default {d.threads})")
    p.add_argument("--model-level", type=int, default=d.model_level, choices=(0, 1),
                   help="resolution of the map's raycast that keyframes are registered against: "
                        "0 every pixel, 1 half (a quarter of the rays, for a station short of "
                        "time; less accurate, docs/ground.md; the map is still fused at full "
                        f"resolution) (default {d.model_level})")
    p.add_argument("--reset-translation", type=float, default=d.reset_translation_m, metavar="M",
                   help="a correction moving the pose further than this increments the reset "
                        f"counter [m] (default {d.reset_translation_m})")
    p.add_argument("--reset-rotation", type=float, default=math.degrees(d.reset_rotation_rad),
                   metavar="DEG", help="the same for rotation [degrees] "
                   f"(default {math.degrees(d.reset_rotation_rad):g})")
    p.add_argument("--submap-distance", type=float, default=d.submaps.max_distance_m,
                   metavar="M", help="a submap closes after the camera travelled this far in it, "
                   "and is checked for loops with the earlier ones near it, 3 for a flight "
                   "through several rooms [m] (default: never; one map, a new submap only where "
                   "keyframes stop registering)")
    p.add_argument("--submap-duration", type=float, default=d.submaps.max_duration_s,
                   metavar="S", help="... or after this long in capture time, 30 with "
                   "--submap-distance 3 [s] (default: never)")


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(
        prog="kinfly-ground",
        description="kinfly ground station: fuses a drone's depth keyframes at full resolution, "
                    "refines each keyframe's pose against the map and sends it back signed.")
    top.add_argument("--version", action="version", version=f"kinfly-ground {__version__}")
    sub = top.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="serve drones live over LCM",
                         description="Listen for keyframes over LCM, fuse them, publish signed "
                                     "pose corrections and the ground's status. Ctrl-C (SIGINT) "
                                     "or SIGTERM: finish the queued keyframes, write the outputs "
                                     "and exit; SIGUSR1: write the outputs now and go on.")
    _add_common(run)
    run.add_argument("--lcm-url", default=os.environ.get("LCM_DEFAULT_URL"),
                     help=f"LCM provider URL (default $LCM_DEFAULT_URL, else {DEFAULT_LCM_URL}, "
                          f"with --peer {PEER_LCM_URL}: it must keep messages on this machine)")
    run.add_argument("--peer", metavar="ADDRESS:PORT[,ADDRESS:PORT]",
                     help="drones to talk to by UDP unicast besides LCM, for Wi-Fi where "
                          "multicast is slow and lossy (docs/wire.md, \"Unicast on Wi-Fi\"): "
                          "their IPv4 addresses, and PORT their link.peer_port")
    run.add_argument("--peer-port", type=int, default=DEFAULT_PEER_PORT, metavar="PORT",
                     help="UDP port the drones' unicast comes to: their link.peers "
                          f"(default {DEFAULT_PEER_PORT})")
    run.add_argument("--key", type=Path, metavar="FILE",
                     help="the vehicle's 32-byte signing key (kinfly-keygen; with --vehicle)")
    run.add_argument("--key-dir", type=Path, metavar="DIR",
                     help="keys of several vehicles, DIR/<id>.key (without --vehicle)")
    run.add_argument("--queue", type=int, default=StationParams().queue_keyframes,
                     help="keyframes that may wait to be fused; when full the oldest is dropped "
                          f"(default {StationParams().queue_keyframes})")
    run.add_argument("--duration", type=float, metavar="S",
                     help="stop after S seconds (default: until SIGINT/SIGTERM)")
    run.add_argument("--mavlink", metavar="URL",
                     help="autopilot link: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or a "
                          "serial device (with --vehicle)")
    run.add_argument("--mavlink-forward", choices=("vision", "odometry"),
                     help="forward corrected poses as VISION_POSITION_ESTIMATE or ODOMETRY")
    run.add_argument("--mavlink-rate", type=float, default=30.0, metavar="HZ",
                     help="most poses forwarded per second (default 30)")
    run.add_argument("--mavlink-key", type=Path, metavar="FILE",
                     help="MAVLink 2 signing secret (32 bytes): sign what is sent, refuse "
                          "unsigned telemetry")
    run.add_argument("--mavlink-baud", type=int, default=57600, help="serial baud rate")

    command = sub.add_parser(
        "command", help="send a signed command to a drone's flight stack",
        description="Send one signed command (flight_command_t in signed_t, the vehicle's key) "
                    "to a drone's flight stack on KINFLY_<vid>_COMMAND, several copies of it "
                    "(the drone takes the first). Positions are in the flight stack's world: "
                    "gravity-aligned, z down, so heights are negative z (docs/flight.md). It "
                    "then waits for the drone's answer (its flight_status_t on "
                    "KINFLY_<vid>_FLIGHT), sending the command again, signed anew, every "
                    f"{RESEND_PERIOD_S:g} s while unanswered (the drone acts on it once), "
                    "and prints it. Exit status: 0 accepted, 1 refused or "
                    "no answer within --wait, 2 a bad command line.")
    command.add_argument("action", choices=sorted(KINDS), help="what the drone is to do")
    command.add_argument("values", nargs="*", metavar="VALUE",
                         help="takeoff: HEIGHT_M; goto: X Y Z; mission: WAYPOINT_FILE (a line "
                              "`x y z` per waypoint, # comments)")
    command.add_argument("--vehicle", type=int, required=True, help="the drone's vehicle id")
    command.add_argument("--key", type=Path, required=True, metavar="FILE",
                         help="the vehicle's 32-byte signing key (kinfly-keygen)")
    command.add_argument("--yaw", type=float, default=None, metavar="DEG",
                         help="goto: the heading to turn to on the way, degrees about world z "
                              "(down) from world x towards world y, in [-360, 360] (default: "
                              "keep the drone's); a goto to where the drone holds turns it in "
                              "place")
    command.add_argument("--max-speed", type=float, default=0.0, metavar="M/S",
                         help="mission: its peak speed (default: the drone's "
                              "flight.max_speed_m_s)")
    command.add_argument("--copies", type=int, default=3,
                         help="copies sent each time, 20 ms apart (default 3)")
    command.add_argument("--wait", type=float, default=5.0, metavar="S",
                         help="how long to wait for the drone's answer (default 5; 0: do not "
                              "wait, exit 0 once sent)")
    command.add_argument("--lcm-url", default=os.environ.get("LCM_DEFAULT_URL"),
                         help=f"LCM provider URL (default $LCM_DEFAULT_URL, else "
                              f"{DEFAULT_LCM_URL})")

    replay = sub.add_parser("replay", help="fuse a recorded flight log offline",
                            description="Fuse every keyframe of an LCM flight log (recorded "
                                        "with lcm-logger during a flight or `make demo`), "
                                        "with progress; nothing is sent.")
    replay.add_argument("log", type=Path, metavar="LOG", help="LCM event log")
    _add_common(replay)
    return top


def _params(args: argparse.Namespace, **extra: Any) -> StationParams:
    try:
        submaps = dataclasses.replace(StationParams().submaps,
                                      max_distance_m=args.submap_distance,
                                      max_duration_s=args.submap_duration)
    except ValueError:
        raise UsageError(f"--submap-distance {args.submap_distance:g} and --submap-duration "
                         f"{args.submap_duration:g} must be positive") from None
    params = StationParams(voxel_size_m=args.voxel_size, threads=args.threads,
                           model_level=args.model_level,
                           reset_translation_m=args.reset_translation,
                           reset_rotation_rad=math.radians(args.reset_rotation), submaps=submaps,
                           **extra)
    if why := params.validate():
        raise UsageError(why)
    return params


def _check_vehicle(args: argparse.Namespace) -> None:
    if args.vehicle is not None and not 0 <= args.vehicle <= MAX_VEHICLE_ID:
        raise UsageError(f"--vehicle {args.vehicle} outside [0, {MAX_VEHICLE_ID}]")


def _signers(args: argparse.Namespace) -> dict[int, Signer]:
    if args.key and args.key_dir:
        raise UsageError("give --key (one vehicle) or --key-dir (several), not both")
    if args.key:
        if args.vehicle is None:
            raise UsageError("--key needs --vehicle (use --key-dir DIR/<id>.key for several)")
        return {args.vehicle: Signer(load_key_file(args.key), args.vehicle)}
    if not args.key_dir:
        log("no --key: keyframes are mapped but no corrections are sent")
        return {}
    if not args.key_dir.is_dir():
        raise UsageError(f"--key-dir {args.key_dir} is not a directory")
    signers = {}
    for path in sorted(args.key_dir.glob("*.key")):
        if path.stem.isdigit() and 0 <= int(path.stem) <= MAX_VEHICLE_ID:
            vid = int(path.stem)
            if args.vehicle is None or vid == args.vehicle:
                signers[vid] = Signer(load_key_file(path), vid)
    if not signers:
        raise UsageError(f"--key-dir {args.key_dir} holds no <vehicle id>.key file")
    return signers


def _rrd_path(args: argparse.Namespace) -> Path | None:
    return None if args.no_record else (args.save or args.out / "session.rrd")


def _viewer(args: argparse.Namespace) -> Viewer:
    return Viewer(spawn=args.viewer, save_path=_rrd_path(args),
                  recording_name=f"kinfly-ground {time.strftime('%Y-%m-%d %H:%M:%S')}")


# --- run -------------------------------------------------------------------------------------

def _mavlink(args: argparse.Namespace):
    if not args.mavlink:
        if args.mavlink_forward or args.mavlink_key:
            raise UsageError("--mavlink-forward and --mavlink-key need --mavlink URL")
        return None
    if args.vehicle is None:
        raise UsageError("--mavlink needs --vehicle: one autopilot link per vehicle")
    key = load_signing_key(args.mavlink_key) if args.mavlink_key else None
    try:
        return MavlinkBridge(args.mavlink, forward=args.mavlink_forward,
                             rate_hz=args.mavlink_rate, signing_key=key, baud=args.mavlink_baud)
    except ValueError as error:
        raise UsageError(f"--mavlink: {error}") from error


def with_receive_buffer(url: str) -> str:
    """URL with LCM's recv_buf_size option, unless it is not UDP multicast or sets its own."""
    if not url.startswith("udpm://") or "recv_buf_size=" in url:
        return url
    return f"{url}{'&' if '?' in url else '?'}recv_buf_size={RECV_BUFFER_BYTES}"


def check_receive_buffer(url: str) -> None:
    """Says so at start when the kernel will give LCM less receive buffer than asked for."""
    match = re.search(r"recv_buf_size=(\d+)", url)
    if not url.startswith("udpm://") or match is None:
        return
    try:
        cap = int(RMEM_MAX.read_text())
    except (OSError, ValueError):
        return
    wanted = int(match.group(1))
    if cap < wanted:
        log(f"warning: the kernel caps socket receive buffers at {cap // 1024} KB "
            f"(net.core.rmem_max), below the {wanted // 1024} KB asked for to hold a burst of "
            "keyframes while this machine is busy; raise it with `sudo sysctl -w "
            f"net.core.rmem_max={wanted}` (add `net.core.rmem_max = {wanted}` to a file in "
            "/etc/sysctl.d/ to keep it)")


def lcm_url_for(given: str | None, peers: bool) -> str:
    """The LCM URL to use; UsageError for one that sends multicast off the machine besides the
    unicast peers."""
    if given is None:
        return PEER_LCM_URL if peers else DEFAULT_LCM_URL
    ttl = re.search(r"[?&]ttl=(\d+)", given)
    if peers and given.startswith("udpm://") and ttl is not None and int(ttl.group(1)) > 0:
        raise UsageError(f"--lcm-url {given} sends multicast off this machine (ttl="
                         f"{ttl.group(1)}); with --peer it must stay on it (ttl=0), else every "
                         "message crosses the Wi-Fi twice")
    return given


def _peers(args: argparse.Namespace) -> PeerLink | None:
    if args.peer is None:
        return None
    try:
        return PeerLink(args.peer, args.peer_port, args.vehicle)
    except ValueError as error:
        raise UsageError(f"--peer {args.peer} --peer-port {args.peer_port}: {error}") from error


def run(args: argparse.Namespace) -> int:
    import lcm

    _check_vehicle(args)
    params = _params(args, queue_keyframes=args.queue)
    signers = _signers(args)
    truth = read_tum(args.ground_truth) if args.ground_truth else None
    check_writable(args.out)
    url = with_receive_buffer(lcm_url_for(args.lcm_url, args.peer is not None))
    peers = _peers(args)
    bridge = _mavlink(args)
    check_receive_buffer(url)
    try:
        lc = lcm.LCM(url)
    except (OSError, RuntimeError) as error:
        raise UsageError(f"cannot open LCM at {url}: {error} (multicast needs a route: "
                         "see docs/ground.md)") from error
    transport = Transport(lc, peers)
    viewer = _viewer(args)
    started = time.monotonic()
    station = Station(params, viewer, vehicle_id=args.vehicle, signers=signers,
                      publish=transport.publish, forward=bridge.send_pose if bridge else None,
                      log=log)
    keyframes, others = ground_subscriptions(args.vehicle)
    lc.subscribe(keyframes, station.on_message).set_queue_capacity(KEYFRAME_QUEUE_MESSAGES)
    lc.subscribe(others, station.on_message).set_queue_capacity(SMALL_QUEUE_MESSAGES)

    stop = threading.Event()
    export_now = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGUSR1, lambda *_: export_now.set())
    # Only now, with the viewer, the recording and the outputs set up: whoever waits for this
    # line may send keyframes at once.
    unicast = (f" and UDP port {peers.listen_port} (unicast with {args.peer})"
               if peers is not None else "")
    log(f"listening on {url}{unicast} for "
        f"{'every vehicle' if args.vehicle is None else f'vehicle {args.vehicle}'}; "
        f"outputs in {args.out}")

    def snapshot_outputs() -> None:
        try:
            export(station, args.out, "run", started, truth, {})
            log(f"outputs written to {args.out} (on request)")
        except OutputError as error:
            log(f"export on request failed: {error}")

    failure = None
    try:
        _serve(transport, station, bridge, args, started, stop, export_now, snapshot_outputs)
    except Exception as error:  # whatever it was, what was mapped so far is still written
        failure = error
        log(f"stopping on an error: {type(error).__name__}: {error}")
    log("stopping: fusing what is queued, then writing the outputs")
    if not station.drain(DRAIN_TIMEOUT_S):
        log(f"{station.queue_length()} keyframes still queued after {DRAIN_TIMEOUT_S:.0f} s: "
            "left out")
    station.stop()
    _publish_status(transport, station, ground_status_t.RUN_FINAL)
    extra: dict[str, Any] = {}
    if peers is not None:
        extra["unicast"] = {"peers": args.peer, "listen_port": peers.listen_port,
                            **{name: getattr(peers.counters, name) for name in PEER_COUNTERS}}
    if bridge is not None:
        extra["mavlink"] = {"url": args.mavlink, **dataclasses.asdict(bridge.counters),
                            "autopilot": dataclasses.asdict(bridge.state)}
        bridge.close()
    rc = _finish(station, viewer, args, "run", started, truth, extra)
    return 1 if failure is not None else rc


def _serve(transport: Transport, station: Station, bridge: Any, args: argparse.Namespace,
           started: float, stop: threading.Event, export_now: threading.Event,
           snapshot_outputs: Callable[[], None]) -> None:
    """The LCM thread's loop: messages, status at 10 Hz and when a keyframe is done, MAVLink,
    progress, until told to stop."""
    next_status = next_progress = time.monotonic()
    reported_done: dict[int, int] = {}  # each vehicle's last keyframe done, as last published
    while not stop.is_set():
        try:
            transport.handle(20)
        except OSError:
            # Our signals interrupt the wait (EINTR); anything else is real.
            if not (stop.is_set() or export_now.is_set()):
                raise
        now = time.monotonic()
        station.uplink.send_copies(now)
        if args.duration is not None and now - started >= args.duration:
            break
        if export_now.is_set():
            export_now.clear()
            station.run_in_worker(snapshot_outputs)
        if bridge is not None and bridge.poll() and args.vehicle in station.vehicles:
            station.vehicles[args.vehicle].view.telemetry(bridge.state.last_heard_utime,
                                                          bridge.state.as_metrics())
        done = {vid: state.last_done_keyframe_id for vid, state in list(station.vehicles.items())}
        if now >= next_status:
            next_status = now + STATUS_PERIOD_S
            _publish_status(transport, station, ground_status_t.RUN_ACTIVE)
        elif changed := [vid for vid, last in done.items() if reported_done.get(vid) != last]:
            _publish_status(transport, station, ground_status_t.RUN_ACTIVE, changed)
        reported_done = done
        if now >= next_progress:
            next_progress = now + PROGRESS_PERIOD_S
            _progress(station, now - started)


def _publish_status(transport: Transport, station: Station, run_state: int,
                    vehicles: list[int] | None = None) -> None:
    """Every vehicle's status, or VEHICLES' only."""
    now = time.monotonic()
    for state in list(station.vehicles.values()):
        if vehicles is not None and state.vehicle_id not in vehicles:
            continue
        transport.publish(channel_name(Channel.GROUND_STATUS, state.vehicle_id),
                   station.ground_status(state, now, LINK_TIMEOUT_S, run_state).encode())


def _progress(station: Station, elapsed_s: float) -> None:
    for vid, state in sorted(station.vehicles.items()):
        c = state.counters
        lat = state.latencies_ms[-50:]
        line = (f"[{elapsed_s:6.1f} s] vehicle {vid}: {c.keyframes_received} keyframes, "
                f"{c.lost_on_link} lost on the link, {c.keyframes_fused} fused, "
                f"{c.keyframes_lost} not refined, {c.keyframes_dropped} dropped; "
                f"latency median {format_ms(percentile(lat, 50))} ms (last 50); queue "
                f"{station.queue_length()}; map {state.map_blocks} blocks")
        link = station.receiver.link_quality(vid)
        if link is not None and link.chunks_received > 0:
            line += (f"; link {100.0 * link.link_loss:.1f}% lost, "
                     f"{link.goodput_bps * 1e-6:.2f} Mbit/s, {link.repair_requests} repairs, "
                     f"{link.keyframes_recovered} recovered, {link.keyframes_incomplete} "
                     "incomplete")
        d = state.drone_status
        if d is not None and d.chunks_sent > 0:
            line += (f"; drone budget {d.send_budget_bps * 1e-6:.2f} Mbit/s, redundancy "
                     f"{d.redundancy:.2f}, scale 1/{d.keyframe_scale}, {d.keyframes_skipped} "
                     "skipped")
        log(line)


def _finish(station: Station, viewer: Viewer, args: argparse.Namespace, mode: str,
            started: float, truth: list | None, extra: dict[str, Any]) -> int:
    """Finishes the recording, then writes the outputs and prints the summary: 0, or 1 when
    something could not be written (the rest still is)."""
    rrd = _rrd_path(args)
    rc = 0
    # The process after the whole flight, before the final mesh and the evaluation add theirs.
    extra = {**extra, "memory_after_fusion": memory()}
    try:
        station.show_final(truth)
        viewer.close()
    except ViewerError as error:
        log(str(error))
        rrd, rc = None, 1
    try:
        summary = export(station, args.out, mode, started, truth,
                         {**extra, "rrd": None if rrd is None else str(rrd)})
    except OutputError as error:
        log(str(error))
        return 1
    print_summary(summary, args.out, rrd)
    return rc


# --- replay ----------------------------------------------------------------------------------

LCM_LOG_SYNC = bytes.fromhex("eda1da01")  # every event of an LCM event log starts with it


def check_event_log(path: Path) -> None:
    """Refuses a file that is not an LCM event log: LCM's reader would just find no events in
    it, and the user would be told to look for keyframes that were never the problem."""
    try:
        with path.open("rb") as f:
            head = f.read(len(LCM_LOG_SYNC))
    except OSError as error:
        raise UsageError(f"cannot read {path}: {error.strerror or error}") from error
    if not head:
        raise UsageError(f"{path} is empty: not an LCM event log")
    if head != LCM_LOG_SYNC:
        raise UsageError(f"{path} is not an LCM event log (it does not start with LCM's event "
                         "marker); flight logs are written by lcm-logger, kinfly-tum-to-log or "
                         "`make demo`")


def replay(args: argparse.Namespace) -> int:
    import lcm

    _check_vehicle(args)
    params = _params(args)
    if not args.log.is_file():
        raise UsageError(f"{args.log} is not a file")
    check_event_log(args.log)
    try:
        log_file = lcm.EventLog(str(args.log), "r")
    except (OSError, RuntimeError) as error:
        raise UsageError(f"cannot open LCM log {args.log}: {error}") from error
    truth = read_tum(args.ground_truth) if args.ground_truth else None
    check_writable(args.out)
    viewer = _viewer(args)
    started = time.monotonic()
    station = Station(params, viewer, vehicle_id=args.vehicle, signers={}, publish=None,
                      inline=True, log=log)
    size = max(1, log_file.size())
    next_progress = started
    keyframe_messages = 0  # whole keyframes and keyframe chunks in the log

    def received() -> int:
        return sum(state.counters.keyframes_received for state in station.vehicles.values())

    for event in log_file:
        parsed = parse_channel(event.channel)
        if parsed is not None and parsed[0] in (Channel.KEYFRAME, Channel.KEYFRAME_CHUNK):
            keyframe_messages += 1
        station.on_message(event.channel, event.data)
        now = time.monotonic()
        if now >= next_progress:
            next_progress = now + PROGRESS_PERIOD_S
            log(f"replay: {100.0 * log_file.tell() / size:5.1f}% of {args.log.name}, "
                f"{received()} keyframes, {now - started:.1f} s")
    log_file.close()
    if keyframe_messages == 0:
        raise UsageError(f"{args.log} holds no keyframes (KINFLY_<id>_KEYFRAME or "
                         "KINFLY_<id>_KEYFRAME_CHUNK): a sensor recording is flown through "
                         "kinfly-fw first (see `make demo`)")
    log(f"replay: 100.0% of {args.log.name}, {received()} keyframes")
    return _finish(station, viewer, args, "replay", started, truth, {"log": str(args.log)})


def send_command(args: argparse.Namespace) -> int:
    _check_vehicle(args)
    values = args.values
    wanted = {"takeoff": 1, "goto": 3, "mission": 1}.get(args.action, 0)
    if len(values) != wanted:
        raise UsageError(f"{args.action} takes {wanted} value(s) (got {len(values)}): "
                         "kinfly-ground command --help")
    if not 1 <= args.copies <= 100:
        raise UsageError(f"--copies {args.copies} outside [1, 100]")
    try:
        numbers = [float(v) for v in values] if args.action in ("takeoff", "goto") else []
    except ValueError:
        raise UsageError(f"{args.action}: not a number in {' '.join(values)}")
    if args.yaw is not None and (args.action != "goto" or not -360.0 <= args.yaw <= 360.0):
        raise UsageError(f"--yaw {args.yaw:g}: for goto only, in [-360, 360] degrees")
    waypoints = read_waypoints(Path(values[0])) if args.action == "mission" else []
    command_id = time.time_ns() // 1000
    message = build_command(args.vehicle, args.action, command_id,
                            height_m=numbers[0] if args.action == "takeoff" else 0.0,
                            target=numbers if args.action == "goto" else (0.0, 0.0, 0.0),
                            yaw_rad=None if args.yaw is None else math.radians(args.yaw),
                            waypoints=waypoints, max_speed_m_s=args.max_speed)
    if not 0.0 <= args.wait <= 600.0:
        raise UsageError(f"--wait {args.wait:g} outside [0, 600] s")
    signer = Signer(load_key_file(args.key), args.vehicle)
    import lcm  # as in run: only the commands that use the network load it

    lc = lcm.LCM(args.lcm_url or DEFAULT_LCM_URL)
    answers = AnswerWatch(lc, args.vehicle, command_id)  # before sending: never miss it
    name = f"command {command_id} ({args.action})"
    if args.wait == 0.0:
        send(lc, signer, message, args.copies)
        log(f"{name} sent to vehicle {args.vehicle}, {args.copies} copies")
        return 0

    def sent_log(times: int) -> None:
        log(f"{name} sent to vehicle {args.vehicle}, {args.copies} copies; again every "
            f"{RESEND_PERIOD_S:g} s until answered" if times == 1 else
            f"{name}: no answer yet, sent again ({times} times)")

    status, sent = send_until_answered(lc, signer, message, args.copies, answers, args.wait,
                                       sent_log)
    if status is None:
        log(f"command {command_id} ({args.action}): no answer from vehicle {args.vehicle} "
            f"within {args.wait:g} s, sent {sent} times (is its flight backend on, and the "
            "link up?)")
        return 1
    log(f"command {command_id} ({args.action}) {answer(status.command_result)}; vehicle "
        f"{args.vehicle} is in {mode_name(status.mode)}" +
        (f" (sent {sent} times)" if sent > 1 else ""))
    return 0 if status.command_result == ACCEPTED else 1


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        if args.command == "command":
            return send_command(args)
        return run(args) if args.command == "run" else replay(args)
    except (UsageError, KeyFileError, OutputError, ViewerError, MavlinkError,
            CommandError) as error:
        log(f"error: {error}")
        return 2
    finally:
        # The station and its receiver refer to each other: free the maps now, not whenever
        # the interpreter gets to it.
        gc.collect()


if __name__ == "__main__":
    sys.exit(main())
