"""The ground's reading of the drone's flight status (kinfly_ground.flight): a name for every
mode and every refusal the wire defines, the answer's wording, and the estimate carried from the
flight stack's world into the map's frame the viewer draws in."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from kinfly import flight_status_t
from kinfly_ground._native import Channel, Receiver, channel_name
from kinfly_ground.flight import MODE_NAMES, REFUSAL_NAMES, answer, in_map, metrics, mode_name

VEHICLE = 5
# Rigid transforms in double precision.
EXACT_M = 1e-9


def status(T_world_map: np.ndarray) -> flight_status_t:
    m = flight_status_t()
    m.utime, m.vehicle_id, m.mode = 1_700_000_000_000_000, VEHICLE, flight_status_t.MODE_HOLD
    m.command_id, m.command_result = 3, flight_status_t.ACCEPTED
    m.estimator_initialised = True
    m.p_world_m = [1.0, 2.0, -1.5]
    m.setpoint_world_m = [1.0, 2.0, -2.0]
    m.q_world_body_xyzw = [0.0, 0.0, 0.0, 1.0]
    m.T_world_map.position_m = [float(v) for v in T_world_map[:3, 3]]
    m.T_world_map.orientation_xyzw = [
        float(v) for v in Rotation.from_matrix(T_world_map[:3, :3]).as_quat()]
    m.rotors = flight_status_t.ROTORS_NONE
    m.failsafe_vision_lost, m.failsafe_imu_lost = 1, 2
    return m


def test_every_mode_and_refusal_has_a_name() -> None:
    modes = [v for k, v in vars(flight_status_t).items() if k.startswith("MODE_")]
    assert sorted(MODE_NAMES) == sorted(modes) == list(range(len(modes)))
    assert mode_name(flight_status_t.MODE_HANDED_OVER) == "handed over"
    assert mode_name(99) == "mode 99"
    refusals = [v for k, v in vars(flight_status_t).items() if k.startswith("REFUSED_")]
    assert sorted(REFUSAL_NAMES) == sorted(refusals) == list(range(1, len(refusals) + 1))
    assert answer(flight_status_t.ACCEPTED) == "accepted"
    assert answer(flight_status_t.REFUSED_AUTOPILOT_NOT_READY) == "refused: autopilot not ready"


def test_the_estimate_goes_into_the_maps_frame_by_the_estimators_alignment() -> None:
    # The map (the first keyframe's camera: z forward, y down) seen from the gravity-aligned,
    # z-down world: the camera looked along world x, 1 m up.
    T_world_map = np.eye(4)
    T_world_map[:3, :3] = [[0.0, 0.0, 1.0],   # columns: the camera's x (right) is world y,
                           [1.0, 0.0, 0.0],   # its y (down) world z, its z (forward) world x
                           [0.0, 1.0, 0.0]]
    T_world_map[:3, 3] = [0.0, 0.0, -1.0]
    received = Receiver().receive(channel_name(Channel.FLIGHT, VEHICLE),
                                  status(T_world_map).encode())
    assert received is not None and received[0] is Channel.FLIGHT
    s = received[2]
    estimate, setpoint = in_map(s, [s.p_world_m, s.setpoint_world_m])
    for point_map, point_world in ((estimate, s.p_world_m), (setpoint, s.setpoint_world_m)):
        np.testing.assert_allclose(T_world_map[:3, :3] @ point_map + T_world_map[:3, 3],
                                   point_world, atol=EXACT_M)
    assert metrics(s)["setpoint_error_m"] == 0.5 and metrics(s)["failsafes"] == 3.0
