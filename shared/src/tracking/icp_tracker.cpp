#include "kinfly/tracking/icp_tracker.h"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <optional>
#include <sstream>

#include "kinfly/core/noise_model.h"
#include "parallel.h"

namespace kinfly {

void IcpSystem::add(const IcpSystem& other) {
  for (size_t i = 0; i < ata.size(); ++i) ata[i] += other.ata[i];
  for (size_t i = 0; i < atb.size(); ++i) atb[i] += other.atb[i];
  error_sq += other.error_sq;
  noise_sq += other.noise_sq;
  inliers += other.inliers;
  matched += other.matched;
  valid_points += other.valid_points;
}

Status IcpTracker::Params::validate() const {
  std::ostringstream why;
  for (int it : iterations_coarse_to_fine)
    if (it < 0) why << "iterations must be >= 0; ";
  if (!(distance_gate_m > 0.f)) why << "distance_gate_m must be > 0; ";
  if (!(normal_angle_gate_rad > 0.f && normal_angle_gate_rad <= 1.5707964f))
    why << "normal_angle_gate_rad must be in (0, pi/2]; ";
  if (!(min_inlier_fraction > 0.f && min_inlier_fraction <= 1.f)) why << "min_inlier_fraction must be in (0, 1]; ";
  if (min_inliers < 6) why << "min_inliers must be >= 6; ";
  if (!(weak_direction_fraction >= 0.0 && weak_direction_fraction < 1.0 / 6.0))
    why << "weak_direction_fraction must be in [0, 1/6); ";
  if (max_weak_directions < 0 || max_weak_directions > 5)
    why << "max_weak_directions must be in [0, 5]; ";
  if (!(suspect_direction_fraction >= weak_direction_fraction &&
        suspect_direction_fraction < 1.0 / 6.0))
    why << "suspect_direction_fraction must be in [weak_direction_fraction, 1/6); ";
  if (!(facing_cosine > 0.0 && facing_cosine < 1.0)) why << "facing_cosine must be in (0, 1); ";
  if (!(max_translation_m > 0.f)) why << "max_translation_m must be > 0; ";
  if (!(max_rotation_rad > 0.f)) why << "max_rotation_rad must be > 0; ";
  if (!(max_rmse_m > 0.f)) why << "max_rmse_m must be > 0; ";
  if (!(max_rmse_sigmas >= 0.f)) why << "max_rmse_sigmas must be >= 0; ";
  if (!(huber_sigmas >= 0.f)) why << "huber_sigmas must be >= 0; ";
  if (!(normal_gate_sigmas >= 0.f && std::isfinite(normal_gate_sigmas)))
    why << "normal_gate_sigmas must be finite and >= 0; ";
  if (!(convergence_epsilon >= 0.0)) why << "convergence_epsilon must be >= 0; ";
  return why.str().empty() ? Status() : Status::error(why.str());
}

IcpTracker::IcpTracker(const Params& params) : params_(params) {}

IcpTracker::SystemParams IcpTracker::systemParams() const {
  SystemParams system;
  system.distance_gate_m = params_.distance_gate_m;
  system.cos_angle_gate = std::cos(params_.normal_angle_gate_rad);
  system.normal_gate_sigmas = params_.normal_gate_sigmas;
  system.noise_weighting = params_.noise_weighting;
  system.huber_sigmas = params_.huber_sigmas;
  system.parallel = true;
  return system;
}

namespace {

// The system is built four points at a time (lanes::Floats, see lanes.h).
using lanes::Floats;
using lanes::Ints;
using lanes::kWidth;
using lanes::load;
static_assert(PackedPoints::kRowPadding % kWidth == 0, "point loads must stay inside a row");

// Four 3-vectors, one coordinate per register.
struct Vec3s {
  Floats x, y, z;
};
// Sums in Eigen's order for 3-vectors (x + (y + z)), so the gates see the same floats as
// Eigen's scalar expressions would.
inline Floats dot(const Vec3s& a, const Vec3s& b) { return a.x * b.x + (a.y * b.y + a.z * b.z); }
inline Vec3s rotate(const Eigen::Matrix3f& R, const Vec3s& v) {
  return {R(0, 0) * v.x + (R(0, 1) * v.y + R(0, 2) * v.z),
          R(1, 0) * v.x + (R(1, 1) * v.y + R(1, 2) * v.z),
          R(2, 0) * v.x + (R(2, 1) * v.y + R(2, 2) * v.z)};
}
// x and y of a point travel together as one 8-byte lane, two points to a register, and are then
// split by one shuffle each; four separate loads per coordinate would cost twice the instructions.
inline Vec3s gather(const Eigen::Vector3f* map, Ints pixel) {
  typedef double Pairs __attribute__((vector_size(16)));
  const float *p0 = map[pixel[0]].data(), *p1 = map[pixel[1]].data(), *p2 = map[pixel[2]].data(),
              *p3 = map[pixel[3]].data();
  auto pair = [](const float* p) {
    double xy;
    std::memcpy(&xy, p, sizeof xy);
    return xy;
  };
  const Floats xy01 = reinterpret_cast<Floats>(Pairs{pair(p0), pair(p1)});
  const Floats xy23 = reinterpret_cast<Floats>(Pairs{pair(p2), pair(p3)});
  return {lanes::shuffle<0, 2, 4, 6>(xy01, xy23), lanes::shuffle<1, 3, 5, 7>(xy01, xy23),
          Floats{p0[2], p1[2], p2[2], p3[2]}};
}

// Everything the kernels need that is fixed for one system.
struct Association {
  Eigen::Matrix3f R;
  Eigen::Vector3f t;
  float fx, fy, cx, cy;
  int width, height;
  float gate_sq;  // [m^2]
  float cos_gate;
  // The widened gate's tangent per metre of sensor noise sigma (0: the fixed gate alone).
  float tan_gate_per_sigma;
  bool noise_weighting;
  float huber_k;  // Huber threshold in noise sigmas; infinite when the robust weight is off
  // SystemParams::facing: the unit direction, and the squared cosine a normal must reach.
  Eigen::Vector3f facing;
  float facing_cos_sq;
};

// Current points in the reference frame.
inline Vec3s transform(const Association& a, const Vec3s& v_cur) {
  const Vec3s r = rotate(a.R, v_cur);
  return {r.x + a.t.x(), r.y + a.t.y(), r.z + a.t.z()};
}

// Model pixels (row-major index) onto which points p (reference frame) project; `inside` says which
// land in the image in front of the camera, and the others get pixel 0 so any lookup is safe.
inline Ints modelPixel(const Vec3s& p, const Association& a, Ints* inside) {
  const Floats inv_z = 1.f / p.z;
  const Floats u = a.fx * p.x * inv_z + a.cx;
  const Floats v = a.fy * p.y * inv_z + a.cy;
  // Only (-0.5, size) can round into the image; converting nothing else keeps the cast defined.
  const Ints near = (p.z > 0.f) & (u > -0.5f) & (v > -0.5f) &
                    (u < static_cast<float>(a.width)) & (v < static_cast<float>(a.height));
  // Non-negative after the +0.5, so truncation rounds half away from zero (as roundToInt).
  const Ints iu = __builtin_convertvector((near ? u : 0.f) + 0.5f, Ints);
  const Ints iv = __builtin_convertvector((near ? v : 0.f) + 0.5f, Ints);
  *inside = near & (iu < a.width) & (iv < a.height);
  return *inside ? iv * a.width + iu : 0;
}

// Columns of one point-to-plane row: J, the residual e, the residual's weight and the sensor
// noise's variance at its depth (zero for a rejected pair). The system sums w J J^T, w J e and,
// for the residual gate, e^2 and the variance.
constexpr int kColumns = 9;
constexpr int kResidual = 6, kWeight = 7, kNoiseVar = 8;
constexpr int kErrorSum = 27, kNoiseSum = 28;  // after 21 upper-triangle A and 6 b
constexpr int kSums = 29;

// The rows of current points (p in the reference frame, depth z_cur, normal n_cur) against model
// points (q, nq) where `found`; rejected pairs give zero rows. Returns the inlier mask. kFacing:
// only the rows that face SystemParams::facing are inliers.
template <bool kFacing>
inline Ints pointToPlane(const Vec3s& p, Floats z_cur, const Vec3s& n_cur, const Vec3s& q,
                         const Vec3s& nq, Ints found, const Association& a, Floats row[kColumns]) {
  const Vec3s d{p.x - q.x, p.y - q.y, p.z - q.z};
  const Vec3s n_ref = rotate(a.R, n_cur);
  const Floats sigma = lanes::lanewise(kinectNoiseSigmaM, z_cur);
  // The widened gate: cos >= 1 / sqrt(1 + tan^2), squared to spare the root. The fixed gate is
  // its floor, so the wider of the two decides.
  const Floats cos_n = dot(n_ref, nq);
  const Floats tan_w = a.tan_gate_per_sigma * sigma;
  const Ints within_angle =
      ~(cos_n < a.cos_gate) | ((cos_n > 0.f) & ~(cos_n * cos_n * (1.f + tan_w * tan_w) < 1.f));
  Ints inlier = found & ~(dot(d, d) > a.gate_sq) & within_angle;
  // Both normals must face it: the model's normal of a surface seen edge-on is the TSDF's
  // gradient, which the projective distances of grazing rays tilt towards the view, while the
  // frame's, from its own neighbouring points, is not.
  if constexpr (kFacing) {
    const Floats along = a.facing.x() * nq.x + a.facing.y() * nq.y + a.facing.z() * nq.z;
    const Floats along_cur =
        a.facing.x() * n_ref.x + a.facing.y() * n_ref.y + a.facing.z() * n_ref.z;
    inlier &= (along * along >= a.facing_cos_sq) & (along_cur * along_cur >= a.facing_cos_sq);
  }
  const Floats e = dot(nq, d);
  // Noise weight (sigma_1m / sigma)^2, normalised to 1 at 1 m, times the Huber weight k / |r|
  // beyond k sigmas. Using the weight itself, not its square root on both factors, saves a
  // square root; one reciprocal of sigma saves two divisions.
  const Floats inv_sigma = 1.f / sigma;
  const Floats noise_sqrt = kinectNoiseSigmaM(1.f) * inv_sigma;
  const Floats noise = a.noise_weighting ? noise_sqrt * noise_sqrt : lanes::splat(1.f);
  const Floats abs_r = lanes::abs(e) * inv_sigma;
  const Floats weight = abs_r > a.huber_k ? noise * (a.huber_k / abs_r) : noise;
  const Floats values[kColumns] = {p.y * nq.z - p.z * nq.y,  // p x nq
                                   p.z * nq.x - p.x * nq.z,
                                   p.x * nq.y - p.y * nq.x,
                                   nq.x, nq.y, nq.z, e, weight, sigma * sigma};
  for (int k = 0; k < kColumns; ++k) row[k] = inlier ? values[k] : 0.f;
  return inlier;
}

// Rows are gathered a block at a time into columns, one register of four lanes per entry, and
// their products summed down the columns with the accumulators in registers; summing each row's
// 28 products into memory as it comes would make the loop wait on loads and stores.
constexpr int kBlockGroups = 32;  // groups of four points per block: the columns stay in L1
struct Columns {
  Floats c[kColumns][kBlockGroups];
  int groups;
};

// Adds the weighted products of the block's rows with row I of [J e]'s upper triangle
// (w J_I J_b for b >= I, then w J_I e) to sums[0 .. 7 - I). A template so that the short loops
// unroll and the accumulators live in registers.
template <int I>
inline void accumulateRow(const Columns& cols, Floats* sums) {
  Floats acc[7 - I] = {};
  for (int g = 0; g < cols.groups; ++g) {
    const Floats weighted = cols.c[kWeight][g] * cols.c[I][g];
    for (int j = 0; j < 7 - I; ++j) acc[j] += weighted * cols.c[I + j][g];
  }
  for (int j = 0; j < 7 - I; ++j) sums[j] += acc[j];
}

// Adds the block's rows to `sums`: row by row of [J e]'s weighted upper triangle, then the
// squared error and the noise's variance.
inline void accumulate(const Columns& cols, Floats sums[kSums]) {
  accumulateRow<0>(cols, sums);
  accumulateRow<1>(cols, sums + 7);
  accumulateRow<2>(cols, sums + 13);
  accumulateRow<3>(cols, sums + 18);
  accumulateRow<4>(cols, sums + 22);
  accumulateRow<5>(cols, sums + 25);
  Floats error = {}, noise = {};
  for (int g = 0; g < cols.groups; ++g) {
    error += cols.c[kResidual][g] * cols.c[kResidual][g];
    noise += cols.c[kNoiseVar][g];
  }
  sums[kErrorSum] += error;
  sums[kNoiseSum] += noise;
}

// Rows are summed in fixed chunks and the chunks added in order, so the result does not depend
// on the number of threads (serial and parallel loops agree to the last bit).
constexpr int kChunks = 64;

}  // namespace

namespace {

template <bool kFacing>
IcpSystem build(const DepthFrame& current, const ModelMaps& model, int level,
                const Association& assoc, bool parallel) {
  const PackedPoints& points = current.points[level];
  const Eigen::Vector3f* vmodel = model.vertex_ref[level].data();
  const Eigen::Vector3f* nmodel = model.normal_ref[level].data();
  const int h = points.vx.height();
  std::array<IcpSystem, kChunks> chunks;
  forEachDynamic(kChunks, 1, parallel, [&](int c) {
    IcpSystem& s = chunks[c];
    s = IcpSystem();
    const int y0 = h * c / kChunks, y1 = h * (c + 1) / kChunks;
    for (int y = y0; y < y1; ++y) {
      const float *vx = points.vx.view().row(y), *vy = points.vy.view().row(y),
                  *vz = points.vz.view().row(y), *nx = points.nx.view().row(y),
                  *ny = points.ny.view().row(y), *nz = points.nz.view().row(y);
      const int count = points.row_count[y];
      s.valid_points += count;
      // A row sums in float (at most a few thousand terms of similar size), the chunk in double.
      Floats sums[kSums] = {};
      Ints inliers = {}, matched = {};
      Columns cols;
      for (int b = 0; b < count; b += kWidth * kBlockGroups) {
        const int groups = (std::min(count - b, kWidth * kBlockGroups) + kWidth - 1) / kWidth;
        // All of the block's projections first, so that the lookups do not wait on each one.
        Vec3s p[kBlockGroups];
        Ints pixel[kBlockGroups], inside[kBlockGroups];
        for (int g = 0; g < groups; ++g) {
          const int i = b + kWidth * g;
          p[g] = transform(assoc,
                           {load<Floats>(vx + i), load<Floats>(vy + i), load<Floats>(vz + i)});
          pixel[g] = modelPixel(p[g], assoc, &inside[g]);
        }
        // A group of four rejected pairs would add only +0 rows, which change no sum (the sums
        // start at +0 and so are never -0): it is left out of the columns, and the groups kept
        // keep their lanes and their order.
        cols.groups = 0;
        for (int g = 0; g < groups; ++g) {
          if (lanes::none(inside[g])) continue;
          const int i = b + kWidth * g;
          const Vec3s q = gather(vmodel, pixel[g]), nq = gather(nmodel, pixel[g]);
          // Padding past the row's last point takes part in nothing; NaN marks no model point.
          const Ints found =
              (i + Ints{0, 1, 2, 3} < count) & inside[g] & (q.x == q.x) & (nq.x == nq.x);
          if (lanes::none(found)) continue;
          matched -= found;  // true lanes are -1
          Floats row[kColumns];
          const Ints inlier = pointToPlane<kFacing>(
              p[g], load<Floats>(vz + i),
              {load<Floats>(nx + i), load<Floats>(ny + i), load<Floats>(nz + i)}, q, nq, found,
              assoc, row);
          if (lanes::none(inlier)) continue;
          inliers -= inlier;  // true lanes are -1
          for (int k = 0; k < kColumns; ++k) cols.c[k][cols.groups] = row[k];
          ++cols.groups;
        }
        accumulate(cols, sums);
      }
      s.inliers += (inliers[0] + inliers[1]) + (inliers[2] + inliers[3]);
      s.matched += (matched[0] + matched[1]) + (matched[2] + matched[3]);
      std::array<float, kSums> row;
      for (int k = 0; k < kSums; ++k)
        row[k] = (sums[k][0] + sums[k][1]) + (sums[k][2] + sums[k][3]);
      // Back from row by row of [J e]'s upper triangle to A and b.
      int k = 0, ata = 0;
      for (int i = 0; i < 6; ++i) {
        for (int j = i; j < 6; ++j) s.ata[ata++] += row[k++];
        s.atb[i] -= row[k++];
      }
      s.error_sq += row[kErrorSum];
      s.noise_sq += row[kNoiseSum];
    }
  });
  IcpSystem total;
  for (const IcpSystem& s : chunks) total.add(s);
  return total;
}

}  // namespace

IcpSystem IcpTracker::buildSystem(const DepthFrame& current, const ModelMaps& model, int level,
                                  const Eigen::Matrix3f& R_ref_cur,
                                  const Eigen::Vector3f& t_ref_cur,
                                  const SystemParams& params) {
  const PinholeCamera& cam = model.camera[level];
  const float huber_k =
      params.huber_sigmas > 0.f ? params.huber_sigmas : std::numeric_limits<float>::infinity();
  Association assoc{R_ref_cur, t_ref_cur, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height,
                    params.distance_gate_m * params.distance_gate_m, params.cos_angle_gate,
                    model.normal_spacing_m > 0.f
                        ? params.normal_gate_sigmas / model.normal_spacing_m
                        : 0.f,
                    params.noise_weighting, huber_k, {}, 0.f};
  if (!params.facing) return build<false>(current, model, level, assoc, params.parallel);
  assoc.facing = params.facing->direction.normalized().cast<float>();
  assoc.facing_cos_sq = static_cast<float>(params.facing->cosine * params.facing->cosine);
  return build<true>(current, model, level, assoc, params.parallel);
}

namespace {

// Below this (weak_direction_fraction's units) a direction is numerically singular: rounding,
// not the scene.
constexpr double kSingularFraction = 1e-9;
// A scaled unit direction with at least this squared translation part is mostly a translation.
constexpr double kMostlyTranslation = 0.5;

using Matrix6d = Eigen::Matrix<double, 6, 6>;
using Vector6d = Eigen::Matrix<double, 6, 1>;

Matrix6d unpack(const IcpSystem& system) {
  Matrix6d A;
  int k = 0;
  for (int i = 0; i < 6; ++i)
    for (int j = i; j < 6; ++j) A(i, j) = A(j, i) = system.ata[k++];
  return A;
}

// A system in units of y = S^-1 xi (rotations times the lever arm), divided by its weight: S A S
// / weight, whose eigenvalues are the shares of its eigen-directions (weak_direction_fraction's
// units).
struct Scaled {
  double weight;   // sum of w |n|^2 = sum of w
  Vector6d s;      // S's diagonal: 1 / the lever arm for the rotations, 1 for the translations
  Eigen::SelfAdjointEigenSolver<Matrix6d> eig;
};

// Empty when the system has no weight, no lever or is not finite.
std::optional<Scaled> scaled(const Matrix6d& A, const Vector6d& b) {
  const double weight = A.bottomRightCorner<3, 3>().trace();
  const double rotation = A.topLeftCorner<3, 3>().trace();  // sum of w |p x n|^2
  if (!(weight > 0.0) || !(rotation > 0.0) || !A.allFinite() || !b.allFinite())
    return std::nullopt;
  Scaled out;
  out.weight = weight;
  const double inv_lever = std::sqrt(weight / rotation);
  out.s << inv_lever, inv_lever, inv_lever, 1.0, 1.0, 1.0;
  out.eig.compute(out.s.asDiagonal() * A * out.s.asDiagonal() / weight);
  if (out.eig.info() != Eigen::Success) return std::nullopt;
  return out;
}

// Lists the weak directions in *result and solves A xi = b (`scaled_system` is scaled(A, b)): by
// Cholesky, or, where some are weak and `keep_weak`, in the directions the system constrains
// only, leaving xi zero along the weak ones. False when the system is empty, not finite or not
// positive definite.
bool solve(const Matrix6d& A, const Vector6d& b, const std::optional<Scaled>& scaled_system,
           double weak_fraction, bool keep_weak, Vector6d* xi, IcpResult* result) {
  result->weak_directions = 0;
  if (!scaled_system) {
    result->weak_directions = 6;
    return false;
  }
  const double weight = scaled_system->weight;
  const Vector6d& s = scaled_system->s;
  const auto& eig = scaled_system->eig;
  result->weakest_fraction = eig.eigenvalues()(0);
  for (int i = 0; i < 6 && eig.eigenvalues()(i) < weak_fraction; ++i) {  // ascending
    result->weak[result->weak_directions++] =
        s.cwiseProduct(eig.eigenvectors().col(i)).normalized();
  }
  // A direction with no information at all cannot be solved, unless a prior is kept along it.
  const bool kept = keep_weak && result->weak_directions > 0;
  if (eig.eigenvalues()(0) < kSingularFraction && !kept) return false;
  if (!kept) {
    const Eigen::LLT<Eigen::Matrix<double, 6, 6>> llt(A);
    if (llt.info() != Eigen::Success) return false;
    *xi = llt.solve(b);
    return true;
  }
  if (result->weak_directions == 6) return false;
  // Zhang et al.'s solution remapping: the update within the span of the strong directions.
  const Vector6d sb = s.cwiseProduct(b) / weight;
  Vector6d y = Vector6d::Zero();
  for (int i = result->weak_directions; i < 6; ++i) {
    const Vector6d v = eig.eigenvectors().col(i);
    y += v * (v.dot(sb) / eig.eigenvalues()(i));
  }
  *xi = s.cwiseProduct(y);
  return true;
}

// From a prior: each direction ICP moved along (not weak in *result; `system` is the finest one
// solved, at LEVEL) whose share is below suspect_direction_fraction and whose facing pairs' share
// is below weak_direction_fraction is weak too: added to *result, and *T keeps T_prior along it.
// False when that makes more than max_weak_directions.
bool keepPriorAlongScatter(const IcpTracker::Params& params,
                           IcpTracker::SystemParams facing_params,
                           const DepthFrame& current, const ModelMaps& model, const Scaled& system,
                           int level, const Pose& T_prior, Pose* T, IcpResult* result) {
  const Vector6d& s = system.s;
  // The motion since the prior, in the scaled units: T = expTwist(S y) * T_prior.
  const Pose moved = *T * T_prior.inverse();
  const Eigen::AngleAxisd rotation(moved.linear());
  Vector6d xi;
  xi << rotation.angle() * rotation.axis(), moved.translation();
  Vector6d y = xi.cwiseQuotient(s);
  bool scatter = false;
  // The directions solve() left to ICP (its weak ones come first, in ascending share). Only a
  // motion mostly of translation: a rotation's information comes from its levers, many rows'
  // small parts, which no surface faces (the roll about a corridor's axis).
  for (int i = result->weak_directions;
       i < 6 && system.eig.eigenvalues()(i) < params.suspect_direction_fraction; ++i) {
    const Vector6d v = system.eig.eigenvectors().col(i);
    if (v.tail<3>().squaredNorm() < kMostlyTranslation) continue;
    facing_params.facing = IcpTracker::Facing{v.tail<3>(), params.facing_cosine};
    const Matrix6d F =
        unpack(IcpTracker::buildSystem(current, model, level, T->linear().cast<float>(),
                                       T->translation().cast<float>(), facing_params));
    const Vector6d d = s.cwiseProduct(v);
    if (d.dot(F * d) / system.weight >= params.weak_direction_fraction) continue;
    result->weak[result->weak_directions++] = d.normalized();
    y -= v * v.dot(y);
    scatter = true;
  }
  if (scatter) *T = orthonormalized(expTwist(s.cwiseProduct(y)) * T_prior);
  return result->weak_directions <= params.max_weak_directions;
}

}  // namespace

IcpResult IcpTracker::track(const DepthFrame& current, const ModelMaps& model,
                            const Pose& T_ref_cur_guess, bool prior, float gate_scale) const {
  IcpResult result;
  result.T_ref_cur = T_ref_cur_guess;
  SystemParams system = systemParams();
  system.distance_gate_m *= gate_scale;
  const float max_translation_m = params_.max_translation_m * gate_scale;
  const float max_rotation_rad = params_.max_rotation_rad * gate_scale;
  auto fail = [&](const std::string& why) {
    result.status = TrackingStatus::kLost;
    result.T_ref_cur = T_ref_cur_guess;
    result.reason = why;
    return result;
  };

  const auto degenerate = [&](const char* weak_how) {
    std::ostringstream why;
    why << "degenerate geometry: " << result.weak_directions
        << " of the six directions of motion are " << weak_how << " (max_weak_directions "
        << params_.max_weak_directions << ")";
    return fail(why.str());
  };

  Pose T = T_ref_cur_guess;
  IcpSystem last;
  std::optional<Scaled> last_scaled;
  int last_level = kPyramidLevels - 1;
  for (int step = 0; step < kPyramidLevels; ++step) {
    const int level = kPyramidLevels - 1 - step;
    const int iterations = params_.iterations_coarse_to_fine[step];
    for (int it = 0; it < iterations; ++it) {
      const Eigen::Matrix3f R = T.linear().cast<float>();
      const Eigen::Vector3f t = T.translation().cast<float>();
      last = buildSystem(current, model, level, R, t, system);
      last_level = level;
      ++result.iterations;
      if (last.inliers < params_.min_inliers) {
        std::ostringstream why;
        why << "too few correspondences at level " << level << " (" << last.inliers << ")";
        return fail(why.str());
      }
      const Matrix6d A = unpack(last);
      const Vector6d b(last.atb.data());
      last_scaled = scaled(A, b);
      Vector6d xi;
      if (!solve(A, b, last_scaled, params_.weak_direction_fraction, prior, &xi, &result))
        return fail("degenerate geometry: the ICP system is singular");
      // Coarse levels see fewer pixels and often more weak directions: the finest one decides.
      if (level == 0 && result.weak_directions > params_.max_weak_directions)
        return degenerate("weak");
      if (!xi.allFinite()) return fail("non-finite ICP update");
      T = orthonormalized(expTwist(xi) * T);
      if (xi.norm() < params_.convergence_epsilon) break;
    }
  }
  if (!isFinite(T)) return fail("non-finite pose");
  // No system when every level's iterations are 0: the guess is kept as it is.
  if (prior && last_scaled &&
      !keepPriorAlongScatter(params_, systemParams(), current, model, *last_scaled, last_level,
                             T_ref_cur_guess, &T, &result))
    return degenerate("weak, or constrained by scatter alone");

  // Statistics of the finest level from its last iteration (one update before the final pose,
  // which after convergence differs by less than the update tolerance).
  result.inlier_fraction =
      last.valid_points > 0 ? static_cast<float>(last.inliers) / static_cast<float>(last.valid_points) : 0.f;
  result.rmse_m = last.inliers > 0 ? static_cast<float>(std::sqrt(last.error_sq / last.inliers)) : 0.f;
  result.noise_rms_m =
      last.inliers > 0 ? static_cast<float>(std::sqrt(last.noise_sq / last.inliers)) : 0.f;
  result.max_rmse_m = std::max(params_.max_rmse_m, params_.max_rmse_sigmas * result.noise_rms_m);

  const Pose jump = T_ref_cur_guess.inverse() * T;
  std::ostringstream why;
  // Written only when a gate fails: a tracked frame allocates nothing.
  const auto widened = [&](std::ostringstream& out) {
    if (gate_scale != 1.f) out << " times " << gate_scale << " after missed frames";
  };
  if (jump.translation().norm() > max_translation_m) {
    why << "jump of " << jump.translation().norm() << " m exceeds max_translation_m";
    widened(why);
  } else if (rotationAngleRad(jump) > max_rotation_rad) {
    why << "rotation of " << rotationAngleRad(jump) << " rad exceeds max_rotation_rad";
    widened(why);
  } else if (result.inlier_fraction < params_.min_inlier_fraction) {
    why << "inlier fraction " << result.inlier_fraction << " below min_inlier_fraction ("
        << last.matched << " of " << last.valid_points << " points have a model point)";
  } else if (result.rmse_m > result.max_rmse_m) {
    why << "residual " << result.rmse_m << " m exceeds the gate of " << result.max_rmse_m
        << " m (max_rmse_m " << params_.max_rmse_m << ", or max_rmse_sigmas "
        << params_.max_rmse_sigmas << " times the sensor noise's " << result.noise_rms_m
        << " m at these depths)";
  }
  if (!why.str().empty()) return fail(why.str());  // keeps the measured inliers and residual
  result.T_ref_cur = T;
  result.status = TrackingStatus::kOk;
  return result;
}

}  // namespace kinfly
