// kinfly_ground._native's link: the ground station's end of the wire is firmware/link, the same
// C++ as the drone's (channel names, bounded decoding, depth payloads, keyframes in chunks, signing,
// reject counters), so the wire is parsed, checked and signed in one implementation. Python sees
// typed results (Keyframe, GroundTruth, Odometry, the drone's status, the link's quality), never
// raw messages.
#include <nanobind/stl/filesystem.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/pair.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/vector.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "arrays.h"
#include "kinfly/core/camera.h"
#include "kinfly/codec/depth_codec.h"
#include "kinfly/tracking/icp_tracker.h"
#include "kinfly/link/channels.h"
#include "kinfly/link/chunking.h"
#include "kinfly/link/conversions.h"
#include "kinfly/link/counters.h"
#include "kinfly/link/decode.h"
#include "kinfly/link/link_meter.h"
#include "kinfly/link/peer.h"
#include "kinfly/link/repair.h"
#include "kinfly/link/signing.h"
#include "kinfly/link/uplink.h"

namespace kinfly::native {
namespace {

// A key file that must not be used (its mode, size or type); the message says how to fix it.
struct KeyFileError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// A keyframe (or a raw depth frame) as it arrived, its depth decoded.
struct Keyframe {
  int64_t utime = 0;  // [us] capture time
  int32_t vehicle_id = 0;
  int64_t frame_id = 0, keyframe_id = 0;
  PinholeCamera camera;
  double depth_scale_m = 0.0;
  std::optional<TrackingStatus> tracking;  // the onboard odometry's; nullopt: no pose
  Pose T_world_cam = Pose::Identity();     // the onboard pose
  Image<uint16_t> depth;                   // raw units (depth_scale_m)
};

struct StampedPose {
  int64_t utime = 0;
  int32_t vehicle_id = 0;
  Pose T_world_cam = Pose::Identity();
  int32_t reset_counter = 0;   // odometry and corrections
  int64_t keyframe_id = -1;    // corrections
};

nb::object poseOrNone(const Pose& T, bool present) {
  return present ? nb::cast(matrixOf(T), nb::rv_policy::move) : nb::none();
}

link::Key keyOf(const nb::bytes& bytes) {
  link::Key key;
  if (bytes.size() != key.bytes.size())
    throw nb::value_error(("a key is " + std::to_string(key.bytes.size()) + " bytes, not " +
                           std::to_string(bytes.size()))
                              .c_str());
  std::memcpy(key.bytes.data(), bytes.c_str(), key.bytes.size());
  key.id = link::keyIdOf(key.bytes);
  return key;
}

template <class T>
std::vector<uint8_t> encoded(const T& message) {
  std::vector<uint8_t> bytes(static_cast<size_t>(message.getEncodedSize()));
  message.encode(bytes.data(), 0, static_cast<int>(bytes.size()));
  return bytes;
}

nb::bytes bytesOf(const std::vector<uint8_t>& data) {
  return nb::bytes(reinterpret_cast<const char*>(data.data()), data.size());
}

// One vehicle's keyframe link as the ground sees it (Receiver.link_quality): ground_status_t's link
// figures and the chunk assembler's counters.
struct LinkReport {
  // ground_status_t's fields of the same names.
  double link_loss = 0.0;       // [0, 1] chunks lost (sequence gaps)
  double link_loss_run = 1.0;   // [chunks] mean run of lost chunks
  double goodput_bps = 0.0;     // [bit/s]
  double queue_delay_ms = 0.0;  // [ms]
  double redundancy = 0.0;      // m / k of the last keyframe
  double keyframe_age_ms = 0.0; // [ms] the last keyframe's capture to arrival
  int64_t chunks_received = 0;
  int64_t keyframes_recovered = 0;   // with recovery chunks or after a repair request
  int64_t keyframes_incomplete = 0;  // given up with chunks missing
  int64_t repair_requests = 0;       // chunk_request_t handed out (every ask of every group)
  // More detail.
  link::ChunkCounters chunks;        // the assembler's, by outcome
  int64_t keyframes_repaired = 0;    // completed after a repair request (and not by FEC alone)
  int64_t newest_keyframe_id = -1;   // the newest keyframe chunks arrived of; -1: none
};

// Everything the ground station hears goes through one Receiver: the channel is parsed, the
// message decoded within bounds, keyframe chunks assembled, a depth payload decoded, and the
// vehicle checked against the channel; each rejection is counted by reason. Its own channels
// (corrections, chunk requests, its status) are ignored when they loop back on multicast.
class Receiver {
 public:
  // Vehicles whose keyframe link is followed (an assembler and a meter each, a few hundred KB
  // once grown); chunks of further vehicles are refused and counted.
  static constexpr size_t kMaxLinkVehicles = 16;
  explicit Receiver(const link::RepairScheduler::Params& repair)
      : codec_(codecParams(bounds_)), repair_params_(repair) {
    if (const Status valid = assembler_params_.validate(); !valid.ok())
      throw std::logic_error(valid.message());
    if (const Status valid = meter_params_.validate(); !valid.ok())
      throw std::logic_error(valid.message());
    if (const Status valid = repair_params_.validate(); !valid.ok())
      throw std::invalid_argument("repair: " + valid.message());
  }

  // None, or (channel, vehicle id, what arrived: Keyframe (whole, or the chunk that completed
  // one), Odometry/GroundTruth (StampedPose), the drone's status, its flight status, or None for
  // IMU samples and chunks that completed nothing). ARRIVAL_UTIME: the ground's wall clock by default.
  nb::object receive(const std::string& channel, const nb::bytes& data,
                     std::optional<int64_t> arrival_utime) {
    const std::optional<link::ParsedChannel> parsed = link::parseChannel(channel);
    if (!parsed) {
      ++rejects_.unknown_channel;
      return nb::none();
    }
    const int vehicle = parsed->vehicle_id;
    const auto result = [&](nb::object message) {
      return nb::make_tuple(parsed->channel, vehicle, message);
    };
    const auto now = [&] { return arrival_utime.value_or(link::wallClockUtime()); };
    switch (parsed->channel) {
      case link::Channel::kKeyframe:
      case link::Channel::kDepth: {
        if (!decode(data, &keyframe_)) return nb::none();
        nb::object k = keyframeObject(vehicle);
        if (k.is_none()) return k;
        // Whole keyframes (flight logs, wired links, older drones) still tell the keyframe's age.
        if (parsed->channel == link::Channel::kKeyframe)
          if (VehicleLink* v = linkOf(vehicle)) v->meter.onKeyframe(-1, keyframe_.utime, now(), 0.0);
        return result(k);
      }
      case link::Channel::kKeyframeChunk: {
        if (!decode(data, &chunk_) || !sameVehicle(chunk_.vehicle_id, vehicle)) return nb::none();
        VehicleLink* v = linkOf(vehicle);
        if (v == nullptr) return nb::none();
        const int64_t arrival = now();
        v->meter.onChunk(chunk_, arrival, data.size());
        const link::ChunkCounters before = v->assembler.counters();
        const link::ChunkStatus status = v->assembler.add(chunk_);
        const link::ChunkCounters& after = v->assembler.counters();
        if (after.restarts > before.restarts) v->newest_keyframe_id = -1;
        if (status != link::ChunkStatus::kMalformed && status != link::ChunkStatus::kMismatch)
          v->newest_keyframe_id = std::max(v->newest_keyframe_id, chunk_.keyframe_id);
        if (status != link::ChunkStatus::kCompleted) return result(nb::none());
        if (after.keyframes_recovered == before.keyframes_recovered &&
            v->repair.asked(chunk_.utime, chunk_.keyframe_id))
          ++v->keyframes_repaired;
        const std::vector<uint8_t>& message = v->assembler.message();
        if (!decode(message.data(), message.size(), &keyframe_)) return nb::none();
        nb::object k = keyframeObject(vehicle);
        if (k.is_none()) return k;
        v->meter.onKeyframe(keyframe_.keyframe_id, keyframe_.utime, arrival,
                            static_cast<double>(chunk_.recovery) / chunk_.originals);
        return result(k);
      }
      case link::Channel::kOdometry: {
        odometry_t m;
        if (!decode(data, &m) || !sameVehicle(m.vehicle_id, vehicle)) return nb::none();
        return result(nb::cast(StampedPose{m.utime, m.vehicle_id, link::readPose(m.T_world_cam),
                                           m.reset_counter}));
      }
      case link::Channel::kGroundTruth: {
        ground_truth_t m;
        if (!decode(data, &m) || !sameVehicle(m.vehicle_id, vehicle)) return nb::none();
        return result(nb::cast(StampedPose{m.utime, m.vehicle_id, link::readPose(m.T_world_cam)}));
      }
      case link::Channel::kStatus: {
        drone_status_t m;
        if (!decode(data, &m) || !sameVehicle(m.vehicle_id, vehicle)) return nb::none();
        return result(nb::cast(m));
      }
      case link::Channel::kFlight: {
        flight_status_t m;
        if (!decode(data, &m) || !sameVehicle(m.vehicle_id, vehicle)) return nb::none();
        return result(nb::cast(m));
      }
      case link::Channel::kImu: {
        imu_t m;
        if (!decode(data, &m) || !sameVehicle(m.vehicle_id, vehicle)) return nb::none();
        return result(nb::none());
      }
      case link::Channel::kCorrection:
      case link::Channel::kGroundStatus:
      case link::Channel::kChunkRequest:
      case link::Channel::kMotorCommand:
      case link::Channel::kCommand:
      case link::Channel::kSimState: return nb::none();
    }
    return nb::none();
  }

  // The vehicle's keyframe link as of NOW_UTIME (the wall clock by default); None before
  // anything of the vehicle's keyframes arrived.
  std::optional<LinkReport> linkQuality(int vehicle_id, std::optional<int64_t> now_utime) const {
    const VehicleLink* v = findLink(vehicle_id);
    if (v == nullptr) return std::nullopt;
    const link::LinkQuality q = v->meter.quality(now_utime.value_or(link::wallClockUtime()));
    const link::LossStats loss = v->assembler.loss();
    LinkReport r;
    r.link_loss = loss.lossFraction();
    r.link_loss_run = loss.meanLossRun();
    r.goodput_bps = q.goodput_bps;
    r.queue_delay_ms = q.queue_delay_ms;
    r.redundancy = q.redundancy;
    r.keyframe_age_ms = q.keyframe_age_ms;
    r.chunks = v->assembler.counters();
    r.chunks_received = r.chunks.chunks;
    r.keyframes_recovered = r.chunks.keyframes_recovered + v->keyframes_repaired;
    r.keyframes_incomplete = r.chunks.keyframes_evicted;
    r.repair_requests = v->repair.requests();
    r.keyframes_repaired = v->keyframes_repaired;
    r.newest_keyframe_id = v->newest_keyframe_id;
    return r;
  }

  // Encoded chunk_request_t for the vehicle's incomplete groups due to be asked for at NOW_US
  // (link::RepairScheduler: at once, then again while they stay incomplete). The newest keyframe
  // may still be arriving, so it is left out unless INCLUDE_NEWEST.
  nb::list repairRequests(int vehicle_id, bool include_newest, std::optional<int64_t> now_us) {
    nb::list out;
    VehicleLink* v = findLink(vehicle_id);
    if (v == nullptr) return out;
    const int64_t now = now_us.value_or(std::chrono::duration_cast<std::chrono::microseconds>(
        std::chrono::steady_clock::now().time_since_epoch()).count());
    const int n = v->repair.due(v->assembler, include_newest, now, &v->requests);
    for (int i = 0; i < n; ++i) out.append(bytesOf(encoded(v->requests[static_cast<size_t>(i)])));
    return out;
  }

  const link::RejectCounters& rejects() const { return rejects_; }
  const link::RepairScheduler::Params& repairParams() const { return repair_params_; }
  // Keyframe chunks refused because kMaxLinkVehicles vehicles were followed already.
  int64_t linkVehiclesRefused() const { return link_vehicles_refused_; }

 private:
  struct VehicleLink {
    VehicleLink(int32_t id, const link::ChunkAssembler::Params& assembler_params,
                const link::LinkMeter::Params& meter_params,
                const link::RepairScheduler::Params& repair_params)
        : vehicle_id(id), assembler(id, assembler_params), meter(meter_params),
          repair(repair_params) {}
    int32_t vehicle_id;
    link::ChunkAssembler assembler;
    link::LinkMeter meter;
    link::RepairScheduler repair;
    int64_t keyframes_repaired = 0;
    int64_t newest_keyframe_id = -1;
    std::vector<chunk_request_t> requests;  // repairRequests()'s, reused
  };

  static DepthCodec::Params codecParams(const link::DecodeBounds& bounds) {
    DepthCodec::Params params;
    params.max_width_px = bounds.max_width_px;
    params.max_height_px = bounds.max_height_px;
    return params;
  }
  template <class T>
  bool decode(const void* data, size_t size, T* out) {
    const link::DecodeResult r = link::decodeMessage(data, size, bounds_, out);
    rejects_.count(r.status);
    return r.ok();
  }
  template <class T>
  bool decode(const nb::bytes& data, T* out) {
    return decode(data.c_str(), data.size(), out);
  }
  bool sameVehicle(int32_t in_message, int in_channel) {
    if (in_message == in_channel) return true;
    ++rejects_.wrong_vehicle;
    return false;
  }

  // The one path of a decoded depth_keyframe_t (keyframe_), whole or rebuilt from chunks: its
  // depth decoded, its vehicle checked, a typed Keyframe; None (counted) when refused.
  nb::object keyframeObject(int vehicle) {
    if (!link::decodeDepth(codec_, keyframe_, &depth_).ok()) {
      ++rejects_.malformed;
      return nb::none();
    }
    if (!sameVehicle(keyframe_.vehicle_id, vehicle)) return nb::none();
    auto* k = new Keyframe();
    k->utime = keyframe_.utime;
    k->vehicle_id = keyframe_.vehicle_id;
    k->frame_id = keyframe_.frame_id;
    k->keyframe_id = keyframe_.keyframe_id;
    k->camera = link::cameraOf(keyframe_);
    k->depth_scale_m = keyframe_.depth_scale_m;
    k->tracking = link::trackingOf(keyframe_.tracking_status);
    if (k->tracking) k->T_world_cam = link::readPose(keyframe_.T_world_cam);
    k->depth = Image<uint16_t>(depth_.width(), depth_.height());
    k->depth.copyFrom(depth_.view());
    return nb::cast(k, nb::rv_policy::take_ownership);
  }

  const VehicleLink* findLink(int vehicle_id) const {
    for (const auto& v : links_)
      if (v->vehicle_id == vehicle_id) return v.get();
    return nullptr;
  }
  VehicleLink* findLink(int vehicle_id) {
    return const_cast<VehicleLink*>(std::as_const(*this).findLink(vehicle_id));
  }
  // The vehicle's link, made at its first keyframe or chunk; nullptr (counted) beyond
  // kMaxLinkVehicles.
  VehicleLink* linkOf(int vehicle_id) {
    if (VehicleLink* v = findLink(vehicle_id)) return v;
    if (links_.size() >= kMaxLinkVehicles) {
      ++link_vehicles_refused_;
      return nullptr;
    }
    links_.push_back(std::make_unique<VehicleLink>(vehicle_id, assembler_params_, meter_params_,
                                                   repair_params_));
    return links_.back().get();
  }

  link::DecodeBounds bounds_;
  DepthCodec codec_;
  link::RejectCounters rejects_;
  depth_keyframe_t keyframe_;  // reused: its payload keeps its capacity
  keyframe_chunk_t chunk_;     // reused: its block keeps its capacity
  Image<uint16_t> depth_;      // reused: the codec's output
  link::ChunkAssembler::Params assembler_params_;
  link::LinkMeter::Params meter_params_;
  link::RepairScheduler::Params repair_params_;
  std::vector<std::unique_ptr<VehicleLink>> links_;
  int64_t link_vehicles_refused_ = 0;
};

// Signs the ground's corrections for one vehicle.
class Signer {
 public:
  Signer(const nb::bytes& key, int32_t vehicle_id, std::optional<int64_t> first_sequence)
      : vehicle_id_(vehicle_id),
        signer_(keyOf(key), vehicle_id, first_sequence.value_or(link::wallClockUtime())) {}

  // The signed_t envelope, encoded, around any encoded inner message (a flight_command_t).
  nb::bytes sign(const nb::bytes& inner, std::optional<int64_t> utime_now) {
    signer_.sign(reinterpret_cast<const uint8_t*>(inner.c_str()), inner.size(),
                 utime_now.value_or(link::wallClockUtime()), &envelope_);
    return bytesOf(encoded(envelope_));
  }

  // The signed_t envelope, encoded, around the correction of one keyframe.
  nb::bytes signCorrection(int64_t keyframe_id, int64_t utime, const PoseIn& T_world_cam,
                           int32_t reset_counter, std::optional<int64_t> utime_now) {
    link::KeyframeHeader keyframe;
    keyframe.utime = utime;
    keyframe.keyframe_id = keyframe_id;
    pose_correction_t correction;
    link::fillCorrection(vehicle_id_, keyframe, poseOf(T_world_cam), reset_counter, &correction);
    const std::vector<uint8_t> inner = encoded(correction);
    signer_.sign(inner.data(), inner.size(), utime_now.value_or(link::wallClockUtime()),
                 &envelope_);
    return bytesOf(encoded(envelope_));
  }

 private:
  int32_t vehicle_id_;
  link::Signer signer_;
  signed_t envelope_;
};

// The drone's end of the uplink (link::CorrectionReceiver), for tests and tools that check what
// the ground sends as the drone would.
class CorrectionReceiver {
 public:
  CorrectionReceiver(const nb::bytes& key, int32_t vehicle_id, double window_s)
      : receiver_(keyOf(key), vehicle_id, verifierParams(window_s), link::DecodeBounds()) {}

  std::optional<StampedPose> receive(const nb::bytes& data, int64_t now_utime) {
    const auto c = receiver_.receive(data.c_str(), data.size(), now_utime);
    if (!c) return std::nullopt;
    return StampedPose{c->utime, c->vehicle_id, link::readPose(c->T_world_cam), c->reset_counter,
                       c->keyframe_id};
  }
  const link::RejectCounters& rejects() const { return receiver_.rejects(); }
  int64_t accepted() const { return receiver_.accepted(); }
  int64_t duplicates() const { return receiver_.duplicates(); }

 private:
  static link::VerifierParams verifierParams(double window_s) {
    link::VerifierParams params;
    params.window_s = window_s;
    if (const Status valid = params.validate(); !valid.ok())
      throw nb::value_error(valid.message().c_str());
    return params;
  }
  link::CorrectionReceiver receiver_;
};

// The ground's end of the unicast link (peer.h): it takes only what drones send, of one vehicle
// or of any, from the peers' hosts.
class GroundPeers {
 public:
  GroundPeers(const std::string& peers, int listen_port, std::optional<int> vehicle_id)
      : link_(parsed(peers), checkedPort(listen_port), [vehicle_id](std::string_view channel) {
          const auto parsed = link::parseChannel(channel);
          return parsed && !link::sentByGround(parsed->channel) &&
                 (!vehicle_id || parsed->vehicle_id == *vehicle_id);
        }) {
    if (const Status opened = link_.open(); !opened.ok())
      throw std::invalid_argument(opened.message());
  }

  int fileno() const { return link_.fd(); }
  int listenPort() const { return link_.listenPort(); }

  bool send(const std::string& channel, const nb::bytes& data) {
    return link_.send(channel, static_cast<const uint8_t*>(data.data()), data.size());
  }

  std::vector<std::tuple<std::string, nb::bytes>> receive() {
    std::vector<std::tuple<std::string, nb::bytes>> messages;
    link_.receive([&](const char* channel, const uint8_t* data, size_t size) {
      messages.emplace_back(channel, nb::bytes(reinterpret_cast<const char*>(data), size));
    });
    return messages;
  }

  const link::PeerCounters& counters() const { return link_.counters(); }

 private:
  static std::vector<link::PeerAddress> parsed(const std::string& text) {
    std::vector<link::PeerAddress> peers;
    if (const Status status = link::parsePeers(text, &peers); !status.ok())
      throw std::invalid_argument(status.message());
    if (peers.empty()) throw std::invalid_argument("no peer given (ADDRESS:PORT[,ADDRESS:PORT])");
    return peers;
  }
  static uint16_t checkedPort(int port) {
    if (port < 0 || port > 65535)
      throw std::invalid_argument("listen port " + std::to_string(port) +
                                  " is not in [0, 65535]");
    return static_cast<uint16_t>(port);
  }

  link::PeerLink link_;
};

}  // namespace

void bindLink(nb::module_& m) {
  nb::enum_<TrackingStatus>(m, "TrackingStatus", "The engine's tracking status (icp_tracker.h)")
      .value("FIRST_FRAME", TrackingStatus::kFirstFrame)
      .value("OK", TrackingStatus::kOk)
      .value("LOST", TrackingStatus::kLost)
      .value("GIVEN_POSE", TrackingStatus::kGivenPose);
  m.def("tracking_code", [](std::optional<TrackingStatus> s) { return link::trackingCode(s); },
        nb::arg("status").none(), "odometry_t.TRACKING_* of a status (None: TRACKING_NONE)");

  nb::class_<PinholeCamera>(m, "PinholeCamera", "The engine's pinhole camera (camera.h)")
      .def(nb::init<>())
      .def("__init__",
           [](PinholeCamera* self, int width, int height, float fx, float fy, float cx, float cy) {
             new (self) PinholeCamera{fx, fy, cx, cy, width, height};
           },
           nb::arg("width"), nb::arg("height"), nb::arg("fx"), nb::arg("fy"), nb::arg("cx"),
           nb::arg("cy"))
      .def_rw("width", &PinholeCamera::width)
      .def_rw("height", &PinholeCamera::height)
      .def_rw("fx", &PinholeCamera::fx)
      .def_rw("fy", &PinholeCamera::fy)
      .def_rw("cx", &PinholeCamera::cx)
      .def_rw("cy", &PinholeCamera::cy)
      .def("validate", [](const PinholeCamera& camera) { return camera.validate().message(); },
           "empty when valid, else what is wrong")
      .def("__eq__",
           [](const PinholeCamera& a, const PinholeCamera& b) {
             return a.width == b.width && a.height == b.height && a.fx == b.fx && a.fy == b.fy &&
                    a.cx == b.cx && a.cy == b.cy;
           })
      .def("__repr__", [](const PinholeCamera& c) {
        return "PinholeCamera(" + std::to_string(c.width) + "x" + std::to_string(c.height) +
               ", fx=" + std::to_string(c.fx) + ", fy=" + std::to_string(c.fy) +
               ", cx=" + std::to_string(c.cx) + ", cy=" + std::to_string(c.cy) + ")";
      });

  nb::enum_<link::Channel>(m, "Channel", "Kinds of kinfly channel (firmware/link/channels.h)")
      .value("DEPTH", link::Channel::kDepth)
      .value("KEYFRAME", link::Channel::kKeyframe)
      .value("ODOMETRY", link::Channel::kOdometry)
      .value("IMU", link::Channel::kImu)
      .value("STATUS", link::Channel::kStatus)
      .value("CORRECTION", link::Channel::kCorrection)
      .value("GROUND_STATUS", link::Channel::kGroundStatus)
      .value("GROUND_TRUTH", link::Channel::kGroundTruth)
      .value("KEYFRAME_CHUNK", link::Channel::kKeyframeChunk)
      .value("CHUNK_REQUEST", link::Channel::kChunkRequest)
      .value("MOTOR_COMMAND", link::Channel::kMotorCommand)
      .value("COMMAND", link::Channel::kCommand)
      .value("FLIGHT", link::Channel::kFlight)
      .value("SIM_STATE", link::Channel::kSimState);
  m.attr("MAX_VEHICLE_ID") = link::kMaxVehicleId;
  m.def("channel_name",
        [](link::Channel channel, int vehicle_id) {
          if (vehicle_id < 0 || vehicle_id > link::kMaxVehicleId)
            throw nb::value_error(("vehicle id " + std::to_string(vehicle_id) + " outside [0, " +
                                   std::to_string(link::kMaxVehicleId) + "]")
                                      .c_str());
          return link::channelName(channel, vehicle_id);
        },
        nb::arg("channel"), nb::arg("vehicle_id"), "KINFLY_<vehicle id>_<KIND>");
  m.def("parse_channel",
        [](const std::string& name) -> nb::object {
          const auto parsed = link::parseChannel(name);
          if (!parsed) return nb::none();
          return nb::make_tuple(parsed->channel, parsed->vehicle_id);
        },
        nb::arg("name"), "(Channel, vehicle id) of a kinfly channel name; None for anything else");
  m.def("ground_subscriptions",
        [](std::optional<int> vehicle_id) {
          const link::Subscriptions s = link::groundSubscriptions(vehicle_id);
          return std::make_pair(s.keyframes, s.others);
        },
        nb::arg("vehicle_id").none(),
        "LCM patterns (keyframes, everything else) for one vehicle, or every vehicle for None");

  nb::class_<link::RejectCounters>(m, "RejectCounters", "Received messages dropped, by reason")
      .def_ro("unsigned_messages", &link::RejectCounters::unsigned_messages)
      .def_ro("wrong_key", &link::RejectCounters::wrong_key)
      .def_ro("bad_mac", &link::RejectCounters::bad_mac)
      .def_ro("stale", &link::RejectCounters::stale)
      .def_ro("replayed", &link::RejectCounters::replayed)
      .def_ro("malformed", &link::RejectCounters::malformed)
      .def_ro("unknown_channel", &link::RejectCounters::unknown_channel)
      .def_ro("wrong_vehicle", &link::RejectCounters::wrong_vehicle)
      .def("total", &link::RejectCounters::total);

  nb::class_<Keyframe>(m, "Keyframe", "A depth keyframe (or raw frame) as received")
      .def_ro("utime", &Keyframe::utime)
      .def_ro("vehicle_id", &Keyframe::vehicle_id)
      .def_ro("frame_id", &Keyframe::frame_id)
      .def_ro("keyframe_id", &Keyframe::keyframe_id)
      .def_ro("camera", &Keyframe::camera)
      .def_ro("depth_scale_m", &Keyframe::depth_scale_m)
      .def_ro("tracking", &Keyframe::tracking, "the onboard odometry's status; None: no pose")
      .def_prop_ro("T_world_cam",
                   [](const Keyframe& k) { return poseOrNone(k.T_world_cam, k.tracking.has_value()); },
                   "the onboard pose (4x4 camera to world); None when there is none")
      .def_prop_ro("depth",
                   [](nb::handle self) {
                     Keyframe& k = nb::cast<Keyframe&>(self);
                     return DepthOut(k.depth.data(),
                                     {static_cast<size_t>(k.depth.height()),
                                      static_cast<size_t>(k.depth.width())},
                                     self);
                   },
                   "uint16 (height, width) raw depth, a view kept alive by the keyframe");

  nb::class_<StampedPose>(m, "StampedPose", "A received pose: odometry, ground truth, correction")
      .def_ro("utime", &StampedPose::utime)
      .def_ro("vehicle_id", &StampedPose::vehicle_id)
      .def_prop_ro("T_world_cam", [](const StampedPose& p) { return matrixOf(p.T_world_cam); },
                   nb::rv_policy::move)
      .def_ro("reset_counter", &StampedPose::reset_counter)
      .def_ro("keyframe_id", &StampedPose::keyframe_id);

  nb::class_<drone_status_t>(m, "DroneStatus", "The drone's status (drone_status_t)")
#define KINFLY_FIELD(name) .def_ro(#name, &drone_status_t::name)
      KINFLY_FIELD(utime) KINFLY_FIELD(vehicle_id) KINFLY_FIELD(depth_rate_hz)
      KINFLY_FIELD(odometry_rate_hz) KINFLY_FIELD(keyframe_rate_hz) KINFLY_FIELD(frames_captured)
      KINFLY_FIELD(queue_drops) KINFLY_FIELD(keyframes_sent) KINFLY_FIELD(keyframes_dropped)
      KINFLY_FIELD(last_keyframe_id) KINFLY_FIELD(send_budget_bps) KINFLY_FIELD(redundancy)
      KINFLY_FIELD(keyframe_scale) KINFLY_FIELD(chunks_sent) KINFLY_FIELD(chunks_resent)
      KINFLY_FIELD(keyframes_skipped) KINFLY_FIELD(run_state) KINFLY_FIELD(tracking_state)
      KINFLY_FIELD(link_state) KINFLY_FIELD(sensor_state) KINFLY_FIELD(sensor_connects)
      KINFLY_FIELD(sensor_stalls) KINFLY_FIELD(frames_skipped) KINFLY_FIELD(frames_lost)
      KINFLY_FIELD(rejected_unsigned) KINFLY_FIELD(rejected_wrong_key)
      KINFLY_FIELD(rejected_bad_mac) KINFLY_FIELD(rejected_stale) KINFLY_FIELD(rejected_replayed)
      KINFLY_FIELD(rejected_malformed) KINFLY_FIELD(rejected_unknown_channel)
      KINFLY_FIELD(rejected_wrong_vehicle) KINFLY_FIELD(corrections_accepted)
      KINFLY_FIELD(corrections_unknown_keyframe) KINFLY_FIELD(commands_passed)
#undef KINFLY_FIELD
      .def_prop_ro("final", [](const drone_status_t& s) {
        return s.run_state == drone_status_t::RUN_FINAL;
      }, "its last status before kinfly-fw exits");

  nb::class_<flight_status_t>(m, "FlightStatus",
                             "The drone's flight stack (flight_status_t; world z down, body FRD)")
#define KINFLY_FIELD(name) .def_ro(#name, &flight_status_t::name)
      KINFLY_FIELD(utime) KINFLY_FIELD(vehicle_id) KINFLY_FIELD(mode) KINFLY_FIELD(command_id)
      KINFLY_FIELD(command_kind) KINFLY_FIELD(command_result)
      KINFLY_FIELD(estimator_initialised) KINFLY_FIELD(estimator_diverged)
      KINFLY_FIELD(position_std_m) KINFLY_FIELD(vision_age_s) KINFLY_FIELD(vision_fused)
      KINFLY_FIELD(vision_rejected) KINFLY_FIELD(baro_fused) KINFLY_FIELD(baro_rejected)
      KINFLY_FIELD(reset_counter) KINFLY_FIELD(resets)
      KINFLY_FIELD(setpoint_yaw_rad) KINFLY_FIELD(thrust_n) KINFLY_FIELD(rotors)
      KINFLY_FIELD(mode_changes) KINFLY_FIELD(commands_accepted) KINFLY_FIELD(commands_refused)
      KINFLY_FIELD(failsafe_vision_lost) KINFLY_FIELD(failsafe_estimator_diverged)
      KINFLY_FIELD(failsafe_attitude_limit) KINFLY_FIELD(failsafe_imu_lost)
      KINFLY_FIELD(failsafe_geofence) KINFLY_FIELD(failsafe_autopilot_lost)
      KINFLY_FIELD(autopilot_used) KINFLY_FIELD(autopilot_alive) KINFLY_FIELD(autopilot_armed)
      KINFLY_FIELD(autopilot_offboard)
#undef KINFLY_FIELD
#define KINFLY_ARRAY(name)                                                          \
  .def_prop_ro(#name, [](const flight_status_t& s) {                                \
    return std::vector<double>(std::begin(s.name), std::end(s.name));               \
  })
      KINFLY_ARRAY(p_world_m) KINFLY_ARRAY(v_world_m_s) KINFLY_ARRAY(q_world_body_xyzw)
      KINFLY_ARRAY(setpoint_world_m) KINFLY_ARRAY(setpoint_v_world_m_s)
      KINFLY_ARRAY(rotor_speed_rad_s)
#undef KINFLY_ARRAY
      .def_prop_ro("T_world_map", [](const flight_status_t& s) {
        return matrixOf(link::readPose(s.T_world_map));
      }, nb::rv_policy::move, "the map's frame in world: the estimator's alignment");

  nb::class_<link::ChunkCounters>(m, "ChunkCounters",
                                  "Keyframe chunks by outcome (firmware/link/chunking.h)")
#define KINFLY_FIELD(name) .def_ro(#name, &link::ChunkCounters::name)
      KINFLY_FIELD(chunks) KINFLY_FIELD(stored) KINFLY_FIELD(duplicate) KINFLY_FIELD(surplus)
      KINFLY_FIELD(stale) KINFLY_FIELD(mismatch) KINFLY_FIELD(oversized) KINFLY_FIELD(malformed)
      KINFLY_FIELD(digest_mismatch) KINFLY_FIELD(keyframes_completed)
      KINFLY_FIELD(keyframes_recovered) KINFLY_FIELD(keyframes_evicted) KINFLY_FIELD(restarts);
#undef KINFLY_FIELD

  nb::class_<LinkReport>(m, "LinkQuality",
                         "One vehicle's keyframe link: ground_status_t's link figures, and the "
                         "chunk assembler's counters (`chunks`)")
#define KINFLY_FIELD(name) .def_ro(#name, &LinkReport::name)
      KINFLY_FIELD(link_loss) KINFLY_FIELD(link_loss_run) KINFLY_FIELD(goodput_bps)
      KINFLY_FIELD(queue_delay_ms) KINFLY_FIELD(redundancy) KINFLY_FIELD(keyframe_age_ms)
      KINFLY_FIELD(chunks_received) KINFLY_FIELD(keyframes_recovered)
      KINFLY_FIELD(keyframes_incomplete) KINFLY_FIELD(repair_requests) KINFLY_FIELD(chunks)
      KINFLY_FIELD(keyframes_repaired) KINFLY_FIELD(newest_keyframe_id);
#undef KINFLY_FIELD

  nb::class_<Receiver>(m, "Receiver",
                       "Parses, decodes within bounds and checks every received message "
                       "(firmware/link), assembles keyframe chunks and measures each vehicle's "
                       "link, counting what it rejects")
      .def("__init__",
           [](Receiver* self, int repair_max_asks, double repair_retry_s) {
             link::RepairScheduler::Params repair;
             repair.max_asks = repair_max_asks;
             repair.retry_s = repair_retry_s;
             new (self) Receiver(repair);
           },
           nb::arg("repair_max_asks") = link::RepairScheduler::Params().max_asks,
           nb::arg("repair_retry_s") = link::RepairScheduler::Params().retry_s,
           "repair_max_asks [1, 16], repair_retry_s [s] [0.01, 10]: how often and how far apart "
           "an incomplete group is asked for (ValueError outside)")
      .def("receive", &Receiver::receive, nb::arg("channel"), nb::arg("data"),
           nb::arg("arrival_utime") = nb::none(),
           "None when rejected or not for the ground; else (Channel, vehicle id, message). "
           "arrival_utime [us]: the ground's wall clock by default")
      .def("link_quality", &Receiver::linkQuality, nb::arg("vehicle_id"),
           nb::arg("now_utime") = nb::none(),
           "The vehicle's LinkQuality as of now_utime (wall clock by default); None before any "
           "of its keyframes arrived")
      .def("repair_requests", &Receiver::repairRequests, nb::arg("vehicle_id"),
           nb::arg("include_newest"), nb::arg("now_us") = nb::none(),
           "Encoded chunk_request_t for the incomplete groups due at now_us (a monotonic clock, "
           "[us]; CLOCK_MONOTONIC by default): each at once, then every repair_retry_s while it "
           "stays incomplete, at most repair_max_asks times; the newest keyframe only with "
           "include_newest")
      .def_prop_ro("rejects", &Receiver::rejects, nb::rv_policy::reference_internal)
      .def_prop_ro("repair_max_asks",
                   [](const Receiver& r) { return r.repairParams().max_asks; })
      .def_prop_ro("repair_retry_s", [](const Receiver& r) { return r.repairParams().retry_s; })
      .def_prop_ro("link_vehicles_refused", &Receiver::linkVehiclesRefused,
                   "keyframe chunks refused: too many vehicles' links followed already");
  m.attr("MAX_LINK_VEHICLES") = Receiver::kMaxLinkVehicles;

  nb::class_<link::PeerCounters>(m, "PeerCounters", "Unicast datagrams, by fate (peer.h)")
      .def_ro("sent", &link::PeerCounters::sent)
      .def_ro("send_failed", &link::PeerCounters::send_failed)
      .def_ro("too_large", &link::PeerCounters::too_large)
      .def_ro("received", &link::PeerCounters::received)
      .def_ro("foreign", &link::PeerCounters::foreign)
      .def_ro("malformed", &link::PeerCounters::malformed)
      .def_ro("unexpected_channel", &link::PeerCounters::unexpected_channel);
  nb::class_<GroundPeers>(m, "PeerLink",
                          "The ground's end of the unicast link (docs/wire.md, \"Unicast on "
                          "Wi-Fi\"): LCM messages by UDP unicast to and from the drones")
      .def(nb::init<const std::string&, int, std::optional<int>>(), nb::arg("peers"),
           nb::arg("listen_port") = link::PeerLink::kDefaultPort,
           nb::arg("vehicle_id") = nb::none(),
           "PEERS: \"ADDRESS:PORT[,ADDRESS:PORT]\", the drones' IPv4 addresses; takes what they send (of VEHICLE_ID "
           "only, if given) on LISTEN_PORT (0: any free port). ValueError names a bad peer or "
           "a port in use")
      .def("fileno", &GroundPeers::fileno, "the socket, for select()")
      .def_prop_ro("listen_port", &GroundPeers::listenPort)
      .def("send", &GroundPeers::send, nb::arg("channel"), nb::arg("data"),
           "Sends an encoded message to every peer; False if none took it")
      .def("receive", &GroundPeers::receive,
           "[(channel, data)] of every datagram waiting, without blocking")
      .def_prop_ro("counters", &GroundPeers::counters, nb::rv_policy::reference_internal);
  m.attr("DEFAULT_PEER_PORT") = link::PeerLink::kDefaultPort;

  nb::exception<KeyFileError>(m, "KeyFileError");
  m.def("load_key_file",
        [](const std::filesystem::path& path) {
          const StatusOr<link::Key> key = link::loadKeyFile(path.string());
          if (!key.ok()) throw KeyFileError(key.status().message());
          return nb::bytes(reinterpret_cast<const char*>(key->bytes.data()), key->bytes.size());
        },
        nb::arg("path"),
        "A 32-byte key; KeyFileError (like ssh) for a file group or others may access");
  m.def("key_id", [](const nb::bytes& key) { return keyOf(key).id; }, nb::arg("key"),
        "First 4 bytes of SHA-256 of the key, big-endian (unsigned)");

  nb::class_<Signer>(m, "Signer", "Signs the ground's corrections for one vehicle (HMAC-SHA256)")
      .def(nb::init<const nb::bytes&, int32_t, std::optional<int64_t>>(), nb::arg("key"),
           nb::arg("vehicle_id"), nb::arg("first_sequence") = nb::none(),
           "first_sequence: by default the wall clock in microseconds")
      .def("sign", &Signer::sign, nb::arg("inner"), nb::arg("utime_now") = nb::none(),
           "the encoded signed_t around INNER, an encoded LCM message (flight_command_t)")
      .def("sign_correction", &Signer::signCorrection, nb::arg("keyframe_id"), nb::arg("utime"),
           nb::arg("T_world_cam"), nb::arg("reset_counter"), nb::arg("utime_now") = nb::none(),
           "The encoded signed_t around a pose_correction_t of one keyframe");

  nb::class_<CorrectionReceiver>(m, "CorrectionReceiver",
                                 "The drone's end of the uplink: verifies signed corrections")
      .def(nb::init<const nb::bytes&, int32_t, double>(), nb::arg("key"), nb::arg("vehicle_id"),
           nb::arg("window_s") = link::VerifierParams().window_s)
      .def("receive", &CorrectionReceiver::receive, nb::arg("data"), nb::arg("now_utime"),
           "The correction (a StampedPose) if authentic, fresh and well formed; else None")
      .def_prop_ro("rejects", &CorrectionReceiver::rejects, nb::rv_policy::reference_internal)
      .def_prop_ro("accepted", &CorrectionReceiver::accepted)
      .def_prop_ro("duplicates", &CorrectionReceiver::duplicates,
                   "copies of corrections already accepted: not applied again, not rejected");
}

}  // namespace kinfly::native
