// kinfly's one way to say that something failed and why (docs/engine.md, "Errors").
//
// - A function that can fail and returns nothing else returns `Status` (a Params' validate(),
//   a file write).
// - A function that makes a value or fails returns `StatusOr<T>` (opening a source, loading a
//   key), never a bool or an optional with a `std::string* why` beside it.
// - Per-frame outcomes that are counted and reported (`TrackingStatus`, `CodecStatus`,
//   `DecodeStatus`, `SourceStatus`) stay enums in their result structs: they are data, not
//   errors. Where such a struct also carries a "detail" text, that text is what a `Status`
//   message would say, kept beside the enum for logs.
//
// The message is for people: it names the key or file and the allowed range or the cause
// ("odometry.volume_vox must be a multiple of 8 in [16, 512] (got 100)"); callers prefix
// context and pass it on, tests compare it word for word.
#pragma once

#include <cassert>
#include <optional>
#include <string>
#include <type_traits>
#include <utility>

namespace kinfly {

class [[nodiscard]] Status {
 public:
  Status() = default;  // ok
  static Status error(std::string message) {
    assert(!message.empty() && "say what is wrong");
    Status status;
    status.ok_ = false;
    status.message_ = std::move(message);
    return status;
  }

  bool ok() const { return ok_; }
  // Empty when ok.
  const std::string& message() const { return message_; }

 private:
  bool ok_ = true;
  std::string message_;
};

// A value, or the Status that says why there is none (a subset of C++23's
// std::expected<T, Status>, spelled as absl's StatusOr).
template <class T>
class [[nodiscard]] StatusOr {
 public:
  // From a failed Status: `return Status::error("...");`.
  StatusOr(Status status) : status_(std::move(status)) {  // NOLINT: implicit by design
    assert(!status_.ok() && "a StatusOr without a value needs an error");
  }
  // From a value, or anything that converts to one (std::unique_ptr<Derived> for
  // std::unique_ptr<Base>): `return value;`.
  template <class U = T,
            class = std::enable_if_t<std::is_convertible_v<U&&, T> &&
                                     !std::is_same_v<std::decay_t<U>, Status> &&
                                     !std::is_same_v<std::decay_t<U>, StatusOr>>>
  StatusOr(U&& value) : value_(std::forward<U>(value)) {}  // NOLINT: implicit by design

  bool ok() const { return value_.has_value(); }
  const Status& status() const { return status_; }  // ok when there is a value

  // Only when ok().
  T& value() & { return *value_; }
  const T& value() const& { return *value_; }
  T&& value() && { return *std::move(value_); }
  T& operator*() & { return *value_; }
  const T& operator*() const& { return *value_; }
  T&& operator*() && { return *std::move(value_); }
  T* operator->() { return &*value_; }
  const T* operator->() const { return &*value_; }

 private:
  std::optional<T> value_;
  Status status_;
};

}  // namespace kinfly
