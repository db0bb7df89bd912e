// Keyframes in chunks (firmware/link/chunking.h): the wire types' bounded decoding, the MTU rule,
// round trips, recovery from any k of n, every kind of bad chunk counted, the memory bound, repair,
// loss statistics, and the redundancy rule against seeded Monte Carlo channels.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <cstdlib>
#include <new>
#include <cmath>
#include <cstdio>
#include <limits>
#include <map>
#include <numeric>
#include <random>
#include <thread>
#include <tuple>
#include <vector>

#include "kinfly/link/channels.h"
#include "kinfly/link/chunking.h"
#include "kinfly/link/decode.h"
#include "kinfly/link/repair.h"

#include "count_allocations.h"  // g_allocations: for the steady-state test

namespace kinfly::link {
namespace {

constexpr int32_t kVehicle = 7;
constexpr int64_t kUtime = 1'700'000'000'000'000;  // [us] a fixed capture time
constexpr int kIpUdpBytes = 28;                    // IPv4 and UDP headers

template <class T>
std::vector<uint8_t> encode(const T& message) {
  std::vector<uint8_t> bytes(static_cast<size_t>(message.getEncodedSize()));
  EXPECT_EQ(message.encode(bytes.data(), 0, static_cast<int>(bytes.size())),
            static_cast<int>(bytes.size()));
  return bytes;
}

std::vector<uint8_t> randomMessage(size_t size, uint32_t seed) {
  std::mt19937 rng(seed);
  std::vector<uint8_t> bytes(size);
  for (uint8_t& b : bytes) b = static_cast<uint8_t>(rng());
  return bytes;
}

ChunkEncoder::KeyframeIds ids(int64_t keyframe_id) { return {kUtime + keyframe_id, kVehicle, keyframe_id}; }

// The chunks of one encode, copied (the encoder reuses its own).
std::vector<keyframe_chunk_t> chunksOf(ChunkEncoder& encoder, const std::vector<uint8_t>& message,
                                       int64_t keyframe_id, int recovery) {
  const StatusOr<ChunkSpan> span = encoder.encode(message.data(), message.size(), ids(keyframe_id), recovery);
  EXPECT_TRUE(span.ok()) << span.status().message();
  if (!span.ok()) return {};
  return {span->begin(), span->end()};
}

ChunkStatus feed(ChunkAssembler& assembler, const keyframe_chunk_t& chunk) {
  const auto bytes = encode(chunk);
  return assembler.receive(bytes.data(), bytes.size());
}

// ---------------------------------------------------------------------------------------------
// Wire types

// Debian's cm256cc turns on flush-to-zero when it loads (this test program links it); the
// programs undo it.
TEST(ChunkWire, IeeeArithmeticIsRestoredAfterTheErasureCoderLoads) {
  restoreIeeeFloatingPoint();
  EXPECT_TRUE(denormalsKept());
  // On a thread made afterwards too.
  bool kept_on_thread = false;
  std::thread([&] { kept_on_thread = denormalsKept(); }).join();
  EXPECT_TRUE(kept_on_thread);
}

TEST(ChunkWire, ArraysAreTheLastFields) {
  // decodeMessage bounds the block and the index list by the int16 count just before them.
  keyframe_chunk_t chunk{};
  chunk.block.assign(13, 0xAB);
  chunk.block_size = 13;
  auto bytes = encode(chunk);
  const int fixed = keyframe_chunk_t().getEncodedSize();
  ASSERT_EQ(static_cast<int>(bytes.size()), fixed + 13);
  EXPECT_EQ(bytes[static_cast<size_t>(fixed) - 2], 0);
  EXPECT_EQ(bytes[static_cast<size_t>(fixed) - 1], 13);
  chunk_request_t request{};
  request.indices.assign(5, 0xCD);
  request.index_count = 5;
  bytes = encode(request);
  const int request_fixed = chunk_request_t().getEncodedSize();
  ASSERT_EQ(static_cast<int>(bytes.size()), request_fixed + 5);
  EXPECT_EQ(bytes[static_cast<size_t>(request_fixed) - 1], 5);
}

TEST(ChunkWire, DecodesWithinBoundsAndRejectsImpossibleHeaders) {
  ChunkEncoder encoder({});
  const auto chunks = chunksOf(encoder, randomMessage(5000, 1), 3, 2);
  ASSERT_FALSE(chunks.empty());
  const auto bytes = encode(chunks.back());
  keyframe_chunk_t got;
  ASSERT_TRUE(decodeMessage(bytes.data(), bytes.size(), DecodeBounds(), &got).ok());
  EXPECT_EQ(encode(got), bytes);

  // A negative or oversized block count is refused before the decoder sizes anything.
  const size_t count_at = static_cast<size_t>(keyframe_chunk_t().getEncodedSize()) - 2;
  for (uint16_t forged : {uint16_t{0xFFFF}, uint16_t{0x8000}, uint16_t{9001}}) {
    auto bad = bytes;
    bad[count_at] = static_cast<uint8_t>(forged >> 8);
    bad[count_at + 1] = static_cast<uint8_t>(forged);
    keyframe_chunk_t out;
    EXPECT_EQ(decodeMessage(bad.data(), bad.size(), DecodeBounds(), &out).status,
              DecodeStatus::kOutOfBounds) << forged;
    EXPECT_TRUE(out.block.empty());
  }

  const auto expectBad = [](keyframe_chunk_t c, const char* what) {
    const auto b = encode(c);
    keyframe_chunk_t out;
    const DecodeResult r = decodeMessage(b.data(), b.size(), DecodeBounds(), &out);
    EXPECT_EQ(r.status, DecodeStatus::kBadField) << what << ": " << r.detail;
  };
  const keyframe_chunk_t good = chunks.back();
  keyframe_chunk_t c = good;
  c.originals = static_cast<int16_t>(c.originals + 1);
  expectBad(c, "originals off the layout");
  c = good;
  c.recovery = static_cast<int16_t>(257 - c.originals);
  expectBad(c, "k + m above 256");
  c = good;
  c.index = static_cast<int16_t>(c.originals + c.recovery);
  expectBad(c, "index past the group");
  c = good;
  c.group = c.groups;
  expectBad(c, "group past the groups");
  c = good;
  c.groups = 0;
  expectBad(c, "no groups");
  c = good;
  c.message_bytes = static_cast<int32_t>(maxKeyframeMessageBytes(DecodeBounds()) + 1);
  expectBad(c, "message beyond a keyframe's bound");
  c = good;
  c.message_bytes = 0;
  expectBad(c, "empty message");
  c = good;
  c.block_size = 0;
  c.block.clear();
  expectBad(c, "empty block");
  c = good;
  c.vehicle_id = -1;
  expectBad(c, "negative vehicle");
  c = good;
  c.sequence = -1;
  expectBad(c, "negative sequence");
  c = good;
  c.sequence = std::numeric_limits<int64_t>::max();
  expectBad(c, "sequence a window past it would overflow");
  c = good;
  c.sequence = kMaxChunkSequence;
  keyframe_chunk_t decoded;
  const auto highest = encode(c);
  EXPECT_TRUE(decodeMessage(highest.data(), highest.size(), DecodeBounds(), &decoded).ok());
  c = good;
  c.sent_utime = std::numeric_limits<int64_t>::min();
  expectBad(c, "sent long before the epoch");
  c.sent_utime = -1;
  expectBad(c, "sent just before the epoch");

  chunk_request_t request{};
  request.vehicle_id = kVehicle;
  request.keyframe_id = 3;
  request.indices = {1, 2};
  request.index_count = 2;
  auto rb = encode(request);
  chunk_request_t out;
  EXPECT_TRUE(decodeMessage(rb.data(), rb.size(), DecodeBounds(), &out).ok());
  request.indices.clear();
  request.index_count = 0;
  rb = encode(request);
  EXPECT_EQ(decodeMessage(rb.data(), rb.size(), DecodeBounds(), &out).status, DecodeStatus::kBadField);
}

// ---------------------------------------------------------------------------------------------
// Encoder

TEST(ChunkEncoder, ParamsAreValidated) {
  EXPECT_TRUE(ChunkEncoder::Params().validate().ok());
  ChunkEncoder::Params p;
  p.mtu_bytes = 500;
  EXPECT_FALSE(p.validate().ok());
  p = {};
  p.max_originals_per_group = 256;
  EXPECT_FALSE(p.validate().ok());
  p = {};
  p.repair_keyframes = 0;
  EXPECT_FALSE(p.validate().ok());
  EXPECT_TRUE(ChunkAssembler::Params().validate().ok());
  ChunkAssembler::Params a;
  a.reorder_chunks = a.loss_window_chunks;
  EXPECT_FALSE(a.validate().ok());
  EXPECT_TRUE(RedundancyParams().validate().ok());
}

// No chunk datagram is fragmented: IP and UDP headers, LCM's header with the channel name, and the
// encoded chunk fit the MTU; for the longest channel name exactly.
TEST(ChunkEncoder, EveryDatagramFitsTheMtu) {
  for (int mtu : {576, 1500, 9000}) {
    ChunkEncoder::Params params;
    params.mtu_bytes = mtu;
    ChunkEncoder encoder(params);
    for (int vehicle : {0, kVehicle, kMaxVehicleId}) {
      const std::string channel = channelName(Channel::kKeyframeChunk, vehicle);
      const auto message = randomMessage(50'000, 4);
      const auto span = encoder.encode(message.data(), message.size(), {kUtime, vehicle, 1}, 4);
      ASSERT_TRUE(span.ok());
      for (const keyframe_chunk_t& chunk : *span) {
        const int lcm_datagram = 8 + static_cast<int>(channel.size()) + 1 + chunk.getEncodedSize();
        EXPECT_LE(lcm_datagram, mtu - kIpUdpBytes) << mtu << " " << vehicle;
        if (vehicle == kMaxVehicleId) {
          EXPECT_EQ(lcm_datagram, mtu - kIpUdpBytes);
        }
      }
    }
  }
}

TEST(ChunkEncoder, RefusesWhatTheWireCannotCarry) {
  ChunkEncoder encoder({});
  const std::vector<uint8_t> one(1, 7);
  EXPECT_FALSE(encoder.encode(one.data(), 0, ids(1), 1).ok());
  EXPECT_FALSE(encoder.encode(one.data(), 1, ids(1), 256).ok());
  EXPECT_FALSE(encoder.encode(one.data(), 1, ids(-1), 1).ok());
  EXPECT_FALSE(encoder.encode(one.data(), static_cast<size_t>(maxKeyframeMessageBytes(DecodeBounds())) + 1,
                              ids(1), 1)
                   .ok());
  depth_keyframe_t keyframe{};
  keyframe.payload_size = 10;  // more than the (empty) payload holds
  EXPECT_FALSE(encoder.encode(keyframe, 1).ok());
  keyframe.payload.assign(10, 1);
  keyframe.keyframe_id = 4;
  const auto span = encoder.encode(keyframe, 1);
  ASSERT_TRUE(span.ok()) << span.status().message();
  EXPECT_EQ(span->begin()->message_bytes, keyframe.getEncodedSize());
  EXPECT_EQ(span->begin()->keyframe_id, 4);
}

// ---------------------------------------------------------------------------------------------
// Round trips and recovery

struct Case {
  const char* name;
  size_t bytes;
};
std::vector<Case> sizes(int block) {
  return {{"one byte", 1},
          {"one block", static_cast<size_t>(block)},
          {"50 KB keyframe", 50'000},
          {"600 KB, several groups", 600'000}};
}

TEST(ChunkAssembler, RoundTripsEverySizeInOrder) {
  ChunkEncoder encoder({});
  for (const Case& c : sizes(encoder.blockBytes())) {
    const auto message = randomMessage(c.bytes, 5);
    const auto chunks = chunksOf(encoder, message, 10, 3);
    ChunkAssembler assembler(kVehicle, {});
    const int groups = chunks.front().groups;
    const int blocks = blockCount(static_cast<int64_t>(c.bytes), encoder.blockBytes());
    EXPECT_EQ(groups, (blocks + ChunkEncoder::Params().max_originals_per_group - 1) /
                          ChunkEncoder::Params().max_originals_per_group);
    int completed = 0;
    for (const keyframe_chunk_t& chunk : chunks) {
      const ChunkStatus s = feed(assembler, chunk);
      if (s == ChunkStatus::kCompleted) {
        ++completed;
        EXPECT_EQ(assembler.message(), message) << c.name;
      }
    }
    EXPECT_EQ(completed, 1) << c.name;
    EXPECT_EQ(assembler.counters().surplus, 3 * groups) << c.name;  // the recovery chunks
    EXPECT_EQ(assembler.counters().keyframes_recovered, 0) << c.name;
    if (c.bytes == 600'000) {
      EXPECT_GT(groups, 1);
    }
  }
}

// Any k distinct chunks of each group rebuild it: the worst case (exactly m lost per group),
// at random positions, in random order.
TEST(ChunkAssembler, AnyKOfNRecoverInAnyOrder) {
  ChunkEncoder encoder({});
  std::mt19937 rng(6);
  constexpr int kRecovery = 8;
  for (const Case& c : sizes(encoder.blockBytes())) {
    const auto message = randomMessage(c.bytes, 7);
    for (int trial = 0; trial < 10; ++trial) {
      auto chunks = chunksOf(encoder, message, trial, kRecovery);
      std::vector<keyframe_chunk_t> kept;
      for (int g = 0; g < chunks.front().groups; ++g) {
        std::vector<keyframe_chunk_t> group;
        for (const auto& chunk : chunks)
          if (chunk.group == g) group.push_back(chunk);
        std::shuffle(group.begin(), group.end(), rng);
        kept.insert(kept.end(), group.begin() + group.front().recovery, group.end());
      }
      std::shuffle(kept.begin(), kept.end(), rng);
      ChunkAssembler assembler(kVehicle, {});
      for (size_t i = 0; i < kept.size(); ++i) {
        const ChunkStatus s = feed(assembler, kept[i]);
        EXPECT_EQ(s, i + 1 == kept.size() ? ChunkStatus::kCompleted : ChunkStatus::kStored)
            << c.name << " chunk " << i << ": " << toString(s);
      }
      EXPECT_EQ(assembler.message(), message) << c.name;
    }
  }
}

// Once the encoder's kept keyframes and the assembler's slots have grown to the keyframe size,
// neither allocates: encoding, sending through datagrams, losses rebuilt, and completion.
TEST(ChunkAssembler, NothingAllocatesInSteadyState) {
  ChunkEncoder encoder({});
  ChunkAssembler assembler(kVehicle, {});
  const auto message = randomMessage(50'000, 18);
  std::vector<uint8_t> datagram(2000);
  const auto run = [&](int64_t first_id, int keyframes) {
    for (int64_t id = first_id; id < first_id + keyframes; ++id) {
      const auto span = encoder.encode(message.data(), message.size(), ids(id), 4);
      ASSERT_TRUE(span.ok());
      for (const keyframe_chunk_t& chunk : *span) {
        if (chunk.index == static_cast<int16_t>(id % 7)) continue;  // one lost per keyframe
        const int size = chunk.encode(datagram.data(), 0, static_cast<int>(datagram.size()));
        ASSERT_GT(size, 0);
        assembler.receive(datagram.data(), static_cast<size_t>(size));
      }
    }
  };
  run(0, 20);  // more than repair_keyframes and max_keyframes: every buffer has grown
  const int64_t before = g_allocations.load();
  run(20, 20);
  EXPECT_EQ(g_allocations.load() - before, 0);
  EXPECT_EQ(assembler.counters().keyframes_completed, 40);
}

// ---------------------------------------------------------------------------------------------
// Bad chunks: each counted by kind, none fatal

TEST(ChunkAssembler, CountsEveryKindOfBadChunk) {
  ChunkEncoder encoder({});
  const auto message = randomMessage(20'000, 8);
  const auto chunks = chunksOf(encoder, message, 5, 2);
  ChunkAssembler::Params params;
  params.max_message_bytes = 30'000;
  ChunkAssembler assembler(kVehicle, params);

  EXPECT_EQ(feed(assembler, chunks[0]), ChunkStatus::kStored);
  EXPECT_EQ(feed(assembler, chunks[0]), ChunkStatus::kDuplicate);

  keyframe_chunk_t other = chunks[1];
  other.message_digest ^= 1;  // another keyframe 5 (a restarted drone's, or forged)
  EXPECT_EQ(feed(assembler, other), ChunkStatus::kMismatch);
  other = chunks[1];
  other.vehicle_id = kVehicle + 1;
  EXPECT_EQ(feed(assembler, other), ChunkStatus::kMismatch);

  const auto big = randomMessage(40'000, 9);
  EXPECT_EQ(feed(assembler, chunksOf(encoder, big, 6, 0)[0]), ChunkStatus::kOversized);

  const auto datagram = encode(chunks[1]);
  EXPECT_EQ(assembler.receive(datagram.data(), datagram.size() - 1), ChunkStatus::kMalformed);
  EXPECT_EQ(assembler.receive(datagram.data(), 3), ChunkStatus::kMalformed);

  // Originals 1..k-2 and a recovery chunk in place of original k-1: rebuilt.
  const int k = chunks[0].originals;
  for (int i = 1; i < k - 1; ++i) EXPECT_EQ(feed(assembler, chunks[static_cast<size_t>(i)]), ChunkStatus::kStored);
  EXPECT_EQ(feed(assembler, chunks[static_cast<size_t>(k)]), ChunkStatus::kCompleted);
  EXPECT_EQ(assembler.message(), message);
  EXPECT_EQ(feed(assembler, chunks[static_cast<size_t>(k - 1)]), ChunkStatus::kSurplus);  // late
  EXPECT_EQ(feed(assembler, chunks.back()), ChunkStatus::kSurplus);

  // A block corrupted in a way the chunk's header cannot show: the digest catches it.
  auto corrupt = chunksOf(encoder, message, 20, 2);
  corrupt[3].block[100] ^= 0x40;
  for (int i = 0; i < k - 1; ++i) EXPECT_EQ(feed(assembler, corrupt[static_cast<size_t>(i)]), ChunkStatus::kStored);
  EXPECT_EQ(feed(assembler, corrupt[static_cast<size_t>(k - 1)]), ChunkStatus::kDigestMismatch);
  EXPECT_EQ(feed(assembler, corrupt.back()), ChunkStatus::kSurplus);

  // Far behind the newest keyframe: given up, its chunks stale.
  const auto old_chunks = chunksOf(encoder, message, 20 - params.window_keyframes, 2);
  EXPECT_EQ(feed(assembler, old_chunks[0]), ChunkStatus::kStale);

  const ChunkCounters& n = assembler.counters();
  EXPECT_EQ(n.duplicate, 1);
  EXPECT_EQ(n.mismatch, 2);
  EXPECT_EQ(n.oversized, 1);
  EXPECT_EQ(n.malformed, 2);
  EXPECT_EQ(n.surplus, 3);
  EXPECT_EQ(n.digest_mismatch, 1);
  EXPECT_EQ(n.stale, 1);
  EXPECT_EQ(n.keyframes_completed, 1);
  EXPECT_EQ(n.keyframes_recovered, 1);
  EXPECT_EQ(n.chunks, n.stored + n.duplicate + n.mismatch + n.oversized + n.malformed + n.surplus +
                          n.digest_mismatch + n.stale);
}

TEST(ChunkAssembler, NewerKeyframesEvictOldIncompleteOnes) {
  ChunkEncoder encoder({});
  const auto message = randomMessage(10'000, 10);
  ChunkAssembler::Params params;
  params.max_keyframes = 2;
  params.window_keyframes = 4;
  ChunkAssembler assembler(kVehicle, params);
  // Three incomplete keyframes with room for two: the first is given up.
  for (int64_t id : {1, 2, 3}) feed(assembler, chunksOf(encoder, message, id, 1)[0]);
  EXPECT_EQ(assembler.counters().keyframes_evicted, 1);
  // Keyframe 7 is 4 ahead of 3 (and 5 of 2): both are given up.
  feed(assembler, chunksOf(encoder, message, 7, 1)[0]);
  EXPECT_EQ(assembler.counters().keyframes_evicted, 3);
}

// Whatever arrives, the assembler holds at most max_bytes_held: here a flood of distinct keyframe
// ids, each declaring the largest message allowed, in small blocks.
TEST(ChunkAssembler, MemoryStaysBoundedUnderAFlood) {
  ChunkAssembler::Params params;
  params.max_bytes_held = 2 << 20;
  params.max_message_bytes = 1 << 20;
  params.max_keyframes = 8;
  ChunkAssembler assembler(kVehicle, params);
  std::mt19937 rng(11);
  keyframe_chunk_t chunk{};
  chunk.vehicle_id = kVehicle;
  for (int i = 0; i < 600; ++i) {
    chunk.keyframe_id = rng() % 100'000;
    chunk.sequence = i;
    // A fifth of them above max_message_bytes.
    chunk.message_bytes = static_cast<int32_t>(1 + rng() % (params.max_message_bytes * 5 / 4));
    chunk.block_size = static_cast<int16_t>(1 + rng() % 1400);
    const int blocks = blockCount(chunk.message_bytes, chunk.block_size);
    chunk.groups = static_cast<int16_t>(std::min(32767, (blocks + 254) / 255 + static_cast<int>(rng() % 3)));
    if (chunk.groups > blocks) chunk.groups = static_cast<int16_t>(blocks);
    chunk.group = static_cast<int16_t>(rng() % chunk.groups);
    chunk.originals = static_cast<int16_t>(originalsInGroup(blocks, chunk.groups, chunk.group));
    chunk.recovery = static_cast<int16_t>(rng() % (257 - chunk.originals));
    chunk.index = static_cast<int16_t>(rng() % (chunk.originals + chunk.recovery));
    chunk.block.assign(static_cast<size_t>(chunk.block_size), static_cast<uint8_t>(i));
    chunk.message_digest = static_cast<int64_t>(rng());
    assembler.add(chunk);
    ASSERT_LE(assembler.bytesHeld(), params.max_bytes_held) << "after chunk " << i;
  }
  EXPECT_GT(assembler.counters().keyframes_evicted, 0);
  EXPECT_GT(assembler.counters().oversized, 0);
}

TEST(ChunkAssembler, ARestartedDroneStartsAfresh) {
  ChunkEncoder first({});
  const auto message = randomMessage(10'000, 12);
  ChunkAssembler::Params params;
  params.restart_gap_chunks = 100;
  ChunkAssembler assembler(kVehicle, params);
  for (int64_t id = 0; id < 40; ++id)
    for (const auto& chunk : chunksOf(first, message, id, 1)) feed(assembler, chunk);
  EXPECT_EQ(assembler.counters().keyframes_completed, 40);
  ASSERT_GT(first.chunksSent(), params.restart_gap_chunks);
  // The new run's keyframe 0 differs from the old one and its sequence numbers start at 0 again.
  ChunkEncoder second({});
  const auto other = randomMessage(10'000, 13);
  for (const auto& chunk : chunksOf(second, other, 0, 1)) feed(assembler, chunk);
  EXPECT_EQ(assembler.counters().restarts, 1);
  EXPECT_EQ(assembler.counters().keyframes_completed, 41);
  EXPECT_EQ(assembler.message(), other);
}

TEST(ChunkAssembler, ARestartSoonAfterTheStartIsToldApartFromReordering) {
  ChunkAssembler assembler(kVehicle, {});  // restart_gap_chunks 1024, reorder_chunks 32
  const auto message = randomMessage(100'000, 15);  // 74 originals
  ChunkEncoder first({});
  // The sender stamps send times in sending order (kinfly-fw's link thread), 1 ms apart.
  int64_t sent_us = 1'000'000;
  std::vector<keyframe_chunk_t> late;
  for (int64_t id = 0; id < 3; ++id)
    for (auto chunk : chunksOf(first, message, id, 1)) {
      chunk.sent_utime = sent_us += 1000;
      if (id == 1 && chunk.index == 0) {
        late.push_back(chunk);  // held back: it arrives after keyframe 2, 75 chunks late
        continue;
      }
      feed(assembler, chunk);
    }
  // Reordered: a lower number, sent earlier than the highest. Not a restart.
  feed(assembler, late.front());
  EXPECT_EQ(assembler.counters().restarts, 0);
  // A drone restarted after 225 chunks numbers from 0 again, sending later: a restart.
  ChunkEncoder second({});
  const auto other = randomMessage(100'000, 16);
  for (auto chunk : chunksOf(second, other, 0, 1)) {
    chunk.sent_utime = sent_us += 1000;
    feed(assembler, chunk);
  }
  EXPECT_EQ(assembler.counters().restarts, 1);
  EXPECT_EQ(assembler.message(), other);
}

// ---------------------------------------------------------------------------------------------
// Repair

TEST(ChunkRepair, RequestsWhatIsMissingAndTheDroneResendsIt) {
  ChunkEncoder::Params params;
  params.repair_keyframes = 2;
  params.repair_chunks_per_keyframe = 10;
  ChunkEncoder encoder(params);
  const auto message = randomMessage(600'000, 14);
  auto chunks = chunksOf(encoder, message, 20, 2);
  ChunkAssembler assembler(kVehicle, {});
  // Group 1 loses 5 chunks (3 more than its 2 recovery chunks can cover), group 0 none.
  int dropped = 0;
  for (const auto& chunk : chunks) {
    if (chunk.group == 1 && chunk.index % 7 == 0 && dropped < 5) {
      ++dropped;
      continue;
    }
    feed(assembler, chunk);
  }
  std::vector<chunk_request_t> requests;
  EXPECT_EQ(assembler.repairRequests(false, &requests), 0);  // the newest may still be arriving
  ASSERT_EQ(assembler.repairRequests(true, &requests), 1);
  const chunk_request_t& request = requests[0];
  EXPECT_EQ(request.keyframe_id, 20);
  EXPECT_EQ(request.group, 1);
  EXPECT_EQ(request.index_count, 3);
  const auto wire = encode(request);
  chunk_request_t received;
  ASSERT_TRUE(decodeMessage(wire.data(), wire.size(), DecodeBounds(), &received).ok());

  const int64_t sent = encoder.chunksSent();
  ChunkStatus last = ChunkStatus::kStored;
  for (int i = 0; i < received.index_count; ++i) {
    const keyframe_chunk_t* chunk = encoder.resend(received, i);
    ASSERT_NE(chunk, nullptr);
    EXPECT_EQ(chunk->sequence, sent + i);  // a resend is a send: loss statistics stay right
    last = feed(assembler, *chunk);
  }
  EXPECT_EQ(last, ChunkStatus::kCompleted);
  EXPECT_EQ(assembler.message(), message);

  // Only kept keyframes, only real indices, only within the budget.
  chunk_request_t bad = received;
  bad.utime += 1;
  EXPECT_EQ(encoder.resend(bad, 0), nullptr);
  bad = received;
  bad.indices[0] = 255;
  EXPECT_EQ(encoder.resend(bad, 0), nullptr);
  EXPECT_EQ(encoder.resend(received, received.index_count), nullptr);
  for (int i = 3; i < params.repair_chunks_per_keyframe; ++i) EXPECT_NE(encoder.resend(received, 0), nullptr);
  EXPECT_EQ(encoder.resend(received, 0), nullptr);
  chunksOf(encoder, message, 21, 2);
  chunksOf(encoder, message, 22, 2);  // keyframe 20 is no longer kept
  chunk_request_t fresh = received;
  fresh.keyframe_id = 20;
  EXPECT_EQ(encoder.resend(fresh, 0), nullptr);
}

// ---------------------------------------------------------------------------------------------
// Loss channels and statistics

// Gilbert's two-state channel with stationary loss p and mean loss run L (L = 1/(1-p):
// independent loss), seeded.
// A whole one-byte keyframe per chunk, numbered like its sequence number.
keyframe_chunk_t tinyChunk(int64_t sequence) {
  keyframe_chunk_t chunk{};
  chunk.vehicle_id = kVehicle;
  chunk.keyframe_id = sequence;
  chunk.sequence = sequence;
  chunk.message_bytes = 1;
  chunk.block_size = 1;
  chunk.block = {42};
  chunk.message_digest = messageDigest(chunk.block.data(), 1);
  chunk.groups = 1;
  chunk.originals = 1;
  return chunk;
}

class GilbertChannel {
 public:
  GilbertChannel(double p, double run, uint32_t seed)
      : stay_bad_(1.0 - 1.0 / run), to_bad_(p * (1.0 / run) / (1.0 - p)), rng_(seed) {
    bad_ = uniform_(rng_) < p;
  }
  bool lose() {
    const bool lost = bad_;
    bad_ = uniform_(rng_) < (bad_ ? stay_bad_ : to_bad_);
    return lost;
  }

 private:
  double stay_bad_, to_bad_;
  std::mt19937_64 rng_;
  std::uniform_real_distribution<double> uniform_{0.0, 1.0};
  bool bad_ = false;
};

TEST(ChunkLoss, SequenceGapsMeasureTheChannel) {
  // 5 % loss in runs of mean 5, and 1 % independent loss (runs of 1/(1 - p)).
  struct Link {
    double p, run;
  };
  for (const Link& link : {Link{0.05, 5.0}, Link{0.01, 1.0 / 0.99}}) {
    ChunkAssembler::Params params;
    params.loss_window_chunks = 65536;
    ChunkAssembler assembler(kVehicle, params);
    GilbertChannel channel(link.p, link.run, 15);
    for (int64_t s = 0; s < 70'000; ++s)
      if (!channel.lose()) {
        EXPECT_EQ(assembler.add(tinyChunk(s)), ChunkStatus::kCompleted);
      }
    const LossStats stats = assembler.loss();
    EXPECT_EQ(stats.expected, params.loss_window_chunks - params.reorder_chunks);
    // Over 65 000 chunks the loss fraction's standard error is 0.25 % at 5 % in runs of 5 (runs
    // multiply the variance by about 2L - 1), and the mean run's is 4 % of it (some 650 runs of
    // standard deviation ~L): four of each.
    constexpr double kFractionTolerance = 0.01, kRunTolerance = 0.15;
    EXPECT_NEAR(stats.lossFraction(), link.p, kFractionTolerance) << link.p;
    EXPECT_NEAR(stats.meanLossRun(), link.run, kRunTolerance * link.run) << link.p;
  }
}

// A slow link's queue drops at the start (a drone that began too fast) are forgotten after
// loss_window_s, though the chunk window still holds them: they must not set the redundancy for
// minutes.
TEST(ChunkLoss, OnlyTheLastSecondsCount) {
  constexpr int64_t kChunkEvery_us = 20'000;  // 50 chunks a second: 2048 of them span 41 s
  const auto fly = [](ChunkAssembler* assembler) {
    for (int64_t s = 0; s < 1500; ++s) {
      keyframe_chunk_t chunk = tinyChunk(s);
      chunk.sent_utime = s * kChunkEvery_us;
      // Half of the first 200 (4 s) dropped, none after.
      if (s >= 200 || s % 2 == 0) assembler->add(chunk);
    }
    return assembler->loss();
  };
  ChunkAssembler::Params params;  // 2048 chunks, 10 s
  ChunkAssembler assembler(kVehicle, params);
  const LossStats recent = fly(&assembler);
  EXPECT_EQ(recent.lossFraction(), 0.0);
  // The last 10 s of sequence numbers (500 of them, less the newest not yet counted).
  EXPECT_NEAR(static_cast<double>(recent.expected), 500.0 - params.reorder_chunks, 1.0);
  // With a window long enough to hold the start, its drops count.
  params.loss_window_s = 60.0;
  ChunkAssembler longer(kVehicle, params);
  const LossStats all = fly(&longer);
  EXPECT_EQ(all.expected - all.received, 100);
}

TEST(ChunkLoss, ReorderingIsNotLoss) {
  ChunkAssembler assembler(kVehicle, {});
  for (int64_t s = 0; s < 1000; s += 2)
    for (int64_t t : {s + 1, s}) assembler.add(tinyChunk(t));  // every pair swapped
  const LossStats stats = assembler.loss();
  EXPECT_GT(stats.expected, 900);
  EXPECT_EQ(stats.received, stats.expected);
  EXPECT_EQ(stats.lossFraction(), 0.0);
}

// ---------------------------------------------------------------------------------------------
// The redundancy rule

double binomialTail(int n, double p, int m) {  // P(X > m), X ~ Binomial(n, p)
  double tail = 0.0;
  for (int x = m + 1; x <= n; ++x)
    tail += std::exp(std::lgamma(n + 1.0) - std::lgamma(x + 1.0) - std::lgamma(n - x + 1.0) +
                     x * std::log(p) + (n - x) * std::log1p(-p));
  return tail;
}

TEST(Redundancy, IndependentLossIsTheBinomialTail) {
  for (double p : {0.01, 0.05, 0.2}) {
    const LinkLoss loss{p, 1.0};
    for (int m : {0, 2, 6}) {
      // Double rounding over at most 256 terms.
      constexpr double kTolerance = 1e-12;
      EXPECT_NEAR(groupFailureProbability(36, m, loss), binomialTail(36 + m, p, m), kTolerance);
    }
  }
}

TEST(Redundancy, RecoveryChunksForAKeyframe) {
  const RedundancyParams params;
  constexpr int k = 36;  // a 50 KB keyframe in 1376-byte blocks
  const int at1 = recoveryChunks(k, {0.01, 1.0}, params);
  EXPECT_LE(at1, 0.15 * k);  // issue 14's target: at most 15 % more datagrams at 1 % loss
  EXPECT_LE(groupFailureProbability(k, at1, {0.01, 1.0}), params.target_failure);
  EXPECT_GT(groupFailureProbability(k, at1 - 1, {0.01, 1.0}), params.target_failure);
  const int at5 = recoveryChunks(k, {0.05, 1.0}, params);
  const int at10 = recoveryChunks(k, {0.10, 1.0}, params);
  const int bursty = recoveryChunks(k, {0.05, 5.0}, params);
  EXPECT_LT(at1, at5);
  EXPECT_LT(at5, at10);
  EXPECT_LT(at5, bursty);
  // An unmeasured link still gets the floor's protection; a broken one no more than GF(256) allows.
  EXPECT_GT(recoveryChunks(k, {0.0, 1.0}, params), 0);
  EXPECT_EQ(recoveryChunks(200, {0.5, 64.0}, params), 56);
  EXPECT_EQ(recoveryChunks(k, {std::nan(""), 1.0}, params), recoveryChunks(k, {0.5, 1.0}, params));
  std::printf("[ figures  ] m for k=%d: 1%% %d, 5%% %d, 10%% %d, 5%% in runs of 5 %d\n", k, at1, at5,
              at10, bursty);
}

// Keyframes of 50 KB through the encoder, a seeded lossy channel and the assembler, with m from
// the rule for the channel's own loss: at least 1 - target_failure of them arrive.
TEST(Redundancy, MonteCarloDeliversTheTarget) {
  const RedundancyParams params;
  struct Link {
    const char* name;
    double p, run;
  };
  for (const Link& link : {Link{"Bernoulli 1%", 0.01, 1.0 / 0.99}, Link{"Gilbert 5%, runs of 5", 0.05, 5.0}}) {
    ChunkEncoder encoder({});
    ChunkAssembler assembler(kVehicle, {});
    GilbertChannel channel(link.p, link.run, 16);
    const auto message = randomMessage(50'000, 17);
    const int k = encoder.originalsPerGroup(static_cast<int64_t>(message.size()));
    const int m = recoveryChunks(k, {link.p, link.run}, params);
    constexpr int kKeyframes = 4000;
    for (int id = 0; id < kKeyframes; ++id) {
      const auto span = encoder.encode(message.data(), message.size(), ids(id), m);
      ASSERT_TRUE(span.ok());
      for (const keyframe_chunk_t& chunk : *span)
        if (!channel.lose()) assembler.add(chunk);
    }
    const int64_t delivered = assembler.counters().keyframes_completed;
    const double fraction = static_cast<double>(delivered) / kKeyframes;
    // Losses are Binomial(N, <= target): allow three standard deviations above the mean.
    const double tolerance = 3.0 * std::sqrt(params.target_failure / kKeyframes);
    EXPECT_GE(fraction, 1.0 - params.target_failure - tolerance) << link.name;
    EXPECT_EQ(assembler.counters().digest_mismatch, 0);
    std::printf("[ figures  ] %s: k=%d m=%d, %lld of %d keyframes delivered (%.4f), %lld rebuilt\n",
                link.name, k, m, static_cast<long long>(delivered), kKeyframes, fraction,
                static_cast<long long>(assembler.counters().keyframes_recovered));
  }
}

// The ground's asks again (RepairScheduler) against a burst the redundancy was not chosen for:
// keyframes of 50 KB with the m of a link not yet measured as lossy, through 5 % loss in runs of
// 5 both ways (requests, and the resends, can be lost too). Asking once lost 4 % of them (85 of
// 2000); asking again while the drone keeps the chunks meets the redundancy's own target.
TEST(RepairScheduler, AskingAgainRidesOutABurst) {
  constexpr int kKeyframes = 2000;
  // Datagrams of other traffic (status, odometry) between two asks, which move the channel on.
  constexpr int kOtherDatagramsPerRetry = 8;
  const auto run = [&](int max_asks) {
    RepairScheduler::Params params;
    params.max_asks = max_asks;
    RepairScheduler scheduler(params);
    ChunkEncoder encoder({});
    ChunkAssembler assembler(kVehicle, {});
    GilbertChannel down(0.05, 5.0, 18), up(0.05, 5.0, 19);
    const auto message = randomMessage(50'000, 20);
    const int k = encoder.originalsPerGroup(static_cast<int64_t>(message.size()));
    const int m = recoveryChunks(k, {0.0, 1.0}, RedundancyParams());
    const auto retry_us = std::llround(params.retry_s * 1e6);
    int64_t now_us = 0;
    std::vector<chunk_request_t> requests;
    for (int id = 0; id < kKeyframes; ++id) {
      const auto span = encoder.encode(message.data(), message.size(), ids(id), m);
      EXPECT_TRUE(span.ok());
      if (!span.ok()) return int64_t{-1};
      for (const keyframe_chunk_t& chunk : *span)
        if (!down.lose()) assembler.add(chunk);
      for (int round = 0; round < max_asks; ++round, now_us += retry_us) {
        for (int i = 0; i < kOtherDatagramsPerRetry; ++i) down.lose(), up.lose();
        const int n = scheduler.due(assembler, true, now_us, &requests);
        for (int r = 0; r < n; ++r) {
          const chunk_request_t& request = requests[static_cast<size_t>(r)];
          if (up.lose()) continue;
          for (int i = 0; i < request.index_count; ++i)
            if (const keyframe_chunk_t* chunk = encoder.resend(request, i); chunk && !down.lose())
              assembler.add(*chunk);
        }
      }
    }
    EXPECT_EQ(assembler.counters().digest_mismatch, 0);
    std::printf("[ figures  ] k=%d m=%d, %d ask(s): %lld of %d keyframes delivered, %lld requests\n",
                k, m, max_asks, static_cast<long long>(assembler.counters().keyframes_completed),
                kKeyframes, static_cast<long long>(scheduler.requests()));
    return kKeyframes - assembler.counters().keyframes_completed;
  };
  const int64_t lost_asking_once = run(1);
  const int64_t lost_asking_again = run(RepairScheduler::Params().max_asks);
  EXPECT_LT(lost_asking_again, lost_asking_once);
  // As MonteCarloDeliversTheTarget: three standard deviations of a Binomial count above the target.
  const double target = RedundancyParams().target_failure;
  EXPECT_LE(static_cast<double>(lost_asking_again) / kKeyframes,
            target + 3.0 * std::sqrt(target / kKeyframes));
}

// One group of a keyframe incomplete: asked at once, again each retry time, max_asks times in
// all; and however many groups are incomplete at once, none is asked more.
TEST(RepairScheduler, AsksAgainWhileIncompleteAndNoMore) {
  const RepairScheduler::Params params;
  const auto retry_us = std::llround(params.retry_s * 1e6);
  ChunkEncoder::Params small_groups;
  small_groups.max_originals_per_group = 2;
  ChunkEncoder encoder(small_groups);
  ChunkAssembler::Params many;
  many.max_keyframes = 16;  // all of the keyframes below held at once, ~300 groups
  ChunkAssembler assembler(kVehicle, many);
  RepairScheduler scheduler(params);
  std::vector<chunk_request_t> requests;
  std::map<std::tuple<int64_t, int64_t, int>, int> asks;  // (utime, keyframe, group) -> asks
  int64_t now_us = 0;
  const auto ask = [&](bool include_newest) {
    const int n = scheduler.due(assembler, include_newest, now_us, &requests);
    for (int i = 0; i < n; ++i) {
      const chunk_request_t& r = requests[static_cast<size_t>(i)];
      ++asks[{r.utime, r.keyframe_id, r.group}];
    }
    return n;
  };
  const auto message = randomMessage(100'000, 21);
  // Keyframe 0 lacks group 0's first original (no recovery chunks); keyframe 1 arrives whole.
  std::vector<keyframe_chunk_t> first = chunksOf(encoder, message, 0, 0);
  ASSERT_GT(first.back().group, 30);  // 100 KB in groups of two blocks
  const keyframe_chunk_t lost = first[0];
  for (size_t c = 1; c < first.size(); ++c) assembler.add(first[c]);
  for (const auto& chunk : chunksOf(encoder, message, 1, 0)) assembler.add(chunk);
  EXPECT_EQ(ask(false), 1);
  now_us = retry_us - 1;
  EXPECT_EQ(ask(false), 0);
  for (int again = 1; again < params.max_asks; ++again) {
    now_us = again * retry_us;
    EXPECT_EQ(ask(false), 1) << again;
  }
  now_us += 10 * retry_us;
  EXPECT_EQ(ask(false), 0);
  EXPECT_TRUE(scheduler.asked(lost.utime, 0));
  // Seven more keyframes, every group missing a chunk, asked after every one: no group of any
  // keyframe is asked more than max_asks times, however many are held at once.
  for (int id = 2; id <= 8; ++id) {
    for (const auto& chunk : chunksOf(encoder, message, id, 0))
      if (chunk.index != 0) assembler.add(chunk);
    for (int round = 0; round < 2 * params.max_asks; ++round, now_us += retry_us) ask(true);
  }
  int most = 0;
  for (const auto& [group, n] : asks) most = std::max(most, n);
  EXPECT_EQ(most, params.max_asks);
  EXPECT_GT(asks.size(), 100u);
}

TEST(RepairScheduler, ParamsAreValidated) {
  RepairScheduler::Params params;
  EXPECT_TRUE(params.validate().ok());
  params.max_asks = 17;
  EXPECT_EQ(params.validate().message(), "max_asks must be in [1, 16]");
  params = {};
  params.retry_s = 0.0;
  EXPECT_EQ(params.validate().message(), "retry_s must be in [0.01, 10] s");
  EXPECT_THROW(RepairScheduler{params}, std::invalid_argument);
}

}  // namespace
}  // namespace kinfly::link
