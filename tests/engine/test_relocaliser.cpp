// Relocaliser: a view coded twice with fresh sensor noise codes alike, a view turned away codes
// unlike; only new views become keyframes; the nearest keyframes come most alike first and
// within the candidate bound; a full one adds no more and, cleared, has room again; bad settings
// are refused by name.
#include <gtest/gtest.h>

#include <random>

#include "kinfly/synthetic/synthetic_scene.h"
#include "kinfly/tracking/relocaliser.h"
#include "test_util.h"

namespace kinfly {
namespace {

struct RelocaliserFixture : public ::testing::Test {
  RelocaliserFixture()
      : camera(test::tumCamera()), scene(SyntheticScene::cornerRoom()),
        raw(camera.width, camera.height), depth(camera.width, camera.height) {}
  // The corner room from `T_world_cam` with the sensor's noise, coded.
  void code(Relocaliser* r, const Pose& T_world_cam, uint32_t seed) {
    std::mt19937 rng(seed);
    scene.renderRawDepth(camera, T_world_cam, test::kRenderMaxDepthM, test::kTumDepthScale, &rng,
                         raw);
    test::rawToMetres(raw, test::kTumDepthScale, depth);
    r->encode(depth);
  }
  PinholeCamera camera;
  SyntheticScene scene;
  Image<uint16_t> raw;
  Image<float> depth;
};

Pose turned(double deg) {
  return test::makePose(-Eigen::Vector3d::UnitY() * test::degToRad(deg), Eigen::Vector3d::Zero());
}

TEST_F(RelocaliserFixture, KeepsNewViewsOnlyAndFindsTheMostAlike) {
  // The same view with fresh noise differs in a few ferns (a comparison whose threshold lies
  // within the noise of its pixel's depth); under half the share that makes a keyframe.
  constexpr float kSameViewMax = 0.1f;
  Relocaliser r{Relocaliser::Params()};
  ASSERT_TRUE(r.params().validate().ok());
  code(&r, turned(0), 1);
  EXPECT_TRUE(r.harvest(turned(0)));
  code(&r, turned(0), 2);
  EXPECT_FALSE(r.harvest(turned(0))) << "the same view again is no new keyframe";
  Relocaliser::Candidate best[2];
  ASSERT_EQ(r.nearest(2, best), 1);
  EXPECT_LT(best[0].dissimilarity, kSameViewMax);
  code(&r, turned(40), 3);
  EXPECT_TRUE(r.harvest(turned(40))) << "turned 40 degrees is a new view";
  EXPECT_EQ(r.keyframes(), 2);
  // Near the second keyframe: it comes first; the first, turned 37 degrees away, is beyond
  // the candidates' bound.
  code(&r, turned(37), 4);
  ASSERT_EQ(r.nearest(2, best), 1);
  EXPECT_TRUE(best[0].T_world_cam.isApprox(turned(40)));
  EXPECT_LT(best[0].dissimilarity, r.params().max_candidate_dissimilarity);
  // An empty image is like nothing kept.
  depth.fill(0.f);
  r.encode(depth);
  EXPECT_EQ(r.nearest(2, best), 0);
}

TEST_F(RelocaliserFixture, TheNearestAreTheFirstOfAllSortedByLikeness) {
  Relocaliser::Params params;
  params.new_keyframe_dissimilarity = 0.05f;  // every 20 degrees is kept
  params.max_candidate_dissimilarity = 1.f;   // and every one is a candidate
  Relocaliser r(params);
  constexpr int kViews = 5;
  for (int i = 0; i < kViews; ++i) {
    code(&r, turned(20.0 * i), 20 + i);
    ASSERT_TRUE(r.harvest(turned(20.0 * i))) << "view " << i;
  }
  code(&r, turned(38.0), 30);
  Relocaliser::Candidate all[kViews], two[2];
  ASSERT_EQ(r.nearest(kViews, all), kViews);
  for (int i = 1; i < kViews; ++i) EXPECT_LE(all[i - 1].dissimilarity, all[i].dissimilarity);
  EXPECT_TRUE(all[0].T_world_cam.isApprox(turned(40.0))) << "38 degrees is most like 40";
  // Fewer places than keyframes: the kept list evicts as better ones come.
  ASSERT_EQ(r.nearest(2, two), 2);
  for (int i = 0; i < 2; ++i) {
    EXPECT_TRUE(two[i].T_world_cam.isApprox(all[i].T_world_cam)) << i;
    EXPECT_EQ(two[i].dissimilarity, all[i].dissimilarity) << i;
  }
}

TEST_F(RelocaliserFixture, StopsAddingWhenFull) {
  Relocaliser::Params params;
  params.max_keyframes = 2;
  Relocaliser r(params);
  for (int i = 0; i < 4; ++i) {
    code(&r, turned(40.0 * i), 10 + i);
    EXPECT_EQ(r.harvest(turned(40.0 * i)), i < 2) << "view " << i;
  }
  EXPECT_EQ(r.keyframes(), 2);
  // A new map forgets the old one's keyframes (FusionPipeline); there is room again.
  r.clear();
  EXPECT_EQ(r.keyframes(), 0);
  code(&r, turned(40.0), 20);  // a view it kept before
  Relocaliser::Candidate best[1];
  EXPECT_EQ(r.nearest(1, best), 0) << "a cleared relocaliser knows no place";
  EXPECT_TRUE(r.harvest(turned(120.0)));
  EXPECT_EQ(r.keyframes(), 1);
}

TEST(Relocaliser, RefusesBadSettingsByName) {
  Relocaliser::Params p;
  p.ferns = 0;
  p.max_depth_m = p.min_depth_m;
  const Status s = p.validate();
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.message().find("ferns must be in [1, 4096]"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("max_depth_m must be > min_depth_m"), std::string::npos)
      << s.message();
}

}  // namespace
}  // namespace kinfly
