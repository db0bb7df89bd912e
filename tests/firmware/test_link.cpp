// The link's contract: channel names, bounded decoding of every message type, signing and
// verification (each rejection kind), key files, and the drone's correction receiver.
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "kinfly/link/channels.h"
#include "kinfly/link/chunking.h"
#include "kinfly/link/conversions.h"
#include "kinfly/link/decode.h"
#include "kinfly/link/signing.h"
#include "kinfly/link/uplink.h"
#include "kinfly/motor_command_t.hpp"

namespace kinfly::link {
namespace {

constexpr int32_t kVehicle = 7;
constexpr int64_t kNow = 1'700'000'000'000'000;  // [us] a fixed wall-clock time
constexpr int64_t kSecond = 1'000'000;           // [us]

template <class T>
std::vector<uint8_t> encode(const T& message) {
  std::vector<uint8_t> bytes(static_cast<size_t>(message.getEncodedSize()));
  EXPECT_EQ(message.encode(bytes.data(), 0, static_cast<int>(bytes.size())),
            static_cast<int>(bytes.size()));
  return bytes;
}

void setIdentityPose(pose3d_t* pose) {
  pose->position_m[0] = 0.5;
  pose->position_m[1] = -0.25;
  pose->position_m[2] = 1.0;
  pose->orientation_xyzw[0] = pose->orientation_xyzw[1] = pose->orientation_xyzw[2] = 0.0;
  pose->orientation_xyzw[3] = 1.0;
}

depth_keyframe_t sampleKeyframe(int payload_bytes) {
  depth_keyframe_t m;
  m.utime = kNow;
  m.vehicle_id = kVehicle;
  m.frame_id = 42;
  m.keyframe_id = 3;
  m.camera.width = 640;
  m.camera.height = 480;
  m.camera.fx = 535.4f;
  m.camera.fy = 539.2f;
  m.camera.cx = 320.1f;
  m.camera.cy = 247.6f;
  m.depth_scale_m = 1.0 / 5000.0;
  setIdentityPose(&m.T_world_cam);
  m.tracking_status = odometry_t::TRACKING_OK;
  m.encoding = depth_keyframe_t::ENCODING_RVL;
  m.payload.resize(static_cast<size_t>(payload_bytes));
  for (int i = 0; i < payload_bytes; ++i) m.payload[i] = static_cast<uint8_t>(i * 31 + 5);
  m.payload_size = payload_bytes;
  return m;
}

pose_correction_t sampleCorrection(int64_t keyframe_id) {
  pose_correction_t m;
  m.utime = kNow - kSecond / 2;
  m.vehicle_id = kVehicle;
  m.keyframe_id = keyframe_id;
  setIdentityPose(&m.T_world_cam);
  m.reset_counter = 0;
  return m;
}

Key testKey(uint8_t seed) {
  Key key;
  for (size_t i = 0; i < key.bytes.size(); ++i) key.bytes[i] = static_cast<uint8_t>(seed + 7 * i);
  key.id = keyIdOf(key.bytes);
  return key;
}

// ---------------------------------------------------------------------------------------------
// Channels

TEST(Channels, NamesCarryTheVehicleAndParseBack) {
  for (Channel c : {Channel::kDepth, Channel::kKeyframe, Channel::kOdometry, Channel::kImu,
                    Channel::kStatus, Channel::kCorrection, Channel::kGroundStatus,
                    Channel::kGroundTruth, Channel::kKeyframeChunk, Channel::kChunkRequest,
                    Channel::kMotorCommand, Channel::kCommand, Channel::kFlight,
                    Channel::kSimState}) {
    for (int vehicle : {0, 7, kMaxVehicleId}) {
      const std::string name = channelName(c, vehicle);
      EXPECT_NE(name.find(std::to_string(vehicle)), std::string::npos) << name;
      const auto parsed = parseChannel(name);
      ASSERT_TRUE(parsed) << name;
      EXPECT_EQ(parsed->channel, c);
      EXPECT_EQ(parsed->vehicle_id, vehicle);
    }
  }
  EXPECT_EQ(channelName(Channel::kKeyframe, 7), "KINFLY_7_KEYFRAME");
}

TEST(Channels, ForeignOrMalformedNamesDoNotParse) {
  for (const char* name : {"", "KINFLY_", "KINFLY_7", "KINFLY_7_", "KINFLY_7_NOPE", "KINFLY_x_IMU",
                           "KINFLY_07_IMU", "KINFLY_65536_IMU", "KINFLY_123456_IMU",
                           "OTHER_7_IMU", "kinfly_7_imu", "KINFLY_7_IMU_", "KINFLY_-1_IMU",
                           "KINFLY_+1_IMU", "KINFLY_99999999999999999999_IMU"})
    EXPECT_FALSE(parseChannel(name)) << name;
}

// ---------------------------------------------------------------------------------------------
// Bounded decoding

// decodeMessage bounds a variable array by reading its count just before it, at the end of the
// fixed part: that is only right if the generated encoder puts them there.
template <class T>
void expectTrailingPayloadLayout(T message) {
  const int fixed = T().getEncodedSize();
  message.payload.assign(13, 0xAB);
  message.payload_size = 13;
  const auto bytes = encode(message);
  ASSERT_EQ(static_cast<int>(bytes.size()), fixed + 13);
  EXPECT_EQ(bytes[fixed - 1], 13);
  EXPECT_EQ(bytes[fixed - 4] | bytes[fixed - 3] | bytes[fixed - 2], 0);
  EXPECT_EQ(bytes.back(), 0xAB);
}

TEST(Channels, GroundSubscriptionsKeepKeyframesApart) {
  const Subscriptions one = groundSubscriptions(7);
  EXPECT_EQ(one.keyframes, "KINFLY_7_KEYFRAME(_CHUNK)?");
  EXPECT_EQ(one.others, "KINFLY_7_(?!KEYFRAME(_CHUNK)?$).*");
  const Subscriptions every = groundSubscriptions(std::nullopt);
  EXPECT_EQ(every.keyframes, "KINFLY_[0-9]+_KEYFRAME(_CHUNK)?");
  EXPECT_EQ(every.others, "KINFLY_[0-9]+_(?!KEYFRAME(_CHUNK)?$).*");
}

// ---------------------------------------------------------------------------------------------
// Conversions

TEST(Conversions, PosesRoundTripWithNonNegativeW) {
  // A rotation of 200 degrees: Eigen's quaternion of it may come out with w < 0.
  Pose T = Pose::Identity();
  T.linear() = Eigen::AngleAxisd(200.0 * M_PI / 180.0, Eigen::Vector3d(1, 2, 3).normalized())
                   .toRotationMatrix();
  T.translation() = Eigen::Vector3d(1.5, -2.0, 0.25);
  pose3d_t message;
  writePose(T, &message);
  EXPECT_GE(message.orientation_xyzw[3], 0.0);
  EXPECT_TRUE(readPose(message).isApprox(T, 1e-12));
}

TEST(Conversions, TrackingCodesRoundTrip) {
  for (TrackingStatus status : {TrackingStatus::kFirstFrame, TrackingStatus::kOk,
                                TrackingStatus::kLost, TrackingStatus::kGivenPose})
    EXPECT_EQ(trackingOf(trackingCode(status)), status);
  EXPECT_EQ(trackingCode(std::nullopt), odometry_t::TRACKING_NONE);
  EXPECT_EQ(trackingOf(odometry_t::TRACKING_NONE), std::nullopt);
  EXPECT_EQ(trackingOf(17), std::nullopt);
}

TEST(Conversions, CameraRoundTrips) {
  const PinholeCamera camera{525.f, 526.f, 319.5f, 239.5f, 640, 480};
  const PinholeCamera back = cameraOf(cameraMessage(camera));
  EXPECT_EQ(back.fx, camera.fx);
  EXPECT_EQ(back.cy, camera.cy);
  EXPECT_EQ(back.width, camera.width);
  EXPECT_EQ(back.height, camera.height);
}

TEST(Conversions, DroneHealthFillsTheStatus) {
  DroneHealth health;
  health.utime = 1'700'000'000'000'000;
  health.is_final = true;
  health.keyframe_rate_hz = 5.f;
  health.keyframes_sent = 12;
  health.last_keyframe_id = 11;
  health.tracking = TrackingStatus::kOk;
  health.link = LinkState::kStale;
  health.sensor = SensorState::kStalled;
  health.sensor_stalls = 2;
  health.rejects.bad_mac = 3;
  health.corrections_unknown_keyframe = 1;
  drone_status_t status{};
  status.vehicle_id = 7;
  fillDroneStatus(health, &status);
  EXPECT_EQ(status.vehicle_id, 7);  // the caller's
  EXPECT_EQ(status.utime, health.utime);
  EXPECT_EQ(status.run_state, drone_status_t::RUN_FINAL);
  EXPECT_EQ(status.keyframe_rate_hz, 5.f);
  EXPECT_EQ(status.keyframes_sent, 12);
  EXPECT_EQ(status.last_keyframe_id, 11);
  EXPECT_EQ(status.tracking_state, odometry_t::TRACKING_OK);
  EXPECT_EQ(status.link_state, drone_status_t::LINK_STALE);
  EXPECT_EQ(status.sensor_state, drone_status_t::SENSOR_STALLED);
  EXPECT_EQ(status.sensor_stalls, 2);
  EXPECT_EQ(status.rejected_bad_mac, 3);
  EXPECT_EQ(status.corrections_unknown_keyframe, 1);

  fillDroneStatus(DroneHealth(), &status);
  EXPECT_EQ(status.run_state, drone_status_t::RUN_ACTIVE);
  EXPECT_EQ(status.tracking_state, odometry_t::TRACKING_NONE);
  EXPECT_EQ(status.link_state, drone_status_t::LINK_UNKNOWN);
  EXPECT_EQ(status.sensor_state, drone_status_t::SENSOR_STREAMING);
  EXPECT_EQ(status.last_keyframe_id, -1);
}

TEST(Decode, PayloadSizeIsTheLastFixedField) {
  expectTrailingPayloadLayout(sampleKeyframe(0));
  expectTrailingPayloadLayout(signed_t());
}

TEST(Decode, RoundTripsEveryField) {
  const depth_keyframe_t sent = sampleKeyframe(1000);
  const auto bytes = encode(sent);
  depth_keyframe_t got;
  const DecodeResult r = decodeMessage(bytes.data(), bytes.size(), DecodeBounds(), &got);
  ASSERT_TRUE(r.ok()) << r.detail;
  EXPECT_EQ(encode(got), bytes);
}

TEST(Decode, EveryTruncationIsRejected) {
  const auto bytes = encode(sampleKeyframe(300));
  for (size_t n = 0; n < bytes.size(); ++n) {
    depth_keyframe_t got;
    const DecodeResult r = decodeMessage(bytes.data(), n, DecodeBounds(), &got);
    EXPECT_EQ(r.status, DecodeStatus::kTruncated) << n << " bytes: " << r.detail;
  }
}

TEST(Decode, TrailingBytesAreRejected) {
  auto bytes = encode(sampleCorrection(1));
  bytes.push_back(0);
  pose_correction_t got;
  EXPECT_EQ(decodeMessage(bytes.data(), bytes.size(), DecodeBounds(), &got).status,
            DecodeStatus::kTrailingBytes);
}

TEST(Decode, WrongFingerprintIsRejected) {
  const auto bytes = encode(sampleCorrection(1));
  odometry_t got;
  EXPECT_EQ(decodeMessage(bytes.data(), bytes.size(), DecodeBounds(), &got).status,
            DecodeStatus::kWrongType);
  EXPECT_TRUE(hasFingerprint<pose_correction_t>(bytes.data(), bytes.size()));
  EXPECT_FALSE(hasFingerprint<signed_t>(bytes.data(), bytes.size()));
}

// A forged count must be refused before anything is sized from it: -1 and 2^31-1 would make the
// generated decoder resize to gigabytes.
TEST(Decode, ForgedPayloadSizesAreRejectedBeforeAllocating) {
  auto bytes = encode(sampleKeyframe(16));
  const size_t count_at = static_cast<size_t>(depth_keyframe_t().getEncodedSize()) - 4;
  for (uint32_t forged : {0xFFFFFFFFu, 0x7FFFFFFFu, 0x80000000u, uint32_t{8u << 20} + 1}) {
    for (int i = 0; i < 4; ++i) bytes[count_at + i] = static_cast<uint8_t>(forged >> (24 - 8 * i));
    depth_keyframe_t got;
    const DecodeResult r = decodeMessage(bytes.data(), bytes.size(), DecodeBounds(), &got);
    EXPECT_EQ(r.status, DecodeStatus::kOutOfBounds) << forged;
    EXPECT_TRUE(got.payload.empty());
  }
  // A count within the bounds but longer than the datagram: the payload is longer than sent.
  const uint32_t longer = 17;
  for (int i = 0; i < 4; ++i) bytes[count_at + i] = static_cast<uint8_t>(longer >> (24 - 8 * i));
  depth_keyframe_t got;
  EXPECT_EQ(decodeMessage(bytes.data(), bytes.size(), DecodeBounds(), &got).status,
            DecodeStatus::kTruncated);
}

TEST(Decode, ImpossibleFieldsAreRejected) {
  const DecodeBounds bounds;
  const auto expectBad = [&](const depth_keyframe_t& m, const char* what) {
    const auto bytes = encode(m);
    depth_keyframe_t got;
    const DecodeResult r = decodeMessage(bytes.data(), bytes.size(), bounds, &got);
    EXPECT_EQ(r.status, DecodeStatus::kBadField) << what;
    EXPECT_FALSE(r.detail.empty()) << what;
  };
  auto m = sampleKeyframe(8);
  m.camera.width = bounds.max_width_px + 1;
  expectBad(m, "too wide");
  m = sampleKeyframe(8);
  m.camera.height = 0;
  expectBad(m, "no rows");
  m = sampleKeyframe(8);
  m.camera.width = -640;
  expectBad(m, "negative width");
  m = sampleKeyframe(8);
  m.encoding = 9;
  expectBad(m, "unknown encoding");
  m = sampleKeyframe(8);
  m.tracking_status = 17;
  expectBad(m, "unknown tracking status");
  m = sampleKeyframe(8);
  m.T_world_cam.position_m[1] = std::numeric_limits<double>::quiet_NaN();
  expectBad(m, "NaN position");
  m = sampleKeyframe(8);
  m.T_world_cam.orientation_xyzw[3] = 2.0;
  expectBad(m, "non-unit quaternion");
  m = sampleKeyframe(8);
  m.depth_scale_m = 0.0;
  expectBad(m, "zero depth scale");
  m = sampleKeyframe(8);
  m.camera.fx = std::numeric_limits<float>::infinity();
  expectBad(m, "infinite focal length");
  m = sampleKeyframe(8);
  m.vehicle_id = -1;
  expectBad(m, "negative vehicle");

  // A raw capture has no pose yet: its pose fields are not checked.
  m = sampleKeyframe(8);
  m.tracking_status = odometry_t::TRACKING_NONE;
  m.T_world_cam.orientation_xyzw[3] = 0.0;
  const auto bytes = encode(m);
  depth_keyframe_t got;
  EXPECT_TRUE(decodeMessage(bytes.data(), bytes.size(), bounds, &got).ok());
}

flight_status_t sampleFlightStatus() {
  flight_status_t m{};
  m.vehicle_id = kVehicle;
  m.mode = flight_status_t::MODE_HOLD;
  m.command_result = flight_status_t::REFUSED_AUTOPILOT_NOT_READY;
  m.rotors = flight_status_t::ROTORS_NONE;
  m.q_world_body_xyzw[3] = 1.0;
  writePose(Pose::Identity(), &m.T_world_map);
  return m;
}

// The flight status's values: every enum within its constants, state and setpoint finite.
TEST(Decode, FlightStatusFieldsAreChecked) {
  const auto decodes = [](const flight_status_t& m) {
    const auto bytes = encode(m);
    flight_status_t got;
    return decodeMessage(bytes.data(), bytes.size(), DecodeBounds(), &got);
  };
  EXPECT_TRUE(decodes(sampleFlightStatus()).ok());
  const std::vector<std::pair<const char*, void (*)(flight_status_t&)>> wrong = {
      {"mode", [](flight_status_t& m) { m.mode = flight_status_t::MODE_HANDED_OVER + 1; }},
      {"command_result", [](flight_status_t& m) { m.command_result = -1; }},
      {"command_kind", [](flight_status_t& m) { m.command_kind = flight_command_t::LAND + 1; }},
      {"rotors", [](flight_status_t& m) { m.rotors = motor_command_t::FLYING + 1; }},
      {"not finite", [](flight_status_t& m) { m.setpoint_world_m[2] = std::nan(""); }},
      {"orientation", [](flight_status_t& m) { m.T_world_map.orientation_xyzw[3] = 2.0; }},
      {"vehicle", [](flight_status_t& m) { m.vehicle_id = -3; }},
  };
  for (const auto& [what, spoil] : wrong) {
    flight_status_t m = sampleFlightStatus();
    spoil(m);
    const DecodeResult r = decodes(m);
    EXPECT_EQ(r.status, DecodeStatus::kBadField) << what;
    EXPECT_NE(r.detail.find(what), std::string::npos) << r.detail;
  }
}


// A pressure altitude is read only where the sample says it carries one.
TEST(Decode, AnImuSamplesPressureAltitudeIsCheckedWhereItIsSet) {
  imu_t m{};
  m.vehicle_id = kVehicle;
  m.linear_acceleration_m_s2[2] = -9.81;
  m.temperature_c = NAN;
  m.pressure_altitude_m = NAN;
  imu_t got;
  const auto without = encode(m);
  ASSERT_TRUE(decodeMessage(without.data(), without.size(), DecodeBounds(), &got).ok());
  EXPECT_FALSE(got.has_pressure_altitude);
  m.has_pressure_altitude = true;
  const auto not_finite = encode(m);
  const DecodeResult r =
      decodeMessage(not_finite.data(), not_finite.size(), DecodeBounds(), &got);
  EXPECT_EQ(r.status, DecodeStatus::kBadField);
  EXPECT_EQ(r.detail, "pressure_altitude_m is not finite");
  m.pressure_altitude_m = 231.5f;
  const auto with = encode(m);
  ASSERT_TRUE(decodeMessage(with.data(), with.size(), DecodeBounds(), &got).ok());
  EXPECT_EQ(got.pressure_altitude_m, 231.5f);
}
// Seeded random corruption of valid messages of every type: never a crash (ASan runs this too),
// and whatever is accepted re-encodes to exactly the bytes received.
template <class T>
void fuzzDecode(const std::vector<uint8_t>& valid, uint32_t seed) {
  std::mt19937 rng(seed);
  for (int trial = 0; trial < 2000; ++trial) {
    std::vector<uint8_t> bytes = valid;
    const int flips = 1 + static_cast<int>(rng() % 4);
    for (int f = 0; f < flips; ++f)
      bytes[rng() % bytes.size()] ^= static_cast<uint8_t>(1 + rng() % 255);
    if (rng() % 4 == 0) bytes.resize(rng() % (bytes.size() + 1));
    T got;
    if (decodeMessage(bytes.data(), bytes.size(), DecodeBounds(), &got).ok()) {
      EXPECT_EQ(encode(got), bytes);
    }
  }
}

TEST(Decode, RandomCorruptionNeverCrashes) {
  fuzzDecode<depth_keyframe_t>(encode(sampleKeyframe(64)), 1);
  fuzzDecode<pose_correction_t>(encode(sampleCorrection(5)), 2);
  drone_status_t status{};
  status.vehicle_id = kVehicle;
  fuzzDecode<drone_status_t>(encode(status), 3);
  fuzzDecode<flight_status_t>(encode(sampleFlightStatus()), 11);
  ground_status_t ground_status{};
  ground_status.vehicle_id = kVehicle;
  fuzzDecode<ground_status_t>(encode(ground_status), 5);
  signed_t envelope;
  Signer signer(testKey(1), kVehicle, 1);
  const auto inner = encode(sampleCorrection(5));
  signer.sign(inner.data(), inner.size(), kNow, &envelope);
  fuzzDecode<signed_t>(encode(envelope), 4);
  // A chunk of a 3000-byte message, as the drone's encoder makes it.
  ChunkEncoder chunks({});
  const std::vector<uint8_t> message(3000, 7);
  const auto encoded = chunks.encode(message.data(), message.size(), {kNow, kVehicle, 1}, 1);
  ASSERT_TRUE(encoded.ok());
  fuzzDecode<keyframe_chunk_t>(encode(*encoded->first), 6);
}

// ---------------------------------------------------------------------------------------------
// Signing

class Signing : public ::testing::Test {
 protected:
  Key key_ = testKey(1);
  Signer signer_{key_, kVehicle, 1000};
  Verifier verifier_{key_, kVehicle, VerifierParams()};

  signed_t signCorrection(int64_t keyframe_id, int64_t utime) {
    const auto inner = encode(sampleCorrection(keyframe_id));
    signed_t envelope;
    signer_.sign(inner.data(), inner.size(), utime, &envelope);
    return envelope;
  }
};

TEST_F(Signing, AcceptsAGoodEnvelope) {
  const signed_t envelope = signCorrection(1, kNow);
  EXPECT_EQ(envelope.key_id, static_cast<int32_t>(key_.id));
  EXPECT_EQ(envelope.sequence, 1000);
  EXPECT_EQ(verifier_.verify(envelope, kNow), Verdict::kAccepted);
  EXPECT_EQ(verifier_.verify(signCorrection(2, kNow), kNow + kSecond / 10), Verdict::kAccepted);
}

TEST_F(Signing, RejectsAnotherVehicle) {
  Signer other(key_, kVehicle + 1, 1);
  const auto inner = encode(sampleCorrection(1));
  signed_t envelope;
  other.sign(inner.data(), inner.size(), kNow, &envelope);
  EXPECT_EQ(verifier_.verify(envelope, kNow), Verdict::kWrongVehicle);
}

TEST_F(Signing, RejectsAnotherKey) {
  Signer other(testKey(2), kVehicle, 5000);
  const auto inner = encode(sampleCorrection(1));
  signed_t envelope;
  other.sign(inner.data(), inner.size(), kNow, &envelope);
  EXPECT_EQ(verifier_.verify(envelope, kNow), Verdict::kWrongKey);
  // Claiming the right key id does not help without the key.
  envelope.key_id = static_cast<int32_t>(key_.id);
  EXPECT_EQ(verifier_.verify(envelope, kNow), Verdict::kBadMac);
}

TEST_F(Signing, EveryAuthenticatedFieldIsCovered) {
  const signed_t good = signCorrection(1, kNow);
  std::vector<signed_t> tampered(5, good);
  tampered[0].payload[20] ^= 1;
  tampered[1].mac[0] ^= 1;
  tampered[2].sequence += 1;
  tampered[3].utime += 1;
  tampered[4].payload.pop_back();
  tampered[4].payload_size -= 1;
  for (size_t i = 0; i < tampered.size(); ++i)
    EXPECT_EQ(verifier_.verify(tampered[i], kNow), Verdict::kBadMac) << "tampered field " << i;
  // None of the forgeries moved the replay window.
  EXPECT_EQ(verifier_.verify(good, kNow), Verdict::kAccepted);
}

TEST_F(Signing, RejectsStaleAndFutureEnvelopes) {
  const double window_s = VerifierParams().window_s;
  const int64_t window_us = static_cast<int64_t>(window_s * 1e6);
  EXPECT_EQ(verifier_.verify(signCorrection(1, kNow - window_us - 1), kNow), Verdict::kStale);
  EXPECT_EQ(verifier_.verify(signCorrection(2, kNow + window_us + 1), kNow), Verdict::kStale);
  EXPECT_EQ(verifier_.verify(signCorrection(3, kNow - window_us + 1), kNow), Verdict::kAccepted);
}

TEST_F(Signing, RejectsReplayedAndReorderedSequences) {
  const signed_t first = signCorrection(1, kNow);
  const signed_t second = signCorrection(2, kNow);
  EXPECT_EQ(verifier_.verify(second, kNow), Verdict::kAccepted);
  // A copy of what was accepted (the ground sends each correction more than once).
  EXPECT_EQ(verifier_.verify(second, kNow), Verdict::kDuplicate);
  // Never accepted, and older than what was: a replay.
  EXPECT_EQ(verifier_.verify(first, kNow), Verdict::kReplayed);
  EXPECT_EQ(verifier_.verify(signCorrection(3, kNow), kNow), Verdict::kAccepted);
  EXPECT_EQ(verifier_.verify(second, kNow), Verdict::kDuplicate);  // still among the recent
  // Once it has left the recent ones, a copy is a replay again.
  for (int i = 0; i < static_cast<int>(Verifier::kRecentSequences); ++i)
    ASSERT_EQ(verifier_.verify(signCorrection(10 + i, kNow), kNow), Verdict::kAccepted);
  EXPECT_EQ(verifier_.verify(second, kNow), Verdict::kReplayed);
}

// A fixed vector computed with Python's hmac from the layout in docs/wire.md; the Python signer's
// test checks the same vector, so both sides compute the same MAC over the same bytes.
TEST(SigningVector, MacMatchesTheDocumentedLayout) {
  Key key;
  for (size_t i = 0; i < key.bytes.size(); ++i) key.bytes[i] = static_cast<uint8_t>(i);
  key.id = keyIdOf(key.bytes);
  const uint8_t payload[] = {'k', 'i', 'n', 'f', 'l', 'y'};
  const auto mac = computeMac(key, 7, 42, 1'700'000'000'000'000, payload, sizeof payload);
  char hex[65];
  for (size_t i = 0; i < mac.size(); ++i) std::snprintf(hex + 2 * i, 3, "%02x", mac[i]);
  EXPECT_EQ(key.id, 0x630dcd29u);
  EXPECT_STREQ(hex, "1092b8d8ce1e9d43676c5c9ed98aeb77fff29d8a676a849ea16f3d8ee1616561");
}

// ---------------------------------------------------------------------------------------------
// Key files

class KeyFiles : public ::testing::Test {
 protected:
  std::filesystem::path dir_ = std::filesystem::temp_directory_path() /
                               ("kinfly_keys_" + std::to_string(::getpid()));
  void SetUp() override { std::filesystem::create_directories(dir_); }
  void TearDown() override { std::filesystem::remove_all(dir_); }
};

TEST_F(KeyFiles, CreatedKeyLoadsBackWithOwnerOnlyMode) {
  const std::string path = (dir_ / "v7.key").string();
  const StatusOr<Key> created = createKeyFile(path, false);
  ASSERT_TRUE(created.ok()) << created.status().message();
  struct stat st {};
  ASSERT_EQ(::stat(path.c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777, 0600u);
  EXPECT_EQ(st.st_size, static_cast<off_t>(kKeyBytes));
  const StatusOr<Key> loaded = loadKeyFile(path);
  ASSERT_TRUE(loaded.ok()) << loaded.status().message();
  EXPECT_EQ(loaded->bytes, created->bytes);
  EXPECT_EQ(loaded->id, created->id);
  // Never overwritten by accident; replaced on request by a different random key.
  const StatusOr<Key> kept = createKeyFile(path, false);
  EXPECT_FALSE(kept.ok());
  EXPECT_NE(kept.status().message().find("exists"), std::string::npos) << kept.status().message();
  const StatusOr<Key> replaced = createKeyFile(path, true);
  ASSERT_TRUE(replaced.ok()) << replaced.status().message();
  EXPECT_NE(replaced->bytes, created->bytes);
}

TEST_F(KeyFiles, RefusesKeysOthersCanRead) {
  const std::string path = (dir_ / "open.key").string();
  ASSERT_TRUE(createKeyFile(path, false).ok());
  for (mode_t mode : {0640, 0604, 0620, 0660, 0644}) {
    ASSERT_EQ(::chmod(path.c_str(), mode), 0);
    const StatusOr<Key> loaded = loadKeyFile(path);
    EXPECT_FALSE(loaded.ok()) << std::oct << mode;
    const std::string& why = loaded.status().message();
    EXPECT_NE(why.find("chmod 600"), std::string::npos) << why;
  }
  ASSERT_EQ(::chmod(path.c_str(), 0400), 0);
  const StatusOr<Key> loaded = loadKeyFile(path);
  EXPECT_TRUE(loaded.ok()) << loaded.status().message();
}

TEST_F(KeyFiles, RefusesWrongSizesSymlinksAndMissingFiles) {
  const std::string short_path = (dir_ / "short.key").string();
  std::ofstream(short_path) << "too short";
  ASSERT_EQ(::chmod(short_path.c_str(), 0600), 0);
  const StatusOr<Key> too_short = loadKeyFile(short_path);
  EXPECT_FALSE(too_short.ok());
  EXPECT_NE(too_short.status().message().find("bytes"), std::string::npos)
      << too_short.status().message();

  const std::string real = (dir_ / "real.key").string();
  ASSERT_TRUE(createKeyFile(real, false).ok());
  const std::string link = (dir_ / "link.key").string();
  std::filesystem::create_symlink(real, link);
  EXPECT_FALSE(loadKeyFile(link).ok());

  const StatusOr<Key> missing = loadKeyFile((dir_ / "missing.key").string());
  EXPECT_FALSE(missing.ok());
  EXPECT_NE(missing.status().message().find("missing.key"), std::string::npos)
      << missing.status().message();
}

// ---------------------------------------------------------------------------------------------
// The drone's correction receiver: one message of every kind, each counted where it belongs.

TEST(CorrectionReceiver, AcceptsTheGoodAndCountsEachBadKind) {
  const Key key = testKey(1);
  CorrectionReceiver receiver(key, kVehicle, VerifierParams(), DecodeBounds());
  Signer signer(key, kVehicle, 1);
  const auto send = [&](const std::vector<uint8_t>& bytes, int64_t now) {
    return receiver.receive(bytes.data(), bytes.size(), now);
  };
  const auto envelope = [&](const pose_correction_t& c, int64_t utime) {
    const auto inner = encode(c);
    signed_t e;
    signer.sign(inner.data(), inner.size(), utime, &e);
    return e;
  };

  const signed_t held_back = envelope(sampleCorrection(3), kNow);  // sent after a later one
  const signed_t good = envelope(sampleCorrection(4), kNow);
  const auto accepted = send(encode(good), kNow);
  ASSERT_TRUE(accepted);
  EXPECT_EQ(accepted->keyframe_id, 4);

  EXPECT_FALSE(send(encode(good), kNow));                             // a copy: duplicate
  EXPECT_FALSE(send(encode(sampleCorrection(5)), kNow));              // unsigned
  EXPECT_FALSE(send(encode(held_back), kNow));                        // replayed
  EXPECT_FALSE(send(encode(envelope(sampleCorrection(6), kNow - 10 * kSecond)), kNow));  // stale
  signed_t forged = envelope(sampleCorrection(7), kNow);
  forged.payload[30] ^= 4;
  EXPECT_FALSE(send(encode(forged), kNow));                           // bad MAC
  Signer stranger(testKey(9), kVehicle, 1);
  signed_t foreign;
  const auto inner = encode(sampleCorrection(8));
  stranger.sign(inner.data(), inner.size(), kNow, &foreign);
  EXPECT_FALSE(send(encode(foreign), kNow));                          // wrong key
  auto truncated = encode(envelope(sampleCorrection(9), kNow));
  truncated.resize(truncated.size() - 3);
  EXPECT_FALSE(send(truncated, kNow));                                // malformed
  pose_correction_t elsewhere = sampleCorrection(10);
  elsewhere.vehicle_id = kVehicle + 1;
  EXPECT_FALSE(send(encode(envelope(elsewhere, kNow)), kNow));        // signed, wrong inner vehicle

  const RejectCounters& r = receiver.rejects();
  EXPECT_EQ(receiver.accepted(), 1);
  EXPECT_EQ(receiver.duplicates(), 1);
  EXPECT_EQ(r.unsigned_messages, 1);
  EXPECT_EQ(r.replayed, 1);
  EXPECT_EQ(r.stale, 1);
  EXPECT_EQ(r.bad_mac, 1);
  EXPECT_EQ(r.wrong_key, 1);
  EXPECT_EQ(r.malformed, 1);
  EXPECT_EQ(r.wrong_vehicle, 1);
  EXPECT_EQ(r.total(), 7);

  drone_status_t status;
  r.writeTo(&status);
  EXPECT_EQ(status.rejected_bad_mac, 1);
  EXPECT_EQ(status.rejected_unsigned, 1);
}

// ---------------------------------------------------------------------------------------------
// Flight commands: decoded within bounds, and received through the same signed path.

flight_command_t sampleMission(int waypoints) {
  flight_command_t m{};
  m.utime = kNow;
  m.vehicle_id = kVehicle;
  m.command_id = 42;
  m.kind = flight_command_t::MISSION;
  m.max_speed_m_s = 0.5;
  m.waypoint_count = waypoints;
  for (int i = 0; i < waypoints; ++i) m.waypoints_world_m.push_back({1.0 * i, 0.5, -1.0});
  return m;
}

TEST(Decode, FlightCommandsAreBoundedByTheirWaypoints) {
  // The count just before the waypoints, three doubles each, as the bounded decoder assumes.
  const flight_command_t sent = sampleMission(3);
  const auto bytes = encode(sent);
  const size_t fixed = static_cast<size_t>(flight_command_t().getEncodedSize());
  ASSERT_EQ(bytes.size(), fixed + 3 * 24);
  EXPECT_EQ(bytes[fixed - 1], 3);
  flight_command_t got;
  ASSERT_TRUE(decodeMessage(bytes.data(), bytes.size(), DecodeBounds(), &got).ok());
  EXPECT_EQ(got.waypoints_world_m, sent.waypoints_world_m);
  EXPECT_EQ(got.command_id, 42);

  auto forged = bytes;  // a count of 2^31 - 1 waypoints in a 200-byte datagram
  forged[fixed - 4] = 0x7f;
  forged[fixed - 3] = forged[fixed - 2] = forged[fixed - 1] = 0xff;
  EXPECT_EQ(decodeMessage(forged.data(), forged.size(), DecodeBounds(), &got).status,
            DecodeStatus::kOutOfBounds);
  const auto expectBad = [&](const flight_command_t& m, const char* detail) {
    const auto b = encode(m);
    const DecodeResult r = decodeMessage(b.data(), b.size(), DecodeBounds(), &got);
    EXPECT_EQ(r.status, DecodeStatus::kBadField) << detail;
    EXPECT_EQ(r.detail, detail);
  };
  flight_command_t bad = sampleMission(3);
  bad.kind = 9;
  expectBad(bad, "unknown kind 9");
  expectBad(sampleMission(1), "a mission needs at least 2 waypoints (got 1)");
  bad = sampleMission(3);
  bad.waypoints_world_m[1][2] = NAN;
  expectBad(bad, "a waypoint is not finite");
  bad = sampleMission(3);
  bad.height_m = INFINITY;
  expectBad(bad, "a field is not finite");
  bad = sampleMission(3);
  bad.yaw_rad = NAN;  // read only with has_yaw
  const auto no_yaw = encode(bad);
  ASSERT_TRUE(decodeMessage(no_yaw.data(), no_yaw.size(), DecodeBounds(), &got).ok());
  bad.has_yaw = true;
  expectBad(bad, "a field is not finite");
  bad = sampleMission(flight_command_t::MAX_WAYPOINTS + 1);
  const auto too_long = encode(bad);
  EXPECT_EQ(decodeMessage(too_long.data(), too_long.size(), DecodeBounds(), &got).status,
            DecodeStatus::kOutOfBounds);
}

TEST(CommandReceiver, TakesASignedCommandOnceAndRejectsTheRest) {
  const Key key = testKey(1);
  CommandReceiver receiver(key, kVehicle, VerifierParams(), DecodeBounds());
  Signer signer(key, kVehicle, 1);
  const auto send = [&](const std::vector<uint8_t>& bytes) {
    return receiver.receive(bytes.data(), bytes.size(), kNow);
  };
  const auto inner = encode(sampleMission(4));
  signed_t envelope;
  signer.sign(inner.data(), inner.size(), kNow, &envelope);
  const auto taken = send(encode(envelope));
  ASSERT_TRUE(taken);
  EXPECT_EQ(taken->waypoint_count, 4);
  EXPECT_FALSE(send(encode(envelope)));             // a copy
  EXPECT_FALSE(send(inner));                        // unsigned
  // A correction signed with the right key is not a command.
  const auto correction = encode(sampleCorrection(1));
  signed_t wrong_type;
  signer.sign(correction.data(), correction.size(), kNow, &wrong_type);
  EXPECT_FALSE(send(encode(wrong_type)));
  EXPECT_EQ(receiver.accepted(), 1);
  EXPECT_EQ(receiver.duplicates(), 1);
  EXPECT_EQ(receiver.rejects().unsigned_messages, 1);
  EXPECT_EQ(receiver.rejects().malformed, 1);
}

TEST(RecentCommands, ACommandSentAgainIsTakenOnce) {
  RecentCommands recent;
  EXPECT_TRUE(recent.first(100));
  EXPECT_FALSE(recent.first(100));  // resent, signed anew: unanswered at the sender
  EXPECT_TRUE(recent.first(101));
  EXPECT_FALSE(recent.first(100));  // another sender's command came between its resends
  EXPECT_EQ(recent.repeats(), 2);
  // Its memory is bounded: an id long gone is taken again (a sender stops within --wait).
  for (int64_t id = 200; id < 300; ++id) ASSERT_TRUE(recent.first(id));
  EXPECT_TRUE(recent.first(100));
  EXPECT_EQ(recent.repeats(), 2);
}

}  // namespace
}  // namespace kinfly::link
