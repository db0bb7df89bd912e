// Writes the seed corpus of fuzz_chunk_assemble (tests/fuzz/corpus/chunk_assemble): small
// keyframes cut into chunks by the real encoder and delivered whole, with losses it can and cannot
// repair, reordered, duplicated, interleaved, corrupted, cut short, across a restart; each a file
// named after what it holds. Deterministic (fixed seeds), so rerunning it reproduces the committed
// files:
//   build/tests/make_chunk_assemble_corpus tests/fuzz/corpus/chunk_assemble
#include <algorithm>
#include <cstdio>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "chunk_assemble_input.h"
#include "kinfly/link/chunking.h"

namespace {

using kinfly::keyframe_chunk_t;
using Datagrams = std::vector<std::vector<uint8_t>>;

bool writeFile(const std::string& path, const std::vector<uint8_t>& bytes) {
  std::ofstream out(path, std::ios::binary);
  out.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
  return static_cast<bool>(out);
}

// A valid keyframe message of a 2000-byte payload: 5 blocks at the smallest MTU.
kinfly::depth_keyframe_t keyframe(int64_t keyframe_id) {
  kinfly::depth_keyframe_t m{};
  m.utime = 1'700'000'000'000'000 + keyframe_id;
  m.vehicle_id = kinfly::fuzz::kChunkVehicle;
  m.frame_id = keyframe_id * 10;
  m.keyframe_id = keyframe_id;
  m.camera.width = 64;
  m.camera.height = 48;
  m.camera.fx = m.camera.fy = 60.f;
  m.camera.cx = 31.5f;
  m.camera.cy = 23.5f;
  m.depth_scale_m = 0.001;
  m.T_world_cam.orientation_xyzw[3] = 1.0;
  m.tracking_status = kinfly::odometry_t::TRACKING_OK;
  m.encoding = kinfly::depth_keyframe_t::ENCODING_RVL;
  std::mt19937 rng(static_cast<uint32_t>(keyframe_id));
  for (int i = 0; i < 2000; ++i) m.payload.push_back(static_cast<uint8_t>(rng()));
  m.payload_size = static_cast<int32_t>(m.payload.size());
  return m;
}

Datagrams chunks(kinfly::link::ChunkEncoder& encoder, int64_t keyframe_id, int recovery) {
  Datagrams out;
  const auto span = encoder.encode(keyframe(keyframe_id), recovery);
  if (!span.ok()) return out;
  for (const keyframe_chunk_t& chunk : *span) {
    std::vector<uint8_t> bytes(static_cast<size_t>(chunk.getEncodedSize()));
    chunk.encode(bytes.data(), 0, static_cast<int>(bytes.size()));
    out.push_back(std::move(bytes));
  }
  return out;
}

kinfly::link::ChunkEncoder::Params encoderParams(int max_originals_per_group) {
  kinfly::link::ChunkEncoder::Params params;
  params.mtu_bytes = 576;
  params.max_originals_per_group = max_originals_per_group;
  return params;
}

std::vector<uint8_t> input(const Datagrams& datagrams) {
  std::vector<uint8_t> bytes;
  for (const auto& d : datagrams) kinfly::fuzz::appendDatagram(d, &bytes);
  return bytes;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: %s OUTDIR\n", argv[0]);
    return 2;
  }
  const std::string dir = argv[1];
  std::mt19937 rng(1);
  kinfly::link::ChunkEncoder encoder(encoderParams(255));
  int written = 0;
  bool ok = true;
  const auto write = [&](const char* name, const Datagrams& datagrams) {
    ok &= writeFile(dir + "/" + name, input(datagrams));
    ++written;
  };

  write("in_order", chunks(encoder, 1, 2));
  Datagrams d = chunks(encoder, 2, 2);
  d.erase(d.begin() + 1);
  d.erase(d.begin() + 3);
  std::shuffle(d.begin(), d.end(), rng);
  write("two_lost_reordered", d);
  d = chunks(encoder, 3, 2);
  d.erase(d.begin(), d.begin() + 3);
  write("three_lost", d);
  d = chunks(encoder, 4, 1);
  d.insert(d.begin() + 2, d[1]);
  d.push_back(d[0]);
  write("duplicates_and_surplus", d);
  Datagrams a = chunks(encoder, 5, 1), b = chunks(encoder, 6, 1);
  d.clear();
  for (size_t i = 0; i < std::max(a.size(), b.size()); ++i) {
    if (i < a.size()) d.push_back(a[i]);
    if (i < b.size()) d.push_back(b[i]);
  }
  write("two_keyframes_interleaved", d);
  d = chunks(encoder, 7, 1);
  d[2][d[2].size() - 7] ^= 0x20;
  write("corrupt_block", d);
  d = chunks(encoder, 8, 1);
  d[1].resize(d[1].size() / 2);
  write("cut_short", d);
  kinfly::link::ChunkEncoder groups_encoder(encoderParams(2));
  write("several_groups", chunks(groups_encoder, 9, 1));
  d.clear();
  for (int64_t id = 10; id < 20; ++id) {
    Datagrams one = chunks(encoder, id, 0);
    d.push_back(one.front());  // ten keyframes started, none finished: evictions
  }
  write("many_incomplete", d);
  kinfly::link::ChunkEncoder restarted(encoderParams(255));
  d = chunks(encoder, 20, 1);
  for (const auto& chunk : chunks(restarted, 0, 1)) d.push_back(chunk);
  write("restart", d);

  if (!ok) {
    std::fprintf(stderr, "cannot write into %s\n", dir.c_str());
    return 1;
  }
  std::printf("wrote %d inputs into %s\n", written, dir.c_str());
  return 0;
}
