// Authentication of everything the ground sends that changes the drone's state: HMAC-SHA256
// (libsodium) over the encoded inner message plus vehicle id, key id, sequence number and signing
// time, carried in a signed_t envelope. ground/kinfly_ground/signing.py is the same in Python;
// docs/wire.md has the byte layout and the threat model.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>

#include "kinfly/core/status.h"
#include "kinfly/signed_t.hpp"

namespace kinfly::link {

constexpr size_t kKeyBytes = 32;

struct Key {
  std::array<uint8_t, kKeyBytes> bytes{};
  uint32_t id = 0;  // keyIdOf(bytes)
};

// First 4 bytes of SHA-256 of the key, big-endian: names a key on the wire without revealing it.
uint32_t keyIdOf(const std::array<uint8_t, kKeyBytes>& bytes);

// Reads a key file (exactly 32 bytes). Like ssh, it refuses a file that group or others may read
// or write, or that is not a regular file, and says which.
StatusOr<Key> loadKeyFile(const std::string& path);

// Creates a key file of 32 random bytes, mode 0600. Never replaces an existing file unless
// overwrite is set, and then only by renaming a complete new file over it.
StatusOr<Key> createKeyFile(const std::string& path, bool overwrite);

class Signer {
 public:
  // first_sequence: pass the current wall-clock time in microseconds, so a restarted sender
  // continues above every sequence number it used before (the receiver only accepts increases).
  Signer(const Key& key, int32_t vehicle_id, int64_t first_sequence);

  // Fills *out with an envelope around the encoded inner message.
  void sign(const uint8_t* inner, size_t size, int64_t utime_now, signed_t* out);

 private:
  Key key_;
  int32_t vehicle_id_;
  int64_t next_sequence_;
};

enum class Verdict {
  kAccepted,
  kWrongVehicle,  // addressed to another vehicle
  kWrongKey,      // key_id is not the key this side holds
  kBadMac,
  kStale,         // signing time outside the window
  kReplayed,      // sequence not above the last accepted one
  kDuplicate,     // a copy of an envelope accepted lately: the ground sends each more than once
};
const char* toString(Verdict verdict);

struct VerifierParams {
  double window_s = 2.0;  // [s] (0, 3600]: |receiver clock - signing time| accepted
  Status validate() const;
};

class Verifier {
 public:
  Verifier(const Key& key, int32_t vehicle_id, const VerifierParams& params);

  // Checks an envelope decoded with decodeMessage(). Checks run cheapest-first but the MAC comes
  // before the time and sequence, so forged envelopes count as kBadMac, never as stale or
  // replayed, and cannot move the replay window. Only kAccepted advances the sequence. An
  // authentic envelope whose sequence is one of the last kRecentSequences accepted is a copy
  // (kDuplicate: one signer never signs two messages with one sequence number).
  Verdict verify(const signed_t& envelope, int64_t now_utime);

  static constexpr size_t kRecentSequences = 16;

 private:
  Key key_;
  int32_t vehicle_id_;
  VerifierParams params_;
  std::optional<int64_t> last_sequence_;
  std::array<int64_t, kRecentSequences> recent_{};  // accepted sequences, a ring
  size_t recent_count_ = 0, next_recent_ = 0;
};

// [us] since the Unix epoch: the clock signing times are stamped with and checked against (both
// ends must keep it synchronised, e.g. with chrony).
int64_t wallClockUtime();

// HMAC-SHA256 over the envelope's fields and the payload, as the layout in docs/wire.md.
std::array<uint8_t, 32> computeMac(const Key& key, int32_t vehicle_id, int64_t sequence,
                                   int64_t utime, const uint8_t* payload, size_t size);

}  // namespace kinfly::link
