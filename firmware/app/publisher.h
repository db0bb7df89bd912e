// Publishing from one thread without allocating: each thread that sends owns a Publisher with
// its own LCM instance (its own socket, so a keyframe filling the Wi-Fi send buffer never holds
// up an odometry pose) and an encode buffer that grows to the largest message once.
// lcm::LCM::publish(channel, message) would allocate a buffer for every message.
//
// The network may not be there: the Wi-Fi is not up yet at boot, the drone flew out of range,
// there is no multicast route. A Publisher is made whatever the network does; while LCM cannot
// run it is down, publish() returns false (the caller counts what was not sent), and it starts
// LCM again, with backoff, once the kernel has a route to the group. A failed send also puts it
// down: the next start makes fresh sockets, whose multicast membership follows the interface
// that carries the route then.
#pragma once

#include <lcm/lcm-cpp.hpp>

#include <array>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "kinfly/fw/backoff.h"
#include "kinfly/link/channels.h"
#include "kinfly/link/multicast.h"
#include "runtime.h"

namespace kinfly::fw {

class Publisher {
 public:
  // [s] retries after the network went away: soon at first (a send that failed once), then
  // every few seconds at most (a Wi-Fi that is not configured at all).
  static constexpr double kRetryMinS = 0.1, kRetryMaxS = 5.0;

  // Ok when LCM can use `url` once the network is there, else what is wrong with it (a
  // configuration error: waiting cannot mend it).
  static Status checkUrl(const std::string& url);

  // `name` starts its log lines. `on_start` runs after every start of LCM, on the owner's
  // thread (the link subscribes there).
  Publisher(std::string name, const std::string& url, int vehicle_id,
            std::function<void(lcm::LCM&)> on_start = {});

  // Starts LCM if it is down and an attempt is due; cheap otherwise. Owner's thread only.
  void maintain();
  // Whether LCM runs and no send has failed since it started.
  bool up() const { return lcm_ != nullptr; }
  // The running instance, nullptr while down.
  lcm::LCM* lcm() { return lcm_.get(); }

  // False when the message could not be encoded or sent (the network is down); the caller
  // counts it.
  template <class Message>
  bool publish(link::Channel channel, const Message& message) {
    maintain();
    if (!lcm_) return false;
    const int size = message.getEncodedSize();
    if (size <= 0) return false;
    if (buffer_.size() < static_cast<size_t>(size)) buffer_.resize(static_cast<size_t>(size));
    if (message.encode(buffer_.data(), 0, size) != size) return false;
    if (lcm_->publish(channels_[static_cast<size_t>(channel)], buffer_.data(),
                      static_cast<unsigned>(size)) != 0) {
      down();
      return false;
    }
    if (was_down_) sentAgain();
    return true;
  }

  const std::string& channel(link::Channel channel) const {
    return channels_[static_cast<size_t>(channel)];
  }

 private:
  void down();
  void sentAgain();
  void scheduleRetry();

  std::string name_, url_;
  std::optional<link::MulticastTarget> target_;
  std::function<void(lcm::LCM&)> on_start_;
  std::unique_ptr<lcm::LCM> lcm_;
  Backoff backoff_{kRetryMinS, kRetryMaxS};
  Clock::time_point next_attempt_{};
  std::string last_problem_;
  bool started_once_ = false;
  bool was_down_ = false;  // since the last message that went out
  std::array<std::string, link::kChannelCount> channels_;
  std::vector<uint8_t> buffer_;
};

}  // namespace kinfly::fw
