"""`make demo`: a recorded flight end to end through the real programs.

The native kinfly-fw replays a flight log (a depth recording made from the TUM sample with
kinfly-tum-to-log) as the drone; kinfly-ground serves it as the ground station; lcm-logger records
the flight as heard on the link. They talk LCM over UDP multicast inside a private network
namespace (loopback only, with the multicast route), set up here and removed at the end whatever
happens. The outputs land in --out; the ground station prints the summary.

Run with the project's .venv python (the Makefile does). Needs root or passwordless sudo for the
namespace. The integration tests fly their own variations through fly()."""
from __future__ import annotations

import argparse
import dataclasses
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
GROUND_READY_TIMEOUT_S = 60.0   # the ground imports rerun and evo before it listens
GROUND_EXIT_TIMEOUT_S = 120.0   # drain the queue, mesh, evaluate, write
SETTLE_S = 1.0                  # after the drone ends: the last corrections and statuses


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


def ground_command(out: Path, *, key: Path | None, vehicle: int | None = VEHICLE_ID) -> list[str]:
    command = [str(Path(sys.executable).parent / "kinfly-ground"), "run", "--lcm-url", LCM_URL,
               "--out", str(out)]
    if vehicle is not None:
        command += ["--vehicle", str(vehicle)]
    if key is not None:
        command += ["--key", str(key)]
    return command


def drone_command(log: Path, *, key: Path | None, trajectory: Path | None = None) -> list[str]:
    command = [str(BUILD / "kinfly-fw"), "--config", str(FW_CONFIG),
               "--vehicle.id", str(VEHICLE_ID), "--vehicle.key_file", str(key or ""),
               "--source.kind", "log", "--source.path", str(log), "--link.lcm_url", LCM_URL]
    if trajectory is not None:
        command += ["--output.trajectory", str(trajectory)]
    return command


def _echo(stream, prefix: str, lines: list[str], ready: threading.Event | None = None,
          quiet: bool = False) -> None:
    for line in stream:
        lines.append(line)
        if not quiet:
            sys.stdout.write(f"{prefix}{line}")
            sys.stdout.flush()
        if ready is not None and "listening on" in line:
            ready.set()


def fly(netns: list[str], ground: Sequence[str], drones: Sequence[Sequence[str]], *,
        record: Path | None = None, during: Callable[[], None] | None = None,
        quiet: bool = False) -> Flight:
    """Starts the GROUND command in the namespace, waits until it listens, runs each of DRONES
    to its end in turn (a second one is the drone restarting), calls DURING while the last one
    flies, then stops the ground with SIGTERM, as Ctrl-C would."""
    logger = None
    if record is not None:
        logger = subprocess.Popen([*netns, "lcm-logger", "--quiet", "--lcm-url", LCM_URL,
                                   str(record)], stdout=subprocess.DEVNULL,
                                  start_new_session=True)
    ground_proc = subprocess.Popen([*netns, *ground], stdout=subprocess.PIPE,
                                   stderr=subprocess.STDOUT, text=True,
                                   start_new_session=True)
    ground_lines: list[str] = []
    drone_lines: list[str] = []
    ready = threading.Event()
    echo = threading.Thread(target=_echo, args=(ground_proc.stdout, "[ground] ", ground_lines,
                                                ready, quiet), daemon=True)
    echo.start()
    drone_rcs: list[int] = []
    try:
        deadline = time.monotonic() + GROUND_READY_TIMEOUT_S
        while not ready.wait(0.1) and ground_proc.poll() is None and time.monotonic() < deadline:
            pass
        if not ready.is_set():
            echo.join(1.0)
            raise RuntimeError("the ground station did not start listening:\n"
                               + "".join(ground_lines))
        for i, drone in enumerate(drones):
            drone_proc = subprocess.Popen([*netns, *drone], stdout=subprocess.PIPE,
                                          stderr=subprocess.STDOUT, text=True)
            if during is not None and i == len(drones) - 1:
                during()
            _echo(drone_proc.stdout, "[drone]  ", drone_lines, quiet=quiet)
            drone_rcs.append(drone_proc.wait())
        time.sleep(SETTLE_S)
    finally:
        # As Ctrl-C would: the ground finishes its queue and writes the outputs.
        send_signal(ground_proc, signal.SIGTERM)
        ground_rc = ground_proc.wait(GROUND_EXIT_TIMEOUT_S)
        echo.join()
        if logger is not None:
            send_signal(logger, signal.SIGINT)
            logger.wait(10)
    return Flight(ground_rc, drone_rcs, "".join(ground_lines), "".join(drone_lines))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "demo")
    p.add_argument("--log", type=Path, default=SAMPLE_LOG,
                   help="the flight log the drone replays (default: the shipped TUM sample)")
    args = p.parse_args()

    out = args.out
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    key = make_key(out / "vehicle.key")
    started = time.monotonic()
    try:
        with network_namespace("demo") as netns:
            drone = drone_command(args.log, key=key, trajectory=out / "drone_trajectory.tum")
            flight = fly(netns, ground_command(out, key=key), [drone],
                         record=out / "flight.lcmlog")
    except NetnsUnavailable as error:
        print(f"demo: {error}", file=sys.stderr)
        return 1
    if flight.drone_rcs != [0] or flight.ground_rc != 0:
        print(f"demo: kinfly-fw exited {flight.drone_rcs}, kinfly-ground {flight.ground_rc}",
              file=sys.stderr)
        return 1
    applied = re.search(r"(\d+) corrections applied", flight.drone_output)
    print()
    print(f"demo: done in {time.monotonic() - started:.0f} s; the drone applied "
          f"{applied.group(1) if applied else '?'} of the ground's corrections.")
    print(f"demo: outputs in {out}: mesh.ply, trajectory_onboard.tum, trajectory_corrected.tum, "
          "session.rrd, summary.json, ate.png; the flight as heard on the link: flight.lcmlog "
          "(kinfly-ground replay it)")
    print(f"demo: look at it with `{Path(sys.executable).parent / 'rerun'} {out / 'session.rrd'}`")
    return 0


if __name__ == "__main__":
    sys.exit(main())
