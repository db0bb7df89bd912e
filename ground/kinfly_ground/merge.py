"""Several drones in one map (issue 17 §2): recognising one vehicle's map in another's, and the
worlds the vehicles' maps share once merged.

A loop within one chain is guessed by the graph (loops.py, submaps.py); two vehicles' maps have no
guess at all: each is in its own drone's odometry frame (its first keyframe's camera, not even
gravity-aligned), so the transform between them is any rigid motion. Place recognition finds it
from the surfaces alone: KISS-Matcher (Lim et al., ICRA 2025; MIT, from PyPI), which matches
FPFH features and keeps the largest mutually consistent set of matches (ROBIN's max clique) before
a graduated non-convexity solve, so that most wrong matches cannot pull it. Its guess then goes
through the loop check (registration.py: GICP, overlap, residual, conditioning, both ways round)
and last through voxgraph's free-space test: neither map's surface may lie where the other's
cameras saw through. A merge has no graph behind it to out-vote a wrong one, so it must be right
on its own.

Why the free-space test: surfaces that fit are not enough without a guess. A box room turned half
a turn lies on itself: from such a guess (the recognition's, where it found nothing) the loop
check accepted a registration 1.08 m and 171 degrees from the truth, overlap and residual fine
(test_merge.py's room, a throwaway run). And many matches do not make a place right: two drones
that began symmetrically in a rectangular room, each facing its own end, see the same shell in
their own frames, and the recognition laid one map on the other with 78-234 matches; in office0
such a match passed every gate of the loop check, 5.08 m from the truth. There each map's
furniture stands where the other's cameras saw empty floor: 9-47 % of its points lay where they
saw through, at the true places at most 0.1 % (docs/ground.md, "Several drones in one map")"""
from __future__ import annotations

import dataclasses
import threading
from typing import Any

import numpy as np
import small_gicp

from .registration import (LoopCheck, RegistrationParams, check_loop, checked_points,
                           thinned_clouds)


@dataclasses.dataclass(frozen=True)
class PlaceParams:
    # KISS-Matcher's voxel: both clouds are thinned to it and its normal and feature radii are
    # multiples of it (3 and 5 voxels): 5 cm describes furniture and corners, not a map's noise.
    voxel_m: float = 0.05
    # Of the recognition's final, mutually consistent matches: true places gave 83-344, other
    # rooms 0-1; a symmetric place gave up to 234, so this refuses only what found little.
    min_inliers: int = 50
    # The recognition's guess is only as good as its voxels: on the TUM teddy maps 7-19 cm and
    # 1.4-1.7 degrees off, and from such guesses the loop check's GICP at 2 cm, both ways round,
    # landed 1.2-12 mm apart, as partial overlap pulls the two directions into different nearby
    # minima (a CI run refused the true place at 11 mm, beyond max_cycle_m). A GICP at the
    # recognition's voxel first, pairing points up to this far apart, brought every such guess
    # within 6 mm of where the fine one settles, and from there both ways agreed within 1 mm
    # (16 guesses up to 25 cm and 2.5 degrees off, measured). The check's second direction
    # then starts where the first will settle, so for a merge it says little about whether the
    # place is the right one: the free-space test below is what refuses a wrong place (all the
    # symmetric places of test_merge.py were refused by it, before and after this step).
    coarse_correspondence_m: float = 0.3
    # Two vehicles' whole maps overlap only where both flew, a share of each (a loop's submaps
    # are chosen because they do): office0's maps 5 m apart overlapped 0.27 at the truth.
    registration: RegistrationParams = RegistrationParams(min_overlap=0.2)
    # voxgraph's test, on the maps' own depth images (Views): a registered point of one map may
    # lie in front of what the other's cameras saw by at most this, plus the second term times
    # the depth squared, as a depth camera's noise grows. On the TUM teddy sample's own map and
    # views, 8 % of the map's points lay more than 5 cm in front of a view's depth (most at
    # 3-4 m), 1.2 % beyond this margin (17 cm at 3.5 m).
    free_space_margin_m: float = 0.05
    free_space_margin_per_m2: float = 0.01
    # ... and of the points the other map's views saw at all, at most this share may lie where
    # those views saw through. At the true place 0.000-0.001 of them did; the symmetric places
    # put 0.06-0.47 there, the larger of the two ways at least 0.09 (test_merge.py's office and
    # hall, measured while choosing).
    max_seen_through: float = 0.02
    # Both maps are thinned to a point per voxel of this size before that test.
    free_space_voxel_m: float = 0.05
    # The test says nothing where the other's views saw little of the map: at least this share
    # of its thinned points must be seen (at the true places 0.37-1.0 were).
    min_seen: float = 0.1

    def __post_init__(self) -> None:
        if not all(getattr(self, name) > 0 for name in (
                "voxel_m", "coarse_correspondence_m", "free_space_margin_m",
                "free_space_voxel_m")):
            raise ValueError(f"voxel_m, coarse_correspondence_m, free_space_margin_m and "
                             f"free_space_voxel_m must be positive: {self}")
        if not self.free_space_margin_per_m2 >= 0:
            raise ValueError("free_space_margin_per_m2 must not be negative: "
                             f"{self.free_space_margin_per_m2}")
        if not 0 < self.min_seen <= 1:
            raise ValueError(f"min_seen must be in (0, 1]: {self.min_seen}")
        if not 0 <= self.max_seen_through < 1:
            raise ValueError(f"max_seen_through must be in [0, 1): {self.max_seen_through}")
        if self.min_inliers < 3:
            raise ValueError(f"min_inliers must be at least 3 (a rigid motion): {self.min_inliers}")


@dataclasses.dataclass(frozen=True)
class Views:
    """Depth images a map was made from, made small: where its cameras saw through, the space it
    knows is empty. DEPTH_M is K x H x W (0 where no depth, and where the map took none: beyond
    its fusion's depth range), each pixel the nearest depth of the full image's pixels under
    it, so that a point in front of it by a margin lay in front of every surface that pixel
    saw; T_WORLD_CAM is K x 4 x 4 in the map's own frame (optical
    axes: x right, y down, z forward); INTRINSICS are fx, fy, cx, cy at that size."""
    depth_m: np.ndarray
    T_world_cam: np.ndarray
    intrinsics: tuple[float, float, float, float]

    def __post_init__(self) -> None:
        depth, poses = np.asarray(self.depth_m), np.asarray(self.T_world_cam)
        if depth.ndim != 3 or poses.shape != (len(depth), 4, 4):
            raise ValueError(f"views need K x H x W depth and K x 4 x 4 poses, got "
                             f"{depth.shape} and {poses.shape}")
        if not (np.all(np.isfinite(depth)) and np.all(np.isfinite(poses))):
            raise ValueError("views hold depth or poses that are not finite")


def small_depth(depth: np.ndarray, depth_scale_m: float, block: int, min_depth_m: float,
                max_depth_m: float) -> np.ndarray:
    """A keyframe's raw depth made a view's (Views): metres, each BLOCK x BLOCK pixels' nearest
    depth within the range the map fused (MIN_DEPTH_M to MAX_DEPTH_M), 0 where none. The image's
    sides must be multiples of BLOCK."""
    height, width = depth.shape
    if block < 1 or height % block or width % block:
        raise ValueError(f"a {width}x{height} image does not divide into {block}-pixel blocks")
    metres = depth.astype(np.float32) * np.float32(depth_scale_m)
    metres[(metres < min_depth_m) | (metres > max_depth_m)] = np.inf
    nearest = metres.reshape(height // block, block, width // block, block).min(axis=(1, 3))
    nearest[~np.isfinite(nearest)] = 0.0
    return nearest


def seen_through(points: np.ndarray, views: Views, margin_m: float,
                 margin_per_m2: float = 0.0) -> tuple[int, int]:
    """Of POINTS (in the views' frame): how many some view saw (they project onto a pixel with
    depth, in front of the camera), and how many of those lay in front of what a view saw there
    by more than MARGIN_M + MARGIN_PER_M2 times that depth squared: where the camera saw through
    them, the map knows there is nothing."""
    fx, fy, cx, cy = views.intrinsics
    height, width = views.depth_m.shape[1:]
    observed = np.zeros(len(points), dtype=bool)
    through = np.zeros(len(points), dtype=bool)
    for depth, T_world_cam in zip(views.depth_m, views.T_world_cam):
        T_cam_world = np.linalg.inv(T_world_cam)
        p = points @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        z = p[:, 2]
        in_front = z > 0
        u = np.full(len(p), -1)
        v = np.full(len(p), -1)
        u[in_front] = np.floor(fx * p[in_front, 0] / z[in_front] + cx).astype(int)
        v[in_front] = np.floor(fy * p[in_front, 1] / z[in_front] + cy).astype(int)
        inside = np.flatnonzero(in_front & (u >= 0) & (u < width) & (v >= 0) & (v < height))
        seen = depth[v[inside], u[inside]]
        has_depth = seen > 0
        inside, seen = inside[has_depth], seen[has_depth]
        observed[inside] = True
        through[inside[z[inside] < seen - margin_m - margin_per_m2 * seen**2]] = True
    return int(observed.sum()), int(through.sum())


@dataclasses.dataclass(frozen=True)
class PlaceMatch:
    accepted: bool
    # The registered transform; the recognition's guess, coarsely registered, where the
    # check refused before registering; the identity where the recognition found nothing.
    T_target_source: np.ndarray
    inliers: int               # the recognition's final matches
    check: LoopCheck | None    # None where the recognition found nothing
    reason: str                # why refused; "" when accepted


def thinned(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One point per occupied voxel (the first of it)."""
    _, first = np.unique(np.floor(points / voxel_m).astype(np.int64), axis=0, return_index=True)
    return points[np.sort(first)]


def moved(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """POINTS (N x 3) moved by the rigid transform T."""
    return points @ T[:3, :3].T + T[:3, 3]


def _seen_through_share(points: np.ndarray, views: Views, params: PlaceParams
                        ) -> tuple[float, int]:
    observed, through = seen_through(points, views, params.free_space_margin_m,
                                     params.free_space_margin_per_m2)
    return (through / observed if observed else 0.0), observed


def recognise_place(target_points: np.ndarray, target_views: Views, source_points: np.ndarray,
                    source_views: Views, params: PlaceParams | None = None) -> PlaceMatch:
    """Finds SOURCE_POINTS' surface in TARGET_POINTS' with no guess (each in its own frame, with
    the depth images it was made from) and judges the match: T_target_source takes the source's
    points into the target's frame."""
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
    check = check_loop(target, source, _coarsely_registered(target, source, guess, params),
                       params.registration)
    T = check.T_target_source
    if not check.accepted:
        return PlaceMatch(False, T, inliers, check, check.reason)
    for name, points, views in (
            ("source", moved(thinned(source, params.free_space_voxel_m), T), target_views),
            ("target", moved(thinned(target, params.free_space_voxel_m), np.linalg.inv(T)),
             source_views)):
        share, observed = _seen_through_share(points, views, params)
        if observed < params.min_seen * len(points):
            return PlaceMatch(False, T, inliers, check, (
                f"the other's cameras saw only {observed} of the {name} map's {len(points)} "
                f"points, below min_seen {params.min_seen}: too few to test for free space"))
        if share > params.max_seen_through:
            return PlaceMatch(False, T, inliers, check, (
                f"{100 * share:.0f} % of the {name} map's {observed} points that the other's "
                f"cameras saw lie where they saw through (free space), above "
                f"{100 * params.max_seen_through:g} %"))
    return PlaceMatch(True, T, inliers, check, "")


def _coarsely_registered(target: np.ndarray, source: np.ndarray, guess: np.ndarray,
                         params: PlaceParams) -> np.ndarray:
    """GUESS registered at the recognition's voxel (PlaceParams.coarse_correspondence_m says
    why); the loop check judges what comes of it."""
    registration = params.registration
    target_cloud, target_tree, source_cloud, _ = thinned_clouds(target, source, params.voxel_m,
                                                                registration)
    result = small_gicp.align(target_cloud, source_cloud, target_tree, guess,
                              registration_type="GICP",
                              max_correspondence_distance=params.coarse_correspondence_m,
                              max_iterations=registration.max_iterations,
                              num_threads=registration.threads)
    T = np.asarray(result.T_target_source)
    # Where it did not settle, the recognition's own guess goes to the check, which may still
    # register it, or refuses it by its own gates.
    return T if result.converged and np.all(np.isfinite(T)) else guess


class SharedWorlds:
    """Which maps share a world. A map is known by a key (the station's: a key id and its
    odometry frame's number; keys must order). Each map is in its own optimised world until a
    merge places it in another's; a group's world is its lowest key's. Merging two groups moves
    the whole other group into that world, so every map's placement stays one transform
    T_world_map. Thread-safe: the fusion thread merges, any thread reads."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        # key -> (the key whose world its map is in, T_that_world_this_map's_world)
        self._placed: dict[Any, tuple[Any, np.ndarray]] = {}

    def _root(self, key: Any) -> tuple[Any, np.ndarray]:
        return self._placed.get(key, (key, np.eye(4)))

    def world_of(self, key: Any) -> Any:
        """The map whose world KEY's map is in (itself until merged)."""
        with self._lock:
            return self._root(key)[0]

    def T_world_map(self, key: Any) -> np.ndarray:
        """KEY's map's own optimised world placed in its group's world."""
        with self._lock:
            return self._root(key)[1].copy()

    def merged(self, a: Any, b: Any) -> bool:
        with self._lock:
            return self._root(a)[0] == self._root(b)[0]

    def merge(self, a: Any, b: Any, T_a_b: np.ndarray) -> None:
        """B's map registered in A's: T_A_B takes B's own optimised world into A's. The group
        with the greater root joins the other (the lowest key's world stays put)."""
        T_a_b = np.asarray(T_a_b, dtype=np.float64)
        if T_a_b.shape != (4, 4) or not np.all(np.isfinite(T_a_b)):
            raise ValueError(f"a merge's transform must be a finite 4x4 matrix: {T_a_b}")
        with self._lock:
            root_a, T_ra_a = self._root(a)
            root_b, T_rb_b = self._root(b)
            if root_a == root_b:
                raise ValueError(f"maps {a} and {b} share a world already")
            T_ra_rb = T_ra_a @ T_a_b @ np.linalg.inv(T_rb_b)
            if root_b < root_a:  # keep the lower root's world: B's group takes A's in
                root_a, root_b, T_ra_rb = root_b, root_a, np.linalg.inv(T_ra_rb)
            members = [v for v, (root, _) in self._placed.items() if root == root_b]
            for key in {root_b, *members}:
                T_rb_v = self._root(key)[1]
                self._placed[key] = (root_a, T_ra_rb @ T_rb_v)
            self._placed.setdefault(root_a, (root_a, np.eye(4)))
