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

// (tx, ty, tz, qx, qy, qz, qw) <-> pose.
Pose poseFromTum(const std::array<double, 7>& t_xyz_q_xyzw);
std::array<double, 7> poseToTum(const Pose& T);

// Rotation angle of T's rotation in radians, in [0, pi].
double rotationAngleRad(const Pose& T);

bool isFinite(const Pose& T);

}  // namespace kinfly
