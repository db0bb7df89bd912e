"""The uplink: the ground's corrections, signed (the link's C++ Signer) and published on the
vehicle's correction channel; a vehicle without a key is mapped but gets none. Replay publishes
nothing."""
from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from ._native import Channel, Keyframe, channel_name
from .vehicle import VehicleState

Publish = Callable[[str, bytes], None]


class Uplink:
    """PUBLISH sends an encoded message on a channel (None: nothing is sent, as in replay)."""

    def __init__(self, publish: Publish | None, copies: int = 1) -> None:
        self._publish = publish
        self._copies = copies
        # (channel, envelope, copies still to send): the fusion thread adds, the status loop
        # sends (send_copies).
        self._pending: list[tuple[str, bytes, int]] = []
        self._lock = threading.Lock()

    def send(self, state: VehicleState, m: Keyframe, T_corrected: np.ndarray,
             arrival_ns: int) -> None:
        """Sends the correction of keyframe M; the latency is counted from ARRIVAL_NS."""
        if self._publish is not None and state.signer is None:
            state.counters.corrections_unsigned += 1
            return
        if self._publish is not None:
            envelope = state.signer.sign_correction(m.keyframe_id, m.utime, T_corrected,
                                                    state.reset_counter)
            channel = channel_name(Channel.CORRECTION, m.vehicle_id)
            self._publish(channel, envelope)
            if self._copies > 1:
                with self._lock:
                    self._pending.append((channel, envelope, self._copies - 1))
            state.counters.corrections_sent += 1
            state.rates["corrections"].tick(time.monotonic())
        # Replay has nothing to send: its latency is the time to refine and fuse.
        state.latencies_ms.append((time.monotonic_ns() - arrival_ns) / 1e6)

    def send_copies(self) -> None:
        """One more copy of each correction that has copies left (the status loop calls this
        with every status, 0.1 s apart: spaced copies survive a run of lost packets)."""
        if self._publish is None:
            return
        with self._lock:
            due, self._pending = self._pending, [(c, e, n - 1) for c, e, n in self._pending
                                                 if n > 1]
        for channel, envelope, _ in due:
            self._publish(channel, envelope)
