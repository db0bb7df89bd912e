"""The Python side's one conversion file: the messages the ground station fills itself (its
status). Everything else on the wire (channel names, bounded decoding, depth payloads, signed
corrections, reject counters) is firmware/link's C++, through the native module."""
from __future__ import annotations

import time
from typing import Any

from kinfly import ground_status_t

from ._native import RejectCounters, TrackingStatus, tracking_code


def ground_status(vehicle_id: int, *, run_state: int, link_state: int, counters: Any,
                  rates_hz: dict[str, float], last_keyframe_id: int,
                  tracking: TrackingStatus | None, rejects: RejectCounters) -> ground_status_t:
    """The ground's status for one vehicle. COUNTERS: station.VehicleCounters; RATES_HZ: the
    received, fused and corrections rates; TRACKING: the last refinement's (None before one)."""
    s = ground_status_t()
    s.utime = time.time_ns() // 1000
    s.vehicle_id = vehicle_id
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
    s.last_keyframe_id = last_keyframe_id
    s.tracking_state = tracking_code(tracking)
    s.rejected_malformed = rejects.malformed
    s.rejected_unknown_channel = rejects.unknown_channel
    s.rejected_wrong_vehicle = rejects.wrong_vehicle
    return s
