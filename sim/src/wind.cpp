#include "kinfly/sim/wind.h"

#include <algorithm>
#include <cmath>

#include "kinfly/core/range_check.h"

namespace kinfly::sim {

namespace {

constexpr double kFeetPerMetre = 1.0 / 0.3048;
constexpr double kMinHeightFt = 10.0;
constexpr double kMaxHeightFt = 1000.0;

double clampedHeightFt(double height_m) {
  return std::clamp(height_m * kFeetPerMetre, kMinHeightFt, kMaxHeightFt);
}

// One step of the second-order forming filter K (1 + a s) / (1 + b s)^2 driven by noise of
// density pi: state (x, dx/dt) of b^2 x'' + 2 b x' + x = n, output K (x + a x'). Semi-implicit
// Euler (velocity first), stable for dt well below b (b is seconds, dt a millisecond).
double secondOrderStep(Eigen::Vector2d* state, double gain, double a, double b, double noise,
                       double dt_s) {
  Eigen::Vector2d& s = *state;
  s.y() += dt_s * (noise - 2.0 * b * s.y() - s.x()) / (b * b);
  s.x() += dt_s * s.y();
  return gain * (s.x() + a * s.y());
}

}  // namespace

Status WindParams::validate() const {
  if (!(mean_world_m_s.allFinite() && mean_world_m_s.norm() <= 30.0)) {
    return Status::error("wind.mean_m_s must have a norm within [0, 30] m/s");
  }
  return firstError(outOfRange("wind.turbulence_w20_m_s", turbulence_w20_m_s, 0.0, 30.0),
                    outOfRange("wind.min_airspeed_m_s", min_airspeed_m_s, 0.0, 30.0,
                               Bound::kOpen));
}

Wind::Wind(const WindParams& params) : params_(params), random_(params.seed) {}

Eigen::Vector3d Wind::sigmaMS(double height_m) const {
  const double h = clampedHeightFt(height_m);
  const double sigma_w = 0.1 * params_.turbulence_w20_m_s;
  const double sigma_uv = sigma_w / std::pow(0.177 + 0.000823 * h, 0.4);
  return {sigma_uv, sigma_uv, sigma_w};
}

Eigen::Vector3d Wind::scaleLengthM(double height_m) const {
  const double h = clampedHeightFt(height_m);
  const double l_uv_ft = h / std::pow(0.177 + 0.000823 * h, 1.2);
  return Eigen::Vector3d(l_uv_ft, l_uv_ft, h) / kFeetPerMetre;
}

Eigen::Vector3d Wind::step(double time_s, double dt_s, double height_m,
                           const Eigen::Vector3d& v_world_m_s) {
  const Eigen::Vector3d& mean = params_.mean_world_m_s;
  if (params_.turbulence_w20_m_s > 0.0) {
    const double airspeed =
        std::max((v_world_m_s - mean).norm(), params_.min_airspeed_m_s);
    const Eigen::Vector3d sigma = sigmaMS(height_m);
    const Eigen::Vector3d length = scaleLengthM(height_m);
    // White noise of two-sided density pi, sampled over dt: variance pi / dt.
    const double noise_sigma = std::sqrt(M_PI / dt_s);
    const Eigen::Vector3d noise = noise_sigma * random_.vector3();
    const double b_u = length.x() / airspeed;
    const double gain_u = sigma.x() * std::sqrt(2.0 * length.x() / (M_PI * airspeed));
    u_state_ += dt_s / b_u * (gain_u * noise.x() - u_state_);
    const double b_v = length.y() / airspeed;
    const double b_w = length.z() / airspeed;
    const double v = secondOrderStep(&v_state_, sigma.y() * std::sqrt(length.y() / (M_PI * airspeed)),
                                     std::sqrt(3.0) * b_v, b_v, noise.y(), dt_s);
    const double w = secondOrderStep(&w_state_, sigma.z() * std::sqrt(length.z() / (M_PI * airspeed)),
                                     std::sqrt(3.0) * b_w, b_w, noise.z(), dt_s);
    turbulence_uvw_m_s_ << u_state_, v, w;
  }
  // u along the mean wind's horizontal direction (x of the world in still air), w down.
  const Eigen::Vector2d horizontal = mean.head<2>();
  const Eigen::Vector2d along = horizontal.norm() > 1e-9 ? Eigen::Vector2d(horizontal.normalized())
                                                         : Eigen::Vector2d(1.0, 0.0);
  Eigen::Vector3d air = mean;
  air.head<2>() += turbulence_uvw_m_s_.x() * along +
                   turbulence_uvw_m_s_.y() * Eigen::Vector2d(-along.y(), along.x());
  air.z() += turbulence_uvw_m_s_.z();
  for (const Gust& gust : gusts_) {
    const double t = time_s - gust.start_s;
    if (t <= 0.0 || t >= 2.0 * gust.duration_s) continue;
    air += 0.5 * (1.0 - std::cos(M_PI * t / gust.duration_s)) * gust.amplitude_world_m_s;
  }
  return air;
}

}  // namespace kinfly::sim
