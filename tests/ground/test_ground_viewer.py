"""The ground station's rerun output (kinfly_ground.viewer) recorded to an .rrd and read back:
a short synthetic session with a restart gives a file `rerun rrd verify` accepts, holding the
entity paths of the frame tree, stamped with exactly the capture times logged, and the camera
where the keyframes put it. The file only appears under its name once closed; an unwritable path
fails up front, naming it; a viewer with no sink does nothing."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rerun.chunk import RrdReader
from scipy.spatial.transform import Rotation

from kinfly_ground.viewer import Viewer, ViewerError, at_resolution
from rrd_rows import latest, read_rows

SEED = 20261201
T0_US = 1_700_000_000_000_000
KEYFRAME_PERIOD_US = 200_000          # 5 Hz
GROUND_TRUTH_PERIOD_US = 100_000      # twice the keyframe rate, as a mocap would be
KEYFRAMES = 10
RESTART_AFTER = 6                     # keyframes before the drone restarts
HEIGHT, WIDTH = 48, 64                # small: what is tested is the plumbing, not the pixels
INTRINSICS = (53.5, 53.9, 32.0, 24.7)
DEPTH_SCALE_M = 1 / 5000
# Translations travel as float32; poses within 2 m round to well under a micrometre.
TRANSLATION_TOL_M = 1e-6
# The ground's refinement, as a fixed small offset: enough to tell corrected from onboard.
CORRECTION_M = np.array([0.01, -0.02, 0.005])
# Where a loop closure put the mesh's submap: its content moved 3 cm and turned a little.
SUBMAP_CORRECTION = np.eye(4)
SUBMAP_CORRECTION[:3, :3] = Rotation.from_euler("z", 0.02).as_matrix()
SUBMAP_CORRECTION[:3, 3] = [0.03, 0.0, -0.01]


# A pose graph of three submaps: two odometry edges, a loop taken and one refused.
GRAPH_NODES = {0: np.array([0.0, 0.0, 0.0]), 1: np.array([1.0, 0.0, 0.5]),
               2: np.array([0.1, 0.0, 0.05])}
GRAPH_ODOMETRY = [(0, 1), (1, 2)]
GRAPH_LOOPS = [(0, 2, True), (1, 2, False)]


def pose(t_s: float) -> np.ndarray:
    """T_world_cam along a known curve: forward and sideways, slowly yawing."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", 0.2 * t_s).as_matrix()
    T[:3, 3] = [0.3 * t_s, -0.05 * t_s, 0.5 * t_s]
    return T


def depth_image(rng: np.random.Generator) -> np.ndarray:
    """A wall 2 m ahead with Kinect-like noise (~1 cm at 2 m), a few pixels invalid."""
    depth_m = 2.0 + rng.normal(0.0, 0.01, (HEIGHT, WIDTH))
    depth = np.round(depth_m / DEPTH_SCALE_M).astype(np.uint16)
    depth[rng.random((HEIGHT, WIDTH)) < 0.05] = 0
    return depth


def run_session(viewer: Viewer) -> dict[str, Any]:
    """Drive a viewer through keyframes, ground truth, renders, a mesh, health, telemetry and a
    restart; what was logged, for the checks."""
    rng = np.random.default_rng(SEED)
    view = viewer.vehicle(vehicle_id=1, prefix="")
    utimes: set[int] = set()
    last_T_world_cam = np.eye(4)
    onboard_since_restart = []
    restart_utime = 0
    for k in range(KEYFRAMES):
        utime = T0_US + k * KEYFRAME_PERIOD_US
        if k == RESTART_AFTER:
            restart_utime = utime - KEYFRAME_PERIOD_US // 2
            view.restarted(restart_utime)
            utimes.add(restart_utime)
        # After the restart the new odometry frame is the new first keyframe's camera frame.
        t_s = (k - (RESTART_AFTER if k >= RESTART_AFTER else 0)) * KEYFRAME_PERIOD_US * 1e-6
        T_onboard = pose(t_s)
        T_corrected = T_onboard.copy()
        T_corrected[:3, 3] += CORRECTION_M
        # One keyframe the ground could not refine: the camera falls back to the onboard pose.
        corrected = None if k == 3 else T_corrected
        view.keyframe(utime, depth_image(rng), DEPTH_SCALE_M, INTRINSICS, T_onboard, corrected)
        last_T_world_cam = T_onboard if corrected is None else corrected
        if k >= RESTART_AFTER:
            onboard_since_restart.append(T_onboard[:3, 3])
        for half in (0, 1):
            gt_utime = utime + half * GROUND_TRUTH_PERIOD_US
            view.ground_truth(gt_utime, pose(t_s + half * GROUND_TRUTH_PERIOD_US * 1e-6))
            utimes.add(gt_utime)
        view.health(utime, {"link/latency_ms": 12.0 + k, "link/received": k + 1,
                            "tracking/inlier_fraction": 0.9, "tracking/rmse_mm": 4.0})
        view.telemetry(utime, {"battery_voltage_v": 16.0 - 0.01 * k, "altitude_m": 1.5})
        # The flight stack's estimate a centimetre off the camera, its setpoint 10 cm ahead.
        estimate = T_onboard[:3, 3] + [0.01, 0.0, 0.0]
        setpoint = T_onboard[:3, 3] + [0.0, 0.0, 0.1]
        view.flight(utime, estimate, setpoint, {"mode": 3.0, "thrust_n": 4.9 + 0.01 * k})
        last_flight = (estimate, setpoint)
        if k in (2, 8):
            # The second at half resolution, as a station at --model-level 1 renders.
            size = (HEIGHT, WIDTH) if k == 2 else (HEIGHT // 2, WIDTH // 2)
            view.render(utime, rng.integers(0, 256, size, dtype=np.uint8), (HEIGHT, WIDTH))
        utimes.add(utime)
    mesh_utime = T0_US + KEYFRAMES * KEYFRAME_PERIOD_US
    tetrahedron = np.array([[0, 0, 2], [1, 0, 2], [0, 1, 2], [0, 0, 3]], dtype=np.float32)
    view.mesh(mesh_utime, 0, tetrahedron,
              np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int32), None)
    view.submap_poses(mesh_utime, {0: SUBMAP_CORRECTION})
    view.pose_graph(mesh_utime, GRAPH_NODES, GRAPH_ODOMETRY, GRAPH_LOOPS)
    utimes.add(mesh_utime)
    return {"utimes": utimes, "last_T_world_cam": last_T_world_cam, "last_flight": last_flight,
            "onboard_since_restart": np.array(onboard_since_restart),
            "restart_utime": restart_utime}


def test_session_recorded_and_read_back(tmp_path: Path) -> None:
    path = tmp_path / "flight.rrd"
    viewer = Viewer(save_path=path)
    logged = run_session(viewer)
    assert not path.exists(), "the recording must not look complete before close()"
    assert [p.name for p in tmp_path.iterdir()] == ["flight.rrd.partial"]
    viewer.close()
    viewer.close()  # idempotent
    assert [p.name for p in tmp_path.iterdir()] == ["flight.rrd"]

    verify = subprocess.run([Path(sys.executable).parent / "rerun", "rrd", "verify", path],
                            capture_output=True, text=True, timeout=60)
    assert verify.returncode == 0, verify.stderr

    rows = read_rows(path)
    entities = {r.entity for r in rows}
    for expected in ["world", "world/drone/camera", "world/drone/camera/depth",
                     "world/drone/camera/render", "world/map/submap/0/mesh",
                     "world/trajectory/onboard/0", "world/trajectory/corrected/0",
                     "world/trajectory/ground_truth/0", "health/link/latency_ms",
                     "health/link/received", "health/tracking/inlier_fraction",
                     "health/tracking/rmse_mm", "autopilot/battery_voltage_v",
                     "autopilot/altitude_m", "world/drone/estimate", "world/drone/setpoint",
                     "flight/mode", "flight/thrust_n"]:
        assert expected in entities, f"{expected} missing from {sorted(entities)}"

    temporal = [r for r in rows if r.utime is not None]
    assert {r.utime for r in temporal} == logged["utimes"]
    for chunk in RrdReader(path).stream():
        assert chunk.is_static or chunk.timeline_names == ["capture_time"], chunk.entity_path

    translation = latest(rows, "world/drone/camera", "Transform3D:translation")[0]
    np.testing.assert_allclose(translation, logged["last_T_world_cam"][:3, 3],
                               atol=TRANSLATION_TOL_M)
    rotation = np.array(latest(rows, "world/drone/camera", "Transform3D:mat3x3")[0])
    # rerun stores 3x3 matrices column-major.
    np.testing.assert_allclose(rotation.reshape(3, 3).T, logged["last_T_world_cam"][:3, :3],
                               atol=TRANSLATION_TOL_M)

    # The restart cleared the old frame's drawing, and the trajectory started again at block 0
    # with only the new frame's poses.
    cleared = {r.entity for r in rows if r.utime == logged["restart_utime"]
               and r.components.get("Clear:is_recursive") == [True]}
    assert cleared == {"world/trajectory", "world/map", "world/drone"}
    strip = latest(rows, "world/trajectory/onboard/0", "LineStrips3D:strips")[0]
    np.testing.assert_allclose(strip, logged["onboard_since_restart"], atol=TRANSLATION_TOL_M)

    # The submap's mesh stays in its own frame; the pose graph's correction moves it.
    np.testing.assert_allclose(latest(rows, "world/map/submap/0", "Transform3D:translation")[0],
                               SUBMAP_CORRECTION[:3, 3], atol=TRANSLATION_TOL_M)
    # The pose graph: its nodes labelled by submap, each edge between its two nodes.
    nodes = latest(rows, "world/map/graph/nodes", "Points3D:positions")
    np.testing.assert_allclose(nodes, [GRAPH_NODES[k] for k in sorted(GRAPH_NODES)],
                               atol=TRANSLATION_TOL_M)
    assert latest(rows, "world/map/graph/nodes", "Points3D:labels") == ["0", "1", "2"]
    for entity, pairs in (("odometry", GRAPH_ODOMETRY),
                          ("loops/accepted", [(i, j) for i, j, taken in GRAPH_LOOPS if taken]),
                          ("loops/refused", [(i, j) for i, j, taken in GRAPH_LOOPS if not taken])):
        strips = latest(rows, f"world/map/graph/{entity}", "LineStrips3D:strips")
        np.testing.assert_allclose(strips, [[GRAPH_NODES[i], GRAPH_NODES[j]] for i, j in pairs],
                                   atol=TRANSLATION_TOL_M)
    assert latest(rows, "world/drone/camera/depth", "DepthImage:meter") == [
        pytest.approx(1 / DEPTH_SCALE_M)]
    assert latest(rows, "health/link/latency_ms", "Scalars:scalars") == [12.0 + KEYFRAMES - 1]
    estimate, setpoint = logged["last_flight"]
    np.testing.assert_allclose(latest(rows, "world/drone/estimate", "Points3D:positions")[0],
                               estimate, atol=TRANSLATION_TOL_M)
    np.testing.assert_allclose(latest(rows, "world/drone/setpoint", "Points3D:positions")[0],
                               setpoint, atol=TRANSLATION_TOL_M)


def test_long_trajectory_split_into_blocks_without_gaps(tmp_path: Path) -> None:
    """More poses than one block holds: the blocks' last strips, joined at their shared point,
    are the whole trajectory."""
    poses = 600
    path = tmp_path / "long.rrd"
    viewer = Viewer(save_path=path)
    view = viewer.vehicle(vehicle_id=3, prefix="vehicle_3/")
    positions = []
    for i in range(poses):
        T = pose(i * 0.01)
        view.ground_truth(T0_US + i * GROUND_TRUTH_PERIOD_US, T)
        positions.append(T[:3, 3])
    viewer.close()

    rows = read_rows(path)
    blocks = sorted({r.entity for r in rows
                     if r.entity.startswith("vehicle_3/world/trajectory/ground_truth/")},
                    key=lambda e: int(e.rsplit("/", 1)[1]))
    assert len(blocks) > 1
    joined = []
    for b, entity in enumerate(blocks):
        strip = latest(rows, entity, "LineStrips3D:strips")[0]
        joined.extend(strip if b == 0 else strip[1:])
    np.testing.assert_allclose(joined, positions, atol=TRANSLATION_TOL_M)


@pytest.mark.parametrize("where", ["missing_directory", "parent_is_a_file"])
def test_unwritable_path_fails_naming_it(tmp_path: Path, where: str) -> None:
    # Permission bits do not stop root, who runs CI: a missing directory and a file in the way do.
    (tmp_path / "a_file").write_text("")
    parent = tmp_path / ("no_such_dir" if where == "missing_directory" else "a_file")
    path = parent / "flight.rrd"
    with pytest.raises(ViewerError, match=re.escape(str(path))):
        Viewer(save_path=path)


def test_a_coarser_render_is_shown_at_the_keyframes_resolution() -> None:
    """A render at half resolution (kinfly-ground --model-level 1) lies under the keyframe's
    pinhole: each of its pixels covers the 2x2 pixels of the keyframe it was cast for."""
    half = np.arange(6, dtype=np.uint8).reshape(2, 3)
    full = at_resolution(half, (4, 6))
    assert full.shape == (4, 6)
    np.testing.assert_array_equal(full, half.repeat(2, axis=0).repeat(2, axis=1))
    assert at_resolution(full, (4, 6)) is full


def test_no_sink_viewer_is_a_no_op(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    viewer = Viewer()
    view = viewer.vehicle(vehicle_id=1, prefix="")
    view.keyframe(T0_US, np.zeros((HEIGHT, WIDTH), np.uint16), DEPTH_SCALE_M, INTRINSICS,
                  np.eye(4), None)
    view.ground_truth(T0_US, np.eye(4))
    view.render(T0_US, np.zeros((HEIGHT, WIDTH), np.uint8), (HEIGHT, WIDTH))
    view.mesh(T0_US, 0, np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.int32), None)
    view.submap_poses(T0_US, {0: np.eye(4)})
    view.pose_graph(T0_US, GRAPH_NODES, GRAPH_ODOMETRY, GRAPH_LOOPS)
    view.optimised(T0_US, np.zeros((2, 3)))
    view.health(T0_US, {"link/latency_ms": 1.0})
    view.telemetry(T0_US, {"altitude_m": 1.0})
    view.restarted(T0_US)
    viewer.close()
    viewer.close()
    assert list(tmp_path.iterdir()) == []


def test_vehicle_prefixes_are_distinct() -> None:
    viewer = Viewer()
    view = viewer.vehicle(vehicle_id=3, prefix="vehicle_3/")
    assert viewer.vehicle(vehicle_id=3, prefix="vehicle_3/") is view
    with pytest.raises(ValueError):
        viewer.vehicle(vehicle_id=4, prefix="vehicle_3/")
    with pytest.raises(ValueError):
        viewer.vehicle(vehicle_id=3, prefix="vehicle_4/")
    with pytest.raises(ValueError):
        viewer.vehicle(vehicle_id=5, prefix="vehicle_5")


def test_several_vehicles_maps_are_coloured_apart_and_one_alone_is_not(tmp_path: Path) -> None:
    """Serving several vehicles, each map's mesh has its vehicle's colour, so that maps merged
    into one world (merge.py) and drawn in one view (Viewer.shared) tell their vehicles apart; a
    station serving one vehicle draws its map as before, uncoloured."""
    vertices = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1]], dtype=np.float32)
    triangles = np.array([[0, 1, 2]], dtype=np.int32)
    path = tmp_path / "vehicles.rrd"
    viewer = Viewer(save_path=path)
    for vehicle in (3, 4):
        viewer.vehicle(vehicle, f"vehicle_{vehicle}/").mesh(T0_US, 0, vertices, triangles, None)
    viewer.shared([[3, 4]])
    viewer.close()
    rows = read_rows(path)
    colors = [latest(rows, f"vehicle_{v}/world/map/submap/0/mesh", "Mesh3D:albedo_factor")
              for v in (3, 4)]
    assert all(c is not None for c in colors) and colors[0] != colors[1], colors
    alone = tmp_path / "alone.rrd"
    viewer = Viewer(save_path=alone)
    viewer.vehicle(3, "").mesh(T0_US, 0, vertices, triangles, None)
    viewer.close()
    meshes = [r for r in read_rows(alone) if r.entity == "world/map/submap/0/mesh"]
    assert meshes and all(r.components.get("Mesh3D:albedo_factor") is None for r in meshes)
