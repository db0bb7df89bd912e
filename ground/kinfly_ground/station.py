"""The ground station's core: one map per vehicle, fed with the keyframes the Receiver passed.

Threads: keyframes arrive on the LCM thread (`on_message`), which only decodes, checks,
classifies them (duplicate, out of order, a restarted drone) and puts them in a bounded queue:
nothing slow runs there (no viewer, no files, no fusion), or the next keyframes would wait in
LCM's buffers until they overflow. One worker thread refines and fuses them (the native code
releases the GIL), publishes the signed correction at once and only then logs to the viewer; a
low-priority mesher thread meshes copies of the map every few seconds, so marching cubes never
holds up a correction (the threads and the queue are runner.py's). `replay` runs the same steps
on the caller's thread (`inline=True`): every keyframe, nothing dropped.

Losses are counted where they happen: the drone's own (its status: frames its odometry could not
keep up with, keyframes its link could not send), the link's (keyframe ids the drone's status says
it sent that never arrived: `lost_on_link`), and the station's (`keyframes_dropped` from a full
queue, `keyframes_lost` that could not be refined).

Queue: at most `queue_keyframes` keyframes wait (32: about 6 s of keyframes at 5 Hz), so a
laptop busy with other work for a few seconds delays corrections but loses no keyframe from the
map; beyond that the oldest is dropped and counted (runner.py).
"""
from __future__ import annotations

import collections
import dataclasses
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from kinfly import ground_status_t

from ._native import (Channel, DroneStatus, Fusion, Keyframe, MapSnapshot, Receiver, Signer,
                      StampedPose as ReceivedPose, TrackingStatus, channel_name,
                      rotation_angle_rad)
from .conversions import ground_status
from .outputs import ATE_MAX_TIME_DIFF_S, evaluate
from .runner import Runner
from .viewer import VehicleView, Viewer

Publish = Callable[[str, bytes], None]
Forward = Callable[[int, np.ndarray, int], None]  # (utime, T_world_cam, reset_counter)
StampedPose = tuple[int, np.ndarray]  # (utime [us], 4x4 T_world_cam)


@dataclasses.dataclass(frozen=True)
class StationParams:
    voxel_size_m: float = 0.01          # [m] (0.002, 0.1]: the full-resolution map's voxel
    threads: int = 2                    # [1, 64] engine threads for fusion
    queue_keyframes: int = 32           # [1, 1000] keyframes waiting to be fused (then drop oldest)
    # A correction that moves the drone's pose further than this is a jump: reset_counter + 1,
    # which tells consumers such as an autopilot's EKF to re-initialise rather than fuse it.
    reset_translation_m: float = 0.05   # [m] > 0
    reset_rotation_rad: float = math.radians(3.0)  # [rad] > 0
    # A keyframe id below the last one is a late (reordered) keyframe when within this many of
    # it and of close capture time, otherwise the drone restarted (ids from zero, new frame).
    reorder_window: int = 8             # [0, 1000] keyframes
    reorder_window_s: float = 5.0       # [s] > 0
    mesh_interval_s: float = 5.0        # [s] >= 0.5 between meshes sent to the viewer; 0: none
    max_vehicles: int = 16              # [1, 1000] maps held when serving every vehicle

    def validate(self) -> str:
        checks = [
            (0.002 < self.voxel_size_m <= 0.1, "voxel size must be in (0.002, 0.1] m"),
            (1 <= self.threads <= 64, "threads must be in [1, 64]"),
            (1 <= self.queue_keyframes <= 1000, "queue must be in [1, 1000] keyframes"),
            (self.reset_translation_m > 0, "reset translation must be > 0 m"),
            (self.reset_rotation_rad > 0, "reset rotation must be > 0"),
            (0 <= self.reorder_window <= 1000, "reorder window must be in [0, 1000] keyframes"),
            (self.reorder_window_s > 0, "reorder window must be > 0 s"),
            (self.mesh_interval_s == 0 or self.mesh_interval_s >= 0.5,
             "mesh interval must be 0 (off) or >= 0.5 s"),
            (1 <= self.max_vehicles <= 1000, "max vehicles must be in [1, 1000]"),
        ]
        return next((why for ok, why in checks if not ok), "")


@dataclasses.dataclass
class VehicleCounters:
    keyframes_received: int = 0    # passed the Receiver's checks
    lost_on_link: int = 0          # sent by the drone (its status says) but never received
    keyframes_fused: int = 0       # refined (or the first of a map) and fused
    keyframes_lost: int = 0        # the refinement failed: not fused, no correction
    keyframes_dropped: int = 0     # the queue was full (oldest dropped)
    duplicates: int = 0            # the same keyframe id and capture time again
    out_of_order: int = 0          # older than one already received
    drone_restarts: int = 0        # keyframe ids started again from zero
    camera_changes: int = 0        # a keyframe with other intrinsics: the map starts again
    corrections_sent: int = 0
    corrections_unsigned: int = 0  # not sent: no key for this vehicle
    resets: int = 0                # corrections beyond the jump threshold
    failed: int = 0                # keyframes whose handling raised (logged): the station goes on


@dataclasses.dataclass
class Segment:
    """One odometry frame's map and trajectories: a drone restart starts a new segment."""
    fusion: Fusion | None = None
    camera: tuple[Any, ...] | None = None
    onboard: list[StampedPose] = dataclasses.field(default_factory=list)
    corrected: list[StampedPose] = dataclasses.field(default_factory=list)
    ground_truth: list[StampedPose] = dataclasses.field(default_factory=list)
    # Draws the ground truth in the map's frame (None until a refined keyframe anchors it), and
    # how many of its poses have been drawn.
    T_map_truth: np.ndarray | None = None
    truth_drawn: int = 0
    snapshot: MapSnapshot | None = None  # the final map's copy, meshed once for viewer and file
    # The final ATE of each trajectory (outputs.evaluate), made once for viewer and summary.
    evaluation: dict[str, dict[str, Any]] | None = None


@dataclasses.dataclass
class _Job:
    vehicle_id: int
    session: int
    message: Keyframe
    arrival_ns: int  # time.monotonic_ns() when the message came off the socket


class _RateMeter:
    """Events per second over the last WINDOW_S."""

    WINDOW_S = 2.0

    def __init__(self) -> None:
        self._times: collections.deque[float] = collections.deque()

    def tick(self, now_s: float) -> None:
        self._times.append(now_s)

    def rate_hz(self, now_s: float) -> float:
        while self._times and self._times[0] < now_s - self.WINDOW_S:
            self._times.popleft()
        return len(self._times) / self.WINDOW_S


class VehicleState:
    """Everything the station holds about one vehicle. Fields written by the worker are read by
    the other threads only for status and progress, where a value one keyframe old is fine."""

    def __init__(self, vehicle_id: int, make_view: Callable[[], VehicleView],
                 signer: Signer | None) -> None:
        self.vehicle_id = vehicle_id
        self._make_view = make_view
        self._view: VehicleView | None = None
        self.signer = signer
        self.counters = VehicleCounters()
        self.segment = Segment()
        self.finished_segments: list[Segment] = []
        self.reset_counter = 0
        self.latencies_ms: list[float] = []
        self.refine_ms: list[float] = []
        self.last_result: Any = None
        self.mesh_utime: int | None = None  # capture time of the last mesh sent to the viewer
        # Written by the fusion thread: the map itself must not be read while a refine runs.
        self.map_blocks = 0
        # The latest correction as a transform: the drone's odometry frame into the map's.
        self.T_map_onboard = np.eye(4)
        # Arrival side (LCM thread only).
        self.session = 0
        self.last_keyframe: tuple[int, int] | None = None  # (keyframe_id, utime)
        self.worker_session = 0
        self.drone_heard_s: float | None = None
        # The drone's latest status in this session, and what the link lost in earlier ones.
        self.drone_status: DroneStatus | None = None
        self.session_keyframe_ids: set[int] = set()
        self.lost_on_link_before = 0
        # The highest keyframe id of this session the worker is done with (fused, lost or
        # failed): the ground's status tells the drone, which waits for it at the end of a replay.
        self.last_done_keyframe_id = -1
        # Ground truth heard but not yet filed, tagged with the session it arrived in.
        self.pending_truth: list[tuple[int, int, np.ndarray]] = []
        self.rates = {name: _RateMeter() for name in ("received", "fused", "corrections")}
        self.lock = threading.Lock()  # pending_truth, segment swaps, last_done_keyframe_id

    @property
    def view(self) -> VehicleView:
        """Made at first use, on the fusion thread (or at start by a station serving one
        vehicle): rerun takes up to a second to set one up, which the LCM thread must not wait
        for."""
        if self._view is None:
            self._view = self._make_view()
        return self._view

    def lost_on_link_now(self) -> int:
        """Keyframes this session's drone says it sent, up to the last id it reported, that did
        not arrive; plus the earlier sessions'. LCM thread."""
        d = self.drone_status
        if d is None:
            return self.lost_on_link_before
        heard = sum(1 for i in self.session_keyframe_ids if i <= d.last_keyframe_id)
        return self.lost_on_link_before + max(0, d.keyframes_sent - heard)


def jump_exceeds(delta: np.ndarray, translation_m: float, rotation_rad: float) -> bool:
    """Whether the rigid transform DELTA moves further than either bound."""
    return bool(np.linalg.norm(delta[:3, 3]) > translation_m
                or rotation_angle_rad(delta) > rotation_rad)


def truth_anchor(corrected: list[StampedPose], truth: list[StampedPose]) -> np.ndarray | None:
    """T_map_truth that puts the ground truth on the first corrected keyframe that has a
    ground-truth pose within ATE_MAX_TIME_DIFF_S of its capture time; None while none has."""
    if not truth:
        return None
    truth_utimes = np.array([utime for utime, _ in truth])
    for utime, T_map_cam in corrected:
        nearest = int(np.argmin(np.abs(truth_utimes - utime)))
        if abs(truth_utimes[nearest] - utime) <= ATE_MAX_TIME_DIFF_S * 1e6:
            return T_map_cam @ np.linalg.inv(truth[nearest][1])
    return None


def percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


class Station:
    """Maps keyframes into per-vehicle maps and publishes corrections. PUBLISH sends an encoded
    message on a channel (None: nothing is sent, as in replay). SIGNERS maps a vehicle id to its
    signer; a vehicle without one is mapped but gets no corrections. VEHICLE_ID None serves every
    vehicle (each under its own viewer prefix)."""

    def __init__(self, params: StationParams, viewer: Viewer, *, vehicle_id: int | None,
                 signers: dict[int, Signer], publish: Publish | None, inline: bool = False,
                 forward: Forward | None = None, log: Callable[[str], None] = print) -> None:
        """A station serving one vehicle (VEHICLE_ID) sets up its view here, before it can be
        announced ready, so its first keyframe does not wait for it."""
        if why := params.validate():
            raise ValueError(why)
        self.params = params
        self.viewer = viewer
        self.vehicle_id = vehicle_id
        self._signers = signers
        self._publish = publish
        self._forward = forward
        self._log = log
        self.vehicles: dict[int, VehicleState] = {}
        self.rejected_too_many_vehicles = 0
        self.handler_errors = 0
        self.receiver = Receiver()
        self._arrival_ns = 0
        if vehicle_id is not None:
            # Made now, not at the first keyframe: the vehicle's state asks the viewer again then
            # and gets this one.
            viewer.vehicle(vehicle_id, "")
        self.runner: Runner[_Job] = Runner(params.queue_keyframes, self._process_guarded,
                                           self._on_dropped, inline=inline, log=log)

    # --- arrival (LCM thread) -----------------------------------------------------------------

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
        if signer is None and self._publish is not None:
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
        elif channel is Channel.STATUS:
            state.drone_heard_s = now_s
            self._on_drone_status(state, message)
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
        self.runner.submit(_Job(state.vehicle_id, state.session, message, self._arrival_ns))

    def _on_dropped(self, job: _Job) -> None:
        self.vehicles[job.vehicle_id].counters.keyframes_dropped += 1

    # --- fusion (worker thread) ---------------------------------------------------------------

    def _process_guarded(self, job: _Job) -> None:
        """One keyframe that cannot be handled (intrinsics the engine refuses, say) is counted
        and logged; the next one is fused as usual."""
        state = self.vehicles[job.vehicle_id]
        try:
            self._process(job)
        except Exception as error:
            state.counters.failed += 1
            self._log(f"vehicle {job.vehicle_id}: keyframe {job.message.keyframe_id} not "
                      f"handled: {type(error).__name__}: {error}")
        with state.lock:
            if job.session == state.session:
                state.last_done_keyframe_id = max(state.last_done_keyframe_id,
                                                  job.message.keyframe_id)

    def _process(self, job: _Job) -> None:
        state = self.vehicles[job.vehicle_id]
        m = job.message
        c = m.camera
        camera = (c.width, c.height, c.fx, c.fy, c.cx, c.cy, m.depth_scale_m)
        if job.session != state.worker_session:
            state.worker_session = job.session
            self._new_segment(state, m.utime)
        elif state.segment.camera is not None and state.segment.camera != camera:
            state.counters.camera_changes += 1
            self._log(f"vehicle {state.vehicle_id}: the camera changed "
                      f"({state.segment.camera[:6]} -> {camera[:6]}); starting a new map")
            self._new_segment(state, m.utime)
        segment = state.segment
        if segment.fusion is None:
            segment.camera = camera
            segment.fusion = Fusion(c, m.depth_scale_m,
                                    voxel_size_m=self.params.voxel_size_m,
                                    threads=self.params.threads)
        has_onboard = m.tracking is not None
        if has_onboard:
            T_onboard = m.T_world_cam
        else:
            # No onboard pose (its fields are meaningless): start from the last refined one.
            T_onboard = segment.corrected[-1][1] if segment.corrected else np.eye(4)
        depth = m.depth
        result = segment.fusion.refine(depth, m.utime, T_onboard)
        state.map_blocks = segment.fusion.num_blocks
        state.refine_ms.append(result.total_ms)
        state.last_result = result
        if has_onboard:
            segment.onboard.append((m.utime, T_onboard))
        T_corrected = None
        if result.status in (TrackingStatus.FIRST_FRAME, TrackingStatus.OK):
            T_corrected = result.T_world_cam
            segment.corrected.append((m.utime, T_corrected))
            state.counters.keyframes_fused += 1
            state.rates["fused"].tick(time.monotonic())
            self._send_correction(state, m, T_onboard, T_corrected, job.arrival_ns)
        else:
            state.counters.keyframes_lost += 1
            self._log(f"vehicle {state.vehicle_id}: keyframe {m.keyframe_id} not refined "
                      f"({result.lost_reason}); no correction")
        self._show(state, m, depth, T_onboard, T_corrected, result)

    def _send_correction(self, state: VehicleState, m: Keyframe, T_onboard: np.ndarray,
                         T_corrected: np.ndarray, arrival_ns: int) -> None:
        # The move in the camera's own frame: its translation is the distance between the two
        # poses, however far from the origin the drone is.
        if jump_exceeds(np.linalg.inv(T_onboard) @ T_corrected, self.params.reset_translation_m,
                        self.params.reset_rotation_rad):
            state.reset_counter += 1
            state.counters.resets += 1
        state.T_map_onboard = T_corrected @ np.linalg.inv(T_onboard)
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

    def _show(self, state: VehicleState, m: Keyframe, depth: np.ndarray,
              T_onboard: np.ndarray, T_corrected: np.ndarray | None, result: Any) -> None:
        self._file_truth(state)
        c = m.camera
        state.view.keyframe(m.utime, depth, m.depth_scale_m, (c.fx, c.fy, c.cx, c.cy), T_onboard,
                            T_corrected)
        fusion = state.segment.fusion
        if result.status is TrackingStatus.OK:
            # The map as raycast for this keyframe's registration, from its onboard pose (a few
            # mm from the refined one) where it measured depth; a map's first keyframe has none.
            state.view.render(m.utime, fusion.render())
        # What the viewer's two plots show (viewer._layout): the keyframes' fate as the progress
        # line counts it, and how well the ground registered them. The other counters are in
        # summary.json; a first keyframe is not registered, so it has no tracking figures.
        counters = state.counters
        health = {
            "link/received": float(counters.keyframes_received),
            "link/lost_on_link": float(counters.lost_on_link),
            "link/fused": float(counters.keyframes_fused),
            "link/not_refined": float(counters.keyframes_lost),
            "link/dropped": float(counters.keyframes_dropped),
        }
        if T_corrected is not None and state.latencies_ms:
            health["link/latency_ms"] = state.latencies_ms[-1]
        if result.status is not TrackingStatus.FIRST_FRAME:
            health["tracking/inlier_fraction"] = result.inlier_fraction
            health["tracking/rmse_mm"] = result.rmse_m * 1e3
        state.view.health(m.utime, health)
        # By capture time, which runs at the wall clock's pace in flight and at the log's in a
        # replay.
        interval_us = self.params.mesh_interval_s * 1e6
        if interval_us > 0 and (state.mesh_utime is None
                                or m.utime - state.mesh_utime >= interval_us):
            state.mesh_utime = m.utime
            self.runner.mesh(state, m.utime, fusion.snapshot())

    def _file_truth(self, state: VehicleState) -> None:
        """Ground truth goes with the map of the session it arrived in: a restarted drone's
        poses are in another frame, and a replayed log repeats the capture times."""
        with state.lock:
            pending = [e for e in state.pending_truth if e[0] <= state.worker_session]
            state.pending_truth = [e for e in state.pending_truth if e[0] > state.worker_session]
        for session, utime, T in pending:
            if session == state.worker_session:
                state.segment.ground_truth.append((utime, T))
            elif session < state.worker_session and state.finished_segments:
                state.finished_segments[-1].ground_truth.append((utime, T))
        self._draw_truth(state)

    def _draw_truth(self, state: VehicleState) -> None:
        """Ground truth has a frame of its own (a recording's starts at its first sample, which
        need not be the first keyframe's time), so it is drawn in the map's frame, anchored at the
        first refined keyframe with a ground-truth pose at its capture time; poses heard before
        that wait. At the end it is drawn again as the ATE aligns it (cli._finish)."""
        segment = state.segment
        if segment.T_map_truth is None:
            segment.T_map_truth = truth_anchor(segment.corrected, segment.ground_truth)
            if segment.T_map_truth is None:
                return
        for utime, T in segment.ground_truth[segment.truth_drawn:]:
            state.view.ground_truth(utime, segment.T_map_truth @ T)
        segment.truth_drawn = len(segment.ground_truth)

    def _new_segment(self, state: VehicleState, utime: int) -> None:
        with state.lock:
            if state.segment.fusion is not None:
                state.finished_segments.append(state.segment)
            state.segment = Segment()
        state.view.restarted(utime)

    # --- control (any thread) -----------------------------------------------------------------

    def run_in_worker(self, request: Callable[[], None]) -> None:
        """Runs REQUEST on the fusion thread between keyframes (an export on request), where the
        maps are not being changed."""
        self.runner.run_in_worker(request)

    def drain(self, timeout_s: float) -> bool:
        """Waits until every queued keyframe is fused; False when TIMEOUT_S passed first."""
        return self.runner.drain(timeout_s)

    def stop(self) -> None:
        self.runner.stop()

    def queue_length(self) -> int:
        return self.runner.queue_length()

    def show_final(self, truth: list[StampedPose] | None) -> None:
        """Sends every vehicle's map to the viewer as it is at the end, stamped with its last
        keyframe (the periodic meshes miss whatever came after the last one), and its ground
        truth (TRUTH, else what the drone sent) as the ATE aligns it with the corrected
        trajectory: the frame the evaluation compares them in. Call after stop()."""
        for state in self.vehicles.values():
            segment = state.segment
            if segment.fusion is None or not segment.corrected:
                continue
            last_utime = segment.corrected[-1][0]
            segment.snapshot = segment.fusion.snapshot()
            state.view.mesh(last_utime, *segment.snapshot.mesh())
            segment_truth = truth if truth is not None else segment.ground_truth
            segment.evaluation = evaluate({"onboard": segment.onboard,
                                           "corrected": segment.corrected}, segment_truth)
            if "corrected" in segment.evaluation:
                T_map_truth = np.linalg.inv(segment.evaluation["corrected"]["T_truth_estimate"])
                state.view.ground_truth_aligned(
                    last_utime, np.array([(T_map_truth @ T)[:3, 3] for _, T in segment_truth]))

    # --- status -------------------------------------------------------------------------------

    def ground_status(self, state: VehicleState, now_s: float, link_timeout_s: float,
                      run_state: int = ground_status_t.RUN_ACTIVE) -> ground_status_t:
        if state.drone_heard_s is None:
            link_state = ground_status_t.LINK_UNKNOWN
        elif now_s - state.drone_heard_s <= link_timeout_s:
            link_state = ground_status_t.LINK_UP
        else:
            link_state = ground_status_t.LINK_STALE
        result = state.last_result
        return ground_status(
            state.vehicle_id, run_state=run_state, link_state=link_state, counters=state.counters,
            rates_hz={name: meter.rate_hz(now_s) for name, meter in state.rates.items()},
            last_keyframe_id=state.last_done_keyframe_id,
            tracking=None if result is None else result.status, rejects=self.receiver.rejects)
