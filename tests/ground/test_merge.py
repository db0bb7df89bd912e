"""Several drones in one map (kinfly_ground.merge): two vehicles' maps of Replica's office0, each
in its own frame turned half a turn from the other's, are recognised in each other with no guess
and placed within the issue's 2 cm; rooms whose shells look alike from where two drones began, and
another room, are never merged; shared worlds compose as vehicles' groups merge; bad inputs are
refused by name."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from rooms import error, pose, room, submap

from kinfly_ground.merge import PlaceParams, SharedWorlds, recognise_place

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


def _office_maps(mesh: trimesh.Trimesh, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two vehicles' maps of the office (target, source) and the true T_target_source."""
    rng = np.random.default_rng(seed)
    centre = mesh.bounds.mean(axis=0)
    T_world_a = pose(math.pi, (centre[0] - OFFICE_APART_M / 2, centre[1], centre[2]))
    T_world_b = pose(0.3, (centre[0] + OFFICE_APART_M / 2, centre[1] + 0.3, centre[2]))
    return (submap(mesh, T_world_a, rng, OFFICE_MAP_RADIUS_M),
            submap(mesh, T_world_b, rng, OFFICE_MAP_RADIUS_M),
            np.linalg.inv(T_world_a) @ T_world_b)


def _never_merged_wrongly(label: str, mesh: trimesh.Trimesh, T_world_a: np.ndarray,
                          T_world_b: np.ndarray, rng: np.random.Generator, radius_m: float) -> None:
    """Two vehicles' maps of MESH, within RADIUS_M of where each began: merged only at the true
    place, if at all."""
    match = recognise_place(submap(mesh, T_world_a, rng, radius_m),
                            submap(mesh, T_world_b, rng, radius_m))
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
    match = recognise_place(target, source)
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
    choosing the gates: the true place found once in three, and otherwise 115-193 matches that
    lay each map on the other with hardly a turn (floor, ceiling and a wall at the same distance
    in both frames), refused by the residual or by the registration's move from the match."""
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
    match = recognise_place(submap(one, pose(0.3, (2.0, 1.8, 1.2)), rng),
                            submap(other, pose(1.0, (3.0, 2.2, 1.2)), rng))
    print(f"another room: {match.inliers} matches, {match.reason}")
    assert not match.accepted


def _turn(yaw_deg: float, xyz: tuple[float, float, float]) -> np.ndarray:
    return pose(math.radians(yaw_deg), xyz)


def test_shared_worlds_compose_as_groups_merge() -> None:
    """Vehicles 1..4 begin where TRUTH puts them; 3 joins 4's group, 1 and 2 merge, then the two
    groups: every vehicle ends in vehicle 1's world, where the truth puts it, and pairs already
    sharing a world cannot merge again."""
    truth = {1: np.eye(4), 2: _turn(90, (5, 0, 0)), 3: _turn(180, (0, 4, 1)),
             4: _turn(-45, (2, 2, 0))}

    def T(a: int, b: int) -> np.ndarray:
        return np.linalg.inv(truth[a]) @ truth[b]

    worlds = SharedWorlds()
    assert worlds.world_of(3) == 3 and not worlds.merged(1, 2)
    np.testing.assert_array_equal(worlds.T_world_vehicle(2), np.eye(4))
    worlds.merge(4, 3, T(4, 3))
    assert worlds.world_of(3) == 3 and worlds.world_of(4) == 3  # the lower root's world stays
    np.testing.assert_allclose(worlds.T_world_vehicle(4), T(3, 4), atol=1e-12)
    worlds.merge(1, 2, T(1, 2))
    worlds.merge(2, 4, T(2, 4))
    for vehicle in truth:
        assert worlds.world_of(vehicle) == 1
        np.testing.assert_allclose(worlds.T_world_vehicle(vehicle), truth[vehicle], atol=1e-12)
    with pytest.raises(ValueError, match="vehicles 3 and 2 share a world already"):
        worlds.merge(3, 2, T(3, 2))
    with pytest.raises(ValueError, match="finite 4x4"):
        SharedWorlds().merge(1, 2, np.full((4, 4), np.nan))


def test_bad_inputs_are_refused_by_name() -> None:
    points = np.random.default_rng(SEED).uniform(0, 1, (100, 3))
    with pytest.raises(ValueError, match="source_points must be an N x 3"):
        recognise_place(points, points[:, :2])
    with pytest.raises(ValueError, match="target_points holds points that are not finite"):
        recognise_place(np.vstack([points, [np.nan] * 3]), points)
    with pytest.raises(ValueError, match="min_inliers"):
        PlaceParams(min_inliers=2)
    with pytest.raises(ValueError, match="positive"):
        PlaceParams(voxel_m=0.0)
