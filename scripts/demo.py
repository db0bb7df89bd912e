"""`make demo`: a recorded flight end to end through the real programs.

The native kinfly-fw replays a flight log (a depth recording made from the TUM sample with
kinfly-tum-to-log) as the drone; kinfly-ground serves it as the ground station; lcm-logger records
the flight. They talk LCM over UDP multicast inside a private network namespace (loopback only,
with the multicast route), set up here and removed at the end whatever happens. The outputs land
in --out; the ground station prints the summary.

Run with the project's .venv python (the Makefile does). Needs root or passwordless sudo for the
namespace."""
from __future__ import annotations

import argparse
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from netns import NetnsUnavailable, network_namespace  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
VEHICLE_ID = 1
LCM_URL = "udpm://239.255.76.67:7667?ttl=0"
GROUND_READY_TIMEOUT_S = 60.0   # the ground imports rerun and evo before it listens
GROUND_EXIT_TIMEOUT_S = 120.0   # drain the queue, mesh, evaluate, write
SETTLE_S = 1.0                  # after the drone ends: the last corrections and statuses


def _echo(stream, prefix: str, ready: threading.Event | None = None,
          lines: list[str] | None = None) -> None:
    for line in stream:
        if lines is not None:
            lines.append(line)
        sys.stdout.write(f"{prefix}{line}")
        sys.stdout.flush()
        if ready is not None and "listening on" in line:
            ready.set()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "demo")
    p.add_argument("--log", type=Path, default=REPO_ROOT / "tests" / "data" /
                   "tum_teddy_sample.lcmlog", help="the flight log the drone replays")
    p.add_argument("--build", type=Path, default=REPO_ROOT / "build" / "bin")
    p.add_argument("--ground-truth", type=Path, help="TUM file to evaluate against "
                   "(default: the log's own ground truth, which kinfly-fw passes on)")
    args = p.parse_args()

    out = args.out
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    key = out / "vehicle.key"
    subprocess.run([str(args.build / "kinfly-keygen"), "--out", str(key)], check=True,
                   stdout=subprocess.DEVNULL)
    ground_bin = Path(sys.executable).parent / "kinfly-ground"
    ground_cmd = [str(ground_bin), "run", "--vehicle", str(VEHICLE_ID), "--key", str(key),
                  "--lcm-url", LCM_URL, "--out", str(out)]
    if args.ground_truth:
        ground_cmd += ["--ground-truth", str(args.ground_truth)]
    fw_cmd = [str(args.build / "kinfly-fw"), "--config",
              str(REPO_ROOT / "firmware" / "config" / "kinfly-fw.toml"),
              "--vehicle.id", str(VEHICLE_ID), "--vehicle.key_file", str(key),
              "--source.kind", "log", "--source.path", str(args.log),
              "--link.lcm_url", LCM_URL, "--output.trajectory", str(out / "drone_trajectory.tum")]
    started = time.monotonic()
    try:
        with network_namespace("demo") as netns:
            logger = subprocess.Popen([*netns, "lcm-logger", "--quiet", "--lcm-url", LCM_URL,
                                       str(out / "flight.lcmlog")], stdout=subprocess.DEVNULL)
            ground = subprocess.Popen([*netns, *ground_cmd], stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, text=True)
            ready = threading.Event()
            echo = threading.Thread(target=_echo, args=(ground.stdout, "[ground] ", ready),
                                    daemon=True)
            echo.start()
            try:
                if not ready.wait(GROUND_READY_TIMEOUT_S):
                    print("demo: the ground station did not start", file=sys.stderr)
                    return 1
                fw_lines: list[str] = []
                fw = subprocess.Popen([*netns, *fw_cmd], stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, text=True)
                _echo(fw.stdout, "[drone]  ", lines=fw_lines)
                fw_rc = fw.wait()
                time.sleep(SETTLE_S)
            finally:
                # SIGTERM through `ip netns exec` (sudo passes it on): the ground finishes its
                # queue and writes the outputs.
                ground.send_signal(signal.SIGTERM)
                ground_rc = ground.wait(GROUND_EXIT_TIMEOUT_S)
                echo.join()
                logger.send_signal(signal.SIGINT)
                logger.wait(10)
    except NetnsUnavailable as error:
        print(f"demo: {error}", file=sys.stderr)
        return 1
    if fw_rc != 0 or ground_rc != 0:
        print(f"demo: kinfly-fw exited {fw_rc}, kinfly-ground {ground_rc}", file=sys.stderr)
        return 1
    applied = re.search(r"(\d+) corrections applied", "".join(fw_lines))
    print()
    print(f"demo: done in {time.monotonic() - started:.0f} s; the drone applied "
          f"{applied.group(1) if applied else '?'} of the ground's corrections.")
    print(f"demo: outputs in {out}: mesh.ply, trajectory_onboard.tum, trajectory_corrected.tum, "
          "session.rrd, summary.json, ate.png; the flight as heard on the link: flight.lcmlog")
    print(f"demo: look at it with `{Path(sys.executable).parent / 'rerun'} {out / 'session.rrd'}`")
    return 0


if __name__ == "__main__":
    sys.exit(main())
