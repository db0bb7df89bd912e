#include "kinfly/link/chunking.h"

// cm256cc's header must be told the SIMD flavour its library was built with (Debian: SSSE3 on
// amd64, NEON on arm64), or it declares nothing.
#if defined(__x86_64__) || defined(__i386__)
#define USE_SSSE3
#elif defined(__aarch64__) || defined(__ARM_NEON)
#define USE_NEON
#endif
#include <cm256cc/cm256.h>
#include <sodium.h>
#if defined(__x86_64__) || defined(__i386__)
#include <xmmintrin.h>
#endif

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <limits>

#include "kinfly/link/channels.h"

namespace kinfly::link {
namespace {

constexpr int kMaxGroupChunks = keyframe_chunk_t::MAX_GROUP_CHUNKS;
constexpr int kIpUdpHeaderBytes = 20 + 8;  // IPv4 without options, UDP
// LCM's header on a datagram that holds a whole message: magic and sequence number (uint32 each);
// the channel name and its NUL follow.
constexpr int kLcmShortHeaderBytes = 8;

// Sizes a buffer to exactly n elements, allocating only when it must grow, and then exactly n
// (a plain resize may double the capacity), so that what the assembler holds is what it counts.
template <class T>
void fit(std::vector<T>* v, size_t n) {
  if (v->capacity() < n) {
    std::vector<T>().swap(*v);
    v->reserve(n);
  }
  v->resize(n);
}

template <class T>
int64_t capacityBytes(const std::vector<T>& v) {
  return static_cast<int64_t>(v.capacity() * sizeof(T));
}

// One GF(256) context for the process: cm256cc builds 141 KB of tables and prints a line for
// every CM256 constructed, and after construction encoding and decoding only read those tables,
// so encoders and assemblers on any thread share it.
CM256& cm256() {
  static CM256 instance;
  return instance;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Layout

int blockCount(int64_t message_bytes, int block_size) {
  return static_cast<int>((message_bytes + block_size - 1) / block_size);
}

int firstBlockOfGroup(int blocks, int groups, int group) {
  const int base = blocks / groups, larger = blocks % groups;
  return group * base + std::min(group, larger);
}

int originalsInGroup(int blocks, int groups, int group) {
  return blocks / groups + (group < blocks % groups ? 1 : 0);
}

int64_t messageDigest(const uint8_t* data, size_t size) {
  // Picks libsodium's fastest BLAKE2b (idempotent and thread-safe); hashing works either way.
  static const int sodium = sodium_init();
  (void)sodium;
  std::array<uint8_t, crypto_generichash_BYTES_MIN> hash{};
  crypto_generichash(hash.data(), hash.size(), data, size, nullptr, 0);
  uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = (v << 8) | hash[static_cast<size_t>(i)];
  return static_cast<int64_t>(v);
}

std::string chunkProblem(const keyframe_chunk_t& c, int64_t max_message_bytes) {
  if (c.keyframe_id < 0) return "keyframe_id is negative";
  if (c.sequence < 0 || c.sequence > kMaxChunkSequence)
    return "sequence " + std::to_string(c.sequence) + " outside [0, 2^53]";
  // Sent times are differenced for the loss window: a time before the epoch is forged.
  if (c.sent_utime < 0) return "sent_utime is negative";
  if (c.block_size < 1 || c.block_size > keyframe_chunk_t::MAX_BLOCK_BYTES)
    return "block_size " + std::to_string(c.block_size) + " outside [1, " +
           std::to_string(keyframe_chunk_t::MAX_BLOCK_BYTES) + "]";
  if (c.message_bytes < 1 || c.message_bytes > max_message_bytes)
    return "message_bytes " + std::to_string(c.message_bytes) + " outside [1, " +
           std::to_string(max_message_bytes) + "]";
  const int blocks = blockCount(c.message_bytes, c.block_size);
  if (c.groups < 1 || c.groups > blocks)
    return "groups " + std::to_string(c.groups) + " outside [1, " + std::to_string(blocks) +
           "] for " + std::to_string(blocks) + " blocks";
  if (c.group < 0 || c.group >= c.groups) return "group outside [0, groups)";
  const int k = originalsInGroup(blocks, c.groups, c.group);
  if (c.originals != k)
    return "originals " + std::to_string(c.originals) + " where the layout has " +
           std::to_string(k);
  if (c.recovery < 0 || k + c.recovery > kMaxGroupChunks)
    return "originals + recovery above " + std::to_string(kMaxGroupChunks);
  if (c.index < 0 || c.index >= k + c.recovery) return "index outside [0, originals + recovery)";
  if (static_cast<int>(c.block.size()) < c.block_size) return "block shorter than block_size";
  return {};
}

// ---------------------------------------------------------------------------------------------
// Redundancy

Status RedundancyParams::validate() const {
  if (!(target_failure > 0.0 && target_failure <= 0.1))
    return Status::error("target_failure must be in (0, 0.1]");
  if (!(min_loss_fraction >= 0.0 && min_loss_fraction <= 0.5))
    return Status::error("min_loss_fraction must be in [0, 0.5]");
  if (!(max_loss_fraction >= min_loss_fraction && max_loss_fraction <= 0.5))
    return Status::error("max_loss_fraction must be in [min_loss_fraction, 0.5]");
  if (!(max_mean_loss_run >= 1.0 && max_mean_loss_run <= 64.0))
    return Status::error("max_mean_loss_run must be in [1, 64]");
  return {};
}

namespace {

// Gilbert's channel, stepped one chunk at a time from its stationary state: the distribution of
// the number lost so far, split by the state of the last chunk.
class GilbertLosses {
 public:
  explicit GilbertLosses(const LinkLoss& loss) {
    const double p = loss.loss_fraction;
    // Bernoulli loss has runs of mean 1/(1-p): no shorter mean is consistent with p.
    const double run = std::max(loss.mean_loss_run, 1.0 / (1.0 - p));
    stay_bad_ = 1.0 - 1.0 / run;
    // Stationary: p * (1 - stay_bad) = (1 - p) * to_bad.
    to_bad_ = p > 0.0 ? p * (1.0 - stay_bad_) / (1.0 - p) : 0.0;
    good_[0] = 1.0 - p;  // before the first chunk, in the stationary state with nothing lost
    bad_[0] = p;
    first_ = true;
  }

  // Adds one chunk.
  void step() {
    if (first_) {
      // The stationary state already is the first chunk's: it is lost in the bad state.
      for (int x = kMaxGroupChunks; x >= 1; --x) bad_[x] = bad_[x - 1];
      bad_[0] = 0.0;
      first_ = false;
      ++chunks_;
      return;
    }
    std::array<double, kMaxGroupChunks + 1> good{}, bad{};
    for (int x = 0; x <= chunks_; ++x) {
      good[x] += good_[x] * (1.0 - to_bad_) + bad_[x] * (1.0 - stay_bad_);
      bad[x + 1] += good_[x] * to_bad_ + bad_[x] * stay_bad_;
    }
    good_ = good;
    bad_ = bad;
    ++chunks_;
  }

  // P(more than m of the chunks so far lost).
  double moreThan(int m) const {
    double p = 0.0;
    for (int x = m + 1; x <= chunks_; ++x) p += good_[x] + bad_[x];
    return p;
  }

 private:
  double stay_bad_ = 0.0, to_bad_ = 0.0;
  std::array<double, kMaxGroupChunks + 1> good_{}, bad_{};
  int chunks_ = 0;
  bool first_ = true;
};

LinkLoss modelled(const LinkLoss& loss, const RedundancyParams& params) {
  const double p = std::isfinite(loss.loss_fraction) ? loss.loss_fraction : params.max_loss_fraction;
  const double run = std::isfinite(loss.mean_loss_run) ? loss.mean_loss_run : params.max_mean_loss_run;
  return {std::clamp(p, params.min_loss_fraction, params.max_loss_fraction),
          std::clamp(run, 1.0, params.max_mean_loss_run)};
}

}  // namespace

double groupFailureProbability(int originals, int recovery, const LinkLoss& loss) {
  GilbertLosses losses(loss);
  for (int n = 0; n < std::min(originals + recovery, kMaxGroupChunks); ++n) losses.step();
  return losses.moreThan(recovery);
}

int recoveryChunks(int originals, const LinkLoss& loss, const RedundancyParams& params) {
  const int k = std::clamp(originals, 1, kMaxGroupChunks - 1);
  GilbertLosses losses(modelled(loss, params));
  for (int n = 0; n < k; ++n) losses.step();
  for (int m = 0; m < kMaxGroupChunks - k; ++m) {
    if (losses.moreThan(m) <= params.target_failure) return m;
    losses.step();
  }
  return kMaxGroupChunks - k;
}

// ---------------------------------------------------------------------------------------------
// ChunkEncoder

Status ChunkEncoder::Params::validate() const {
  if (mtu_bytes < 576 || mtu_bytes > 9000) return Status::error("mtu_bytes must be in [576, 9000]");
  if (max_originals_per_group < 1 || max_originals_per_group > kMaxGroupChunks - 1)
    return Status::error("max_originals_per_group must be in [1, 255]");
  if (repair_keyframes < 1 || repair_keyframes > 64)
    return Status::error("repair_keyframes must be in [1, 64]");
  if (repair_chunks_per_keyframe < 0 || repair_chunks_per_keyframe > 4096)
    return Status::error("repair_chunks_per_keyframe must be in [0, 4096]");
  return {};
}

int ChunkEncoder::blockBytesFor(int mtu_bytes) {
  const int channel = static_cast<int>(channelName(Channel::kKeyframeChunk, kMaxVehicleId).size());
  const int chunk_fields = keyframe_chunk_t().getEncodedSize();  // fingerprint and fields, no block
  return std::min<int>(mtu_bytes - kIpUdpHeaderBytes - kLcmShortHeaderBytes - (channel + 1) -
                           chunk_fields,
                       keyframe_chunk_t::MAX_BLOCK_BYTES);
}

ChunkEncoder::ChunkEncoder(const Params& params)
    : params_(params),
      block_bytes_(blockBytesFor(params.mtu_bytes)),
      kept_(static_cast<size_t>(params.repair_keyframes)) {}

ChunkEncoder::~ChunkEncoder() = default;

void ChunkEncoder::reserve(int64_t max_message_bytes) {
  const size_t block = static_cast<size_t>(block_bytes_);
  const int blocks = blockCount(std::max<int64_t>(max_message_bytes, 1), block_bytes_);
  const int groups = (blocks + params_.max_originals_per_group - 1) / params_.max_originals_per_group;
  // Each group holds at most MAX_GROUP_CHUNKS chunks, whatever its share of recovery.
  const size_t chunks = static_cast<size_t>(std::min(blocks + groups * (kMaxGroupChunks - 1),
                                                     groups * kMaxGroupChunks));
  encoded_.reserve(static_cast<size_t>(max_message_bytes));
  padded_.reserve(static_cast<size_t>(blocks) * block);
  recovery_.reserve(static_cast<size_t>(kMaxGroupChunks - 1) * block);
  for (Kept& kept : kept_) {
    if (kept.chunks.size() < chunks) kept.chunks.resize(chunks);
    for (keyframe_chunk_t& c : kept.chunks) c.block.reserve(block);
  }
}

int ChunkEncoder::originalsPerGroup(int64_t message_bytes) const {
  const int blocks = blockCount(std::max<int64_t>(message_bytes, 1), block_bytes_);
  const int groups = (blocks + params_.max_originals_per_group - 1) / params_.max_originals_per_group;
  return originalsInGroup(blocks, groups, 0);
}

StatusOr<ChunkSpan> ChunkEncoder::encode(const depth_keyframe_t& keyframe, int recovery) {
  // lcm-gen's encoder reads payload_size bytes whatever the vector holds.
  if (keyframe.payload_size < 0 || static_cast<size_t>(keyframe.payload_size) > keyframe.payload.size())
    return Status::error("the keyframe's payload_size exceeds its payload");
  const int size = keyframe.getEncodedSize();
  if (size <= 0) return Status::error("the keyframe cannot be encoded");
  fit(&encoded_, static_cast<size_t>(size));
  if (keyframe.encode(encoded_.data(), 0, size) != size)
    return Status::error("the keyframe cannot be encoded");
  return encode(encoded_.data(), encoded_.size(),
                {keyframe.utime, keyframe.vehicle_id, keyframe.keyframe_id}, recovery);
}

StatusOr<ChunkSpan> ChunkEncoder::encode(const uint8_t* message, size_t size,
                                         const KeyframeIds& ids, int recovery) {
  const int64_t max_bytes = maxKeyframeMessageBytes(DecodeBounds());
  if (size < 1 || static_cast<int64_t>(size) > max_bytes)
    return Status::error("a chunked message is 1 to " + std::to_string(max_bytes) + " bytes (got " +
                         std::to_string(size) + ")");
  if (recovery < 0 || recovery > kMaxGroupChunks - 1)
    return Status::error("recovery must be in [0, 255] (got " + std::to_string(recovery) + ")");
  if (ids.vehicle_id < 0 || ids.vehicle_id > kMaxVehicleId || ids.keyframe_id < 0)
    return Status::error("a chunked keyframe needs a vehicle id in [0, 65535] and a keyframe id >= 0");

  const size_t block = static_cast<size_t>(block_bytes_);
  const int blocks = blockCount(static_cast<int64_t>(size), block_bytes_);
  const int groups = (blocks + params_.max_originals_per_group - 1) / params_.max_originals_per_group;
  // cm256 reads whole blocks: the message is copied into whole, zero-padded ones.
  fit(&padded_, static_cast<size_t>(blocks) * block);
  std::memcpy(padded_.data(), message, size);
  std::fill(padded_.begin() + static_cast<long>(size), padded_.end(), uint8_t{0});

  keyframe_chunk_t header{};  // sent_utime and sequence are set per chunk, as it goes out
  header.utime = ids.utime;
  header.vehicle_id = ids.vehicle_id;
  header.keyframe_id = ids.keyframe_id;
  header.message_bytes = static_cast<int32_t>(size);
  header.message_digest = messageDigest(message, size);
  header.groups = static_cast<int16_t>(groups);
  header.block_size = static_cast<int16_t>(block_bytes_);

  Kept& kept = kept_[next_kept_];
  next_kept_ = (next_kept_ + 1) % kept_.size();
  kept.utime = ids.utime;
  kept.keyframe_id = ids.keyframe_id;
  kept.resends = 0;
  kept.count = 0;
  const auto add = [&](int group, int k, int m, int index, const uint8_t* data) {
    if (kept.count == kept.chunks.size()) kept.chunks.emplace_back();
    keyframe_chunk_t& c = kept.chunks[kept.count++];
    std::vector<uint8_t> storage;
    storage.swap(c.block);  // the chunk's own buffer survives the header's copy
    c = header;
    c.block.swap(storage);
    c.sequence = next_sequence_++;
    c.group = static_cast<int16_t>(group);
    c.originals = static_cast<int16_t>(k);
    c.recovery = static_cast<int16_t>(m);
    c.index = static_cast<int16_t>(index);
    c.block.resize(block);
    std::memcpy(c.block.data(), data, block);
  };

  std::array<CM256::cm256_block, kMaxGroupChunks> originals{};
  for (int g = 0; g < groups; ++g) {
    const int k = originalsInGroup(blocks, groups, g);
    const int m = std::min(recovery, kMaxGroupChunks - k);
    const uint8_t* first = padded_.data() + static_cast<size_t>(firstBlockOfGroup(blocks, groups, g)) * block;
    for (int i = 0; i < k; ++i) add(g, k, m, i, first + static_cast<size_t>(i) * block);
    if (m == 0) continue;
    for (int i = 0; i < k; ++i) {
      originals[static_cast<size_t>(i)].Block = const_cast<uint8_t*>(first + static_cast<size_t>(i) * block);
      originals[static_cast<size_t>(i)].Index = static_cast<unsigned char>(i);
    }
    fit(&recovery_, static_cast<size_t>(m) * block);
    const CM256::cm256_encoder_params params{k, m, block_bytes_};
    if (cm256().cm256_encode(params, originals.data(), recovery_.data()) != 0)
      return Status::error("cm256 refused to encode a group of " + std::to_string(k) + "+" +
                           std::to_string(m) + " blocks");
    for (int j = 0; j < m; ++j) add(g, k, m, k + j, recovery_.data() + static_cast<size_t>(j) * block);
  }
  return ChunkSpan{kept.chunks.data(), kept.count};
}

const keyframe_chunk_t* ChunkEncoder::resend(const chunk_request_t& request, int i) {
  if (i < 0 || i >= request.index_count || i >= static_cast<int>(request.indices.size()))
    return nullptr;
  for (Kept& kept : kept_) {
    if (kept.count == 0 || kept.keyframe_id != request.keyframe_id || kept.utime != request.utime)
      continue;
    if (kept.resends >= params_.repair_chunks_per_keyframe) return nullptr;
    for (size_t c = 0; c < kept.count; ++c) {
      keyframe_chunk_t& chunk = kept.chunks[c];
      if (chunk.group != request.group || chunk.index != request.indices[static_cast<size_t>(i)])
        continue;
      ++kept.resends;
      chunk.sequence = next_sequence_++;
      return &chunk;
    }
    return nullptr;
  }
  return nullptr;
}

// ---------------------------------------------------------------------------------------------
// ChunkAssembler

const char* toString(ChunkStatus status) {
  switch (status) {
    case ChunkStatus::kStored: return "stored";
    case ChunkStatus::kCompleted: return "completed";
    case ChunkStatus::kDuplicate: return "duplicate";
    case ChunkStatus::kSurplus: return "surplus";
    case ChunkStatus::kStale: return "stale";
    case ChunkStatus::kMismatch: return "mismatch";
    case ChunkStatus::kOversized: return "oversized";
    case ChunkStatus::kMalformed: return "malformed";
    case ChunkStatus::kDigestMismatch: return "digest mismatch";
  }
  return "?";
}

double LossStats::lossFraction() const {
  return expected > 0 ? static_cast<double>(expected - received) / static_cast<double>(expected) : 0.0;
}

double LossStats::meanLossRun() const {
  return loss_runs > 0 ? static_cast<double>(expected - received) / static_cast<double>(loss_runs)
                       : 1.0;
}

Status ChunkAssembler::Params::validate() const {
  if (max_keyframes < 1 || max_keyframes > 64) return Status::error("max_keyframes must be in [1, 64]");
  if (max_bytes_held < (int64_t{64} << 10) || max_bytes_held > (int64_t{1} << 30))
    return Status::error("max_bytes_held must be in [64 KiB, 1 GiB]");
  const int64_t largest = depth_keyframe_t().getEncodedSize() + (int64_t{64} << 20);
  if (max_message_bytes < 1 || max_message_bytes > largest)
    return Status::error("max_message_bytes must be in [1, 64 MiB + a keyframe's header]");
  if (window_keyframes < 1 || window_keyframes > 1024)
    return Status::error("window_keyframes must be in [1, 1024]");
  if (restart_gap_chunks < 1 || restart_gap_chunks > (int64_t{1} << 40))
    return Status::error("restart_gap_chunks must be in [1, 2^40]");
  if (loss_window_chunks < 64 || loss_window_chunks > 65536)
    return Status::error("loss_window_chunks must be in [64, 65536]");
  if (reorder_chunks < 0 || reorder_chunks > loss_window_chunks / 2)
    return Status::error("reorder_chunks must be in [0, loss_window_chunks / 2]");
  if (!(loss_window_s > 0.0 && loss_window_s <= 3600.0))
    return Status::error("loss_window_s must be in (0, 3600]");
  return bounds.validate();
}

int64_t ChunkAssembler::Slot::bytes() const {
  return capacityBytes(storage) + capacityBytes(held_index) + capacityBytes(groups);
}

ChunkAssembler::ChunkAssembler(int32_t vehicle_id, const Params& params)
    : vehicle_id_(vehicle_id),
      params_(params),
      slots_(static_cast<size_t>(params.max_keyframes)),
      done_(static_cast<size_t>(params.window_keyframes)),
      seen_(static_cast<size_t>(params.loss_window_chunks), false),
      seen_sent_utime_(static_cast<size_t>(params.loss_window_chunks), 0) {}

ChunkAssembler::~ChunkAssembler() = default;

int64_t ChunkAssembler::bytesHeld() const {
  int64_t total = 0;
  for (const Slot& slot : slots_) total += slot.bytes();
  return total;
}

ChunkStatus ChunkAssembler::count(ChunkStatus status) {
  switch (status) {
    case ChunkStatus::kStored: ++counters_.stored; break;
    case ChunkStatus::kCompleted: ++counters_.stored; ++counters_.keyframes_completed; break;
    case ChunkStatus::kDuplicate: ++counters_.duplicate; break;
    case ChunkStatus::kSurplus: ++counters_.surplus; break;
    case ChunkStatus::kStale: ++counters_.stale; break;
    case ChunkStatus::kMismatch: ++counters_.mismatch; break;
    case ChunkStatus::kOversized: ++counters_.oversized; break;
    case ChunkStatus::kMalformed: ++counters_.malformed; break;
    case ChunkStatus::kDigestMismatch: ++counters_.digest_mismatch; break;
  }
  return status;
}

ChunkStatus ChunkAssembler::receive(const void* data, size_t size) {
  if (!decodeMessage(data, size, params_.bounds, &chunk_).ok()) {
    ++counters_.chunks;
    return count(ChunkStatus::kMalformed);
  }
  return add(chunk_);
}

ChunkStatus ChunkAssembler::add(const keyframe_chunk_t& chunk) {
  ++counters_.chunks;
  if (chunk.vehicle_id != vehicle_id_) return count(ChunkStatus::kMismatch);
  if (!chunkProblem(chunk, maxKeyframeMessageBytes(params_.bounds)).empty())
    return count(ChunkStatus::kMalformed);
  noteSequence(chunk.sequence, chunk.sent_utime);
  if (chunk.message_bytes > params_.max_message_bytes) return count(ChunkStatus::kOversized);

  if (chunk.keyframe_id > newest_id_) {
    newest_id_ = chunk.keyframe_id;
    for (Slot& slot : slots_)
      if (slot.used && slot.header.keyframe_id <= newest_id_ - params_.window_keyframes) evict(slot);
  }
  if (Slot* slot = findSlot(chunk.keyframe_id)) {
    const keyframe_chunk_t& h = slot->header;
    if (chunk.utime != h.utime || chunk.message_bytes != h.message_bytes ||
        chunk.message_digest != h.message_digest || chunk.groups != h.groups ||
        chunk.block_size != h.block_size)
      return count(ChunkStatus::kMismatch);
    return count(store(*slot, chunk));
  }
  for (const Done& done : done_)
    if (done.keyframe_id == chunk.keyframe_id)
      return count(done.digest == chunk.message_digest ? ChunkStatus::kSurplus
                                                       : ChunkStatus::kMismatch);
  if (chunk.keyframe_id <= newest_id_ - params_.window_keyframes) return count(ChunkStatus::kStale);
  Slot* slot = newSlot(chunk);
  if (slot == nullptr) return count(ChunkStatus::kOversized);
  return count(store(*slot, chunk));
}

ChunkAssembler::Slot* ChunkAssembler::findSlot(int64_t keyframe_id) {
  for (Slot& slot : slots_)
    if (slot.used && slot.header.keyframe_id == keyframe_id) return &slot;
  return nullptr;
}

ChunkAssembler::Slot* ChunkAssembler::newSlot(const keyframe_chunk_t& chunk) {
  const int blocks = blockCount(chunk.message_bytes, chunk.block_size);
  const int64_t need = int64_t{blocks} * chunk.block_size + blocks +
                       int64_t{chunk.groups} * static_cast<int64_t>(sizeof(Group));
  if (need > params_.max_bytes_held) return nullptr;

  // A free place if there is one (one whose buffers are large enough, so that nothing
  // allocates), else the oldest keyframe's.
  Slot* slot = nullptr;
  for (Slot& s : slots_)
    if (!s.used && (slot == nullptr || (slot->bytes() < need && s.bytes() > slot->bytes())))
      slot = &s;
  if (slot == nullptr) {
    slot = &*std::min_element(slots_.begin(), slots_.end(),
                              [](const Slot& a, const Slot& b) { return a.started < b.started; });
    evict(*slot);
  }
  // Room: first the buffers of free places, then the oldest keyframes.
  const auto others = [&] { return bytesHeld() - slot->bytes(); };
  for (Slot& s : slots_)
    if (&s != slot && !s.used && others() + need > params_.max_bytes_held) release(s);
  while (others() + need > params_.max_bytes_held) {
    Slot* oldest = nullptr;
    for (Slot& s : slots_)
      if (&s != slot && s.used && (oldest == nullptr || s.started < oldest->started)) oldest = &s;
    if (oldest == nullptr) break;  // unreachable: need <= max_bytes_held
    evict(*oldest);
    release(*oldest);
  }
  if (slot->bytes() > need && others() + slot->bytes() > params_.max_bytes_held) release(*slot);

  slot->used = true;
  slot->started = arrivals_++;
  slot->header.utime = chunk.utime;
  slot->header.vehicle_id = chunk.vehicle_id;
  slot->header.keyframe_id = chunk.keyframe_id;
  slot->header.message_bytes = chunk.message_bytes;
  slot->header.message_digest = chunk.message_digest;
  slot->header.groups = chunk.groups;
  slot->header.block_size = chunk.block_size;
  slot->blocks = blocks;
  slot->groups_complete = 0;
  fit(&slot->storage, static_cast<size_t>(blocks) * static_cast<size_t>(chunk.block_size));
  fit(&slot->held_index, static_cast<size_t>(blocks));
  fit(&slot->groups, static_cast<size_t>(chunk.groups));
  std::fill(slot->groups.begin(), slot->groups.end(), Group{});
  return slot;
}

void ChunkAssembler::evict(Slot& slot) {
  if (!slot.used) return;
  slot.used = false;
  ++counters_.keyframes_evicted;
}

void ChunkAssembler::release(Slot& slot) {
  std::vector<uint8_t>().swap(slot.storage);
  std::vector<uint8_t>().swap(slot.held_index);
  std::vector<Group>().swap(slot.groups);
}

ChunkStatus ChunkAssembler::store(Slot& slot, const keyframe_chunk_t& chunk) {
  Group& group = slot.groups[static_cast<size_t>(chunk.group)];
  if (group.recovery < 0) group.recovery = chunk.recovery;
  if (chunk.recovery != group.recovery) return ChunkStatus::kMismatch;
  const int k = chunk.originals;
  if (group.held == k) return ChunkStatus::kSurplus;
  if (group.have.test(static_cast<size_t>(chunk.index))) return ChunkStatus::kDuplicate;

  // Any k distinct chunks rebuild the group: they fill its k positions in arrival order.
  const size_t position =
      static_cast<size_t>(firstBlockOfGroup(slot.blocks, slot.header.groups, chunk.group) + group.held);
  const size_t block = static_cast<size_t>(chunk.block_size);
  std::memcpy(slot.storage.data() + position * block, chunk.block.data(), block);
  slot.held_index[position] = static_cast<uint8_t>(chunk.index);
  group.have.set(static_cast<size_t>(chunk.index));
  if (++group.held < k) return ChunkStatus::kStored;
  if (++slot.groups_complete < slot.header.groups) return ChunkStatus::kStored;
  return complete(slot);
}

ChunkStatus ChunkAssembler::complete(Slot& slot) {
  const keyframe_chunk_t& h = slot.header;
  const size_t block = static_cast<size_t>(h.block_size);
  fit(&message_, static_cast<size_t>(slot.blocks) * block);
  bool recovered = false;
  std::array<CM256::cm256_block, kMaxGroupChunks> blocks{};
  for (int g = 0; g < h.groups; ++g) {
    const int first = firstBlockOfGroup(slot.blocks, h.groups, g);
    const int k = originalsInGroup(slot.blocks, h.groups, g);
    bool originals_only = true;
    for (int i = 0; i < k; ++i) {
      const size_t position = static_cast<size_t>(first + i);
      blocks[static_cast<size_t>(i)].Block = slot.storage.data() + position * block;
      blocks[static_cast<size_t>(i)].Index = slot.held_index[position];
      originals_only &= slot.held_index[position] < k;
    }
    if (!originals_only) {
      recovered = true;
      const CM256::cm256_encoder_params params{k, slot.groups[static_cast<size_t>(g)].recovery,
                                               h.block_size};
      // Rebuilds the missing originals in place of the recovery blocks, relabelling them.
      if (cm256().cm256_decode(params, blocks.data()) != 0) {
        evict(slot);
        return ChunkStatus::kMalformed;
      }
    }
    for (int i = 0; i < k; ++i) {
      const size_t index = blocks[static_cast<size_t>(i)].Index;
      std::memcpy(message_.data() + (static_cast<size_t>(first) + index) * block,
                  blocks[static_cast<size_t>(i)].Block, block);
    }
  }
  message_.resize(static_cast<size_t>(h.message_bytes));
  slot.used = false;
  done_[next_done_] = {h.keyframe_id, h.message_digest};
  next_done_ = (next_done_ + 1) % done_.size();
  if (messageDigest(message_.data(), message_.size()) != h.message_digest) {
    message_.clear();
    return ChunkStatus::kDigestMismatch;
  }
  if (recovered) ++counters_.keyframes_recovered;
  return ChunkStatus::kCompleted;
}

// ---------------------------------------------------------------------------------------------
// Loss from sequence numbers

void ChunkAssembler::restart() {
  ++counters_.restarts;
  for (Slot& slot : slots_) evict(slot);
  std::fill(done_.begin(), done_.end(), Done{});
  newest_id_ = -1;
  highest_sequence_ = -1;
}

void ChunkAssembler::noteSequence(int64_t sequence, int64_t sent_utime) {
  const int64_t window = params_.loss_window_chunks;
  // A drone that restarted numbers from 0 again: far below the highest number, or below it by
  // more than reordering explains while sent later than the chunk that had the highest (a chunk
  // the network reordered was sent earlier).
  if (highest_sequence_ >= 0 &&
      (sequence < highest_sequence_ - params_.restart_gap_chunks ||
       (sequence < highest_sequence_ - params_.reorder_chunks && sent_utime > highest_sent_utime_)))
    restart();
  if (highest_sequence_ < 0) {
    std::fill(seen_.begin(), seen_.end(), false);
    highest_sequence_ = lowest_tracked_ = sequence;
    highest_sent_utime_ = sent_utime;
  }
  if (sequence > highest_sequence_) {
    // The positions the window moves over are unseen until their chunk arrives.
    for (int64_t s = std::max(highest_sequence_ + 1, sequence - window + 1); s <= sequence; ++s)
      seen_[static_cast<size_t>(s % window)] = false;
    highest_sequence_ = sequence;
    highest_sent_utime_ = sent_utime;
    lowest_tracked_ = std::max(lowest_tracked_, sequence - window + 1);
  }
  if (sequence >= lowest_tracked_) {
    seen_[static_cast<size_t>(sequence % window)] = true;
    seen_sent_utime_[static_cast<size_t>(sequence % window)] = sent_utime;
  }
}

LossStats ChunkAssembler::loss() const {
  LossStats stats;
  if (highest_sequence_ < 0) return stats;
  const int64_t window = params_.loss_window_chunks;
  // From just after the newest chunk seen that was sent more than loss_window_s before the
  // newest: what was missing before it was sent before it too.
  const auto cutoff_utime =
      highest_sent_utime_ - static_cast<int64_t>(params_.loss_window_s * 1e6);
  int64_t first = lowest_tracked_;
  for (int64_t s = lowest_tracked_; s <= highest_sequence_; ++s)
    if (seen_[static_cast<size_t>(s % window)] &&
        seen_sent_utime_[static_cast<size_t>(s % window)] < cutoff_utime)
      first = s + 1;
  bool in_run = false;
  for (int64_t s = first; s <= highest_sequence_ - params_.reorder_chunks; ++s) {
    const bool seen = seen_[static_cast<size_t>(s % window)];
    ++stats.expected;
    if (seen) ++stats.received;
    if (!seen && !in_run) ++stats.loss_runs;
    in_run = !seen;
  }
  return stats;
}

// ---------------------------------------------------------------------------------------------
// Repair

int ChunkAssembler::repairRequests(bool include_newest, std::vector<chunk_request_t>* out) const {
  int n = 0;
  for (const Slot& slot : slots_) {
    if (!slot.used || (!include_newest && slot.header.keyframe_id == newest_id_)) continue;
    const keyframe_chunk_t& h = slot.header;
    for (int g = 0; g < h.groups; ++g) {
      const Group& group = slot.groups[static_cast<size_t>(g)];
      const int k = originalsInGroup(slot.blocks, h.groups, g);
      if (group.held == k) continue;
      if (static_cast<size_t>(n) == out->size()) out->emplace_back();
      chunk_request_t& request = (*out)[static_cast<size_t>(n++)];
      request.utime = h.utime;
      request.vehicle_id = h.vehicle_id;
      request.keyframe_id = h.keyframe_id;
      request.group = static_cast<int16_t>(g);
      // A group whose recovery count is not known yet has only its originals to ask for.
      const int indices = k + std::max<int>(group.recovery, 0);
      request.indices.clear();
      for (int i = 0; i < indices && static_cast<int>(request.indices.size()) < k - group.held; ++i)
        if (!group.have.test(static_cast<size_t>(i))) request.indices.push_back(static_cast<uint8_t>(i));
      request.index_count = static_cast<int16_t>(request.indices.size());
    }
  }
  return n;
}

void restoreIeeeFloatingPoint() {
#if defined(__x86_64__) || defined(__i386__)
  constexpr unsigned kFlushToZero = 1u << 15, kDenormalsAreZero = 1u << 6;  // MXCSR
  _mm_setcsr(_mm_getcsr() & ~(kFlushToZero | kDenormalsAreZero));
#elif defined(__aarch64__)
  constexpr uint64_t kFlushToZero = uint64_t{1} << 24;  // FPCR.FZ
  uint64_t fpcr = 0;
  asm volatile("mrs %0, fpcr" : "=r"(fpcr));
  fpcr &= ~kFlushToZero;
  asm volatile("msr fpcr, %0" : : "r"(fpcr));
#endif
}

bool denormalsKept() {
  // volatile: computed now, under this thread's mode, not folded by the compiler.
  volatile float smallest_normal = std::numeric_limits<float>::min();
  volatile float denormal = std::numeric_limits<float>::denorm_min();
  const float halved = smallest_normal * 0.5f;  // a denormal result
  const float kept = denormal * 1.0f;           // a denormal input
  return halved != 0.0f && kept != 0.0f;
}

}  // namespace kinfly::link
