"""`make sim`: the drone flown in the simulated room through the real programs.

kinfly-sim (the world: dynamics, wind, IMU, the depth camera rendered by Embree) drives the native
kinfly-fw (depth over LCM, the motors backend, the IMU as its only clock) in lockstep, and
kinfly-ground maps the keyframes and sends its corrections, each keyframe's before the drone's
next frame (source.lockstep), so that a seed flies the same flight on any machine. lcm-logger
records the flight. They talk LCM over UDP multicast in a private network namespace, as `make
demo` does. The simulator flies its mission (the room tour unless told otherwise: take off, three
go-tos, a figure eight, land) and the run succeeds only
when the drone landed without a collision or a failsafe and the ground mapped what it was sent.
Nothing waits a fixed time: each program's readiness and end are what the next step waits for.

Run with the project's .venv python (the Makefile does). Needs root or passwordless sudo for the
namespace (docs/sim.md)."""
from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from demo import (BUILD, FW_CONFIG, GROUND_EXIT_TIMEOUT_S, GROUND_READY_TIMEOUT_S,  # noqa: E402
                  LCM_URL, VEHICLE_ID, Watched, check_flight, fresh_output, ground_command,
                  list_outputs, report)
from netns import NetnsUnavailable, network_namespace, send_signal  # noqa: E402
from sim_plots import kinfly_eval, write as write_plots  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
DRONE_EXIT_TIMEOUT_S = 60.0  # kinfly-fw's last corrections and its summary after SIGINT
ROOM_TOUR = REPO_ROOT / "sim" / "missions" / "room_tour.toml"
HOVER = "hover"  # --mission: kinfly-sim's built-in take off, hold, land
# What lcm-logger records: everything but the raw depth frames (30 a second at VGA; the keyframes
# that reached the ground are in their chunks).
RECORDED = (f"KINFLY_{VEHICLE_ID}_(IMU|MOTOR_COMMAND|SIM_STATE|ODOMETRY|KEYFRAME_CHUNK|STATUS|"
            "FLIGHT|GROUND_STATUS|CORRECTION|COMMAND|CHUNK_REQUEST|GROUND_TRUTH)")
OUTPUTS = {
    "sim_summary.json": "the simulator's figures: hover against truth, touchdown, collisions",
    "summary.json": "the ground station's: keyframes, corrections, ATE, memory",
    "session.rrd": "the rerun recording (open it with rerun)",
    "mesh.ply": "the ground's map of the room (binary PLY)",
    "trajectory_onboard.tum": "each keyframe's pose as the drone sent it",
    "trajectory_corrected.tum": "each keyframe's pose as the ground refined it",
    "trajectory_ground_truth.tum": "the simulator's true camera poses",
    "flight.lcmlog": "the flight on LCM but the raw depth (kinfly-ground replay reads it)",
    "tracking.png": "position and attitude: truth, the drone's estimate, its setpoint",
    "errors.png": "the estimate's and the tracking's errors against truth",
    "flight_errors.json": "their RMS while airborne",
    "scene.ply": "the scene's mesh, the truth the map is scored against",
    "map_accuracy.json": "the map's vertices' distances to the scene's surface",
    "drone_trajectory.tum": "every pose the drone's odometry published",
    "vehicle.key": "the signing key made for this flight",
}


def drone_command(key: Path, out: Path) -> list[str]:
    return [str(BUILD / "kinfly-fw"), "--config", str(FW_CONFIG), "--vehicle.id", str(VEHICLE_ID),
            "--vehicle.key_file", str(key), "--link.lcm_url", LCM_URL, "--source.kind", "lcm",
            "--source.realtime", "false", "--source.lockstep", "true", "--flight.backend", "motors",
            "--flight.imu", "lcm", "--flight.lockstep", "true",
            "--output.trajectory", str(out / "drone_trajectory.tum")]


def sim_command(key: Path, out: Path, args: argparse.Namespace) -> list[str]:
    return [str(BUILD / "kinfly-sim"), "--key-file", str(key), "--vehicle", str(VEHICLE_ID),
            "--lcm-url", LCM_URL, "--scene", args.scene, "--seed", str(args.seed),
            "--hover-s", str(args.hover_s), "--camera-downsample", str(args.camera_downsample),
            "--summary", str(out / "sim_summary.json"), "--scene-mesh", str(out / "scene.ply"),
            *([] if args.mission == HOVER else ["--mission", str(args.mission)])]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "sim")
    p.add_argument("--scene", default="room", help="room | corridor (default room)")
    p.add_argument("--seed", type=int, default=1, help="the simulator's seed (default 1)")
    p.add_argument("--hover-s", type=float, default=20.0,
                   help=f"seconds the drone holds at 1 m before it lands (default 20); "
                   f"--mission {HOVER} only")
    p.add_argument("--mission", default=str(ROOM_TOUR),
                   help=f"a mission file (sim/missions/, docs/sim.md), or {HOVER!r} for "
                   f"kinfly-sim's built-in take off, hold --hover-s, land (default: the room "
                   f"tour, {ROOM_TOUR.relative_to(REPO_ROOT)})")
    p.add_argument("--camera-downsample", type=int, default=1,
                   help="the simulated Kinect at 1/N of 640x480 (default 1)")
    args = p.parse_args()
    out = args.out
    key = fresh_output(out)
    started = time.monotonic()
    problems: list[str] = []
    try:
        with network_namespace("sim") as netns:
            logger = subprocess.Popen([*netns, "lcm-logger", "--quiet", "--lcm-url", LCM_URL,
                                       "--channel", RECORDED, str(out / "flight.lcmlog")],
                                      stdout=subprocess.DEVNULL, start_new_session=True)
            ground = Watched([*netns, *ground_command(out, key=key)], "[ground] ", quiet=False)
            drone = None
            try:
                if not ground.wait_for("listening on", 1, GROUND_READY_TIMEOUT_S):
                    raise RuntimeError("the ground station did not start listening:\n"
                                       + ground.output())
                drone = Watched([*netns, *drone_command(key, out)], "[drone]  ", quiet=False)
                sim = Watched([*netns, *sim_command(key, out, args)], "[sim]    ", quiet=False)
                sim_rc = sim.finish(None)
                if sim_rc != 0:
                    problems.append(f"kinfly-sim exited {sim_rc}: the flight failed (above)")
            finally:
                if drone is not None:
                    send_signal(drone.process, signal.SIGINT)
                    drone_rc = drone.finish(DRONE_EXIT_TIMEOUT_S)
                    if drone_rc != 0:
                        problems.append(f"kinfly-fw exited {drone_rc}")
                send_signal(ground.process, signal.SIGTERM)
                if ground.finish(GROUND_EXIT_TIMEOUT_S) != 0:
                    problems.append("kinfly-ground failed (above)")
                send_signal(logger, signal.SIGINT)
                logger.wait(10)
    except NetnsUnavailable as error:
        print(f"sim: {error}", file=sys.stderr)
        return 1
    if drone is not None and "control: failsafe:" in drone.output():
        problems.append("a failsafe acted in flight (the drone's log above says which)")
    problems += check_flight(out, max_missing=0)
    errors = None
    if (out / "flight.lcmlog").is_file():
        try:
            errors = write_plots(out, VEHICLE_ID)
        except (OSError, ValueError, ImportError) as error:
            problems.append(f"no plots or map score: {error}")
    print(f"\nsim: {time.monotonic() - started:.0f} s; files in {out}:\n"
          f"{list_outputs(out, OUTPUTS)}")
    problems += [f"{name} was not written" for name in OUTPUTS if not (out / name).is_file()]
    summary = out / "sim_summary.json"
    if summary.is_file():
        figures = json.loads(summary.read_text())
        hover = figures["hover_rms_m"]
        print(f"sim: hover RMS against truth "
              f"{'-' if hover is None else f'{hover * 100:.1f} cm'}, touchdown "
              f"{figures['touchdown_m_s']:.2f} m/s, {figures['failsafes']} failsafes, "
              f"{figures['real_time_factor']:.2f}x real time")
    if errors and errors["samples"]:
        print(f"sim: airborne {errors['airborne_s']:.0f} s: estimate against truth "
              f"{errors['estimator_position_rms_m'] * 100:.1f} cm, "
              f"{errors['estimator_velocity_rms_m_s'] * 100:.1f} cm/s, "
              f"{errors['estimator_tilt_rms_deg']:.2f}° RMS; setpoint against truth "
              f"{errors['tracking_rms_m'] * 100:.1f} cm RMS")
    if errors and "map" in errors:
        print(f"sim: the map against the scene: mean {errors['map']['mean_m'] * 1000:.1f} mm, "
              f"{errors['map']['outlier_fraction'] * 100:.1f} % of its vertices beyond "
              f"{kinfly_eval.MESH_INLIER_M * 100:.0f} cm")
    return report("sim", out, problems)


if __name__ == "__main__":
    sys.exit(main())
