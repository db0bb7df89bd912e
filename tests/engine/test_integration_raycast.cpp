// TsdfIntegrator + Raycaster on analytic planes and spheres, for both volumes: the raycast
// surface is where the scene says it is, voxels hold the signed distance, and threading does
// not change a single voxel.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <memory>
#include <random>
#include <vector>

#include "kinfly/raycast/raycaster.h"
#include "kinfly/volume/tsdf_integrator.h"
#include "kinfly/volume/tsdf_volume.h"
#include "test_util.h"

namespace kinfly {
namespace {

constexpr float kHashedVoxelM = 0.01f;
constexpr float kHashedTruncationM = 0.04f;  // 4 voxels, the engine default
constexpr float kDenseVoxelM = 0.02f;
constexpr float kDenseTruncationM = 0.06f;   // must exceed 2 voxels
constexpr int kNoisyFrames = 10;

// A plane tilted ~10 degrees, 1.5 m in front of the camera; n faces the camera.
struct TiltedPlane {
  Eigen::Vector3f n = Eigen::Vector3f(0.15f, -0.1f, -1.f).normalized();
  float offset = n.dot(Eigen::Vector3f(0.f, 0.f, 1.5f));
  SyntheticScene scene() const {
    SyntheticScene s;
    s.addPlane(n, offset);
    return s;
  }
};

std::unique_ptr<TsdfVolume> makeVolume(bool dense, const Pose& T_world_cam) {
  if (dense) {
    DenseVolume::Params p;
    p.resolution_vox = 128;  // 2.56 m cube, centred 1.5 m ahead: holds the whole view
    p.voxel_size_m = kDenseVoxelM;
    p.lookahead_m = 1.5f;
    auto v = std::make_unique<DenseVolume>(p);
    v->followCamera(T_world_cam, 0.f);
    return v;
  }
  HashedVolume::Params p;
  p.voxel_size_m = kHashedVoxelM;
  return std::make_unique<HashedVolume>(p);
}

float truncationFor(bool dense) { return dense ? kDenseTruncationM : kHashedTruncationM; }

TsdfIntegrator integratorFor(bool dense) {
  TsdfIntegrator::Params params;
  params.truncation_m = truncationFor(dense);
  return TsdfIntegrator(params);
}

struct Stats {
  int hits = 0;
  std::vector<double> depth_err_m;
  std::vector<double> normal_err_deg;
  Eigen::Vector3f normal_sum = Eigen::Vector3f::Zero();
  double quantile(std::vector<double> v, double q) const {
    std::sort(v.begin(), v.end());
    return v[static_cast<size_t>(q * static_cast<double>(v.size() - 1))];
  }
  double mean(const std::vector<double>& v) const {
    double s = 0;
    for (double x : v) s += x;
    return s / static_cast<double>(v.size());
  }
};

// Voxels whose trilinear cell reaches outside the view frustum were observed on one side only,
// so the surface there is extrapolated. Two 2 cm voxels at 1.5 m span ~14 px.
constexpr int kBorderPx = 16;

// Compares a raycast (level 0 of `maps`) with the noise-free depth `truth`, away from the
// image border.
Stats compare(const ModelMaps& maps, const Image<float>& truth, const Eigen::Vector3f& n_cam) {
  Stats s;
  for (int y = kBorderPx; y < truth.height() - kBorderPx; ++y) {
    for (int x = kBorderPx; x < truth.width() - kBorderPx; ++x) {
      const Eigen::Vector3f& v = maps.vertex_ref[0](x, y);
      const Eigen::Vector3f& nm = maps.normal_ref[0](x, y);
      if (!isValid(v)) continue;
      ++s.hits;
      s.depth_err_m.push_back(std::abs(v.z() - truth(x, y)));
      s.normal_err_deg.push_back(test::angleDeg(nm, n_cam));
      s.normal_sum += nm;
    }
  }
  return s;
}

// True where the truth surface at (x, y) is smooth over 5x5 pixels and seen within 60 degrees
// of head-on.
bool awayFromEdges(const Image<float>& depth, const Image<Eigen::Vector3f>& vertex,
                   const Image<Eigen::Vector3f>& normal, int x, int y) {
  constexpr int kRadiusPx = 2;
  constexpr float kEdgeJumpM = 0.05f;
  constexpr float kMinCosIncidence = 0.5f;
  if (x < kRadiusPx || y < kRadiusPx || x + kRadiusPx >= depth.width() ||
      y + kRadiusPx >= depth.height())
    return false;
  for (int dy = -kRadiusPx; dy <= kRadiusPx; ++dy)
    for (int dx = -kRadiusPx; dx <= kRadiusPx; ++dx)
      if (!(std::abs(depth(x + dx, y + dy) - depth(x, y)) < kEdgeJumpM)) return false;
  return -normal(x, y).dot(vertex(x, y).normalized()) > kMinCosIncidence;
}

class IntegrateRaycast : public ::testing::TestWithParam<bool> {};  // param: dense volume

TEST_P(IntegrateRaycast, NoisyPlaneRaycastsAtPlaneDepth) {
  const bool dense = GetParam();
  const TiltedPlane plane;
  const SyntheticScene scene = plane.scene();
  const PinholeCamera cam = test::tumCamera();
  const Pose T_world_cam = Pose::Identity();
  auto volume = makeVolume(dense, T_world_cam);
  TsdfIntegrator integrator = integratorFor(dense);
  Image<uint16_t> raw(cam.width, cam.height);
  Image<float> depth(cam.width, cam.height);
  for (int frame = 0; frame < kNoisyFrames; ++frame) {
    test::renderNoisyMetres(scene, cam, T_world_cam, 500 + frame, raw, depth);
    const IntegrateResult r = integrator.integrate(depth, cam, T_world_cam, volume.get());
    EXPECT_GT(r.blocks_updated, 0);
    EXPECT_EQ(r.blocks_rejected, 0) << "the dense window holds the whole view";
  }
  Image<float> truth(cam.width, cam.height);
  scene.renderDepth(cam, T_world_cam, test::kRenderMaxDepthM, truth);

  Raycaster raycaster(cam, Raycaster::Params());
  ModelMaps maps(cam);
  const RaycastResult rr = raycaster.raycast(*volume, truncationFor(dense), T_world_cam, &maps);
  const Stats s = compare(maps, truth, plane.n);
  EXPECT_GE(rr.hits, s.hits);
  // Border pixels may lack an observed 8-voxel neighbourhood; everything else must hit.
  EXPECT_GT(rr.hit_fraction, 0.9f);
  ASSERT_GT(s.hits, 0);
  // Per-frame noise at 1.5 m is 3.5 mm; ten frames average it to 1.1 mm per voxel, and
  // trilinear interpolation averages further. Mean 1.5 mm and 99% within 5 mm (> 4 sigma of
  // the averaged noise) hold for a correct zero crossing, and fail for a half-voxel bias
  // (5 mm hashed, 10 mm dense) or a truncation scale error.
  constexpr double kMeanDepthTolM = 0.0015;
  constexpr double kP99DepthTolM = 0.005;
  EXPECT_LT(s.mean(s.depth_err_m), kMeanDepthTolM);
  EXPECT_LT(s.quantile(s.depth_err_m, 0.99), kP99DepthTolM);
  // Noise tilts individual gradients by a few degrees; their mean must be the plane normal.
  constexpr double kMeanNormalTolDeg = 1.0;
  EXPECT_LT(test::angleDeg(s.normal_sum, plane.n), kMeanNormalTolDeg);
}

TEST_P(IntegrateRaycast, ExactPlaneGivesExactSurfaceAndNormals) {
  const bool dense = GetParam();
  const TiltedPlane plane;
  const SyntheticScene scene = plane.scene();
  const PinholeCamera cam = test::tumCamera();
  // A camera moved off the origin, so the world-to-camera transforms are exercised.
  const Pose T_world_cam =
      test::makePose(Eigen::Vector3d(0.02, -0.03, 0.01), Eigen::Vector3d(0.05, -0.02, 0.1));
  auto volume = makeVolume(dense, T_world_cam);
  TsdfIntegrator integrator = integratorFor(dense);
  Image<float> depth(cam.width, cam.height);
  scene.renderDepth(cam, T_world_cam, test::kRenderMaxDepthM, depth);
  integrator.integrate(depth, cam, T_world_cam, volume.get());

  Raycaster raycaster(cam, Raycaster::Params());
  ModelMaps maps(cam);
  const RaycastResult rr = raycaster.raycast(*volume, truncationFor(dense), T_world_cam, &maps);
  EXPECT_GT(rr.hit_fraction, 0.9f);
  const Eigen::Vector3f n_cam = T_world_cam.linear().cast<float>().transpose() * plane.n;
  const Stats s = compare(maps, depth, n_cam);
  // Without noise the only error is nearest-pixel lookup during integration: half a pixel along
  // a 10-degree slope, ~0.25 mm at 1.5 m, which also tilts a 1-2 cm gradient by ~1 degree.
  constexpr double kP99DepthTolM = 0.001;
  constexpr double kP95NormalTolDeg = 2.0;
  constexpr double kMeanNormalTolDeg = 0.3;
  EXPECT_LT(s.quantile(s.depth_err_m, 0.99), kP99DepthTolM);
  EXPECT_LT(s.quantile(s.normal_err_deg, 0.95), kP95NormalTolDeg);
  EXPECT_LT(test::angleDeg(s.normal_sum, n_cam), kMeanNormalTolDeg);
  for (int i = 0; i < maps.normal_ref[0].numPixels(); ++i) {
    const Eigen::Vector3f& nm = maps.normal_ref[0].data()[i];
    if (isValid(nm)) {
      ASSERT_LT(nm.dot(maps.vertex_ref[0].data()[i]), 0.f) << "faces the camera";
    }
  }
}

// The tracking raycast (Newton from the measured depth, march only as a fallback) against the
// full march, on a scene with depth edges, seen from several poses so the fused field is an
// average of views, as in a real sequence.
TEST_P(IntegrateRaycast, HintedRaycastAgreesWithFullMarch) {
  const bool dense = GetParam();
  const SyntheticScene scene = SyntheticScene::cornerRoom();
  const PinholeCamera cam = test::tumCamera();
  const Pose T_world_cam = Pose::Identity();
  auto volume = makeVolume(dense, T_world_cam);
  TsdfIntegrator integrator = integratorFor(dense);
  Image<uint16_t> raw(cam.width, cam.height);
  Image<float> depth(cam.width, cam.height);
  for (int frame = 0; frame < kNoisyFrames; ++frame) {
    const Pose T = test::makePose(Eigen::Vector3d(0.0, 0.01 * frame, 0.0),
                                  Eigen::Vector3d(0.01 * frame, 0.0, 0.0));
    test::renderNoisyMetres(scene, cam, T, 700 + frame, raw, depth);
    integrator.integrate(depth, cam, T, volume.get());
  }
  // The hint: one more noisy frame from the raycast pose, with a hole in it.
  test::renderNoisyMetres(scene, cam, T_world_cam, 799, raw, depth);
  constexpr int kHoleLo = 200, kHoleHi = 260;
  for (int y = kHoleLo; y < kHoleHi; ++y)
    for (int x = kHoleLo; x < kHoleHi; ++x) depth(x, y) = 0.f;

  Raycaster raycaster(cam, Raycaster::Params());
  ModelMaps full(cam), hinted(cam);
  raycaster.raycast(*volume, truncationFor(dense), T_world_cam, &full);
  raycaster.raycast(*volume, truncationFor(dense), T_world_cam, &hinted, depth);

  // Ground truth: exact depth, and normals from it (exact on the planes, away from edges).
  Image<float> truth(cam.width, cam.height);
  scene.renderDepth(cam, T_world_cam, test::kRenderMaxDepthM, truth);
  Image<Eigen::Vector3f> truth_vertex(cam.width, cam.height), truth_normal(cam.width, cam.height);
  computeVertexMap(truth, cam, truth_vertex);
  computeNormalMap(truth_vertex, truth_normal);

  // A pixel the march finds within two voxels of the truth and the hinted raycast misses counts
  // against it, away from depth edges and grazing surfaces: there, whether a march notices a
  // crossing on nearest voxels depends on where its steps happen to land, so two marches
  // started at different depths legitimately disagree.
  const float voxel_m = dense ? kDenseVoxelM : kHashedVoxelM;
  int both = 0, full_only = 0;
  double full_depth_err = 0, hinted_depth_err = 0, full_normal_err = 0, hinted_normal_err = 0;
  for (int y = 0; y < cam.height; ++y)
    for (int x = 0; x < cam.width; ++x) {
      const Eigen::Vector3f& vh = hinted.vertex_ref[0](x, y);
      if (!(depth(x, y) > 0.f)) {
        ASSERT_FALSE(isValid(vh)) << "pixel without a measurement cast at " << x << "," << y;
        continue;
      }
      const Eigen::Vector3f& vf = full.vertex_ref[0](x, y);
      if (!isValid(vf) || !isValid(truth_normal(x, y))) continue;
      if (!isValid(vh)) {
        full_only += std::abs(vf.z() - truth(x, y)) < 2.f * voxel_m &&
                     awayFromEdges(truth, truth_vertex, truth_normal, x, y);
        continue;
      }
      ++both;
      full_depth_err += std::abs(vf.z() - truth(x, y));
      hinted_depth_err += std::abs(vh.z() - truth(x, y));
      full_normal_err += test::angleDeg(full.normal_ref[0](x, y), truth_normal(x, y));
      hinted_normal_err += test::angleDeg(hinted.normal_ref[0](x, y), truth_normal(x, y));
    }
  // The dense window (2.56 m) ends before the back wall; the hashed volume holds it all.
  const int min_compared = dense ? cam.width * cam.height / 5 : cam.width * cam.height / 2;
  ASSERT_GT(both, min_compared);
  // Newton converges on the same interpolant the march refines, so it must be as accurate
  // (mean error no more than a tenth of a millimetre or degree worse) and find nearly every
  // surface the march finds at a measured pixel: it leaves out only measurements whose cell
  // has an unobserved corner, on the edge of the observed field.
  constexpr double kDepthSlackM = 1e-4;
  constexpr double kNormalSlackDeg = 0.1;
  constexpr double kMaxMissed = 0.005;
  EXPECT_LT(hinted_depth_err / both, full_depth_err / both + kDepthSlackM);
  EXPECT_LT(hinted_normal_err / both, full_normal_err / both + kNormalSlackDeg);
  EXPECT_LT(static_cast<double>(full_only) / both, kMaxMissed);
}

INSTANTIATE_TEST_SUITE_P(Volumes, IntegrateRaycast, ::testing::Values(false, true),
                         [](const ::testing::TestParamInfo<bool>& param_info) {
                           return param_info.param ? "Dense" : "Hashed";
                         });

TEST(TsdfIntegrator, VoxelsHoldSignedDistanceOverTruncation) {
  // Wall at z = 1.5 m facing a camera at the origin; voxel centres sit on a 1 cm grid, so the
  // wall passes exactly through voxel layer gz = 150.
  SyntheticScene scene;
  scene.addPlane(Eigen::Vector3f(0.f, 0.f, -1.f), -1.5f);
  const PinholeCamera cam = test::tumCamera();
  Image<float> depth(cam.width, cam.height);
  scene.renderDepth(cam, Pose::Identity(), test::kRenderMaxDepthM, depth);
  HashedVolume volume(HashedVolume::Params{});
  TsdfIntegrator integrator = integratorFor(/*dense=*/false);
  integrator.integrate(depth, cam, Pose::Identity(), &volume);
  const float mu = kHashedTruncationM;
  for (int gx = -5; gx <= 5; ++gx) {
    for (int gy = -5; gy <= 5; ++gy) {
      for (int gz = 140; gz <= 160; ++gz) {
        const Voxel* v = test::voxelAt(volume, Eigen::Vector3i(gx, gy, gz));
        const Eigen::Vector3f p =
            Eigen::Vector3i(gx, gy, gz).cast<float>() * kHashedVoxelM;
        const float dist = 1.5f - p.z();  // signed distance to the wall, + in front
        if (dist < -mu - 1e-3f) {
          // Far behind the surface is unknown, not free.
          if (v != nullptr) {
            EXPECT_EQ(v->weight, 0.f) << gz;
          }
          continue;
        }
        if (std::abs(dist) > mu - 1e-3f) {
          // Outside the band (or on its edge), allocation is optional; free space reads +1.
          if (v != nullptr && v->weight > 0.f && dist > mu + 1e-3f) {
            EXPECT_EQ(v->tsdf, 1.f) << gz;
          }
          continue;
        }
        ASSERT_NE(v, nullptr) << "voxel in the band must be allocated: " << gz;
        EXPECT_EQ(v->weight, 1.f);
        // KinectFusion measures along the pixel ray, which is longer than the distance in z by
        // lambda = |K^-1 [u 1]| (< 1.0003 within 5 cm of the axis at 1.5 m).
        const float lambda = std::sqrt(1.f + (p.x() * p.x() + p.y() * p.y()) / (p.z() * p.z()));
        const float expected = std::clamp(dist * lambda / mu, -1.f, 1.f);
        // Float rounding of 1.5 - z is ~1e-7 m: 1e-5 in TSDF units leaves margin.
        EXPECT_NEAR(v->tsdf, expected, 1e-5f) << gx << "," << gy << "," << gz;
        EXPECT_NEAR(v->tsdf, std::clamp(dist / mu, -1.f, 1.f), 1e-3f);
      }
    }
  }
}

TEST(TsdfIntegrator, SerialAndParallelGiveIdenticalVoxels) {
  const SyntheticScene scene = SyntheticScene::cornerRoom();
  const PinholeCamera cam = test::tumCamera();
  HashedVolume serial(HashedVolume::Params{}), parallel(HashedVolume::Params{});
  TsdfIntegrator integrator_s{TsdfIntegrator::Params()}, integrator_p{TsdfIntegrator::Params()};
  Image<uint16_t> raw(cam.width, cam.height);
  Image<float> depth(cam.width, cam.height);
  for (int frame = 0; frame < 3; ++frame) {
    const Pose T = test::makePose(Eigen::Vector3d(0.0, 0.02 * frame, 0.0),
                                  Eigen::Vector3d(0.03 * frame, 0.0, 0.0));
    test::renderNoisyMetres(scene, cam, T, 40 + frame, raw, depth);
    integrator_s.integrate(depth, cam, T, &serial, false);
    integrator_p.integrate(depth, cam, T, &parallel, true);
  }
  ASSERT_EQ(serial.numAllocatedBlocks(), parallel.numAllocatedBlocks());
  ASSERT_GT(serial.numAllocatedBlocks(), 100u);
  for (const VoxelBlock* a : serial.allocatedBlocks()) {
    const VoxelBlock* b = parallel.findBlock(a->index);
    ASSERT_NE(b, nullptr);
    for (int i = 0; i < kBlockVoxels; ++i) {
      // Each voxel's update is independent of every other: exactly equal, not just close.
      ASSERT_EQ(a->voxels[i].tsdf, b->voxels[i].tsdf);
      ASSERT_EQ(a->voxels[i].weight, b->voxels[i].weight);
    }
  }
}

TEST(TsdfIntegrator, EachChangedVoxelIsTheRunningAverageOfItsPixelsDistance) {
  // The update four voxels at a time against the seed's per-voxel definition, computed here in
  // double: the voxel's pixel (nearest, of its projection), the distance along that pixel's
  // ray, then the truncated distance averaged in with weight one, the weight capped. A voxel
  // whose projection or distance lies within rounding of a decision (a pixel's edge, a hole's
  // border, the band's far edge) is left out of the check, not judged.
  const SyntheticScene scene = SyntheticScene::cornerRoom();
  const PinholeCamera cam = test::tumCamera();
  HashedVolume volume(HashedVolume::Params{});
  TsdfIntegrator::Params params;
  params.max_weight = 2.f;  // the third frame reaches the cap
  TsdfIntegrator integrator(params);
  const double mu = params.truncation_m;
  constexpr double kEdgePx = 1e-3;        // [px] projections this close to a pixel's edge
  constexpr double kEdgeM = 1e-4;         // [m] distances this close to -truncation
  constexpr double kMaxMissedBandShare = 1e-3;
  // The engine places voxels in float, stepping along block rows: up to 4 m off, a few of its
  // ulps (0.24 um there) against this double position.
  constexpr double kDistanceToleranceM = 4e-6;
  Image<uint16_t> raw(cam.width, cam.height);
  Image<float> depth(cam.width, cam.height);
  std::mt19937 holes(7);
  int checked = 0, updated = 0, band = 0, missed = 0;
  for (int frame = 0; frame < 3; ++frame) {
    const Pose T = test::makePose(Eigen::Vector3d(0.0, 0.03 * frame, 0.0),
                                  Eigen::Vector3d(0.02 * frame, 0.0, 0.01 * frame));
    test::renderNoisyMetres(scene, cam, T, 60 + frame, raw, depth);
    for (int y = 0; y < cam.height; ++y)
      for (int x = 0; x < cam.width; ++x)
        if (holes() % 10 == 0) depth(x, y) = 0.f;  // a tenth of the pixels without depth
    std::vector<VoxelBlock> before;
    for (const VoxelBlock* b : volume.allocatedBlocks()) before.push_back(*b);
    integrator.integrate(depth, cam, T, &volume);
    const Pose T_cam_world = T.inverse();
    for (const VoxelBlock* b : volume.allocatedBlocks()) {
      const auto old = std::find_if(before.begin(), before.end(),
                                    [&](const VoxelBlock& o) { return o.index == b->index; });
      for (int z = 0; z < kBlockSide; ++z)
        for (int y = 0; y < kBlockSide; ++y)
          for (int x = 0; x < kBlockSide; ++x) {
            const int i = VoxelBlock::linear(x, y, z);
            const Voxel was = old == before.end() ? Voxel() : old->voxels[i];
            const Voxel now = b->voxels[i];
            const bool changed = now.tsdf != was.tsdf || now.weight != was.weight;
            const Eigen::Vector3d p =
                T_cam_world * volume.voxelCentre(b->index, x, y, z).cast<double>();
            const double u = cam.fx * p.x() / p.z() + cam.cx, v = cam.fy * p.y() / p.z() + cam.cy;
            const double u_frac = u + 0.5 - std::floor(u + 0.5), v_frac = v + 0.5 - std::floor(v + 0.5);
            if (p.z() <= 0.0 || u_frac < kEdgePx || u_frac > 1.0 - kEdgePx ||
                v_frac < kEdgePx || v_frac > 1.0 - kEdgePx)
              continue;
            const int pu = static_cast<int>(std::floor(u + 0.5));
            const int pv = static_cast<int>(std::floor(v + 0.5));
            const bool in_image = pu >= 0 && pv >= 0 && pu < cam.width && pv < cam.height;
            const double d = in_image ? depth(pu, pv) : 0.0;
            const double lambda = std::sqrt(1.0 + (p.x() * p.x() + p.y() * p.y()) / (p.z() * p.z()));
            const double sdf = (d - p.z()) * lambda;
            if (d > 0.0 && std::abs(sdf + mu) < kEdgeM) continue;
            const bool measured = d > 0.0 && sdf >= -mu;
            ++checked;
            const bool in_band = measured && std::abs(sdf) < mu - kEdgeM;
            band += in_band;
            if (!changed) {
              // One in front of the band may lie in a block no band crosses.
              missed += in_band;
              continue;
            }
            ++updated;
            ASSERT_TRUE(measured) << "voxel updated without a measurement, frame " << frame;
            const double tsdf = std::min(1.0, sdf / mu);
            const double expected = (was.tsdf * static_cast<double>(was.weight) + tsdf) /
                                    (static_cast<double>(was.weight) + 1.0);
            EXPECT_NEAR(now.tsdf, expected, kDistanceToleranceM / mu) << "frame " << frame;
            EXPECT_EQ(now.weight, std::min(was.weight + 1.f, params.max_weight));
          }
    }
  }
  EXPECT_GT(updated, 100000) << "checked " << checked;
  // Blocks are listed from every second pixel's band (allocation_stride_px), sampled half a
  // block apart: a block that the bands only clip, or that only holes' rays cross, can be
  // missed, and its band voxels with it. Measured: 246 of the band's 1.6 million voxels here.
  EXPECT_LT(missed, kMaxMissedBandShare * band) << missed << " of " << band;
}

TEST(SampleTsdf, GradientOnSpherePointsOutward) {
  const Eigen::Vector3f c(0.05f, -0.03f, 1.5f);
  const float r = 0.3f;
  SyntheticScene scene;
  scene.addSphere(c, r);
  const PinholeCamera cam = test::tumCamera();
  HashedVolume volume(HashedVolume::Params{});
  TsdfIntegrator integrator{TsdfIntegrator::Params()};
  Image<float> depth(cam.width, cam.height);
  scene.renderDepth(cam, Pose::Identity(), test::kRenderMaxDepthM, depth);
  integrator.integrate(depth, cam, Pose::Identity(), &volume);

  // Points on the cap facing the camera (within 45 degrees of the direction to it). Nearer the
  // silhouette, projective distances along grazing rays are stretched by 1/cos and the field
  // stops being a distance field, as in every KinectFusion map.
  const Eigen::Vector3f to_camera = -c.normalized();
  std::mt19937 rng(77);
  std::normal_distribution<float> n01(0.f, 1.f);
  int sampled = 0, tried = 0;
  double angle_sum = 0.0;
  for (int i = 0; i < 5000; ++i) {
    Eigen::Vector3f dir(n01(rng), n01(rng), n01(rng));
    dir.normalize();
    if (dir.dot(to_camera) < std::cos(test::degToRad(45.0))) continue;
    ++tried;
    float tsdf;
    Eigen::Vector3f grad;
    if (!sampleTsdf(volume, c + r * dir, &tsdf, &grad)) continue;
    ++sampled;
    // On the surface the TSDF is ~0: 0.1 (4 mm) covers the projective stretch at 45 degrees
    // of a voxel's half-diagonal.
    EXPECT_LT(std::abs(tsdf), 0.1f);
    const double angle = test::angleDeg(grad, dir);
    // Along a ray the projective distance is the true distance over cos(incidence), which
    // varies slowly, so the gradient stays close to the normal; nearest-pixel lookup on 1 cm
    // voxels adds a few degrees. An inward or sideways gradient is off by 90-180 degrees.
    constexpr double kMaxAngleDeg = 15.0;
    EXPECT_LT(angle, kMaxAngleDeg) << dir.transpose();
    angle_sum += angle;
  }
  ASSERT_GT(tried, 100);
  EXPECT_GT(sampled, 0.95 * tried) << "points on the seen surface must be observed";
  EXPECT_LT(angle_sum / sampled, 5.0);  // typically ~2 degrees
  float tsdf;
  EXPECT_FALSE(sampleTsdf(volume, Eigen::Vector3f(10.f, 10.f, 10.f), &tsdf));
  EXPECT_FALSE(sampleTsdf(volume, c, &tsdf)) << "the sphere's inside was never observed";
}

}  // namespace
}  // namespace kinfly
