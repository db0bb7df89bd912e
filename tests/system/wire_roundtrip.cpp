// Cross-language check of the wire contract (driven by tests/system/test_wire.py): the
// lcm-gen Python types, which the tests and tools use to write and read messages, agree with the
// C++ ones that kinfly-fw and the ground station's native module decode with.
//   wire_roundtrip encode DIR   writes DIR/<type>.bin, one sample message per type, and prints
//                               "<type> <fingerprint hex>" per type
//   wire_roundtrip decode DIR   reads DIR/<type>.bin (written by Python from its own copy of the
//                               same samples), decodes each within bounds and prints
//                               "<type> ok" or "<type> <what differs>"
// The sample values are exactly representable in float32, so both languages agree bit for bit.
#include <cstdio>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "kinfly/link/decode.h"

namespace {

using namespace kinfly;

void samplePose(pose3d_t* pose) {
  const double p[3] = {1.25, -2.5, 0.75}, q[4] = {0.5, -0.5, 0.5, 0.5};
  for (int i = 0; i < 3; ++i) pose->position_m[i] = p[i];
  for (int i = 0; i < 4; ++i) pose->orientation_xyzw[i] = q[i];
}

depth_keyframe_t sampleKeyframe() {
  depth_keyframe_t m;
  m.utime = 1'700'000'000'123'456;
  m.vehicle_id = 7;
  m.frame_id = 1234;
  m.keyframe_id = 56;
  m.camera.width = 640;
  m.camera.height = 480;
  m.camera.fx = 535.25f;
  m.camera.fy = 539.125f;
  m.camera.cx = 320.5f;
  m.camera.cy = 247.75f;
  m.depth_scale_m = 0.0002;
  samplePose(&m.T_world_cam);
  m.tracking_status = odometry_t::TRACKING_OK;
  m.encoding = depth_keyframe_t::ENCODING_RVL_ZSTD;
  for (int i = 0; i < 1000; ++i) m.payload.push_back(static_cast<uint8_t>((i * 37) % 251));
  m.payload_size = static_cast<int32_t>(m.payload.size());
  return m;
}

odometry_t sampleOdometry() {
  odometry_t m;
  m.utime = 1'700'000'000'200'000;
  m.vehicle_id = 7;
  m.frame_id = 1240;
  samplePose(&m.T_world_cam);
  m.tracking_status = odometry_t::TRACKING_LOST;
  m.inlier_fraction = 0.625f;
  m.residual_m = 0.0078125f;
  m.reset_counter = 3;
  return m;
}

imu_t sampleImu() {
  imu_t m;
  m.utime = 1'700'000'000'201'000;
  m.vehicle_id = 7;
  const double w[3] = {0.125, -0.25, 0.5}, a[3] = {0.5, -0.25, -9.8125};
  for (int i = 0; i < 3; ++i) {
    m.angular_velocity_rad_s[i] = w[i];
    m.linear_acceleration_m_s2[i] = a[i];
  }
  m.temperature_c = 41.5f;
  m.has_pressure_altitude = true;
  m.pressure_altitude_m = 112.375f;
  return m;
}

ground_truth_t sampleGroundTruth() {
  ground_truth_t m;
  m.utime = 1'700'000'000'300'000;
  m.vehicle_id = 7;
  samplePose(&m.T_world_cam);
  return m;
}

pose_correction_t sampleCorrection() {
  pose_correction_t m;
  m.utime = 1'700'000'000'123'456;
  m.vehicle_id = 7;
  m.keyframe_id = 56;
  samplePose(&m.T_world_cam);
  m.reset_counter = 2;
  return m;
}

drone_status_t sampleDroneStatus() {
  drone_status_t m;
  m.utime = 1'700'000'000'400'000;
  m.vehicle_id = 7;
  m.depth_rate_hz = 30.f;
  m.odometry_rate_hz = 29.5f;
  m.keyframe_rate_hz = 5.25f;
  m.frames_captured = 9000;
  m.queue_drops = 12;
  m.keyframes_sent = 1500;
  m.keyframes_dropped = 4;
  m.last_keyframe_id = 1503;
  m.send_budget_bps = 8e6f;
  m.redundancy = 0.25f;
  m.keyframe_scale = 2;
  m.chunks_sent = 55'000;
  m.chunks_resent = 120;
  m.keyframes_skipped = 7;
  m.run_state = drone_status_t::RUN_FINAL;
  m.tracking_state = odometry_t::TRACKING_OK;
  m.link_state = drone_status_t::LINK_UP;
  m.sensor_state = drone_status_t::SENSOR_STALLED;
  m.sensor_connects = 2;
  m.sensor_stalls = 3;
  m.frames_skipped = 11;
  m.frames_lost = 13;
  m.rejected_unsigned = 1;
  m.rejected_wrong_key = 2;
  m.rejected_bad_mac = 3;
  m.rejected_stale = 4;
  m.rejected_replayed = 5;
  m.rejected_malformed = 6;
  m.rejected_unknown_channel = 7;
  m.rejected_wrong_vehicle = 8;
  m.corrections_accepted = 1400;
  m.corrections_unknown_keyframe = 9;
  m.commands_passed = 3;
  return m;
}

ground_status_t sampleGroundStatus() {
  ground_status_t m;
  m.utime = 1'700'000'000'450'000;
  m.vehicle_id = 7;
  m.keyframe_rate_hz = 5.25f;
  m.fused_rate_hz = 5.f;
  m.correction_rate_hz = 4.75f;
  m.keyframes_received = 1490;
  m.keyframes_skipped = 3;
  m.keyframes_dropped = 2;
  m.keyframes_lost = 5;
  m.corrections_sent = 1480;
  m.last_keyframe_id = 1499;
  m.run_state = ground_status_t::RUN_ACTIVE;
  m.tracking_state = odometry_t::TRACKING_OK;
  m.link_state = ground_status_t::LINK_STALE;
  m.link_loss = 0.0625f;
  m.link_loss_run = 2.5f;
  m.goodput_bps = 6.5e6f;
  m.queue_delay_ms = 12.5f;
  m.redundancy = 0.25f;
  m.keyframe_age_ms = 85.5f;
  m.chunks_received = 54'000;
  m.keyframes_recovered = 40;
  m.keyframes_incomplete = 2;
  m.repair_requests = 17;
  m.rejected_malformed = 6;
  m.rejected_unknown_channel = 7;
  m.rejected_wrong_vehicle = 8;
  return m;
}

signed_t sampleSigned() {
  signed_t m;
  m.utime = 1'700'000'000'500'000;
  m.vehicle_id = 7;
  m.key_id = -123456789;
  m.sequence = 1'700'000'000'000'001;
  for (int i = 0; i < 32; ++i) m.mac[i] = static_cast<uint8_t>(255 - i);
  const pose_correction_t inner = sampleCorrection();
  m.payload.resize(static_cast<size_t>(inner.getEncodedSize()));
  inner.encode(m.payload.data(), 0, static_cast<int>(m.payload.size()));
  m.payload_size = static_cast<int32_t>(m.payload.size());
  return m;
}

keyframe_chunk_t sampleChunk() {
  keyframe_chunk_t m;
  m.utime = 1'700'000'000'123'456;
  m.vehicle_id = 7;
  m.keyframe_id = 56;
  m.sequence = 2'024;
  m.sent_utime = 1'700'000'000'124'000;
  m.message_bytes = 3'000;
  m.message_digest = -1'234'567'890'123;
  m.groups = 2;
  m.group = 1;
  m.originals = 2;  // 3000 bytes in 600-byte blocks: 5 blocks, in groups of 3 and 2
  m.recovery = 2;
  m.index = 3;
  for (int i = 0; i < 600; ++i) m.block.push_back(static_cast<uint8_t>((i * 13) % 256));
  m.block_size = static_cast<int16_t>(m.block.size());
  return m;
}

chunk_request_t sampleRequest() {
  chunk_request_t m;
  m.utime = 1'700'000'000'123'456;
  m.vehicle_id = 7;
  m.keyframe_id = 56;
  m.group = 1;
  m.indices = {0, 3, 6};
  m.index_count = 3;
  return m;
}

template <class T>
std::vector<uint8_t> encode(const T& m) {
  std::vector<uint8_t> bytes(static_cast<size_t>(m.getEncodedSize()));
  m.encode(bytes.data(), 0, static_cast<int>(bytes.size()));
  return bytes;
}

template <class T>
bool encodeOne(const std::string& dir, const T& m) {
  const auto bytes = encode(m);
  std::ofstream out(dir + "/" + T::getTypeName() + ".bin", std::ios::binary);
  out.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
  std::printf("%s %016llx\n", T::getTypeName(), static_cast<unsigned long long>(T::getHash()));
  return static_cast<bool>(out);
}

template <class T>
bool decodeOne(const std::string& dir, const T& expected) {
  const std::string path = dir + "/" + T::getTypeName() + ".bin";
  std::ifstream in(path, std::ios::binary);
  const std::vector<uint8_t> bytes((std::istreambuf_iterator<char>(in)),
                                   std::istreambuf_iterator<char>());
  T got;
  const auto r = link::decodeMessage(bytes.data(), bytes.size(), link::DecodeBounds(), &got);
  if (!r.ok()) {
    std::printf("%s rejected: %s (%s)\n", T::getTypeName(), link::toString(r.status),
                r.detail.c_str());
    return false;
  }
  // Equal encodings of the decoded and the expected message mean every field is equal.
  if (encode(got) != encode(expected)) {
    std::printf("%s fields differ from the C++ sample\n", T::getTypeName());
    return false;
  }
  std::printf("%s ok\n", T::getTypeName());
  return true;
}

template <template <class> class Op>
bool forEachSample(const std::string& dir) {
  bool ok = true;
  ok &= Op<depth_keyframe_t>::run(dir, sampleKeyframe());
  ok &= Op<odometry_t>::run(dir, sampleOdometry());
  ok &= Op<imu_t>::run(dir, sampleImu());
  ok &= Op<ground_truth_t>::run(dir, sampleGroundTruth());
  ok &= Op<pose_correction_t>::run(dir, sampleCorrection());
  ok &= Op<drone_status_t>::run(dir, sampleDroneStatus());
  ok &= Op<ground_status_t>::run(dir, sampleGroundStatus());
  ok &= Op<signed_t>::run(dir, sampleSigned());
  ok &= Op<keyframe_chunk_t>::run(dir, sampleChunk());
  ok &= Op<chunk_request_t>::run(dir, sampleRequest());
  return ok;
}

template <class T>
struct Encode {
  static bool run(const std::string& dir, const T& m) { return encodeOne(dir, m); }
};
template <class T>
struct Decode {
  static bool run(const std::string& dir, const T& m) { return decodeOne(dir, m); }
};

}  // namespace

int main(int argc, char** argv) {
  const std::string mode = argc == 3 ? argv[1] : "";
  if (mode == "encode") return forEachSample<Encode>(argv[2]) ? 0 : 1;
  if (mode == "decode") return forEachSample<Decode>(argv[2]) ? 0 : 1;
  std::fprintf(stderr, "usage: wire_roundtrip encode|decode DIR\n");
  return 2;
}
