#include "kinfly/link/uplink.h"

#include <algorithm>

namespace kinfly::link {

template <class Inner>
SignedReceiver<Inner>::SignedReceiver(const Key& key, int32_t vehicle_id,
                                      const VerifierParams& verifier, const DecodeBounds& bounds)
    : vehicle_id_(vehicle_id), verifier_(key, vehicle_id, verifier), bounds_(bounds) {}

template <class Inner>
std::optional<Inner> SignedReceiver<Inner>::receive(const void* data, size_t size,
                                                    int64_t now_utime) {
  if (hasFingerprint<Inner>(data, size)) {
    ++rejects_.unsigned_messages;
    return std::nullopt;
  }
  if (const DecodeResult decoded = decodeMessage(data, size, bounds_, &envelope_); !decoded.ok()) {
    rejects_.count(decoded.status);
    return std::nullopt;
  }
  if (const Verdict verdict = verifier_.verify(envelope_, now_utime);
      verdict != Verdict::kAccepted) {
    if (verdict == Verdict::kDuplicate) ++duplicates_;
    rejects_.count(verdict);
    return std::nullopt;
  }
  Inner inner;
  if (const DecodeResult decoded = decodeMessage(envelope_.payload.data(),
                                                 envelope_.payload.size(), bounds_, &inner);
      !decoded.ok()) {
    rejects_.count(decoded.status);
    return std::nullopt;
  }
  // The envelope's vehicle id is authenticated; the inner one must agree with it.
  if (inner.vehicle_id != vehicle_id_) {
    ++rejects_.wrong_vehicle;
    return std::nullopt;
  }
  ++accepted_;
  return inner;
}

bool RecentCommands::first(int64_t command_id) {
  for (size_t i = 0; i < held_; ++i) {
    if (ids_[i] == command_id) {
      ++repeats_;
      return false;
    }
  }
  ids_[next_] = command_id;
  next_ = (next_ + 1) % kKept;
  held_ = std::min(held_ + 1, kKept);
  return true;
}

template class SignedReceiver<pose_correction_t>;
template class SignedReceiver<flight_command_t>;

}  // namespace kinfly::link
