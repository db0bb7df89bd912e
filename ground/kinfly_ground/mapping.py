"""The maps (the worker thread): each keyframe is refined against its vehicle's open submap from
the drone's onboard pose and fused (the GIL released), its correction goes out at once
(uplink.py), then the viewer gets the keyframe, the render and the health figures, and every few
seconds a copy of the submap to mesh (runner.py). A submap that has gone far or long enough then
closes, and its loop candidates are checked off the keyframe path (loops.py); the loops found are
added to the chain's graph before the next keyframe, which moves the submaps (submaps.py). The
correction policy: a correction that moves the onboard pose beyond the reset bounds is a jump
(reset_counter + 1), as after a loop that moved the open submap. Ground truth is filed with the
map of the session it arrived in and drawn in the map's frame. Several vehicles' maps are checked
for a common place now and then (merge.py, in the loop checks' process); once found, the two
share a world, and every correction to either drone is in it (a jump, counted as a reset)."""
from __future__ import annotations

import dataclasses
import importlib.util
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from . import flight
from ._native import Fusion, Keyframe, MapSnapshot, TrackingStatus, rotation_angle_rad
from .loops import LoopCloser
from .merge import PlaceParams, SharedWorlds, Views, moved, recognise_place, small_depth, thinned
from .outputs import ATE_MAX_TIME_DIFF_S, evaluate
from .submaps import Submap, SubmapChain
from .uplink import Uplink
from .vehicle import Job, Segment, StampedPose, VehicleState


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


MapKey = tuple[int, int]  # (vehicle id, its segment's number): one odometry frame's map


def _map_key(state: VehicleState) -> MapKey:
    return state.vehicle_id, len(state.finished_segments)


def pair_due(params: Any, checked: dict[MapKey, tuple[int, int]] | None,
             key: MapKey, utime: int, blocks: dict[MapKey, int]) -> bool:
    """Whether a pair of maps is due a check, at KEY's map's capture time UTIME, with BLOCKS
    each map's blocks now; CHECKED: each map's capture time and blocks at the pair's last check
    (StationParams.merge_min_growth says when)."""
    if checked is None:
        return True
    elapsed_us = utime - checked[key][0]
    if elapsed_us < params.merge_interval_s * 1e6:
        return False
    grown = any(now >= (1 + params.merge_min_growth) * checked[k][1] for k, now in blocks.items())
    return grown or elapsed_us >= params.merge_max_interval_s * 1e6


def _points(parts: list[tuple[MapSnapshot, np.ndarray]]) -> np.ndarray:
    """The surface of a map's submaps, each meshed and moved by its correction."""
    clouds = [moved(np.asarray(snapshot.mesh()[0], dtype=np.float64), C) for snapshot, C in parts]
    return np.concatenate(clouds) if clouds else np.zeros((0, 3))


@dataclasses.dataclass(frozen=True, repr=False)
class MergeJob:
    """One merge check: the source map's surface sought in the target's (merge.py), each map in
    its own optimised world. Its snapshots are meshed on the checks' thread (arguments)."""
    target: MapKey
    source: MapKey
    target_parts: list[tuple[MapSnapshot, np.ndarray]]
    source_parts: list[tuple[MapSnapshot, np.ndarray]]
    target_views: Views
    source_views: Views
    params: PlaceParams

    def arguments(self) -> tuple[Any, ...]:
        # Thinned to the registration's own voxel here: a map's mesh can hold millions of
        # vertices, which the process would be sent whole.
        voxel = self.params.registration.downsampling_m
        return (thinned(_points(self.target_parts), voxel), self.target_views,
                thinned(_points(self.source_parts), voxel), self.source_views, self.params)

    def __str__(self) -> str:
        return f"of vehicles {self.target[0]} and {self.source[0]}"


class Mapper:
    """Handles queued keyframes (`process`, on the worker thread). MESH hands a submap's copy
    (vehicle, capture time, submap index, snapshot) to the mesher. MERGES: the vehicles' maps are
    checked for a common place (a station serving every vehicle); SHOW_SHARED tells the viewer which
vehicles' maps share a world (groups of vehicle ids) after each merge."""

    def __init__(self, params: Any, vehicles: dict[int, VehicleState], uplink: Uplink,
                 mesh: Callable[[VehicleState, int, int, MapSnapshot], None],
                 log: Callable[[str], None], merges: bool = False,
                 show_shared: Callable[[list[list[int]]], None] = lambda groups: None) -> None:
        self.params = params
        self.vehicles = vehicles
        self._uplink = uplink
        self._mesh = mesh
        self._log = log
        self.loops = LoopCloser(log)
        self.worlds = SharedWorlds()
        self._merges = merges and self._can_merge(log)
        self._show_shared = show_shared
        self._no_views: set[int] = set()  # vehicles told their keyframes make no views
        # The last check of each pair of maps: each map's capture time and blocks then.
        self._pair_checked: dict[frozenset[MapKey], dict[MapKey, tuple[int, int]]] = {}
        self._merge_pending = False  # one merge check at a time, beside the loops
        # The depth range a map fuses, which its views keep (once, not per keyframe).
        preprocess = params.pipeline_params().preprocess
        self._view_range_m = (preprocess.min_depth_m, preprocess.max_depth_m)

    @staticmethod
    def _can_merge(log: Callable[[str], None]) -> bool:
        """Whether place recognition can run here (kiss_matcher: PyPI has it for x86_64 only);
        said once where it cannot, rather than a failed check every merge_interval_s."""
        if importlib.util.find_spec("kiss_matcher") is not None:
            return True
        log("the kiss_matcher package is not installed (PyPI has it for x86_64 only): "
            "the vehicles' maps will not be merged")
        return False

    def process(self, job: Job) -> None:
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

    def _process(self, job: Job) -> None:
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
        if segment.chain is None:
            segment.camera = camera
            pipeline = self.params.pipeline_params()
            pipeline.preprocess.depth_scale_m = m.depth_scale_m
            volume = self.params.volume_params()
            segment.chain = SubmapChain(self.params.submaps, lambda: Fusion(
                c, volume, pipeline, threads=self.params.threads))
        chain = segment.chain
        self._take_merges()
        self._add_loops(state, chain, m.utime)
        has_onboard = m.tracking is not None
        if has_onboard:
            T_onboard = m.T_world_cam
        else:
            # No onboard pose (its fields are meaningless): start from the last refined one, in
            # the world the drone's poses are in.
            T_onboard = chain.last_pose_published()
        depth = m.depth
        result, T_corrected, closed = chain.refine(depth, m.utime, T_onboard)
        if closed is not None:
            state.counters.submaps_after_loss += 1
            self._log(f"vehicle {state.vehicle_id}: keyframe {m.keyframe_id} begins submap "
                      f"{chain.active.index} at the drone's pose: "
                      f"{self.params.submaps.new_after_lost} keyframes in a row did not register")
        state.map_blocks = chain.num_blocks
        state.refine_ms.append(result.total_ms)
        state.last_result = result
        # The trajectories are kept in the map's own world, a merge's jump taken out: the drone's
        # pose in the world its guess came from, the correction in the one it goes out in.
        if has_onboard:
            segment.onboard.append((m.utime, np.linalg.inv(chain.guess_placement) @ T_onboard))
        if T_corrected is not None:
            segment.corrected.append((m.utime, np.linalg.inv(chain.placement) @ T_corrected))
            self._keep_view(state, m, depth)
            state.counters.keyframes_fused += 1
            state.rates["fused"].tick(time.monotonic())
            if self._correct(state, m, T_onboard, chain.guess_moved @ T_onboard, T_corrected,
                             job.arrival_ns):
                chain.correction_sent()
        else:
            state.counters.keyframes_lost += 1
            self._log(f"vehicle {state.vehicle_id}: keyframe {m.keyframe_id} not refined "
                      f"({result.lost_reason}); no correction")
        self._show(state, m, depth, T_onboard, T_corrected, result)
        # After the correction went out and the viewer has the keyframe: closing a submap
        # snapshots it and begins the next with this keyframe.
        if closed is None:
            closed = chain.close_if_due(depth, m.utime)
            if closed is not None:
                state.counters.submaps_closed += 1
        if closed is not None:
            self._closed(state, chain, closed, m.utime)
        self._merge_if_due(state, m.utime)

    def _keep_view(self, state: VehicleState, m: Keyframe, depth: np.ndarray) -> None:
        """The keyframe's depth made small, for the map's views in a merge check (none where
        the image does not divide into the blocks, and none where nothing is merged)."""
        if not self._merges:
            return
        block = self.params.merge_view_block
        height, width = depth.shape
        if height % block or width % block:
            if state.vehicle_id not in self._no_views:
                self._no_views.add(state.vehicle_id)
                self._log(f"vehicle {state.vehicle_id}: its {width}x{height} keyframes do not "
                          f"divide into {block}-pixel views (merge_view_block): its map will "
                          "not be merged with others")
            return
        segment = state.segment
        if segment.view_intrinsics is None:
            c = m.camera
            segment.view_intrinsics = (c.fx / block, c.fy / block, c.cx / block, c.cy / block)
        segment.views.append((m.utime, small_depth(depth, m.depth_scale_m, block,
                                                   *self._view_range_m)))
        if len(segment.views) > self.params.merge_max_views:
            # Every other one goes: the views stay spread over the whole flight.
            segment.views = segment.views[::2]

    @staticmethod
    def _views(segment: Segment) -> Views:
        """The map's views: its keyframes' small depth where its own optimised world puts them."""
        poses = dict(segment.chain.trajectory(shared=False))
        kept = [(depth, poses[utime]) for utime, depth in segment.views if utime in poses]
        return Views(np.stack([d for d, _ in kept]), np.stack([T for _, T in kept]),
                     segment.view_intrinsics)

    def _merge_if_due(self, state: VehicleState, utime: int) -> None:
        """Pairs of maps that share no world are checked for a common place, each pair at most
        every merge_interval_s of this vehicle's capture time (each map's own clock: drones'
        clocks need not agree), and again sooner than merge_max_interval_s only where a map
        grew; of the pairs due, the one checked longest ago, one check at a time."""
        segment = state.segment
        if (not self._merges or self._merge_pending or segment.chain is None
                or not segment.views
                or len(segment.corrected) < self.params.merge_min_keyframes):
            return
        key = _map_key(state)
        due = []
        for other in self.vehicles.values():
            o, other_key = other.segment, _map_key(other)
            if (other is state or o.chain is None or not o.views
                    or len(o.corrected) < self.params.merge_min_keyframes
                    or self.worlds.merged(other_key, key)):
                continue
            checked = self._pair_checked.get(frozenset((key, other_key)))
            if pair_due(self.params, checked, key, utime, {
                    key: segment.chain.num_blocks, other_key: o.chain.num_blocks}):
                due.append((-1 if checked is None else checked[key][0], other))
        if not due:
            return
        _, other = min(due, key=lambda pair: pair[0])
        other_key = _map_key(other)
        self._pair_checked[frozenset((key, other_key))] = {
            key: (utime, segment.chain.num_blocks),
            other_key: (other.segment.corrected[-1][0], other.segment.chain.num_blocks)}
        job = MergeJob(other_key, key, other.segment.chain.parts(shared=False),
                       segment.chain.parts(shared=False), self._views(other.segment),
                       self._views(segment), self.params.merge)
        self._merge_pending = True
        state.counters.merge_checks += 1
        other.counters.merge_checks += 1
        self.loops.submit_merge(job, recognise_place)

    def _take_merges(self) -> None:
        """Merges the maps whose checks found a common place since the last keyframe: from now
        on both drones' corrections are in the shared world."""
        for done in self.loops.take_merges():
            self._merge_pending = False
            job = done.job
            target, source = self.vehicles[job.target[0]], self.vehicles[job.source[0]]
            pair = f"vehicles {job.target[0]} and {job.source[0]}"
            if done.match is None:
                for state in (target, source):
                    state.counters.merge_checks_failed += 1
                continue
            if (done.match.accepted and (_map_key(target) != job.target
                                         or _map_key(source) != job.source)):
                reason = "a common place found, but a drone restarted since"
            else:
                reason = done.match.reason
            if reason or self.worlds.merged(job.target, job.source):
                for state in (target, source):
                    state.counters.merges_refused += 1
                self._log(f"{pair}: not merged ({reason or 'they share a world already'})")
                continue
            self.worlds.merge(job.target, job.source, done.match.T_target_source)
            for state in (target, source):
                state.counters.merges += 1
            T = done.match.T_target_source
            self._log(f"{pair} share a map: vehicle {job.source[0]}'s found in vehicle "
                      f"{job.target[0]}'s ({done.match.inliers} feature matches, overlap "
                      f"{done.match.check.overlap:.2f}), {np.linalg.norm(T[:3, 3]):.2f} m and "
                      f"{np.degrees(rotation_angle_rad(T)):.0f} deg apart; both now in vehicle "
                      f"{self.worlds.world_of(job.source)[0]}'s world")
            self._place_maps()

    def _place_maps(self) -> None:
        """Every map, earlier odometry frames' included, placed where the shared worlds now put
        it; then the current ones drawn there and the viewer told which maps share a world."""
        groups: dict[MapKey, list[int]] = {}
        for state in self.vehicles.values():
            for number, segment in enumerate([*state.finished_segments, state.segment]):
                if segment.chain is not None:
                    segment.chain.place(self.worlds.T_world_map((state.vehicle_id, number)))
            if state.segment.chain is not None:
                groups.setdefault(self.worlds.world_of(_map_key(state)), []).append(
                    state.vehicle_id)
        for state in self.vehicles.values():
            segment = state.segment
            if segment.chain is not None and segment.corrected:
                utime = segment.corrected[-1][0]
                self._draw_map(state, segment.chain, utime)
                state.view.optimised(utime, np.array([T[:3, 3]
                                                      for _, T in segment.chain.trajectory()]))
        self._show_shared([sorted(g) for _, g in sorted(groups.items()) if len(g) > 1])

    def _closed(self, state: VehicleState, chain: SubmapChain, closed: Submap,
                utime: int) -> None:
        self._log(f"vehicle {state.vehicle_id}: submap {closed.index} closed after "
                  f"{closed.path_m:.1f} m, {(utime - closed.first_utime) * 1e-6:.0f} s, "
                  f"{len(closed.keyframes)} keyframes")
        # Its whole mesh once, so the viewer keeps it complete (meshing it also serves the
        # loop check, which reads the same snapshot).
        state.view.submap_poses(utime, {closed.index: chain.correction(closed.index)})
        state.view.pose_graph(utime, *chain.graph())
        self._mesh(state, utime, closed.index, closed.snapshot)
        candidates = chain.loop_candidates(closed)
        state.counters.loop_candidates += len(candidates)
        self.loops.submit(chain, candidates)

    def _add_loops(self, state: VehicleState, chain: SubmapChain, utime: int,
                   draw: bool = True) -> None:
        """Adds the loops checked since the last keyframe to the graph: the submaps move, and
        the next correction carries the open submap's move to the drone. DRAW: the chain is the
        one the viewer shows."""
        done = self.loops.take_done(chain)
        state.counters.loop_checks_failed += sum(1 for d in done if d.check is None)
        checked = [(d.candidate, d.check) for d in done if d.check is not None]
        if not checked:
            return
        try:
            added = chain.add_loops(checked)
        except Exception as error:  # a graph that cannot be optimised: the keyframe goes on
            state.counters.loop_checks_failed += len(checked)
            self._log(f"vehicle {state.vehicle_id}: {len(checked)} loops not added: "
                      f"{type(error).__name__}: {error}")
            return
        counters = state.counters
        for outcome in added.new:
            c, check = outcome.candidate, outcome.check
            if outcome.accepted_by_graph:
                counters.loops_accepted += 1
                verdict = "accepted"
            elif check.accepted:
                counters.loops_refused_by_graph += 1
                verdict = "refused by the graph"
            else:
                counters.loops_refused_by_check += 1
                verdict = f"refused ({check.reason})"
            self._log(f"vehicle {state.vehicle_id}: loop between submaps {c.older} and "
                      f"{c.newer} {verdict}")
        # The counters say what the graph holds now: a loop it took may be out-voted later.
        for outcome in added.revised:
            c, step = outcome.candidate, 1 if outcome.accepted_by_graph else -1
            counters.loops_accepted += step
            counters.loops_refused_by_graph -= step
            self._log(f"vehicle {state.vehicle_id}: loop between submaps {c.older} and "
                      f"{c.newer} now {'accepted' if step > 0 else 'refused'} by the graph, "
                      "with the loops added since")
        if draw:
            self._draw_map(state, chain, utime)
            state.view.optimised(utime, np.array([T[:3, 3] for _, T in chain.trajectory()]))

    @staticmethod
    def _draw_map(state: VehicleState, chain: SubmapChain, utime: int) -> None:
        """Every submap where the graph now puts it, and the graph."""
        state.view.submap_poses(utime, chain.corrections())
        state.view.pose_graph(utime, *chain.graph())

    def _correct(self, state: VehicleState, m: Keyframe, T_onboard: np.ndarray,
                 T_onboard_now: np.ndarray, T_corrected: np.ndarray, arrival_ns: int) -> bool:
        """The correction policy, then the uplink: whether the correction went out.
        T_ONBOARD_NOW is the drone's pose moved into the world of the last correction (the
        chain's guess_moved): what this correction moves it from."""
        # The move in the camera's own frame: its translation is the distance between the two
        # poses, however far from the origin the drone is.
        if jump_exceeds(np.linalg.inv(T_onboard_now) @ T_corrected,
                        self.params.reset_translation_m,
                        self.params.reset_rotation_rad):
            state.reset_counter += 1
            state.counters.resets += 1
        state.T_map_onboard = T_corrected @ np.linalg.inv(T_onboard)
        return self._uplink.send(state, m, T_corrected, arrival_ns)

    def _show(self, state: VehicleState, m: Keyframe, depth: np.ndarray,
              T_onboard: np.ndarray, T_corrected: np.ndarray | None, result: Any) -> None:
        self._file_truth(state)
        self._draw_flight(state)
        c = m.camera
        state.view.keyframe(m.utime, depth, m.depth_scale_m, (c.fx, c.fy, c.cx, c.cy), T_onboard,
                            T_corrected)
        chain = state.segment.chain
        # None while no keyframe had the depth to begin a map.
        active = chain.active
        if result.status is TrackingStatus.OK:
            # The map as raycast for this keyframe's registration, from its onboard pose (a few
            # mm from the refined one) where it measured depth; a map's first keyframe has none.
            state.view.render(m.utime, active.fusion.render(), depth.shape)
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
        link = state.link_quality
        if link is not None:
            # The link as this keyframe found it (what the ground's status tells the drone).
            health.update({
                "link/loss_percent": 100.0 * link.link_loss,
                "link/goodput_mbps": link.goodput_bps * 1e-6,
                "link/redundancy": link.redundancy,
                "link/keyframe_age_ms": link.keyframe_age_ms,
                "link/queue_delay_ms": link.queue_delay_ms,
            })
        if result.status is not TrackingStatus.FIRST_FRAME:
            health["tracking/inlier_fraction"] = result.inlier_fraction
            health["tracking/rmse_mm"] = result.rmse_m * 1e3
        state.view.health(m.utime, health)
        # By capture time, which runs at the wall clock's pace in flight and at the log's in a
        # replay.
        interval_us = self.params.mesh_interval_s * 1e6
        if active is not None and interval_us > 0 and (
                state.mesh_utime is None or m.utime - state.mesh_utime >= interval_us):
            state.mesh_utime = m.utime
            # A submap begun after a loop continues its predecessor's correction.
            state.view.submap_poses(m.utime, {active.index: chain.correction(active.index)})
            self._mesh(state, m.utime, active.index, active.fusion.snapshot())

    def _draw_flight(self, state: VehicleState) -> None:
        """The flight stack's newest state with each keyframe: the estimate and the setpoint in
        the map's frame (by the estimator's alignment), and its scalars."""
        with state.lock:
            status, state.pending_flight = state.pending_flight, None
        if status is None or not status.estimator_initialised:
            return
        estimate, setpoint = flight.in_map(status, [status.p_world_m, status.setpoint_world_m])
        state.view.flight(status.utime, estimate, setpoint, flight.metrics(status))

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
            if state.segment.chain is not None:
                state.segment.views = []  # only a current map is checked for merges
                state.finished_segments.append(state.segment)
            state.segment = Segment()
        state.view.restarted(utime)

    def show_final(self, truth: list[StampedPose] | None, loops_timeout_s: float) -> None:
        """Adds the loops still being checked (waiting up to LOOPS_TIMEOUT_S), then sends every
        vehicle's map to the viewer as it is at the end, stamped with its last keyframe (the
        periodic meshes miss whatever came after the last one), and its ground truth (TRUTH,
        else what the drone sent) as the ATE aligns it with the optimised trajectory: the frame
        the map is drawn in. Call after stop()."""
        try:
            self._show_final(truth, loops_timeout_s)
        finally:
            self.loops.close()

    def _show_final(self, truth: list[StampedPose] | None, loops_timeout_s: float) -> None:
        if not self.loops.wait_idle(loops_timeout_s):
            self._log(f"loop checks still running after {loops_timeout_s:g} s: left out")
        self._take_merges()
        for state in self.vehicles.values():
            # Checks that finished after their drone restarted still belong to its old map.
            for finished in state.finished_segments:
                if finished.corrected:
                    self._add_loops(state, finished.chain, finished.corrected[-1][0], draw=False)
            segment = state.segment
            if segment.chain is None or not segment.corrected:
                continue
            chain = segment.chain
            last_utime = segment.corrected[-1][0]
            self._add_loops(state, chain, last_utime)
            active = chain.active
            self._draw_map(state, chain, last_utime)
            state.view.mesh(last_utime, active.index, *active.fusion.snapshot().mesh())
            segment.final_mesh = chain.mesh()
            segment_truth = truth if truth is not None else segment.ground_truth
            segment.evaluation = evaluate({"onboard": segment.onboard,
                                           "corrected": segment.corrected,
                                           "optimised": chain.trajectory()}, segment_truth)
            # The map is where the graph put it: the ground truth is drawn in that frame.
            if "optimised" in segment.evaluation:
                T_map_truth = np.linalg.inv(segment.evaluation["optimised"]["T_truth_estimate"])
                # Stamped no earlier than the last truth drawn during the flight (frames after
                # the last keyframe have truth too), or a viewer at the end would show that.
                drawn = (segment.ground_truth[segment.truth_drawn - 1][0]
                         if segment.truth_drawn else 0)
                state.view.ground_truth_aligned(
                    max(last_utime, drawn),
                    np.array([(T_map_truth @ T)[:3, 3] for _, T in segment_truth]))
