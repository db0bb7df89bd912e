// Conversions between messages and the engine's types: the C++ side's one conversion file
// (ground/kinfly_ground/conversions.py is the Python one).
#pragma once

#include <cstdint>

#include "kinfly/core/camera.h"
#include "kinfly/codec/depth_codec.h"
#include "kinfly/depth_keyframe_t.hpp"
#include "kinfly/core/image.h"
#include "kinfly/core/se3.h"

namespace kinfly::link {

// A message's (position_m, orientation_xyzw) pair <-> T_world_cam.
void writePose(const Pose& T_world_cam, double position_m[3], double orientation_xyzw[4]);
Pose readPose(const double position_m[3], const double orientation_xyzw[4]);

PinholeCamera cameraOf(const depth_keyframe_t& message);

// Fills the image part of a keyframe message (size, intrinsics, depth scale, encoding, payload)
// from raw sensor depth; ids, time and pose are the caller's. The payload vector keeps its
// capacity, so a message reused across frames stops allocating.
CodecResult encodeDepth(DepthCodec& codec, ImageView<const uint16_t> raw,
                        const PinholeCamera& camera, double depth_scale_m,
                        depth_keyframe_t* message);

// Decodes a keyframe message's payload (decoded within bounds already) into raw depth.
CodecResult decodeDepth(DepthCodec& codec, const depth_keyframe_t& message,
                        Image<uint16_t>* raw);

}  // namespace kinfly::link
