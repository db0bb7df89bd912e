#!/usr/bin/env python3
"""Evaluation of kinfly-fuse runs against ground truth: trajectory ATE and mesh accuracy.

Importable (the integration tests and the benchmark use it) and a CLI:

    python tests/eval/kinfly_eval.py tum     --fuse build/bin/kinfly-fuse --data DIR [fuse args...]
    python tests/eval/kinfly_eval.py replica --fuse build/bin/kinfly-fuse --data DIR [fuse args...]
    python tests/eval/kinfly_eval.py all     --fuse build/bin/kinfly-fuse [--data SHARED_DATA]
    python tests/eval/kinfly_eval.py ate TRAJ.tum GT.tum
    python tests/eval/kinfly_eval.py mesh MESH.ply GT.ply

Each prints one JSON object. `--data` is a TUM sequence folder for `tum` and the Replica folder
(the one holding cam_params.json and office0/) for `replica`.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Sequence

import numpy as np

# --- Targets (DESIGN.md "Budgets"; the figures the README reports against) -----------------------
# ATE RMSE on the shared 200-frame TUM teddy sequence, ground configuration (hashed, 640x480).
ATE_TARGET_GROUND_M = 0.030
# The onboard configuration (QVGA, dense volume, 1 thread) may be somewhat less accurate: it only
# has to be good enough for the ground station to refine.
ATE_TARGET_ONBOARD_M = 0.040
# Mean distance from our Replica mesh vertices to the ground-truth surface (noise-free renders,
# given poses, 1 cm voxels: what is left is TSDF/marching-cubes discretisation error).
MESH_MEAN_TARGET_M = 0.0020

# --- Data layout under the shared data folder (see its README.md) -------------------------------
TUM_SEQUENCE_SUBDIR = "tum_rgbd_freiburg3_teddy_first200/rgbd_dataset_freiburg3_teddy"
REPLICA_SUBDIR = "replica_office0_nvblox/replica"

# The onboard configuration of kinfly-fuse: QVGA (640x480 halved), rolling dense volume, 1 thread.
ONBOARD_ARGS = ["--downsample", "2", "--volume", "dense", "--threads", "1",
                "--icp-fine-iterations", "2", "--model-level", "1"]

# Replica office0 as rendered for NICE-SLAM (cam_params.json): fx, fy, cx, cy and units per metre.
REPLICA_INTRINSICS = "600,600,599.5,339.5"
REPLICA_DEPTH_SCALE = 6553.5
REPLICA_VOXEL_SIZE_M = 0.01
REPLICA_FRAMES = 4  # the sample holds depth000000.png .. depth000003.png only

# Exact point-to-triangle queries cost memory per point; chunks keep the peak small.
_MESH_QUERY_CHUNK = 20000
# The decimated Replica GT mesh lacks some small surfaces the renders show (noise-free rendered
# depth itself lands up to 0.7 m from it on ~0.15 % of pixels), so besides the plain mean we report
# the mean over vertices within this distance, which measures the surface error alone.
MESH_INLIER_M = 0.02


def repo_root() -> Path:
    return Path(__file__).resolve().parents[2]


def data_root(root: Path | None = None) -> Path:
    """The shared data folder: $KINFLY_DATA, else `<repo>/../shared/data` (a sibling of the repo
    in every clone, CI's included)."""
    env = os.environ.get("KINFLY_DATA")
    if env:
        return Path(env).resolve()
    return ((root or repo_root()) / ".." / "shared" / "data").resolve()


# --- ATE -----------------------------------------------------------------------------------------
def ate(traj_path: str | Path, gt_path: str | Path) -> dict[str, float | int]:
    """The ground station's ATE (kinfly_ground.outputs.ate: nearest-time association within
    20 ms, SE(3) Umeyama alignment without scale) of a TUM trajectory file against a TUM ground
    truth file, without the per-pose errors."""
    # Imported here so that the mesh tooling works without evo (and imports stay fast).
    from kinfly_ground import outputs

    result = outputs.ate(outputs.read_tum(Path(traj_path)), outputs.read_tum(Path(gt_path)))
    if result is None:
        raise ValueError(f"{traj_path}: fewer than 3 poses match {gt_path} in time")
    return outputs.ate_figures(result)


def tum_rows(path: str | Path) -> list[tuple[float, str]]:
    """(timestamp, the rest of the line) of a TUM list (depth.txt, rgb.txt: the file;
    groundtruth.txt: the pose), comments and blank lines left out."""
    rows: list[tuple[float, str]] = []
    for line in Path(path).read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            stamp, rest = line.split(maxsplit=1)
            rows.append((float(stamp), rest.strip()))
    return rows


def depth_frame_count(tum_dir: str | Path) -> int:
    """Frames listed in a TUM folder's depth.txt (comment lines start with '#')."""
    lines = (Path(tum_dir) / "depth.txt").read_text().splitlines()
    return sum(1 for line in lines if line.strip() and not line.startswith("#"))


# --- Replica -> TUM layout -----------------------------------------------------------------------
def replica_to_tum(replica_dir: str | Path, out_dir: str | Path,
                   n_frames: int = REPLICA_FRAMES) -> dict[str, Path]:
    """Lays the Replica office0 sample out as a TUM folder kinfly-fuse can read.

    out_dir/depth/NNNNNN.png are symlinks to the Replica depth images (no copies), depth.txt lists
    them with timestamps i * 1.0 s, and poses.tum holds the matching traj.txt poses (row-major 4x4
    camera-to-world, OpenCV axes: already kinfly's camera convention, so no axis change)."""
    replica_dir, out_dir = Path(replica_dir).resolve(), Path(out_dir)
    from kinfly_ground.outputs import tum_lines

    results = replica_dir / "office0" / "results"
    matrices = np.loadtxt(replica_dir / "office0" / "traj.txt").reshape(-1, 4, 4)
    if n_frames > len(matrices):
        raise ValueError(f"{replica_dir}/office0/traj.txt has {len(matrices)} poses, "
                         f"{n_frames} requested")
    (out_dir / "depth").mkdir(parents=True, exist_ok=True)
    depth_lines = ["# depth maps", "# Replica office0 (converted by kinfly_eval.py)",
                   "# timestamp filename"]
    poses_stamped = []
    for i in range(n_frames):
        source = results / f"depth{i:06d}.png"
        if not source.is_file():
            raise FileNotFoundError(f"{source}: missing Replica depth frame")
        link = out_dir / "depth" / f"{i:06d}.png"
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(source)
        # Replica has no capture times; any monotonic clock (here 1 s a frame) pairs frames and
        # poses.
        depth_lines.append(f"{i}.000000 depth/{i:06d}.png")
        poses_stamped.append((i * 1_000_000, matrices[i]))
    depth_txt, poses = out_dir / "depth.txt", out_dir / "poses.tum"
    depth_txt.write_text("\n".join(depth_lines) + "\n")
    poses.write_text("# timestamp tx ty tz qx qy qz qw (camera-to-world, from traj.txt)\n"
                     + tum_lines(poses_stamped))
    return {"dir": out_dir, "depth_txt": depth_txt, "poses": poses}


# --- Mesh accuracy -------------------------------------------------------------------------------
def load_mesh(path: str | Path):
    import trimesh

    # process=False: keep the vertices exactly as written (no merging), they are what we measure.
    mesh = trimesh.load(str(path), process=False, force="mesh")
    if len(mesh.vertices) == 0:
        raise ValueError(f"{path}: mesh has no vertices")
    return mesh


def point_to_surface_distances(points: np.ndarray, gt_mesh) -> np.ndarray:
    """Exact Euclidean distance from each point to the nearest triangle of gt_mesh."""
    import trimesh

    out = np.empty(len(points))
    for start in range(0, len(points), _MESH_QUERY_CHUNK):
        chunk = points[start:start + _MESH_QUERY_CHUNK]
        _, dist, _ = trimesh.proximity.closest_point(gt_mesh, chunk)
        out[start:start + len(chunk)] = dist
    return out


def distance_stats(dist: np.ndarray) -> dict[str, float | int]:
    inliers = dist[dist <= MESH_INLIER_M]
    return {
        "mean_m": float(np.mean(dist)),
        "inlier_mean_m": float(np.mean(inliers)) if len(inliers) else float("nan"),
        "outlier_fraction": float(1.0 - len(inliers) / len(dist)),
        "median_m": float(np.median(dist)),
        "p90_m": float(np.percentile(dist, 90)),
        "max_m": float(np.max(dist)),
        "points": int(len(dist)),
    }


def mesh_accuracy(mesh_ply: str | Path, gt_ply: str | Path) -> dict[str, float | int]:
    """Accuracy of our mesh: distances from every one of its vertices to the ground-truth surface
    (not to GT vertices, whose spacing on the decimated Replica mesh is centimetres)."""
    ours, gt = load_mesh(mesh_ply), load_mesh(gt_ply)
    stats = distance_stats(point_to_surface_distances(np.asarray(ours.vertices), gt))
    stats["faces"] = int(len(ours.faces))
    return stats


def replica_depth_points(replica_dir: str | Path, n_frames: int = REPLICA_FRAMES) -> np.ndarray:
    """Every valid depth pixel of the Replica sample, back-projected and placed in the world by
    its traj.txt pose (N x 3)."""
    from PIL import Image

    replica_dir = Path(replica_dir)
    fx, fy, cx, cy = (float(v) for v in REPLICA_INTRINSICS.split(","))
    matrices = np.loadtxt(replica_dir / "office0" / "traj.txt").reshape(-1, 4, 4)
    clouds = []
    for i in range(n_frames):
        depth = np.asarray(Image.open(replica_dir / "office0" / "results" / f"depth{i:06d}.png"),
                           dtype=np.float64) / REPLICA_DEPTH_SCALE
        v, u = np.nonzero(depth > 0)
        z = depth[v, u]
        cam = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=1)
        clouds.append(cam @ matrices[i, :3, :3].T + matrices[i, :3, 3])
    return np.concatenate(clouds)


def depth_floor(mesh_ply: str | Path, depth_points: np.ndarray,
                gt_ply: str | Path) -> dict[str, float | int]:
    """How far the depth data itself lies from the ground-truth surface where our mesh lies: for
    each of our vertices, the nearest depth point's distance to the surface. A mesh that
    reproduced the depth exactly would score this: a reference, not a strict bound (a mesh that
    leaves out where the two disagree, or smooths towards the decimated surface, can score less).
    (The Replica depth is rendered from the full scan, the GT mesh is that scan decimated.)"""
    from scipy.spatial import cKDTree

    ours, gt = load_mesh(mesh_ply), load_mesh(gt_ply)
    _, nearest = cKDTree(depth_points).query(np.asarray(ours.vertices))
    # Neighbouring vertices share depth points: each point is measured once.
    unique, back = np.unique(nearest, return_inverse=True)
    stats = distance_stats(point_to_surface_distances(depth_points[unique], gt)[back])
    return {"mean_m": stats["mean_m"], "median_m": stats["median_m"], "points": stats["points"]}


# --- Running kinfly-fuse -------------------------------------------------------------------------
def run_fuse(fuse: str | Path, tum_dir: str | Path, out_dir: str | Path,
             extra_args: Sequence[str] = (), timeout_s: float = 1200) -> dict[str, Any]:
    """Runs kinfly-fuse and returns its stats.json. Raises with the tool's output on failure, so a
    failing test shows why the engine gave up."""
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    cmd = [str(fuse), "--tum", str(tum_dir), "--out", str(out_dir), *extra_args]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {proc.returncode}\n"
                           f"stdout:\n{proc.stdout}\nstderr:\n{proc.stderr}")
    return json.loads((Path(out_dir) / "stats.json").read_text())


def stats_summary(stats: dict[str, Any]) -> dict[str, Any]:
    """The stats.json figures worth printing next to accuracy."""
    return {
        "frames": stats.get("frames"),
        "frame_ms_median": stats.get("frame_ms", {}).get("median"),
        "frame_ms_p90": stats.get("frame_ms", {}).get("p90"),
        "tracking": stats.get("tracking"),
        "peak_rss_mb": stats.get("peak_rss_mb"),
        "allocated_blocks": stats.get("allocated_blocks"),
    }


def eval_tum(fuse: str | Path, tum_dir: str | Path, out_dir: str | Path,
             extra_args: Sequence[str] = ()) -> dict[str, Any]:
    stats = run_fuse(fuse, tum_dir, out_dir, extra_args)
    result = {"ate": ate(Path(out_dir) / "trajectory.tum", Path(tum_dir) / "groundtruth.txt")}
    result.update(stats_summary(stats))
    return result


def eval_replica(fuse: str | Path, replica_dir: str | Path, out_dir: str | Path,
                 extra_args: Sequence[str] = ()) -> dict[str, Any]:
    out_dir = Path(out_dir)
    converted = replica_to_tum(replica_dir, out_dir / "replica_tum")
    args = ["--intrinsics", REPLICA_INTRINSICS, "--depth-scale", str(REPLICA_DEPTH_SCALE),
            "--poses", str(converted["poses"]), "--voxel-size", str(REPLICA_VOXEL_SIZE_M),
            *extra_args]
    stats = run_fuse(fuse, converted["dir"], out_dir / "fuse", args)
    mesh, gt = out_dir / "fuse" / "mesh.ply", Path(replica_dir) / "office0_mesh.ply"
    result = {"mesh_accuracy": mesh_accuracy(mesh, gt),
              "depth_floor": depth_floor(mesh, replica_depth_points(replica_dir), gt)}
    result.update(stats_summary(stats))
    return result


def eval_all(fuse: str | Path, data: str | Path, out_dir: str | Path) -> dict[str, Any]:
    """What `make eval` reports: ATE in the ground and onboard configurations on the shared TUM
    sequence and mesh accuracy on Replica, each next to its target."""
    data, out_dir = Path(data), Path(out_dir)
    tum_dir = data / TUM_SEQUENCE_SUBDIR
    ground = eval_tum(fuse, tum_dir, out_dir / "tum_ground")
    onboard = eval_tum(fuse, tum_dir, out_dir / "tum_onboard", ONBOARD_ARGS)
    replica = eval_replica(fuse, data / REPLICA_SUBDIR, out_dir / "replica")
    checks = {
        "ate_ground": (ground["ate"]["rmse_m"], ATE_TARGET_GROUND_M),
        "ate_onboard": (onboard["ate"]["rmse_m"], ATE_TARGET_ONBOARD_M),
        "mesh_mean": (replica["mesh_accuracy"]["mean_m"], MESH_MEAN_TARGET_M),
    }
    report = {
        "summary": {name: {"value_m": round(value, 5), "target_m": target,
                           "met": bool(value <= target)}
                    for name, (value, target) in checks.items()},
        "tum_ground": ground,
        "tum_onboard": onboard | {"fuse_args": ONBOARD_ARGS},
        "replica": replica,
    }
    # Kept beside the runs' outputs so that figures quoted in the README can be traced back.
    (out_dir / "eval.json").write_text(json.dumps(report, indent=2) + "\n")
    return report


# --- CLI -----------------------------------------------------------------------------------------
def _out_dir(requested: str | None) -> tuple[Path, tempfile.TemporaryDirectory | None]:
    if requested:
        Path(requested).mkdir(parents=True, exist_ok=True)
        return Path(requested), None
    tmp = tempfile.TemporaryDirectory(prefix="kinfly-eval-")
    return Path(tmp.name), tmp


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("tum", "replica"):
        p = sub.add_parser(name, allow_abbrev=False,
                           help=f"run kinfly-fuse on a {name} folder and evaluate it")
        p.add_argument("--fuse", default=str(repo_root() / "build" / "bin" / "kinfly-fuse"))
        p.add_argument("--data", required=True)
        p.add_argument("--out", help="output folder (default: a temporary one, removed after)")
    p = sub.add_parser("all", help="everything `make eval` reports, on the shared data folder")
    p.add_argument("--fuse", default=str(repo_root() / "build" / "bin" / "kinfly-fuse"))
    p.add_argument("--data", default=None, help="shared data folder (default: $KINFLY_DATA, "
                   "else <repo>/../shared/data)")
    p.add_argument("--out", help="output folder (default: a temporary one, removed after)")
    p = sub.add_parser("ate", help="ATE of a TUM trajectory against TUM ground truth")
    p.add_argument("traj")
    p.add_argument("gt")
    p = sub.add_parser("mesh", help="distance of a mesh's vertices to a ground-truth surface")
    p.add_argument("mesh")
    p.add_argument("gt")
    # Unknown arguments are passed through to kinfly-fuse (e.g. --downsample 2 --volume dense).
    args, fuse_args = parser.parse_known_args(argv)
    if fuse_args and args.command not in ("tum", "replica"):
        parser.error(f"unrecognised arguments: {' '.join(fuse_args)}")

    if args.command == "ate":
        result: dict[str, Any] = ate(args.traj, args.gt)
    elif args.command == "mesh":
        result = mesh_accuracy(args.mesh, args.gt)
    elif args.command == "all":
        out, tmp = _out_dir(args.out)
        try:
            result = eval_all(args.fuse, args.data or data_root(), out)
        finally:
            if tmp:
                tmp.cleanup()
    else:
        out, tmp = _out_dir(args.out)
        try:
            evaluate = eval_tum if args.command == "tum" else eval_replica
            result = evaluate(args.fuse, args.data, out, fuse_args)
            result["fuse_args"] = fuse_args
        finally:
            if tmp:
                tmp.cleanup()
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
