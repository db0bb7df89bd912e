#include "kinfly/icp_tracker.h"

#include <Eigen/Geometry>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <cmath>

#include "kinfly/noise_model.h"
#include "kinfly/numeric.h"
#include <sstream>

namespace kinfly {

const char* toString(TrackingStatus status) {
  switch (status) {
    case TrackingStatus::kFirstFrame: return "first";
    case TrackingStatus::kOk: return "ok";
    case TrackingStatus::kLost: return "lost";
    case TrackingStatus::kGivenPose: return "given";
  }
  return "unknown";
}

ModelMaps::ModelMaps(const PinholeCamera& level0_camera) {
  for (int l = 0; l < kPyramidLevels; ++l) {
    camera[l] = level0_camera.scaled(1 << l);
    vertex_ref[l] = Image<Eigen::Vector3f>(camera[l].width, camera[l].height, invalidVector());
    normal_ref[l] = Image<Eigen::Vector3f>(camera[l].width, camera[l].height, invalidVector());
  }
}

void ModelMaps::buildPyramid() {
  for (int l = 1; l < kPyramidLevels; ++l) {
    const int w = camera[l].width, h = camera[l].height;
#pragma omp parallel for schedule(static)
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        vertex_ref[l](x, y) = vertex_ref[l - 1](2 * x, 2 * y);
        normal_ref[l](x, y) = normal_ref[l - 1](2 * x, 2 * y);
      }
  }
}

void IcpSystem::add(const IcpSystem& other) {
  for (size_t i = 0; i < ata.size(); ++i) ata[i] += other.ata[i];
  for (size_t i = 0; i < atb.size(); ++i) atb[i] += other.atb[i];
  error_sq += other.error_sq;
  inliers += other.inliers;
  valid_points += other.valid_points;
}

std::string IcpTracker::Params::validate() const {
  std::ostringstream why;
  for (int it : iterations_coarse_to_fine)
    if (it < 0) why << "iterations must be >= 0; ";
  if (!(distance_gate_m > 0.f)) why << "distance_gate_m must be > 0; ";
  if (!(normal_angle_gate_rad > 0.f && normal_angle_gate_rad <= 1.5707964f))
    why << "normal_angle_gate_rad must be in (0, pi/2]; ";
  if (!(min_inlier_fraction > 0.f && min_inlier_fraction <= 1.f)) why << "min_inlier_fraction must be in (0, 1]; ";
  if (min_inliers < 6) why << "min_inliers must be >= 6; ";
  if (!(min_eigenvalue_ratio > 0.0 && min_eigenvalue_ratio < 1.0)) why << "min_eigenvalue_ratio must be in (0, 1); ";
  if (!(max_translation_m > 0.f)) why << "max_translation_m must be > 0; ";
  if (!(max_rotation_rad > 0.f)) why << "max_rotation_rad must be > 0; ";
  if (!(max_rmse_m > 0.f)) why << "max_rmse_m must be > 0; ";
  if (!(huber_sigmas >= 0.f)) why << "huber_sigmas must be >= 0; ";
  if (!(convergence_epsilon >= 0.0)) why << "convergence_epsilon must be >= 0; ";
  return why.str();
}

IcpTracker::IcpTracker(const Params& params) : params_(params) {}

namespace {

// Projective association and the point-to-plane row for one current pixel. Returns false when
// the pixel has no acceptable correspondence.
inline bool correspondence(const Eigen::Vector3f& v_cur, const Eigen::Vector3f& n_cur,
                           const Eigen::Matrix3f& R, const Eigen::Vector3f& t,
                           const PinholeCamera& cam, const ModelMaps& model, int level,
                           float gate_sq, float cos_gate, Eigen::Matrix<float, 6, 1>* J,
                           float* e) {
  const Eigen::Vector3f p = R * v_cur + t;
  if (p.z() <= 0.f) return false;
  const int u = roundToInt(cam.fx * p.x() / p.z() + cam.cx);
  const int v = roundToInt(cam.fy * p.y() / p.z() + cam.cy);
  if (u < 0 || v < 0 || u >= cam.width || v >= cam.height) return false;
  const Eigen::Vector3f& q = model.vertex_ref[level](u, v);
  const Eigen::Vector3f& nq = model.normal_ref[level](u, v);
  if (!isValid(q) || !isValid(nq)) return false;
  const Eigen::Vector3f d = p - q;
  if (d.squaredNorm() > gate_sq) return false;
  if ((R * n_cur).dot(nq) < cos_gate) return false;
  J->head<3>() = p.cross(nq);
  J->tail<3>() = nq;
  *e = nq.dot(d);
  return true;
}

// Rows are summed in fixed chunks and the chunks added in order, so the result does not depend
// on the number of threads (serial and parallel loops agree to the last bit).
constexpr int kChunks = 64;

}  // namespace

IcpSystem IcpTracker::buildSystem(const DepthFrame& current, const ModelMaps& model, int level,
                                  const Eigen::Matrix3f& R_ref_cur,
                                  const Eigen::Vector3f& t_ref_cur, float distance_gate_m,
                                  float cos_angle_gate, bool noise_weighting, float huber_sigmas,
                                  bool parallel) {
  const float sigma_1m = kinectNoiseSigmaM(1.f);
  const ImageView<const Eigen::Vector3f> vmap = current.vertex_cam[level].view();
  const ImageView<const Eigen::Vector3f> nmap = current.normal_cam[level].view();
  const PinholeCamera& cam = model.camera[level];
  const int h = vmap.height(), w = vmap.width();
  const float gate_sq = distance_gate_m * distance_gate_m;
  std::array<IcpSystem, kChunks> chunks;
#pragma omp parallel for schedule(dynamic, 1) if (parallel)
  for (int c = 0; c < kChunks; ++c) {
    IcpSystem& s = chunks[c];
    s = IcpSystem();
    const int y0 = h * c / kChunks, y1 = h * (c + 1) / kChunks;
    for (int y = y0; y < y1; ++y) {
      const Eigen::Vector3f* vrow = vmap.row(y);
      const Eigen::Vector3f* nrow = nmap.row(y);
      // A row sums in float (at most a few thousand terms of similar size), the chunk in double.
      std::array<float, 28> row{};  // 21 upper-triangle A, 6 b, 1 squared error
      for (int x = 0; x < w; ++x) {
        if (!isValid(vrow[x]) || !isValid(nrow[x])) continue;
        ++s.valid_points;
        Eigen::Matrix<float, 6, 1> J;
        float e;
        if (!correspondence(vrow[x], nrow[x], R_ref_cur, t_ref_cur, cam, model, level, gate_sq,
                            cos_angle_gate, &J, &e))
          continue;
        row[27] += e * e;  // the reported residual stays in metres, unweighted
        const float sigma = kinectNoiseSigmaM(vrow[x].z());
        float weight = noise_weighting ? (sigma_1m * sigma_1m) / (sigma * sigma) : 1.f;
        const float abs_r = std::fabs(e) / sigma;
        if (huber_sigmas > 0.f && abs_r > huber_sigmas) weight *= huber_sigmas / abs_r;
        // The weight enters J^T J and J^T e once each: scale both factors by its square root.
        const float sqrt_w = std::sqrt(weight);
        J *= sqrt_w;
        e *= sqrt_w;
        int k = 0;
        for (int i = 0; i < 6; ++i)
          for (int j = i; j < 6; ++j) row[k++] += J[i] * J[j];
        for (int i = 0; i < 6; ++i) row[21 + i] -= J[i] * e;
        ++s.inliers;
      }
      for (int i = 0; i < 21; ++i) s.ata[i] += row[i];
      for (int i = 0; i < 6; ++i) s.atb[i] += row[21 + i];
      s.error_sq += row[27];
    }
  }
  IcpSystem total;
  for (const IcpSystem& s : chunks) total.add(s);
  return total;
}

IcpResult IcpTracker::track(const DepthFrame& current, const ModelMaps& model,
                            const Pose& T_ref_cur_guess) const {
  IcpResult result;
  result.T_ref_cur = T_ref_cur_guess;
  const float cos_gate = std::cos(params_.normal_angle_gate_rad);
  auto fail = [&](const std::string& why) {
    result.status = TrackingStatus::kLost;
    result.T_ref_cur = T_ref_cur_guess;
    result.reason = why;
    return result;
  };

  Pose T = T_ref_cur_guess;
  IcpSystem last;
  for (int step = 0; step < kPyramidLevels; ++step) {
    const int level = kPyramidLevels - 1 - step;
    const int iterations = params_.iterations_coarse_to_fine[step];
    for (int it = 0; it < iterations; ++it) {
      const Eigen::Matrix3f R = T.linear().cast<float>();
      const Eigen::Vector3f t = T.translation().cast<float>();
      last = buildSystem(current, model, level, R, t, params_.distance_gate_m, cos_gate,
                         params_.noise_weighting, params_.huber_sigmas, true);
      ++result.iterations;
      if (last.inliers < params_.min_inliers) {
        std::ostringstream why;
        why << "too few correspondences at level " << level << " (" << last.inliers << ")";
        return fail(why.str());
      }
      Eigen::Matrix<double, 6, 6> A;
      int k = 0;
      for (int i = 0; i < 6; ++i)
        for (int j = i; j < 6; ++j) A(i, j) = A(j, i) = last.ata[k++];
      const Eigen::Matrix<double, 6, 1> b(last.atb.data());
      const Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 6, 6>> eig(A, Eigen::EigenvaluesOnly);
      const double max_ev = eig.eigenvalues()(5), min_ev = eig.eigenvalues()(0);
      if (!(max_ev > 0.0) || !(min_ev / max_ev >= params_.min_eigenvalue_ratio))
        return fail("degenerate geometry (the scene does not constrain all six degrees of freedom)");
      const Eigen::LLT<Eigen::Matrix<double, 6, 6>> llt(A);
      if (llt.info() != Eigen::Success) return fail("Cholesky factorisation failed");
      const Eigen::Matrix<double, 6, 1> xi = llt.solve(b);
      if (!xi.allFinite()) return fail("non-finite ICP update");
      T = orthonormalized(expTwist(xi) * T);
      if (xi.norm() < params_.convergence_epsilon) break;
    }
  }
  if (!isFinite(T)) return fail("non-finite pose");

  // Statistics of the finest level from its last iteration (one update before the final pose,
  // which after convergence differs by less than the update tolerance).
  result.inlier_fraction =
      last.valid_points > 0 ? static_cast<float>(last.inliers) / static_cast<float>(last.valid_points) : 0.f;
  result.rmse_m = last.inliers > 0 ? static_cast<float>(std::sqrt(last.error_sq / last.inliers)) : 0.f;

  const Pose jump = T_ref_cur_guess.inverse() * T;
  std::ostringstream why;
  if (jump.translation().norm() > params_.max_translation_m)
    why << "jump of " << jump.translation().norm() << " m exceeds max_translation_m";
  else if (rotationAngleRad(jump) > params_.max_rotation_rad)
    why << "rotation of " << rotationAngleRad(jump) << " rad exceeds max_rotation_rad";
  else if (result.inlier_fraction < params_.min_inlier_fraction)
    why << "inlier fraction " << result.inlier_fraction << " below min_inlier_fraction";
  else if (result.rmse_m > params_.max_rmse_m)
    why << "residual " << result.rmse_m << " m exceeds max_rmse_m";
  if (!why.str().empty()) return fail(why.str());  // keeps the measured inliers and residual
  result.T_ref_cur = T;
  result.status = TrackingStatus::kOk;
  return result;
}

}  // namespace kinfly
