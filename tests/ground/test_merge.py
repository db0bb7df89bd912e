"""Several drones in one map (kinfly_ground.merge): two vehicles' maps of Replica's office0, each
in its own frame turned half a turn from the other's, are recognised in each other with no guess
and placed within the issue's 2 cm, and so are two maps of the TUM teddy sample's real depth;
rooms whose shells look alike from where two drones began, and
another room, are never merged; shared worlds compose as vehicles' groups merge; bad inputs are
refused by name."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from rooms import error, pose, room, submap, views

from kinfly_ground._native import Fusion, FusionPipelineParams, HashedVolumeParams, PinholeCamera
from kinfly_ground.merge import (PlaceParams, SharedWorlds, Views, recognise_place, seen_through,
                                 small_depth)
from kinfly_ground.outputs import read_tum

SEED = 31
# The issue's bound on the relative pose error between two drones' merged maps.
MERGE_TOLERANCE_M = 0.02
MERGE_TOLERANCE_RAD = math.radians(1.0)
# Two drones in office0 (4.4 x 5.0 m), each map the surface within this of where it began (a
# drone's first minute in a small office), 2 m apart and facing opposite ways.
OFFICE_MAP_RADIUS_M = 2.5
OFFICE_APART_M = 2.0
# The issue's two drones 5 m apart facing away, along office0's diagonal (0.7 m from its walls).
FAR_APART_M = 5.0
FAR_MARGIN_M = 0.7
FAR_MAP_RADIUS_M = 3.5
# Two drones 5 m apart in a 10 x 6 m furnished box room, facing away from each other (each
# towards its end wall), each map the surface within 4 m of it: in its own frame each map is a
# room end 2.5 m ahead with walls 3 m either side, so the shells match with no turn at all and
# only the furniture tells the places apart.
HALL_SIZE_M = (10.0, 6.0, 2.7)
HALL_FURNITURE = 12
HALL_MAP_RADIUS_M = 4.0
HALL_SEEDS = (0, 1, 2)
# The TUM teddy sample mapped twice, from its 4th and 5th frames on (every 3rd frame each, so no
# keyframe is in both), the second map 5 m away and turned half a turn, as a second drone's
# odometry frame would be.
TEDDY_FX, TEDDY_FY, TEDDY_CX, TEDDY_CY = 535.4, 539.2, 320.1, 247.6  # freiburg3
TEDDY_DEPTH_SCALE_M = 1 / 5000
TEDDY_FIRST_FRAMES = (4, 5)
TEDDY_FRAME_STEP = 3
TEDDY_VIEW_BLOCK = 8       # 640 x 480 keyframes as 80 x 60 views
GT_MAX_DIFF_US = 20_000


Map = tuple[np.ndarray, Views]  # a vehicle's map: its surface and the depth images it saw


def _map(mesh: trimesh.Trimesh, T_world_map: np.ndarray, rng: np.random.Generator,
         radius_m: float) -> Map:
    """A vehicle's map of MESH in its own frame: the surface within RADIUS_M of where it began,
    and what its camera saw as it turned on the spot there."""
    return submap(mesh, T_world_map, rng, radius_m), Views(*views(mesh, T_world_map, rng))


def _recognise(target: Map, source: Map):
    return recognise_place(target[0], target[1], source[0], source[1])


def _teddy_map(sample_dir: Path, first: int, T_other_world: np.ndarray) -> Map:
    """The sample's keyframes from FIRST on, refined from their true poses moved by
    T_OTHER_WORLD (the drone's odometry frame) and fused at 1 cm: the map's surface and views."""
    truth = read_tum(sample_dir / "groundtruth.txt")
    rows = [line.split() for line in (sample_dir / "depth.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    camera = PinholeCamera(width=640, height=480, fx=TEDDY_FX, fy=TEDDY_FY, cx=TEDDY_CX,
                           cy=TEDDY_CY)
    volume = HashedVolumeParams()
    volume.voxel_size_m = 0.01
    pipeline = FusionPipelineParams()
    pipeline.preprocess.depth_scale_m = TEDDY_DEPTH_SCALE_M
    fusion = Fusion(camera, volume, pipeline, threads=2)
    depths, poses = [], []
    for t, name in rows[first::TEDDY_FRAME_STEP]:
        utime = round(float(t) * 1e6)
        t_truth, T = min(truth, key=lambda pose: abs(pose[0] - utime))
        assert abs(t_truth - utime) <= GT_MAX_DIFF_US
        depth = np.ascontiguousarray(np.asarray(Image.open(sample_dir / name), dtype=np.uint16))
        result = fusion.refine(depth, utime, T_other_world @ T)
        depths.append(small_depth(depth, TEDDY_DEPTH_SCALE_M, TEDDY_VIEW_BLOCK,
                                  pipeline.preprocess.min_depth_m,
                                  pipeline.preprocess.max_depth_m))
        poses.append(result.T_world_cam)
    vertices, _, _ = fusion.snapshot().mesh()
    b = TEDDY_VIEW_BLOCK
    return (np.asarray(vertices, dtype=np.float64),
            Views(np.stack(depths), np.stack(poses),
                  (TEDDY_FX / b, TEDDY_FY / b, TEDDY_CX / b, TEDDY_CY / b)))


def test_two_maps_of_a_real_sequence_are_merged(sample_dir: Path) -> None:
    """Real depth: the Kinect's noise at 3-4 m is what the free-space margin's second term is
    for (without it 8 % of the map's own points lay in front of its own views)."""
    T_other_world = pose(math.pi, (5.0, 0.0, 0.3))
    first, second = TEDDY_FIRST_FRAMES
    match = _recognise(_teddy_map(sample_dir, first, np.eye(4)),
                       _teddy_map(sample_dir, second, T_other_world))
    translation_m, rotation_rad = error(match.T_target_source, np.linalg.inv(T_other_world))
    print(f"TUM teddy, mapped twice: {match.inliers} matches, {match.reason or 'merged'}; "
          f"{1000 * translation_m:.1f} mm, {math.degrees(rotation_rad):.2f} deg from the truth")
    assert match.accepted, match.reason
    assert translation_m <= MERGE_TOLERANCE_M
    assert rotation_rad <= MERGE_TOLERANCE_RAD


def _office_maps(mesh: trimesh.Trimesh, seed: int) -> tuple[Map, Map, np.ndarray]:
    """Two vehicles' maps of the office (target, source) and the true T_target_source."""
    rng = np.random.default_rng(seed)
    centre = mesh.bounds.mean(axis=0)
    T_world_a = pose(math.pi, (centre[0] - OFFICE_APART_M / 2, centre[1], centre[2]))
    T_world_b = pose(0.3, (centre[0] + OFFICE_APART_M / 2, centre[1] + 0.3, centre[2]))
    return (_map(mesh, T_world_a, rng, OFFICE_MAP_RADIUS_M),
            _map(mesh, T_world_b, rng, OFFICE_MAP_RADIUS_M),
            np.linalg.inv(T_world_a) @ T_world_b)


def _never_merged_wrongly(label: str, mesh: trimesh.Trimesh, T_world_a: np.ndarray,
                          T_world_b: np.ndarray, rng: np.random.Generator, radius_m: float) -> None:
    """Two vehicles' maps of MESH, within RADIUS_M of where each began: merged only at the true
    place, if at all."""
    match = _recognise(_map(mesh, T_world_a, rng, radius_m), _map(mesh, T_world_b, rng, radius_m))
    translation_m, rotation_rad = error(match.T_target_source,
                                        np.linalg.inv(T_world_a) @ T_world_b)
    print(f"{label}: {match.inliers} matches, {match.reason or 'merged'}; "
          f"{translation_m:.3f} m from the truth")
    if match.accepted:
        assert translation_m <= MERGE_TOLERANCE_M and rotation_rad <= MERGE_TOLERANCE_RAD


@pytest.mark.parametrize("seed", [SEED, SEED + 1])
def test_two_vehicles_maps_of_one_office_are_merged_with_no_guess(replica_dir: Path,
                                                                  seed: int) -> None:
    mesh = trimesh.load(replica_dir / "office0_mesh.ply")
    target, source, truth = _office_maps(mesh, seed)
    match = _recognise(target, source)
    translation_m, rotation_rad = error(match.T_target_source, truth)
    print(f"office0, {OFFICE_APART_M} m apart and turned: {match.inliers} matches, "
          f"{match.reason or 'merged'}; {1000 * translation_m:.1f} mm, "
          f"{math.degrees(rotation_rad):.2f} deg from the truth")
    assert match.accepted, match.reason
    assert translation_m <= MERGE_TOLERANCE_M
    assert rotation_rad <= MERGE_TOLERANCE_RAD


@pytest.mark.parametrize("seed", [SEED, SEED + 1])
def test_office_maps_5_m_apart_are_never_merged_wrongly(replica_dir: Path, seed: int) -> None:
    """The issue's two drones 5 m apart facing away, in office0 (its diagonal: each map the
    surface within 3.5 m of its drone, a quarter of either in the other). Measured while
    choosing the gates: the true place found once in three, and otherwise 115-234 matches that
    lay each map on the other with hardly a turn (floor, ceiling and a wall at the same distance
    in both frames), which the loop check's gates passed and the free-space test refused."""
    mesh = trimesh.load(replica_dir / "office0_mesh.ply")
    rng = np.random.default_rng(seed)
    lo, hi = mesh.bounds
    diagonal = (hi - lo)[:2] - 2 * FAR_MARGIN_M
    diagonal /= np.linalg.norm(diagonal)
    heading = math.atan2(diagonal[1], diagonal[0])
    a = mesh.bounds.mean(axis=0)
    a[:2] -= FAR_APART_M / 2 * diagonal
    b = a.copy()
    b[:2] += FAR_APART_M * diagonal
    _never_merged_wrongly(f"office0, {FAR_APART_M} m apart facing away", mesh,
                          pose(heading + math.pi, tuple(a)), pose(heading, tuple(b)), rng,
                          FAR_MAP_RADIUS_M)


@pytest.mark.parametrize("seed", HALL_SEEDS)
def test_rooms_whose_shells_look_alike_are_not_merged_on_the_shell(seed: int) -> None:
    """Whatever the recognition finds (mostly nothing; once, 96-100 matches that put the two ends of
    the hall on each other), nothing is merged unless it is the true place."""
    rng = np.random.default_rng(seed)
    hall = room(rng, size_m=HALL_SIZE_M, furniture=HALL_FURNITURE)
    _never_merged_wrongly(f"hall seed {seed}", hall, pose(math.pi, (2.5, 3.0, 1.2)),
                          pose(0.0, (7.5, 3.0, 1.2)), rng, HALL_MAP_RADIUS_M)


def test_another_room_is_not_merged() -> None:
    rng = np.random.default_rng(SEED)
    one, other = room(rng), room(rng, size_m=(6.0, 3.5, 2.7))
    match = _recognise(_map(one, pose(0.3, (2.0, 1.8, 1.2)), rng, 2.5),
                       _map(other, pose(1.0, (3.0, 2.2, 1.2)), rng, 2.5))
    print(f"another room: {match.inliers} matches, {match.reason}")
    assert not match.accepted


def _turn(yaw_deg: float, xyz: tuple[float, float, float]) -> np.ndarray:
    return pose(math.radians(yaw_deg), xyz)


def test_shared_worlds_compose_as_groups_merge() -> None:
    """Vehicles 1..4 begin where TRUTH puts them; 4 is merged with 3 (4 joins 3's world, the
    lower key's), 1 and 2 merge, then the two groups: every vehicle ends in vehicle 1's world, where the truth puts it, and pairs already
    sharing a world cannot merge again."""
    truth = {1: np.eye(4), 2: _turn(90, (5, 0, 0)), 3: _turn(180, (0, 4, 1)),
             4: _turn(-45, (2, 2, 0))}

    def T(a: int, b: int) -> np.ndarray:
        return np.linalg.inv(truth[a]) @ truth[b]

    worlds = SharedWorlds()
    assert worlds.world_of(3) == 3 and not worlds.merged(1, 2)
    np.testing.assert_array_equal(worlds.T_world_map(2), np.eye(4))
    worlds.merge(4, 3, T(4, 3))
    assert worlds.world_of(3) == 3 and worlds.world_of(4) == 3  # the lower root's world stays
    np.testing.assert_allclose(worlds.T_world_map(4), T(3, 4), atol=1e-12)
    worlds.merge(1, 2, T(1, 2))
    worlds.merge(2, 4, T(2, 4))
    for vehicle in truth:
        assert worlds.world_of(vehicle) == 1
        np.testing.assert_allclose(worlds.T_world_map(vehicle), truth[vehicle], atol=1e-12)
    with pytest.raises(ValueError, match="maps 3 and 2 share a world already"):
        worlds.merge(3, 2, T(3, 2))
    with pytest.raises(ValueError, match="finite 4x4"):
        SharedWorlds().merge(1, 2, np.full((4, 4), np.nan))


def test_a_point_is_seen_through_only_in_front_of_what_a_view_saw() -> None:
    """One view of a wall 3 m ahead: a point on it is seen, one 20 cm in front of it is seen
    through, one behind it is hidden and one outside the view not seen at all."""
    depth = np.full((1, 60, 80), 3.0, dtype=np.float32)
    view = Views(depth, np.eye(4)[None], (70.0, 70.0, 40.0, 30.0))
    points = np.array([[0.0, 0.0, 3.0], [0.1, 0.0, 2.8], [0.0, 0.1, 4.0], [0.0, 0.0, -1.0],
                       [5.0, 0.0, 1.0]])
    assert seen_through(points, view, margin_m=0.05) == (3, 1)
    # The margin grows with the depth seen: 0.05 + 0.03 x 3² m = 32 cm hides the 20 cm.
    assert seen_through(points, view, margin_m=0.05, margin_per_m2=0.03) == (3, 0)


def test_a_keyframe_is_made_small_by_its_nearest_depth_in_range() -> None:
    depth = np.array([[5000, 10000, 0, 0],
                      [20000, 1000, 0, 30000]], dtype=np.uint16)  # 1 m, 2 m; 4 m, 0.2 m; 6 m
    small = small_depth(depth, 1 / 5000, block=2, min_depth_m=0.3, max_depth_m=5.0)
    np.testing.assert_allclose(small, [[1.0, 0.0]])  # 0.2 m and 6 m are out of range
    with pytest.raises(ValueError, match="does not divide into 3-pixel blocks"):
        small_depth(depth, 1 / 5000, block=3, min_depth_m=0.3, max_depth_m=5.0)


def test_bad_inputs_are_refused_by_name() -> None:
    points = np.random.default_rng(SEED).uniform(0, 1, (100, 3))
    view = Views(np.ones((1, 4, 4), np.float32), np.eye(4)[None], (2.0, 2.0, 2.0, 2.0))
    with pytest.raises(ValueError, match="source_points must be an N x 3"):
        recognise_place(points, view, points[:, :2], view)
    with pytest.raises(ValueError, match="target_points holds points that are not finite"):
        recognise_place(np.vstack([points, [np.nan] * 3]), view, points, view)
    with pytest.raises(ValueError, match="min_inliers"):
        PlaceParams(min_inliers=2)
    with pytest.raises(ValueError, match="positive"):
        PlaceParams(voxel_m=0.0)
    with pytest.raises(ValueError, match="max_seen_through"):
        PlaceParams(max_seen_through=1.0)
    with pytest.raises(ValueError, match="min_seen"):
        PlaceParams(min_seen=0.0)
    with pytest.raises(ValueError, match="K x H x W depth and K x 4 x 4 poses"):
        Views(np.ones((2, 4, 4)), np.eye(4)[None], (2.0, 2.0, 2.0, 2.0))
