// The loop: preprocess -> track -> integrate -> raycast, once per frame. Stage loops use the
// OpenMP thread count set by the caller (omp_set_num_threads / OMP_NUM_THREADS). The map (volume) is
// passed in, not owned, so the same pipeline runs onboard (dense) and on the ground (hashed).
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "kinfly/core/camera.h"
#include "kinfly/core/image.h"
#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"
#include "kinfly/frame/depth_frame.h"
#include "kinfly/frame/model_maps.h"
#include "kinfly/frame/tracking_status.h"
#include "kinfly/preprocessing/depth_preprocessor.h"
#include "kinfly/raycast/raycaster.h"
#include "kinfly/tracking/icp_tracker.h"
#include "kinfly/tracking/relocaliser.h"
#include "kinfly/volume/tsdf_integrator.h"
#include "kinfly/volume/tsdf_volume.h"

namespace kinfly {

struct StageTimesMs {
  double preprocess = 0, track = 0, integrate = 0, raycast = 0, total = 0;
};

struct FrameResult {
  int64_t utime = 0;                   // [us] capture time, carried through unchanged
  Pose T_world_cam = Pose::Identity();
  TrackingStatus status = TrackingStatus::kLost;
  float inlier_fraction = 0.f;
  float rmse_m = 0.f;
  float valid_depth_fraction = 0.f;
  // Why the status is kLost (empty otherwise): a per-frame outcome for logs and counts, not an
  // error (kinfly/core/status.h); the pipeline goes on with the next frame.
  std::string lost_reason;
  // The directions of T_world_cam the scene did not pin down (IcpResult::weak, in world); the
  // pose keeps the prior along them where processFrame had one.
  WeakDirections weak;
  double weakest_fraction = 0.0;  // IcpResult's: how close the frame came to degenerate
  // Frames lost in a row, this one included (0 once one is tracked); on the first frame tracked
  // after a loss, `recovered_after` says how many were lost before it; `missed` counts the
  // frames missed between the last tracked frame and this one, lost or never delivered
  // (processFrame only).
  int lost_in_a_row = 0;
  int recovered_after = 0;
  int missed = 0;
  bool relocalised = false;  // tracked again from a keyframe's pose (Relocaliser)
  // The old map was given up and this frame began a new one (status kFirstFrame) at the prior's
  // pose (Params::new_map_after_failed_frames).
  bool new_map = false;
  StageTimesMs ms;
};

class FusionPipeline {
 public:
  struct Params {
    DepthPreprocessor::Params preprocess;
    IcpTracker::Params icp;
    TsdfIntegrator::Params integrate;
    Raycaster::Params raycast;
    // Frames with fewer valid depth pixels than this are not tracked or integrated.
    float min_valid_depth_fraction = 0.05f;  // [0, 1)
    // After missed frames (lost, or never delivered: a gap in the frames' times) ICP's gates
    // widen by one per frame missed, up to this factor (IcpTracker::track's gate_scale): without
    // a prior the camera has moved that many frames' worth since the last tracked one. With
    // one, ICP searches as wide, but the pose it finds must lie within max_prior_disagreement_m
    // and _rad of the prior (processFrame).
    float max_recovery_gate_scale = 3.f;  // >= 1
    // With a prior, a pose found after missed frames must lie this close to it: the IMU carries
    // the camera across a second of missed frames within a few centimetres and a degree (3 cm
    // and 1° in the tests), far below one frame's free motion (the ICP's jump gates, 20 cm and
    // 20°, the rule until 2026-12-07, which let a relocalisation in the simulated ring's second
    // corridor land 16 cm along it from a prior one frame old).
    float max_prior_disagreement_m = 0.05f;    // (0, 1]
    float max_prior_disagreement_rad = 0.05f;  // (0, 1]
    // Where neither the prior nor the last pose tracks a frame after missed ones, the frame is
    // tracked from the poses of the keyframes most like it (processFrame keeps them).
    bool relocalise = true;
    Relocaliser::Params relocaliser;
    // Where this many frames with depth since the last fused one were lost (the first of them
    // tried from the last pose only, the rest also from the prior's view and the keyframes),
    // and the frame comes with a prior, processFrame gives the map up and begins a new one with
    // the frame at the prior's pose: the IMU's, so the odometry's frame goes on without a jump.
    // A camera that sees only what the map never held would otherwise stay lost for good.
    // Without a prior the frame stays lost: a new map could only begin at the last tracked
    // pose, a jump in the odometry that nothing would announce (kinfly-fw without its flight
    // stack, kinfly-fuse). 0: never. Frames without depth (a covered sensor) do not count: they
    // say nothing of whether the map still fits.
    int new_map_after_failed_frames = 10;  // >= 0
    // The pyramid level whose resolution the model is raycast at for tracking (ModelMaps'
    // first_level). The raycast was the largest stage onboard (2.4 of 6.5 ms at 320x240); at
    // level 1 it casts a quarter of the rays and ICP pairs four of the frame's finest points
    // with each model pixel, whose plane (point and normal) they are measured against
    // (docs/engine.md, departure 4). 0: every pixel, as KinectFusion does.
    int model_level = 0;  // [0, kPyramidLevels - 2]
    Status validate(float voxel_size_m) const;
  };

  // `input_camera` describes the raw depth images; `volume` must outlive the pipeline.
  FusionPipeline(const PinholeCamera& input_camera, const Params& params, TsdfVolume* volume);

  // Tracks the frame against the model, then fuses it. ICP starts from the last pose, or from
  // `T_world_cam_prior` where the caller predicts the motion (the drone's IMU): where the scene
  // leaves a direction weak, the pose follows the prior along it. After missed frames (lost, or
  // a gap in `utime` of at least one and a half times the median interval) it tries from
  // the prior first, against the model seen from there (the last pose's view may overlap the
  // frame little by then), then from the last pose, both with widened gates, then from the
  // keyframes most like it (relocalisation). Tracked frames that show something new become
  // keyframes.
  FrameResult processFrame(ImageView<const uint16_t> raw_depth, int64_t utime,
                           const Pose* T_world_cam_prior = nullptr);
  // Tracks the frame against the model as seen from a pose guess, then fuses it: the ground
  // station refines a keyframe starting from the drone's onboard pose. Keyframes are far apart,
  // so the model is raycast from the guess rather than from the last fused pose, which would
  // overlap the new view less. The first frame is fused at the guess.
  FrameResult processFrameFromGuess(ImageView<const uint16_t> raw_depth, int64_t utime,
                                    const Pose& T_world_cam_guess);
  // Fuses the frame at a given pose (motion capture, or a ground-station correction).
  FrameResult processFrameAtPose(ImageView<const uint16_t> raw_depth, int64_t utime,
                                 const Pose& T_world_cam);

  const Pose& pose() const { return T_world_cam_; }
  const PinholeCamera& camera() const { return preprocessor_.camera(); }
  // The raw depth images' camera, before any downsampling.
  const PinholeCamera& inputCamera() const { return preprocessor_.inputCamera(); }
  const DepthFrame& frame() const { return frame_; }
  const ModelMaps& model() const { return model_; }
  // Lambertian render of the model from the latest pose: a full raycast, every pixel, on demand
  // (the per-frame model maps only cover the pixels measured), at camera()'s size.
  void renderShaded(ImageView<uint8_t> out);
  // The same from the per-frame model maps, only where the latest frame measured depth but
  // without another raycast. After processFrameFromGuess these maps are the prediction from
  // that frame's guess, which the frame was registered against; processFrameAtPose leaves them
  // as the last prediction made (empty where only given poses were fused). At the model's size,
  // model().camera[0] (camera()'s unless Params::model_level > 0).
  void shadeModel(ImageView<uint8_t> out) const;

 private:
  // Fills the result's first fields; false when the frame has too little depth to use.
  bool preprocess(ImageView<const uint16_t> raw_depth, int64_t utime, const Pose& T_world_cam,
                  FrameResult* result);
  // Raycasts model_ from a pose, masked by the current frame's depth.
  void predict(const Pose& T_world_cam, FrameResult* result);
  // ICP against model_, which was raycast from T_world_ref, from a guess of the pose relative to
  // it (a prior: IcpTracker::track); fuses on success.
  // With `T_world_cam_near`, a pose farther from it than the (unwidened) jump gates is lost,
  // before anything is fused.
  FrameResult trackAndFuse(FrameResult result, const Pose& T_world_ref,
                           const Pose& T_ref_cur_guess, bool prior, bool predict_from_pose,
                           float gate_scale = 1.f, const Pose* T_world_cam_near = nullptr);
  // After every other try lost the frame (`lost` says why): tracks from the poses of the
  // keyframes most like it; with a prior, only to a pose that agrees with it within the jump
  // gates.
  FrameResult relocalise(FrameResult lost, const Pose* T_world_cam_prior);
  // Counts a lost frame with depth; the one that reaches new_map_after_failed_frames, with a
  // prior, begins a new map at it instead of being lost.
  FrameResult failedOrNewMap(FrameResult lost, const Pose* T_world_cam_prior);
  static constexpr int kRelocaliseCandidates = 2;  // ICP runs at most this many times more
  // Frames missed since the last tracked one, from the gap between `utime` and the last frame's
  // in units of the median of the latest intervals; 0 until a few intervals are known.
  int undeliveredBefore(int64_t utime);
  static constexpr int kIntervals = 15, kMinIntervals = 3;
  // Counts of missed frames stop here: only the gates' scale (capped far lower) and reports read
  // them, and a long loss must not overflow.
  static constexpr int kMaxMissedCounted = 100000;
  // Integrates at result.T_world_cam; with predict_from_pose, raycasts model_ from there for
  // the next frame to track against.
  FrameResult fuse(FrameResult result, bool predict_from_pose);
  // The median depth of the frame's coarsest level (0 without depth), where a volume that
  // follows the camera centres itself (TsdfVolume::followCamera).
  float medianViewDepthM();

  Params params_;
  TsdfVolume* volume_;
  DepthPreprocessor preprocessor_;
  IcpTracker tracker_;
  TsdfIntegrator integrator_;
  Raycaster raycaster_;
  // Only with params_.relocalise: its keyframes' codes and poses are reserved at construction
  // (0.6 MB at the defaults), which a pipeline without relocalisation should not hold.
  std::optional<Relocaliser> relocaliser_;
  DepthFrame frame_;
  std::vector<float> view_depths_;  // medianViewDepthM's, sized once for a following volume
  ModelMaps model_;
  // Allocated by the first renderShaded(), raycaster_ serving where the model is full-size.
  std::unique_ptr<Raycaster> render_raycaster_;
  std::unique_ptr<ModelMaps> render_maps_;
  bool has_model_ = false;
  bool model_at_pose_ = false;  // model_ was raycast from T_world_cam_
  int lost_in_a_row_ = 0;        // processFrame's frames lost since the last fused one
  int missed_ = 0;               // those and the frames not delivered between them
  int failed_since_tracked_ = 0;  // of those lost, the frames with depth
  int64_t last_utime_ = -1;      // processFrame's last frame, tracked or not
  std::array<int64_t, kIntervals> intervals_{};  // [us] the latest intervals between its frames
  int interval_count_ = 0;
  // Latest fused pose. The model maps are raycast from it, except after a lost frame that was
  // tried from another view (the prior, a keyframe): model_at_pose_ says which.
  Pose T_world_cam_ = Pose::Identity();
};

}  // namespace kinfly
