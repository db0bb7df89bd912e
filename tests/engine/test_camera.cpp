// PinholeCamera (core/camera.h): projection and back-projection are inverses, downsampled
// intrinsics follow the pyramid's pixel convention, and validation and --intrinsics parsing
// reject what they should, naming the field.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <random>
#include <string>

#include "kinfly/core/camera.h"
#include "test_util.h"

namespace kinfly {
namespace {

// Float arithmetic on pixel coordinates up to 640 and depths up to 5 m: ~1e-4 px and ~1e-6 m
// after a divide and a multiply-add. A wrong principal point or focal length is off by pixels.
constexpr float kPixelTol = 1e-3f;
constexpr float kMetreTol = 1e-5f;
constexpr uint32_t kSeed = 4242;

TEST(Camera, BackProjectThenProjectIsIdentity) {
  const PinholeCamera cam = test::tumCamera();
  std::mt19937 rng(kSeed);
  std::uniform_real_distribution<float> u(0.f, static_cast<float>(cam.width - 1));
  std::uniform_real_distribution<float> v(0.f, static_cast<float>(cam.height - 1));
  std::uniform_real_distribution<float> depth(0.3f, 5.f);
  for (int i = 0; i < 1000; ++i) {
    const float u_px = u(rng), v_px = v(rng), d_m = depth(rng);
    const Eigen::Vector3f p = cam.backProject(u_px, v_px, d_m);
    EXPECT_FLOAT_EQ(p.z(), d_m) << "depth is the z coordinate, not the range";
    const Eigen::Vector2f uv = cam.project(p);
    EXPECT_NEAR(uv.x(), u_px, kPixelTol);
    EXPECT_NEAR(uv.y(), v_px, kPixelTol);
    // And the other way round from the point.
    EXPECT_LT((cam.backProject(uv.x(), uv.y(), p.z()) - p).norm(), kMetreTol);
  }
}

TEST(Camera, OpticalAxisAndFrameConvention) {
  const PinholeCamera cam = test::tumCamera();
  // The optical axis meets the image at the principal point.
  const Eigen::Vector2f centre = cam.project(Eigen::Vector3f(0.f, 0.f, 2.f));
  EXPECT_FLOAT_EQ(centre.x(), cam.cx);
  EXPECT_FLOAT_EQ(centre.y(), cam.cy);
  // x right, y down: a point right of and below the axis lands right of and below the centre,
  // one focal length per unit of x/z.
  const Eigen::Vector2f uv = cam.project(Eigen::Vector3f(0.5f, 0.25f, 1.f));
  EXPECT_NEAR(uv.x(), cam.cx + 0.5f * cam.fx, kPixelTol);
  EXPECT_NEAR(uv.y(), cam.cy + 0.25f * cam.fy, kPixelTol);
  // The image corners back-project inside the field of view and project back inside the image.
  for (float u_px : {0.f, static_cast<float>(cam.width - 1)}) {
    for (float v_px : {0.f, static_cast<float>(cam.height - 1)}) {
      const Eigen::Vector2f back = cam.project(cam.backProject(u_px, v_px, 1.f));
      EXPECT_GE(back.x(), -kPixelTol);
      EXPECT_LE(back.x(), static_cast<float>(cam.width - 1) + kPixelTol);
      EXPECT_GE(back.y(), -kPixelTol);
      EXPECT_LE(back.y(), static_cast<float>(cam.height - 1) + kPixelTol);
    }
  }
}

TEST(Camera, ScaledIntrinsicsFollowThePyramidConvention) {
  const PinholeCamera cam = test::tumCamera();
  std::mt19937 rng(kSeed);
  std::uniform_real_distribution<float> xy(-1.f, 1.f), z(0.5f, 4.f);
  for (int factor : {1, 2, 4}) {
    const PinholeCamera coarse = cam.scaled(factor);
    EXPECT_EQ(coarse.width, cam.width / factor);
    EXPECT_EQ(coarse.height, cam.height / factor);
    EXPECT_TRUE(coarse.validate().ok()) << coarse.validate().message();
    // Coarse pixel x samples fine pixel factor * x: every point projects to the fine pixel
    // divided by the factor.
    for (int i = 0; i < 200; ++i) {
      const Eigen::Vector3f p(xy(rng), xy(rng), z(rng));
      const Eigen::Vector2f fine = cam.project(p), coarse_uv = coarse.project(p);
      EXPECT_NEAR(coarse_uv.x() * static_cast<float>(factor), fine.x(), kPixelTol);
      EXPECT_NEAR(coarse_uv.y() * static_cast<float>(factor), fine.y(), kPixelTol);
    }
  }
  // Odd sizes round down: the last fine column has no coarse pixel.
  PinholeCamera odd = cam;
  odd.width = 641;
  odd.height = 481;
  EXPECT_EQ(odd.scaled(2).width, 320);
  EXPECT_EQ(odd.scaled(2).height, 240);
}

TEST(Camera, ValidateNamesTheBadField) {
  EXPECT_TRUE(test::tumCamera().validate().ok());
  const float nan = std::numeric_limits<float>::quiet_NaN();
  struct Case {
    PinholeCamera camera;
    std::string field;
  };
  auto with = [](auto change) {
    PinholeCamera c = test::tumCamera();
    change(c);
    return c;
  };
  const Case cases[] = {
      {with([](PinholeCamera& c) { c.fx = 0.f; }), "fx"},
      {with([&](PinholeCamera& c) { c.fx = nan; }), "fx"},
      {with([](PinholeCamera& c) { c.fy = -1.f; }), "fy"},
      {with([](PinholeCamera& c) { c.width = 0; }), "image size"},
      {with([](PinholeCamera& c) { c.height = -4; }), "image size"},
      {with([](PinholeCamera& c) { c.cx = 700.f; }), "cx"},
      {with([](PinholeCamera& c) { c.cx = -1.f; }), "cx"},
      {with([](PinholeCamera& c) { c.cy = 500.f; }), "cy"},
  };
  for (const Case& c : cases) {
    const Status valid = c.camera.validate();
    EXPECT_FALSE(valid.ok()) << c.field;
    const std::string& why = valid.message();
    EXPECT_NE(why.find(c.field), std::string::npos) << "'" << why << "' should name " << c.field;
  }
}

TEST(Camera, ParseIntrinsics) {
  PinholeCamera cam;
  const Status parsed = parseIntrinsics("525,526.5,319.5,239.5", &cam);
  ASSERT_TRUE(parsed.ok()) << parsed.message();
  EXPECT_FLOAT_EQ(cam.fx, 525.f);
  EXPECT_FLOAT_EQ(cam.fy, 526.5f);
  EXPECT_FLOAT_EQ(cam.cx, 319.5f);
  EXPECT_FLOAT_EQ(cam.cy, 239.5f);
  EXPECT_EQ(cam.width, 640) << "the image size is not part of --intrinsics";
  const PinholeCamera before = cam;
  for (const char* bad : {"525,526,319", "525,526,319,239,1", "525,abc,319,239", "525,526q,319,239",
                          ""}) {
    const Status refused = parseIntrinsics(bad, &cam);
    EXPECT_FALSE(refused.ok()) << bad;
    EXPECT_FALSE(refused.message().empty()) << bad;
    EXPECT_FLOAT_EQ(cam.fx, before.fx) << "a rejected text leaves the camera alone: " << bad;
  }
}

}  // namespace
}  // namespace kinfly
