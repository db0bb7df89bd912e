// The drone's state estimator: an error-state Kalman filter (Solà, "Quaternion kinematics for the
// error-state Kalman filter", 2017, §5 and §6) over IMU samples, with the onboard odometry's
// delayed poses and the ground's corrections (docs/flight.md, "State estimator").
//
// Frames: body FRD; `world` gravity-aligned with z down (g_world = (0, 0, +g)); `odom` the
// odometry's frame (its first keyframe's optical camera frame). q_world_body is Hamilton and
// maps body to world. Error state, in this order: δp, δv (world), δθ (body, R_true = R ⊗ Exp(δθ)),
// δb_g, δb_a, δφ (the tilt of `odom` against gravity: world's x and y, left of T_world_odom).
//
// A barometer's height, where the IMU samples carry one, is fused with the sample it came with, so
// that a replay after a delayed pose fuses it again.
//
// Delayed poses are fused at their capture time: every IMU step stores the state, its covariance
// and the sample in a ring allocated at construction; a pose rolls the filter back to its capture
// time, is fused there, and the stored samples are integrated again up to now. Nothing allocates
// after construction.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <limits>
#include <optional>
#include <vector>

#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"

namespace kinfly::flight {

constexpr int kErrorStates = 17;
constexpr int kMaxDivergedResets = 16;
using Covariance = Eigen::Matrix<double, kErrorStates, kErrorStates>;

// Where each block of the error state starts in it (the order above).
namespace error_state {
constexpr int kP = 0, kV = 3, kTheta = 6, kBg = 9, kBa = 12, kPhi = 15;
}  // namespace error_state

// A vision pose linearised about the state: its innovation (measured less predicted: the
// camera's position in world, then the body's attitude error in the body) and the innovation's
// Jacobian in the error state, H (innovation(x ⊕ δx) ≈ innovation(x) − H δx).
struct VisionLinearisation {
  Eigen::Matrix<double, 6, 1> innovation;
  Eigen::Matrix<double, 6, kErrorStates> H;
};

// The body at (p_world_body_m, q_world_body), odom at T_world_odom with its tilt applied
// (Exp(φ) of the start's alignment), the camera on the body at T_body_cam. The filter's own
// model, apart so that a test holds H against finite differences.
VisionLinearisation lineariseVision(const Eigen::Vector3d& p_world_body_m,
                                    const Eigen::Quaterniond& q_world_body,
                                    const Pose& T_world_odom, const Pose& T_odom_cam,
                                    const Pose& T_body_cam);

struct EstimatorParams {
  // IMU noise, continuous-time densities: the ADIS16448 of the EuRoC MAV dataset as its
  // sensor.yaml gives them (Burri et al., IJRR 2016).
  double gyro_noise_rad_s_rthz = 1.6968e-4;        // [rad/s/√Hz] (0, 1]
  double accel_noise_m_s2_rthz = 2.0e-3;           // [m/s²/√Hz] (0, 10]
  double gyro_bias_walk_rad_s2_rthz = 1.9393e-5;   // [rad/s²/√Hz] (0, 1]
  double accel_bias_walk_m_s3_rthz = 3.0e-3;       // [m/s³/√Hz] (0, 10]
  double gravity_m_s2 = 9.81;                      // [m/s²] [9.7, 9.9]
  // A longer step between samples is counted as a gap (and still integrated).
  double imu_gap_s = 0.02;                         // [s] (0, 1]

  // 1σ uncertainty of the initial state.
  double init_pos_std_m = 0.01;                    // [m] (0, 100]
  double init_vel_std_m_s = 0.05;                  // [m/s] (0, 100]
  double init_att_std_rad = 0.02;                  // [rad] (0, 3.15]
  double init_gyro_bias_std_rad_s = 0.005;         // [rad/s] (0, 1]
  double init_accel_bias_std_m_s2 = 0.05;          // [m/s²] (0, 10]
  // `odom`'s alignment with gravity is taken from the body's tilt at the start, which the
  // accelerometer's bias tilts by |b_a| / g: 0.05 m/s² is 0.29°, and the poses would then hold
  // the estimate's tilt there for good. It is estimated (δφ); the motion tells the two apart
  // (a bias turns with the body, a tilted frame does not). Its 1σ at the start, per axis:
  double init_odom_tilt_std_rad = 0.005;           // [rad] (0, 0.5]
  // The odometry's own tilt drifts (rotation drift the ground's corrections leave to the IMU):
  // a random walk of this density.
  double odom_tilt_walk_rad_rts = 1.0e-4;          // [rad/√s] [0, 0.1]
  // At rest before the first pose: the accelerometer's mean over this long gives the tilt.
  double init_still_s = 0.5;                       // [s] [0.01, 10]

  // Camera (optical) to body; the default looks forward: optical z = body x, x = y, y = z.
  Pose T_body_cam = defaultBodyCam();              // rotation orthonormal, |t| <= 1 m
  // Odometry pose noise, 1σ per axis: position in `odom`, rotation in the camera frame.
  double vision_pos_std_m = 0.01;                  // [m] (0, 10]
  double vision_att_std_rad = 0.01;                // [rad] (0, 1]
  // 1σ along a direction the odometry reports weak (VisionPose::weak): so large that the pose
  // says nothing there and the IMU carries the state along it.
  double vision_weak_std = 10.0;                   // [m or rad] (0, 1000]
  // Chi-square gate on the 6-DoF pose innovation; 22.46 is the 99.9 % quantile for 6 dof.
  double vision_gate_chi2 = 22.46;                 // [-] [1, 1000]
  // Vision counts as fused while its last fused pose is at most this old.
  double vision_timeout_s = 0.2;                   // [s] (0, 10]

  // Barometric height (ImuSample::baro_alt_m), 1σ per reading. Its reference is the mean of the
  // first init_still_s of readings after the start, less the state's heights; this is 3 times an MS5611's noise at its finest oversampling, and its slow drift (the
  // weather, the building's air, the rotors' wash) is left in this noise rather than estimated:
  // vision outweighs it wherever vision sees the height (30 poses/s at 1 cm against 50 readings/s
  // at this), and where it does not, the barometer's drift is what bounds the height's error
  // instead of the accelerometer's bias integrated twice.
  double baro_noise_m = 0.3;                       // [m] (0, 100]
  // Gate on the height innovation, in its σ (PX4's EKF2_BARO_GATE is 5).
  double baro_gate_sigma = 5.0;                    // [-] [1, 100]

  // The state history poses can reach back into; the ring holds history_s * imu_rate_max_hz.
  double history_s = 0.4;                          // [s] [0.3, 2]
  double imu_rate_max_hz = 1000.0;                 // [Hz] [50, 4000]

  // This many poses in a row outside the gate reset the filter to the pose (PX4's EKF2 resets to
  // its external vision the same way): either the IMU's biases stepped and the state drifted off,
  // or the odometry jumped, which the ground's next correction takes back out.
  int vision_reset_rejections = 5;                 // [-] [1, 1000]
  // Diverged: the position's 1σ beyond this, or this many resets to a pose within the window
  // (vision and the IMU keep disagreeing: neither can be trusted).
  double diverged_pos_std_m = 2.0;                 // [m] (0, 1000]
  int diverged_resets = 3;                         // [-] [1, kMaxDivergedResets]
  double diverged_reset_window_s = 10.0;           // [s] (0, 3600]

  Status validate() const;
  static Pose defaultBodyCam();
};

struct ImuSample {
  int64_t utime = 0;                                  // [µs] capture
  Eigen::Vector3d gyro_rad_s = Eigen::Vector3d::Zero();  // body FRD
  Eigen::Vector3d accel_m_s2 = Eigen::Vector3d::Zero();  // specific force, body FRD
  // [m] A barometer's pressure altitude (up, any reference) read with this sample; NaN when the
  // sample carries no new reading (a barometer is slower than the IMU, or there is none).
  double baro_alt_m = std::numeric_limits<double>::quiet_NaN();
};

// The onboard odometry's camera pose.
struct VisionPose {
  int64_t utime = 0;  // [µs] capture of the depth frame
  Pose T_odom_cam = Pose::Identity();
  WeakDirections weak;  // the position parts in odom
};

// The ground's correction: the odometry's frame jumped (new odom coordinates = T_new_old * old).
struct OdomReset {
  int64_t utime = 0;  // [µs] from this capture time on, poses are in the new frame
  Pose T_odomNew_odomOld = Pose::Identity();
  int32_t reset_counter = 0;  // the ground's counter, passed through
  double pos_std_m = 0.05;    // [m] 1σ of the corrected position
  double yaw_std_rad = 0.02;  // [rad] 1σ of the corrected heading
};

// A known start (tests, a restart from a stored state).
struct EstimatorInit {
  int64_t utime = 0;  // [µs]
  Eigen::Vector3d p_world_body_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d v_world_body_m_s = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_world_body = Eigen::Quaterniond::Identity();
  Eigen::Vector3d gyro_bias_rad_s = Eigen::Vector3d::Zero();
  Eigen::Vector3d accel_bias_m_s2 = Eigen::Vector3d::Zero();
  Pose T_world_odom = Pose::Identity();  // its tilt is then corrected as the state's δφ
};

struct EstimatorState {
  int64_t utime = 0;  // [µs] of the last IMU sample
  Eigen::Vector3d p_world_body_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d v_world_body_m_s = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_world_body = Eigen::Quaterniond::Identity();
  Eigen::Vector3d gyro_bias_rad_s = Eigen::Vector3d::Zero();
  Eigen::Vector3d accel_bias_m_s2 = Eigen::Vector3d::Zero();
  Eigen::Vector3d omega_body_rad_s = Eigen::Vector3d::Zero();  // gyro less its bias
  Eigen::Vector3d f_body_m_s2 = Eigen::Vector3d::Zero();       // accelerometer less its bias
  // The correction to the start's alignment of `odom` (about world's x and y, z zero):
  // T_world_odom() = Exp(odom_tilt_rad) * the start's.
  Eigen::Vector3d odom_tilt_rad = Eigen::Vector3d::Zero();
};

enum class VisionOutcome {
  kFused,
  kNotInitialised,  // before the start; the pose may start the filter (see addVision)
  kRejectedGate,    // innovation outside the chi-square gate
  kResetToPose,     // the last of vision_reset_rejections gated poses: the filter starts from it
  kRejectedTooOld,  // older than the history, or captured before the last reset
  kRejectedOutOfOrder,  // captured before the last fused pose
  kRejectedInvalid,     // non-finite pose
};

struct EstimatorHealth {
  bool initialised = false;
  bool imu_fused = false;     // samples arrive within imu_gap_s
  bool vision_fused = false;  // a pose fused within vision_timeout_s
  bool diverged = false;
  double time_since_vision_s = -1.0;  // [s] to the last fused pose's capture; -1 before any
  // Innovation test ratios of the last pose: NIS / gate (≤ 1 passes), whole and split.
  double vision_test_ratio = 0.0;
  double vision_pos_test_ratio = 0.0;
  double vision_att_test_ratio = 0.0;
  int64_t imu_samples = 0;
  int64_t imu_rejected = 0;  // time not increasing, or a reading not finite (an infinite height)
  int64_t imu_gaps = 0;
  int64_t vision_fused_count = 0;
  int64_t vision_rejected_gate = 0;
  int64_t vision_rejected_too_old = 0;
  int64_t vision_rejected_out_of_order = 0;
  int64_t vision_rejected_invalid = 0;
  int consecutive_gate_rejections = 0;
  int64_t baro_fused = 0;
  int64_t baro_rejected_gate = 0;
  double baro_test_ratio = 0.0;  // of the last reading: its innovation's NIS / the gate²
  int64_t pose_resets = 0;  // kResetToPose outcomes
  int32_t reset_counter = 0;  // the last applied reset's
  int64_t resets = 0;
  int64_t resets_rejected = 0;
};

class Estimator {
 public:
  // params must validate.
  explicit Estimator(const EstimatorParams& params);

  void initialise(const EstimatorInit& init);

  // Before the start, samples feed the still-start average. Returns false for a sample whose
  // time does not increase (counted, ignored).
  bool addImu(const ImuSample& sample);
  // Before the start, the first pose after init_still_s of samples starts the filter there:
  // world's origin at the body, its heading the body's, its tilt from the mean specific force.
  // The body has not moved since the rest began, so odom is anchored on the first pose captured
  // in it: the odometry's error grows from its first frame on, and a later pose of the same
  // place would carry its drift into world's definition for good.
  VisionOutcome addVision(const VisionPose& pose);
  // Resets position and heading to follow the jump; velocity and tilt stay continuous. False
  // (counted, nothing changes) before the start or for a non-finite jump or a std not > 0; before
  // the start the rest's first pose follows the jump into the new frame.
  bool applyReset(const OdomReset& reset);

  bool initialised() const { return count_ > 0; }
  EstimatorState state() const;
  // Of the error state, in the order above; only when initialised().
  const Covariance& covariance() const;
  // The odometry's frame in world, with the estimated tilt.
  Pose T_world_odom() const;
  EstimatorHealth health() const;

 private:
  struct Nominal {
    Eigen::Vector3d p_world_body_m = Eigen::Vector3d::Zero();
    Eigen::Vector3d v_world_body_m_s = Eigen::Vector3d::Zero();
    Eigen::Quaterniond q_world_body = Eigen::Quaterniond::Identity();
    Eigen::Vector3d gyro_bias_rad_s = Eigen::Vector3d::Zero();
    Eigen::Vector3d accel_bias_m_s2 = Eigen::Vector3d::Zero();
    // Small (the start's error), so that adding δφ to it (as the filter does) is composing on
    // the left to first order; z stays 0.
    Eigen::Vector3d odom_tilt_rad = Eigen::Vector3d::Zero();
  };
  // The filter after the sample `imu` (which held over the step that ends at imu.utime).
  struct Entry {
    ImuSample imu;
    Nominal x;
    Covariance P = Covariance::Zero();
  };

  void start(int64_t utime, const Nominal& x);
  // The covariance of a fresh start: no cross-correlation, each block at its init_*_std.
  Covariance initialCovariance() const;
  VisionOutcome startFromStill(const VisionPose& pose);
  void predict(Nominal& x, Covariance& P, const ImuSample& imu, double dt_s) const;
  // The sample's barometric height fused into (x, P); false (nothing changes) when gated out, and
  // the test ratio in *test_ratio unless null. Only for a sample with a reading, after the
  // reference is set.
  bool fuseHeight(Nominal& x, Covariance& P, double baro_alt_m, double* test_ratio) const;
  enum class Height { kNone, kFused, kRejectedGate };
  // One sample: the prediction over its step, then its height if it carries one and the reference
  // is set (the test ratio, if any, in *test_ratio unless null).
  Height step(Nominal& x, Covariance& P, const ImuSample& imu, double dt_s,
              double* test_ratio) const;
  // Adds the error dx to the nominal state and takes P about it (Solà §6.3's reset).
  static void inject(const Eigen::Matrix<double, kErrorStates, 1>& dx, Nominal& x, Covariance& P);
  // Fuses the pose, in odom, into (x, P), with no information along its weak directions; false
  // when gated out.
  bool fuse(Nominal& x, Covariance& P, const Pose& T_odom_cam, const WeakDirections& weak);
  // Index 0 is the oldest stored state.
  Entry& at(int index) { return ring_[(head_ + index) % ring_.size()]; }
  const Entry& at(int index) const { return ring_[(head_ + index) % ring_.size()]; }
  const Entry& newest() const { return at(count_ - 1); }
  int newestAtOrBefore(int64_t utime) const;
  // Predicts the newest state over the sample into the next slot, dropping the oldest when full.
  void push(const ImuSample& sample, double dt_s);
  void updateDivergence();
  // Stores (x, P) as the state at the pose's capture, the stored sample k + 1 split there when
  // `split`, and integrates the later samples again up to now.
  void replayFrom(int k, bool split, const VisionPose& pose, const Nominal& x,
                  const Covariance& P);
  void resetToPose(Nominal& x, Covariance& P, const Pose& T_odom_cam,
                   const WeakDirections& weak) const;
  // `odom` in world as the state x has it: its tilt applied to the start's alignment.
  Pose alignment(const Nominal& x) const;
  // Adds vision_weak_std² along each weak direction, in the innovation's (and the error state's)
  // position and attitude terms, to a pose's 6x6 covariance; R_world_odom turns the directions.
  void addWeak(const WeakDirections& weak, const Eigen::Matrix3d& R_world_odom,
               Eigen::Matrix<double, 6, 6>* cov) const;

  EstimatorParams params_;
  Covariance Q_density_;  // diagonal, per second: times dt gives the step's process noise
  std::vector<Entry> ring_;  // oldest at head_, count_ entries
  int head_ = 0;
  int count_ = 0;
  Pose T_world_odom_ = Pose::Identity();  // the start's alignment, less the states' odom_tilt_rad
  // Poses captured before this would meet states that do not yet hold the last fusion.
  int64_t barrier_utime_ = 0;
  // Poses captured before the last reset are in the odometry's old frame.
  int64_t reset_utime_ = 0;
  int64_t last_vision_utime_ = -1;
  Eigen::Vector3d still_accel_sum_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d still_gyro_sum_ = Eigen::Vector3d::Zero();
  int64_t still_samples_ = 0;
  int64_t still_first_utime_ = -1;
  // The barometer's reading at world's height 0: the mean over init_still_s of readings after
  // the start, less the state's heights; NaN until then.
  double baro_ref_m_ = std::numeric_limits<double>::quiet_NaN();
  double baro_ref_sum_m_ = 0.0;
  int64_t baro_ref_samples_ = 0;
  int64_t baro_ref_first_utime_ = 0;
  // The first pose captured at rest (since still_first_utime_), which anchors odom at the start.
  std::optional<VisionPose> still_pose_;
  int64_t last_imu_utime_ = -1;
  // Capture times of the last resets to a pose, a ring of diverged_resets (read only once it
  // holds that many).
  std::array<int64_t, kMaxDivergedResets> pose_reset_utimes_{};
  EstimatorHealth health_;
};

const char* toString(VisionOutcome outcome);

}  // namespace kinfly::flight
