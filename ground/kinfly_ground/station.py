"""The ground station: one map per vehicle, fed with the keyframes the link let through. Station
puts its parts together:

- arrivals.py (the LCM thread): decoding (the native Receiver), classification (duplicate, late,
  a restarted drone), sessions, the drone's status, odometry forwarding;
- mapping.py (the worker thread): refine and fuse, the correction policy, the viewer, ground truth;
- uplink.py: signed corrections out;
- conversions.py: the ground's status;
- runner.py: the threads and the bounded queue; vehicle.py: what is held per vehicle.

Losses are counted where they happen: the drone's own (its status: frames its odometry could not
keep up with, keyframes its link could not send), the link's (keyframe ids the drone's status says
it sent that never arrived: `lost_on_link`), and the station's (`keyframes_dropped` from a full
queue, `keyframes_lost` that could not be refined). Keyframes that arrive in chunks are rebuilt by
the native Receiver, which also measures each vehicle's link (`Receiver.link_quality`: loss,
goodput, queue delay, keyframe age) for the ground's status; a station that sends asks the drone
once per incomplete chunk group to resend what is missing (arrivals.py). `replay` runs the same
steps on the caller's thread (`inline=True`): every keyframe, nothing dropped.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

from kinfly import ground_status_t

from ._native import FusionPipelineParams, HashedVolumeParams, Receiver, Signer
from .arrivals import Arrivals, Forward
from .mapping import Mapper
from .runner import Runner
from .submaps import SubmapParams
from .conversions import ground_status
from .uplink import Publish, Uplink
from .vehicle import Job, StampedPose, VehicleState
from .merge import PlaceParams
from .viewer import Viewer


@dataclasses.dataclass(frozen=True)
class StationParams:
    # The map's voxel (HashedVolumeParams.voxel_size_m); the truncation band is four of them.
    voxel_size_m: float = 0.01          # [m] (0.002, 0.1]
    threads: int = 2                    # [1, 64] engine threads for fusion
    # Each keyframe is registered against the map raycast at this level of its pyramid
    # (FusionPipelineParams.model_level): 0, every pixel's ray, the seed's; 1, half the
    # keyframe's resolution, a quarter of the rays, for a station short of time (the map itself
    # is fused at full resolution either way). docs/ground.md has what 1 costs in accuracy.
    model_level: int = 0                # [0, 1]
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
    # The newest keyframe's missing chunks are asked for only once the drone's status says it
    # sent that keyframe and no chunk has arrived for this long: until then they may still come.
    repair_quiet_s: float = 0.05        # [s] [0.005, 1]
    # A resend can be lost too (the request, or a burst of the chunks): a group still incomplete
    # is asked for again after repair_retry_s, at most repair_asks times in all. The drone keeps
    # its last 4 keyframes' chunks (0.8 s at 5 Hz): (repair_asks - 1) * repair_retry_s should
    # fit in that, or the last asks go unanswered.
    repair_asks: int = 3                # [1, 16]
    repair_retry_s: float = 0.2         # [s] [0.01, 10]
    # Each correction is sent this many times, correction_copy_interval_s apart, so that a run
    # of lost packets rarely takes every copy; the drone applies the first and counts the others
    # as duplicates. At 10 % independent loss, 4 copies lose 1 in 10 000 (3: 1 in 1000, which
    # the 99.9 % target would meet only half the time). The copies go out before
    # the next keyframe's correction (one comes every 0.2 s at 5 Hz), which would make a later
    # copy a replay.
    correction_copies: int = 4          # [1, 10]
    correction_copy_interval_s: float = 0.03  # [s] [0.005, 0.5]
    # The map as a chain of submaps and its loop closure (submaps.py); each closed submap's
    # loops are checked in a process beside the fusion (loops.py). At the end of a run the
    # checks still under way get this long to finish before the outputs are written.
    submaps: SubmapParams = SubmapParams()
    final_loops_timeout_s: float = 60.0  # [s] > 0
    # Several drones in one map (merge.py): every merge_interval_s of a vehicle's capture time,
    # once its map holds merge_min_keyframes, its map and one it does not share a world with yet
    # are checked for a common place in the loop checks' process (inf: never). A map's views
    # are its keyframes' depth, merge_view_block pixels square to a view's pixel.
    merge_interval_s: float = 10.0      # [s] > 0
    # A pair already refused is checked again only once either map grew by this share of its
    # blocks since (new ground to find the other in), or after merge_max_interval_s whatever it
    # did: a check costs 2-6 s of a core (test_merge.py), and drones that keep to their own
    # rooms, or hover, would otherwise spend the loop checks' process on them every 10 s.
    merge_min_growth: float = 0.1       # [0, 10]; 0: every merge_interval_s
    merge_max_interval_s: float = 120.0  # [s] >= merge_interval_s
    merge_min_keyframes: int = 10       # [1, 10000]
    merge_view_block: int = 8           # [1, 64] pixels
    # A map keeps at most this many views: beyond it, every other one is let go (19 KB each at
    # 640 x 480: 5 MB a vehicle, where every keyframe of an hour at 5 Hz would be 340 MB).
    merge_max_views: int = 256          # [8, 100000]
    merge: PlaceParams = PlaceParams()

    def volume_params(self) -> HashedVolumeParams:
        """The engine's parameters for each map's hashed volume."""
        volume = HashedVolumeParams()
        volume.voxel_size_m = self.voxel_size_m
        return volume

    def pipeline_params(self) -> FusionPipelineParams:
        """The engine's parameters for each map's pipeline: its defaults, with a truncation band
        of four voxels and the model at model_level. The depth scale is each map's first
        keyframe's (mapping.py)."""
        pipeline = FusionPipelineParams()
        pipeline.integrate.truncation_m = 4.0 * self.voxel_size_m
        pipeline.model_level = self.model_level
        return pipeline

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
            (0.005 <= self.repair_quiet_s <= 1.0, "repair quiet time must be in [0.005, 1] s"),
            (1 <= self.repair_asks <= 16, "repair asks must be in [1, 16]"),
            (0.01 <= self.repair_retry_s <= 10.0, "repair retry must be in [0.01, 10] s"),
            (1 <= self.correction_copies <= 10, "correction copies must be in [1, 10]"),
            (0.005 <= self.correction_copy_interval_s <= 0.5,
             "correction copy interval must be in [0.005, 0.5] s"),
            (self.final_loops_timeout_s > 0, "final loops timeout must be > 0 s"),
            (self.merge_interval_s > 0, "merge interval must be > 0 s"),
            (0 <= self.merge_min_growth <= 10, "merge min growth must be in [0, 10]"),
            (self.merge_max_interval_s >= self.merge_interval_s
             or math.isinf(self.merge_interval_s),  # never checked: the rule says nothing
             "merge max interval must be >= the merge interval"),
            (1 <= self.merge_min_keyframes <= 10000, "merge min keyframes must be in [1, 10000]"),
            (1 <= self.merge_view_block <= 64, "merge view block must be in [1, 64] pixels"),
            (8 <= self.merge_max_views <= 100000, "merge max views must be in [8, 100000]"),
        ]
        if why := next((why for ok, why in checks if not ok), ""):
            return why
        # Then the engine's own ranges, at its fields.
        return self.volume_params().validate() or self.pipeline_params().validate(
            self.voxel_size_m)


class Station:
    """Maps keyframes into per-vehicle maps and publishes corrections. PUBLISH sends an encoded
    message on a channel (None: nothing is sent, as in replay). SIGNERS maps a vehicle id to its
    signer; a vehicle without one is mapped but gets no corrections. VEHICLE_ID None serves every
    vehicle (each under its own viewer prefix). The parts: arrivals (LCM thread), the maps and
    their correction policy (worker thread), the uplink, the status, and the runner's threads."""

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
        if vehicle_id is not None:
            # Made now, not at the first keyframe: the vehicle's state asks the viewer again then
            # and gets this one.
            viewer.vehicle(vehicle_id, "")
        self.arrivals = Arrivals(params, viewer, vehicle_id=vehicle_id, signers=signers,
                                 publish=publish, forward=forward,
                                 submit=lambda job: self.runner.submit(job), log=log)
        self.vehicles = self.arrivals.vehicles
        self.uplink = Uplink(publish, params.correction_copies, params.correction_copy_interval_s)
        # Only a station serving every vehicle holds several maps to merge.
        self.mapper = Mapper(params, self.vehicles, self.uplink,
                             lambda *job: self.runner.mesh(*job), log,
                             merges=vehicle_id is None, show_shared=viewer.shared)
        self.runner: Runner[Job] = Runner(params.queue_keyframes, self.mapper.process,
                                          self.arrivals.on_dropped, inline=inline, log=log)

    @property
    def receiver(self) -> Receiver:
        return self.arrivals.receiver

    @property
    def rejected_too_many_vehicles(self) -> int:
        return self.arrivals.rejected_too_many_vehicles

    @property
    def handler_errors(self) -> int:
        return self.arrivals.handler_errors

    def on_message(self, channel: str, data: bytes) -> None:
        """One received message (LCM thread)."""
        self.arrivals.on_message(channel, data)

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
        """The loops still being checked, then the maps and ground truth as they are at the end
        (Mapper.show_final); after stop()."""
        self.mapper.show_final(truth, self.params.final_loops_timeout_s)

    def ground_status(self, state: VehicleState, now_s: float, link_timeout_s: float,
                      run_state: int = ground_status_t.RUN_ACTIVE) -> ground_status_t:
        return ground_status(state, self.receiver.rejects,
                             self.receiver.link_quality(state.vehicle_id), now_s, link_timeout_s,
                             run_state)
