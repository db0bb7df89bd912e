"""The evaluation tooling itself, on inputs whose answer is known: if these are wrong, every
accuracy figure kinfly reports is wrong. Needs no kinfly binary."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

import kinfly_eval
from png_write import write_gray_png

RNG_SEED = 7  # fixed: tests never seed from the clock


def write_tum(path: Path, stamps: np.ndarray, positions: np.ndarray,
              quats_xyzw: np.ndarray) -> None:
    lines = [f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*p, *q))
             for t, p, q in zip(stamps, positions, quats_xyzw)]
    path.write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")


def random_trajectory(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(RNG_SEED)
    stamps = 1000.0 + np.arange(n) / 30.0
    positions = np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0)
    rotations = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.02, (n, 3)), axis=0))
    return stamps, positions, rotations.as_quat()


def test_ate_is_zero_for_a_rigidly_moved_copy(tmp_path: Path) -> None:
    # kinfly's trajectory lives in the first camera's frame, GT in the mocap frame: the SE(3)
    # alignment must remove exactly that difference.
    stamps, positions, quats = random_trajectory(100)
    R = Rotation.from_euler("xyz", [0.3, -1.1, 2.0])
    offset = np.array([1.0, -2.0, 0.5])
    write_tum(tmp_path / "gt.tum", stamps, positions, quats)
    write_tum(tmp_path / "est.tum", stamps + 0.005, R.apply(positions) + offset,
              (R * Rotation.from_quat(quats)).as_quat())
    result = kinfly_eval.ate(tmp_path / "est.tum", tmp_path / "gt.tum")
    assert result["matched_poses"] == 100
    assert result["rmse_m"] < 1e-6


def test_ate_sees_translation_noise_and_no_scale_correction(tmp_path: Path) -> None:
    stamps, positions, quats = random_trajectory(200)
    write_tum(tmp_path / "gt.tum", stamps, positions, quats)
    # Scaled by 2 about the centroid: a Sim(3) alignment would hide this, SE(3) must not.
    centred = positions - positions.mean(axis=0)
    write_tum(tmp_path / "est.tum", stamps, 2.0 * centred, quats)
    result = kinfly_eval.ate(tmp_path / "est.tum", tmp_path / "gt.tum")
    expected = np.sqrt(np.mean(np.sum(centred**2, axis=1)))  # best SE(3) fit leaves |x|
    assert result["rmse_m"] == pytest.approx(expected, rel=0.05)


def test_ate_skips_frames_without_ground_truth_within_20ms(tmp_path: Path) -> None:
    stamps, positions, quats = random_trajectory(50)
    write_tum(tmp_path / "gt.tum", stamps[10:], positions[10:], quats[10:])
    write_tum(tmp_path / "est.tum", stamps, positions, quats)
    assert kinfly_eval.ate(tmp_path / "est.tum", tmp_path / "gt.tum")["matched_poses"] == 40


def make_replica(root: Path, matrices: np.ndarray) -> Path:
    results = root / "office0" / "results"
    results.mkdir(parents=True)
    np.savetxt(root / "office0" / "traj.txt", matrices.reshape(len(matrices), 16))
    for i in range(len(matrices)):
        write_gray_png(results / f"depth{i:06d}.png", np.full((4, 6), 13107, np.uint16))
    return root


def test_replica_to_tum_keeps_poses_and_links_frames(tmp_path: Path) -> None:
    rng = np.random.default_rng(RNG_SEED)
    matrices = np.tile(np.eye(4), (5, 1, 1))
    matrices[:, :3, :3] = Rotation.random(5, random_state=RNG_SEED).as_matrix()
    matrices[:, :3, 3] = rng.normal(0, 1, (5, 3))
    replica = make_replica(tmp_path / "replica", matrices)

    out = kinfly_eval.replica_to_tum(replica, tmp_path / "tum", n_frames=3)
    entries = [line.split() for line in out["depth_txt"].read_text().splitlines()
               if not line.startswith("#")]
    poses = np.array([line.split() for line in out["poses"].read_text().splitlines()
                      if not line.startswith("#")], dtype=float)
    assert len(entries) == len(poses) == 3
    for i, (stamp, rel) in enumerate(entries):
        assert float(stamp) == poses[i, 0]
        image = out["dir"] / rel
        assert image.resolve() == (replica / "office0" / "results" / f"depth{i:06d}.png")
        np.testing.assert_allclose(poses[i, 1:4], matrices[i, :3, 3], atol=1e-8)
        rotation = Rotation.from_quat(poses[i, 4:8]).as_matrix()
        np.testing.assert_allclose(rotation, matrices[i, :3, :3], atol=1e-8)
    assert all(float(a[0]) < float(b[0]) for a, b in zip(entries, entries[1:]))


def test_mesh_accuracy_measures_distance_to_the_surface_not_vertices(tmp_path: Path) -> None:
    # GT: one large square (4 vertices, 2 triangles). Ours: a dense grid 3 mm above it. Distance
    # to the GT *vertices* would be up to ~1.4 m; to the surface it is 3 mm everywhere.
    gt = trimesh.Trimesh(vertices=[[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]],
                         faces=[[0, 1, 2], [0, 2, 3]], process=False)
    grid = trimesh.creation.box(extents=[1.0, 1.0, 1e-4]).subdivide().subdivide()
    ours = trimesh.Trimesh(vertices=grid.vertices + [0, 0, 0.003], faces=grid.faces,
                           process=False)
    gt.export(tmp_path / "gt.ply")
    ours.export(tmp_path / "ours.ply")  # binary little-endian, as kinfly writes
    result = kinfly_eval.mesh_accuracy(tmp_path / "ours.ply", tmp_path / "gt.ply")
    assert result["points"] == len(ours.vertices)
    assert result["mean_m"] == pytest.approx(0.003, abs=1e-4)
    assert result["p90_m"] == pytest.approx(0.003, abs=1e-4)
    assert result["outlier_fraction"] == 0.0


def test_depth_floor_is_the_data_s_own_distance_where_the_mesh_lies(tmp_path: Path) -> None:
    # GT: the square z = 0. Depth points 1 mm above it on the left half (x < 0) and 2 mm above it
    # on the right, every 5 mm. Our mesh: 3 mm above it, on the left half only. The floor is the
    # left half's 1 mm, not the 1.5 mm of all the data, nor our 3 mm.
    gt = trimesh.Trimesh(vertices=[[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]],
                         faces=[[0, 1, 2], [0, 2, 3]], process=False)
    x, y = np.meshgrid(np.arange(-0.5, 0.5, 0.005), np.arange(-0.5, 0.5, 0.005))
    x, y = x.ravel(), y.ravel()
    points = np.stack([x, y, np.where(x < 0, 0.001, 0.002)], axis=1)
    grid = trimesh.creation.box(extents=[0.4, 0.8, 1e-4]).subdivide().subdivide()
    ours = trimesh.Trimesh(vertices=grid.vertices + [-0.25, 0, 0.003], faces=grid.faces,
                           process=False)
    gt.export(tmp_path / "gt.ply")
    ours.export(tmp_path / "ours.ply")
    floor = kinfly_eval.depth_floor(tmp_path / "ours.ply", points, tmp_path / "gt.ply")
    assert floor["points"] == len(ours.vertices)
    assert floor["mean_m"] == pytest.approx(0.001, abs=1e-6)
    accuracy = kinfly_eval.mesh_accuracy(tmp_path / "ours.ply", tmp_path / "gt.ply")
    assert accuracy["mean_m"] == pytest.approx(0.003, abs=1e-4)
