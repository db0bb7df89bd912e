#include "kinfly/link/conversions.h"

namespace kinfly::link {

void writePose(const Pose& T_world_cam, double position_m[3], double orientation_xyzw[4]) {
  const std::array<double, 7> t_q = poseToTum(T_world_cam);
  for (int i = 0; i < 3; ++i) position_m[i] = t_q[i];
  for (int i = 0; i < 4; ++i) orientation_xyzw[i] = t_q[3 + i];
}

Pose readPose(const double position_m[3], const double orientation_xyzw[4]) {
  return poseFromTum({position_m[0], position_m[1], position_m[2], orientation_xyzw[0],
                      orientation_xyzw[1], orientation_xyzw[2], orientation_xyzw[3]});
}

PinholeCamera cameraOf(const depth_keyframe_t& message) {
  return {message.fx, message.fy, message.cx, message.cy, message.width, message.height};
}

CodecResult encodeDepth(DepthCodec& codec, ImageView<const uint16_t> raw,
                        const PinholeCamera& camera, double depth_scale_m,
                        depth_keyframe_t* message) {
  message->width = raw.width();
  message->height = raw.height();
  message->fx = camera.fx;
  message->fy = camera.fy;
  message->cx = camera.cx;
  message->cy = camera.cy;
  message->depth_scale_m = depth_scale_m;
  message->encoding = static_cast<int8_t>(codec.params().encoding);
  const CodecResult result = codec.encode(raw, &message->payload);
  message->payload_size = static_cast<int32_t>(message->payload.size());
  return result;
}

CodecResult decodeDepth(DepthCodec& codec, const depth_keyframe_t& message,
                        Image<uint16_t>* raw) {
  return codec.decode(message.payload.data(), message.payload.size(),
                      static_cast<DepthEncoding>(message.encoding), message.width,
                      message.height, raw);
}

}  // namespace kinfly::link
