"""What a station run leaves behind, and its evaluation against ground truth.

Every file is written under a temporary name in its final directory and renamed into place once
complete, so an interrupted export never leaves a file that looks finished; summary.json goes
last and lists the files it vouches for."""
from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

# Poses further apart in time than this are not compared (TUM's own association tolerance).
ATE_MAX_TIME_DIFF_S = 0.02
StampedPose = tuple[int, np.ndarray]


class OutputError(Exception):
    """An output that cannot be written; the message names the file."""


def check_writable(directory: Path) -> None:
    """Creates DIRECTORY and proves a file can be made in it, so that a run fails at its start,
    not after an hour of flight."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=directory, prefix=".kinfly-write-test-"):
            pass
    except OSError as error:
        raise OutputError(f"cannot write to the output directory {directory}: "
                          f"{error.strerror or error}") from error


def write_atomically(path: Path, write: Callable[[Path], Any]) -> Any:
    """Calls WRITE with a temporary path beside PATH, then renames it to PATH."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        result = write(tmp)
        os.replace(tmp, path)
        return result
    except OSError as error:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"cannot write {path}: {error.strerror or error}") from error
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def tum_lines(poses: Iterable[StampedPose]) -> str:
    """TUM trajectory text: `t tx ty tz qx qy qz qw`, camera to world, t in seconds."""
    lines = []
    for utime, T in poses:
        q = Rotation.from_matrix(T[:3, :3]).as_quat()  # (x, y, z, w)
        t = T[:3, 3]
        # Nanometres and 1e-9 of a quaternion component: given poses (a dataset's) are kept
        # as they were, far below any error measured.
        lines.append(f"{utime // 1_000_000}.{utime % 1_000_000:06d} {t[0]:.9f} {t[1]:.9f} "
                     f"{t[2]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")
    return "".join(lines)


def write_tum(path: Path, poses: Iterable[StampedPose]) -> None:
    text = tum_lines(poses)
    write_atomically(path, lambda tmp: tmp.write_text(text))


def _json_safe(value: Any) -> Any:
    """VALUE with every non-finite number as None: JSON has no infinity or NaN (Python writes
    `Infinity`, which strict parsers refuse), and a setting that is off is infinite (a submap's
    distance and duration)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: _json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(item) for item in value]
    return value


def write_json(path: Path, value: Any) -> None:
    text = json.dumps(_json_safe(value), indent=2, allow_nan=False) + "\n"
    write_atomically(path, lambda tmp: tmp.write_text(text))


def _trajectory(poses: list[StampedPose]):
    from evo.core.trajectory import PoseTrajectory3D  # evo is slow to import; only when used
    return PoseTrajectory3D(poses_se3=[T for _, T in poses],
                            timestamps=np.array([u * 1e-6 for u, _ in poses]))


def ate(estimate: list[StampedPose], truth: list[StampedPose]) -> dict[str, Any] | None:
    """Absolute trajectory error (translation) after nearest-time association and SE(3) Umeyama
    alignment, without scale (depth is metric: a scale error is an error). None when fewer than
    three poses match. 'errors' holds each matched pose's (t [s], error [m]), 'T_truth_estimate'
    the alignment (4x4: the estimate's frame into the truth's)."""
    from evo.core import metrics, sync
    from evo.core.geometry import GeometryException
    from evo.core.sync import SyncException

    if len(estimate) < 3 or len(truth) < 3:
        return None
    try:
        gt_sync, est_sync = sync.associate_trajectories(_trajectory(truth), _trajectory(estimate),
                                                        max_diff=ATE_MAX_TIME_DIFF_S)
    except SyncException:
        return None
    if est_sync.num_poses < 3:
        return None
    try:
        rotation, translation, _ = est_sync.align(gt_sync, correct_scale=False)
    except GeometryException:  # degenerate: a hover or a straight line gives no rotation
        return None
    T_truth_estimate = np.eye(4)
    T_truth_estimate[:3, :3], T_truth_estimate[:3, 3] = rotation, translation
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((gt_sync, est_sync))
    stats = ape.get_all_statistics()
    return {
        "rmse_m": float(stats["rmse"]), "mean_m": float(stats["mean"]),
        "median_m": float(stats["median"]), "max_m": float(stats["max"]),
        "matched_poses": int(est_sync.num_poses),
        "errors": list(zip(est_sync.timestamps.tolist(), ape.error.tolist())),
        "T_truth_estimate": T_truth_estimate,
    }


def ate_figures(result: dict[str, Any]) -> dict[str, Any]:
    """An ate() result without its per-pose errors and its alignment: what a summary reports."""
    return {k: v for k, v in result.items() if k not in ("errors", "T_truth_estimate")}


def evaluate(trajectories: dict[str, list[StampedPose]],
             truth: list[StampedPose]) -> dict[str, dict[str, Any]]:
    """ate() of each named trajectory against TRUTH, those that have one."""
    return {name: r for name, poses in trajectories.items()
            if (r := ate(poses, truth)) is not None}


def write_error_plot(path: Path, results: dict[str, dict[str, Any]]) -> None:
    """Translation error over time of each evaluated trajectory (name -> ate() result)."""
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    figure, axes = plt.subplots(figsize=(8, 4))
    start = min(r["errors"][0][0] for r in results.values())
    for name, r in results.items():
        t, e = zip(*r["errors"])
        axes.plot(np.array(t) - start, np.array(e) * 100.0,
                  label=f"{name} (RMSE {r['rmse_m'] * 100:.2f} cm)")
    axes.set_xlabel("time since the first matched pose [s]")
    axes.set_ylabel("translation error [cm]")
    axes.set_title("ATE against ground truth (SE(3)-aligned)")
    axes.grid(True, alpha=0.3)
    axes.legend()
    figure.tight_layout()
    write_atomically(path, lambda tmp: figure.savefig(tmp, format="png", dpi=100))
    plt.close(figure)


def memory() -> dict[str, float]:
    """This process's resident memory now and at its peak [MB, 10^6 bytes]. Both from one read
    of /proc/self/status, where the peak (VmHWM) already includes the present (VmRSS); two
    sources (statm, getrusage) sampled apart could put the peak below the present."""
    kib = {}
    with open("/proc/self/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                kib[key] = int(value.split()[0])
    return {"rss_mb": kib["VmRSS"] * 1024 / 1e6, "peak_rss_mb": kib["VmHWM"] * 1024 / 1e6}


def read_tum(path: Path) -> list[StampedPose]:
    """A TUM trajectory file (ground truth given on the command line)."""
    poses = []
    try:
        text = path.read_text()
    except OSError as error:
        raise OutputError(f"cannot read {path}: {error.strerror or error}") from error
    for number, line in enumerate(text.splitlines(), 1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        try:
            values = [float(v) for v in fields]
            if len(values) != 8:
                raise ValueError
        except ValueError:
            raise OutputError(f"{path}:{number}: not a TUM pose line "
                              "(t tx ty tz qx qy qz qw)") from None
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(values[4:8]).as_matrix()
        T[:3, 3] = values[1:4]
        poses.append((round(values[0] * 1e6), T))
    return poses
