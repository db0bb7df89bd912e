"""The uplink: the ground's corrections, signed (the link's C++ Signer) and published on the
vehicle's correction channel; a vehicle without a key is mapped but gets none. Replay publishes
nothing."""
from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ._native import Channel, Keyframe, channel_name
from .vehicle import VehicleState

Publish = Callable[[str, bytes], None]


class Uplink:
    """PUBLISH sends an encoded message on a channel (None: nothing is sent, as in replay)."""

    def __init__(self, publish: Publish | None) -> None:
        self._publish = publish

    def send(self, state: VehicleState, m: Keyframe, T_corrected: np.ndarray,
             arrival_ns: int) -> None:
        """Sends the correction of keyframe M; the latency is counted from ARRIVAL_NS."""
        if self._publish is not None and state.signer is None:
            state.counters.corrections_unsigned += 1
            return
        if self._publish is not None:
            envelope = state.signer.sign_correction(m.keyframe_id, m.utime, T_corrected,
                                                    state.reset_counter)
            self._publish(channel_name(Channel.CORRECTION, m.vehicle_id), envelope)
            state.counters.corrections_sent += 1
            state.rates["corrections"].tick(time.monotonic())
        # Replay has nothing to send: its latency is the time to refine and fuse.
        state.latencies_ms.append((time.monotonic_ns() - arrival_ns) / 1e6)
