#include "kinfly/link/conversions.h"

namespace kinfly::link {

void writePose(const Pose& T_world_cam, pose3d_t* message) {
  std::array<double, 7> t_q = poseToTum(T_world_cam);
  const double sign = t_q[6] < 0.0 ? -1.0 : 1.0;  // q and -q are the same rotation
  for (int i = 0; i < 3; ++i) message->position_m[i] = t_q[i];
  for (int i = 0; i < 4; ++i) message->orientation_xyzw[i] = sign * t_q[3 + i];
}

Pose readPose(const pose3d_t& message) {
  const double* p = message.position_m;
  const double* q = message.orientation_xyzw;
  return poseFromTum({p[0], p[1], p[2], q[0], q[1], q[2], q[3]});
}

camera_t cameraMessage(const PinholeCamera& camera) {
  camera_t message;
  message.width = camera.width;
  message.height = camera.height;
  message.fx = camera.fx;
  message.fy = camera.fy;
  message.cx = camera.cx;
  message.cy = camera.cy;
  return message;
}

PinholeCamera cameraOf(const camera_t& m) { return {m.fx, m.fy, m.cx, m.cy, m.width, m.height}; }

PinholeCamera cameraOf(const depth_keyframe_t& message) { return cameraOf(message.camera); }

int8_t trackingCode(std::optional<TrackingStatus> status) {
  if (!status) return odometry_t::TRACKING_NONE;
  switch (*status) {
    case TrackingStatus::kFirstFrame: return odometry_t::TRACKING_FIRST;
    case TrackingStatus::kOk: return odometry_t::TRACKING_OK;
    case TrackingStatus::kLost: return odometry_t::TRACKING_LOST;
    case TrackingStatus::kGivenPose: return odometry_t::TRACKING_GIVEN;
  }
  return odometry_t::TRACKING_NONE;
}

std::optional<TrackingStatus> trackingOf(int8_t code) {
  switch (code) {
    case odometry_t::TRACKING_FIRST: return TrackingStatus::kFirstFrame;
    case odometry_t::TRACKING_OK: return TrackingStatus::kOk;
    case odometry_t::TRACKING_LOST: return TrackingStatus::kLost;
    case odometry_t::TRACKING_GIVEN: return TrackingStatus::kGivenPose;
    default: return std::nullopt;
  }
}

void fillOdometry(const FrameResult& result, int64_t frame_id, const Pose& T_world_cam,
                  int32_t reset_counter, odometry_t* message) {
  message->utime = result.utime;
  message->frame_id = frame_id;
  writePose(T_world_cam, &message->T_world_cam);
  message->tracking_status = trackingCode(result.status);
  message->inlier_fraction = result.inlier_fraction;
  message->residual_m = result.rmse_m;
  message->reset_counter = reset_counter;
}

void fillGroundTruth(int64_t utime, const Pose& T_world_cam, ground_truth_t* message) {
  message->utime = utime;
  writePose(T_world_cam, &message->T_world_cam);
}

void fillKeyframe(const KeyframeHeader& header, depth_keyframe_t* message) {
  message->utime = header.utime;
  message->frame_id = header.frame_id;
  message->keyframe_id = header.keyframe_id;
  writePose(header.T_world_cam, &message->T_world_cam);
  message->tracking_status = trackingCode(header.tracking);
}

void fillCorrection(int32_t vehicle_id, const KeyframeHeader& keyframe, const Pose& T_corrected,
                    int32_t reset_counter, pose_correction_t* message) {
  message->utime = keyframe.utime;
  message->vehicle_id = vehicle_id;
  message->keyframe_id = keyframe.keyframe_id;
  writePose(T_corrected, &message->T_world_cam);
  message->reset_counter = reset_counter;
}

void fillDroneStatus(const DroneHealth& h, drone_status_t* message) {
  drone_status_t& s = *message;
  s.utime = h.utime;
  s.run_state = h.is_final ? drone_status_t::RUN_FINAL : drone_status_t::RUN_ACTIVE;
  s.depth_rate_hz = h.depth_rate_hz;
  s.odometry_rate_hz = h.odometry_rate_hz;
  s.keyframe_rate_hz = h.keyframe_rate_hz;
  s.frames_captured = h.frames_captured;
  s.queue_drops = h.queue_drops;
  s.keyframes_sent = h.keyframes_sent;
  s.keyframes_dropped = h.keyframes_dropped;
  s.last_keyframe_id = h.last_keyframe_id;
  s.send_budget_bps = h.send_budget_bps;
  s.redundancy = h.redundancy;
  s.keyframe_scale = static_cast<int8_t>(h.keyframe_scale);
  s.chunks_sent = h.chunks_sent;
  s.chunks_resent = h.chunks_resent;
  s.keyframes_skipped = h.keyframes_skipped;
  s.tracking_state = trackingCode(h.tracking);
  switch (h.link) {
    case LinkState::kUnknown: s.link_state = drone_status_t::LINK_UNKNOWN; break;
    case LinkState::kUp: s.link_state = drone_status_t::LINK_UP; break;
    case LinkState::kStale: s.link_state = drone_status_t::LINK_STALE; break;
  }
  switch (h.sensor) {
    case SensorState::kStreaming: s.sensor_state = drone_status_t::SENSOR_STREAMING; break;
    case SensorState::kWaiting: s.sensor_state = drone_status_t::SENSOR_WAITING; break;
    case SensorState::kStalled: s.sensor_state = drone_status_t::SENSOR_STALLED; break;
    case SensorState::kEnded: s.sensor_state = drone_status_t::SENSOR_ENDED; break;
  }
  s.sensor_connects = h.sensor_connects;
  s.sensor_stalls = h.sensor_stalls;
  s.frames_skipped = h.frames_skipped;
  s.frames_lost = h.frames_lost;
  h.rejects.writeTo(&s);
  s.corrections_accepted = h.corrections_accepted;
  s.corrections_unknown_keyframe = h.corrections_unknown_keyframe;
  s.commands_passed = h.commands_passed;
}

CodecResult encodeDepth(DepthCodec& codec, ImageView<const uint16_t> raw,
                        const PinholeCamera& camera, double depth_scale_m,
                        depth_keyframe_t* message) {
  PinholeCamera sized = camera;
  sized.width = raw.width();
  sized.height = raw.height();
  message->camera = cameraMessage(sized);
  message->depth_scale_m = depth_scale_m;
  message->encoding = static_cast<int8_t>(codec.params().encoding);
  const CodecResult result = codec.encode(raw, &message->payload);
  message->payload_size = static_cast<int32_t>(message->payload.size());
  return result;
}

CodecResult decodeDepth(DepthCodec& codec, const depth_keyframe_t& message,
                        Image<uint16_t>* raw) {
  return codec.decode(message.payload.data(), message.payload.size(),
                      static_cast<DepthEncoding>(message.encoding), message.camera.width,
                      message.camera.height, raw);
}

}  // namespace kinfly::link
