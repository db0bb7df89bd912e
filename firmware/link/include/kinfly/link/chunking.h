// Keyframes in chunks (docs/wire.md, "Keyframes in chunks"): a keyframe too large for one Wi-Fi
// frame goes out as keyframe_chunk_t datagrams that IP never fragments, with Cauchy Reed-Solomon
// recovery chunks (cm256) per group, so a keyframe survives the loss of any m chunks of a group.
//
//   drone:  ChunkEncoder::encode(keyframe, m) -> publish each chunk; resend() answers a
//           chunk_request_t from the chunks it keeps.
//   ground: ChunkAssembler::receive(datagram) -> kCompleted: message() holds the encoded
//           depth_keyframe_t, for decodeMessage(); repairRequests() lists what is missing, loss()
//           the link's loss, from which the drone's m is chosen (recoveryChunks()).
// Both keep their buffers between keyframes: nothing allocates per chunk once they have grown to
// the largest keyframe seen.
#pragma once

#include <bitset>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "kinfly/chunk_request_t.hpp"
#include "kinfly/core/status.h"
#include "kinfly/depth_keyframe_t.hpp"
#include "kinfly/keyframe_chunk_t.hpp"
#include "kinfly/link/decode.h"

namespace kinfly::link {

// --- The layout, which the encoder, the decoder's field checks and the assembler share.
// A message of message_bytes is cut into blocks of block_size (the last one zero-padded); the
// blocks are split into `groups` consecutive groups whose sizes differ by at most one, the larger
// ones first.
int blockCount(int64_t message_bytes, int block_size);
int firstBlockOfGroup(int blocks, int groups, int group);
int originalsInGroup(int blocks, int groups, int group);

// keyframe_chunk_t.message_digest of a message (BLAKE2b-128, first 8 bytes big-endian).
int64_t messageDigest(const uint8_t* data, size_t size);

// Sequence numbers above this are forged: a drone sending 10^5 chunks a second reaches it after
// 2800 years, and the assembler's windows count up to a number one past the highest seen.
constexpr int64_t kMaxChunkSequence = int64_t{1} << 53;

// The fields of a chunk that contradict each other or the bounds (empty when none): what
// decodeMessage<keyframe_chunk_t> calls a bad field. max_message_bytes: of the whole keyframe.
std::string chunkProblem(const keyframe_chunk_t& chunk, int64_t max_message_bytes);

// --- How many recovery chunks a group needs.
// The link is modelled as Gilbert's two-state channel: a packet is lost in the bad state and
// delivered in the good one; the bad state lasts a geometric number of packets with mean L (the
// mean loss run) and the stationary loss fraction is p. With L = 1/(1 - p) this is independent
// (Bernoulli) loss, so L is raised to at least that.
struct LinkLoss {
  double loss_fraction = 0.0;  // p [0, 1): fraction of chunks lost
  double mean_loss_run = 1.0;  // L [1, inf): mean number of chunks lost in a row
};

struct RedundancyParams {
  // (0, 0.1]: the probability, under the model, that a group loses more than its m recovery chunks
  // (and so the keyframe, unless repaired).
  double target_failure = 1e-3;
  // [0, 0.5]: the loss fraction assumed at least, so that an unmeasured or lossless-looking link
  // still gets some protection.
  double min_loss_fraction = 0.005;
  // [0, 0.5]: measured loss is capped here; beyond it the link is broken, not lossy.
  double max_loss_fraction = 0.5;
  // [1, 64] chunks: the mean loss run is capped here (a longer outage no FEC group rides out).
  double max_mean_loss_run = 64.0;
  Status validate() const;
};

// The smallest m with P(more than m of the k + m chunks lost) <= target_failure, for
// k = originals in [1, 255]; at most 256 - k (GF(256)), which it returns when the target is out
// of reach. Exact for the model above (started in its stationary state), by dynamic programming
// over the group's chunks.
int recoveryChunks(int originals, const LinkLoss& loss, const RedundancyParams& params);
// The model's probability that a group of `originals` + `recovery` chunks loses more than
// `recovery` of them (what recoveryChunks() compares with the target).
double groupFailureProbability(int originals, int recovery, const LinkLoss& loss);

// --- The drone's side.
// The chunks of one keyframe, originals then recovery, group by group; valid until the encoder's
// next encode() (their sequence numbers until the next resend()).
struct ChunkSpan {
  const keyframe_chunk_t* first = nullptr;
  size_t count = 0;
  const keyframe_chunk_t* begin() const { return first; }
  const keyframe_chunk_t* end() const { return first + count; }
  size_t size() const { return count; }
};

class ChunkEncoder {
 public:
  struct Params {
    // [bytes] [576, 9000]: the IP MTU of the link (Wi-Fi and Ethernet: 1500); no chunk datagram,
    // with its IP, UDP and LCM headers, is larger, so IP never fragments one.
    int mtu_bytes = 1500;
    // [chunks] [1, 255]: originals per FEC group; a larger message is split into equal groups.
    // Larger groups need relatively fewer recovery chunks for the same loss; k + m <= 256.
    int max_originals_per_group = 128;
    // [keyframes] [1, 64]: the last keyframes whose chunks are kept for resend() (the one just
    // encoded included); the ground asks within a keyframe or two.
    int repair_keyframes = 4;
    // [chunks] [0, 4096]: resends per kept keyframe at most, whatever the requests ask.
    int repair_chunks_per_keyframe = 64;
    Status validate() const;
  };

  // The block size that keeps a chunk datagram within mtu_bytes: the MTU less the IP and UDP
  // headers, LCM's header (with the longest chunk channel name) and the chunk's own fields.
  static int blockBytesFor(int mtu_bytes);

  // params must validate().
  explicit ChunkEncoder(const Params& params);
  ~ChunkEncoder();
  ChunkEncoder(const ChunkEncoder&) = delete;
  ChunkEncoder& operator=(const ChunkEncoder&) = delete;

  // Grows every buffer, the kept keyframes' chunks included, for messages up to max_message_bytes
  // at any redundancy, so that encode() and resend() never allocate after this (a drone's link
  // thread reserves for its camera's largest keyframe at start).
  void reserve(int64_t max_message_bytes);

  int blockBytes() const { return block_bytes_; }
  // k of the largest group of a message of message_bytes: what recoveryChunks() is asked about.
  int originalsPerGroup(int64_t message_bytes) const;

  struct KeyframeIds {
    int64_t utime = 0;  // [us] the keyframe's capture time
    int32_t vehicle_id = 0;
    int64_t keyframe_id = 0;
  };
  // Cuts an encoded message (1 byte up to a depth_keyframe_t's bound) into chunks with
  // `recovery` in [0, 255] recovery chunks per group (fewer where k + m would pass 256).
  StatusOr<ChunkSpan> encode(const uint8_t* message, size_t size, const KeyframeIds& ids,
                             int recovery);
  // The same for a keyframe message, encoded into a buffer the encoder keeps.
  StatusOr<ChunkSpan> encode(const depth_keyframe_t& keyframe, int recovery);

  // The chunk that request.indices[i] asks for, stamped with the next sequence number, or
  // nullptr: the keyframe (utime and id) is no longer kept, the group or index does not exist, or
  // the keyframe's repair budget is spent. The caller checks the request's vehicle.
  const keyframe_chunk_t* resend(const chunk_request_t& request, int i);

  // Chunks stamped so far (encoded and resent): the next sequence number.
  int64_t chunksSent() const { return next_sequence_; }

 private:
  struct Kept {
    int64_t utime = 0;
    int64_t keyframe_id = -1;
    size_t count = 0;  // chunks in use at the front of `chunks`
    int resends = 0;
    std::vector<keyframe_chunk_t> chunks;
  };

  Params params_;
  int block_bytes_;
  std::vector<Kept> kept_;  // a ring of repair_keyframes
  size_t next_kept_ = 0;
  int64_t next_sequence_ = 0;
  std::vector<uint8_t> encoded_;   // encode(depth_keyframe_t)'s message
  std::vector<uint8_t> padded_;    // the message in whole blocks
  std::vector<uint8_t> recovery_;  // cm256's output for one group
};

// --- The ground's side.
enum class ChunkStatus {
  kStored,          // kept; its keyframe is not complete yet
  kCompleted,       // completed its keyframe: message() holds it, its digest checked
  kDuplicate,       // an index already held
  kSurplus,         // its group or keyframe is already complete: late redundancy, not an error
  kStale,           // its keyframe is window_keyframes or more behind the newest: given up
  kMismatch,        // another vehicle's, or its header disagrees with the keyframe's first chunk
  kOversized,       // message_bytes above Params::max_message_bytes (or more than max_bytes_held)
  kMalformed,       // refused by decodeMessage or chunkProblem()
  kDigestMismatch,  // completed the keyframe, whose digest is wrong: the keyframe is dropped
};
const char* toString(ChunkStatus status);

struct ChunkCounters {
  int64_t chunks = 0;  // everything given to receive() or add()
  int64_t stored = 0;  // kStored and kCompleted
  int64_t duplicate = 0;
  int64_t surplus = 0;
  int64_t stale = 0;
  int64_t mismatch = 0;
  int64_t oversized = 0;
  int64_t malformed = 0;
  int64_t digest_mismatch = 0;
  int64_t keyframes_completed = 0;
  int64_t keyframes_recovered = 0;  // of those, rebuilt with recovery chunks
  int64_t keyframes_evicted = 0;    // given up incomplete: too old, or for room
  int64_t restarts = 0;             // sequence numbers that went back: the drone restarted
};

// Loss seen in the chunks' sequence numbers over the assembler's window.
struct LossStats {
  int64_t expected = 0;   // sequence numbers in the window
  int64_t received = 0;   // of those, received
  int64_t loss_runs = 0;  // maximal runs of missing sequence numbers
  double lossFraction() const;
  double meanLossRun() const;  // 1 when nothing was lost
  LinkLoss linkLoss() const { return {lossFraction(), meanLossRun()}; }
};

class ChunkAssembler {
 public:
  struct Params {
    // [keyframes] [1, 64]: keyframes being assembled at once; the one that started first is
    // given up when another needs its place.
    int max_keyframes = 4;
    // [bytes] [64 KiB, 1 GiB]: what all keyframes being assembled may hold together (blocks and
    // their bookkeeping); the oldest are given up for room.
    int64_t max_bytes_held = int64_t{32} << 20;
    // [bytes] [1, 64 MiB + a keyframe's header]: the largest keyframe message accepted.
    int64_t max_message_bytes = maxKeyframeMessageBytes(DecodeBounds());
    // [keyframes] [1, 1024]: a keyframe this many ids behind the newest is given up (too late to
    // be worth repairing) and its chunks are stale.
    int window_keyframes = 8;
    // [chunks] [1, 2^40]: a sequence number this far below the highest seen means the drone
    // restarted (its counters went back to 0): everything being assembled is given up. So does
    // one more than reorder_chunks below it that was sent later than the highest.
    int64_t restart_gap_chunks = 1024;
    // [chunks] [64, 65536]: loss() covers the last this many sequence numbers.
    int loss_window_chunks = 2048;
    // [s] (0, 3600]: ... and only those sent in the last this many seconds. On a slow link
    // 2048 chunks span minutes, and the queue drops of a start that sent too fast would set the
    // drone's redundancy, and with it the keyframes' size, for all that time.
    double loss_window_s = 10.0;
    // [chunks] [0, loss_window_chunks / 2]: the newest this many sequence numbers are not yet
    // counted as lost, so that a chunk reordered by up to this much still counts as received.
    int reorder_chunks = 32;
    DecodeBounds bounds;  // for decoding datagrams (receive())
    Status validate() const;
  };

  // Assembles one vehicle's keyframes (chunks of others are kMismatch). params must validate().
  ChunkAssembler(int32_t vehicle_id, const Params& params);
  ~ChunkAssembler();
  ChunkAssembler(const ChunkAssembler&) = delete;
  ChunkAssembler& operator=(const ChunkAssembler&) = delete;

  // One datagram from the chunk channel, decoded within bounds, then add().
  ChunkStatus receive(const void* data, size_t size);
  ChunkStatus add(const keyframe_chunk_t& chunk);

  // After kCompleted: the whole encoded message (for decodeMessage<depth_keyframe_t>), until the
  // next receive() or add().
  const std::vector<uint8_t>& message() const { return message_; }

  const ChunkCounters& counters() const { return counters_; }
  LossStats loss() const;
  // [bytes] what the keyframes being assembled hold now (always <= max_bytes_held).
  int64_t bytesHeld() const;

  // Fills (*out)[0..n) with one request per incomplete group, asking for as many of its missing
  // indices (lowest first) as it lacks, and returns n; *out only grows. The newest keyframe may
  // still be arriving, so it is left out unless include_newest.
  int repairRequests(bool include_newest, std::vector<chunk_request_t>* out) const;
  // The newest keyframe id chunks were accepted of; -1 before any, or after a restart.
  int64_t newestKeyframeId() const { return newest_id_; }

 private:
  struct Group {
    std::bitset<256> have;  // indices held
    int16_t held = 0;
    int16_t recovery = -1;  // m, from the group's first chunk
  };
  struct Slot {
    bool used = false;
    int64_t started = 0;  // arrival number of its first chunk: the oldest is given up first
    keyframe_chunk_t header;  // the first chunk's fields (its block unused)
    int blocks = 0;
    int groups_complete = 0;
    std::vector<uint8_t> storage;  // block_size bytes per block position, group by group
    std::vector<uint8_t> held_index;  // per block position: the chunk index stored there
    std::vector<Group> groups;
    int64_t bytes() const;  // capacity of the three buffers
  };
  struct Done {
    int64_t keyframe_id = -1;
    int64_t digest = 0;
  };

  ChunkStatus store(Slot& slot, const keyframe_chunk_t& chunk);
  ChunkStatus complete(Slot& slot);
  Slot* findSlot(int64_t keyframe_id);
  Slot* newSlot(const keyframe_chunk_t& chunk);
  void evict(Slot& slot);
  void release(Slot& slot);
  void noteSequence(int64_t sequence, int64_t sent_utime);
  void restart();
  ChunkStatus count(ChunkStatus status);

  int32_t vehicle_id_;
  Params params_;
  std::vector<Slot> slots_;
  std::vector<Done> done_;  // a ring of the last window_keyframes completed
  size_t next_done_ = 0;
  int64_t arrivals_ = 0;
  int64_t newest_id_ = -1;  // -1: none since the start or a restart
  std::vector<uint8_t> message_;
  keyframe_chunk_t chunk_;  // receive()'s decoded datagram; its block keeps its capacity
  ChunkCounters counters_;

  // Sequence numbers seen: a ring of loss_window_chunks bits ending at the highest one, and
  // the sent_utime of each chunk seen.
  std::vector<bool> seen_;
  std::vector<int64_t> seen_sent_utime_;
  int64_t highest_sequence_ = -1;  // -1: none yet
  int64_t highest_sent_utime_ = 0;  // [us] that chunk's sent_utime
  int64_t lowest_tracked_ = 0;     // the window's first sequence number
};

// Debian's libcm256cc is built with -ffast-math, so loading it runs GCC's crtfastmath
// constructor: flush-to-zero and denormals-are-zero for the thread that loads it, and every
// thread made after (they inherit the mode): the engine's arithmetic, numpy in the ground
// station. kinfly computes in IEEE arithmetic, so each program that links the chunk code calls
// this first thing, before it makes a thread.
void restoreIeeeFloatingPoint();
// Whether this thread keeps denormal numbers (as input and as result) now.
bool denormalsKept();

}  // namespace kinfly::link
