#include "kinfly/link/channels.h"

#include <array>
#include <cstdlib>
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
}};

}  // namespace

std::string channelName(Channel channel, int vehicle_id) {
  for (const auto& [kind, suffix] : kKinds)
    if (kind == channel) return kPrefix + std::to_string(vehicle_id) + "_" + suffix;
  return {};
}

std::optional<ParsedChannel> parseChannel(const std::string& name) {
  const std::string prefix = kPrefix;
  if (name.compare(0, prefix.size(), prefix) != 0) return std::nullopt;
  size_t pos = prefix.size();
  size_t digits_end = pos;
  while (digits_end < name.size() && name[digits_end] >= '0' && name[digits_end] <= '9')
    ++digits_end;
  // At most 5 digits and no leading zero, so every id has exactly one name.
  const size_t digits = digits_end - pos;
  if (digits == 0 || digits > 5 || (digits > 1 && name[pos] == '0')) return std::nullopt;
  if (digits_end >= name.size() || name[digits_end] != '_') return std::nullopt;
  const int vehicle_id = std::atoi(name.substr(pos, digits).c_str());
  if (vehicle_id > kMaxVehicleId) return std::nullopt;
  const std::string suffix = name.substr(digits_end + 1);
  for (const auto& [kind, kind_suffix] : kKinds)
    if (suffix == kind_suffix) return ParsedChannel{kind, vehicle_id};
  return std::nullopt;
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
