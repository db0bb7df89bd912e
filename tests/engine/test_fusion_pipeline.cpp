// FusionPipeline end to end on a synthetic sequence with Kinect noise: tracks the known
// trajectory, survives an empty frame, respects given poses, along a wall, where only a motion
// prior can, follows it where the scene leaves the pose weak, and tracks a scene 3.6 m off.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <optional>
#include <random>
#include <vector>

#include "kinfly/pipeline/fusion_pipeline.h"
#include "kinfly/volume/tsdf_volume.h"
#include "test_util.h"

namespace kinfly {
namespace {

constexpr int kFrames = 30;
constexpr double kStepM = 0.02;     // translation per frame
constexpr double kStepDeg = 1.0;    // rotation per frame

// Drift tolerances after 30 frames. Each frame-to-model step is accurate to a few tenths of a
// millimetre (see test_icp), so 30 frames accumulate a few millimetres at most; 2 cm and 1 degree
// sit under the 3 cm ATE budget of the design and fail at once if any frame loses track, keeps
// a stale pose or composes transforms in the wrong order (that would be off by the 58 cm /
// 29 degree motion).
constexpr double kPoseTolM = 0.02;
constexpr double kPoseTolDeg = 1.0;
// Refined keyframes: each is registered against the model directly, so the error stays at the
// ICP's few millimetres instead of accumulating; the last guess is off by 15 mm and 1.5 degrees.
constexpr double kRefineTolM = 0.005;
constexpr double kRefineTolDeg = 0.5;

// Ground truth: a smooth 6-DoF motion, 2 cm and 1 degree per frame, starting at the world
// origin (the pipeline's world is its first camera frame).
Pose groundTruth(int k) {
  const Eigen::Vector3d axis = Eigen::Vector3d(0.2, -1.0, 0.1).normalized();
  const Eigen::Vector3d dir = Eigen::Vector3d(1.0, -0.1, 0.15).normalized();
  return test::makePose(axis * test::degToRad(kStepDeg * k), dir * (kStepM * k));
}

struct PipelineFixture : public ::testing::Test {
  PipelineFixture()
      : camera(test::tumCamera()),
        scene(SyntheticScene::cornerRoom()),
        volume(HashedVolume::Params{}),
        pipeline(camera, FusionPipeline::Params(), &volume),
        raw(camera.width, camera.height) {}

  void render(int k, uint32_t seed) { renderAt(groundTruth(k), seed); }
  void renderAt(const Pose& T_world_cam, uint32_t seed) {
    std::mt19937 rng(seed);
    scene.renderRawDepth(camera, T_world_cam, test::kRenderMaxDepthM, test::kTumDepthScale, &rng,
                         raw);
  }
  static int64_t utimeOf(int k) { return 1'000'000'000 + 33'333 * static_cast<int64_t>(k); }

  PinholeCamera camera;
  SyntheticScene scene;
  HashedVolume volume;
  FusionPipeline pipeline;
  Image<uint16_t> raw;
};

TEST_F(PipelineFixture, TracksSyntheticSequence) {
  ASSERT_TRUE(FusionPipeline::Params().validate(volume.voxelSizeM()).ok());
  for (int k = 0; k < kFrames; ++k) {
    render(k, 1000 + k);
    const FrameResult r = pipeline.processFrame(raw, utimeOf(k));
    EXPECT_EQ(r.utime, utimeOf(k));
    if (k == 0) {
      EXPECT_EQ(r.status, TrackingStatus::kFirstFrame);
      EXPECT_TRUE(r.T_world_cam.isApprox(Pose::Identity()));
    } else {
      ASSERT_EQ(r.status, TrackingStatus::kOk) << "frame " << k << ": " << r.lost_reason;
    }
    EXPECT_TRUE(r.T_world_cam.isApprox(pipeline.pose()));
    // A pose that is not a rigid transform poisons every Isometry inverse downstream.
    EXPECT_LT(test::orthonormalityError(r.T_world_cam), test::kOrthonormalityTol) << "frame " << k;
    EXPECT_LT(test::translationErrorM(r.T_world_cam, groundTruth(k)), kPoseTolM) << "frame " << k;
    EXPECT_LT(test::radToDeg(test::rotationErrorRad(r.T_world_cam, groundTruth(k))), kPoseTolDeg)
        << "frame " << k;
  }
  EXPECT_GT(volume.numAllocatedBlocks(), 0u);
}

// The model raycast at half resolution (Params::model_level 1, the drone's): its finest two
// levels are one 320x240 image, the coarsest every second pixel of it, and the sequence is
// tracked within the same bounds as with every pixel cast.
TEST_F(PipelineFixture, AModelRaycastAtHalfResolutionTracksTheSequence) {
  FusionPipeline::Params params;
  params.model_level = 1;
  ASSERT_TRUE(params.validate(volume.voxelSizeM()).ok());
  HashedVolume half_volume{HashedVolume::Params{}};
  FusionPipeline half(camera, params, &half_volume);
  const ModelMaps& model = half.model();
  EXPECT_EQ(model.camera[0].width, camera.width / 2);
  EXPECT_EQ(model.camera[1].width, camera.width / 2);
  EXPECT_EQ(model.camera[2].width, camera.width / 4);
  EXPECT_EQ(model.vertex_ref[0].height(), camera.height / 2);
  for (int k = 0; k < kFrames; ++k) {
    render(k, 1000 + k);
    const FrameResult r = half.processFrame(raw, utimeOf(k));
    if (k > 0) {
      ASSERT_EQ(r.status, TrackingStatus::kOk) << "frame " << k << ": " << r.lost_reason;
    }
    EXPECT_LT(test::translationErrorM(r.T_world_cam, groundTruth(k)), kPoseTolM) << "frame " << k;
    EXPECT_LT(test::radToDeg(test::rotationErrorRad(r.T_world_cam, groundTruth(k))), kPoseTolDeg)
        << "frame " << k;
  }
  int hits = 0;
  for (int y = 0; y < model.camera[1].height; ++y)
    for (int x = 0; x < model.camera[1].width; ++x) {
      hits += model.vertex_ref[0](x, y).allFinite() ? 1 : 0;
      ASSERT_EQ(model.vertex_ref[1](x, y).allFinite(), model.vertex_ref[0](x, y).allFinite());
      if (model.vertex_ref[0](x, y).allFinite()) {
        ASSERT_EQ(model.vertex_ref[1](x, y), model.vertex_ref[0](x, y)) << "level 1 is level 0";
      }
    }
  EXPECT_GT(hits, model.camera[0].width * model.camera[0].height / 2);
  for (int y = 0; y < model.camera[2].height; ++y)
    for (int x = 0; x < model.camera[2].width; ++x) {
      ASSERT_EQ(model.vertex_ref[2](x, y).allFinite(), model.vertex_ref[1](2 * x, 2 * y).allFinite());
      if (model.vertex_ref[2](x, y).allFinite()) {
        ASSERT_EQ(model.vertex_ref[2](x, y), model.vertex_ref[1](2 * x, 2 * y));
      }
    }
  // A render is still of the whole image; the model's own shading is of its size.
  Image<uint8_t> full(camera.width, camera.height, 0), own(camera.width / 2, camera.height / 2, 0);
  half.renderShaded(full.view());
  half.shadeModel(own.view());
  EXPECT_GT(std::count_if(full.data(), full.data() + full.numPixels(), [](uint8_t v) { return v > 0; }),
            full.numPixels() / 2);
  EXPECT_GT(std::count_if(own.data(), own.data() + own.numPixels(), [](uint8_t v) { return v > 0; }),
            own.numPixels() / 2);
  params.model_level = kPyramidLevels - 1;
  EXPECT_NE(params.validate(volume.voxelSizeM()).message().find("model_level"), std::string::npos);
}

// The half-resolution model's pixel (x, y) is the ray through the frame's pixel (2x, 2y), as
// the depth pyramid's level 1 is: the same map seen from the same pose gives, there, the point
// that a model of every pixel gives at its level 1. Hinted by another depth (the pyramid's
// mean against the pixel's own), Newton ends anywhere within half a voxel of the crossing, and
// at a depth edge on another surface, so the bound holds for most pixels, not each.
TEST_F(PipelineFixture, TheHalfResolutionModelsPixelsAreThePyramidsPixels) {
  constexpr float kSamePointM = 1e-3f;
  FusionPipeline::Params half_params;
  half_params.model_level = 1;
  HashedVolume half_volume{HashedVolume::Params{}};
  FusionPipeline half(camera, half_params, &half_volume);
  for (int k = 0; k < 3; ++k) {
    render(k, 1000 + k);
    pipeline.processFrameAtPose(raw, utimeOf(k), groundTruth(k));
    half.processFrameAtPose(raw, utimeOf(k), groundTruth(k));
  }
  render(3, 1003);
  pipeline.processFrameFromGuess(raw, utimeOf(3), groundTruth(3));
  half.processFrameFromGuess(raw, utimeOf(3), groundTruth(3));
  const ModelMaps &full_model = pipeline.model(), &half_model = half.model();
  // Measured: 89 % within 1 mm (median 0.06 mm; Newton stops within half a voxel, so a few
  // mm remain where the two hints start it apart). Against the fine pixel beside, (2x + 1, 2y),
  // the median is 5.7 mm.
  constexpr double kMost = 0.8, kNearlyEvery = 0.99;
  int both = 0, either = 0, same = 0;
  for (int y = 0; y < half_model.camera[0].height; ++y)
    for (int x = 0; x < half_model.camera[0].width; ++x) {
      const Eigen::Vector3f &a = half_model.vertex_ref[0](x, y), &b = full_model.vertex_ref[1](x, y);
      either += a.allFinite() || b.allFinite() ? 1 : 0;
      if (!a.allFinite() || !b.allFinite()) continue;
      ++both;
      same += (a - b).norm() < kSamePointM ? 1 : 0;
    }
  std::printf("[pipeline] half-resolution model: %d of %d points within %.0f mm of the full "
              "model's level 1, %d pixels hit by either\n", same, both, 1e3 * kSamePointM, either);
  EXPECT_GT(both, half_model.camera[0].width * half_model.camera[0].height / 2);
  EXPECT_GT(both, kNearlyEvery * either) << "the two models hit at the same pixels";
  EXPECT_GT(same, kMost * both);
}

TEST_F(PipelineFixture, EmptyFrameIsLostAndTrackingRecovers) {
  constexpr int kEmptyFrame = 15;
  Pose before_empty = Pose::Identity();
  for (int k = 0; k < kFrames; ++k) {
    if (k == kEmptyFrame) {
      raw.fill(0);
      const size_t blocks = volume.numAllocatedBlocks();
      const FrameResult r = pipeline.processFrame(raw, utimeOf(k));
      EXPECT_EQ(r.status, TrackingStatus::kLost);
      EXPECT_FALSE(r.lost_reason.empty());
      EXPECT_EQ(r.valid_depth_fraction, 0.f);
      EXPECT_TRUE(isFinite(r.T_world_cam));
      EXPECT_TRUE(pipeline.pose().isApprox(before_empty)) << "a lost frame keeps the last pose";
      EXPECT_EQ(volume.numAllocatedBlocks(), blocks) << "nothing is fused from a lost frame";
      continue;
    }
    render(k, 2000 + k);
    const FrameResult r = pipeline.processFrame(raw, utimeOf(k));
    if (k > 0) {
      // The frame after the gap starts 2 steps (4 cm, 2 degrees) from the last pose.
      ASSERT_EQ(r.status, TrackingStatus::kOk) << "frame " << k << ": " << r.lost_reason;
    }
    before_empty = r.T_world_cam;
  }
  EXPECT_LT(test::translationErrorM(pipeline.pose(), groundTruth(kFrames - 1)), kPoseTolM);
  EXPECT_LT(test::radToDeg(test::rotationErrorRad(pipeline.pose(), groundTruth(kFrames - 1))),
            kPoseTolDeg);
}

TEST_F(PipelineFixture, ProcessFrameAtPoseKeepsGivenPose) {
  for (int k = 0; k < 3; ++k) {
    render(k, 3000 + k);
    pipeline.processFrame(raw, utimeOf(k));
  }
  // A correction from outside (e.g. the ground station): exactly the ground truth of frame 3,
  // which the tracker's estimate would differ from by a little.
  render(3, 3003);
  const Pose given = groundTruth(3);
  const FrameResult r = pipeline.processFrameAtPose(raw, utimeOf(3), given);
  EXPECT_EQ(r.status, TrackingStatus::kGivenPose);
  // Fused without a prediction: the frame tracked next raycasts the model as it needs.
  EXPECT_EQ(r.ms.raycast, 0.0);
  EXPECT_EQ(r.utime, utimeOf(3));
  EXPECT_TRUE(r.T_world_cam.matrix() == given.matrix());
  EXPECT_TRUE(pipeline.pose().matrix() == given.matrix());
  // Tracking continues from the given pose.
  render(4, 3004);
  const FrameResult next = pipeline.processFrame(raw, utimeOf(4));
  ASSERT_EQ(next.status, TrackingStatus::kOk) << next.lost_reason;
  EXPECT_LT(test::translationErrorM(next.T_world_cam, groundTruth(4)), kPoseTolM);
}

TEST_F(PipelineFixture, FirstFramesAtGivenPosesBuildAMapToTrackAgainst) {
  // Fusing only at given poses must also produce the model the tracker needs.
  for (int k = 0; k < 2; ++k) {
    render(k, 4000 + k);
    pipeline.processFrameAtPose(raw, utimeOf(k), groundTruth(k));
  }
  render(2, 4002);
  const FrameResult r = pipeline.processFrame(raw, utimeOf(2));
  ASSERT_EQ(r.status, TrackingStatus::kOk) << r.lost_reason;
  EXPECT_LT(test::translationErrorM(r.T_world_cam, groundTruth(2)), kPoseTolM);
}

TEST_F(PipelineFixture, RefinesKeyframesFromADriftedGuess) {
  // The ground station's use: keyframes 5 frames apart (10 cm, 5 degrees), each starting from
  // an onboard pose that has drifted. The drift grows 3 mm and 0.3 degrees per keyframe about
  // an axis the motion does not share, so a refinement that ignored the guess, or returned it,
  // fails the pose tolerance by the last keyframes.
  constexpr int kKeyframeStride = 5;
  constexpr int kKeyframes = 6;
  const Eigen::Vector3d drift_axis = Eigen::Vector3d(1.0, 0.3, -0.4).normalized();
  for (int i = 0; i < kKeyframes; ++i) {
    const int k = i * kKeyframeStride;
    render(k, 5000 + k);
    const Pose drift = test::makePose(drift_axis * test::degToRad(0.3 * i),
                                      Eigen::Vector3d(0.003, -0.002, 0.001) * i);
    const Pose guess = groundTruth(k) * drift;
    const FrameResult r = pipeline.processFrameFromGuess(raw, utimeOf(k), guess);
    EXPECT_EQ(r.utime, utimeOf(k));
    if (i == 0) {
      EXPECT_EQ(r.status, TrackingStatus::kFirstFrame);
      EXPECT_TRUE(r.T_world_cam.isApprox(guess)) << "the first keyframe defines the map";
      continue;
    }
    ASSERT_EQ(r.status, TrackingStatus::kOk) << "keyframe " << i << ": " << r.lost_reason;
    EXPECT_TRUE(r.T_world_cam.isApprox(pipeline.pose()));
    EXPECT_LT(test::orthonormalityError(r.T_world_cam), test::kOrthonormalityTol);
    EXPECT_LT(test::translationErrorM(r.T_world_cam, groundTruth(k)), kRefineTolM) << "keyframe " << i;
    EXPECT_LT(test::radToDeg(test::rotationErrorRad(r.T_world_cam, groundTruth(k))), kRefineTolDeg)
        << "keyframe " << i;
  }
  // Plain tracking carries on from the last refined pose, although the model maps it left are
  // the prediction from that keyframe's guess.
  const int next = (kKeyframes - 1) * kKeyframeStride + 1;
  render(next, 5000 + next);
  const FrameResult r = pipeline.processFrame(raw, utimeOf(next));
  ASSERT_EQ(r.status, TrackingStatus::kOk) << r.lost_reason;
  EXPECT_LT(test::translationErrorM(r.T_world_cam, groundTruth(next)), kRefineTolM);
}

// Along a wall that fills the view, which fixes only the distance to it and the two tilts: with
// the motion an IMU saw, off by a centimetre towards the wall every frame, the pose follows the
// prior within the wall and the wall across it, and the three weak directions are named in the
// world's and the camera's frames. The depth is noise-free: a map fused from a few noisy frames
// has normals a few degrees off, which give 2 % of a full constraint along the wall, far above
// the tracker's threshold (set where the map has been fused from many frames, docs/engine.md).
TEST(PipelineDegenerate, AlongAWallThePoseFollowsThePriorWithinItAndTheWallAcrossIt) {
  constexpr int kWallFrames = 20;
  // The weak directions lie in the null space of the noise-free wall, to the fraction of a degree
  // that the map's voxels tilt its normals by; frames swapped or unrotated would be off by ~0.5.
  constexpr double kNullSpaceTol = 1e-2;
  // A wall tilted against the camera, which starts turned: the directions' conversion to world
  // and camera frames is then no identity.
  const Eigen::Vector3d n = Eigen::Vector3d(0.2, -0.1, -1.0).normalized();
  const Eigen::Vector3d along1 = n.cross(Eigen::Vector3d::UnitY()).normalized();
  const Eigen::Vector3d along2 = n.cross(along1);
  const Eigen::Vector3d prior_error_m = 0.01 * n;  // towards the wall, every frame
  SyntheticScene scene;
  scene.addPlane(n.cast<float>(), static_cast<float>(n.dot(Eigen::Vector3d(0.0, 0.0, 1.5))));
  const PinholeCamera camera = test::tumCamera();
  Image<float> depth(camera.width, camera.height);
  Image<uint16_t> raw(camera.width, camera.height);
  const Pose start = test::makePose(Eigen::Vector3d(0.04, -0.06, 0.08), Eigen::Vector3d::Zero());
  const auto truth = [&](int k) {
    // Within the wall, and turning about its normal: everything the wall leaves weak.
    return test::makePose(n * test::degToRad(0.5) * k,
                          kStepM * k * (along1 - 0.5 * along2)) * start;
  };
  const auto render = [&](int k) {
    scene.renderDepth(camera, truth(k), test::kRenderMaxDepthM, depth);
    for (int y = 0; y < camera.height; ++y)
      for (int x = 0; x < camera.width; ++x)
        raw(x, y) = static_cast<uint16_t>(std::lround(depth(x, y) / test::kTumDepthScale));
  };
  HashedVolume volume{HashedVolume::Params{}};
  FusionPipeline pipeline(camera, FusionPipeline::Params(), &volume);
  render(0);
  pipeline.processFrameAtPose(raw, 1'000'000, truth(0));
  FrameResult r;
  for (int k = 1; k < kWallFrames; ++k) {
    render(k);
    Pose prior = pipeline.pose() * truth(k - 1).inverse() * truth(k);
    prior.translation() += prior_error_m;
    r = pipeline.processFrame(raw, 1'000'000 + 33'333 * k, &prior);
    ASSERT_EQ(r.status, TrackingStatus::kOk) << "frame " << k << ": " << r.lost_reason;
    ASSERT_EQ(r.weak.count, 3) << "frame " << k;
    const Eigen::Vector3d n_cam = truth(k).linear().transpose() * n;
    for (int i = 0; i < r.weak.count; ++i) {
      // The camera moves within the wall (world), or turns about its normal (camera frame).
      EXPECT_LT(std::abs(r.weak.d[i].head<3>().dot(n)), kNullSpaceTol) << r.weak.d[i].transpose();
      EXPECT_LT(r.weak.d[i].tail<3>().cross(n_cam).norm(), kNullSpaceTol)
          << r.weak.d[i].transpose();
    }
    const Eigen::Vector3d error = r.T_world_cam.translation() - truth(k).translation();
    EXPECT_LT(std::abs(error.dot(n)), kRefineTolM) << "frame " << k << ": the prior's error";
    EXPECT_LT(error.norm(), kPoseTolM) << "frame " << k;
    EXPECT_LT(test::radToDeg(test::rotationErrorRad(r.T_world_cam, truth(k))), kPoseTolDeg);
  }
  std::printf("[pipeline] along a wall with the IMU's prior: moved %.3f m of %.3f m\n",
              (r.T_world_cam.translation() - truth(0).translation()).norm(),
              (truth(kWallFrames - 1).translation() - truth(0).translation()).norm());
}

// Recovery (issue 17): tracking back within this many frames after a loss.
constexpr int kMaxRecoveryFrames = 10;

// A second without depth, 30 frames: the drone has turned 56 degrees to the right at 105 deg/s
// and turns back meanwhile, moving 9 cm. The IMU's prediction over the gap is off by 3 cm and 1
// degree at its end. From the last pose the model shows the right of the room, little of what
// the camera sees now (4 % inliers: lost for good); the model seen from the prediction shows it,
// mapped before the turn. `covered`: the frames come, empty (lost); otherwise none come at all
// (a gap in the frames' times). Nothing is fused meanwhile, and the rest of the sequence tracks
// as before. Returns the frames from the first after the gap to the first tracked.
int turnAndRecover(PipelineFixture* f, bool covered) {
  constexpr int kTurn = 16, kGap = 30, kEnd = 60;
  constexpr double kTurnDegPerFrame = 3.5;
  const auto truth = [&](int k) {
    const double turned = kTurnDegPerFrame * kTurn;
    const double deg = k < kTurn         ? kTurnDegPerFrame * k
                       : k < kTurn + kGap ? turned * (1.0 - double(k - kTurn) / kGap)
                                          : -0.3 * (k - kTurn - kGap);
    return test::makePose(-Eigen::Vector3d::UnitY() * test::degToRad(deg),
                          Eigen::Vector3d(0.003 * k, 0.0, 0.0));
  };
  const Eigen::Vector3d drift_m_per_frame = Eigen::Vector3d(0.6, -0.3, 0.8).normalized() * 0.001;
  const Eigen::Vector3d drift_rad_per_frame =
      Eigen::Vector3d(0.2, 1.0, 0.3).normalized() * test::degToRad(1.0 / kGap);
  int last_tracked = -1, recovered_at = -1;
  for (int k = 0; k < kEnd; ++k) {
    const bool in_gap = k >= kTurn && k < kTurn + kGap;
    if (in_gap && !covered) continue;
    if (in_gap) {
      f->raw.fill(0);
    } else {
      f->renderAt(truth(k), 6000 + k);
    }
    // The IMU's motion since the last tracked frame, off by a drift that grows with the time.
    std::optional<Pose> prior;
    if (last_tracked >= 0) {
      const int n = k - last_tracked;
      prior = f->pipeline.pose() *
              test::makePose(drift_rad_per_frame * n, drift_m_per_frame * n) *
              truth(last_tracked).inverse() * truth(k);
    }
    const size_t blocks = f->volume.numAllocatedBlocks();
    const FrameResult r =
        f->pipeline.processFrame(f->raw, PipelineFixture::utimeOf(k), prior ? &*prior : nullptr);
    if (in_gap) {
      EXPECT_EQ(r.status, TrackingStatus::kLost) << "frame " << k;
      EXPECT_EQ(r.lost_in_a_row, k - kTurn + 1);
      EXPECT_EQ(f->volume.numAllocatedBlocks(), blocks) << "nothing is fused from a lost frame";
      continue;
    }
    if (r.status == TrackingStatus::kLost) continue;
    if (recovered_at < 0 && k >= kTurn + kGap) {
      recovered_at = k;
      // Frames lost, not frames that never came.
      EXPECT_EQ(r.recovered_after, covered ? k - last_tracked - 1 : k - kTurn - kGap);
    }
    last_tracked = k;
    EXPECT_LT(test::translationErrorM(r.T_world_cam, truth(k)), kPoseTolM) << "frame " << k;
    EXPECT_LT(test::radToDeg(test::rotationErrorRad(r.T_world_cam, truth(k))), kPoseTolDeg)
        << "frame " << k;
  }
  EXPECT_EQ(last_tracked, kEnd - 1);
  return recovered_at < 0 ? kEnd : recovered_at - (kTurn + kGap);
}

TEST_F(PipelineFixture, ASecondCoveredIsRecoveredFromTheImusPrediction) {
  const int frames = turnAndRecover(this, /*covered=*/true);
  std::printf("[pipeline] a second covered while turning back 56 deg, the IMU's prediction 3 cm "
              "and 1 deg off: tracking back %d frames after the sensor was uncovered\n",
              frames);
  EXPECT_LE(frames, kMaxRecoveryFrames);
  EXPECT_EQ(frames, 0) << "with the prediction's view the first frame uncovered is tracked";
}

TEST_F(PipelineFixture, ASecondWithoutFramesIsRecoveredFromTheImusPrediction) {
  const int frames = turnAndRecover(this, /*covered=*/false);
  std::printf("[pipeline] a second without frames while turning back 56 deg: tracking back %d "
              "frames after they came again\n",
              frames);
  EXPECT_LE(frames, kMaxRecoveryFrames);
  // The gap in the frames' times counts as missed frames: without it the first frame is tried
  // against the last pose's view only, and lost.
  EXPECT_EQ(frames, 0) << "the first frame after the gap is tracked";
}

// Missed frames are read from the frames' times against the median interval: jitter, a repeated
// time (a log's frames 1 us apart) and a clock that goes back (a restarted log or sensor) are
// no gap; three frames' time without frames is three missed.
TEST_F(PipelineFixture, OnlyARealGapInTheFramesTimesCountsAsMissed) {
  constexpr int kRepeatedAt = 10, kBackAt = 15, kGapAt = 20, kGapFrames = 3;
  constexpr double kJitter = 0.3;  // of a frame's interval, either way
  std::mt19937 rng(77);
  std::uniform_real_distribution<double> jitter(-kJitter, kJitter);
  int64_t t = 1'000'000'000;
  for (int k = 0; k < kFrames; ++k) {
    if (k == kRepeatedAt) t += 1;
    else if (k == kBackAt) t = 5'000'000;
    else if (k > 0) t += std::llround(33'333 * ((k == kGapAt ? 1 + kGapFrames : 1) + jitter(rng)));
    render(k, 9000 + k);
    const FrameResult r = pipeline.processFrame(raw, t);
    ASSERT_NE(r.status, TrackingStatus::kLost) << "frame " << k << ": " << r.lost_reason;
    EXPECT_EQ(r.missed, k == kGapAt ? kGapFrames : 0) << "frame " << k;
  }
}

// Without an IMU: 11 frames lost, empty (24 cm and 12 degrees, beyond the 20 cm a frame may
// jump); the gates widen with the frames lost and the frame after them is tracked from the last
// pose.
TEST_F(PipelineFixture, LostFramesWithoutAPriorAreRecoveredByWidenedGates) {
  constexpr int kLostFrom = 10, kLost = 11, kEnd = 30;
  int recovered_at = -1;
  for (int k = 0; k < kEnd; ++k) {
    const bool lost = k >= kLostFrom && k < kLostFrom + kLost;
    if (lost) {
      raw.fill(0);
    } else {
      render(k, 7000 + k);
    }
    const FrameResult r = pipeline.processFrame(raw, utimeOf(k));
    if (lost || r.status == TrackingStatus::kLost) continue;
    if (recovered_at < 0 && k >= kLostFrom + kLost) {
      recovered_at = k;
      EXPECT_FALSE(r.relocalised) << "tracked from the last pose, not from a keyframe";
      EXPECT_EQ(r.recovered_after, kLost);
    }
    EXPECT_LT(test::translationErrorM(r.T_world_cam, groundTruth(k)), kPoseTolM) << "frame " << k;
    EXPECT_LT(test::radToDeg(test::rotationErrorRad(r.T_world_cam, groundTruth(k))), kPoseTolDeg)
        << "frame " << k;
  }
  ASSERT_GE(recovered_at, 0) << "never tracked again";
  std::printf("[pipeline] 11 frames lost, no prior: tracking back %d frames after\n",
              recovered_at - (kLostFrom + kLost));
  EXPECT_LE(recovered_at - (kLostFrom + kLost), kMaxRecoveryFrames);
}

// With an IMU, a frame after a missed one is tracked with widened gates, but its pose must lie
// within max_prior_disagreement_m (5 cm) and _rad of the IMU's prediction, whichever try found
// it: the prediction's error over two frames is far below that. Here the frame after an empty
// one is at the truth, and the prediction is moved off along the path's direction: 3 cm off (the
// IMU's error after a covered second in the tests below), the frame tracks to the truth; 10 cm
// off (within the doubled gates after one missed frame, and within one frame's 20 cm gate, the
// rule until 2026-12-07) the vision and the IMU disagree beyond what the IMU allows and the
// frame is lost, the map untouched. In the ring's corridors (docs/sim.md) it was the vision that
// was 32 cm, then a relocalisation 16 cm, off, and was taken.
TEST_F(PipelineFixture, AfterAMissedFrameThePoseMustAgreeWithTheImusPrediction) {
  FusionPipeline::Params unbounded;
  unbounded.max_prior_disagreement_rad = 0.f;
  EXPECT_EQ(unbounded.validate(0.01f).message(), "max_prior_disagreement_rad must be in (0, 1]");
  constexpr int kEmpty = 10;
  const Eigen::Vector3d along = Eigen::Vector3d(1.0, -0.1, 0.15).normalized();
  for (const double prior_off_m : {0.03, 0.10}) {
    SCOPED_TRACE(prior_off_m);
    HashedVolume map{HashedVolume::Params{}};
    FusionPipeline p(camera, FusionPipeline::Params(), &map);
    for (int k = 0; k < kEmpty; ++k) {
      render(k, 9000 + k);
      ASSERT_NE(p.processFrame(raw, utimeOf(k)).status, TrackingStatus::kLost) << "frame " << k;
    }
    raw.fill(0);
    ASSERT_EQ(p.processFrame(raw, utimeOf(kEmpty)).status, TrackingStatus::kLost);
    const int k = kEmpty + 1;
    render(k, 9000 + k);
    Pose prior = p.pose() * groundTruth(kEmpty - 1).inverse() * groundTruth(k);
    prior.translation() += prior_off_m * along;
    const size_t blocks = map.numAllocatedBlocks();
    const FrameResult r = p.processFrame(raw, utimeOf(k), &prior);
    if (prior_off_m < FusionPipeline::Params().max_prior_disagreement_m) {
      ASSERT_EQ(r.status, TrackingStatus::kOk) << r.lost_reason;
      EXPECT_LT(test::translationErrorM(r.T_world_cam, groundTruth(k)), kPoseTolM);
      continue;
    }
    EXPECT_EQ(r.status, TrackingStatus::kLost) << "tracked "
        << test::translationErrorM(r.T_world_cam, groundTruth(k)) << " m from the truth";
    EXPECT_NE(r.lost_reason.find("from the prior"), std::string::npos) << r.lost_reason;
    EXPECT_EQ(map.numAllocatedBlocks(), blocks) << "nothing is fused from a lost frame";
  }
}

// Kidnapped (issue 17): after 40 frames along the fixture's path (78 cm and 39 degrees from the
// start) five frames come empty and the camera is then back near where it started, 2 cm and 1
// degree off the path's fourth pose, without a prior. From the last pose that is beyond even the
// widened gates; the keyframes the pipeline kept along the way know the place. The camera stays
// back one frame longer than recovery may take, so that without relocalisation it is seen to
// stay lost for all of them.
TEST_F(PipelineFixture, AKidnappedCameraIsRelocalisedWhereItHasBeen) {
  constexpr int kPath = 40, kEmpty = 5, kBack = kMaxRecoveryFrames + 1;
  const Pose offset = test::makePose(Eigen::Vector3d(0.01, 0.012, -0.008),
                                     Eigen::Vector3d(0.012, -0.01, 0.012));
  const auto back = [&](int j) { return groundTruth(3) * offset * test::makePose(
      Eigen::Vector3d::Zero(), Eigen::Vector3d(0.005 * j, 0.0, 0.0)); };
  for (const bool relocalise : {true, false}) {
    HashedVolume map{HashedVolume::Params{}};
    FusionPipeline::Params params;
    params.relocalise = relocalise;
    FusionPipeline p(camera, params, &map);
    int k = 0, recovered_at = -1;
    bool relocalised = false;
    for (; k < kPath; ++k) {
      render(k, 8000 + k);
      ASSERT_NE(p.processFrame(raw, utimeOf(k)).status, TrackingStatus::kLost) << "frame " << k;
    }
    for (; k < kPath + kEmpty; ++k) {
      raw.fill(0);
      ASSERT_EQ(p.processFrame(raw, utimeOf(k)).status, TrackingStatus::kLost);
    }
    for (int j = 0; j < kBack; ++j, ++k) {
      renderAt(back(j), 8000 + k);
      const FrameResult r = p.processFrame(raw, utimeOf(k));
      if (r.status == TrackingStatus::kLost) continue;
      if (recovered_at < 0) {
        recovered_at = j;
        relocalised = r.relocalised;
        EXPECT_TRUE(r.lost_reason.empty()) << r.lost_reason;
      }
      EXPECT_LT(test::translationErrorM(r.T_world_cam, back(j)), kPoseTolM) << "frame " << k;
      EXPECT_LT(test::radToDeg(test::rotationErrorRad(r.T_world_cam, back(j))), kPoseTolDeg)
          << "frame " << k;
    }
    if (!relocalise) {
      EXPECT_EQ(recovered_at, -1) << "tracked again without relocalisation";
      continue;
    }
    std::printf("[pipeline] kidnapped 78 cm and 39 deg back to the start: relocalised %d frames "
                "after it came back\n", recovered_at);
    ASSERT_GE(recovered_at, 0) << "never relocalised";
    EXPECT_TRUE(relocalised);
    EXPECT_LE(recovered_at, kMaxRecoveryFrames);
  }
}


// Turned about to face what the map never held (issue 17: "if that also fails, it starts a new
// submap instead of staying lost"): 10 frames along the fixture's path in a closed room, then
// the camera faces the other way and moves on, about 1 cm a frame, for 14 frames: the new map
// begins at the 10th and four more track in it. Neither the prior's view, the
// last pose's nor any keyframe shows that half of the room, so each frame is lost; with the
// IMU's prior (here exact) the 10th begins a new map at the prior's pose, the old map cleared,
// and the frames after it track in the new map. Without a prior, or without new maps, the
// camera stays lost to the end: a new map could only begin at the last pose, a jump.
TEST_F(PipelineFixture, AfterEveryTryFailsANewMapBeginsAtThePriorAndTracks) {
  constexpr int kPath = 10, kTurned = 14;
  constexpr int kFailed = 10;  // FusionPipeline::Params' default
  scene.addPlane(Eigen::Vector3f(-1.f, 0.f, 0.f), -1.4f);  // right wall x = 1.4
  scene.addPlane(Eigen::Vector3f(0.f, 0.f, 1.f), -1.0f);   // front wall z = -1.0
  // Something in front of that wall: a wall alone leaves the motion along it to the prior.
  scene.addBox(Eigen::Vector3f(0.15f, 0.2f, -0.75f), Eigen::Vector3f(0.15f, 0.15f, 0.1f));
  scene.addSphere(Eigen::Vector3f(0.6f, -0.1f, -0.8f), 0.15f);
  const auto turned = [&](int j) {
    return groundTruth(kPath - 1) *
           test::makePose(Eigen::Vector3d::UnitY() * M_PI, Eigen::Vector3d::Zero()) *
           test::makePose(Eigen::Vector3d::Zero(), Eigen::Vector3d(0.005 * j, 0.0, 0.008 * j));
  };
  ASSERT_EQ(FusionPipeline::Params().new_map_after_failed_frames, kFailed);
  FusionPipeline::Params negative;
  negative.new_map_after_failed_frames = -1;
  EXPECT_EQ(negative.validate(0.01f).message(),
            "new_map_after_failed_frames must be >= 0 (0: never)");
  struct Case {
    int new_map_after;
    bool with_prior;
  };
  for (const Case c : {Case{kFailed, true}, Case{kFailed, false}, Case{0, true}}) {
    SCOPED_TRACE(testing::Message() << "new_map_after_failed_frames " << c.new_map_after
                                    << (c.with_prior ? ", with a prior" : ", without"));
    const bool expect_new_map = c.new_map_after > 0 && c.with_prior;
    HashedVolume map{HashedVolume::Params{}};
    FusionPipeline::Params params;
    params.new_map_after_failed_frames = c.new_map_after;
    FusionPipeline p(camera, params, &map);
    for (int k = 0; k < kPath; ++k) {
      renderAt(groundTruth(k), 11000 + k);
      ASSERT_NE(p.processFrame(raw, utimeOf(k)).status, TrackingStatus::kLost) << "frame " << k;
    }
    const size_t old_map_blocks = map.numAllocatedBlocks();
    int began_at = -1;
    for (int j = 0; j < kTurned; ++j) {
      renderAt(turned(j), 12000 + j);
      const Pose prior = turned(j);
      const size_t blocks_before = map.numAllocatedBlocks();
      const FrameResult r =
          p.processFrame(raw, utimeOf(kPath + j), c.with_prior ? &prior : nullptr);
      if (began_at < 0) {
        if (r.status == TrackingStatus::kLost) {
          EXPECT_EQ(map.numAllocatedBlocks(), blocks_before) << "nothing fused from frame " << j;
          continue;
        }
        began_at = j;
        EXPECT_TRUE(r.new_map);
        EXPECT_EQ(r.status, TrackingStatus::kFirstFrame);
        EXPECT_EQ(r.recovered_after, j);
        EXPECT_TRUE(r.lost_reason.empty()) << r.lost_reason;
        EXPECT_TRUE(r.T_world_cam.isApprox(prior)) << "the new map begins at the prior";
        // The old map is gone: what is allocated now is this frame's alone.
        EXPECT_LT(map.numAllocatedBlocks(), old_map_blocks);
        continue;
      }
      ASSERT_EQ(r.status, TrackingStatus::kOk) << "frame " << j << ": " << r.lost_reason;
      EXPECT_FALSE(r.new_map);
      EXPECT_LT(test::translationErrorM(r.T_world_cam, turned(j)), kPoseTolM) << "frame " << j;
      EXPECT_LT(test::radToDeg(test::rotationErrorRad(r.T_world_cam, turned(j))), kPoseTolDeg)
          << "frame " << j;
    }
    if (!expect_new_map) {
      EXPECT_EQ(began_at, -1) << "tracked again";
      continue;
    }
    std::printf("[pipeline] turned to face what the map never held: a new map %d frames after "
                "the turn\n", began_at);
    EXPECT_EQ(began_at, kFailed - 1);
    EXPECT_LE(began_at, kMaxRecoveryFrames);
  }
}

// Far range (issue 17: "frames declared lost on a sequence whose mean depth is 3.5 m: 0"). The
// far end of a hall, 3.3-3.9 m off (mean depth 3.6 m): floor, end wall, crates, a ball, with the
// sensor's noise drawn anew for every pixel (sigma 2 cm at 3.6 m, three pixels' spacing there).
// The camera drifts sideways, down and forwards 1.1 cm and turns 0.5 degrees a frame.
constexpr int kFarFrames = 40;
// Each frame is matched against a map whose every normal is a difference of such noise over one
// 1 cm voxel, and the end wall fixes a turn about the vertical only together with a step
// sideways (both move the far scene alike): the two drift together, by 2 cm and 1.1 degrees in
// the first 30 frames, then hold. 3 cm (the design's ATE budget) and 2 degrees; a frame lost and
// not fused, or tracked to a wrong surface, is off by more (with the fixed gate, 44 cm).
constexpr double kFarPoseTolM = 0.03;
constexpr double kFarPoseTolDeg = 2.0;

SyntheticScene farHall() {
  SyntheticScene scene;
  scene.addPlane(Eigen::Vector3f(0.f, -1.f, 0.f), -1.5f);  // the floor 1.5 m below (y down)
  scene.addPlane(Eigen::Vector3f(0.f, 0.f, -1.f), -3.9f);  // the end wall
  scene.addBox(Eigen::Vector3f(-1.0f, 1.0f, 3.0f), Eigen::Vector3f(0.4f, 0.5f, 0.3f));
  scene.addBox(Eigen::Vector3f(0.9f, 0.7f, 3.3f), Eigen::Vector3f(0.3f, 0.8f, 0.3f));
  scene.addBox(Eigen::Vector3f(0.0f, -0.6f, 3.7f), Eigen::Vector3f(0.6f, 0.3f, 0.2f));
  scene.addSphere(Eigen::Vector3f(-0.3f, 0.6f, 2.8f), 0.35f);
  return scene;
}

// The drone's configuration (kinfly-fw's defaults): 320x240, a dense cube of 3 cm voxels
// following the camera, a truncation of four voxels, two ICP iterations at the finest level,
// the model raycast at 160x120.
FusionPipeline::Params onboardParams(const DenseVolume::Params& volume) {
  FusionPipeline::Params params;
  params.preprocess.downsample = 2;
  params.integrate.truncation_m = 4.f * volume.voxel_size_m;
  params.icp.iterations_coarse_to_fine.back() = 2;
  params.model_level = 1;
  return params;
}

// Flies the far hall into VOLUME; returns the frames lost, and fails on a pose off by more than
// the bounds where `check_poses`.
int flyTheFarHall(const FusionPipeline::Params& params, TsdfVolume* volume, bool check_poses) {
  const PinholeCamera camera = test::tumCamera();
  const SyntheticScene scene = farHall();
  FusionPipeline pipeline(camera, params, volume);
  Image<uint16_t> raw(camera.width, camera.height);
  const Eigen::Vector3d axis = Eigen::Vector3d(0.1, 1.0, 0.05).normalized();
  int lost = 0;
  for (int k = 0; k < kFarFrames; ++k) {
    const Pose truth = test::makePose(axis * test::degToRad(0.5 * k),
                                      Eigen::Vector3d(0.01, 0.002, 0.005) * k);
    std::mt19937 rng(5000 + static_cast<uint32_t>(k));
    scene.renderRawDepth(camera, truth, test::kRenderMaxDepthM, test::kTumDepthScale, &rng, raw);
    if (k == 0) {
      double sum_m = 0.0;
      int n = 0;
      for (int y = 0; y < camera.height; ++y)
        for (int x = 0; x < camera.width; ++x)
          if (raw(x, y) > 0) sum_m += raw(x, y) * test::kTumDepthScale, ++n;
      EXPECT_NEAR(sum_m / n, 3.6, 0.1) << "the scene is no longer seen from 3.5 m";
    }
    const FrameResult r = pipeline.processFrame(raw, 1'000'000 + 33'333 * k);
    if (r.status == TrackingStatus::kLost) ++lost;
    if (!check_poses) continue;
    EXPECT_NE(r.status, TrackingStatus::kLost) << "frame " << k << ": " << r.lost_reason;
    EXPECT_LT(test::translationErrorM(r.T_world_cam, truth), kFarPoseTolM) << "frame " << k;
    EXPECT_LT(test::radToDeg(test::rotationErrorRad(r.T_world_cam, truth)), kFarPoseTolDeg)
        << "frame " << k;
    if (k == kFarFrames - 1)
      std::printf("[pipeline] far hall: %d of %d frames lost, last pose %.1f mm off\n", lost,
                  kFarFrames, 1000.0 * test::translationErrorM(r.T_world_cam, truth));
  }
  return lost;
}

TEST(PipelineFar, AHallSeenFromThreeAndAHalfMetresIsTrackedEveryFrame) {
  {
    HashedVolume volume{HashedVolume::Params{}};
    EXPECT_EQ(flyTheFarHall(FusionPipeline::Params(), &volume, true), 0);
  }
  // The fixed 20 degree gate alone refuses most correct pairs there, and the frames are lost.
  FusionPipeline::Params fixed_gate;
  fixed_gate.icp.normal_gate_sigmas = 0.f;
  HashedVolume volume{HashedVolume::Params{}};
  EXPECT_GT(flyTheFarHall(fixed_gate, &volume, false), kFarFrames / 2);
}

// The cube is centred at the median depth of the frame: a wall 2.46 m off (between the limits,
// 6 cm inside a 24 cm block, so that its noise cannot move the block) centres it there; a wall
// 1.2 m off leaves it at lookahead_m.
TEST(PipelineFar, TheDronesCubeIsCentredWhereTheViewsMedianDepthIs) {
  const PinholeCamera camera = test::tumCamera();
  const DenseVolume::Params cube;
  Image<uint16_t> raw(camera.width, camera.height);
  for (const float wall_m : {2.46f, 1.2f}) {
    SyntheticScene scene;
    scene.addPlane(Eigen::Vector3f(0.f, 0.f, -1.f), -wall_m);
    std::mt19937 rng(77);
    scene.renderRawDepth(camera, Pose::Identity(), test::kRenderMaxDepthM, test::kTumDepthScale,
                         &rng, raw);
    DenseVolume volume(cube);
    FusionPipeline pipeline(camera, onboardParams(cube), &volume);
    ASSERT_EQ(pipeline.processFrame(raw, 1'000'000).status, TrackingStatus::kFirstFrame);
    const float ahead_m = std::max(wall_m, cube.lookahead_m);
    EXPECT_EQ(volume.originBlock(),
              BlockIndex(volume.blockOf(Eigen::Vector3f(0.f, 0.f, ahead_m)) -
                         BlockIndex::Constant(volume.blocksPerSide() / 2)))
        << "a wall " << wall_m << " m off";
  }
}

TEST(PipelineFar, TheDronesCubeGoesOutToAFarScene) {
  const DenseVolume::Params cube;
  {
    DenseVolume volume(cube);
    EXPECT_EQ(flyTheFarHall(onboardParams(cube), &volume, true), 0);
  }
  // Held 2 m ahead, the cube ends short of the end wall and the frames are lost.
  DenseVolume::Params held = cube;
  held.max_lookahead_m = held.lookahead_m;
  DenseVolume volume(held);
  EXPECT_GT(flyTheFarHall(onboardParams(held), &volume, false), kFarFrames / 2);
}

}  // namespace
}  // namespace kinfly
