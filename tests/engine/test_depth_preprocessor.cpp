// DepthPreprocessor: conversion, bilateral filter, pyramid, vertex and normal maps, each checked
// against what the analytic scene says the answer must be, and the frame's fast loops against
// the per-pixel definitions.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "kinfly/preprocessing/depth_preprocessor.h"
#include "test_util.h"

namespace kinfly {
namespace {

// Float metres from integer units: one rounding of a product, < 1 ulp at 4 m (~0.5 um).
constexpr float kConversionTolM = 1e-6f;

DepthPreprocessor::Params defaultParams() { return DepthPreprocessor::Params(); }

// Calls f(vertex, normal, row) for each of the frame's packed points of one level.
template <typename F>
void forEachPoint(const PackedPoints& points, F f) {
  for (int y = 0; y < static_cast<int>(points.row_count.size()); ++y)
    for (int i = 0; i < points.row_count[y]; ++i)
      f(Eigen::Vector3f(points.vx(i, y), points.vy(i, y), points.vz(i, y)),
        Eigen::Vector3f(points.nx(i, y), points.ny(i, y), points.nz(i, y)), y);
}

// A level's maps by the per-pixel definitions, from the frame's depth at that level.
struct Maps {
  Image<Eigen::Vector3f> vertex, normal;
};
Maps definitionMaps(const DepthFrame& frame, int l) {
  const PinholeCamera& c = frame.camera[l];
  Maps maps{Image<Eigen::Vector3f>(c.width, c.height), Image<Eigen::Vector3f>(c.width, c.height)};
  computeVertexMap(frame.depth_m[l], c, maps.vertex);
  computeNormalMap(maps.vertex, maps.normal);
  return maps;
}

// The packed points are exactly the pixels of `maps` with a vertex and a normal, row by row in
// column order, bit for bit (a copy). Returns how many there are.
int expectPackedAreValidPixels(const PackedPoints& points, const Maps& maps, int level) {
  int total = 0;
  for (int y = 0; y < maps.vertex.height(); ++y) {
    int i = 0;
    for (int x = 0; x < maps.vertex.width(); ++x) {
      const Eigen::Vector3f& v = maps.vertex(x, y);
      const Eigen::Vector3f& n = maps.normal(x, y);
      if (!isValid(v) || !isValid(n)) continue;
      EXPECT_LT(i, points.row_count[y]) << "level " << level << " row " << y;
      if (i >= points.row_count[y]) return total;
      const bool same = points.vx(i, y) == v.x() && points.vy(i, y) == v.y() &&
                        points.vz(i, y) == v.z() && points.nx(i, y) == n.x() &&
                        points.ny(i, y) == n.y() && points.nz(i, y) == n.z();
      EXPECT_TRUE(same) << "level " << level << " pixel " << x << "," << y;
      if (!same) return total;
      ++i;
    }
    EXPECT_EQ(i, points.row_count[y]) << "level " << level << " row " << y;
    total += i;
  }
  return total;
}

TEST(DepthPreprocessor, ConvertsWithScaleAndClampsRange) {
  const PinholeCamera cam = test::tumCamera();
  DepthPreprocessor::Params params = defaultParams();
  params.depth_scale_m = 1.0 / 1000.0;  // OpenNI millimetres, to check the scale is used
  params.min_depth_m = 0.5f;
  params.max_depth_m = 3.0f;
  DepthPreprocessor pre(cam, params);
  Image<uint16_t> raw(cam.width, cam.height, 0);
  // Columns cycle through: no reading, too near, valid, valid, too far.
  const uint16_t values[5] = {0, 400, 1234, 2999, 3500};
  int expected_valid = 0;
  for (int y = 0; y < cam.height; ++y) {
    for (int x = 0; x < cam.width; ++x) {
      raw(x, y) = values[x % 5];
      expected_valid += (x % 5 == 2 || x % 5 == 3);
    }
  }
  DepthFrame frame(pre.camera());
  const PreprocessResult result = pre.process(raw, &frame);
  EXPECT_EQ(result.valid_pixels, expected_valid);
  EXPECT_NEAR(result.valid_fraction, 0.4f, 1e-6f);
  for (int y = 0; y < cam.height; y += 3) {
    for (int x = 0; x < cam.width; ++x) {
      const float d = frame.raw_depth_m(x, y);
      switch (x % 5) {
        case 2: EXPECT_NEAR(d, 1.234f, kConversionTolM); break;
        case 3: EXPECT_NEAR(d, 2.999f, kConversionTolM); break;
        default: EXPECT_EQ(d, 0.f) << "x=" << x; break;
      }
    }
  }
}

TEST(DepthPreprocessor, AllZeroFrameHasNoValidPixels) {
  const PinholeCamera cam = test::tumCamera();
  DepthPreprocessor pre(cam, defaultParams());
  Image<uint16_t> raw(cam.width, cam.height, 0);
  DepthFrame frame(pre.camera());
  const PreprocessResult result = pre.process(raw, &frame);
  EXPECT_EQ(result.valid_pixels, 0);
  EXPECT_EQ(result.valid_fraction, 0.f);
  for (int l = 0; l < kPyramidLevels; ++l) {
    for (int i = 0; i < frame.depth_m[l].numPixels(); ++i) {
      ASSERT_EQ(frame.depth_m[l].data()[i], 0.f);
    }
    for (const int count : frame.points[l].row_count) ASSERT_EQ(count, 0);
  }
}

// A noisy tilted plane with a rectangular hole and a ragged invalid border.
struct HoleyPlane {
  Image<uint16_t> raw;
  Image<float> truth_m;  // noise-free depth
};

HoleyPlane makeHoleyPlane(const PinholeCamera& cam, uint32_t seed) {
  SyntheticScene scene;
  const Eigen::Vector3f n = Eigen::Vector3f(0.2f, -0.1f, -1.f).normalized();
  scene.addPlane(n, n.dot(Eigen::Vector3f(0.f, 0.f, 1.5f)));
  HoleyPlane p{Image<uint16_t>(cam.width, cam.height), Image<float>(cam.width, cam.height)};
  std::mt19937 rng(seed);
  scene.renderRawDepth(cam, Pose::Identity(), test::kRenderMaxDepthM, test::kTumDepthScale, &rng,
                       p.raw);
  scene.renderDepth(cam, Pose::Identity(), test::kRenderMaxDepthM, p.truth_m);
  for (int y = 200; y < 260; ++y) {
    for (int x = 300; x < 380; ++x) p.raw(x, y) = 0;
  }
  for (int y = 0; y < cam.height; ++y) {
    for (int x = 0; x < cam.width; ++x) {
      if ((x * 7 + y * 13) % 23 == 0) p.raw(x, y) = 0;  // scattered dropouts
    }
  }
  return p;
}

TEST(DepthPreprocessor, BilateralNeverMixesValidAndInvalid) {
  const PinholeCamera cam = test::tumCamera();
  DepthPreprocessor pre(cam, defaultParams());
  const HoleyPlane plane = makeHoleyPlane(cam, 11);
  DepthFrame frame(pre.camera());
  pre.process(plane.raw, &frame);
  const int r = pre.params().bilateral_radius_px;
  for (int y = 0; y < cam.height; ++y) {
    for (int x = 0; x < cam.width; ++x) {
      const float in = frame.raw_depth_m(x, y);
      const float out = frame.depth_m[0](x, y);
      if (in == 0.f) {
        ASSERT_EQ(out, 0.f) << "invalid pixel became valid at " << x << "," << y;
        continue;
      }
      // A weighted mean of valid neighbours lies within their range; a single zero tap pulled
      // in would drag it far below the minimum.
      float lo = in, hi = in;
      for (int qy = std::max(0, y - r); qy <= std::min(cam.height - 1, y + r); ++qy) {
        for (int qx = std::max(0, x - r); qx <= std::min(cam.width - 1, x + r); ++qx) {
          const float q = frame.raw_depth_m(qx, qy);
          if (q > 0.f) {
            lo = std::min(lo, q);
            hi = std::max(hi, q);
          }
        }
      }
      ASSERT_GE(out, lo - 1e-6f) << x << "," << y;
      ASSERT_LE(out, hi + 1e-6f) << x << "," << y;
    }
  }
}

TEST(DepthPreprocessor, BilateralReducesNoiseOnPlane) {
  const PinholeCamera cam = test::tumCamera();
  DepthPreprocessor pre(cam, defaultParams());
  const HoleyPlane plane = makeHoleyPlane(cam, 12);
  DepthFrame frame(pre.camera());
  pre.process(plane.raw, &frame);
  double raw_sq = 0, filtered_sq = 0;
  int n = 0;
  for (int y = 0; y < cam.height; ++y) {
    for (int x = 0; x < cam.width; ++x) {
      if (frame.raw_depth_m(x, y) == 0.f) continue;
      const double truth = plane.truth_m(x, y);
      raw_sq += std::pow(frame.raw_depth_m(x, y) - truth, 2);
      filtered_sq += std::pow(frame.depth_m[0](x, y) - truth, 2);
      ++n;
    }
  }
  const double raw_rms = std::sqrt(raw_sq / n);
  const double filtered_rms = std::sqrt(filtered_sq / n);
  // sigma_range (30 mm) is ~9x the noise at 1.5 m (3.5 mm), so the filter acts as a Gaussian
  // of sigma 1.5 px over radius 2: that averages ~10 effective pixels, an RMS ratio of ~0.35.
  // 0.6 leaves room for the plane's slope and the holes, and still fails for a no-op filter.
  constexpr double kMaxNoiseRatio = 0.6;
  EXPECT_LT(filtered_rms, kMaxNoiseRatio * raw_rms)
      << "raw " << raw_rms * 1e3 << " mm, filtered " << filtered_rms * 1e3 << " mm";
}

TEST(DepthPreprocessor, PyramidSizesAndCameras) {
  const PinholeCamera cam = test::tumCamera();
  DepthPreprocessor pre(cam, defaultParams());
  DepthFrame frame(pre.camera());
  for (int l = 0; l < kPyramidLevels; ++l) {
    const PinholeCamera expected = cam.scaled(1 << l);
    EXPECT_EQ(frame.camera[l].width, cam.width >> l);
    EXPECT_EQ(frame.camera[l].height, cam.height >> l);
    EXPECT_EQ(frame.camera[l].fx, expected.fx);
    EXPECT_EQ(frame.camera[l].fy, expected.fy);
    EXPECT_EQ(frame.camera[l].cx, expected.cx);
    EXPECT_EQ(frame.camera[l].cy, expected.cy);
    EXPECT_EQ(frame.depth_m[l].width(), cam.width >> l);
    EXPECT_EQ(frame.depth_m[l].height(), cam.height >> l);
    EXPECT_GE(frame.points[l].vx.width(), cam.width >> l);
    EXPECT_EQ(frame.points[l].row_count.size(), static_cast<size_t>(cam.height >> l));
  }
}

TEST(DepthPreprocessor, PyramidDoesNotMixAcrossDiscontinuity) {
  const PinholeCamera cam = test::tumCamera();
  DepthPreprocessor pre(cam, defaultParams());
  // Left of an odd column at 1 m, right at 2 m, with noise, so every 2x2 and 5x5 window along
  // the edge straddles it.
  Image<uint16_t> raw(cam.width, cam.height);
  std::mt19937 rng(21);
  std::normal_distribution<float> n01(0.f, 1.f);
  for (int y = 0; y < cam.height; ++y) {
    for (int x = 0; x < cam.width; ++x) {
      const float z = x < 321 ? 1.f : 2.f;
      raw(x, y) = static_cast<uint16_t>(
          std::lround((z + kinectNoiseSigmaM(z) * n01(rng)) / test::kTumDepthScale));
    }
  }
  DepthFrame frame(pre.camera());
  pre.process(raw, &frame);
  for (int l = 0; l < kPyramidLevels; ++l) {
    int near = 0, far = 0;
    for (int i = 0; i < frame.depth_m[l].numPixels(); ++i) {
      const float d = frame.depth_m[l].data()[i];
      ASSERT_FALSE(d > 1.1f && d < 1.9f) << "level " << l << " mixed the two planes: " << d;
      near += d > 0.f && d <= 1.1f;
      far += d >= 1.9f;
    }
    EXPECT_GT(near, 0);
    EXPECT_GT(far, 0);
  }
}

TEST(DepthPreprocessor, VertexMapIsBackProjection) {
  const PinholeCamera cam = test::tumCamera();
  DepthPreprocessor pre(cam, defaultParams());
  const HoleyPlane plane = makeHoleyPlane(cam, 13);
  DepthFrame frame(pre.camera());
  pre.process(plane.raw, &frame);
  for (int l = 0; l < kPyramidLevels; ++l) {
    const PinholeCamera& c = frame.camera[l];
    const Maps maps = definitionMaps(frame, l);
    for (int y = 0; y < c.height; ++y) {
      for (int x = 0; x < c.width; ++x) {
        const float d = frame.depth_m[l](x, y);
        const Eigen::Vector3f& v = maps.vertex(x, y);
        if (d == 0.f) {
          ASSERT_FALSE(isValid(v));
          continue;
        }
        const Eigen::Vector3f expected =
            c.backProject(static_cast<float>(x), static_cast<float>(y), d);
        ASSERT_LT((v - expected).norm(), 1e-6f) << "level " << l;  // same float formula
      }
    }
  }
}

// Normals of a plane, from the noise-free but quantised (0.2 mm) TUM-like image.
TEST(DepthPreprocessor, NormalMapOfPlaneIsPlaneNormal) {
  const PinholeCamera cam = test::tumCamera();
  DepthPreprocessor pre(cam, defaultParams());
  SyntheticScene scene;
  // Free side of the plane faces the camera, so n is the normal the map must report.
  const Eigen::Vector3f n = Eigen::Vector3f(0.3f, -0.2f, -1.f).normalized();
  scene.addPlane(n, n.dot(Eigen::Vector3f(0.f, 0.f, 1.5f)));
  Image<float> depth(cam.width, cam.height);
  scene.renderDepth(cam, Pose::Identity(), test::kRenderMaxDepthM, depth);
  Image<uint16_t> raw(cam.width, cam.height);
  test::metresToRaw(depth, raw);
  DepthFrame frame(pre.camera());
  pre.process(raw, &frame);
  // Quantisation staircases the plane in 0.2 mm steps over ~2.8 mm pixels; the bilateral filter
  // smooths them to a slope error of about a degree. 3 degrees for 95% of pixels, and 0.5
  // degrees for the mean normal (the staircase averages out), catch any sign or axis error.
  constexpr double kPixelAngleTolDeg = 3.0;
  constexpr double kMinFractionWithin = 0.95;
  constexpr double kMeanAngleTolDeg = 0.5;
  for (int l = 0; l < kPyramidLevels; ++l) {
    int valid = 0, within = 0;
    Eigen::Vector3f sum = Eigen::Vector3f::Zero();
    forEachPoint(frame.points[l], [&](const Eigen::Vector3f& v, const Eigen::Vector3f& nm, int) {
      ++valid;
      EXPECT_NEAR(nm.norm(), 1.f, 1e-5f);
      EXPECT_LT(nm.dot(v), 0.f) << "normal must face the camera";
      within += test::angleDeg(nm, n) < kPixelAngleTolDeg;
      sum += nm;
    });
    ASSERT_GT(valid, frame.camera[l].width * frame.camera[l].height / 2);
    EXPECT_GT(static_cast<double>(within) / valid, kMinFractionWithin) << "level " << l;
    EXPECT_LT(test::angleDeg(sum, n), kMeanAngleTolDeg) << "level " << l;
  }
}

TEST(DepthPreprocessor, ComputeNormalMapOfExactPlane) {
  // The kernel itself on exact vertices: only float rounding remains.
  const PinholeCamera cam = test::tumCamera();
  SyntheticScene scene;
  const Eigen::Vector3f n = Eigen::Vector3f(-0.4f, 0.3f, -1.f).normalized();
  scene.addPlane(n, n.dot(Eigen::Vector3f(0.f, 0.f, 2.f)));
  Image<float> depth(cam.width, cam.height);
  scene.renderDepth(cam, Pose::Identity(), test::kRenderMaxDepthM, depth);
  Image<Eigen::Vector3f> vertex(cam.width, cam.height), normal(cam.width, cam.height);
  computeVertexMap(depth, cam, vertex);
  computeNormalMap(vertex, normal);
  constexpr double kExactAngleTolDeg = 0.1;  // float differences of ~2 m points 4 mm apart
  for (int y = 0; y + 1 < cam.height; y += 3) {
    for (int x = 0; x + 1 < cam.width; x += 3) {
      ASSERT_TRUE(isValid(normal(x, y)));
      ASSERT_LT(test::angleDeg(normal(x, y), n), kExactAngleTolDeg) << x << "," << y;
    }
  }
}

TEST(DepthPreprocessor, PackedPointsAreTheValidPixelsInRowOrder) {
  const PinholeCamera cam = test::tumCamera();
  DepthPreprocessor pre(cam, defaultParams());
  const HoleyPlane plane = makeHoleyPlane(cam, 14);
  DepthFrame frame(pre.camera());
  pre.process(plane.raw, &frame);
  for (int l = 0; l < kPyramidLevels; ++l) {
    const int total = expectPackedAreValidPixels(frame.points[l], definitionMaps(frame, l), l);
    EXPECT_GT(total, frame.camera[l].width * frame.camera[l].height / 2) << "level " << l;
  }
}

TEST(DepthPreprocessor, FrameMatchesPerPixelDefinitionsBitForBit) {
  // Radii change the filter's tiles and kept rows; an image width that is not a multiple of four
  // (634, 317, 158 along the pyramid) leaves partial groups for the four-pixel loops; a range
  // sigma of 1 m puts invalid (0) neighbours inside the range table, where only the validity
  // test keeps them out.
  PinholeCamera odd = test::tumCamera();
  odd.width = 634;
  odd.height = 474;
  struct Case {
    PinholeCamera camera;
    int downsample;
  };
  for (const Case& input : {Case{test::tumCamera(), 1}, Case{test::tumCamera(), 4}, Case{odd, 1}}) {
    const HoleyPlane plane = makeHoleyPlane(input.camera, 15);
    for (const int radius : {1, 2, 3, BilateralKernel::kMaxRadius}) {
      DepthPreprocessor::Params params = defaultParams();
      params.bilateral_radius_px = radius;
      params.downsample = input.downsample;
      if (radius == 3) params.bilateral_sigma_range_m = 1.f;
      DepthPreprocessor pre(input.camera, params);
      DepthFrame frame(pre.camera());
      pre.process(plane.raw, &frame);
      const BilateralKernel kernel(radius, params.bilateral_sigma_space_px,
                                   params.bilateral_sigma_range_m);
      const float max_diff_m = params.pyramid_range_sigmas * params.bilateral_sigma_range_m;
      for (int l = 0; l < kPyramidLevels; ++l) {
        const PinholeCamera& c = frame.camera[l];
        for (int y = 0; y < c.height; ++y) {
          for (int x = 0; x < c.width; ++x) {
            const float expected = l == 0 ? bilateralPixel(frame.raw_depth_m, x, y, kernel)
                                          : pyrDownPixel(frame.depth_m[l - 1], x, y, max_diff_m);
            ASSERT_EQ(frame.depth_m[l](x, y), expected)
                << "radius " << radius << " width " << c.width << " level " << l << " "
                << x << "," << y;
          }
        }
        expectPackedAreValidPixels(frame.points[l], definitionMaps(frame, l), l);
        ASSERT_FALSE(HasFailure()) << "radius " << radius << " width " << c.width;
      }
    }
  }
}

TEST(DepthPreprocessor, DownsampleTwoGivesQvgaWithScaledIntrinsics) {
  const PinholeCamera cam = test::tumCamera();
  DepthPreprocessor::Params params = defaultParams();
  params.downsample = 2;
  DepthPreprocessor pre(cam, params);
  EXPECT_EQ(pre.camera().width, 320);
  EXPECT_EQ(pre.camera().height, 240);
  EXPECT_FLOAT_EQ(pre.camera().fx, cam.fx / 2);
  EXPECT_FLOAT_EQ(pre.camera().fy, cam.fy / 2);
  const PinholeCamera expected = cam.scaled(2);
  EXPECT_EQ(pre.camera().cx, expected.cx);
  EXPECT_EQ(pre.camera().cy, expected.cy);

  // A tilted plane seen through the downsampled camera: vertices must still lie on it, which
  // only holds if the intrinsics match the pixels that were kept.
  SyntheticScene scene;
  const Eigen::Vector3f n = Eigen::Vector3f(0.5f, 0.f, -1.f).normalized();
  const float offset = n.dot(Eigen::Vector3f(0.f, 0.f, 1.5f));
  scene.addPlane(n, offset);
  Image<float> depth(cam.width, cam.height);
  scene.renderDepth(cam, Pose::Identity(), test::kRenderMaxDepthM, depth);
  Image<uint16_t> raw(cam.width, cam.height);
  test::metresToRaw(depth, raw);
  DepthFrame frame(pre.camera());
  EXPECT_EQ(frame.raw_depth_m.width(), 320);
  pre.process(raw, &frame);
  // Quantisation (0.1 mm max) plus bilateral smoothing of a linear ramp: well under 1 mm; a
  // principal point off by half a (level-1) pixel puts points ~1.3 mm off this slope at 1.5 m.
  constexpr float kOnPlaneTolM = 1e-3f;
  for (int l = 0; l < kPyramidLevels; ++l) {
    EXPECT_EQ(frame.camera[l].width, 320 >> l);
    // The vertices the frame's points are made of (the bit-for-bit test above ties them).
    const Maps maps = definitionMaps(frame, l);
    for (int y = 4; y < frame.camera[l].height - 4; y += 2) {
      for (int x = 4; x < frame.camera[l].width - 4; x += 2) {
        const Eigen::Vector3f& v = maps.vertex(x, y);
        ASSERT_TRUE(isValid(v));
        ASSERT_NEAR(n.dot(v), offset, kOnPlaneTolM) << "level " << l << " " << x << "," << y;
      }
    }
  }
}

}  // namespace
}  // namespace kinfly
