// Retry intervals after losing a device: short at first (a loose cable comes back at once), then
// doubling to a ceiling, so a sensor that is gone for good costs one attempt every few seconds
// instead of a busy loop; back to the shortest once it is found.
#pragma once

#include <algorithm>

namespace kinfly::fw {

class Backoff {
 public:
  Backoff(double min_s, double max_s) : min_s_(min_s), max_s_(max_s), next_s_(min_s) {}

  // [s] the wait before the next attempt; each call doubles the one after, up to max_s.
  double next() {
    const double wait_s = next_s_;
    next_s_ = std::min(2.0 * next_s_, max_s_);
    return wait_s;
  }
  void reset() { next_s_ = min_s_; }

 private:
  double min_s_, max_s_, next_s_;
};

}  // namespace kinfly::fw
