"""The Python side's one conversion file: the message the ground station fills itself, its status
for each vehicle (10 times a second; cli.py publishes it): the counters, rates and the last
refinement, whether the drone is heard, and the keyframe link's quality, from which the drone
chooses its redundancy and send budget. Everything else on the wire (channel names, bounded
decoding, keyframe chunks, depth payloads, signed corrections, reject counters) is firmware/link's
C++, through the native module."""
from __future__ import annotations

import time

from kinfly import ground_status_t

from ._native import LinkQuality, RejectCounters, tracking_code
from .vehicle import VehicleState


def ground_status(state: VehicleState, rejects: RejectCounters, link: LinkQuality | None,
                  now_s: float, link_timeout_s: float,
                  run_state: int = ground_status_t.RUN_ACTIVE) -> ground_status_t:
    """The ground's status for one vehicle as of NOW_S (time.monotonic()). LINK: the Receiver's
    link_quality for the vehicle (None before any keyframe: the link fields stay 0, the loss run
    1). The drone is LINK_UP when heard within LINK_TIMEOUT_S."""
    if state.drone_heard_s is None:
        link_state = ground_status_t.LINK_UNKNOWN
    elif now_s - state.drone_heard_s <= link_timeout_s:
        link_state = ground_status_t.LINK_UP
    else:
        link_state = ground_status_t.LINK_STALE
    counters = state.counters
    rates_hz = {name: meter.rate_hz(now_s) for name, meter in state.rates.items()}
    result = state.last_result

    s = ground_status_t()
    s.utime = time.time_ns() // 1000
    s.vehicle_id = state.vehicle_id
    s.run_state = run_state
    s.link_state = link_state
    s.keyframe_rate_hz = rates_hz["received"]
    s.fused_rate_hz = rates_hz["fused"]
    s.correction_rate_hz = rates_hz["corrections"]
    s.keyframes_received = counters.keyframes_received
    s.keyframes_skipped = counters.duplicates + counters.out_of_order
    s.keyframes_dropped = counters.keyframes_dropped
    s.keyframes_lost = counters.keyframes_lost
    s.corrections_sent = counters.corrections_sent
    s.last_keyframe_id = state.last_done_keyframe_id
    s.tracking_state = tracking_code(None if result is None else result.status)
    s.link_loss_run = 1.0
    if link is not None:
        s.link_loss = link.link_loss
        s.link_loss_run = link.link_loss_run
        s.goodput_bps = link.goodput_bps
        s.queue_delay_ms = link.queue_delay_ms
        s.redundancy = link.redundancy
        s.keyframe_age_ms = link.keyframe_age_ms
        s.chunks_received = link.chunks_received
        s.keyframes_recovered = link.keyframes_recovered
        s.keyframes_incomplete = link.keyframes_incomplete
        s.repair_requests = link.repair_requests
    s.rejected_malformed = rejects.malformed
    s.rejected_unknown_channel = rejects.unknown_channel
    s.rejected_wrong_vehicle = rejects.wrong_vehicle
    return s
