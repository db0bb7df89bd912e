"""Several drones in one map (issue 17 §2): recognising one vehicle's map in another's, and the
worlds the vehicles' maps share once merged.

A loop within one chain is guessed by the graph (loops.py, submaps.py); two vehicles' maps have no
guess at all: each is in its own drone's odometry frame (its first keyframe's camera, not even
gravity-aligned), so the transform between them is any rigid motion. Place recognition finds it
from the surfaces alone: KISS-Matcher (Lim et al., ICRA 2025; MIT, from PyPI), which matches
FPFH features and keeps the largest mutually consistent set of matches (ROBIN's max clique) before
a graduated non-convexity solve, so that most wrong matches cannot pull it. Its guess then goes
through the loop check (registration.py: GICP, overlap, residual, conditioning, both ways round),
and the registration may move it only by a voxel or two of the recognition: a merge has no graph
behind it to out-vote a wrong one, so it must be right on its own.

Why the two extra gates: a box room turned half a turn lies on itself. From such a guess (the
recognition's, where it found nothing: 0 matches) the loop check accepted a registration 1.08 m
and 171 degrees from the truth, overlap and residual fine (test_merge.py's room, a throwaway run).
And many matches do not make a place right: two drones that began symmetrically in a rectangular
room, each facing its own end, see the same shell in their own frames, and the recognition laid
one map on the other with 100-193 matches; the residual, the conditioning or the move from the
match refused each such case seen (docs/ground.md, "Several drones in one map")."""
from __future__ import annotations

import dataclasses
import math
import threading

import numpy as np

from ._native import rotation_angle_rad
from .registration import LoopCheck, RegistrationParams, check_loop, checked_points


@dataclasses.dataclass(frozen=True)
class PlaceParams:
    # KISS-Matcher's voxel: both clouds are thinned to it and its normal and feature radii are
    # multiples of it (3 and 5 voxels): 5 cm describes furniture and corners, not a map's noise.
    voxel_m: float = 0.05
    # Of the recognition's final, mutually consistent matches: true places gave 135-333, other
    # rooms 0-1; a symmetric place gave up to 193, so this refuses only what found nothing.
    min_inliers: int = 50
    # How far the registration may move the recognition's guess: a voxel, and the turn a voxel
    # makes across a metre.
    max_move_m: float = 0.05
    max_move_rad: float = math.radians(3.0)
    # Two vehicles' whole maps overlap only where both flew, a share of each (a loop's submaps
    # are chosen because they do): office0's maps 5 m apart overlapped 0.27 at the truth.
    registration: RegistrationParams = RegistrationParams(min_overlap=0.2)

    def __post_init__(self) -> None:
        if not (self.voxel_m > 0 and self.max_move_m > 0 and self.max_move_rad > 0):
            raise ValueError(f"voxel_m, max_move_m and max_move_rad must be positive: {self}")
        if self.min_inliers < 3:
            raise ValueError(f"min_inliers must be at least 3 (a rigid motion): {self.min_inliers}")


@dataclasses.dataclass(frozen=True)
class PlaceMatch:
    accepted: bool
    # The registered transform; the recognition's guess where the check refused before
    # registering; the identity where the recognition found nothing.
    T_target_source: np.ndarray
    inliers: int               # the recognition's final matches
    check: LoopCheck | None    # None where the recognition found nothing
    reason: str                # why refused; "" when accepted


def recognise_place(target_points: np.ndarray, source_points: np.ndarray,
                    params: PlaceParams | None = None) -> PlaceMatch:
    """Finds SOURCE_POINTS' surface in TARGET_POINTS' with no guess (each in its own frame) and
    judges the match: T_target_source takes the source's points into the target's frame."""
    params = params or PlaceParams()
    target = checked_points("target_points", target_points)
    source = checked_points("source_points", source_points)
    try:
        # Here, not at the top: PyPI has it for x86_64 only, and the rest of the station runs
        # without it (requirements.txt).
        import kiss_matcher
    except ImportError as error:
        raise RuntimeError("place recognition needs the kiss_matcher package, which PyPI has "
                           f"for x86_64 only ({error})") from error
    matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(params.voxel_m))
    solution = matcher.estimate(source, target)
    inliers = int(matcher.get_num_final_inliers())
    if not solution.valid or inliers < params.min_inliers:
        return PlaceMatch(False, np.eye(4), inliers, None,
                          f"not recognised: {inliers} consistent feature matches, "
                          f"{params.min_inliers} needed")
    guess = np.eye(4)
    guess[:3, :3] = np.asarray(solution.rotation)
    guess[:3, 3] = np.asarray(solution.translation).ravel()
    check = check_loop(target, source, guess, params.registration)
    if not check.accepted:
        return PlaceMatch(False, check.T_target_source, inliers, check, check.reason)
    move = np.linalg.inv(guess) @ check.T_target_source
    move_m, move_rad = float(np.linalg.norm(move[:3, 3])), rotation_angle_rad(move)
    if move_m > params.max_move_m or move_rad > params.max_move_rad:
        return PlaceMatch(False, check.T_target_source, inliers, check, (
            f"the registration moved the recognised place {100 * move_m:.1f} cm and "
            f"{math.degrees(move_rad):.1f} deg, beyond {100 * params.max_move_m:g} cm and "
            f"{math.degrees(params.max_move_rad):g} deg"))
    return PlaceMatch(True, check.T_target_source, inliers, check, "")


class SharedWorlds:
    """Which vehicles' maps share a world. Each vehicle's map is in its own optimised world until
    a merge places it in another's; a group's world is its first vehicle's. Merging two groups
    moves the whole newer group into the older one's world, so every vehicle's placement stays
    one transform T_world_vehicle. Thread-safe: the fusion thread merges, any thread reads."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        # vehicle -> (the vehicle whose world it is in, T_that_vehicle's_world_this_one's)
        self._placed: dict[int, tuple[int, np.ndarray]] = {}

    def _root(self, vehicle: int) -> tuple[int, np.ndarray]:
        return self._placed.get(vehicle, (vehicle, np.eye(4)))

    def world_of(self, vehicle: int) -> int:
        """The vehicle whose world VEHICLE's map is in (itself until merged)."""
        with self._lock:
            return self._root(vehicle)[0]

    def T_world_vehicle(self, vehicle: int) -> np.ndarray:
        """VEHICLE's own optimised world placed in its group's world."""
        with self._lock:
            return self._root(vehicle)[1].copy()

    def merged(self, a: int, b: int) -> bool:
        with self._lock:
            return self._root(a)[0] == self._root(b)[0]

    def merge(self, a: int, b: int, T_a_b: np.ndarray) -> None:
        """B's map registered in A's: T_A_B takes B's own optimised world into A's. The group
        with the greater root joins the other (the first vehicle's world stays put)."""
        T_a_b = np.asarray(T_a_b, dtype=np.float64)
        if T_a_b.shape != (4, 4) or not np.all(np.isfinite(T_a_b)):
            raise ValueError(f"a merge's transform must be a finite 4x4 matrix: {T_a_b}")
        with self._lock:
            root_a, T_ra_a = self._root(a)
            root_b, T_rb_b = self._root(b)
            if root_a == root_b:
                raise ValueError(f"vehicles {a} and {b} share a world already")
            T_ra_rb = T_ra_a @ T_a_b @ np.linalg.inv(T_rb_b)
            if root_b < root_a:  # keep the lower root's world: B's group takes A's in
                root_a, root_b, T_ra_rb = root_b, root_a, np.linalg.inv(T_ra_rb)
            members = [v for v, (root, _) in self._placed.items() if root == root_b]
            for vehicle in {root_b, *members}:
                T_rb_v = self._root(vehicle)[1]
                self._placed[vehicle] = (root_a, T_ra_rb @ T_rb_v)
            self._placed.setdefault(root_a, (root_a, np.eye(4)))
