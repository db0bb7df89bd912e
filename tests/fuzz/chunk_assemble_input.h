// How fuzz_chunk_assemble reads its input, shared with the corpus generator: a sequence of
// datagrams as the ground receives them on a chunk channel, each a 2-byte big-endian length and
// that many bytes (the last one cut at the input's end).
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "kinfly/link/chunking.h"

namespace kinfly::fuzz {

constexpr int32_t kChunkVehicle = 7;

// Small bounds, so that the fuzzer reaches eviction, the memory bound and a restart within a few
// kilobytes of input.
inline link::ChunkAssembler::Params chunkAssemblerParams() {
  link::ChunkAssembler::Params params;
  params.max_keyframes = 3;
  params.max_bytes_held = 256 << 10;
  params.max_message_bytes = 64 << 10;
  params.window_keyframes = 4;
  params.restart_gap_chunks = 64;
  params.loss_window_chunks = 64;
  params.reorder_chunks = 8;
  return params;
}

inline void appendDatagram(const std::vector<uint8_t>& datagram, std::vector<uint8_t>* input) {
  input->push_back(static_cast<uint8_t>(datagram.size() >> 8));
  input->push_back(static_cast<uint8_t>(datagram.size()));
  input->insert(input->end(), datagram.begin(), datagram.end());
}

}  // namespace kinfly::fuzz
