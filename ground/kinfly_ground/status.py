"""The ground's status for each vehicle, 10 times a second (cli.py publishes it): the counters,
rates and the last refinement, and whether the drone is heard."""
from __future__ import annotations

from kinfly import ground_status_t

from ._native import RejectCounters
from .conversions import ground_status as ground_status_message
from .vehicle import VehicleState


def ground_status(state: VehicleState, rejects: RejectCounters, now_s: float,
                  link_timeout_s: float,
                  run_state: int = ground_status_t.RUN_ACTIVE) -> ground_status_t:
    if state.drone_heard_s is None:
        link_state = ground_status_t.LINK_UNKNOWN
    elif now_s - state.drone_heard_s <= link_timeout_s:
        link_state = ground_status_t.LINK_UP
    else:
        link_state = ground_status_t.LINK_STALE
    result = state.last_result
    return ground_status_message(
        state.vehicle_id, run_state=run_state, link_state=link_state, counters=state.counters,
        rates_hz={name: meter.rate_hz(now_s) for name, meter in state.rates.items()},
        last_keyframe_id=state.last_done_keyframe_id,
        tracking=None if result is None else result.status, rejects=rejects)
