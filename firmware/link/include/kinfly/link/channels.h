// LCM channel names: the one place they are spelled (LCM constants cannot be strings, so not in
// proto/; the ground station gets them through its native module; proto/README.md has the
// table). Every channel carries the vehicle id, so several drones can share one network:
// KINFLY_<vehicle id>_<KIND>.
#pragma once

#include <cstddef>
#include <optional>
#include <string>
#include <string_view>
#include <utility>

namespace kinfly::link {

enum class Channel {
  kDepth,         // depth_keyframe_t, every captured frame (flight logs only)
  kKeyframe,      // depth_keyframe_t, keyframes with the onboard pose (drone -> ground)
  kOdometry,      // odometry_t (drone -> ground)
  kImu,           // imu_t (drone -> ground; simulator -> drone, the control task's IMU)
  kStatus,        // drone_status_t (drone -> ground)
  kCorrection,    // signed_t around pose_correction_t (ground -> drone)
  kGroundStatus,  // ground_status_t (ground -> drone)
  kGroundTruth,   // ground_truth_t, in converted datasets and from the simulator
  kKeyframeChunk, // keyframe_chunk_t, keyframes cut into FEC-coded datagrams (drone -> ground)
  kChunkRequest,  // chunk_request_t, resends the ground asks for (ground -> drone)
  kMotorCommand,  // motor_command_t, the control task's rotor speeds (drone -> simulator/ESCs)
  kCommand,       // signed_t around flight_command_t (ground -> drone)
  kFlight,        // flight_status_t, the flight stack's state (drone -> ground)
  kSimState,      // sim_state_t, the simulated vehicle's true state (kinfly-sim -> ground, logs)
};
// Channels are numbered from 0 in the order above (arrays of per-channel names index by it).
constexpr size_t kChannelCount = static_cast<size_t>(Channel::kSimState) + 1;

constexpr int kMaxVehicleId = 65535;  // ids are 0..kMaxVehicleId

std::string channelName(Channel channel, int vehicle_id);

struct ParsedChannel {
  Channel channel;
  int vehicle_id;
};
// Parses a kinfly channel name; nullopt for anything else (another vehicle's channels parse).
std::optional<ParsedChannel> parseChannel(std::string_view name);

// Whether the ground station sends on the channel (to the drone); every other channel the
// drone sends, or a converted dataset or the simulator.
bool sentByGround(Channel channel);

// Regular expression (LCM subscription syntax) matching every kinfly channel of one vehicle.
std::string vehicleChannelsRegex(int vehicle_id);

// The ground station's two subscriptions (LCM anchors the patterns), so that keyframes have a
// queue of their own: one vehicle's keyframes (whole or in chunks) and its other channels, or
// every vehicle's when vehicle_id is nullopt.
struct Subscriptions {
  std::string keyframes, others;
};
Subscriptions groundSubscriptions(std::optional<int> vehicle_id);

}  // namespace kinfly::link
