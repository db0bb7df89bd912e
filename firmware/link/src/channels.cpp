#include "kinfly/link/channels.h"

#include <array>
#include <charconv>
#include <utility>

namespace kinfly::link {
namespace {

constexpr const char* kPrefix = "KINFLY_";

constexpr std::array<std::pair<Channel, const char*>, kChannelCount> kKinds{{
    {Channel::kDepth, "DEPTH"},
    {Channel::kKeyframe, "KEYFRAME"},
    {Channel::kOdometry, "ODOMETRY"},
    {Channel::kImu, "IMU"},
    {Channel::kStatus, "STATUS"},
    {Channel::kCorrection, "CORRECTION"},
    {Channel::kGroundStatus, "GROUND_STATUS"},
    {Channel::kGroundTruth, "GROUND_TRUTH"},
    {Channel::kKeyframeChunk, "KEYFRAME_CHUNK"},
    {Channel::kChunkRequest, "CHUNK_REQUEST"},
    {Channel::kMotorCommand, "MOTOR_COMMAND"},
    {Channel::kCommand, "COMMAND"},
    {Channel::kFlight, "FLIGHT"},
    {Channel::kSimState, "SIM_STATE"},
}};

}  // namespace

std::string channelName(Channel channel, int vehicle_id) {
  for (const auto& [kind, suffix] : kKinds)
    if (kind == channel) return kPrefix + std::to_string(vehicle_id) + "_" + suffix;
  return {};
}

std::optional<ParsedChannel> parseChannel(std::string_view name) {
  const std::string_view prefix = kPrefix;
  if (name.substr(0, prefix.size()) != prefix) return std::nullopt;
  name.remove_prefix(prefix.size());
  int vehicle_id = 0;
  const auto [digits_end, error] =
      std::from_chars(name.data(), name.data() + name.size(), vehicle_id);
  // At most 5 digits and no leading zero, so every id has exactly one name.
  const size_t digits = static_cast<size_t>(digits_end - name.data());
  if (error != std::errc() || name[0] == '-' || name[0] == '+' || digits > 5 ||
      (digits > 1 && name[0] == '0'))
    return std::nullopt;
  if (digits >= name.size() || name[digits] != '_') return std::nullopt;
  if (vehicle_id > kMaxVehicleId) return std::nullopt;
  const std::string_view suffix = name.substr(digits + 1);
  for (const auto& [kind, kind_suffix] : kKinds)
    if (suffix == kind_suffix) return ParsedChannel{kind, vehicle_id};
  return std::nullopt;
}

bool sentByGround(Channel channel) {
  return channel == Channel::kCorrection || channel == Channel::kGroundStatus ||
         channel == Channel::kChunkRequest || channel == Channel::kCommand;
}

std::string vehicleChannelsRegex(int vehicle_id) {
  return kPrefix + std::to_string(vehicle_id) + "_.*";
}

Subscriptions groundSubscriptions(std::optional<int> vehicle_id) {
  const std::string vehicle = kPrefix + (vehicle_id ? std::to_string(*vehicle_id) : "[0-9]+") + "_";
  const std::string keyframes = "KEYFRAME(_CHUNK)?";
  return {vehicle + keyframes, vehicle + "(?!" + keyframes + "$).*"};
}

}  // namespace kinfly::link
