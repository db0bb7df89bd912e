"""`make demo`: a recorded flight end to end through the real programs.

The native kinfly-fw replays a flight log (a depth recording made from the TUM sample with
kinfly-tum-to-log) as the drone; kinfly-ground serves it as the ground station; lcm-logger records
the flight as heard on the link. They talk LCM over UDP multicast inside a private network
namespace (loopback only, with the multicast route), set up here and removed at the end whatever
happens. The outputs land in --out; the ground station prints the summary.

The demo succeeds only when the flight did: every keyframe the drone sent was fused (beyond
--max-missing), every output is there and the ATE could be computed. Otherwise it says which
and exits 1. Nothing in it waits a fixed time: it waits for the ground station to say it is
listening, for the drone to exit (it waits for the ground's last corrections itself), and for
the ground station to report the drone's final status.

Run with the project's .venv python (the Makefile does). Needs root or passwordless sudo for the
namespace. The integration tests fly their own variations through fly()."""
from __future__ import annotations

import argparse
import dataclasses
import json
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from netns import NetnsUnavailable, network_namespace, send_signal  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
BUILD = REPO_ROOT / "build" / "bin"
FW_CONFIG = REPO_ROOT / "firmware" / "config" / "kinfly-fw.toml"
SAMPLE_LOG = REPO_ROOT / "tests" / "data" / "tum_teddy_sample.lcmlog"
VEHICLE_ID = 1
LCM_URL = "udpm://239.255.76.67:7667?ttl=0"
# Bounds on waits for events, not waits: a loaded laptop may take long, a broken one forever.
GROUND_READY_TIMEOUT_S = 120.0  # the ground imports rerun and evo and sets up its viewer
DRONE_FINAL_TIMEOUT_S = 30.0    # the drone's last status reaching the ground after it exits
GROUND_EXIT_TIMEOUT_S = 120.0   # drain the queue, mesh, evaluate, write
DRONE_STOPPED = "the drone stopped"  # the ground's line when it hears a drone's final status
# The demo's files, in the order they are listed, with what each is.
OUTPUTS = {
    "mesh.ply": "the full-resolution map (binary PLY; MeshLab, Blender)",
    "session.rrd": "the rerun recording (open it with rerun)",
    "trajectory_onboard.tum": "each keyframe's pose as the drone sent it",
    "trajectory_corrected.tum": "each keyframe's pose as the ground refined it",
    "trajectory_optimised.tum": "each keyframe's pose where the map's pose graph puts it at the end",
    "trajectory_ground_truth.tum": "the motion capture that came with the log",
    "ate.png": "the trajectories' error against the ground truth over time",
    "summary.json": "keyframes, losses, latency, ATE, memory",
    "flight.lcmlog": "every message on the link (kinfly-ground replay reads it)",
    "drone_trajectory.tum": "every pose the drone published",
    "vehicle.key": "the signing key made for this flight (kinfly-keygen; secret on a real drone)",
}


@dataclasses.dataclass
class Flight:
    ground_rc: int
    drone_rcs: list[int]
    ground_output: str
    drone_output: str


def make_key(path: Path) -> Path:
    subprocess.run([str(BUILD / "kinfly-keygen"), "--out", str(path)], check=True,
                   stdout=subprocess.DEVNULL)
    return path


def fresh_output(out: Path) -> Path:
    """Empties OUT (a run's outputs never mix with an earlier run's) and makes the flight's key
    in it."""
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    return make_key(out / "vehicle.key")


def ground_command(out: Path, *, key: Path | None, vehicle: int | None = VEHICLE_ID,
                   lcm_url: str = LCM_URL) -> list[str]:
    command = [str(Path(sys.executable).parent / "kinfly-ground"), "run", "--lcm-url", lcm_url,
               "--out", str(out)]
    if vehicle is not None:
        command += ["--vehicle", str(vehicle)]
    if key is not None:
        command += ["--key", str(key)]
    return command


def drone_command(log: Path, *, key: Path | None, trajectory: Path | None = None,
                  program: Sequence[str] | None = None) -> list[str]:
    """kinfly-fw replaying LOG as vehicle 1; PROGRAM is what runs it (default build/bin/kinfly-fw;
    the aarch64 tests put qemu-aarch64 before the arm64 build)."""
    command = [*(program or [str(BUILD / "kinfly-fw")]), "--config", str(FW_CONFIG),
               "--vehicle.id", str(VEHICLE_ID), "--vehicle.key_file", str(key or ""),
               "--source.kind", "log", "--source.path", str(log), "--link.lcm_url", LCM_URL]
    if trajectory is not None:
        command += ["--output.trajectory", str(trajectory)]
    return command


def _echo(stream, prefix: str, lines: list[str], quiet: bool,
          events: threading.Condition | None = None) -> None:
    for line in stream:
        if events is None:
            lines.append(line)
        else:
            with events:
                lines.append(line)
                events.notify_all()
        if not quiet:
            sys.stdout.write(f"{prefix}{line}")
            sys.stdout.flush()


class Watched:
    """A process and its output (stdout and stderr together) as it comes, so that whoever
    started it can wait for what it says instead of for a time. Started in a session of its
    own (netns.send_signal)."""

    def __init__(self, command: Sequence[str], prefix: str = "", quiet: bool = True,
                 answered: bool = False) -> None:
        """ANSWERED: its standard input is a pipe, for `answer`."""
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE,
                                        stderr=subprocess.STDOUT, text=True,
                                        stdin=subprocess.PIPE if answered else None,
                                        start_new_session=True)
        self.lines: list[str] = []
        self._events = threading.Condition()
        self._echo = threading.Thread(target=_echo, args=(self.process.stdout, prefix,
                                                          self.lines, quiet, self._events),
                                      daemon=True)
        self._echo.start()

    def wait_for(self, text: str, count: int, timeout_s: float) -> bool:
        """Until COUNT lines contain TEXT, the process exits, or TIMEOUT_S passes."""
        deadline = time.monotonic() + timeout_s
        with self._events:
            while sum(text in line for line in self.lines) < count:
                left = deadline - time.monotonic()
                if left <= 0 or not self._echo.is_alive():
                    return False
                self._events.wait(min(left, 0.5))
        return True

    def answer(self) -> None:
        """Writes a line to its standard input (started ANSWERED): what a program that waits for
        it takes as "done"."""
        assert self.process.stdin is not None
        self.process.stdin.write("\n")
        self.process.stdin.flush()

    def output(self) -> str:
        with self._events:
            return "".join(self.lines)

    def latest(self, text: str) -> str | None:
        """The last line so far that contains TEXT (a progress line), or None."""
        with self._events:
            return next((line for line in reversed(self.lines) if text in line), None)

    def finish(self, timeout_s: float) -> int:
        """Its exit status, once it has exited (within TIMEOUT_S) and all it said is read."""
        self.process.wait(timeout_s)
        self._echo.join()
        return self.process.returncode


def start_ground(command: Sequence[str], quiet: bool = False) -> Watched:
    """kinfly-ground from COMMAND (with the namespace's prefix), once it listens; if it does not
    within GROUND_READY_TIMEOUT_S it is stopped and RuntimeError says what it printed."""
    ground = Watched(command, "[ground] ", quiet)
    if not ground.wait_for("listening on", 1, GROUND_READY_TIMEOUT_S):
        send_signal(ground.process, signal.SIGTERM)
        ground.finish(GROUND_EXIT_TIMEOUT_S)
        raise RuntimeError("the ground station did not start listening:\n" + ground.output())
    return ground


def fly(netns: list[str], ground: Sequence[str], drones: Sequence[Sequence[str]], *,
        record: Path | None = None, record_url: str = LCM_URL,
        during: Callable[[], None] | None = None, quiet: bool = False,
        drone_heard: bool = True) -> Flight:
    """Starts the GROUND command in the namespace, waits until it says it is listening, runs each
    of DRONES to its end in turn (a second one is the drone restarting), calls DURING while the
    last one flies, then stops the ground with SIGTERM, as Ctrl-C would. With DRONE_HEARD (the
    ground serves the drones' vehicle) each drone's final status must have reached the ground
    first: then every keyframe it sent has arrived or is lost, and the drone itself waited for
    the ground's corrections before it exited."""
    ground_proc = start_ground([*netns, *ground], quiet)
    logger = None
    if record is not None:  # before any drone: the whole flight is recorded
        logger = subprocess.Popen([*netns, "lcm-logger", "--quiet", "--lcm-url", record_url,
                                   str(record)], stdout=subprocess.DEVNULL,
                                  start_new_session=True)
    drone_lines: list[str] = []
    drone_rcs: list[int] = []
    try:
        for i, drone in enumerate(drones):
            drone_proc = subprocess.Popen([*netns, *drone], stdout=subprocess.PIPE,
                                          stderr=subprocess.STDOUT, text=True)
            if during is not None and i == len(drones) - 1:
                during()
            _echo(drone_proc.stdout, "[drone]  ", drone_lines, quiet)
            drone_rcs.append(drone_proc.wait())
            if drone_heard and drone_rcs[-1] == 0 and not ground_proc.wait_for(
                    DRONE_STOPPED, i + 1, DRONE_FINAL_TIMEOUT_S):
                print(f"demo: the ground station did not hear drone run {i + 1}'s final status "
                      f"within {DRONE_FINAL_TIMEOUT_S:.0f} s", file=sys.stderr)
    finally:
        # As Ctrl-C would: the ground finishes its queue and writes the outputs.
        send_signal(ground_proc.process, signal.SIGTERM)
        ground_rc = ground_proc.finish(GROUND_EXIT_TIMEOUT_S)
        if logger is not None:
            send_signal(logger, signal.SIGINT)
            logger.wait(10)
    return Flight(ground_rc, drone_rcs, ground_proc.output(), "".join(drone_lines))


def check_flight(out: Path, max_missing: int, vehicle_id: int = VEHICLE_ID) -> list[str]:
    """What is wrong with VEHICLE_ID's flight whose outputs are in OUT: an empty list when it
    mapped every keyframe the drone sent (up to MAX_MISSING), wrote every output and has an
    ATE."""
    summary_path = out / "summary.json"
    if not summary_path.is_file():
        return [f"{summary_path} was not written"]
    summary = json.loads(summary_path.read_text())
    vehicle = summary["vehicles"].get(str(vehicle_id))
    if vehicle is None:
        return [f"the ground station received nothing from vehicle {vehicle_id}"]
    problems = []
    k, drone = vehicle["keyframes"], vehicle.get("drone_reported")
    if drone is None or not drone["final"]:
        problems.append("the ground station never heard the drone's final status, so what it "
                        "sent is unknown")
    else:
        missing = drone["keyframes_sent"] - k["keyframes_fused"]
        if missing > max_missing:
            problems.append(
                f"the drone sent {drone['keyframes_sent']} keyframes but the ground fused "
                f"{k['keyframes_fused']}: {k['lost_on_link']} lost on the link, "
                f"{k['keyframes_dropped']} dropped from the ground's queue, "
                f"{k['keyframes_lost']} not refined, {k['failed']} failed (at most "
                f"{max_missing} may be missing)")
    for name in OUTPUTS:
        path = out / name
        if name == "vehicle.key":
            continue
        if not path.is_file() or path.stat().st_size == 0:
            problems.append(f"{name} is missing or empty")
    if not vehicle["ate"]["available"]:
        problems.append(f"no ATE: {vehicle['ate']['reason']}")
    return problems


def list_outputs(out: Path, outputs: dict[str, str] = OUTPUTS) -> str:
    """The files of OUTPUTS that are in OUT, each with its size and what it is."""
    rows = []
    for name, what in outputs.items():
        path = out / name
        if path.is_file():
            rows.append(f"  {name:<28} {path.stat().st_size / 1e3:9.1f} KB  {what}")
    return "\n".join(rows)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "demo")
    p.add_argument("--log", type=Path, default=SAMPLE_LOG,
                   help="the flight log the drone replays (default: the shipped TUM sample)")
    p.add_argument("--max-missing", type=int, default=0, metavar="N",
                   help="keyframes the drone sent that the ground may fail to fuse before the "
                        "demo fails (default 0: on loopback none is lost)")
    args = p.parse_args()

    out = args.out
    key = fresh_output(out)
    started = time.monotonic()
    try:
        with network_namespace("demo") as netns:
            drone = drone_command(args.log, key=key, trajectory=out / "drone_trajectory.tum")
            flight = fly(netns, ground_command(out, key=key), [drone],
                         record=out / "flight.lcmlog")
    except NetnsUnavailable as error:
        print(f"demo: {error}", file=sys.stderr)
        return 1
    print()
    problems = []
    if flight.drone_rcs != [0] or flight.ground_rc != 0:
        problems.append(f"kinfly-fw exited {flight.drone_rcs}, kinfly-ground {flight.ground_rc}")
    problems += check_flight(out, args.max_missing)
    applied = re.search(r"(\d+) corrections applied", flight.drone_output)
    print(f"demo: {time.monotonic() - started:.0f} s; the drone applied "
          f"{applied.group(1) if applied else 'none'} of the ground's corrections.")
    print(f"demo: files in {out}:\n{list_outputs(out)}")
    return report("demo", out, problems)


def report(tool: str, out: Path, problems: list[str]) -> int:
    """The run's verdict: its PROBLEMS and exit status 1, or how to look at it and 0."""
    if problems:
        print(f"{tool}: FAILED:\n" + "\n".join(f"  - {problem}" for problem in problems),
              file=sys.stderr)
        return 1
    print(f"{tool}: look at it with `{Path(sys.executable).parent / 'rerun'} "
          f"{out / 'session.rrd'}`")
    return 0


if __name__ == "__main__":
    sys.exit(main())
