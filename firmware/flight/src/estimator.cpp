#include "kinfly/flight/estimator.h"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>

#include "kinfly/core/range_check.h"

namespace kinfly::flight {

namespace {

using Eigen::Matrix3d;
using Eigen::Quaterniond;
using Eigen::Vector3d;
using Vector6d = Eigen::Matrix<double, 6, 1>;
using Matrix6d = Eigen::Matrix<double, 6, 6>;
using Jacobian = Eigen::Matrix<double, 6, kErrorStates>;

using namespace error_state;

constexpr double kUsToS = 1e-6;
// A weak direction whose translation (rotation) part is at least this long, of the unit
// 6-vector, moves the position (turns the attitude): a reset to a pose keeps the state's own
// there.
constexpr double kWeakPartShare = 0.1;
// Below this angle the series of Exp and Log is exact in double precision.
constexpr double kSmallAngleRad = 1e-8;

Matrix3d skew(const Vector3d& v) {
  Matrix3d S;
  S << 0.0, -v.z(), v.y(), v.z(), 0.0, -v.x(), -v.y(), v.x(), 0.0;
  return S;
}

Quaterniond expRotation(const Vector3d& rotation_vector_rad) {
  const double angle = rotation_vector_rad.norm();
  if (angle < kSmallAngleRad) {
    return Quaterniond(1.0, 0.5 * rotation_vector_rad.x(), 0.5 * rotation_vector_rad.y(),
                       0.5 * rotation_vector_rad.z())
        .normalized();
  }
  return Quaterniond(Eigen::AngleAxisd(angle, rotation_vector_rad / angle));
}

Vector3d logRotation(Quaterniond q) {
  if (q.w() < 0.0) q.coeffs() = -q.coeffs();  // the short way round
  const double s = q.vec().norm();
  if (s < kSmallAngleRad) return 2.0 * q.vec() / q.w();
  return 2.0 * std::atan2(s, q.w()) * q.vec() / s;
}

// The error-state transition of one IMU step, Solà (2017) §5.4: the identity but for the
// blocks below. Multiplying by its blocks costs a sixth of the dense 17x17 product, and this runs
// on every sample and again for every sample a delayed pose replays.
struct Transition {
  double dt_s;
  Matrix3d dv_dtheta;      // -R [f]x dt
  Matrix3d dv_dba;         // -R dt
  Matrix3d dtheta_dtheta;  // Exp(omega dt)^T
  // F X; the velocity and angle rows read the old X.
  Covariance times(const Covariance& X) const {
    Covariance FX = X;
    FX.middleRows<3>(kP) += dt_s * X.middleRows<3>(kV);
    FX.middleRows<3>(kV) += dv_dtheta * X.middleRows<3>(kTheta) + dv_dba * X.middleRows<3>(kBa);
    FX.middleRows<3>(kTheta) =
        dtheta_dtheta * X.middleRows<3>(kTheta) - dt_s * X.middleRows<3>(kBg);
    return FX;
  }
};

// The projector onto the span of the weak directions' translation (part 0) or rotation
// (part 3) parts where they are at least kWeakPartShare long, each turned by R into the frame
// wanted; Gram-Schmidt, so nothing allocates.
Matrix3d weakProjector(const WeakDirections& weak, int part, const Matrix3d& R) {
  Matrix3d along = Matrix3d::Zero();
  for (int i = 0; i < weak.count; ++i) {
    const Vector3d d = weak.d[i].segment<3>(part);
    if (d.norm() <= kWeakPartShare) continue;
    Vector3d u = R * d.normalized();
    u -= along * u;
    if (u.norm() <= kWeakPartShare) continue;
    u.normalize();
    along += u * u.transpose();
  }
  return along;
}

void symmetrise(Covariance& P) { P = 0.5 * (P + P.transpose()).eval(); }

bool isFiniteState(const Covariance& P, const Vector3d& p, const Vector3d& v) {
  return P.allFinite() && p.allFinite() && v.allFinite();
}

}  // namespace

Pose EstimatorParams::defaultBodyCam() {
  Pose T = Pose::Identity();
  // Columns: the optical axes in body FRD (x right = body y, y down = body z, z ahead = body x).
  T.linear() << 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0;
  return T;
}

Status EstimatorParams::validate() const {
  const Matrix3d R = T_body_cam.linear();
  const double orthonormality = (R * R.transpose() - Matrix3d::Identity()).norm();
  return firstError(
      outOfRange("estimator.gyro_noise_rad_s_rthz", gyro_noise_rad_s_rthz, 0, 1, Bound::kOpen),
      outOfRange("estimator.accel_noise_m_s2_rthz", accel_noise_m_s2_rthz, 0, 10, Bound::kOpen),
      outOfRange("estimator.gyro_bias_walk_rad_s2_rthz", gyro_bias_walk_rad_s2_rthz, 0, 1,
                 Bound::kOpen),
      outOfRange("estimator.accel_bias_walk_m_s3_rthz", accel_bias_walk_m_s3_rthz, 0, 10,
                 Bound::kOpen),
      outOfRange("estimator.gravity_m_s2", gravity_m_s2, 9.7, 9.9),
      outOfRange("estimator.imu_gap_s", imu_gap_s, 0, 1, Bound::kOpen),
      outOfRange("estimator.init_pos_std_m", init_pos_std_m, 0, 100, Bound::kOpen),
      outOfRange("estimator.init_vel_std_m_s", init_vel_std_m_s, 0, 100, Bound::kOpen),
      outOfRange("estimator.init_att_std_rad", init_att_std_rad, 0, 3.15, Bound::kOpen),
      outOfRange("estimator.init_gyro_bias_std_rad_s", init_gyro_bias_std_rad_s, 0, 1,
                 Bound::kOpen),
      outOfRange("estimator.init_accel_bias_std_m_s2", init_accel_bias_std_m_s2, 0, 10,
                 Bound::kOpen),
      outOfRange("estimator.init_odom_tilt_std_rad", init_odom_tilt_std_rad, 0, 0.5, Bound::kOpen),
      outOfRange("estimator.odom_tilt_walk_rad_rts", odom_tilt_walk_rad_rts, 0, 0.1),
      outOfRange("estimator.init_still_s", init_still_s, 0.01, 10),
      // The rotation's distance from orthonormal (Frobenius): 1e-6 is float rounding of a
      // configured matrix, anything larger is a typo.
      outOfRange("estimator.T_body_cam rotation's |R R^T - I|", orthonormality, 0, 1e-6),
      outOfRange("estimator.T_body_cam rotation's determinant", R.determinant(), 0, 2,
                 Bound::kOpen),
      outOfRange("estimator.T_body_cam translation's length [m]", T_body_cam.translation().norm(),
                 0, 1),
      outOfRange("estimator.vision_pos_std_m", vision_pos_std_m, 0, 10, Bound::kOpen),
      outOfRange("estimator.vision_att_std_rad", vision_att_std_rad, 0, 1, Bound::kOpen),
      outOfRange("estimator.vision_weak_std", vision_weak_std, 0, 1000, Bound::kOpen),
      outOfRange("estimator.vision_gate_chi2", vision_gate_chi2, 1, 1000),
      outOfRange("estimator.vision_timeout_s", vision_timeout_s, 0, 10, Bound::kOpen),
      outOfRange("estimator.baro_noise_m", baro_noise_m, 0, 100, Bound::kOpen),
      outOfRange("estimator.baro_gate_sigma", baro_gate_sigma, 1, 100),
      outOfRange("estimator.history_s", history_s, 0.3, 2),
      outOfRange("estimator.imu_rate_max_hz", imu_rate_max_hz, 50, 4000),
      outOfRange("estimator.diverged_pos_std_m", diverged_pos_std_m, 0, 1000, Bound::kOpen),
      outOfRange("estimator.vision_reset_rejections", vision_reset_rejections, 1, 1000),
      outOfRange("estimator.diverged_resets", diverged_resets, 1, kMaxDivergedResets),
      outOfRange("estimator.diverged_reset_window_s", diverged_reset_window_s, 0, 3600,
                 Bound::kOpen));
}

Estimator::Estimator(const EstimatorParams& params)
    : params_(params),
      ring_(static_cast<size_t>(std::ceil(params.history_s * params.imu_rate_max_hz)) + 1) {
  // Solà (2017) §5.4's perturbation impulses, from densities: a step of dt adds density² * dt to
  // the velocity, angle and bias errors; position gets its noise through velocity only.
  Q_density_.setZero();
  Q_density_.diagonal().segment<3>(kV).setConstant(std::pow(params.accel_noise_m_s2_rthz, 2));
  Q_density_.diagonal().segment<3>(kTheta).setConstant(std::pow(params.gyro_noise_rad_s_rthz, 2));
  Q_density_.diagonal().segment<3>(kBg).setConstant(
      std::pow(params.gyro_bias_walk_rad_s2_rthz, 2));
  Q_density_.diagonal().segment<3>(kBa).setConstant(
      std::pow(params.accel_bias_walk_m_s3_rthz, 2));
  Q_density_.diagonal().segment<2>(kPhi).setConstant(std::pow(params.odom_tilt_walk_rad_rts, 2));
}

void Estimator::initialise(const EstimatorInit& init) {
  Nominal x;
  x.p_world_body_m = init.p_world_body_m;
  x.v_world_body_m_s = init.v_world_body_m_s;
  x.q_world_body = init.q_world_body.normalized();
  x.gyro_bias_rad_s = init.gyro_bias_rad_s;
  x.accel_bias_m_s2 = init.accel_bias_m_s2;
  T_world_odom_ = init.T_world_odom;
  health_ = EstimatorHealth();
  last_imu_utime_ = init.utime;
  start(init.utime, x);
}

void Estimator::start(int64_t utime, const Nominal& x) {
  head_ = 0;
  count_ = 1;
  Entry& first = ring_[0];
  first.imu = ImuSample();
  first.imu.utime = utime;
  first.x = x;
  first.P = initialCovariance();
  barrier_utime_ = utime;
  reset_utime_ = utime;
  last_vision_utime_ = -1;
  baro_ref_m_ = std::numeric_limits<double>::quiet_NaN();
  baro_ref_sum_m_ = 0.0;
  baro_ref_samples_ = 0;
}

Covariance Estimator::initialCovariance() const {
  Covariance P = Covariance::Zero();
  P.diagonal().segment<3>(kP).setConstant(std::pow(params_.init_pos_std_m, 2));
  P.diagonal().segment<3>(kV).setConstant(std::pow(params_.init_vel_std_m_s, 2));
  P.diagonal().segment<3>(kTheta).setConstant(std::pow(params_.init_att_std_rad, 2));
  P.diagonal().segment<3>(kBg).setConstant(std::pow(params_.init_gyro_bias_std_rad_s, 2));
  P.diagonal().segment<3>(kBa).setConstant(std::pow(params_.init_accel_bias_std_m_s2, 2));
  P.diagonal().segment<2>(kPhi).setConstant(std::pow(params_.init_odom_tilt_std_rad, 2));
  return P;
}

void Estimator::push(const ImuSample& sample, double dt_s) {
  const Entry& previous = newest();
  const bool full = count_ == static_cast<int>(ring_.size());
  // The slot after the newest: when full, that is the oldest, dropped here.
  Entry& next = ring_[(head_ + count_) % ring_.size()];
  next.x = previous.x;
  next.P = previous.P;
  next.imu = sample;
  switch (step(next.x, next.P, sample, dt_s, &health_.baro_test_ratio)) {
    case Height::kFused: ++health_.baro_fused; break;
    case Height::kRejectedGate: ++health_.baro_rejected_gate; break;
    case Height::kNone:
      // The reference: the mean of the first init_still_s of readings after the start, each
      // less the state's height (world's z is down): one reading's noise would stay in it for
      // good.
      if (std::isfinite(sample.baro_alt_m) && !std::isfinite(baro_ref_m_)) {
        if (baro_ref_samples_ == 0) baro_ref_first_utime_ = sample.utime;
        baro_ref_sum_m_ += sample.baro_alt_m + next.x.p_world_body_m.z();
        ++baro_ref_samples_;
        if (static_cast<double>(sample.utime - baro_ref_first_utime_) * kUsToS >=
            params_.init_still_s)
          baro_ref_m_ = baro_ref_sum_m_ / static_cast<double>(baro_ref_samples_);
      }
      break;
  }
  if (full) {
    head_ = (head_ + 1) % static_cast<int>(ring_.size());
  } else {
    ++count_;
  }
}

VisionLinearisation lineariseVision(const Vector3d& p_world_body_m,
                                    const Quaterniond& q_world_body, const Pose& T_world_odom,
                                    const Pose& T_odom_cam, const Pose& T_body_cam) {
  const Matrix3d R_world_body = q_world_body.toRotationMatrix();
  const Vector3d t_body_cam_m = T_body_cam.translation();
  const Pose T_world_cam = T_world_odom * T_odom_cam;
  VisionLinearisation model;
  // The camera's position and the body's attitude: the attitude innovation lives in the same body
  // frame as δθ, so its Jacobian is the identity; the lever arm couples δθ into the position.
  model.innovation.head<3>() =
      T_world_cam.translation() - (p_world_body_m + R_world_body * t_body_cam_m);
  const Matrix3d R_world_body_measured = T_world_cam.linear() * T_body_cam.linear().transpose();
  model.innovation.tail<3>() =
      logRotation(Quaterniond(R_world_body.transpose() * R_world_body_measured).normalized());

  Jacobian& H = model.H;
  H.setZero();
  H.block<3, 3>(0, kP).setIdentity();
  H.block<3, 3>(0, kTheta) = -R_world_body * skew(t_body_cam_m);
  H.block<3, 3>(3, kTheta).setIdentity();
  // The pose as measured turns with odom's tilt about world's origin: Exp(δφ) moves the camera by
  // δφ × p and turns the measured attitude by R^T δφ in the body (world's x and y only).
  H.block<3, 2>(0, kPhi) = skew(T_world_cam.translation()).leftCols<2>();
  H.block<3, 2>(3, kPhi) = -R_world_body.transpose().leftCols<2>();
  return model;
}

// Solà (2017) §5.4 (nominal state and error-state Jacobian), the angular error local to the body.
void Estimator::predict(Nominal& x, Covariance& P, const ImuSample& imu, double dt_s) const {
  const Vector3d omega_rad_s = imu.gyro_rad_s - x.gyro_bias_rad_s;
  const Vector3d f_body_m_s2 = imu.accel_m_s2 - x.accel_bias_m_s2;
  const Matrix3d R_world_body = x.q_world_body.toRotationMatrix();
  const Quaterniond dq = expRotation(omega_rad_s * dt_s);
  // The specific force turned by the mid-step attitude: with the start's, a rotating body would
  // see a bias of |f| * |omega| * dt / 2 (25 mm/s² at 1 rad/s and 200 Hz).
  const Matrix3d R_world_body_mid =
      R_world_body * expRotation(0.5 * omega_rad_s * dt_s).toRotationMatrix();
  const Vector3d a_world_m_s2 =
      R_world_body_mid * f_body_m_s2 + Vector3d(0.0, 0.0, params_.gravity_m_s2);

  x.p_world_body_m += x.v_world_body_m_s * dt_s + 0.5 * a_world_m_s2 * dt_s * dt_s;
  x.v_world_body_m_s += a_world_m_s2 * dt_s;
  x.q_world_body = (x.q_world_body * dq).normalized();

  const Transition F{dt_s, -R_world_body_mid * skew(f_body_m_s2) * dt_s, -R_world_body_mid * dt_s,
                     dq.toRotationMatrix().transpose()};
  // F P F^T = F (F P)^T, P symmetric.
  P = F.times(F.times(P).transpose()) + Q_density_ * dt_s;
  symmetrise(P);
}

bool Estimator::fuse(Nominal& x, Covariance& P, const Pose& T_odom_cam,
                     const WeakDirections& weak) {
  const Pose T_world_odom = alignment(x);
  const VisionLinearisation model = lineariseVision(x.p_world_body_m, x.q_world_body,
                                                    T_world_odom, T_odom_cam, params_.T_body_cam);
  const Vector6d& innovation = model.innovation;
  const Jacobian& H = model.H;

  // Isotropic noise is the same in odom, world, camera and body frames.
  Matrix6d R_noise = Matrix6d::Zero();
  R_noise.diagonal().head<3>().setConstant(std::pow(params_.vision_pos_std_m, 2));
  R_noise.diagonal().tail<3>().setConstant(std::pow(params_.vision_att_std_rad, 2));
  addWeak(weak, T_world_odom.linear(), &R_noise);

  const Eigen::Matrix<double, 6, kErrorStates> HP = H * P;
  const Matrix6d S = HP * H.transpose() + R_noise;
  const Eigen::LLT<Matrix6d> S_llt(S);
  const double nis = innovation.dot(S_llt.solve(innovation));
  const double nis_pos = innovation.head<3>().dot(
      S.topLeftCorner<3, 3>().llt().solve(Vector3d(innovation.head<3>())));
  const double nis_att = innovation.tail<3>().dot(
      S.bottomRightCorner<3, 3>().llt().solve(Vector3d(innovation.tail<3>())));
  health_.vision_test_ratio = nis / params_.vision_gate_chi2;
  health_.vision_pos_test_ratio = nis_pos / params_.vision_gate_chi2;
  health_.vision_att_test_ratio = nis_att / params_.vision_gate_chi2;
  if (!(nis <= params_.vision_gate_chi2)) return false;  // NaN fails too

  // K = P H^T S^-1, from S's factor (S and P symmetric).
  const Eigen::Matrix<double, kErrorStates, 6> K = S_llt.solve(HP).transpose();
  const Eigen::Matrix<double, kErrorStates, 1> dx = K * innovation;
  // Joseph form: stays symmetric positive definite under rounding.
  const Covariance I_KH = Covariance::Identity() - K * H;
  P = (I_KH * P * I_KH.transpose()).eval() + K * R_noise * K.transpose();

  inject(dx, x, P);
  return true;
}

void Estimator::inject(const Eigen::Matrix<double, kErrorStates, 1>& dx, Nominal& x,
                       Covariance& P) {
  x.p_world_body_m += dx.segment<3>(kP);
  x.v_world_body_m_s += dx.segment<3>(kV);
  x.q_world_body = (x.q_world_body * expRotation(dx.segment<3>(kTheta))).normalized();
  x.gyro_bias_rad_s += dx.segment<3>(kBg);
  x.accel_bias_m_s2 += dx.segment<3>(kBa);
  x.odom_tilt_rad.head<2>() += dx.segment<2>(kPhi);

  // Solà (2017) §6.3, the reset: the error is now taken about the corrected attitude.
  Covariance G = Covariance::Identity();
  G.block<3, 3>(kTheta, kTheta) -= skew(0.5 * dx.segment<3>(kTheta));
  P = (G * P * G.transpose()).eval();
  symmetrise(P);
}

bool Estimator::fuseHeight(Nominal& x, Covariance& P, double baro_alt_m,
                           double* test_ratio) const {
  // Measured height less predicted (world's z is down): innovation(x ⊕ δx) = innovation + δp_z,
  // so H is -1 at δp_z, and P H^T is P's δp_z column negated.
  const double innovation = (baro_alt_m - baro_ref_m_) + x.p_world_body_m.z();
  const double r = std::pow(params_.baro_noise_m, 2);
  const double s = P(kP + 2, kP + 2) + r;
  const double ratio = innovation * innovation / (s * std::pow(params_.baro_gate_sigma, 2));
  if (test_ratio != nullptr) *test_ratio = ratio;
  if (!(ratio <= 1.0)) return false;  // NaN fails too
  const Eigen::Matrix<double, kErrorStates, 1> K = -P.col(kP + 2) / s;
  // Joseph form, as for a pose: I - K H is the identity plus K in δp_z's column.
  Covariance I_KH = Covariance::Identity();
  I_KH.col(kP + 2) += K;
  P = (I_KH * P * I_KH.transpose()).eval() + r * K * K.transpose();
  inject(K * innovation, x, P);
  return true;
}

Estimator::Height Estimator::step(Nominal& x, Covariance& P, const ImuSample& imu, double dt_s,
                                  double* test_ratio) const {
  predict(x, P, imu, dt_s);
  if (!std::isfinite(imu.baro_alt_m) || !std::isfinite(baro_ref_m_)) return Height::kNone;
  return fuseHeight(x, P, imu.baro_alt_m, test_ratio) ? Height::kFused : Height::kRejectedGate;
}

bool Estimator::addImu(const ImuSample& sample) {
  if (sample.utime <= last_imu_utime_ || !sample.gyro_rad_s.allFinite() ||
      !sample.accel_m_s2.allFinite() || std::isinf(sample.baro_alt_m)) {
    ++health_.imu_rejected;
    return false;
  }
  ++health_.imu_samples;
  if (!initialised()) {
    if (still_samples_ == 0) still_first_utime_ = sample.utime;
    still_accel_sum_ += sample.accel_m_s2;
    still_gyro_sum_ += sample.gyro_rad_s;
    ++still_samples_;
    last_imu_utime_ = sample.utime;
    return true;
  }
  const double dt_s = static_cast<double>(sample.utime - last_imu_utime_) * kUsToS;
  health_.imu_fused = dt_s <= params_.imu_gap_s;
  if (!health_.imu_fused) ++health_.imu_gaps;
  last_imu_utime_ = sample.utime;
  push(sample, dt_s);
  updateDivergence();
  return true;
}

int Estimator::newestAtOrBefore(int64_t utime) const {
  int lo = 0, hi = count_ - 1;  // at(lo).imu.utime <= utime is the caller's precondition
  while (lo < hi) {
    const int mid = (lo + hi + 1) / 2;
    if (at(mid).imu.utime <= utime) {
      lo = mid;
    } else {
      hi = mid - 1;
    }
  }
  return lo;
}

VisionOutcome Estimator::startFromStill(const VisionPose& pose) {
  if (still_samples_ > 0 && !still_pose_ && pose.utime >= still_first_utime_) still_pose_ = pose;
  const double still_s = static_cast<double>(last_imu_utime_ - still_first_utime_) * kUsToS;
  if (still_samples_ == 0 || still_s < params_.init_still_s) return VisionOutcome::kNotInitialised;
  const Pose& T_odom_cam_at_rest = still_pose_ ? still_pose_->T_odom_cam : pose.T_odom_cam;
  // At rest the accelerometer reads -g: world's z (down) seen from the body is opposite to it.
  const Vector3d down_body = -still_accel_sum_.normalized();
  // World's x: the body's x made level, so that world's heading is the body's at the start.
  const Vector3d x_world_body = (Vector3d::UnitX() - down_body.x() * down_body).normalized();
  Matrix3d R_body_world;
  R_body_world.col(0) = x_world_body;
  R_body_world.col(1) = down_body.cross(x_world_body);
  R_body_world.col(2) = down_body;

  Nominal x;
  x.q_world_body = Quaterniond(R_body_world.transpose()).normalized();
  x.gyro_bias_rad_s = still_gyro_sum_ / static_cast<double>(still_samples_);
  Pose T_world_body = Pose::Identity();
  T_world_body.linear() = R_body_world.transpose();
  T_world_odom_ = T_world_body * params_.T_body_cam * T_odom_cam_at_rest.inverse();
  start(last_imu_utime_, x);
  last_vision_utime_ = pose.utime;
  ++health_.vision_fused_count;
  return VisionOutcome::kFused;
}

VisionOutcome Estimator::addVision(const VisionPose& pose) {
  if (!isFinite(pose.T_odom_cam)) {
    ++health_.vision_rejected_invalid;
    return VisionOutcome::kRejectedInvalid;
  }
  if (!initialised()) return startFromStill(pose);
  if (pose.utime <= last_vision_utime_ || pose.utime < barrier_utime_) {
    ++health_.vision_rejected_out_of_order;
    return VisionOutcome::kRejectedOutOfOrder;
  }
  if (pose.utime < at(0).imu.utime || pose.utime < reset_utime_) {
    ++health_.vision_rejected_too_old;
    return VisionOutcome::kRejectedTooOld;
  }

  // The state at the capture time: the stored one just before it, integrated over the part of
  // the next sample's step up to the capture (a pose newer than the last sample meets the newest
  // state: at most one IMU period early).
  const int k = newestAtOrBefore(pose.utime);
  const bool split = pose.utime > at(k).imu.utime && k + 1 < count_;
  Nominal x = at(k).x;
  Covariance P = at(k).P;
  if (split) {
    predict(x, P, at(k + 1).imu,
            static_cast<double>(pose.utime - at(k).imu.utime) * kUsToS);
  }
  VisionOutcome outcome = VisionOutcome::kFused;
  if (!fuse(x, P, pose.T_odom_cam, pose.weak)) {
    ++health_.vision_rejected_gate;
    ++health_.consecutive_gate_rejections;
    if (health_.consecutive_gate_rejections < params_.vision_reset_rejections) {
      updateDivergence();
      return VisionOutcome::kRejectedGate;
    }
    resetToPose(x, P, pose.T_odom_cam, pose.weak);
    pose_reset_utimes_[health_.pose_resets % params_.diverged_resets] = pose.utime;
    ++health_.pose_resets;
    outcome = VisionOutcome::kResetToPose;
  }
  replayFrom(k, split, pose, x, P);
  last_vision_utime_ = pose.utime;
  ++health_.vision_fused_count;
  health_.consecutive_gate_rejections = 0;
  updateDivergence();
  return outcome;
}

void Estimator::replayFrom(int k, bool split, const VisionPose& pose, const Nominal& x,
                           const Covariance& P) {
  int first_replayed = k + 1;
  Entry& fused = at(split ? k + 1 : k);
  fused.x = x;
  fused.P = P;
  if (split) {
    step(fused.x, fused.P, at(k + 1).imu,
         static_cast<double>(at(k + 1).imu.utime - pose.utime) * kUsToS,
         /*test_ratio=*/nullptr);  // counted, with their ratios, when they came
    first_replayed = k + 2;
  }
  barrier_utime_ = fused.imu.utime;
  for (int j = first_replayed; j < count_; ++j) {
    Entry& entry = at(j);
    const Entry& previous = at(j - 1);
    entry.x = previous.x;
    entry.P = previous.P;
    step(entry.x, entry.P, entry.imu,
         static_cast<double>(entry.imu.utime - previous.imu.utime) * kUsToS,
         /*test_ratio=*/nullptr);
  }
}

Pose Estimator::alignment(const Nominal& x) const {
  return Pose(expRotation(x.odom_tilt_rad)) * T_world_odom_;
}

Pose Estimator::T_world_odom() const {
  return initialised() ? alignment(newest().x) : T_world_odom_;
}

void Estimator::addWeak(const WeakDirections& weak, const Matrix3d& R_world_odom,
                        Matrix6d* cov) const {
  // A weak direction moves the camera's position in odom and turns it in its own frame: in the
  // innovation's terms (and the error state's), the position in world and the body's attitude.
  const Matrix3d R_body_cam = params_.T_body_cam.linear();
  for (int i = 0; i < weak.count; ++i) {
    Vector6d m;
    m << R_world_odom * weak.d[i].head<3>(), R_body_cam * weak.d[i].tail<3>();
    *cov += std::pow(params_.vision_weak_std, 2) * m * m.transpose();
  }
}

void Estimator::resetToPose(Nominal& x, Covariance& P, const Pose& T_odom_cam,
                            const WeakDirections& weak) const {
  const Vector3d p_before_m = x.p_world_body_m;
  const Quaterniond q_before = x.q_world_body;
  const Matrix3d P_pos_before = P.block<3, 3>(kP, kP);
  const Matrix3d P_att_before = P.block<3, 3>(kTheta, kTheta);
  const Pose T_world_odom = alignment(x);
  const Pose T_world_cam = T_world_odom * T_odom_cam;
  // Position and attitude from the pose; the velocity stays (vision has none to give) but its
  // uncertainty, and the biases', go back to the start's so that the next poses can correct them:
  // a bias that stepped is what a drift the gate could not follow most often means.
  //
  // Along the pose's weak directions it measured nothing, so there the state keeps its own
  // position, attitude and their uncertainty (the IMU's, a barometer's). Taking the pose's
  // with a weak σ instead made every reset in a corridor a divergence (10 m, beyond
  // diverged_pos_std_m), and, facing a single wall, tilted the estimate by the odometry's roll
  // about the view.
  const Matrix3d pos_along = weakProjector(weak, 0, T_world_odom.linear());
  const Matrix3d att_along = weakProjector(weak, 3, params_.T_body_cam.linear());
  const Matrix3d R_pose_body = T_world_cam.linear() * params_.T_body_cam.linear().transpose();
  const Vector3d turn_rad =
      logRotation(Quaterniond(q_before.toRotationMatrix().transpose() * R_pose_body).normalized());
  x.q_world_body = (q_before * expRotation(turn_rad - att_along * turn_rad)).normalized();
  const Matrix3d R_world_body = x.q_world_body.toRotationMatrix();
  x.p_world_body_m = T_world_cam.translation() - R_world_body * params_.T_body_cam.translation();
  x.p_world_body_m += pos_along * (p_before_m - x.p_world_body_m);
  // The pose says nothing about odom's tilt: what the filter knew of it stays, and the reset's
  // position and attitude, taken through Exp(φ), carry its error: δp = -[p]x δφ, δθ = R^T δφ.
  const Eigen::Matrix2d P_phi = P.block<2, 2>(kPhi, kPhi);
  Eigen::Matrix<double, 6, 2> J;
  J.topRows<3>() = -skew(x.p_world_body_m).leftCols<2>();
  J.bottomRows<3>() = R_world_body.transpose().leftCols<2>();
  P = initialCovariance();
  P.diagonal().segment<3>(kP).setConstant(std::pow(params_.vision_pos_std_m, 2));
  P.diagonal().segment<3>(kTheta).setConstant(std::pow(params_.vision_att_std_rad, 2));
  P.block<2, 2>(kPhi, kPhi) = P_phi;
  const Eigen::Matrix<double, 6, 2> JP = J * P_phi;
  P.block<3, 2>(kP, kPhi) = JP.topRows<3>();
  P.block<3, 2>(kTheta, kPhi) = JP.bottomRows<3>();
  P.block<2, 3>(kPhi, kP) = JP.topRows<3>().transpose();
  P.block<2, 3>(kPhi, kTheta) = JP.bottomRows<3>().transpose();
  // The reset pose's own uncertainty: the tilt's error through it, and nothing known along its
  // weak directions (what of them the state's own takes over below).
  Matrix6d pose_cov = JP * J.transpose();
  addWeak(weak, T_world_odom.linear(), &pose_cov);
  P.block<3, 3>(kP, kP) += pose_cov.topLeftCorner<3, 3>();
  P.block<3, 3>(kP, kTheta) += pose_cov.topRightCorner<3, 3>();
  P.block<3, 3>(kTheta, kP) += pose_cov.bottomLeftCorner<3, 3>();
  P.block<3, 3>(kTheta, kTheta) += pose_cov.bottomRightCorner<3, 3>();
  const auto keepOwn = [&P](int block, const Matrix3d& along, const Matrix3d& P_before) {
    const Matrix3d across = Matrix3d::Identity() - along;
    P.middleRows<3>(block) = (across * P.middleRows<3>(block)).eval();
    P.middleCols<3>(block) = (P.middleCols<3>(block) * across).eval();
    P.block<3, 3>(block, block) += along * P_before * along;
  };
  keepOwn(kP, pos_along, P_pos_before);
  keepOwn(kTheta, att_along, P_att_before);
}

bool Estimator::applyReset(const OdomReset& reset) {
  // Before the start the poses anchor the new frame anyway, the rest's first once it is in it
  // (one captured from the reset on is in it already).
  if (!initialised() && still_pose_ && still_pose_->utime < reset.utime &&
      isFinite(reset.T_odomNew_odomOld))
    still_pose_->T_odom_cam = reset.T_odomNew_odomOld * still_pose_->T_odom_cam;
  if (!initialised() || !isFinite(reset.T_odomNew_odomOld) || !(reset.pos_std_m > 0.0) ||
      !(reset.yaw_std_rad > 0.0)) {
    ++health_.resets_rejected;
    return false;
  }
  // The jump in world coordinates. Only its heading and position are applied (tilt is the IMU's
  // to know); whatever tilt the ground's jump had goes into the alignment, so that the next
  // poses agree with the continuous tilt.
  const Pose T_world_odom = alignment(newest().x);
  const Pose D_world = T_world_odom * reset.T_odomNew_odomOld * T_world_odom.inverse();
  const double yaw_rad = std::atan2(D_world.linear()(1, 0), D_world.linear()(0, 0));
  const Matrix3d R_yaw = Eigen::AngleAxisd(yaw_rad, Vector3d::UnitZ()).toRotationMatrix();
  const Vector3d p_now_m = newest().x.p_world_body_m;
  Pose D_applied = Pose::Identity();
  D_applied.linear() = R_yaw;
  // Moves the body now exactly where the full jump would.
  D_applied.translation() = D_world * p_now_m - R_yaw * p_now_m;
  // World turns by the yaw, and the tilt of odom, a rotation vector in world, with it; the start's
  // alignment takes the rest.
  const Vector3d odom_tilt_rad = R_yaw * newest().x.odom_tilt_rad;
  T_world_odom_ = Pose(expRotation(-odom_tilt_rad)) * D_applied * D_world.inverse() * T_world_odom;

  // Every stored state moves too, so that poses captured after the reset but before now are
  // fused against states in the new frame.
  const Quaterniond q_yaw(R_yaw);
  const Eigen::Matrix2d R_yaw_xy = R_yaw.topLeftCorner<2, 2>();
  for (int j = 0; j < count_; ++j) {
    Entry& entry = at(j);
    entry.x.p_world_body_m = D_applied * entry.x.p_world_body_m;
    entry.x.odom_tilt_rad = R_yaw * entry.x.odom_tilt_rad;
    entry.x.v_world_body_m_s = R_yaw * entry.x.v_world_body_m_s;
    entry.x.q_world_body = (q_yaw * entry.x.q_world_body).normalized();
    // Heading in the body-local δθ: the world's z seen from the body.
    const Vector3d u = entry.x.q_world_body.conjugate() * Vector3d::UnitZ();
    const Matrix3d tilt_only = Matrix3d::Identity() - u * u.transpose();
    // G X, G the identity but for these blocks: by blocks, as the whole ring goes through it.
    const auto G_times = [&](const Covariance& X) {
      Covariance GX = X;
      GX.middleRows<3>(kP).setZero();
      GX.middleRows<3>(kV) = R_yaw * X.middleRows<3>(kV);
      GX.middleRows<3>(kTheta) = tilt_only * X.middleRows<3>(kTheta);
      GX.middleRows<2>(kPhi) = R_yaw_xy * X.middleRows<2>(kPhi);
      return GX;
    };
    entry.P = G_times(G_times(entry.P).transpose());  // G P G^T, P symmetric
    entry.P.block<3, 3>(kP, kP).diagonal().array() += std::pow(reset.pos_std_m, 2);
    entry.P.block<3, 3>(kTheta, kTheta) += std::pow(reset.yaw_std_rad, 2) * u * u.transpose();
    symmetrise(entry.P);
  }
  reset_utime_ = std::max(reset_utime_, reset.utime);
  health_.reset_counter = reset.reset_counter;
  ++health_.resets;
  updateDivergence();
  return true;
}

void Estimator::updateDivergence() {
  const Entry& now = newest();
  const double pos_var_max = now.P.diagonal().segment<3>(kP).maxCoeff();
  // The ring holds the last diverged_resets resets: the slot written next is the oldest of them.
  const int n = params_.diverged_resets;
  const bool resets_repeat =
      health_.pose_resets >= n &&
      static_cast<double>(pose_reset_utimes_[(health_.pose_resets - 1) % n] -
                          pose_reset_utimes_[health_.pose_resets % n]) *
              kUsToS <=
          params_.diverged_reset_window_s;
  // Sticky: a failsafe acts once and a fresh initialise() clears it.
  health_.diverged = health_.diverged ||
                     !isFiniteState(now.P, now.x.p_world_body_m, now.x.v_world_body_m_s) ||
                     !(pos_var_max <= std::pow(params_.diverged_pos_std_m, 2)) || resets_repeat;
}

EstimatorState Estimator::state() const {
  EstimatorState out;
  if (!initialised()) return out;
  const Entry& now = newest();
  out.utime = now.imu.utime;
  out.p_world_body_m = now.x.p_world_body_m;
  out.v_world_body_m_s = now.x.v_world_body_m_s;
  out.q_world_body = now.x.q_world_body;
  out.gyro_bias_rad_s = now.x.gyro_bias_rad_s;
  out.accel_bias_m_s2 = now.x.accel_bias_m_s2;
  out.odom_tilt_rad = now.x.odom_tilt_rad;
  out.omega_body_rad_s = now.imu.gyro_rad_s - now.x.gyro_bias_rad_s;
  out.f_body_m_s2 = now.imu.accel_m_s2 - now.x.accel_bias_m_s2;
  return out;
}

const Covariance& Estimator::covariance() const { return newest().P; }

EstimatorHealth Estimator::health() const {
  EstimatorHealth out = health_;
  out.initialised = initialised();
  if (last_vision_utime_ >= 0) {
    out.time_since_vision_s = static_cast<double>(last_imu_utime_ - last_vision_utime_) * kUsToS;
    out.vision_fused = out.time_since_vision_s <= params_.vision_timeout_s;
  }
  return out;
}

const char* toString(VisionOutcome outcome) {
  switch (outcome) {
    case VisionOutcome::kFused: return "fused";
    case VisionOutcome::kNotInitialised: return "not initialised";
    case VisionOutcome::kRejectedGate: return "rejected by the gate";
    case VisionOutcome::kResetToPose: return "gated too often: the filter reset to it";
    case VisionOutcome::kRejectedTooOld: return "rejected: older than the history";
    case VisionOutcome::kRejectedOutOfOrder: return "rejected: out of order";
    case VisionOutcome::kRejectedInvalid: return "rejected: not finite";
  }
  return "?";
}

}  // namespace kinfly::flight
