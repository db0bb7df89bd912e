"""Synthetic rooms for the registration tests (test_registration.py, test_merge.py): a box room
with furniture, and a submap's surface cut from it as a fused map would hold it, with noise, in
the submap's own frame."""
from __future__ import annotations

import numpy as np
import trimesh

POINTS_PER_M2 = 4000      # sampled surface density, above the 2 cm thinning's 2500 per m²
POINT_NOISE_M = 0.003     # a fused submap's surface noise at 1 cm voxels
SUBMAP_RADIUS_M = 2.5     # what a submap holds around where it was made


def pose(yaw_rad: float, xyz: tuple[float, float, float]) -> np.ndarray:
    T = trimesh.transformations.rotation_matrix(yaw_rad, [0, 0, 1])
    T[:3, 3] = xyz
    return T


def room(rng: np.random.Generator, size_m: tuple[float, float, float] = (5.0, 4.0, 2.5),
         furniture: int = 6) -> trimesh.Trimesh:
    """A box room with furniture: boxes of random size and heading on the floor."""
    sx, sy, sz = size_m
    parts = [trimesh.creation.box((sx, sy, sz), pose(0.0, (sx / 2, sy / 2, sz / 2)))]
    for _ in range(furniture):
        extent = rng.uniform([0.3, 0.3, 0.4], [1.2, 0.8, 1.5])
        centre = (rng.uniform(0.6, sx - 0.6), rng.uniform(0.6, sy - 0.6), extent[2] / 2)
        parts.append(trimesh.creation.box(extent, pose(rng.uniform(0, np.pi), centre)))
    return trimesh.util.concatenate(parts)


def submap(mesh: trimesh.Trimesh, T_world_submap: np.ndarray, rng: np.random.Generator,
           radius_m: float = SUBMAP_RADIUS_M) -> np.ndarray:
    """The surface within RADIUS_M of the submap's origin, with noise, in its frame."""
    count = int(mesh.area * POINTS_PER_M2)
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=int(rng.integers(1 << 31)))
    points = points[np.linalg.norm(points - T_world_submap[:3, 3], axis=1) < radius_m]
    points = points + rng.normal(0.0, POINT_NOISE_M, points.shape)
    return trimesh.transform_points(points, np.linalg.inv(T_world_submap))


def perturbed(T: np.ndarray, rng: np.random.Generator, error_m: float, error_rad: float
              ) -> np.ndarray:
    """T moved by ERROR_M along a random direction and turned ERROR_RAD about a random axis."""
    axis = rng.normal(size=3)
    turn = trimesh.transformations.rotation_matrix(error_rad, axis / np.linalg.norm(axis))
    direction = rng.normal(size=3)
    turn[:3, 3] = error_m * direction / np.linalg.norm(direction)
    return T @ turn


def error(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """T's distance from TRUTH: metres and radians."""
    delta = np.linalg.inv(truth) @ T
    angle = np.arccos(np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1.0, 1.0))
    return float(np.linalg.norm(delta[:3, 3])), float(angle)


# A drone's camera for views(): 58 degrees across, as the Kinect's depth, rendered at twice the
# views' size and each 2 x 2 kept at its nearest, so that a near surface sampled more thinly than
# the pixels still hides what lies behind it.
VIEW_FOV_RAD = np.deg2rad(58.0)
VIEW_SIZE = (80, 60)
VIEW_POINTS_PER_M2 = 8000


def views(mesh: trimesh.Trimesh, T_world_submap: np.ndarray, rng: np.random.Generator,
          headings: int = 8) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float, float]]:
    """What a drone that turned on the spot at the submap's origin saw: HEADINGS depth images
    (level, evenly turned) of MESH by z-buffered surface samples, their camera poses in the
    submap's frame and the intrinsics; kinfly_ground.merge.Views' three fields."""
    width, height = VIEW_SIZE
    fine_w, fine_h = 2 * width, 2 * height
    f = fine_w / 2 / np.tan(VIEW_FOV_RAD / 2)
    count = int(mesh.area * VIEW_POINTS_PER_M2)
    samples, _ = trimesh.sample.sample_surface(mesh, count, seed=int(rng.integers(1 << 31)))
    samples = trimesh.transform_points(samples, np.linalg.inv(T_world_submap))
    depths, poses = [], []
    for k in range(headings):
        heading = 2 * np.pi * k / headings
        forward = np.array([np.cos(heading), np.sin(heading), 0.0])
        right = np.array([np.sin(heading), -np.cos(heading), 0.0])
        T_submap_cam = np.eye(4)
        T_submap_cam[:3, :3] = np.column_stack([right, [0.0, 0.0, -1.0], forward])
        p = samples @ T_submap_cam[:3, :3]  # into the camera (the origin is shared)
        z = p[:, 2]
        keep = z > 0.1
        u = np.floor(f * p[keep, 0] / z[keep] + fine_w / 2).astype(int)
        v = np.floor(f * p[keep, 1] / z[keep] + fine_h / 2).astype(int)
        inside = (u >= 0) & (u < fine_w) & (v >= 0) & (v < fine_h)
        fine = np.full((fine_h, fine_w), np.inf)
        np.minimum.at(fine, (v[inside], u[inside]), z[keep][inside])
        depth = fine.reshape(height, 2, width, 2).min(axis=(1, 3))
        depths.append(np.where(np.isfinite(depth), depth, 0.0).astype(np.float32))
        poses.append(T_submap_cam)
    return np.stack(depths), np.stack(poses), (f / 2, f / 2, width / 2, height / 2)
