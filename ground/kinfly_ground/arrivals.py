"""Arrivals (the LCM thread): every received message goes through the native Receiver (the link's
C++: channel, bounded decoding, keyframe chunks, depth), then keyframes are classified against the
vehicle's last one (duplicate, late, a restarted drone: a new session) and handed to the worker;
the drone's status tells what the link lost; odometry is forwarded to an autopilot, corrected.
Nothing slow runs here (no viewer, no files, no fusion), or the next keyframes would wait in LCM's
buffers until they overflow.

Repairs (a station that sends): the chunks of a keyframe that did not all arrive are asked for
again as soon as a chunk of a newer keyframe shows that the drone has moved on; the newest
keyframe's once the drone's status says it was sent and no chunk has arrived for
StationParams.repair_quiet_s. A group still incomplete is asked for again after
StationParams.repair_retry_s, up to repair_asks times (the Receiver keeps count)."""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ._native import (Channel, DroneStatus, FlightStatus, Keyframe, Receiver, Signer,
                      channel_name)
from .flight import answer, mode_name
from ._native import StampedPose as ReceivedPose
from .uplink import Publish
from .viewer import Viewer
from .vehicle import Job, VehicleState

Forward = Callable[[int, np.ndarray, int], None]  # (utime, T_world_cam, reset_counter)


class Arrivals:
    """SUBMIT hands a keyframe to the worker. SIGNERS, PUBLISH: see Station (PUBLISH sends the
    repair requests here)."""

    def __init__(self, params: Any, viewer: Viewer, *, vehicle_id: int | None,
                 signers: dict[int, Signer], publish: Publish | None, forward: Forward | None,
                 submit: Callable[[Job], None], log: Callable[[str], None]) -> None:
        self.params = params
        self.viewer = viewer
        self.vehicle_id = vehicle_id
        self._signers = signers
        self._publish = publish
        self._sends = publish is not None
        self._forward = forward
        self._submit = submit
        self._log = log
        self.vehicles: dict[int, VehicleState] = {}
        self.rejected_too_many_vehicles = 0
        self.handler_errors = 0
        self.receiver = Receiver(repair_max_asks=params.repair_asks,
                                 repair_retry_s=params.repair_retry_s)
        self._arrival_ns = 0

    def on_message(self, channel: str, data: bytes) -> None:
        # The arrival is stamped when Python gets the message: time spent waiting for the GIL
        # before that is not in the latency.
        self._arrival_ns = time.monotonic_ns()
        try:
            received = self.receiver.receive(channel, data)
            if received is not None:
                self._on_received(*received)
        except Exception as error:  # a message that passed decoding but broke a handler
            self.handler_errors += 1
            self._log(f"{channel}: message not handled: {type(error).__name__}: {error}")

    def _vehicle(self, vehicle_id: int) -> VehicleState | None:
        state = self.vehicles.get(vehicle_id)
        if state is not None:
            return state
        if self.vehicle_id is not None and vehicle_id != self.vehicle_id:
            return None  # the subscription only lets this vehicle through; belt and braces
        if len(self.vehicles) >= self.params.max_vehicles:
            self.rejected_too_many_vehicles += 1
            return None
        prefix = "" if self.vehicle_id is not None else f"vehicle_{vehicle_id}/"
        signer = self._signers.get(vehicle_id)
        if signer is None and self._sends:
            self._log(f"vehicle {vehicle_id}: no key, so its keyframes are mapped but no "
                      "corrections are sent")
        state = VehicleState(vehicle_id, lambda: self.viewer.vehicle(vehicle_id, prefix), signer)
        self.vehicles[vehicle_id] = state
        return state

    def _on_received(self, channel: Channel, vehicle_id: int, message: Any) -> None:
        """What the native Receiver let through: a Keyframe, the drone's status, a pose
        (odometry, ground truth) or None (an IMU sample)."""
        state = self._vehicle(vehicle_id)
        if state is None:
            return
        now_s = time.monotonic()
        if channel is Channel.KEYFRAME:
            self._on_keyframe(state, message, now_s)
        elif channel is Channel.KEYFRAME_CHUNK:
            self._on_chunk(state, message, now_s)
        elif channel is Channel.STATUS:
            state.drone_heard_s = now_s
            self._on_drone_status(state, message)
            self._repair_newest(state, message, now_s)
        elif channel is Channel.FLIGHT:
            state.drone_heard_s = now_s
            self._on_flight_status(state, message)
        elif channel is Channel.GROUND_TRUTH:
            with state.lock:
                state.pending_truth.append((state.session, message.utime, message.T_world_cam))
        elif channel in (Channel.ODOMETRY, Channel.IMU, Channel.DEPTH):
            state.drone_heard_s = now_s
            if channel is Channel.ODOMETRY and self._forward is not None:
                self._forward_odometry(state, message)

    def _on_drone_status(self, state: VehicleState, message: DroneStatus) -> None:
        last = state.drone_status
        if last is not None and message.keyframes_sent < last.keyframes_sent:
            # A restarted drone, before its first keyframe has started a new session here: its
            # counters count from zero again and are not this session's.
            return
        state.drone_status = message
        state.counters.lost_on_link = state.lost_on_link_now()
        if message.final and (last is None or not last.final):
            self._log(f"vehicle {state.vehicle_id}: the drone stopped: it sent "
                      f"{message.keyframes_sent} keyframes (ids up to "
                      f"{message.last_keyframe_id}); {state.counters.lost_on_link} lost on the "
                      f"link; {message.queue_drops} frames its odometry could not keep up with, "
                      f"{message.keyframes_dropped} keyframes its link could not send")

    def _on_flight_status(self, state: VehicleState, message: FlightStatus) -> None:
        """Logs the mode's changes and the answers to commands; the fusion worker draws it."""
        last = state.flight_status
        state.flight_status = message
        with state.lock:
            state.pending_flight = message
        if last is None or message.mode != last.mode:
            self._log(f"vehicle {state.vehicle_id}: flight mode {mode_name(message.mode)}")
        if message.command_id >= 0 and (last is None or message.command_id != last.command_id):
            self._log(f"vehicle {state.vehicle_id}: command {message.command_id} "
                      f"{answer(message.command_result)}")

    def _on_chunk(self, state: VehicleState, message: Keyframe | None, now_s: float) -> None:
        """A keyframe chunk; MESSAGE is the keyframe it completed, if it did."""
        state.drone_heard_s = state.last_chunk_s = now_s
        if message is not None:
            self._on_keyframe(state, message, now_s)
        # The Receiver leaves the newest keyframe out: only older ones, which the drone has
        # finished sending, are asked for here.
        self._send_repairs(state.vehicle_id, include_newest=False)

    def _repair_newest(self, state: VehicleState, drone: DroneStatus, now_s: float) -> None:
        """The newest keyframe's missing chunks, once the drone says it sent that keyframe (or a
        later one) and the chunks have stopped coming."""
        if (not self._sends or state.last_chunk_s is None
                or now_s - state.last_chunk_s < self.params.repair_quiet_s):
            return
        link = self.receiver.link_quality(state.vehicle_id)
        if link is not None and 0 <= link.newest_keyframe_id <= drone.last_keyframe_id:
            self._send_repairs(state.vehicle_id, include_newest=True)

    def _send_repairs(self, vehicle_id: int, *, include_newest: bool) -> None:
        if self._publish is None:
            return
        for request in self.receiver.repair_requests(vehicle_id, include_newest):
            self._publish(channel_name(Channel.CHUNK_REQUEST, vehicle_id), request)

    def _forward_odometry(self, state: VehicleState, message: ReceivedPose) -> None:
        """The drone's pose at the camera's rate, corrected: a drone that applies the ground's
        corrections (its status says so) already sends it re-anchored; for one that does not
        (no key, a wrong one) the ground's latest correction is applied here."""
        T = message.T_world_cam
        drone = state.drone_status
        if drone is not None and drone.corrections_accepted > 0:
            self._forward(message.utime, T, message.reset_counter)
        else:
            self._forward(message.utime, state.T_map_onboard @ T, state.reset_counter)

    def _on_keyframe(self, state: VehicleState, message: Keyframe, now_s: float) -> None:
        state.drone_heard_s = now_s
        key = (message.keyframe_id, message.utime)
        last = state.last_keyframe
        if last is not None and key == last:
            state.counters.duplicates += 1
            return
        if last is not None and message.keyframe_id <= last[0]:
            late = (message.keyframe_id != 0
                    and last[0] - message.keyframe_id <= self.params.reorder_window
                    and abs(message.utime - last[1]) <= self.params.reorder_window_s * 1e6)
            if late:
                # Its correction would be older than one the drone already applied.
                state.counters.out_of_order += 1
                state.session_keyframe_ids.add(message.keyframe_id)
                return
            state.lost_on_link_before = state.lost_on_link_now()
            state.drone_status = None
            state.session_keyframe_ids = set()
            with state.lock:
                state.session += 1
                state.last_done_keyframe_id = -1
            state.counters.drone_restarts += 1
            self._log(f"vehicle {state.vehicle_id}: keyframe {message.keyframe_id} after "
                      f"{last[0]}: the drone restarted; starting a new map")
        state.last_keyframe = key
        state.session_keyframe_ids.add(message.keyframe_id)
        state.counters.lost_on_link = state.lost_on_link_now()
        state.counters.keyframes_received += 1
        state.rates["received"].tick(now_s)
        # The link as this keyframe found it, for the viewer's link plot (mapping.py).
        state.link_quality = self.receiver.link_quality(state.vehicle_id)
        self._submit(Job(state.vehicle_id, state.session, message, self._arrival_ns))

    def on_dropped(self, job: Job) -> None:
        """A keyframe pushed out of the full queue."""
        self.vehicles[job.vehicle_id].counters.keyframes_dropped += 1
