// SyntheticScene against closed-form geometry: every rendered depth back-projects onto the
// surface it claims to hit, nearer surfaces win, and the noise matches the Kinect model.
#include <gtest/gtest.h>

#include <cmath>

#include "kinfly/synthetic/synthetic_scene.h"
#include "test_util.h"

namespace kinfly {
namespace {

// Single-precision ray casting at a few metres: t is exact to a few float ulps of ~3 m.
constexpr float kGeometryTolM = 1e-5f;

TEST(SyntheticScene, FrontoParallelPlaneHasConstantDepth) {
  SyntheticScene scene;
  scene.addPlane(Eigen::Vector3f(0.f, 0.f, -1.f), -2.f);  // z = 2, facing the camera
  const PinholeCamera cam = test::tumCamera();
  Image<float> depth(cam.width, cam.height);
  scene.renderDepth(cam, Pose::Identity(), test::kRenderMaxDepthM, depth);
  for (int v = 0; v < cam.height; v += 7) {
    for (int u = 0; u < cam.width; u += 7) EXPECT_NEAR(depth(u, v), 2.f, kGeometryTolM);
  }
}

TEST(SyntheticScene, TiltedPlaneFromMovedCameraLiesOnPlane) {
  const Eigen::Vector3f n = Eigen::Vector3f(0.3f, -0.2f, -1.f).normalized();
  const float offset = n.dot(Eigen::Vector3f(0.5f, 0.1f, 2.5f));
  SyntheticScene scene;
  scene.addPlane(n, offset);
  const PinholeCamera cam = test::tumCamera();
  const Pose T_world_cam =
      test::makePose(Eigen::Vector3d(0.05, -0.1, 0.02), Eigen::Vector3d(0.2, -0.1, 0.3));
  Image<float> depth(cam.width, cam.height);
  scene.renderDepth(cam, T_world_cam, test::kRenderMaxDepthM, depth);
  const Eigen::Isometry3f T = T_world_cam.cast<float>();
  for (int v = 0; v < cam.height; v += 5) {
    for (int u = 0; u < cam.width; u += 5) {
      ASSERT_GT(depth(u, v), 0.f);
      const Eigen::Vector3f p_world = T * cam.backProject(static_cast<float>(u),
                                                          static_cast<float>(v), depth(u, v));
      EXPECT_NEAR(n.dot(p_world), offset, kGeometryTolM);
    }
  }
}

TEST(SyntheticScene, SphereDepthLiesOnSphereAndMissesGiveZero) {
  const Eigen::Vector3f c(0.1f, -0.05f, 1.5f);
  const float r = 0.25f;
  SyntheticScene scene;
  scene.addSphere(c, r);
  const PinholeCamera cam = test::tumCamera();
  Image<float> depth(cam.width, cam.height);
  scene.renderDepth(cam, Pose::Identity(), test::kRenderMaxDepthM, depth);
  int hits = 0;
  for (int v = 0; v < cam.height; ++v) {
    for (int u = 0; u < cam.width; ++u) {
      const Eigen::Vector3f ray((static_cast<float>(u) - cam.cx) / cam.fx,
                                (static_cast<float>(v) - cam.cy) / cam.fy, 1.f);
      // Distance from the sphere centre to the ray line decides hit or miss analytically.
      const float dist_to_line = ray.normalized().cross(c).norm();
      if (depth(u, v) == 0.f) {
        EXPECT_GT(dist_to_line, r - 1e-4f) << u << "," << v;
        continue;
      }
      ++hits;
      EXPECT_LT(dist_to_line, r + 1e-4f);
      const Eigen::Vector3f p = cam.backProject(static_cast<float>(u), static_cast<float>(v),
                                                depth(u, v));
      EXPECT_NEAR((p - c).norm(), r, kGeometryTolM);
      EXPECT_LT((p - c).dot(p), 0.f) << "must be the near side of the sphere";
    }
  }
  EXPECT_GT(hits, 1000);
  const Eigen::Vector2f centre_px = cam.project(c);
  EXPECT_NEAR(depth(static_cast<int>(std::lround(centre_px.x())),
                    static_cast<int>(std::lround(centre_px.y()))),
              c.z() - r, 2e-3f);  // nearest pixel is within ~1 mm of the sphere's pole
}

TEST(SyntheticScene, BoxFrontFaceAndSlabs) {
  const Eigen::Vector3f centre(0.f, 0.f, 2.f);
  const Eigen::Vector3f half(0.3f, 0.2f, 0.1f);
  SyntheticScene scene;
  scene.addBox(centre, half);
  const PinholeCamera cam = test::tumCamera();
  // Slightly off-axis so side faces are seen as well as the front.
  const Pose T_world_cam =
      test::makePose(Eigen::Vector3d(0.0, 0.25, 0.0), Eigen::Vector3d(-0.4, -0.15, 0.0));
  Image<float> depth(cam.width, cam.height);
  scene.renderDepth(cam, T_world_cam, test::kRenderMaxDepthM, depth);
  const Eigen::Isometry3f T = T_world_cam.cast<float>();
  int hits = 0;
  int side_hits = 0;
  for (int v = 0; v < cam.height; v += 2) {
    for (int u = 0; u < cam.width; u += 2) {
      if (depth(u, v) == 0.f) continue;
      ++hits;
      const Eigen::Vector3f p =
          T * cam.backProject(static_cast<float>(u), static_cast<float>(v), depth(u, v));
      // On the surface of an axis-aligned box the largest normalised coordinate is exactly 1.
      const Eigen::Vector3f q = (p - centre).cwiseAbs().cwiseQuotient(half);
      EXPECT_NEAR(q.maxCoeff(), 1.f, 1e-4f);
      if (std::abs(q.x() - 1.f) < 1e-4f) ++side_hits;
    }
  }
  EXPECT_GT(hits, 1000);
  EXPECT_GT(side_hits, 50) << "the camera at x = -0.4 m looking right must see the -x face";
}

TEST(SyntheticScene, NearestSurfaceWinsAndMaxDepthCuts) {
  SyntheticScene scene;
  scene.addPlane(Eigen::Vector3f(0.f, 0.f, -1.f), -3.f);  // wall z = 3
  scene.addSphere(Eigen::Vector3f(0.f, 0.f, 2.f), 0.3f);
  scene.addBox(Eigen::Vector3f(0.f, 0.f, 1.f), Eigen::Vector3f(0.05f, 0.05f, 0.05f));
  const PinholeCamera cam = test::tumCamera();
  Image<float> depth(cam.width, cam.height);
  scene.renderDepth(cam, Pose::Identity(), test::kRenderMaxDepthM, depth);
  const int u = static_cast<int>(std::lround(cam.cx));
  const int v = static_cast<int>(std::lround(cam.cy));
  EXPECT_NEAR(depth(u, v), 0.95f, 1e-4f);  // box front face, in front of sphere and wall
  {
    // Sphere, solved in double: |t r - c|^2 = R^2 with c = (0, 0, 2), R = 0.3, r.z = 1.
    const double rx = (u + 60 - static_cast<double>(cam.cx)) / cam.fx;
    const double ry = (v - static_cast<double>(cam.cy)) / cam.fy;
    const double a = rx * rx + ry * ry + 1.0;
    const double t = (2.0 - std::sqrt(4.0 - a * (4.0 - 0.09))) / a;
    EXPECT_NEAR(depth(u + 60, v), t, kGeometryTolM);
  }
  EXPECT_NEAR(depth(5, 5), 3.f, kGeometryTolM);  // wall in the corner

  scene.renderDepth(cam, Pose::Identity(), 2.5f, depth);
  EXPECT_EQ(depth(5, 5), 0.f);  // the wall lies beyond max depth
  EXPECT_GT(depth(u, v), 0.f);
  EXPECT_TRUE(std::isinf(scene.intersect(Eigen::Vector3f::Zero(), Eigen::Vector3f(0, 0, -1))));
}

// The noise test uses a fronto-parallel wall, where the true depth is the same at every pixel,
// so the whole image is one sample of N(z, sigma(z)) plus quantisation.
class SyntheticNoise : public ::testing::TestWithParam<float> {};

TEST_P(SyntheticNoise, StdMatchesKinectModel) {
  const float z = GetParam();
  SyntheticScene scene;
  scene.addPlane(Eigen::Vector3f(0.f, 0.f, -1.f), -z);
  const PinholeCamera cam = test::tumCamera();
  Image<uint16_t> raw(cam.width, cam.height);
  std::mt19937 rng(1234);
  scene.renderRawDepth(cam, Pose::Identity(), test::kRenderMaxDepthM, test::kTumDepthScale, &rng,
                       raw);
  double sum = 0, sum_sq = 0;
  const int n = raw.numPixels();
  for (int i = 0; i < n; ++i) {
    ASSERT_GT(raw.data()[i], 0);
    const double e = raw.data()[i] * test::kTumDepthScale - z;
    sum += e;
    sum_sq += e * e;
  }
  const double mean = sum / n;
  const double std_m = std::sqrt(sum_sq / n - mean * mean);
  const double sigma = kinectNoiseSigmaM(z);
  // The sample std of 307200 Gaussian draws has a relative standard error of 1/sqrt(2N) = 0.13%;
  // 0.2 mm quantisation adds (0.058 mm)^2 of variance, < 0.05% of sigma^2 at 1 m. 2% is > 10
  // standard errors, yet a wrong model (e.g. linear in z, or sigma at a different range) is off
  // by far more.
  constexpr double kRelStdTol = 0.02;
  EXPECT_NEAR(std_m / sigma, 1.0, kRelStdTol) << "z = " << z;
  // The mean's standard error is sigma/sqrt(N) < 0.02 mm here; 5 standard errors.
  EXPECT_NEAR(mean, 0.0, 5.0 * sigma / std::sqrt(static_cast<double>(n)) + 1e-5);
}

INSTANTIATE_TEST_SUITE_P(Ranges, SyntheticNoise, ::testing::Values(1.0f, 2.0f, 3.5f));

TEST(SyntheticScene, RawDepthIsDeterministicAndZeroWithoutHit) {
  SyntheticScene scene;
  scene.addSphere(Eigen::Vector3f(0.f, 0.f, 2.f), 0.4f);
  const PinholeCamera cam = test::tumCamera();
  Image<uint16_t> a(cam.width, cam.height), b(cam.width, cam.height), c(cam.width, cam.height);
  std::mt19937 rng_a(7), rng_b(7), rng_c(8);
  scene.renderRawDepth(cam, Pose::Identity(), 5.f, test::kTumDepthScale, &rng_a, a);
  scene.renderRawDepth(cam, Pose::Identity(), 5.f, test::kTumDepthScale, &rng_b, b);
  scene.renderRawDepth(cam, Pose::Identity(), 5.f, test::kTumDepthScale, &rng_c, c);
  int differing = 0;
  for (int i = 0; i < a.numPixels(); ++i) {
    ASSERT_EQ(a.data()[i], b.data()[i]);
    differing += a.data()[i] != c.data()[i];
  }
  EXPECT_GT(differing, 1000) << "a different seed must give different noise";
  EXPECT_EQ(a(0, 0), 0);  // the corner ray misses the sphere
  const int u = static_cast<int>(std::lround(cam.cx));
  const int v = static_cast<int>(std::lround(cam.cy));
  // 1.6 m +- 5 sigma (sigma = 3.9 mm): a draw beyond is a 1-in-3-million event.
  EXPECT_NEAR(a(u, v) * test::kTumDepthScale, 1.6, 5 * kinectNoiseSigmaM(1.6f));
}

}  // namespace
}  // namespace kinfly
