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

    def __init__(self, publish: Publish | None, copies: int = 1,
                 copy_interval_s: float = 0.03) -> None:
        self._publish = publish
        self._copies = copies
        self._interval_s = copy_interval_s
        # (when due [monotonic s], channel, envelope, copies still to send): the fusion thread
        # adds, the LCM thread's loop sends (send_copies).
        self._pending: list[tuple[float, str, bytes, int]] = []
        self._lock = threading.Lock()

    def send(self, state: VehicleState, m: Keyframe, T_corrected: np.ndarray,
             arrival_ns: int) -> bool:
        """Sends the correction of keyframe M; the latency is counted from ARRIVAL_NS. Whether
        it went out (not in a replay, nor to a vehicle without a key)."""
        if self._publish is not None and state.signer is None:
            state.counters.corrections_unsigned += 1
            return False
        if self._publish is not None:
            envelope = state.signer.sign_correction(m.keyframe_id, m.utime, T_corrected,
                                                    state.reset_counter)
            channel = channel_name(Channel.CORRECTION, m.vehicle_id)
            self._publish(channel, envelope)
            if self._copies > 1:
                with self._lock:
                    self._pending.append((time.monotonic() + self._interval_s, channel,
                                          envelope, self._copies - 1))
            state.counters.corrections_sent += 1
            state.rates["corrections"].tick(time.monotonic())
        # Replay has nothing to send: its latency is the time to refine and fuse.
        state.latencies_ms.append((time.monotonic_ns() - arrival_ns) / 1e6)
        return self._publish is not None

    def send_copies(self, now_s: float) -> None:
        """The copies due by NOW_S (monotonic), each once; the LCM thread's loop calls this
        every turn (at least every 20 ms)."""
        if self._publish is None:
            return
        with self._lock:
            due = [p for p in self._pending if p[0] <= now_s]
            if not due:
                return
            self._pending = [p for p in self._pending if p[0] > now_s] + [
                (t + self._interval_s, c, e, n - 1) for t, c, e, n in due if n > 1]
        for _, channel, envelope, _ in due:
            self._publish(channel, envelope)
