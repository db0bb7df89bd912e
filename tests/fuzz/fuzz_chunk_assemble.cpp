// libFuzzer target for the ground's side of keyframes in chunks: datagrams (input layout:
// chunk_assemble_input.h) through decodeMessage<keyframe_chunk_t> and ChunkAssembler, and every
// completed message through decodeMessage<depth_keyframe_t>. Built with ASan and UBSan by
// `make fuzz`, which runs it on the committed corpus.
//
// Besides never reading or writing out of bounds: the assembler never holds more than its bound,
// and what it completes has the size its chunks declared. A fresh assembler per input keeps every
// finding reproducible from its input alone.
#include <cstdlib>
#include <vector>

#include "chunk_assemble_input.h"
#include "kinfly/link/chunking.h"
#include "kinfly/link/decode.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static kinfly::depth_keyframe_t keyframe;
  static std::vector<kinfly::chunk_request_t> requests;
  const kinfly::link::ChunkAssembler::Params params = kinfly::fuzz::chunkAssemblerParams();
  kinfly::link::ChunkAssembler assembler(kinfly::fuzz::kChunkVehicle, params);

  size_t at = 0;
  while (at + 2 <= size) {
    size_t length = (size_t{data[at]} << 8) | data[at + 1];
    at += 2;
    if (length > size - at) length = size - at;
    const kinfly::link::ChunkStatus status = assembler.receive(data + at, length);
    at += length;
    if (assembler.bytesHeld() > params.max_bytes_held) std::abort();
    if (status == kinfly::link::ChunkStatus::kCompleted) {
      const std::vector<uint8_t>& message = assembler.message();
      if (message.empty() || static_cast<int64_t>(message.size()) > params.max_message_bytes)
        std::abort();
      (void)kinfly::link::decodeMessage(message.data(), message.size(), kinfly::link::DecodeBounds(),
                                        &keyframe);
    }
  }
  const int n = assembler.repairRequests(true, &requests);
  for (int i = 0; i < n; ++i) {
    const kinfly::chunk_request_t& request = requests[static_cast<size_t>(i)];
    if (request.index_count < 1 || request.index_count != static_cast<int>(request.indices.size()))
      std::abort();
  }
  const kinfly::link::LossStats loss = assembler.loss();
  if (loss.received > loss.expected) std::abort();
  return 0;
}
