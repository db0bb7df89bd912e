"""A simulated flight's estimate, setpoint and map against the truth (docs/sim.md).

Reads `flight_status_t` (the drone's estimate and position setpoint, 10 Hz, on the IMU's clock)
and `sim_state_t` (the simulator's truth, 100 Hz, same clock) from `flight.lcmlog`, interpolates
the truth at each status, and writes:
- `tracking.png`: position (x, y, z) and attitude (roll, pitch, yaw) against time, truth,
  estimate and setpoint, a line at each change of flight mode;
- `errors.png`: the estimator's position, velocity and tilt errors against truth, and the
  tracking error (setpoint - truth);
- `flight_errors.json`: their RMS while airborne (a flying mode and off the floor), the figures issue 16
  asks of the estimator (<= 1 cm, 3 cm/s, 0.3 deg) and of tracking;
- `map_accuracy.json`: the ground's map (`mesh.ply`) against the scene's mesh (`scene.ply`,
  kinfly-sim --scene-mesh): the exact distance from every map vertex to the scene's surface
  (make eval's measure), the map placed in the scene by the true pose of the camera whose first
  frame defined the map's frame.

The truth's world is the scene's; the flight stack's is where the drone stood at the start,
facing its heading then (docs/sim.md, "Missions"): the truth is moved into it by the simulator's
first state. Run with the project's .venv python: `python scripts/sim_plots.py out/sim`."""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import lcm
import matplotlib
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from kinfly.flight_status_t import flight_status_t  # noqa: E402
from kinfly.ground_truth_t import ground_truth_t  # noqa: E402
from kinfly.sim_state_t import sim_state_t  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "eval"))
import kinfly_eval  # noqa: E402  (make eval's mesh accuracy)

MODE_NAMES = {flight_status_t.MODE_DISARMED: "disarmed", flight_status_t.MODE_ARMED: "armed",
              flight_status_t.MODE_TAKE_OFF: "take-off", flight_status_t.MODE_HOLD: "hold",
              flight_status_t.MODE_GO_TO: "go-to", flight_status_t.MODE_MISSION: "mission",
              flight_status_t.MODE_LAND: "land", flight_status_t.MODE_DESCEND: "descend",
              flight_status_t.MODE_MOTORS_CUT: "motors cut",
              flight_status_t.MODE_HANDED_OVER: "handed over"}
FLYING_MODES = {flight_status_t.MODE_TAKE_OFF, flight_status_t.MODE_HOLD,
                flight_status_t.MODE_GO_TO, flight_status_t.MODE_MISSION,
                flight_status_t.MODE_LAND, flight_status_t.MODE_DESCEND}


@dataclass
class Flight:
    t_s: np.ndarray          # simulated seconds since the simulator's first state
    mode: np.ndarray
    p_est: np.ndarray        # N x 3, the flight stack's world
    v_est: np.ndarray
    q_est: Rotation
    p_sp: np.ndarray
    p_true: np.ndarray       # the truth at the same instants, in the flight stack's world
    v_true: np.ndarray
    q_true: Rotation
    airborne: np.ndarray     # flying mode and the truth off the floor


def read(log_path: Path, vehicle: int) -> Flight:
    status: list[flight_status_t] = []
    truth: list[sim_state_t] = []
    for event in lcm.EventLog(str(log_path), "r"):
        if event.channel == f"KINFLY_{vehicle}_FLIGHT":
            status.append(flight_status_t.decode(event.data))
        elif event.channel == f"KINFLY_{vehicle}_SIM_STATE":
            truth.append(sim_state_t.decode(event.data))
    if len(truth) < 2:
        raise ValueError(f"{log_path}: no simulator states on KINFLY_{vehicle}_SIM_STATE")
    truth_us = np.array([s.utime for s in truth], dtype=np.int64)
    # Before the first IMU sample the control task ticks on the wall clock: only statuses on
    # the simulator's clock are compared.
    # The link sends the newest status at 10 Hz of the wall clock: one tick's may come twice.
    by_utime = {s.utime: s for s in status if truth_us[0] <= s.utime <= truth_us[-1]}
    status = [by_utime[u] for u in sorted(by_utime)]
    if not status:
        raise ValueError(f"{log_path}: no flight status on KINFLY_{vehicle}_FLIGHT within the "
                         "simulated flight")
    t_us = np.array([s.utime for s in status], dtype=np.int64)

    def at_status_times(values: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(t_us, truth_us, values[:, i])
                                for i in range(values.shape[1])])

    p_scene = np.array([s.p_world_m for s in truth])
    v_scene = np.array([s.v_world_m_s for s in truth])
    q_scene = Rotation.from_quat([s.q_world_body for s in truth])
    # The flight stack's world: the body's start position and heading.
    yaw0 = q_scene[0].as_euler("ZYX")[0]
    R_flight_scene = Rotation.from_euler("Z", -yaw0)
    p_true = R_flight_scene.apply(at_status_times(p_scene) - p_scene[0])
    v_true = R_flight_scene.apply(at_status_times(v_scene))
    q_true = R_flight_scene * Slerp(truth_us, q_scene)(t_us)
    # The last state at or before each status.
    on_floor = np.array([truth[np.searchsorted(truth_us, u, side="right") - 1].on_floor
                         for u in t_us])
    mode = np.array([s.mode for s in status])
    return Flight(
        t_s=(t_us - truth_us[0]) * 1e-6, mode=mode,
        p_est=np.array([s.p_world_m for s in status]),
        v_est=np.array([s.v_world_m_s for s in status]),
        q_est=Rotation.from_quat([s.q_world_body_xyzw for s in status]),
        p_sp=np.array([s.setpoint_world_m for s in status]),
        p_true=p_true, v_true=v_true, q_true=q_true,
        airborne=np.isin(mode, list(FLYING_MODES)) & ~on_floor)


def tilt_error_rad(q_est: Rotation, q_true: Rotation) -> np.ndarray:
    """Angle between the estimated and true directions of gravity in the body."""
    down_est = q_est.inv().apply([0.0, 0.0, 1.0])
    down_true = q_true.inv().apply([0.0, 0.0, 1.0])
    return np.arctan2(np.linalg.norm(np.cross(down_est, down_true), axis=1),
                      np.sum(down_est * down_true, axis=1))


def rms(values: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(values ** 2))) if values.size else None


def figures(flight: Flight) -> dict:
    a = flight.airborne
    position = np.linalg.norm(flight.p_est - flight.p_true, axis=1)[a]
    velocity = np.linalg.norm(flight.v_est - flight.v_true, axis=1)[a]
    tilt = tilt_error_rad(flight.q_est, flight.q_true)[a]
    tracking = np.linalg.norm(flight.p_sp - flight.p_true, axis=1)[a]
    tilt_rms = rms(tilt)
    dt_s = np.diff(flight.t_s, append=flight.t_s[-1])
    return {"airborne_s": round(float(dt_s[a].sum()), 1),
            "samples": int(a.sum()),
            "estimator_position_rms_m": rms(position),
            "estimator_velocity_rms_m_s": rms(velocity),
            "estimator_tilt_rms_deg": None if tilt_rms is None else float(np.degrees(tilt_rms)),
            "tracking_rms_m": rms(tracking),
            "tracking_max_m": float(tracking.max()) if tracking.size else None}


def plot_tracking(flight: Flight, path: Path) -> None:
    fig, axes = plt.subplots(6, 1, figsize=(11, 14), sharex=True)
    euler_true = np.degrees(flight.q_true.as_euler("ZYX")[:, ::-1])
    euler_est = np.degrees(flight.q_est.as_euler("ZYX")[:, ::-1])
    for i, name in enumerate("xyz"):
        ax = axes[i]
        ax.plot(flight.t_s, flight.p_true[:, i], "k-", lw=1.2, label="truth")
        ax.plot(flight.t_s, flight.p_est[:, i], "C0--", lw=1.0, label="estimate")
        ax.plot(flight.t_s, flight.p_sp[:, i], "C1:", lw=1.2, label="setpoint")
        ax.set_ylabel(f"{name} [m]")
    for i, name in enumerate(("roll", "pitch", "yaw")):
        ax = axes[3 + i]
        ax.plot(flight.t_s, euler_true[:, i], "k-", lw=1.2, label="truth")
        ax.plot(flight.t_s, euler_est[:, i], "C0--", lw=1.0, label="estimate")
        ax.set_ylabel(f"{name} [°]")
    _mark_modes(axes, flight)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title("position and attitude in the flight stack's world (z down)")
    axes[-1].set_xlabel("simulated time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_errors(flight: Flight, path: Path) -> None:
    fig, axes = plt.subplots(4, 1, figsize=(11, 9), sharex=True)
    series = [
        (np.linalg.norm(flight.p_est - flight.p_true, axis=1) * 100, "estimate position [cm]"),
        (np.linalg.norm(flight.v_est - flight.v_true, axis=1) * 100, "estimate velocity [cm/s]"),
        (np.degrees(tilt_error_rad(flight.q_est, flight.q_true)), "estimate tilt [°]"),
        (np.linalg.norm(flight.p_sp - flight.p_true, axis=1) * 100, "setpoint - truth [cm]")]
    for ax, (values, label) in zip(axes, series):
        ax.plot(flight.t_s, values, "C3-", lw=1.0)
        ax.set_ylabel(label, fontsize=9)
    _mark_modes(axes, flight)
    axes[0].set_title("errors against the simulator's truth")
    axes[-1].set_xlabel("simulated time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _mark_modes(axes: np.ndarray, flight: Flight) -> None:
    """A vertical line and the mode's name at each mode change."""
    changes = [0] + [i for i in range(1, len(flight.mode)) if flight.mode[i] != flight.mode[i - 1]]
    for i in changes:
        for ax in axes:
            ax.axvline(flight.t_s[i], color="0.8", lw=0.8, zorder=0)
        axes[0].annotate(MODE_NAMES.get(int(flight.mode[i]), "?"), (flight.t_s[i], 1.0),
                         xycoords=("data", "axes fraction"), fontsize=7, rotation=90,
                         va="top", ha="right", color="0.4")


# [µs] the TUM file's stamps are written to 1 µs; a frame's stamps are 33 ms apart.
FIRST_FRAME_MATCH_US = 500


def pose_matrix(row: np.ndarray) -> np.ndarray:
    """A TUM line's (t, tx, ty, tz, qx, qy, qz, qw) pose as a 4x4 matrix."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(row[4:8]).as_matrix()
    T[:3, 3] = row[1:4]
    return T


def map_accuracy(out: Path, vehicle: int) -> dict:
    """The map's vertices against the scene's surface. The map's frame is the odometry's first
    camera (drone_trajectory.tum's first pose); its true pose in the scene is the simulator's
    ground_truth_t for that frame in flight.lcmlog (the ground's trajectory_ground_truth.tum
    holds only what it heard: nothing before a restart)."""
    odometry = np.loadtxt(out / "drone_trajectory.tum", comments="#", ndmin=2)
    first_us = round(odometry[0, 0] * 1e6)
    first = None
    log = lcm.EventLog(str(out / "flight.lcmlog"), "r")
    try:
        for event in log:
            if event.channel == f"KINFLY_{vehicle}_GROUND_TRUTH":
                truth = ground_truth_t.decode(event.data)
                if abs(truth.utime - first_us) <= FIRST_FRAME_MATCH_US:
                    first = truth
                    break
    finally:
        log.close()
    if first is None:
        raise ValueError(f"{out / 'flight.lcmlog'}: no true pose on KINFLY_{vehicle}_GROUND_TRUTH "
                         f"at the odometry's first frame (t = {odometry[0, 0]:.3f} s)")
    pose = first.T_world_cam
    T_scene_map = pose_matrix(np.array([0.0, *pose.position_m, *pose.orientation_xyzw])) \
        @ np.linalg.inv(pose_matrix(odometry[0]))
    ours = kinfly_eval.load_mesh(out / "mesh.ply")
    scene = kinfly_eval.load_mesh(out / "scene.ply")
    vertices = np.asarray(ours.vertices) @ T_scene_map[:3, :3].T + T_scene_map[:3, 3]
    return kinfly_eval.distance_stats(kinfly_eval.point_to_surface_distances(vertices, scene))


def write(out: Path, vehicle: int) -> dict:
    flight = read(out / "flight.lcmlog", vehicle)
    plot_tracking(flight, out / "tracking.png")
    plot_errors(flight, out / "errors.png")
    result = figures(flight)
    (out / "flight_errors.json").write_text(json.dumps(result, indent=2) + "\n")
    if (out / "mesh.ply").is_file() and (out / "scene.ply").is_file():
        result["map"] = map_accuracy(out, vehicle)
        (out / "map_accuracy.json").write_text(json.dumps(result["map"], indent=2) + "\n")
    return result


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", type=Path, help="the flight's folder (flight.lcmlog in it)")
    p.add_argument("--vehicle", type=int, default=1, help="vehicle id (default 1)")
    args = p.parse_args()
    try:
        result = write(args.out, args.vehicle)
    except (OSError, ValueError) as error:
        print(f"sim_plots: {error}", file=sys.stderr)
        return 1
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
