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
//
// With unicast peers (link.peers, docs/wire.md "Unicast on Wi-Fi") every message also goes to
// each peer by UDP unicast, and what the peers send reaches the same handler as LCM's.
#pragma once

#include <lcm/lcm-cpp.hpp>

#include <array>
#include <atomic>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "config.h"
#include "kinfly/fw/backoff.h"
#include "kinfly/link/channels.h"
#include "kinfly/link/multicast.h"
#include "kinfly/link/peer.h"
#include "runtime.h"

namespace kinfly::fw {

using MessageHandler = std::function<void(const lcm_recv_buf_t* message, const char* channel)>;

struct UnicastPeers {
  std::vector<link::PeerAddress> addresses;  // empty: no unicast
  uint16_t listen_port = 0;                  // 0: this publisher only sends
  MessageHandler on_message;                 // what arrives from the peers (listening only)
};

class Publisher {
 public:
  // [s] retries after the network went away: soon at first (a send that failed once), then
  // every few seconds at most (a Wi-Fi that is not configured at all).
  static constexpr double kRetryMinS = 0.1, kRetryMaxS = 5.0;

  // Ok when LCM can use `url` once the network is there, else what is wrong with it (a
  // configuration error: waiting cannot mend it).
  static Status checkUrl(const std::string& url);

  // Ok when `url` suits unicast peers: one that keeps messages on this machine (memq://, or
  // udpm with ttl=0), else every message would cross the Wi-Fi twice.
  static Status checkPeerUrl(const std::string& url);

  // `name` starts its log lines. `on_start` runs after every start of LCM, on the owner's
  // thread (the link subscribes there). The peers' channels are this vehicle's that the ground
  // sends.
  Publisher(std::string name, const std::string& url, int vehicle_id,
            std::function<void(lcm::LCM&)> on_start = {}, UnicastPeers peers = {});

  // Starts LCM (and opens the peers' socket) if down and an attempt is due; cheap otherwise.
  // Owner's thread only.
  void maintain();
  // Whether LCM runs (and the peers' socket is open) and no send has failed since it started.
  bool up() const { return lcm_ != nullptr && !going_down_ && (!peer_ || peer_->isOpen()); }
  // Handles what LCM and the peers deliver within timeout_ms, and all LCM has queued by then;
  // false while down.
  bool handle(int timeout_ms);
  // nullptr without peers.
  const link::PeerLink* peer() const { return peer_.get(); }

  // Adds to *bytes what each message but a keyframe chunk puts on the link (headers and every
  // unicast copy included): the small messages go first, and the keyframes' budget pays for them
  // (docs/wire.md, "Priorities").
  void chargeTo(std::atomic<int64_t>* bytes) { charge_to_ = bytes; }

  // False when the message could not be encoded or sent (the network is down); the caller
  // counts it.
  template <class Message>
  bool publish(link::Channel channel, const Message& message) {
    maintain();
    if (!up()) return false;
    const int size = message.getEncodedSize();
    if (size <= 0) return false;
    if (buffer_.size() < static_cast<size_t>(size)) buffer_.resize(static_cast<size_t>(size));
    if (message.encode(buffer_.data(), 0, size) != size) return false;
    if (lcm_->publish(channels_[static_cast<size_t>(channel)], buffer_.data(),
                      static_cast<unsigned>(size)) != 0) {
      down();
      return false;
    }
    if (peer_ && !sendToPeers(channels_[static_cast<size_t>(channel)], size)) return false;
    if (was_down_) sentAgain();
    if (charge_to_ && channel != link::Channel::kKeyframeChunk)
      charge_to_->fetch_add(linkBytes(channel, size), std::memory_order_relaxed);
    return true;
  }

  const std::string& channel(link::Channel channel) const {
    return channels_[static_cast<size_t>(channel)];
  }

 private:
  void down();
  void sentAgain();
  void scheduleRetry();
  bool sendToPeers(const std::string& channel, int size);
  int64_t linkBytes(link::Channel channel, int size) const;

  std::string name_, url_;
  std::optional<link::MulticastTarget> target_;
  std::function<void(lcm::LCM&)> on_start_;
  std::unique_ptr<lcm::LCM> lcm_;
  std::unique_ptr<link::PeerLink> peer_;
  MessageHandler on_peer_message_;
  bool peer_failing_ = false;  // since the last send a peer took
  // handle() is dispatching (LCM is in use); a send that failed meanwhile put it down, to be
  // released once the dispatch is over.
  bool dispatching_ = false, going_down_ = false;
  std::atomic<int64_t>* charge_to_ = nullptr;
  Backoff backoff_{kRetryMinS, kRetryMaxS};
  Clock::time_point next_attempt_{};
  std::string last_problem_;
  bool started_once_ = false;
  bool was_down_ = false;  // since the last message that went out
  std::array<std::string, link::kChannelCount> channels_;
  std::vector<uint8_t> buffer_;
};

// The unicast peers of the link's configuration (validated at start), listening on
// listen_port (0: sending only) and handing what arrives to on_message.
UnicastPeers unicastPeers(const LinkConfig& link, uint16_t listen_port, MessageHandler on_message);

}  // namespace kinfly::fw
