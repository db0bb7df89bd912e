// The queue between the capture thread and the odometry: fixed capacity, and when full the
// oldest item is dropped (and counted), so a slow consumer always gets the newest frames and the
// producer never blocks. Items are moved through preallocated slots: with types that keep their
// buffers when moved (Image), nothing allocates once every slot has held a frame.
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <utility>
#include <vector>

namespace kinfly::fw {

template <class T>
class BoundedQueue {
 public:
  explicit BoundedQueue(size_t capacity) : slots_(capacity == 0 ? 1 : capacity) {}
  // Every slot starts as make(): items whose buffers are allocated here never allocate later.
  template <class Make>
  BoundedQueue(size_t capacity, Make make) : BoundedQueue(capacity) {
    for (T& slot : slots_) slot = make();
  }

  // Swaps `item` into the queue; `item` comes back holding a stale slot's contents (reuse its
  // buffers). Returns false when the queue was full and its oldest item was dropped.
  bool push(T& item) {
    bool kept_all = true;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (closed_) return true;
      if (size_ == slots_.size()) {
        head_ = (head_ + 1) % slots_.size();
        --size_;
        ++dropped_;
        kept_all = false;
      }
      std::swap(slots_[(head_ + size_) % slots_.size()], item);
      ++size_;
    }
    ready_.notify_one();
    return kept_all;
  }

  // Swaps the oldest item into *item. Waits up to `timeout`; false on timeout or when closed and
  // empty.
  template <class Rep, class Period>
  bool pop(T* item, std::chrono::duration<Rep, Period> timeout) {
    std::unique_lock<std::mutex> lock(mutex_);
    if (!ready_.wait_for(lock, timeout, [this] { return size_ > 0 || closed_; })) return false;
    if (size_ == 0) return false;
    std::swap(slots_[head_], *item);
    head_ = (head_ + 1) % slots_.size();
    --size_;
    return true;
  }

  // Wakes every waiting pop(); later pushes are ignored.
  void close() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      closed_ = true;
    }
    ready_.notify_all();
  }

  int64_t dropped() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return dropped_;
  }
  size_t size() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return size_;
  }
  size_t capacity() const { return slots_.size(); }

 private:
  mutable std::mutex mutex_;
  std::condition_variable ready_;
  std::vector<T> slots_;
  size_t head_ = 0, size_ = 0;
  int64_t dropped_ = 0;
  bool closed_ = false;
};

}  // namespace kinfly::fw
