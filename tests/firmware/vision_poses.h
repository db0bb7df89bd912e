// The onboard odometry as the estimator's tests and the closed-loop position tests see it: the
// camera's pose in `odom` at 30 Hz with noise of the estimator's own parameters (seeded),
// delivered 30 ms after its capture. One definition, so the estimator's figures and the flights
// that fly on its estimate meet the same odometry.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>

#include "gaussian.h"
#include "kinfly/core/se3.h"
#include "kinfly/flight/estimator.h"

namespace kinfly::flight::test {

constexpr int64_t kVisionPeriodUs = 33333;  // 30 Hz odometry
constexpr int64_t kVisionDelayUs = 30000;   // capture to arrival, as in flight

inline Eigen::Quaterniond rotationFromVector(const Eigen::Vector3d& v) {
  const double angle = v.norm();
  if (angle == 0.0) return Eigen::Quaterniond::Identity();
  return Eigen::Quaterniond(Eigen::AngleAxisd(angle, v / angle));
}

// A pose and when it reaches the estimator.
struct Delivery {
  int64_t arrival_utime;
  VisionPose pose;
};

// The odometry's pose of the camera on the body at T_world_body, captured at capture_utime:
// position noise of vision_pos_std_m in `odom`, rotation noise of vision_att_std_rad in the
// camera frame (the position's drawn first).
inline Delivery odometryPose(int64_t capture_utime, const Pose& T_world_body,
                             const Pose& T_odom_world, const EstimatorParams& params,
                             Gaussian& gaussian) {
  Pose T_odom_cam = T_odom_world * T_world_body * params.T_body_cam;
  T_odom_cam.translation() += params.vision_pos_std_m * gaussian();
  T_odom_cam.linear() =
      T_odom_cam.linear() *
      rotationFromVector(params.vision_att_std_rad * gaussian()).toRotationMatrix();
  return {capture_utime + kVisionDelayUs, {capture_utime, T_odom_cam, {}}};
}

}  // namespace kinfly::flight::test
