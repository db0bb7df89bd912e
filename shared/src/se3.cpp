#include "kinfly/core/se3.h"

#include <cmath>

namespace kinfly {

Pose expTwist(const Eigen::Matrix<double, 6, 1>& xi) {
  const Eigen::Vector3d omega = xi.head<3>();
  const double angle = omega.norm();
  Pose T = Pose::Identity();
  if (angle > 0.0) T.linear() = Eigen::AngleAxisd(angle, omega / angle).toRotationMatrix();
  T.translation() = xi.tail<3>();
  return T;
}

Pose poseFromTum(const std::array<double, 7>& v) {
  // Eigen's constructor order is (w, x, y, z); TUM's is (x, y, z, w).
  Eigen::Quaterniond q(v[6], v[3], v[4], v[5]);
  q.normalize();
  Pose T = Pose::Identity();
  T.linear() = q.toRotationMatrix();
  T.translation() = Eigen::Vector3d(v[0], v[1], v[2]);
  return T;
}

std::array<double, 7> poseToTum(const Pose& T) {
  const Eigen::Quaterniond q(T.rotation());
  const Eigen::Vector3d t = T.translation();
  return {t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w()};
}

Pose orthonormalized(const Pose& T) {
  Pose out = T;
  out.linear() = Eigen::Quaterniond(T.linear()).normalized().toRotationMatrix();
  return out;
}

double rotationAngleRad(const Pose& T) {
  const Eigen::Matrix3d& R = T.linear();
  const Eigen::Vector3d axis_sin(R(2, 1) - R(1, 2), R(0, 2) - R(2, 0), R(1, 0) - R(0, 1));
  return std::atan2(0.5 * axis_sin.norm(), 0.5 * (R.trace() - 1.0));
}

bool isFinite(const Pose& T) { return T.matrix().allFinite(); }

}  // namespace kinfly
