"""The ground station's rerun output: a live viewer, an .rrd recording, both or neither.

Entity paths mirror the frame tree under each vehicle's prefix ("" for one vehicle, "vehicle_3/"
when serving several):
  world                            ViewCoordinates RDF: `world` is the first keyframe's camera frame
  world/drone/camera               Transform3D T_world_cam (the corrected one when there is
                                   one) + Pinhole
  world/drone/camera/depth         DepthImage, raw uint16
  world/drone/camera/render        raycast shaded render from the current pose
  world/drone/estimate             Points3D: the drone's own state estimate of its body, and ...
  world/drone/setpoint             ... the setpoint its position loop follows (flight_status_t,
                                   in the map's frame by the estimator's alignment)
  world/trajectory/<name>/<block>  onboard, corrected, ground_truth (see _Trajectory)
  world/map/submap/<k>             Transform3D C_k: where the pose graph puts submap k
  world/map/submap/<k>/mesh        Mesh3D, in the frame the submap was fused in
  world/map/graph/nodes            Points3D: the pose graph's nodes, each submap's anchor where
                                   the graph puts it (labelled by submap index)
  world/map/graph/odometry         LineStrips3D: its odometry edges, submap to submap
  world/map/graph/loops/accepted   LineStrips3D: loop edges the graph took, and ...
  world/map/graph/loops/refused    ... those it refused (a loop refused by its check never
                                   reaches the graph and is not drawn)
  health/<group>/<name>            Scalars, names from the caller ("link/latency_ms")
  autopilot/<name>                 Scalars, MAVLink telemetry
  flight/<name>                    Scalars, the flight stack's (flight.metrics)
Every entry is stamped with its capture time `utime` on the timestamp timeline "capture_time".

The layout (a rerun blueprint, see _layout) is sent with each new vehicle, so a recording opens
on it: the map large, and beside it the camera and one plot each of health/link and
health/tracking. autopilot/ is recorded but has no view of its own.

Only numpy and rerun: it works from the source tree, without the native module.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

APPLICATION_ID = "kinfly-ground"
TIMELINE = "capture_time"
# The port rr.spawn starts the viewer on is the one the gRPC sink connects to.
_VIEWER_PORT = 9876
# A trajectory block's poses, the last shared with the next block. Each new pose re-logs its
# block, so per pose at most this many points (3 KB) are written, small against the 600 KB depth
# image logged with it, and a long flight costs blocks, not a re-logged whole strip.
_BLOCK_POSES = 256
_TRAJECTORY_RADIUS = rr.Radius.ui_points(2.0)
_TRAJECTORY_COLORS = {
    "onboard": (255, 140, 0),
    "corrected": (0, 200, 80),
    "ground_truth": (200, 200, 200),
}
# The flight stack's estimate and setpoint: larger than a trajectory's points, in colours of
# their own (the trajectories' are orange, green and grey).
_FLIGHT_RADIUS = rr.Radius.ui_points(6.0)
_FLIGHT_COLORS = {"estimate": (60, 120, 255), "setpoint": (230, 0, 200)}
_GRAPH_RADIUS = rr.Radius.ui_points(4.0)
_GRAPH_COLORS = {"nodes": (255, 200, 0), "odometry": (160, 160, 160),
                 "accepted": (0, 200, 80), "refused": (230, 40, 40)}
# Each vehicle's map where a station serves several, so that merged maps (merge.py) drawn in
# one view tell their vehicles apart; in turn by the order the vehicles arrive.
_VEHICLE_MAP_COLORS = [(230, 159, 0), (86, 180, 233), (0, 158, 115), (240, 228, 66),
                       (0, 114, 178), (213, 94, 0), (204, 121, 167)]
# The map's column against the side column (camera over the two plots): the map is what a
# person flies by, and the side views stay readable at a laptop's 1600 px.
_MAP_COLUMN_SHARES = [2.0, 1.0]
# The side column's rows: the camera, then the link and tracking plots.
_SIDE_ROW_SHARES = [2.0, 1.0, 1.0]
# The render drawn over the depth in the camera view, half see-through so the measured depth
# shows where the model has no surface yet.
_RENDER_OPACITY = 0.5


def at_resolution(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """IMAGE resized to SHAPE (height, width) by nearest neighbour: each pixel of SHAPE takes the
    IMAGE pixel it falls in. IMAGE itself when it has SHAPE already."""
    if image.shape[:2] == tuple(shape):
        return image
    rows = np.arange(shape[0]) * image.shape[0] // shape[0]
    columns = np.arange(shape[1]) * image.shape[1] // shape[1]
    return image[rows[:, None], columns]


class ViewerError(Exception):
    """The viewer could not be started or the recording not written."""


def _vehicle_layout(prefix: str) -> rrb.Horizontal:
    """One vehicle's views: its map (mesh, trajectories, camera frustum with depth and render),
    the camera's own view with the render over the depth, and the two health plots."""
    camera = f"/{prefix}world/drone/camera"
    return rrb.Horizontal(
        rrb.Spatial3DView(name="map", origin=f"/{prefix}world"),
        rrb.Vertical(
            rrb.Spatial2DView(name="camera", origin=camera,
                              overrides={f"{camera}/render":
                                         rr.Image.from_fields(opacity=_RENDER_OPACITY)}),
            rrb.TimeSeriesView(name="link", origin=f"/{prefix}health/link"),
            rrb.TimeSeriesView(name="tracking", origin=f"/{prefix}health/tracking"),
            row_shares=_SIDE_ROW_SHARES),
        column_shares=_MAP_COLUMN_SHARES,
        name=prefix.rstrip("/") or None)


def _shared_layout(prefixes: list[str]) -> rrb.Spatial3DView:
    """One 3D view of the maps and trajectories of vehicles whose maps share a world (merged)."""
    names = " + ".join(prefix.rstrip("/") for prefix in prefixes)
    return rrb.Spatial3DView(
        name=f"shared map: {names}", origin="/",
        contents=[f"+ /{prefix}world/{part}/**" for prefix in prefixes
                  for part in ("map", "trajectory")])


def _layout(prefixes: list[str], shared: list[list[str]] | None = None) -> rrb.Blueprint:
    """PREFIXES' views; several vehicles get a tab each, as every vehicle maps in its own
    `world` frame and one 3D view of them all would draw unrelated frames over each other. Each
    group of vehicles in SHARED (their prefixes), whose maps were merged into one world, gets a
    tab of its own first, with their maps in one view."""
    layouts = ([_shared_layout(group) for group in shared or []]
               + [_vehicle_layout(prefix) for prefix in prefixes])
    # Open, the blueprint and selection panels would take a third of a laptop's width from the
    # map and the time panel a quarter of its height; collapsed, the time panel keeps its
    # playback bar, and a click opens any of them.
    return rrb.Blueprint(layouts[0] if len(layouts) == 1 else rrb.Tabs(*layouts),
                         rrb.BlueprintPanel(state="collapsed"),
                         rrb.SelectionPanel(state="collapsed"),
                         rrb.TimePanel(state="collapsed"))


class _Trajectory:
    """One trajectory as a polyline split into blocks, each its own entity `<path>/<k>`.

    Why blocks rather than one new 2-point segment per pose: a segment logged at time t is shown
    only while it is the latest value of its entity, so accumulating segments needs a visible time
    range in a blueprint, and rerun's range queries ignore Clear: restarted() could not remove
    the old frame's trajectory. Blocks are shown by plain latest-at (a finished block stays
    visible, scrubbing back in time shows the trajectory as it was) and a recursive Clear on the
    parent removes them all."""

    def __init__(self, rec: rr.RecordingStream, path: str, color: tuple[int, int, int]) -> None:
        self._rec = rec
        self._path = path
        self._color = color
        self._positions = np.empty((_BLOCK_POSES, 3), dtype=np.float32)
        self._count = 0
        self._block = 0

    def append(self, T_world_cam: np.ndarray) -> None:
        self._add(T_world_cam[:3, 3])
        self._log_block()

    def replace(self, positions: np.ndarray) -> None:
        """POSITIONS (Nx3) instead of what was drawn, from the time the caller set on; each
        block is logged once, full."""
        self._rec.log(self._path, rr.Clear(recursive=True))
        self.reset()
        for position in positions:
            if self._count == _BLOCK_POSES:
                self._log_block()
            self._add(position)
        self._log_block()

    def _add(self, position: np.ndarray) -> None:
        if self._count == _BLOCK_POSES:
            # The new block starts where the full one ends, so the line has no gap.
            self._positions[0] = self._positions[-1]
            self._count = 1
            self._block += 1
        self._positions[self._count] = position
        self._count += 1

    def _log_block(self) -> None:
        if self._count >= 2:  # one pose is not a line yet
            self._rec.log(f"{self._path}/{self._block}",
                          rr.LineStrips3D([self._positions[:self._count]],
                                          colors=self._color, radii=_TRAJECTORY_RADIUS))

    def reset(self) -> None:
        """Start again at block 0; the caller has cleared the old blocks."""
        self._count = 0
        self._block = 0


class VehicleView:
    """One vehicle's entities, under its prefix. Made by Viewer.vehicle().

    The calls that touch the trajectories (keyframe, ground_truth, ground_truth_aligned,
    restarted) must come from one thread, the station's fusion thread (or after it stopped). render, mesh, health and telemetry may come from any
    thread: rerun's time is per thread and each call sets it before logging."""

    def __init__(self, rec: rr.RecordingStream | None, prefix: str,
                 map_color: tuple[int, int, int] | None = None) -> None:
        self._rec = rec
        self._prefix = prefix
        self._map_color = map_color
        if rec is None:
            return
        rec.log(f"{prefix}world", rr.ViewCoordinates.RDF, static=True)
        self._trajectories = {
            name: _Trajectory(rec, f"{prefix}world/trajectory/{name}", color)
            for name, color in _TRAJECTORY_COLORS.items()}

    def keyframe(self, utime: int, depth: np.ndarray, depth_scale_m: float,
                 intrinsics: tuple[float, float, float, float], T_world_cam_onboard: np.ndarray,
                 T_world_cam_corrected: np.ndarray | None) -> None:
        """The camera at the corrected pose (the onboard one while the ground has none) with its
        depth; both trajectories grow, the corrected one only when there is a corrected pose."""
        if self._rec is None:
            return
        T_world_cam = (T_world_cam_onboard if T_world_cam_corrected is None
                       else T_world_cam_corrected)
        fx, fy, cx, cy = intrinsics
        height, width = depth.shape
        camera = f"{self._prefix}world/drone/camera"
        self._stamp(utime)
        # Pinhole with every keyframe (tens of bytes): it is back right after restarted()'s Clear
        # and follows a change of camera, with no state kept here.
        self._rec.log(camera,
                      rr.Transform3D(translation=T_world_cam[:3, 3], mat3x3=T_world_cam[:3, :3]),
                      rr.Pinhole(focal_length=(fx, fy), principal_point=(cx, cy),
                                 width=width, height=height, camera_xyz=rr.ViewCoordinates.RDF))
        self._rec.log(f"{camera}/depth", rr.DepthImage(depth, meter=1.0 / depth_scale_m))
        self._trajectories["onboard"].append(T_world_cam_onboard)
        if T_world_cam_corrected is not None:
            self._trajectories["corrected"].append(T_world_cam_corrected)

    def ground_truth(self, utime: int, T_world_cam: np.ndarray) -> None:
        if self._rec is None:
            return
        self._stamp(utime)
        self._trajectories["ground_truth"].append(T_world_cam)

    def ground_truth_aligned(self, utime: int, positions: np.ndarray) -> None:
        """The whole ground truth drawn again from UTIME on, as POSITIONS (Nx3, in `world`):
        once the evaluation has aligned it with the map, it replaces the path drawn during the
        flight, which could only be anchored at one keyframe."""
        if self._rec is None:
            return
        self._stamp(utime)
        self._trajectories["ground_truth"].replace(positions)

    def render(self, utime: int, image: np.ndarray, shape: tuple[int, int]) -> None:
        """IMAGE: uint8, the model raycast from the current pose; SHAPE: the keyframe depth's
        (height, width), its pinhole's. A render at a coarser resolution (kinfly-ground
        --model-level 1) is shown at SHAPE, so that it lies under that pinhole."""
        if self._rec is None:
            return
        self._stamp(utime)
        self._rec.log(f"{self._prefix}world/drone/camera/render",
                      rr.Image(at_resolution(image, shape), color_model="L"))

    def mesh(self, utime: int, submap: int, vertices: np.ndarray, triangles: np.ndarray,
             normals: np.ndarray | None) -> None:
        """Submap SUBMAP's mesh: VERTICES float32 Nx3 in the frame it was fused in (the
        drone's odometry), TRIANGLES int32 Mx3, NORMALS float32 Nx3 or None. submap_poses puts
        it in `world`."""
        if self._rec is None:
            return
        self._stamp(utime)
        self._rec.log(f"{self._prefix}world/map/submap/{submap}/mesh",
                      rr.Mesh3D(vertex_positions=vertices, triangle_indices=triangles,
                                vertex_normals=normals, albedo_factor=self._map_color))

    def submap_poses(self, utime: int, corrections: dict[int, np.ndarray]) -> None:
        """Where the pose graph puts each submap: CORRECTIONS maps a submap's index to the 4x4
        transform of its content into `world` (submaps.py's C_k)."""
        if self._rec is None:
            return
        self._stamp(utime)
        for submap, C in corrections.items():
            self._rec.log(f"{self._prefix}world/map/submap/{submap}",
                          rr.Transform3D(translation=C[:3, 3], mat3x3=C[:3, :3]))

    def pose_graph(self, utime: int, nodes: dict[int, np.ndarray],
                   odometry: list[tuple[int, int]], loops: list[tuple[int, int, bool]]) -> None:
        """The pose graph as it now stands: NODES maps a submap's index to its anchor's position
        in `world`, ODOMETRY lists the edges between consecutive submaps, LOOPS the loop edges
        (older, newer, accepted by the graph)."""
        if self._rec is None:
            return
        self._stamp(utime)
        root = f"{self._prefix}world/map/graph"
        indices = sorted(nodes)
        self._rec.log(f"{root}/nodes", rr.Points3D(
            [nodes[k] for k in indices], labels=[str(k) for k in indices],
            colors=[_GRAPH_COLORS["nodes"]] * len(indices), radii=_GRAPH_RADIUS))
        edges = {"odometry": [(i, j) for i, j in odometry],
                 "loops/accepted": [(i, j) for i, j, taken in loops if taken],
                 "loops/refused": [(i, j) for i, j, taken in loops if not taken]}
        for name, pairs in edges.items():
            color = _GRAPH_COLORS[name.rpartition("/")[2]]
            self._rec.log(f"{root}/{name}", rr.LineStrips3D(
                [[nodes[i], nodes[j]] for i, j in pairs], colors=[color] * len(pairs)))

    def optimised(self, utime: int, positions: np.ndarray) -> None:
        """After a loop closure, the corrected trajectory drawn again from UTIME on as the
        optimised graph places its keyframes (POSITIONS Nx3 in `world`)."""
        if self._rec is None:
            return
        self._stamp(utime)
        self._trajectories["corrected"].replace(positions)

    def health(self, utime: int, metrics: dict[str, float]) -> None:
        """METRICS: "group/name" -> value, each its own series health/group/name."""
        self._series(utime, "health", metrics)

    def flight(self, utime: int, estimate_m: np.ndarray, setpoint_m: np.ndarray,
               metrics: dict[str, float]) -> None:
        """The flight stack's estimate and setpoint of the body (map frame, metres) and METRICS,
        each its own series flight/name."""
        if self._rec is None:
            return
        self._stamp(utime)
        self._rec.log(f"{self._prefix}world/drone/estimate",
                      rr.Points3D([estimate_m], colors=[_FLIGHT_COLORS["estimate"]],
                                  radii=_FLIGHT_RADIUS))
        self._rec.log(f"{self._prefix}world/drone/setpoint",
                      rr.Points3D([setpoint_m], colors=[_FLIGHT_COLORS["setpoint"]],
                                  radii=_FLIGHT_RADIUS))
        self._series(utime, "flight", metrics)

    def telemetry(self, utime: int, metrics: dict[str, float]) -> None:
        """METRICS: MAVLink telemetry name -> value, each its own series autopilot/name."""
        self._series(utime, "autopilot", metrics)

    def restarted(self, utime: int) -> None:
        """The drone restarted with a new odometry frame: from UTIME on, nothing of the old frame
        (trajectories, map, camera) is drawn over the new one. Earlier times keep it."""
        if self._rec is None:
            return
        self._stamp(utime)
        # The children, not `world` itself: its ViewCoordinates are static and stay.
        for child in ("trajectory", "map", "drone"):
            self._rec.log(f"{self._prefix}world/{child}", rr.Clear(recursive=True))
        for trajectory in self._trajectories.values():
            trajectory.reset()

    def _series(self, utime: int, root: str, metrics: dict[str, float]) -> None:
        if self._rec is None:
            return
        self._stamp(utime)
        for name, value in metrics.items():
            self._rec.log(f"{self._prefix}{root}/{name}", rr.Scalars(value))

    def _stamp(self, utime: int) -> None:
        # datetime64 in µs keeps utime exact; a float of seconds would round it.
        self._rec.set_time(TIMELINE, timestamp=np.datetime64(utime, "us"))


class Viewer:
    """The rerun recording of one station run.

    SAVE_PATH is written under a temporary name in the same directory (SAVE_PATH + ".partial")
    and renamed to SAVE_PATH by close() only: a crashed run never leaves a file that looks
    complete. A .partial file lacks rerun's footer but its data reads back, and
    `rerun rrd optimize X.rrd.partial > X.rrd` makes it whole. With neither SPAWN nor SAVE_PATH
    every method returns at once, so the station calls it unconditionally."""

    def __init__(self, *, spawn: bool = False, save_path: Path | None = None,
                 recording_name: str = "kinfly-ground") -> None:
        self._save_path = save_path
        self._partial_path = None if save_path is None else save_path.with_name(
            save_path.name + ".partial")
        self._views: dict[int, tuple[str, VehicleView]] = {}
        self._shared: list[list[str]] = []  # prefixes of the vehicles whose maps were merged
        self._rec: rr.RecordingStream | None = None
        if not spawn and save_path is None:
            return
        rec = rr.RecordingStream(APPLICATION_ID)
        if not rec.is_enabled():
            raise ViewerError("rerun is disabled in this environment (RERUN=off): "
                              "nothing would be shown or saved")
        # Wall-clock log_time would make two replays of one flight differ; capture_time is the
        # only timeline.
        rec.set_log_time_enabled(False)
        sinks: list[rr.GrpcSink | rr.FileSink] = []
        if spawn:
            # The rerun next to this interpreter is the SDK's own version, found even when the
            # virtualenv is not on PATH.
            bundled = Path(sys.executable).parent / "rerun"
            try:
                rr.spawn(port=_VIEWER_PORT, connect=False, recording=rec,
                         executable_path=str(bundled) if bundled.exists() else None)
            except (RuntimeError, OSError) as error:
                raise ViewerError(f"cannot start the rerun viewer: {error}") from error
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{_VIEWER_PORT}/proxy"))
        if self._partial_path is not None:
            sinks.append(rr.FileSink(self._partial_path))
        try:
            rec.set_sinks(*sinks)  # creates the file
        except (RuntimeError, OSError) as error:
            raise ViewerError(f"cannot write the recording {save_path}: {error}") from error
        rec.send_recording_name(recording_name)
        self._rec = rec

    def vehicle(self, vehicle_id: int, prefix: str) -> VehicleView:
        """The view of VEHICLE_ID, its entities under PREFIX ("" or ending in "/"); a new vehicle
        sends the layout again, with its views added. Asking again for the same vehicle gives the
        same view, whose trajectories carry on."""
        if prefix and not prefix.endswith("/"):
            raise ValueError(f"vehicle prefix {prefix!r} must be empty or end in '/'")
        if vehicle_id in self._views:
            known_prefix, view = self._views[vehicle_id]
            if known_prefix != prefix:
                raise ValueError(f"vehicle {vehicle_id} is already shown under {known_prefix!r}, "
                                 f"not {prefix!r}")
            return view
        if any(known_prefix == prefix for known_prefix, _ in self._views.values()):
            raise ValueError(f"another vehicle is already shown under prefix {prefix!r}")
        # A prefix: the station serves several vehicles, whose maps may come to share a view.
        color = (_VEHICLE_MAP_COLORS[len(self._views) % len(_VEHICLE_MAP_COLORS)] if prefix
                 else None)
        view = VehicleView(self._rec, prefix, color)
        self._views[vehicle_id] = (prefix, view)
        self._send_layout()
        return view

    def shared(self, groups: list[list[int]]) -> None:
        """GROUPS of vehicles whose maps now share a world (merge.py): each gets a view of their
        maps together, before the vehicles' own tabs."""
        self._shared = [[self._views[v][0] for v in group if v in self._views]
                        for group in groups]
        self._send_layout()

    def _send_layout(self) -> None:
        if self._rec is not None:
            # Made active, so a new vehicle's tab appears at once; it replaces whatever layout the
            # user arranged in the viewer meanwhile, a fair price for a vehicle joining mid-flight.
            self._rec.send_blueprint(_layout([p for p, _ in self._views.values()], self._shared),
                                     make_active=True, make_default=True)

    def close(self) -> None:
        """Flush everything logged, finish the .rrd and rename it into place. Later calls to
        this viewer and its vehicle views do nothing."""
        if self._rec is None:
            return
        rec, self._rec = self._rec, None
        for _, view in self._views.values():
            view._rec = None
        # rerun encodes and writes on its own threads: flush() waits until all is in the file,
        # disconnect() then writes the footer and closes it.
        rec.flush()
        rec.disconnect()
        if self._partial_path is not None:
            try:
                os.replace(self._partial_path, self._save_path)
            except OSError as error:
                raise ViewerError(f"cannot move the recording into place at {self._save_path}: "
                                  f"{error}") from error
