#include "kinfly/link/signing.h"

#include <fcntl.h>
#include <sodium.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>

namespace kinfly::link {
namespace {

// Domain separation: a MAC made for this envelope can never be valid for another use of the key.
constexpr char kDomain[] = "kinfly-signed-v1";

void ensureSodium() {
  // sodium_init() is idempotent and thread-safe; it fails only if no entropy source exists, and
  // then neither keys nor MACs are trustworthy.
  static const int ok = sodium_init();
  if (ok < 0) {
    std::fputs("kinfly: libsodium failed to initialise\n", stderr);
    std::abort();
  }
}

template <int N>
void appendBigEndian(crypto_auth_hmacsha256_state* state, int64_t value) {
  uint8_t bytes[N];
  for (int i = 0; i < N; ++i)
    bytes[i] = static_cast<uint8_t>(static_cast<uint64_t>(value) >> (8 * (N - 1 - i)));
  crypto_auth_hmacsha256_update(state, bytes, N);
}

std::string errnoText() { return std::strerror(errno); }

// Closes the descriptor on every return path.
struct FileDescriptor {
  int fd;
  ~FileDescriptor() {
    if (fd >= 0) ::close(fd);
  }
};

}  // namespace

int64_t wallClockUtime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

uint32_t keyIdOf(const std::array<uint8_t, kKeyBytes>& bytes) {
  ensureSodium();
  uint8_t digest[crypto_hash_sha256_BYTES];
  crypto_hash_sha256(digest, bytes.data(), bytes.size());
  return (uint32_t{digest[0]} << 24) | (uint32_t{digest[1]} << 16) | (uint32_t{digest[2]} << 8) |
         uint32_t{digest[3]};
}

StatusOr<Key> loadKeyFile(const std::string& path) {
  FileDescriptor file{::open(path.c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW)};
  if (file.fd < 0) {
    return Status::error("cannot open key file " + path + ": " + errnoText());
  }
  struct stat st {};
  if (::fstat(file.fd, &st) != 0) {
    return Status::error("cannot stat key file " + path + ": " + errnoText());
  }
  if (!S_ISREG(st.st_mode)) {
    return Status::error("key file " + path + " is not a regular file");
  }
  if ((st.st_mode & 077) != 0) {
    char mode[8];
    std::snprintf(mode, sizeof mode, "%04o", static_cast<unsigned>(st.st_mode & 07777));
    return Status::error("key file " + path + " has mode " + mode +
                         ": group and others must have no access (chmod 600 " + path + ")");
  }
  if (st.st_size != static_cast<off_t>(kKeyBytes)) {
    return Status::error("key file " + path + " holds " + std::to_string(st.st_size) +
                         " bytes, not " + std::to_string(kKeyBytes) +
                         " (create one with kinfly-keygen)");
  }
  Key key;
  size_t got = 0;
  while (got < kKeyBytes) {
    const ssize_t n = ::read(file.fd, key.bytes.data() + got, kKeyBytes - got);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) {
      return Status::error("cannot read key file " + path +
                           (n < 0 ? ": " + errnoText() : ": short read"));
    }
    got += static_cast<size_t>(n);
  }
  key.id = keyIdOf(key.bytes);
  return key;
}

StatusOr<Key> createKeyFile(const std::string& path, bool overwrite) {
  ensureSodium();
  if (!overwrite && ::access(path.c_str(), F_OK) == 0) {
    return Status::error(path + " already exists (pass --force to replace it)");
  }
  Key key;
  randombytes_buf(key.bytes.data(), key.bytes.size());
  key.id = keyIdOf(key.bytes);

  // Written to a temporary beside the target and renamed, so a reader never sees a partial key
  // and a failure leaves any old key in place.
  const std::string temporary = path + ".tmp." + std::to_string(::getpid());
  FileDescriptor file{::open(temporary.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0600)};
  if (file.fd < 0) {
    return Status::error("cannot create " + temporary + ": " + errnoText());
  }
  const bool written =
      ::write(file.fd, key.bytes.data(), key.bytes.size()) ==
          static_cast<ssize_t>(key.bytes.size()) &&
      ::fchmod(file.fd, 0600) == 0 && ::fsync(file.fd) == 0;
  if (!written || ::rename(temporary.c_str(), path.c_str()) != 0) {
    Status failed = Status::error("cannot write key file " + path + ": " + errnoText());
    ::unlink(temporary.c_str());
    return failed;
  }
  return key;
}

std::array<uint8_t, 32> computeMac(const Key& key, int32_t vehicle_id, int64_t sequence,
                                   int64_t utime, const uint8_t* payload, size_t size) {
  ensureSodium();
  crypto_auth_hmacsha256_state state;
  crypto_auth_hmacsha256_init(&state, key.bytes.data(), key.bytes.size());
  crypto_auth_hmacsha256_update(&state, reinterpret_cast<const uint8_t*>(kDomain),
                                sizeof kDomain - 1);
  appendBigEndian<4>(&state, vehicle_id);
  appendBigEndian<4>(&state, static_cast<int32_t>(key.id));
  appendBigEndian<8>(&state, sequence);
  appendBigEndian<8>(&state, utime);
  crypto_auth_hmacsha256_update(&state, payload, size);
  std::array<uint8_t, 32> mac{};
  crypto_auth_hmacsha256_final(&state, mac.data());
  sodium_memzero(&state, sizeof state);
  return mac;
}

Signer::Signer(const Key& key, int32_t vehicle_id, int64_t first_sequence)
    : key_(key), vehicle_id_(vehicle_id), next_sequence_(first_sequence) {}

void Signer::sign(const uint8_t* inner, size_t size, int64_t utime_now, signed_t* out) {
  out->utime = utime_now;
  out->vehicle_id = vehicle_id_;
  out->key_id = static_cast<int32_t>(key_.id);
  out->sequence = next_sequence_++;
  const auto mac = computeMac(key_, vehicle_id_, out->sequence, utime_now, inner, size);
  std::memcpy(out->mac, mac.data(), mac.size());
  out->payload.assign(inner, inner + size);
  out->payload_size = static_cast<int32_t>(size);
}

const char* toString(Verdict verdict) {
  switch (verdict) {
    case Verdict::kAccepted: return "accepted";
    case Verdict::kWrongVehicle: return "wrong vehicle";
    case Verdict::kWrongKey: return "wrong key";
    case Verdict::kBadMac: return "bad MAC";
    case Verdict::kStale: return "stale";
    case Verdict::kReplayed: return "replayed";
    case Verdict::kDuplicate: return "duplicate";
  }
  return "?";
}

Status VerifierParams::validate() const {
  if (!(window_s > 0.0 && window_s <= 3600.0))
    return Status::error("window_s must be in (0, 3600] s (got " + std::to_string(window_s) + ")");
  return {};
}

Verifier::Verifier(const Key& key, int32_t vehicle_id, const VerifierParams& params)
    : key_(key), vehicle_id_(vehicle_id), params_(params) {}

Verdict Verifier::verify(const signed_t& envelope, int64_t now_utime) {
  if (envelope.vehicle_id != vehicle_id_) return Verdict::kWrongVehicle;
  if (static_cast<uint32_t>(envelope.key_id) != key_.id) return Verdict::kWrongKey;
  const auto mac = computeMac(key_, envelope.vehicle_id, envelope.sequence, envelope.utime,
                              envelope.payload.data(), envelope.payload.size());
  if (envelope.payload.size() != static_cast<size_t>(envelope.payload_size) ||
      sodium_memcmp(mac.data(), envelope.mac, mac.size()) != 0)
    return Verdict::kBadMac;
  const double age_s = static_cast<double>(now_utime - envelope.utime) * 1e-6;
  if (!(std::abs(age_s) <= params_.window_s)) return Verdict::kStale;
  for (size_t i = 0; i < recent_count_; ++i)
    if (recent_[i] == envelope.sequence) return Verdict::kDuplicate;
  if (last_sequence_ && envelope.sequence <= *last_sequence_) return Verdict::kReplayed;
  last_sequence_ = envelope.sequence;
  recent_[next_recent_] = envelope.sequence;
  next_recent_ = (next_recent_ + 1) % recent_.size();
  recent_count_ = std::min(recent_count_ + 1, recent_.size());
  return Verdict::kAccepted;
}

}  // namespace kinfly::link
