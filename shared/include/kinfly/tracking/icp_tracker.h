// Stage 5: frame-to-model tracking. Projective data association against the raycast model maps,
// point-to-plane error linearised with small angles (Low 2004), 6x6 normal equations summed in
// parallel and solved by Cholesky, coarse to fine; in degenerate geometry, from a prior, only
// along the directions the scene constrains.
#pragma once

#include <Eigen/Core>
#include <array>
#include <optional>
#include <string>

#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"
#include "kinfly/frame/depth_frame.h"
#include "kinfly/frame/model_maps.h"
#include "kinfly/frame/tracking_status.h"

namespace kinfly {

struct IcpResult {
  Pose T_ref_cur = Pose::Identity();  // current camera in the reference (model) camera frame
  TrackingStatus status = TrackingStatus::kLost;
  float inlier_fraction = 0.f;  // finest level: inliers / valid current pixels
  float rmse_m = 0.f;           // finest level point-to-plane RMS over inliers
  float noise_rms_m = 0.f;      // finest level: RMS of the sensor's noise sigma over inliers
  float max_rmse_m = 0.f;       // the residual gate this frame was held to (Params::max_rmse_m,
                                // max_rmse_sigmas)
  int iterations = 0;           // total over all levels
  // Degenerate geometry (a corridor, a single wall): the directions of motion the scene does not
  // pin down (Params::weak_direction_fraction), as unit twists [w; t] of T_ref_cur
  // (T' = exp([w; t]) * T, the reference camera's axes), the rotation in rad and the translation
  // in metres. From a prior the pose keeps it along them (track); the first `weak_directions`
  // are set.
  int weak_directions = 0;
  std::array<Eigen::Matrix<double, 6, 1>, 6> weak{};
  // The least constrained direction's share (Params::weak_direction_fraction's units) in the
  // last system solved: how close the frame came to degenerate.
  double weakest_fraction = 0.0;
  // Why the status is kLost (empty otherwise): data for FrameResult::lost_reason, not a Status.
  std::string reason;
};

// One 6x6 system: A = sum w J^T J, b = -sum w J^T e, with J = [p x n, n] and w the residual's
// weight. Upper triangle packed.
struct IcpSystem {
  std::array<double, 21> ata{};
  std::array<double, 6> atb{};
  double error_sq = 0.0;   // [m^2] sum of squared point-to-plane residuals over inliers
  double noise_sq = 0.0;   // [m^2] sum of the sensor noise's variance at the inliers' depths
  int inliers = 0;
  int matched = 0;         // current pixels projected onto a model pixel with a point
  int valid_points = 0;    // current pixels with a vertex and a normal
  void add(const IcpSystem& other);
};

class IcpTracker {
 public:
  struct Params {
    // Iterations per pyramid level, listed coarse to fine (level 2, 1, 0), as the seed gives them.
    std::array<int, kPyramidLevels> iterations_coarse_to_fine{10, 5, 4};  // each >= 0
    float distance_gate_m = 0.10f;        // [m] > 0: correspondence rejected beyond this
    float normal_angle_gate_rad = 0.349066f;  // [rad] (0, pi/2]: 20 degrees
    // The model's normal is the TSDF's gradient, a difference over one voxel of distances each
    // as noisy as the sensor at that depth: at 3.6 m (sigma 2 cm) against 1 cm voxels a map
    // fused from a few frames has normals tens of degrees off, and the fixed 20 degrees refused
    // 95 % of the correct pairs (docs/engine.md, departure 9). So the gate's tangent is the
    // larger of tan(normal_angle_gate_rad) and this many times sigma(z) / spacing
    // (ModelMaps::normal_spacing_m). Near the sensor (sigma 6 mm at 2 m) the fixed gate decides.
    float normal_gate_sigmas = 0.5f;  // >= 0; 0 leaves the fixed gate alone
    float min_inlier_fraction = 0.10f;    // (0, 1]: fewer inliers at the finest level -> lost
    int min_inliers = 100;                // >= 6: absolute floor per level, guards tiny images
    // Degeneracy (Zhang, Kaess and Singh, ICRA 2016): an eigen-direction of the 6x6 system,
    // with rotations scaled by the system's lever arm (so that both are metres of motion at the
    // surface) and divided by its weight, gets 1 where every residual's normal lies along it.
    // Below this share it is weak: a wall seen with the floor and nothing beside leaves the
    // sideways motion to a few edge pixels. The result names the weak directions; from a prior
    // (the IMU's motion) the update leaves the prior along them. In the simulated room the weak
    // direction fell to 0.001 where the odometry drifted 1.5 cm a frame, while healthy frames
    // stayed above 0.002 (docs/engine.md, departure 8).
    double weak_direction_fraction = 0.002;  // [0, 1/6)
    // More weak directions than this at the finest level and the frame is lost; a lone plane
    // leaves three, the most it allows.
    int max_weak_directions = 3;             // [0, 5]
    // Scatter is not information. Beyond 2 m the model's normals of a wall or floor seen edge-on
    // scatter by 0.06-0.1 (the simulated ring, docs/sim.md), and in a corridor that scatter
    // alone gave the motion along it a share of 0.0024, above weak_direction_fraction: ICP then
    // followed the scatter and pulled the pose back by the prior's whole step. So, from a prior,
    // a direction whose share is below suspect_direction_fraction is measured again on the
    // pairs that face it only (Facing, at facing_cosine), and is weak if that share is below
    // weak_direction_fraction; the pose then keeps the prior along it. Scatter of at most 0.1
    // gives a share of at most 0.01; a surface within 73 degrees of the direction (cosine 0.3,
    // three scatters of 0.1) is information, not scatter (docs/engine.md, departure 8).
    double suspect_direction_fraction = 0.01;  // [weak_direction_fraction, 1/6)
    double facing_cosine = 0.3;                // (0, 1)
    float max_translation_m = 0.20f;      // [m] per frame: a larger jump is a divergence -> lost
    float max_rotation_rad = 0.35f;       // [rad] per frame (20 degrees)
    // The finest level's RMS residual is compared with the larger of max_rmse_m and
    // max_rmse_sigmas times the RMS of the sensor's noise sigma (noise_model.h) at the depths
    // of the inliers: at 3.5 m the sensor's own noise (2 cm) reaches the fixed gate, and a
    // correct alignment would be refused. A correct alignment's residual is about one sigma
    // (the frame's noise; the fused model's is averaged down); 2.5 leaves room for the model's
    // and the quantisation's. Near the sensor (sigma 2 mm at 1 m) max_rmse_m decides, as before.
    float max_rmse_m = 0.02f;             // [m] > 0
    float max_rmse_sigmas = 2.5f;         // >= 0; 0 leaves max_rmse_m alone
    // Weight each residual by the inverse variance of the sensor's depth noise at its range
    // (noise_model.h), normalised to 1 at 1 m: the maximum-likelihood estimate under the seed's
    // noise model. Without it the few far, noisy points (sigma ~ z^2) pull the pose off.
    bool noise_weighting = true;
    // Huber threshold in units of that noise sigma: residuals beyond it (pairs across depth
    // edges, moved objects) get weight k/|r| instead of 1, so they cannot drag the solve.
    // 0 disables the robust weight.
    float huber_sigmas = 3.f;  // >= 0
    // Stop a level early when the update is this small (metres and radians alike).
    double convergence_epsilon = 1e-5;    // >= 0

    Status validate() const;
  };

  // A system of only the pairs that face a direction of translation (Params::facing_cosine):
  // whose model normal makes an angle with `direction` whose cosine's magnitude is at least
  // `cosine`.
  struct Facing {
    Eigen::Vector3d direction = Eigen::Vector3d::UnitZ();  // any length but zero
    double cosine = 0.3;                                   // (0, 1)
  };
  // How buildSystem associates and weighs one level's pairs: the part of Params the system
  // needs, with the angle gate as its cosine. Defaults are Params' defaults.
  struct SystemParams {
    float distance_gate_m = 0.10f;        // [m] > 0
    float cos_angle_gate = 0.9396926f;    // (0, 1]: cos of normal_angle_gate_rad (20 degrees)
    float normal_gate_sigmas = 0.5f;      // >= 0: Params::normal_gate_sigmas
    bool noise_weighting = true;
    float huber_sigmas = 3.f;             // >= 0; 0 disables the robust weight
    bool parallel = true;                 // threads over fixed row chunks: the same result
    std::optional<Facing> facing;         // set: only the pairs that face it
  };

  explicit IcpTracker(const Params& params);
  const Params& params() const { return params_; }
  // What track() builds its systems with.
  SystemParams systemParams() const;

  // Estimates the pose of `current` relative to the reference camera of `model`, starting from
  // `T_ref_cur_guess`. On failure the result keeps the guess and says why. A guess that is a
  // `prior` (a motion measured otherwise, the IMU's) is kept along the weak directions; any
  // other guess (the last pose) is not, since there the scene's weak answer is still the best.
  // `gate_scale` (>= 1) widens the correspondence gate and the jump gates: after lost frames the
  // motion since the last tracked frame, or the prior's error, has grown with every frame lost.
  IcpResult track(const DepthFrame& current, const ModelMaps& model, const Pose& T_ref_cur_guess,
                  bool prior = false, float gate_scale = 1.f) const;

  // Builds one level's system; serial and threaded loops use the same per-pixel kernel.
  static IcpSystem buildSystem(const DepthFrame& current, const ModelMaps& model, int level,
                               const Eigen::Matrix3f& R_ref_cur, const Eigen::Vector3f& t_ref_cur,
                               const SystemParams& params);

 private:
  Params params_;
};

}  // namespace kinfly
