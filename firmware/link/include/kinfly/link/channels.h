// LCM channel names: the one place the C++ side spells them (ground/kinfly_ground/channels.py is
// the Python one; proto/README.md is the table both follow). Every channel carries the vehicle id,
// so several drones can share one network: KINFLY_<vehicle id>_<KIND>.
#pragma once

#include <optional>
#include <string>

namespace kinfly::link {

enum class Channel {
  kDepth,         // depth_keyframe_t, every captured frame (flight logs only)
  kKeyframe,      // depth_keyframe_t, keyframes with the onboard pose (drone -> ground)
  kOdometry,      // odometry_t (drone -> ground)
  kImu,           // imu_t (drone -> ground)
  kStatus,        // status_t, the drone's (drone -> ground)
  kCorrection,    // signed_t around pose_correction_t (ground -> drone)
  kGroundStatus,  // status_t, the ground station's (ground -> drone)
  kGroundTruth,   // pose_t, in converted datasets only
};

constexpr int kMaxVehicleId = 65535;  // ids are 0..kMaxVehicleId

std::string channelName(Channel channel, int vehicle_id);

struct ParsedChannel {
  Channel channel;
  int vehicle_id;
};
// Parses a kinfly channel name; nullopt for anything else (another vehicle's channels parse).
std::optional<ParsedChannel> parseChannel(const std::string& name);

// Regular expression (LCM subscription syntax) matching every kinfly channel of one vehicle.
std::string vehicleChannelsRegex(int vehicle_id);

}  // namespace kinfly::link
