"""scripts/sim_plots.py on a made flight log whose errors are known: the truth moved into the
flight stack's world by the simulator's first state, the estimate's offsets, the tilt error and
the tracking error measured while airborne only, the plots written, and a log without the
simulator's states refused naming the channel."""
from __future__ import annotations

import math
from pathlib import Path

import lcm
import numpy as np
import pytest
from kinfly.flight_status_t import flight_status_t
from kinfly.ground_truth_t import ground_truth_t
from kinfly.pose3d_t import pose3d_t
from kinfly.sim_state_t import sim_state_t
from scipy.spatial.transform import Rotation

import sim_plots

VEHICLE = 3
START_US = 1_000_000
# The scene's start: the drone stands at (2, -1) on its gear, facing 90° left of the scene's x.
START_SCENE_M = np.array([2.0, -1.0, -0.1])
START_YAW_RAD = math.pi / 2
# What the made estimate gets wrong, and the setpoint.
POSITION_OFFSET_M = np.array([0.01, 0.0, 0.0])
VELOCITY_OFFSET_M_S = np.array([0.0, 0.02, 0.0])
TILT_ERROR_DEG = 0.5
SETPOINT_OFFSET_M = np.array([0.0, 0.0, 0.03])
# The stack flies (hold) from 2 s to 8 s; the truth leaves the floor 0.3 s after the mode
# changed: only [2.3 s, 8 s) is airborne, and outside it the made estimate is off by a metre, so a
# wrong mask shows in every figure.
FLYING_FROM_S, LIFT_OFF_S, AIRBORNE_TO_S, END_S = 2.0, 2.3, 8.0, 10.0
GROUND_ERROR_M = 1.0
# The statuses fall between the simulator's 100 Hz states, as they do in a flight.
STATUS_OFFSET_US = 5_000
# The made flight is linear in time between its steps, so interpolation is exact: what is left is
# float rounding.
TOL = 1e-6


def airborne(t_s: float) -> bool:
    return LIFT_OFF_S <= t_s < AIRBORNE_TO_S


def flight_in_the_stack_world(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The truth's position and velocity in the flight stack's world: moving along its x, 1 m
    up while airborne."""
    return (np.array([0.1 * t_s, 0.0, -1.0 if airborne(t_s) else 0.0]),
            np.array([0.1, 0.0, 0.0]))


def make_log(path: Path, with_truth: bool = True) -> None:
    log = lcm.EventLog(str(path), "w", overwrite=True)
    R_scene_flight = Rotation.from_euler("Z", START_YAW_RAD)
    q_flight_body = Rotation.identity()
    for k in range(int(END_S * 100) + 1):  # the simulator's states at 100 Hz
        t_s = k / 100
        utime = START_US + k * 10_000
        p, v = flight_in_the_stack_world(t_s)
        if with_truth:
            state = sim_state_t()
            state.utime, state.vehicle_id = utime, VEHICLE
            state.p_world_m = list(R_scene_flight.apply(p) + START_SCENE_M)
            state.v_world_m_s = list(R_scene_flight.apply(v))
            state.q_world_body = list((R_scene_flight * q_flight_body).as_quat())
            state.on_floor = not airborne(t_s)
            log.write_event(utime, f"KINFLY_{VEHICLE}_SIM_STATE", state.encode())
        if k % 10 == 0 and k < END_S * 100:  # the drone's status at 10 Hz, each sent twice
            status_us = utime + STATUS_OFFSET_US
            status_s = t_s + STATUS_OFFSET_US * 1e-6
            p, v = flight_in_the_stack_world(status_s)
            status = flight_status_t()
            status.utime, status.vehicle_id = status_us, VEHICLE
            status.mode = (flight_status_t.MODE_HOLD if FLYING_FROM_S <= status_s < AIRBORNE_TO_S
                           else flight_status_t.MODE_DISARMED)
            error_m = POSITION_OFFSET_M if airborne(status_s) else np.full(3, GROUND_ERROR_M)
            status.p_world_m = list(p + error_m)
            status.v_world_m_s = list(v + VELOCITY_OFFSET_M_S)
            status.q_world_body_xyzw = list(
                (q_flight_body * Rotation.from_euler("X", TILT_ERROR_DEG, degrees=True)).as_quat())
            status.setpoint_world_m = list(p + SETPOINT_OFFSET_M)
            for _ in range(2):
                log.write_event(status_us, f"KINFLY_{VEHICLE}_FLIGHT", status.encode())
    log.close()


def test_known_errors_are_measured_while_airborne(tmp_path: Path) -> None:
    make_log(tmp_path / "flight.lcmlog")
    figures = sim_plots.write(tmp_path, VEHICLE)
    # Statuses 0.1 s apart: the airborne time is theirs, to one status.
    assert figures["airborne_s"] == pytest.approx(AIRBORNE_TO_S - LIFT_OFF_S, abs=0.1 + TOL)
    # 2.305 s ... 7.905 s; each status counted once.
    assert figures["samples"] == 57
    assert figures["estimator_position_rms_m"] == pytest.approx(0.01, abs=TOL)
    assert figures["estimator_velocity_rms_m_s"] == pytest.approx(0.02, abs=TOL)
    # The tilt passes through arctan2 of rotated unit vectors: rounding of a few 1e-8 rad.
    assert figures["estimator_tilt_rms_deg"] == pytest.approx(TILT_ERROR_DEG, abs=1e-6)
    assert figures["tracking_rms_m"] == pytest.approx(0.03, abs=TOL)
    for name in ("tracking.png", "errors.png", "flight_errors.json"):
        assert (tmp_path / name).stat().st_size > 0, name


def test_a_log_without_the_simulators_states_is_refused(tmp_path: Path) -> None:
    make_log(tmp_path / "flight.lcmlog", with_truth=False)
    with pytest.raises(ValueError, match=f"no simulator states on KINFLY_{VEHICLE}_SIM_STATE"):
        sim_plots.write(tmp_path, VEHICLE)


def test_the_map_is_placed_by_the_first_cameras_true_pose_and_scored(tmp_path: Path) -> None:
    """A floor 4 m square as the scene; the map holds points 3 mm above it, written in the
    frame of a first camera that stood 1.5 m up, tilted and turned: the score is 3 mm only if
    the map is placed in the scene by that camera's true pose."""
    import trimesh

    floor = trimesh.Trimesh(vertices=[[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]],
                            faces=[[0, 1, 2], [0, 2, 3]], process=False)
    floor.export(tmp_path / "scene.ply")
    T_scene_cam0 = np.eye(4)
    T_scene_cam0[:3, :3] = Rotation.from_euler("ZYX", [30, 10, -100], degrees=True).as_matrix()
    T_scene_cam0[:3, 3] = [0.2, -0.3, -1.5]
    axis = np.linspace(-1, 1, 21)
    grid = np.array([[x, y, -0.003] for x in axis for y in axis])
    in_map = (grid - T_scene_cam0[:3, 3]) @ T_scene_cam0[:3, :3]
    points = trimesh.Trimesh(vertices=in_map, faces=[[0, 1, 2]], process=False)
    points.export(tmp_path / "mesh.ply")
    # The simulator's truth in the log: a frame before the odometry's first (whose pose would
    # put the map elsewhere), then that first one's.
    log = lcm.EventLog(str(tmp_path / "flight.lcmlog"), "w", overwrite=True)
    for utime, T in ((966_000, np.eye(4)), (1_000_000, T_scene_cam0)):
        truth = ground_truth_t()
        truth.utime, truth.vehicle_id = utime, VEHICLE
        truth.T_world_cam = pose3d_t()
        truth.T_world_cam.position_m = list(T[:3, 3])
        truth.T_world_cam.orientation_xyzw = list(Rotation.from_matrix(T[:3, :3]).as_quat())
        log.write_event(utime, f"KINFLY_{VEHICLE}_GROUND_TRUTH", truth.encode())
    log.close()
    (tmp_path / "drone_trajectory.tum").write_text("# odometry\n1.000 0 0 0 0 0 0 1\n")
    stats = sim_plots.map_accuracy(tmp_path, VEHICLE)
    assert stats["points"] == len(grid)
    assert stats["mean_m"] == pytest.approx(0.003, abs=1e-6)
    assert stats["outlier_fraction"] == 0.0
