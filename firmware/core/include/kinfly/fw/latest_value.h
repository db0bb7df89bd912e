// The newest value from one writer thread to one reader thread, neither ever waiting for the
// other: a triple buffer. The control task reads the odometry's newest pose through it, so a
// vision thread that is descheduled mid-write can never hold up a 1 kHz tick (a mutex could).
// One slot is the writer's, one the reader's, and the third is handed over by an atomic exchange;
// a value the reader never fetched is overwritten by a newer one, never queued.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>

namespace kinfly::fw {

template <class T>
class LatestValue {
 public:
  LatestValue() = default;
  // Every slot starts as `initial`: types whose buffers are allocated here never allocate later.
  explicit LatestValue(const T& initial) {
    for (Slot& slot : slots_) slot.value = initial;
  }
  LatestValue(const LatestValue&) = delete;
  LatestValue& operator=(const LatestValue&) = delete;

  // Writer only: the slot to fill, then publish() hands it over.
  T& back() { return slots_[back_].value; }
  void publish() {
    // Release: the filled slot is visible to whoever takes it; acquire: the slot received back
    // was released by the reader's last exchange, so nothing reads it any more.
    back_ = middle_.exchange(static_cast<uint8_t>(back_ | kFresh), std::memory_order_acq_rel) &
            kIndex;
  }

  // Reader only: true when a value newer than the last fetched one was published; front() then
  // holds it. front() is stable between fetches.
  bool fetch() {
    if (!(middle_.load(std::memory_order_relaxed) & kFresh)) return false;
    front_ = middle_.exchange(front_, std::memory_order_acq_rel) & kIndex;
    return true;
  }
  const T& front() const { return slots_[front_].value; }

 private:
  static constexpr uint8_t kIndex = 3;  // the low two bits: which slot
  static constexpr uint8_t kFresh = 4;  // set by publish(), cleared by the fetch that takes it
  // A cache line each, so the writer's stores do not keep evicting the reader's slot.
  struct alignas(64) Slot {
    T value{};
  };
  std::array<Slot, 3> slots_;
  std::atomic<uint8_t> middle_{1};
  uint8_t back_ = 0;   // the writer's thread only
  uint8_t front_ = 2;  // the reader's thread only
};

}  // namespace kinfly::fw
