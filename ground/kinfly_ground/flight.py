"""The drone's flight stack as its flight_status_t says (KINFLY_<vid>_FLIGHT, docs/flight.md,
"Flight telemetry"): names for its modes and for the answers to commands, and the estimate and
setpoint in the map's frame, where the viewer draws them."""
from __future__ import annotations

import numpy as np

from kinfly import flight_status_t


def _names(prefix: str) -> dict[int, str]:
    return {getattr(flight_status_t, name): name[len(prefix):].lower().replace("_", " ")
            for name in dir(flight_status_t) if name.startswith(prefix)}


ACCEPTED = flight_status_t.ACCEPTED
MODE_NAMES = _names("MODE_")
REFUSAL_NAMES = _names("REFUSED_")


def mode_name(mode: int) -> str:
    return MODE_NAMES.get(mode, f"mode {mode}")


def answer(result: int) -> str:
    """'accepted', or 'refused: <why>'."""
    if result == ACCEPTED:
        return "accepted"
    return f"refused: {REFUSAL_NAMES.get(result, f'reason {result}')}"


def in_map(status, points_world_m: np.ndarray) -> np.ndarray:
    """Points of the flight stack's world (rows) in the map's frame (the first keyframe's
    camera, the viewer's `world`), by the estimator's alignment T_world_map."""
    T_map_world = np.linalg.inv(np.asarray(status.T_world_map))
    points = np.atleast_2d(np.asarray(points_world_m, dtype=float))
    return points @ T_map_world[:3, :3].T + T_map_world[:3, 3]


def metrics(status) -> dict[str, float]:
    """The flight status as the viewer's scalars (flight/<name>)."""
    return {
        "mode": float(status.mode),
        "thrust_n": float(status.thrust_n),
        "position_std_m": float(status.position_std_m),
        "vision_age_s": float(status.vision_age_s),
        "setpoint_error_m": float(np.linalg.norm(np.subtract(status.setpoint_world_m,
                                                             status.p_world_m))),
        "failsafes": float(status.failsafe_vision_lost + status.failsafe_estimator_diverged +
                           status.failsafe_attitude_limit + status.failsafe_imu_lost +
                           status.failsafe_geofence + status.failsafe_autopilot_lost),
    }
