// Rigid transforms. Poses are Eigen::Isometry3d named T_a_b (p_a = T_a_b * p_b).
// Quaternion component order on every wire and file is (x, y, z, w), as TUM writes it;
// Eigen's Quaterniond constructor takes (w, x, y, z), so conversions go through these helpers only.
#pragma once

#include <Eigen/Geometry>
#include <array>

namespace kinfly {

using Pose = Eigen::Isometry3d;

// Small-motion update from the ICP twist xi = (rx, ry, rz, tx, ty, tz): the linearisation assumes
// small angles, but the applied update is the exact rotation so repeated updates stay orthonormal.
Pose expTwist(const Eigen::Matrix<double, 6, 1>& xi);

// Projects the rotation back onto SO(3). Chained products drift off it by rounding, and
// Isometry::inverse() transposes the rotation, which amplifies that drift frame after frame:
// every pose the pipeline keeps passes through here.
Pose orthonormalized(const Pose& T);

// (tx, ty, tz, qx, qy, qz, qw) <-> pose.
Pose poseFromTum(const std::array<double, 7>& t_xyz_q_xyzw);
std::array<double, 7> poseToTum(const Pose& T);

// Rotation angle of T's rotation in radians, in [0, pi] (atan2 form: exact for small angles and
// well defined for a slightly non-orthonormal matrix, unlike acos of the trace).
double rotationAngleRad(const Pose& T);

bool isFinite(const Pose& T);

// Degenerate geometry (a corridor, a lone wall): the directions of a camera pose that the scene
// did not pin down, as unit perturbations [the camera's position in the pose's frame (m); a
// rotation in the camera frame (rad)], which is how a filter fusing the pose writes its error.
// Where the pose was tracked from a prior (the IMU's motion), it keeps the prior along them.
struct WeakDirections {
  int count = 0;  // the first `count` of d are set
  std::array<Eigen::Matrix<double, 6, 1>, 6> d{};
};

}  // namespace kinfly
