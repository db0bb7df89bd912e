#include "publisher.h"

#include <poll.h>
#include <pthread.h>
#include <spdlog/spdlog.h>

#include <cstring>

namespace kinfly::fw {
namespace {

// LCM's receive thread takes the name of the thread that started it. Under the owner's name, a
// per-thread count (the control task's allocations, tests/firmware/test_control_task.py) would
// charge LCM's receive buffers to the owner; so it starts under a name of its own.
class ThreadNamedWhileLcmStarts {
 public:
  explicit ThreadNamedWhileLcmStarts(const std::string& owner) {
    pthread_getname_np(pthread_self(), saved_, sizeof(saved_));
    const std::string name = ("lcm-" + owner).substr(0, 15);  // the kernel's limit
    pthread_setname_np(pthread_self(), name.c_str());
  }
  ~ThreadNamedWhileLcmStarts() { pthread_setname_np(pthread_self(), saved_); }
  ThreadNamedWhileLcmStarts(const ThreadNamedWhileLcmStarts&) = delete;
  ThreadNamedWhileLcmStarts& operator=(const ThreadNamedWhileLcmStarts&) = delete;

 private:
  char saved_[16] = {};
};

}  // namespace

Publisher::Publisher(std::string name, const std::string& url, int vehicle_id,
                     std::function<void(lcm::LCM&)> on_start, UnicastPeers peers)
    : name_(std::move(name)), url_(url), target_(link::multicastTarget(url)),
      on_start_(std::move(on_start)), on_peer_message_(std::move(peers.on_message)) {
  for (size_t i = 0; i < channels_.size(); ++i)
    channels_[i] = link::channelName(static_cast<link::Channel>(i), vehicle_id);
  if (!peers.addresses.empty()) {
    // Only this vehicle's channels that the ground sends: nothing else has a handler here.
    // A publisher that only sends keeps the kernel's receive buffer.
    const int receive_buffer_bytes = peers.listen_port == 0 ? 0 : 4 << 20;
    peer_ = std::make_unique<link::PeerLink>(
        std::move(peers.addresses), peers.listen_port,
        [vehicle_id](std::string_view channel) {
          const auto parsed = link::parseChannel(channel);
          return parsed && parsed->vehicle_id == vehicle_id && link::sentByGround(parsed->channel);
        },
        receive_buffer_bytes);
  }
  maintain();
}

Status Publisher::checkPeerUrl(const std::string& url) {
  const auto target = link::multicastTarget(url);
  if (target && target->ttl > 0)
    return Status::error("link.lcm_url \"" + url + "\" sends multicast off the drone (ttl=" +
                         std::to_string(target->ttl) +
                         "); with link.peers it must stay on it (memq://, or ttl=0), else every "
                         "message crosses the Wi-Fi twice");
  return Status();
}

Status Publisher::checkUrl(const std::string& url) {
  if (const auto target = link::multicastTarget(url)) {
    const Status valid = link::checkMulticastTarget(*target);
    if (valid.ok()) return valid;
    return Status::error("link.lcm_url \"" + url + "\": " + valid.message());
  }
  // Providers without a network (memq://, file://) start at once, or never.
  if (lcm::LCM(url).good()) return Status();
  return Status::error("LCM cannot start on \"" + url + "\" (link.lcm_url)");
}

void Publisher::maintain() {
  if (up() || Clock::now() < next_attempt_) return;
  std::string problem;
  if (!lcm_) {
    // Only when the kernel has a route: LCM itself would print a page of advice on every try.
    const Status route = target_ ? link::checkMulticastRoute(*target_) : Status();
    problem = route.ok() ? std::string() : route.message();
    if (route.ok()) {
      ThreadNamedWhileLcmStarts naming(name_);
      auto lcm = std::make_unique<lcm::LCM>(url_);
      if (lcm->good()) {
        lcm_ = std::move(lcm);
        if (on_start_) {
          on_start_(*lcm_);
          // udpm starts its receive thread at the first subscription or this, whichever comes
          // first: here, under the name above. A publisher that only sends has none.
          lcm_->getFileno();
        }
      } else {
        problem = "LCM cannot start on \"" + url_ + "\" (link.lcm_url)";
      }
    }
  }
  if (lcm_ && peer_) {
    // A peer's name may resolve only once the Wi-Fi is up.
    const Status opened = peer_->open();
    if (!opened.ok()) problem = "unicast: " + opened.message();
  }
  if (up()) {
    if (!started_once_)
      spdlog::info("{}: LCM started on \"{}\"{}", name_, url_,
                   peer_ ? fmt::format(", unicast to {} peer(s) from UDP port {}",
                                       peer_->peerCount(), peer_->listenPort())
                         : std::string());
    started_once_ = true;
    last_problem_.clear();
    return;
  }
  scheduleRetry();
  // One line when the reason changes, not one per attempt: a drone without Wi-Fi for an hour
  // must not fill its log.
  if (problem != last_problem_)
    spdlog::warn("{}: {}: the network is down; nothing is sent, the odometry goes on; retrying "
                 "every {:.1f} s at most",
                 name_, problem, kRetryMaxS);
  was_down_ = true;
  last_problem_ = std::move(problem);
}

bool Publisher::handle(int timeout_ms) {
  if (!up()) return false;
  // A handler's answer may fail and put LCM down: it is released only after the dispatch.
  dispatching_ = true;
  // Everything LCM has queued, not one message a call: at 1 kHz (the control task's IMU) a loop
  // that took one message a wake-up fell behind on a busy machine, and LCM dropped the rest.
  const auto drain = [this](int first_timeout_ms) {
    if (lcm_->handleTimeout(first_timeout_ms) <= 0) return;
    while (!going_down_ && lcm_->handleTimeout(0) > 0) {
    }
  };
  if (!peer_) {
    drain(timeout_ms);
    dispatching_ = false;
    if (going_down_) down();
    return true;
  }
  pollfd ready[2] = {{lcm_->getFileno(), POLLIN, 0}, {peer_->fd(), POLLIN, 0}};
  if (poll(ready, 2, timeout_ms) <= 0) {
    dispatching_ = false;
    return true;
  }
  if (ready[0].revents != 0) drain(0);
  if (ready[1].revents != 0 && on_peer_message_) {
    peer_->receive([this](const char* channel, const uint8_t* data, size_t size) {
      lcm_recv_buf_t message{};
      message.data = const_cast<uint8_t*>(data);
      message.data_size = static_cast<uint32_t>(size);
      message.recv_utime = link::wallClockUtime();
      on_peer_message_(&message, channel);
    });
  }
  dispatching_ = false;
  if (going_down_) down();
  return true;
}

bool Publisher::sendToPeers(const std::string& channel, int size) {
  if (peer_->send(channel, buffer_.data(), static_cast<size_t>(size))) {
    if (peer_failing_) spdlog::info("{}: unicast: the peers take messages again", name_);
    peer_failing_ = false;
    return true;
  }
  // Not put down: the socket stays good while the route comes back (the Wi-Fi at boot).
  if (!peer_failing_)
    spdlog::warn("{}: unicast: no peer takes messages ({}); nothing is sent until one does",
                 name_, std::strerror(peer_->lastSendError()));
  peer_failing_ = true;
  return false;
}

int64_t Publisher::linkBytes(link::Channel channel, int size) const {
  // IPv4 and UDP, LCM's small-message header, the channel and its NUL: one datagram each.
  constexpr int64_t kHeaderBytes = 20 + 8 + 8 + 1;
  const int64_t datagram = kHeaderBytes + static_cast<int64_t>(channels_[static_cast<size_t>(channel)].size()) + size;
  return datagram * static_cast<int64_t>(peer_ ? peer_->peerCount() : 1);
}

void Publisher::down() {
  going_down_ = dispatching_;
  if (!dispatching_) lcm_.reset();
  scheduleRetry();
  if (!was_down_)
    spdlog::warn("{}: LCM cannot send: the network is down; nothing is sent until it is back",
                 name_);
  was_down_ = true;
}

void Publisher::sentAgain() {
  was_down_ = false;
  backoff_.reset();
  spdlog::info("{}: the network is back", name_);
}

void Publisher::scheduleRetry() {
  next_attempt_ = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                     std::chrono::duration<double>(backoff_.next()));
}

UnicastPeers unicastPeers(const LinkConfig& link, uint16_t listen_port,
                          MessageHandler on_message) {
  UnicastPeers peers;
  // LinkConfig::validate has refused peers that do not parse.
  static_cast<void>(link::parsePeers(link.peers, &peers.addresses));
  peers.listen_port = listen_port;
  peers.on_message = std::move(on_message);
  return peers;
}

}  // namespace kinfly::fw
