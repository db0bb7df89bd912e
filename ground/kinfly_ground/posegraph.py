"""A vehicle's pose graph (issue 17 §2): one node per submap, placed by its anchor T_world_submap;
odometry edges between consecutive submaps, trusted; loop edges from registration, any of which
may be wrong. Optimised by GTSAM's graduated non-convexity (Yang et al., RA-L 2020) with a
truncated quadratic: a loop edge that the rest of the graph cannot agree with gets weight 0 and
moves nothing, however far off it is. Huber or Cauchy kernels only shrink a false loop's pull,
and a few wrong loops in a repeated structure still bend the map.

Poses are 4x4 numpy arrays (T_a_b maps points from b into a, as everywhere in kinfly); GTSAM's
tangent order (rotation first) stays inside this file."""
from __future__ import annotations

import dataclasses

import gtsam
import numpy as np


@dataclasses.dataclass(frozen=True)
class EdgeSigma:
    """One standard deviation of an edge's error per axis: the same on each of the three axes of
    translation and of rotation, so the frame GTSAM measures the error in does not matter."""
    translation_m: float
    rotation_rad: float

    def noise(self) -> gtsam.noiseModel.Base:
        if not (self.translation_m > 0 and self.rotation_rad > 0):
            raise ValueError(f"edge sigmas must be positive: {self}")
        return gtsam.noiseModel.Diagonal.Sigmas(
            np.array([self.rotation_rad] * 3 + [self.translation_m] * 3))


@dataclasses.dataclass(frozen=True)
class PoseGraphParams:
    # A loop's residual, in its own sigmas, is accepted up to this probability of the chi-square
    # distribution with 6 degrees of freedom (GTSAM's own default, 0.99: 16.8 sigma² summed).
    inlier_probability: float = 0.99
    # GNC's weights are 0 or 1 for a truncated quadratic once it has converged; 0.5 splits them.
    accept_weight: float = 0.5

    def __post_init__(self) -> None:
        if not 0.5 <= self.inlier_probability < 1.0:
            raise ValueError(f"inlier_probability must be in [0.5, 1): {self.inlier_probability}")
        if not 0.0 < self.accept_weight < 1.0:
            raise ValueError(f"accept_weight must be in (0, 1): {self.accept_weight}")


@dataclasses.dataclass(frozen=True)
class PoseGraphResult:
    poses: dict[int, np.ndarray]  # node -> optimised T_world_node
    loop_accepted: list[bool]     # per loop, in the order added
    loop_weights: list[float]     # GNC's final weight per loop (0 rejected .. 1 accepted)


# A rigid transform's rotation is orthonormal to round-off; a scaled or sheared one is a bug.
_RIGID_TOLERANCE = 1e-6


def _pose3(T: np.ndarray) -> gtsam.Pose3:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"a pose must be a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError("a pose must be finite, got NaN or infinity")
    R = T[:3, :3]
    if (not np.allclose(R.T @ R, np.eye(3), atol=_RIGID_TOLERANCE)
            or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1])):
        raise ValueError("a pose must be rigid: an orthonormal rotation with determinant +1 and "
                         "a last row of 0 0 0 1")
    return gtsam.Pose3(gtsam.Rot3(R), gtsam.Point3(T[:3, 3]))


class PoseGraph:
    """Nodes are added in any order with an initial estimate; the first one added is held where
    it is (the map's origin does not move). Odometry edges are known inliers; loops are judged."""

    # Holds the first node: far tighter than any edge, so it fixes the gauge without pulling.
    _ANCHOR_SIGMA = 1e-6

    def __init__(self, params: PoseGraphParams | None = None) -> None:
        self.params = params or PoseGraphParams()
        self._graph = gtsam.NonlinearFactorGraph()
        self._initial = gtsam.Values()
        self._known_inliers: list[int] = []
        self._loop_factors: list[int] = []
        self._loops: list[tuple[int, int]] = []

    @property
    def loops(self) -> list[tuple[int, int]]:
        return list(self._loops)

    def add_node(self, node: int, T_world_node: np.ndarray) -> None:
        if not isinstance(node, int) or node < 0:
            raise ValueError(f"a node is a non-negative integer, got {node!r}")
        if self._initial.exists(node):
            raise ValueError(f"node {node} is already in the graph")
        pose = _pose3(T_world_node)
        if self._initial.empty():
            self._known_inliers.append(self._graph.size())
            self._graph.add(gtsam.PriorFactorPose3(
                node, pose, gtsam.noiseModel.Isotropic.Sigma(6, self._ANCHOR_SIGMA)))
        self._initial.insert(node, pose)

    def add_odometry(self, i: int, j: int, T_i_j: np.ndarray, sigma: EdgeSigma) -> None:
        self._check_nodes(i, j)
        self._known_inliers.append(self._graph.size())
        self._graph.add(gtsam.BetweenFactorPose3(i, j, _pose3(T_i_j), sigma.noise()))

    def add_loop(self, i: int, j: int, T_i_j: np.ndarray, sigma: EdgeSigma) -> int:
        """A registered loop between nodes I and J; returns its index in the results."""
        self._check_nodes(i, j)
        self._loop_factors.append(self._graph.size())
        self._graph.add(gtsam.BetweenFactorPose3(i, j, _pose3(T_i_j), sigma.noise()))
        self._loops.append((i, j))
        return len(self._loops) - 1

    def _check_nodes(self, i: int, j: int) -> None:
        for node in (i, j):
            if not self._initial.exists(node):
                raise KeyError(f"node {node} is not in the graph")
        if i == j:
            raise ValueError(f"an edge needs two nodes, got {i} twice")

    def optimise(self) -> PoseGraphResult:
        """Optimises from the initial estimates (the graph is small: submaps, not keyframes)."""
        if self._initial.empty():
            return PoseGraphResult({}, [], [])
        if self._loop_factors:
            gnc = gtsam.GncLMParams()
            gnc.setLossType(gtsam.GncLossType.TLS)
            gnc.setKnownInliers(self._known_inliers)
            optimizer = gtsam.GncLMOptimizer(self._graph, self._initial, gnc)
            optimizer.setInlierCostThresholdsAtProbability(self.params.inlier_probability)
            values = optimizer.optimize()
            weights = np.asarray(optimizer.getWeights())[self._loop_factors]
        else:
            values = gtsam.LevenbergMarquardtOptimizer(self._graph, self._initial).optimize()
            weights = np.zeros(0)
        poses = {int(k): values.atPose3(k).matrix() for k in values.keys()}
        return PoseGraphResult(poses, [bool(w > self.params.accept_weight) for w in weights],
                               [float(w) for w in weights])
