"""Loop checks by registering submaps (kinfly_ground.registration) on synthetic rooms: a room with
furniture seen from two places a metre apart is registered from a guess off by the drift of a lap
and accepted; another room, a place a repeated structure makes look alike, a bare wall, a
corridor and a round room are refused, each for its own reason; bad inputs are refused by
name."""
from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from rooms import error as _error, perturbed, pose as _pose, room as _room, submap as _submap

from kinfly_ground.registration import RegistrationParams, check_loop

SEED = 23
# A lap's drift (test_posegraph's three laps drift 23 cm in all): the proximity guess is off by
# this much.
GUESS_ERROR_M = 0.15
GUESS_ERROR_RAD = np.deg2rad(8.0)
# GICP on 3 mm noise at 2 cm thinning: well within a voxel of the 1 cm map.
TRANSLATION_TOLERANCE_M = 0.01
ROTATION_TOLERANCE_RAD = np.deg2rad(0.5)
# Near enough that the check meets the surfaces and has to judge their sliding (from 15 cm off a
# lone wall is not found at all: refused for overlap).
SLIDE_GUESS_ERROR_M = 0.03
SLIDE_GUESS_ERROR_RAD = np.deg2rad(2.0)


# Where the two submaps were made: a metre apart, turned 40 degrees, 1.2 m up.
T_WORLD_TARGET = _pose(0.3, (2.0, 1.8, 1.2))
T_WORLD_SOURCE = _pose(1.0, (3.0, 2.2, 1.2))
T_TARGET_SOURCE = np.linalg.inv(T_WORLD_TARGET) @ T_WORLD_SOURCE


def test_a_revisited_place_is_registered_from_a_drifted_guess() -> None:
    rng = np.random.default_rng(SEED)
    room = _room(rng)
    target, source = _submap(room, T_WORLD_TARGET, rng), _submap(room, T_WORLD_SOURCE, rng)
    guess = perturbed(T_TARGET_SOURCE, rng, GUESS_ERROR_M, GUESS_ERROR_RAD)
    check = check_loop(target, source, guess)
    translation_m, rotation_rad = _error(check.T_target_source, T_TARGET_SOURCE)
    print(f"revisited: overlap {check.overlap:.2f}, rms {1000 * check.rms_m:.1f} mm, "
          f"conditioning {check.conditioning:.2f}; error {1000 * translation_m:.1f} "
          f"mm, {np.rad2deg(rotation_rad):.2f} deg (guess {_error(guess, T_TARGET_SOURCE)[0]:.2f} m)")
    assert check.accepted, check.reason
    assert translation_m < TRANSLATION_TOLERANCE_M
    assert rotation_rad < ROTATION_TOLERANCE_RAD


def test_another_room_is_refused() -> None:
    rng = np.random.default_rng(SEED)
    room, other = _room(rng), _room(rng, size_m=(6.0, 3.5, 2.7))
    check = check_loop(_submap(room, T_WORLD_TARGET, rng), _submap(other, T_WORLD_SOURCE, rng),
                       perturbed(T_TARGET_SOURCE, rng, GUESS_ERROR_M, GUESS_ERROR_RAD))
    print(f"another room: {check.reason}")
    assert not check.accepted
    assert "overlap" in check.reason or "residual" in check.reason


def test_a_guess_a_metre_off_is_refused() -> None:
    """The same room, the guess a metre off along the wall, as a place that looks alike gives:
    refused (from a metre off, partners sought within 10 cm do not find the true place); never a
    loop a metre wrong. (Twin rooms, one shell with other furniture, are not told apart here: 0.45
    overlap, 4.0 mm residual. The pose graph rejects such a loop where the odometry disagrees.)"""
    rng = np.random.default_rng(SEED)
    room = _room(rng)
    shifted = T_TARGET_SOURCE @ _pose(0.0, (1.0, 0.0, 0.0))
    check = check_loop(_submap(room, T_WORLD_TARGET, rng), _submap(room, T_WORLD_SOURCE, rng),
                       shifted)
    translation_m, _ = _error(check.T_target_source, T_TARGET_SOURCE)
    print(f"a metre off: {check.reason or 'accepted'}, {translation_m:.2f} m from the truth")
    assert not check.accepted, "a loop a metre wrong"


def test_a_guess_too_far_off_to_register_is_refused_before_registering() -> None:
    """The same room, the guess 2 m off and turned a quarter turn: too few points lie within
    GICP's partner distance of the other submap for it to reach min_overlap, so nothing is
    registered (it cost up to 16 s of a core, docs/ground.md) and the guess comes back as it
    was."""
    rng = np.random.default_rng(SEED)
    room = _room(rng)
    turned = T_TARGET_SOURCE @ _pose(math.pi / 2, (2.0, 0.0, 0.0))
    check = check_loop(_submap(room, T_WORLD_TARGET, rng), _submap(room, T_WORLD_SOURCE, rng),
                       turned)
    print(f"2 m and a quarter turn off: {check.reason}")
    assert not check.accepted
    assert check.reason.startswith("at the guess only"), check.reason
    assert check.overlap < RegistrationParams().min_overlap
    np.testing.assert_array_equal(check.T_target_source, turned)


@pytest.mark.parametrize("scene", ["wall", "corridor", "round room"])
def test_surfaces_that_can_slide_or_turn_are_refused_as_degenerate(scene: str) -> None:
    rng = np.random.default_rng(SEED)
    if scene == "wall":
        mesh = trimesh.creation.box((8.0, 0.01, 3.0), _pose(0.0, (2.5, 4.0, 1.5)))
    elif scene == "corridor":  # two long walls and a floor, open at both ends
        mesh = trimesh.util.concatenate([
            trimesh.creation.box((20.0, 0.01, 2.5), _pose(0.0, (2.5, y, 1.25)))
            for y in (0.3, 3.3)] + [trimesh.creation.box((20.0, 3.0, 0.01),
                                                         _pose(0.0, (2.5, 1.8, 0.0)))])
    else:  # floor, ceiling and a round wall: every translation fixed, the turn about its axis not
        mesh = trimesh.creation.cylinder(radius=2.2, height=2.5, sections=128,
                                         transform=_pose(0.0, (2.5, 2.0, 1.25)))
    T_world_source = _pose(0.3, (3.0, 1.8, 1.2))
    T_target_source = np.linalg.inv(T_WORLD_TARGET) @ T_world_source
    check = check_loop(_submap(mesh, T_WORLD_TARGET, rng), _submap(mesh, T_world_source, rng),
                       perturbed(T_target_source, rng, SLIDE_GUESS_ERROR_M,
                                  SLIDE_GUESS_ERROR_RAD))
    print(f"{scene}: {check.reason}")
    assert not check.accepted
    assert check.reason.startswith("degenerate")


def test_bad_inputs_are_refused_by_name() -> None:
    points = np.random.default_rng(SEED).uniform(0, 1, (100, 3))
    with pytest.raises(ValueError, match="source_points must be an N x 3"):
        check_loop(points, points[:, :2], np.eye(4))
    with pytest.raises(ValueError, match="target_points holds points that are not finite"):
        check_loop(np.vstack([points, [np.nan] * 3]), points, np.eye(4))
    with pytest.raises(ValueError, match="guess must be a finite 4x4"):
        check_loop(points, points, np.eye(3))
    with pytest.raises(ValueError, match="min_overlap"):
        RegistrationParams(min_overlap=0.0)
    few = check_loop(points[:5], points, np.eye(4))
    assert not few.accepted and few.reason.startswith("too few points")
