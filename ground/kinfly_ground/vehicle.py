"""What the station holds about each vehicle, shared by its parts (arrivals.py on the LCM thread,
mapping.py on the worker thread, conversions.py for the status): counters, sessions and their maps
(segments)."""
from __future__ import annotations

import collections
import dataclasses
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from ._native import DroneStatus, FlightStatus, Keyframe, LinkQuality, Signer
from .submaps import Mesh, SubmapChain
from .viewer import VehicleView

StampedPose = tuple[int, np.ndarray]  # (utime [us], 4x4 T_world_cam)


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
    submaps_closed: int = 0        # by distance or time; a new one begins with the same keyframe
    submaps_after_loss: int = 0    # begun at the drone's pose after keyframes that did not register
    loop_candidates: int = 0       # closed submaps near an earlier one, checked (loops.py)
    loops_refused_by_check: int = 0  # too little overlap, residual or constraint (registration.py)
    loops_refused_by_graph: int = 0  # passed the check, inconsistent with the rest (posegraph.py)
    loops_accepted: int = 0
    loop_checks_failed: int = 0    # the check raised (logged): no loop
    merge_checks: int = 0          # this vehicle's map checked against another's (merge.py)
    merges: int = 0                # of those, found there: the maps share a world since
    merges_refused: int = 0        # not recognised, refused by the check, or stale (logged)
    merge_checks_failed: int = 0   # the check raised (logged)


@dataclasses.dataclass
class Segment:
    """One odometry frame's map (a chain of submaps) and trajectories: a drone restart starts a
    new segment. `corrected` holds the poses as corrected when each keyframe came; the chain's
    trajectory() is where the optimised graph puts them now."""
    chain: SubmapChain | None = None
    camera: tuple[Any, ...] | None = None
    onboard: list[StampedPose] = dataclasses.field(default_factory=list)
    corrected: list[StampedPose] = dataclasses.field(default_factory=list)
    ground_truth: list[StampedPose] = dataclasses.field(default_factory=list)
    # Draws the ground truth in the map's frame (None until a refined keyframe anchors it), and
    # how many of its poses have been drawn.
    T_map_truth: np.ndarray | None = None
    truth_drawn: int = 0
    # The final map (vertices, triangles, normals), meshed once for viewer and file.
    final_mesh: Mesh | None = None
    # The final ATE of each trajectory (outputs.evaluate), made once for viewer and summary.
    evaluation: dict[str, dict[str, Any]] | None = None
    # Each registered keyframe's depth made small (merge.small_depth), by capture time: the
    # map's views for a merge check, and their intrinsics (fx, fy, cx, cy).
    views: list[tuple[int, np.ndarray]] = dataclasses.field(default_factory=list)
    view_intrinsics: tuple[float, float, float, float] | None = None


@dataclasses.dataclass
class Job:
    """A keyframe waiting for the worker: the vehicle's session it arrived in, and when."""
    vehicle_id: int
    session: int
    message: Keyframe  # typed: camera, onboard pose, tracking status, depth
    arrival_ns: int  # time.monotonic_ns() when the message came off the socket


class RateMeter:
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
        self.last_chunk_s: float | None = None  # time.monotonic() of the last keyframe chunk
        # The link as the last keyframe found it (Receiver.link_quality), for the viewer.
        self.link_quality: LinkQuality | None = None
        # The drone's latest status in this session, and what the link lost in earlier ones.
        self.drone_status: DroneStatus | None = None
        # The flight stack's newest status (LCM thread), and the newest not yet drawn (taken by
        # the fusion worker with the next keyframe).
        self.flight_status: FlightStatus | None = None
        self.pending_flight: FlightStatus | None = None
        self.session_keyframe_ids: set[int] = set()
        self.lost_on_link_before = 0
        # The highest keyframe id of this session the worker is done with (fused, lost or
        # failed): the ground's status tells the drone, which waits for it at the end of a replay.
        self.last_done_keyframe_id = -1
        # Ground truth heard but not yet filed, tagged with the session it arrived in.
        self.pending_truth: list[tuple[int, int, np.ndarray]] = []
        self.rates = {name: RateMeter() for name in ("received", "fused", "corrections")}
        # pending_truth, pending_flight, segment swaps, last_done_keyframe_id
        self.lock = threading.Lock()

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


def percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None
