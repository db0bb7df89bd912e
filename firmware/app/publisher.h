// Publishing from one thread without allocating: each thread that sends owns a Publisher with
// its own LCM instance (its own socket, so a keyframe filling the Wi-Fi send buffer never holds
// up an odometry pose) and an encode buffer that grows to the largest message once.
// lcm::LCM::publish(channel, message) would allocate a buffer for every message.
#pragma once

#include <lcm/lcm-cpp.hpp>

#include <array>
#include <memory>
#include <string>
#include <vector>

#include "kinfly/link/channels.h"

namespace kinfly::fw {

class Publisher {
 public:
  // nullptr and *why when LCM cannot start on `url` ("" = LCM_DEFAULT_URL or LCM's default).
  static std::unique_ptr<Publisher> open(const std::string& url, int vehicle_id,
                                         std::string* why);

  // False when the message could not be encoded or LCM could not send it (no route, network
  // down); the caller counts and logs.
  template <class Message>
  bool publish(link::Channel channel, const Message& message) {
    const int size = message.getEncodedSize();
    if (size <= 0) return false;
    if (buffer_.size() < static_cast<size_t>(size)) buffer_.resize(static_cast<size_t>(size));
    if (message.encode(buffer_.data(), 0, size) != size) return false;
    return lcm_.publish(channels_[static_cast<size_t>(channel)], buffer_.data(),
                        static_cast<unsigned>(size)) == 0;
  }

  lcm::LCM& lcm() { return lcm_; }
  const std::string& channel(link::Channel channel) const {
    return channels_[static_cast<size_t>(channel)];
  }

 private:
  Publisher(const std::string& url, int vehicle_id);

  lcm::LCM lcm_;
  std::array<std::string, static_cast<size_t>(link::Channel::kGroundTruth) + 1> channels_;
  std::vector<uint8_t> buffer_;
};

}  // namespace kinfly::fw
