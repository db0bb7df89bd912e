#include "publisher.h"

#include <spdlog/spdlog.h>

namespace kinfly::fw {

Publisher::Publisher(std::string name, const std::string& url, int vehicle_id,
                     std::function<void(lcm::LCM&)> on_start)
    : name_(std::move(name)), url_(url), target_(link::multicastTarget(url)),
      on_start_(std::move(on_start)) {
  for (size_t i = 0; i < channels_.size(); ++i)
    channels_[i] = link::channelName(static_cast<link::Channel>(i), vehicle_id);
  maintain();
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
  if (lcm_ || Clock::now() < next_attempt_) return;
  // Only when the kernel has a route: LCM itself would print a page of advice on every try.
  const Status route = target_ ? link::checkMulticastRoute(*target_) : Status();
  std::string problem = route.ok() ? std::string() : route.message();
  if (route.ok()) {
    auto lcm = std::make_unique<lcm::LCM>(url_);
    if (lcm->good()) {
      lcm_ = std::move(lcm);
      if (on_start_) on_start_(*lcm_);
      if (!started_once_) spdlog::info("{}: LCM started on \"{}\"", name_, url_);
      started_once_ = true;
      last_problem_.clear();
      return;
    }
    problem = "LCM cannot start on \"" + url_ + "\" (link.lcm_url)";
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

void Publisher::down() {
  lcm_.reset();
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

}  // namespace kinfly::fw
