// Conversions between messages and the engine's types: the C++ side's one conversion file, used
// by the drone and, through its native module, by the ground station. Every message field kinfly
// fills in C++ is filled here (ground/kinfly_ground/conversions.py fills the ground's status).
#pragma once

#include <cstdint>
#include <optional>

#include "kinfly/core/camera.h"
#include "kinfly/camera_t.hpp"
#include "kinfly/codec/depth_codec.h"
#include "kinfly/depth_keyframe_t.hpp"
#include "kinfly/drone_status_t.hpp"
#include "kinfly/pipeline/fusion_pipeline.h"
#include "kinfly/ground_truth_t.hpp"
#include "kinfly/frame/tracking_status.h"
#include "kinfly/core/image.h"
#include "kinfly/odometry_t.hpp"
#include "kinfly/pose3d_t.hpp"
#include "kinfly/pose_correction_t.hpp"
#include "kinfly/core/se3.h"
#include "kinfly/link/counters.h"

namespace kinfly::link {

// pose3d_t <-> T_world_cam (the quaternion written with w >= 0).
void writePose(const Pose& T_world_cam, pose3d_t* message);
Pose readPose(const pose3d_t& message);

// camera_t <-> the engine's camera.
camera_t cameraMessage(const PinholeCamera& camera);
PinholeCamera cameraOf(const camera_t& message);
PinholeCamera cameraOf(const depth_keyframe_t& message);

// The engine's tracking status <-> odometry_t::TRACKING_*; TRACKING_NONE (no pose) is nullopt.
int8_t trackingCode(std::optional<TrackingStatus> status);
std::optional<TrackingStatus> trackingOf(int8_t code);

// One odometry result: the frame's id, its pose re-anchored by the corrections (T_world_cam)
// and the anchor's reset counter; vehicle_id is the caller's, set once.
void fillOdometry(const FrameResult& result, int64_t frame_id, const Pose& T_world_cam,
                  int32_t reset_counter, odometry_t* message);

void fillGroundTruth(int64_t utime, const Pose& T_world_cam, ground_truth_t* message);

// A keyframe's ids, time and onboard pose; the image part is encodeDepth's, vehicle_id the
// caller's.
struct KeyframeHeader {
  int64_t utime = 0;        // [us] capture time
  int64_t frame_id = 0;
  int64_t keyframe_id = 0;
  Pose T_world_cam = Pose::Identity();
  std::optional<TrackingStatus> tracking;  // nullopt: no pose (a raw capture)
};
void fillKeyframe(const KeyframeHeader& header, depth_keyframe_t* message);

// The refined pose of one keyframe (the ground's correction, signed before it is sent).
void fillCorrection(int32_t vehicle_id, const KeyframeHeader& keyframe, const Pose& T_corrected,
                    int32_t reset_counter, pose_correction_t* message);

// The drone's state as its status reports it, in the link's own terms: the firmware maps its
// link timeout and its sensor watch (firmware/core) onto these, so the link needs neither.
enum class LinkState { kUnknown, kUp, kStale };                     // drone_status_t::LINK_*
enum class SensorState { kStreaming, kWaiting, kStalled, kEnded };  // drone_status_t::SENSOR_*

// The drone's figures for one status message; counts are totals since kinfly-fw started.
struct DroneHealth {
  int64_t utime = 0;              // [us] when taken, on the drone's wall clock
  bool is_final = false;          // the last status before kinfly-fw exits: its counts are final
  float depth_rate_hz = 0.f;      // [Hz] depth frames captured
  float odometry_rate_hz = 0.f;   // [Hz] frames processed by the odometry
  float keyframe_rate_hz = 0.f;   // [Hz] keyframes sent
  int64_t frames_captured = 0;
  int64_t queue_drops = 0;        // frames the full capture queue dropped
  int64_t keyframes_sent = 0;
  int64_t keyframes_dropped = 0;  // not sent: the link was busy or down
  int64_t last_keyframe_id = -1;  // the highest id sent, -1 before the first
  float send_budget_bps = 0.f;    // [bit/s] what keyframe chunks may use now
  float redundancy = 0.f;         // recovery chunks per original chunk, last keyframe
  int keyframe_scale = 1;         // 1: full-size images, 2: half width and height, ...
  int64_t chunks_sent = 0;        // keyframe chunks, resends included
  int64_t chunks_resent = 0;      // answers to the ground's chunk requests
  int64_t keyframes_skipped = 0;  // not sent: a newer keyframe was ready first
  std::optional<TrackingStatus> tracking;  // the odometry's last verdict; nullopt before a frame
  LinkState link = LinkState::kUnknown;
  SensorState sensor = SensorState::kStreaming;
  int64_t sensor_connects = 0;
  int64_t sensor_stalls = 0;
  int64_t frames_skipped = 0;     // unreadable or undecodable frames
  int64_t frames_lost = 0;        // frames the odometry could not track
  RejectCounters rejects;         // received messages dropped, by reason
  int64_t corrections_accepted = 0;
  int64_t corrections_unknown_keyframe = 0;
  int64_t commands_passed = 0;    // signed flight commands handed to the flight stack
};
// vehicle_id is the caller's, set once.
void fillDroneStatus(const DroneHealth& health, drone_status_t* message);

// Fills the image part of a keyframe message (camera, depth scale, encoding, payload) from raw
// sensor depth. The payload vector keeps its capacity, so a message reused across frames stops
// allocating.
CodecResult encodeDepth(DepthCodec& codec, ImageView<const uint16_t> raw,
                        const PinholeCamera& camera, double depth_scale_m,
                        depth_keyframe_t* message);

// Decodes a keyframe message's payload (decoded within bounds already) into raw depth.
CodecResult decodeDepth(DepthCodec& codec, const depth_keyframe_t& message,
                        Image<uint16_t>* raw);

}  // namespace kinfly::link
