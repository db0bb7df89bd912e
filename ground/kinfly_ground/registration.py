"""Checks a loop candidate by registering two submaps' surfaces (issue 17 §2): small_gicp's
generalised ICP (Segal et al. 2009; Koide's small_gicp, a kept library) from the candidate's
guess, then tests before the loop reaches the pose graph: it converged, the surfaces overlap,
they agree closely where they do, and the overlap fixes every direction of motion (a single wall
or a corridor lets one submap slide along the other, a round room lets it turn, so the
registration there says nothing about that direction), and registered the other way round,
target onto source, it lands where it did (partial overlap pulls the two directions apart). The
pose graph's robust kernel is the second line: what passes here can still be rejected there if
the rest of the graph disagrees."""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import small_gicp
from scipy.spatial import cKDTree


@dataclasses.dataclass(frozen=True)
class RegistrationParams:
    # Both clouds are thinned to one point per voxel of this size first: GICP's covariances come
    # from each point's neighbours at this scale, and the cost is its count.
    downsampling_m: float = 0.02
    # Each point's normal and covariance from this many neighbours (about 4 cm across at 2 cm):
    # with GICP's default 10, 3 mm of surface noise tilts the normals enough that a corridor's
    # conditioning (below, on translation alone) read 0.03, with 20 it read 0.005.
    normal_neighbours: int = 20
    # How far GICP looks for a partner: the guess's error it can take (proximity candidates are
    # off by the drift since the earlier visit). From 25 cm GICP slid 0.1-0.8 m along the TUM
    # teddy submaps' floor from guesses a few mm right, and the slid fits still passed the
    # gates below (docs/ground.md).
    max_correspondence_m: float = 0.1
    max_iterations: int = 40
    # After alignment, a point of the smaller cloud overlaps when a point of the other lies
    # within this (a voxel or two of the submaps' TSDF).
    inlier_distance_m: float = 0.02
    min_overlap: float = 0.3        # of the smaller cloud's points
    max_rms_m: float = 0.008        # of the overlapping points' distances
    # The weakest direction's share of the strongest in the overlap's point-to-plane
    # information over the six directions of motion: a plane's in-plane directions have none, a
    # corridor's axis and a round room's turn about its axis next to none.
    min_conditioning: float = 0.02
    # The same pair registered the other way round (the target onto the source, from the
    # inverse guess) must land where the forward registration did: the two composed may move the
    # smaller cloud's points by at most this, RMS (half the overlap's inlier distance). GICP
    # pairs each source point with its nearest target point, so partial overlap pulls the two
    # directions differently: on the TUM teddy chain's pairs true loops came back within 0.4 cm
    # and 0.11 degrees, while fits slid along the floor or held near a wrong guess disagreed by
    # 2-17 cm (docs/ground.md, "The loop check").
    max_cycle_m: float = 0.01
    threads: int = 1

    def __post_init__(self) -> None:
        for name in ("downsampling_m", "max_correspondence_m", "inlier_distance_m", "max_rms_m",
                     "max_cycle_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive: {getattr(self, name)}")
        if not 0 < self.min_overlap <= 1:
            raise ValueError(f"min_overlap must be in (0, 1]: {self.min_overlap}")
        if not 0 <= self.min_conditioning < 1:
            raise ValueError(f"min_conditioning must be in [0, 1): {self.min_conditioning}")
        if self.max_iterations < 1 or self.threads < 1 or self.normal_neighbours < 3:
            raise ValueError("max_iterations and threads must be at least 1, normal_neighbours "
                             f"at least 3: {self}")


@dataclasses.dataclass(frozen=True)
class LoopCheck:
    accepted: bool
    T_target_source: np.ndarray  # the registered transform (the guess where GICP did not run)
    overlap: float               # fraction of the smaller cloud's points with a partner
    rms_m: float                 # RMS distance of those points to their partners' planes
    conditioning: float          # the weakest direction of motion's share of the strongest
    reason: str                  # why refused; "" when accepted


# GICP's covariances need each point's neighbours: a cloud thinned to fewer than this many
# points per neighbourhood's worth has none to speak of.
_MIN_POINTS_PER_NEIGHBOURHOOD = 2


def checked_points(name: str, points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must be an N x 3 array of points, got shape {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{name} holds points that are not finite")
    return points


def _conditioning(points: np.ndarray, normals: np.ndarray) -> float:
    """How well the overlap's surfaces fix the motion: the point-to-plane information
    Σ J Jᵀ over the overlapping points, J = [(p − c) × n / r; n] (rotation about their centroid
    c, scaled by their RMS distance r from it so that both halves are in metres); its smallest
    eigenvalue over its largest."""
    if len(normals) < 6:
        return 0.0
    offsets = points - points.mean(axis=0)
    radius = float(np.sqrt(np.mean(np.sum(offsets**2, axis=1))))
    if radius == 0.0:
        return 0.0
    J = np.hstack([np.cross(offsets, normals) / radius, normals])
    eigenvalues = np.linalg.eigvalsh(J.T @ J)
    return float(max(eigenvalues[0], 0.0) / eigenvalues[-1]) if eigenvalues[-1] > 0 else 0.0


def _in_target(target_cloud, source_cloud, T: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SOURCE_CLOUD moved by T beside TARGET_CLOUD, in the target's frame, seen from the smaller
    of the two (a submap wholly inside a larger one overlaps fully): the smaller's points, the
    larger's points and the larger's normals."""
    source_in_target = (T[:3, :3] @ source_cloud.points()[:, :3].T).T + T[:3, 3]
    target_xyz = target_cloud.points()[:, :3]
    if len(target_xyz) < len(source_in_target):
        return target_xyz, source_in_target, (T[:3, :3] @ source_cloud.normals()[:, :3].T).T
    return source_in_target, target_xyz, target_cloud.normals()[:, :3]


def _partners(target_cloud, source_cloud, T: np.ndarray, radius_m: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """_in_target's three, and each smaller point's distance to its nearest partner within
    RADIUS_M (inf where none) and that partner's index."""
    small, large, large_normals = _in_target(target_cloud, source_cloud, T)
    distances, nearest = cKDTree(large).query(small, distance_upper_bound=radius_m)
    return small, large, large_normals, distances, nearest


def _cycle_m(target_cloud, source_cloud, T: np.ndarray, T_back: np.ndarray) -> float:
    """How far the forward registration T composed with the backward one T_BACK (identity
    where the two agree) moves the smaller cloud's points, RMS, in the target's frame."""
    xyz, _, _ = _in_target(target_cloud, source_cloud, T)
    cycle = T @ T_back
    moved = (cycle[:3, :3] @ xyz.T).T + cycle[:3, 3]
    return float(np.sqrt(np.mean(np.sum((moved - xyz) ** 2, axis=1))))


def _fit(target_cloud, source_cloud, T: np.ndarray,
         params: RegistrationParams) -> tuple[float, float, float]:
    """How well SOURCE_CLOUD moved by T fits TARGET_CLOUD: the overlap, the RMS distance along
    the partners' normals, and the overlap's conditioning."""
    small, large, large_normals, distances, nearest = _partners(
        target_cloud, source_cloud, T, params.inlier_distance_m)
    inliers = np.isfinite(distances)
    overlap = float(np.mean(inliers))
    normals = large_normals[nearest[inliers]]
    # Along the partner's normal: two samplings of one surface lie a point spacing apart, but
    # on the same plane.
    along_normal = np.einsum("ij,ij->i", small[inliers] - large[nearest[inliers]], normals)
    rms = float(np.sqrt(np.mean(np.square(along_normal)))) if inliers.any() else float("inf")
    return overlap, rms, _conditioning(large[nearest[inliers]], normals)


def thinned_clouds(target: np.ndarray, source: np.ndarray, downsampling_m: float,
                   params: RegistrationParams) -> tuple[Any, Any, Any, Any]:
    """Both clouds thinned to DOWNSAMPLING_M voxels with their covariances, for small_gicp:
    (target cloud, its tree, source cloud, its tree)."""
    clouds = [small_gicp.preprocess_points(points, downsampling_resolution=downsampling_m,
                                           num_neighbors=params.normal_neighbours,
                                           num_threads=params.threads)
              for points in (target, source)]
    return (*clouds[0], *clouds[1])


def check_loop(target_points: np.ndarray, source_points: np.ndarray,
               T_target_source_guess: np.ndarray,
               params: RegistrationParams | None = None) -> LoopCheck:
    """Registers SOURCE_POINTS (in the source submap's frame) onto TARGET_POINTS (in the
    target's) from the guess, and judges the result."""
    params = params or RegistrationParams()
    target = checked_points("target_points", target_points)
    source = checked_points("source_points", source_points)
    guess = np.asarray(T_target_source_guess, dtype=np.float64)
    if guess.shape != (4, 4) or not np.all(np.isfinite(guess)):
        raise ValueError(f"the guess must be a finite 4x4 matrix, got shape {guess.shape}")
    target_cloud, target_tree, source_cloud, source_tree = thinned_clouds(
        target, source, params.downsampling_m, params)
    min_points = _MIN_POINTS_PER_NEIGHBOURHOOD * params.normal_neighbours
    if target_cloud.size() < min_points or source_cloud.size() < min_points:
        return LoopCheck(False, guess, 0.0, float("inf"), 0.0,
                         f"too few points ({source_cloud.size()} source, "
                         f"{target_cloud.size()} target after thinning)")
    # GICP pairs points only within max_correspondence_m, so from a guess where too few have a
    # partner that near it cannot reach min_overlap: a proximity candidate is off by the drift
    # since the earlier visit, well inside that. Refused here, such a guess (a place 1-2 m
    # along, the place turned) costs a tenth of a second; registered, up to 16 s of a core
    # (small_gicp's Levenberg-Marquardt retrying each of its 40 iterations: test_submaps.py's
    # wrong candidates, measured).
    _, _, _, distances, _ = _partners(target_cloud, source_cloud, guess,
                                      params.max_correspondence_m)
    near_at_guess = float(np.mean(np.isfinite(distances)))
    if near_at_guess < params.min_overlap:
        return LoopCheck(False, guess, near_at_guess, float("inf"), 0.0,
                         f"at the guess only {near_at_guess:.2f} of the points lie within "
                         f"{100 * params.max_correspondence_m:g} cm of the other submap, below "
                         f"min_overlap {params.min_overlap}: too far off to register")
    result = small_gicp.align(target_cloud, source_cloud, target_tree, guess,
                              registration_type="GICP",
                              max_correspondence_distance=params.max_correspondence_m,
                              max_iterations=params.max_iterations, num_threads=params.threads)
    T = np.asarray(result.T_target_source)
    overlap, rms, conditioning = _fit(target_cloud, source_cloud, T, params)
    # The place first (does the fit put the surfaces together at all), then whether they can
    # slide, then whether GICP settled: a fit in the wrong place is reported as that, and
    # sliding surfaces seldom converge, but the sliding is the reason.
    reason = ""
    if overlap < params.min_overlap:
        reason = f"overlap {overlap:.2f} below min_overlap {params.min_overlap}"
    elif rms > params.max_rms_m:
        reason = f"residual {1000 * rms:.1f} mm exceeds max_rms_m {1000 * params.max_rms_m:.1f} mm"
    elif conditioning < params.min_conditioning:
        reason = (f"degenerate: conditioning {conditioning:.3f} below {params.min_conditioning} "
                  "(the surfaces can slide or turn)")
    elif not result.converged:
        reason = f"GICP did not converge in {result.iterations} iterations"
    else:
        # Last, as it costs a second registration: only a fit that passed everything else.
        back = small_gicp.align(source_cloud, target_cloud, source_tree, np.linalg.inv(guess),
                                registration_type="GICP",
                                max_correspondence_distance=params.max_correspondence_m,
                                max_iterations=params.max_iterations, num_threads=params.threads)
        cycle = _cycle_m(target_cloud, source_cloud, T, np.asarray(back.T_target_source))
        if not back.converged:
            reason = (f"registered the other way round GICP did not converge in "
                      f"{back.iterations} iterations")
        elif cycle > params.max_cycle_m:
            reason = (f"registered the other way round it lands {100 * cycle:.1f} cm away, "
                      f"beyond max_cycle_m {100 * params.max_cycle_m:g} cm (the fit is not "
                      "unique)")
    return LoopCheck(reason == "", T, overlap, rms, conditioning, reason)
