// Faults that repeat every frame (a sensor sending garbage, a ground station gone, a flood of
// forged corrections) must not fill the drone's small disk with log lines: one line at the
// first occurrence, then at most one per period, saying how many were not logged.
#pragma once

#include <cstdint>

namespace kinfly::fw {

class LogThrottle {
 public:
  explicit LogThrottle(double period_s = 1.0) : period_s_(period_s) {}

  // Counts one occurrence at now_s (a monotonic clock). True when it should be logged; then
  // suppressed() tells how many occurrences since the last logged one were not.
  bool allow(double now_s) {
    if (logged_ && now_s - last_logged_s_ < period_s_) {
      ++pending_;
      return false;
    }
    logged_ = true;
    last_logged_s_ = now_s;
    suppressed_ = pending_;
    pending_ = 0;
    return true;
  }
  int64_t suppressed() const { return suppressed_; }

 private:
  double period_s_;
  bool logged_ = false;
  double last_logged_s_ = 0.0;
  int64_t pending_ = 0;
  int64_t suppressed_ = 0;
};

}  // namespace kinfly::fw
