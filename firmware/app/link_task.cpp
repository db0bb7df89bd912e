#include "link_task.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "kinfly/link/channels.h"
#include "kinfly/link/conversions.h"

namespace kinfly::fw {

LinkTask::LinkTask(const FirmwareConfig& config, std::optional<link::Key> key,
                   SharedAnchor* anchor, Counters* counters, BoundedQueue<KeyframeJob>* keyframes,
                   const BoundedQueue<DepthCapture>* capture_queue, const PinholeCamera& camera,
                   double depth_scale_m, LatestValue<CommandMail>* commands,
                   LatestValue<flight_status_t>* flight_status, const StopToken* stop)
    : config_(config), anchor_(anchor), counters_(counters), keyframes_(keyframes),
      capture_queue_(capture_queue), stop_token_(stop), camera_(camera), depth_scale_m_(depth_scale_m),
      codec_(DepthCodec::Params()), job_(withDepthImage<KeyframeJob>(camera)),
      scaled_(camera.width / 2, camera.height / 2), chunks_(config.link.chunks),
      // A burst of two chunks: the budget's pace holds from the first keyframe on.
      bucket_(config.link.rate.start_bps / 8.0, 2.0 * config.link.chunks.mtu_bytes),
      rate_(config.link.rate), watch_(config.source.watch),
      publisher_(
          "link", config.link.effectiveLcmUrl(), config.vehicle.id,
          [this](lcm::LCM& lcm) {
            // Every channel of this vehicle but those the drone sends itself, which multicast
            // loops back: LCM reassembles a fragmented message (an allocation the size of a
            // keyframe) only on a channel someone subscribed to, and memq:// allocates for each
            // message a subscription takes. LCM's patterns are GLib (PCRE) regular expressions.
            std::string own;
            for (size_t i = 0; i < link::kChannelCount; ++i) {
              const auto channel = static_cast<link::Channel>(i);
              if (link::sentByGround(channel)) continue;
              own += (own.empty() ? "" : "|") + link::channelName(channel, config_.vehicle.id);
            }
            const std::string channels =
                "(?!(" + own + ")$)" + link::vehicleChannelsRegex(config_.vehicle.id);
            lcm_subscribe(lcm.getUnderlyingLCM(), channels.c_str(), &LinkTask::onMessage, this);
          },
          unicastPeers(config.link, static_cast<uint16_t>(config.link.peer_port),
                [this](const lcm_recv_buf_t* message, const char* channel) {
                  handle(message, channel);
                })) {
  commands_ = commands;
  flight_status_ = flight_status;
  if (key) {
    corrections_.emplace(*key, config.vehicle.id, config.link.signing, link::DecodeBounds());
    command_receiver_.emplace(*key, config.vehicle.id, config.link.signing,
                              link::DecodeBounds());
  }
  codec_.reserve(camera.width, camera.height, &message_.payload);
  // The largest keyframe this camera can make, at any redundancy: no allocation while flying.
  chunks_.reserve(depth_keyframe_t().getEncodedSize() +
                  static_cast<int64_t>(message_.payload.capacity()));
  out_.block.reserve(static_cast<size_t>(chunks_.blockBytes()));
  status_.vehicle_id = config.vehicle.id;
  publisher_.chargeTo(&counters->priority_bytes);
}

void LinkTask::run() {
  {
    Clock::time_point next_status = Clock::now();
    while (!stop_) serve(&next_status);
  }
  // What the odometry selected before it stopped still goes out (the newest of the queue), at
  // the budget's pace, while the network is there.
  Clock::time_point next_status = Clock::now();
  while ((sending() || keyframes_->size() > 0) && publisher_.up()) serve(&next_status);
  if (await_corrections_) awaitCorrections();
  watchSensor();
  publishStatus(/*is_final=*/true);
  if (const link::PeerLink* peer = publisher_.peer()) {
    const link::PeerCounters& c = peer->counters();
    spdlog::info("link: unicast: {} datagrams sent, {} not ({} too large); {} received, dropped: "
                 "{} from other hosts, {} malformed, {} on other channels",
                 c.sent, c.send_failed, c.too_large, c.received, c.foreign, c.malformed,
                 c.unexpected_channel);
  }
}

void LinkTask::serve(Clock::time_point* next_status) {
  using namespace std::chrono_literals;
  publisher_.maintain();
  if (!sending()) takeKeyframe();
  if (publisher_.up()) {
    // What went first (status, odometry, telemetry) is paid for by the keyframes.
    const int64_t priority_bytes = counters_->priority_bytes.exchange(0);
    priority_window_bytes_ += priority_bytes;
    bucket_.charge(static_cast<double>(priority_bytes), secondsSince(began_));
    // Listens until the next chunk is due (at most 10 ms, so a new keyframe waits no longer),
    // rounded up to whole milliseconds: the thread sleeps rather than spins on the odometry's
    // core.
    const double wait_s =
        sending() ? bucket_.waitS(pending_.first[next_chunk_].getEncodedSize(),
                                  secondsSince(began_))
                  : 0.01;
    publisher_.handle(static_cast<int>(std::clamp(std::ceil(wait_s * 1e3), 0.0, 10.0)));
    sendChunks();
  } else {
    // What the odometry sent meanwhile is not the keyframes' debt once the link is back.
    counters_->priority_bytes.exchange(0);
    // Nothing to hear and nothing can go out: what was being sent is lost (counted), and the
    // odometry's keyframes are taken (and dropped) as they come.
    if (sending()) {
      ++counters_->keyframes_failed;
      next_chunk_ = pending_.size();
    }
    if (keyframes_->pop(&job_, 10ms)) {
      ++counters_->keyframes_failed;
      if (send_log_.allow(secondsSince(began_)))
        spdlog::warn("link: keyframe {} not sent: the network is down ({} more since the last "
                     "report)",
                     job_.keyframe_id, send_log_.suppressed());
    }
  }
  if (Clock::now() >= *next_status) {
    watchSensor();
    publishStatus();
    *next_status += std::chrono::duration_cast<Clock::duration>(
        std::chrono::duration<double>(1.0 / config_.link.status_rate_hz));
  }
}

bool LinkTask::groundHeard() const {
  return ground_status_heard_ && Clock::now() - last_ground_heard_ <=
                                     std::chrono::duration<double>(config_.link.timeout_s);
}

void LinkTask::awaitCorrections() {
  const auto deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                           std::chrono::duration<double>(config_.link.final_wait_s));
  // Only for a ground station that is there: one never heard, or gone quiet, sends nothing.
  if (last_keyframe_sent_ < 0 || !groundHeard()) return;
  spdlog::info("link: waiting up to {:.1f} s for the ground's corrections of the last keyframes",
               config_.link.final_wait_s);
  Clock::time_point next_status = Clock::now();
  while (!stop_token_->interrupted() && Clock::now() < deadline && groundHeard() &&
         ground_status_.last_keyframe_id < last_keyframe_sent_)
    serve(&next_status);
  if (ground_status_.last_keyframe_id < last_keyframe_sent_)
    spdlog::warn("link: the ground station had not answered keyframe {} (its last: {}) when the "
                 "wait ended",
                 last_keyframe_sent_, ground_status_.last_keyframe_id);
}

link::RejectCounters LinkTask::rejects() const {
  link::RejectCounters all = rejects_;
  if (corrections_) all += corrections_->rejects();
  if (command_receiver_) all += command_receiver_->rejects();
  return all;
}

void LinkTask::onMessage(const lcm_recv_buf_t* rbuf, const char* channel, void* self) {
  static_cast<LinkTask*>(self)->handle(rbuf, channel);
}

void LinkTask::handle(const lcm_recv_buf_t* rbuf, const char* channel) {
  const double now_s = secondsSince(began_);
  const auto parsed = link::parseChannel(channel);
  if (!parsed) {
    ++rejects_.unknown_channel;
    if (reject_log_.allow(now_s)) spdlog::warn("link: message on unknown channel {}", channel);
    return;
  }
  if (parsed->channel == link::Channel::kGroundStatus) {
    onGroundStatus(rbuf);
    return;
  }
  if (parsed->channel == link::Channel::kChunkRequest) {
    onChunkRequest(rbuf);
    return;
  }
  if (parsed->channel == link::Channel::kCommand) {
    onCommand(rbuf);
    return;
  }
  if (parsed->channel != link::Channel::kCorrection) return;  // another drone's traffic
  last_ground_heard_ = Clock::now();
  const auto correction = receiveSigned(corrections_, rbuf, "correction", now_s);
  if (!correction) return;
  std::lock_guard<std::mutex> lock(anchor_->mutex);
  const Pose corrected = link::readPose(correction->T_world_cam);
  const auto outcome =
      anchor_->anchor.apply(correction->keyframe_id, corrected, correction->reset_counter);
  if (outcome != CorrectionAnchor::Outcome::kApplied) {
    ++counters_->corrections_unknown;
    spdlog::warn("link: correction of keyframe {} not applied: {}", correction->keyframe_id,
                 outcome == CorrectionAnchor::Outcome::kUnknownKeyframe
                     ? "unknown keyframe"
                     : "older than one already applied");
  }
}

namespace {

// flight_command_t's kinds in the flight stack's terms (the decoder refused any other).
flight::CommandKind commandKind(int8_t kind) {
  switch (kind) {
    case flight_command_t::ARM: return flight::CommandKind::kArm;
    case flight_command_t::DISARM: return flight::CommandKind::kDisarm;
    case flight_command_t::TAKE_OFF: return flight::CommandKind::kTakeOff;
    case flight_command_t::GO_TO: return flight::CommandKind::kGoTo;
    case flight_command_t::MISSION: return flight::CommandKind::kMission;
    case flight_command_t::LAND: return flight::CommandKind::kLand;
    default: return flight::CommandKind::kHold;
  }
}

}  // namespace

template <class Inner>
std::optional<Inner> LinkTask::receiveSigned(std::optional<link::SignedReceiver<Inner>>& receiver,
                                             const lcm_recv_buf_t* rbuf, const char* what,
                                             double now_s) {
  if (!receiver) {
    ++rejects_.unsigned_messages;
    if (reject_log_.allow(now_s))
      spdlog::warn("link: {} ignored: no key loaded (vehicle.key_file)", what);
    return std::nullopt;
  }
  const int64_t rejected_before = receiver->rejects().total();
  auto received = receiver->receive(rbuf->data, rbuf->data_size, link::wallClockUtime());
  // The receiver counts every refusal by its reason (and copies apart).
  if (!received && receiver->rejects().total() > rejected_before && reject_log_.allow(now_s))
    spdlog::warn("link: {} rejected ({} rejected in all, by reason in the status)", what,
                 rejected_before + 1);
  return received;
}

void LinkTask::onCommand(const lcm_recv_buf_t* rbuf) {
  const auto received = receiveSigned(command_receiver_, rbuf, "command", secondsSince(began_));
  if (!received) return;
  const flight_command_t& m = *received;
  if (!recent_commands_.first(m.command_id)) return;  // answered, or being answered
  if (commands_ == nullptr) {
    ++commands_dropped_;
    spdlog::warn("link: command {} ignored: no control task (flight.backend = none)",
                 m.command_id);
    return;
  }
  CommandMail& mail = commands_->back();
  mail.command_id = m.command_id;
  mail.command = flight::FlightCommand{
      commandKind(m.kind), m.height_m,
      Eigen::Vector3d(m.target_world_m[0], m.target_world_m[1], m.target_world_m[2]),
      m.has_yaw ? m.yaw_rad : std::numeric_limits<double>::quiet_NaN()};
  mail.mission.reset();
  if (m.kind == flight_command_t::MISSION) {
    std::vector<Eigen::Vector3d> waypoints;
    for (const auto& w : m.waypoints_world_m) waypoints.emplace_back(w[0], w[1], w[2]);
    flight::TrajectoryParams params = config_.flight.stack.trajectory;
    if (m.max_speed_m_s > 0.0) params.max_speed_m_s = m.max_speed_m_s;
    auto mission = flight::Trajectory::minimumSnap(waypoints, params, 0.0);
    if (!mission.ok()) {
      ++commands_dropped_;
      spdlog::warn("link: mission of command {} not flown: {}", m.command_id,
                   mission.status().message());
      return;
    }
    mail.mission = *std::move(mission);
  }
  commands_->publish();
  ++commands_passed_;
  spdlog::info("link: command {} ({}) passed to the control task", m.command_id,
               flight::toString(mail.command.kind));
}

void LinkTask::onGroundStatus(const lcm_recv_buf_t* rbuf) {
  last_ground_heard_ = Clock::now();
  const link::DecodeResult r =
      link::decodeMessage(rbuf->data, rbuf->data_size, link::DecodeBounds(), &ground_status_);
  ground_status_heard_ = r.ok() && ground_status_.vehicle_id == config_.vehicle.id;
  // Handled after the correction the ground sent before this status: it is applied by now.
  if (ground_status_heard_) {
    counters_->ground_done_keyframe = ground_status_.last_keyframe_id;
    ++counters_->ground_statuses;
  }
  if (!r.ok())
    ++rejects_.malformed;
  else if (ground_status_.vehicle_id != config_.vehicle.id)
    ++rejects_.wrong_vehicle;
  if (!ground_status_heard_) return;
  // The ground's goodput counts keyframe chunks only; the budget covers all the drone sends.
  const double window_s = secondsSince(priority_window_start_);
  if (window_s >= 1.0) {
    priority_bps_ = 8.0 * static_cast<double>(priority_window_bytes_) / window_s;
    priority_window_bytes_ = 0;
    priority_window_start_ = Clock::now();
  }
  rate_.onReport(ground_status_.goodput_bps + priority_bps_, ground_status_.queue_delay_ms,
                 limited_, secondsSince(began_));
  bucket_.setRate(rate_.budgetBps() / 8.0);
  limited_ = false;
}

void LinkTask::onChunkRequest(const lcm_recv_buf_t* rbuf) {
  last_ground_heard_ = Clock::now();
  const link::DecodeResult r =
      link::decodeMessage(rbuf->data, rbuf->data_size, link::DecodeBounds(), &request_);
  if (!r.ok()) {
    ++rejects_.malformed;
    return;
  }
  if (request_.vehicle_id != config_.vehicle.id) {
    ++rejects_.wrong_vehicle;
    return;
  }
  // Answered at once, ahead of the keyframe being sent (the ground still wants this one), and
  // paid from the same budget, so the next chunks wait for it.
  for (int i = 0; i < request_.index_count; ++i) {
    const keyframe_chunk_t* chunk = chunks_.resend(request_, i);
    if (!chunk) break;  // no longer kept, or its repair budget spent
    bucket_.charge(chunk->getEncodedSize(), secondsSince(began_));
    if (!publishChunk(*chunk)) return;
    ++chunks_resent_;
  }
}

bool LinkTask::takeKeyframe() {
  using namespace std::chrono_literals;
  bool taken = false;
  while (keyframes_->pop(&job_, 0ms)) {
    if (taken) ++keyframes_skipped_;
    taken = true;
  }
  if (taken) startKeyframe(job_);
  return taken;
}

namespace {

// Every scale-th pixel of every scale-th row, as PinholeCamera::scaled(scale) describes: raw
// values are kept (an average would invent depths across edges).
void subsample(ImageView<const uint16_t> in, int scale, ImageView<uint16_t> out) {
  for (int y = 0; y < out.height(); ++y) {
    const uint16_t* src = in.row(y * scale);
    uint16_t* dst = out.row(y);
    for (int x = 0; x < out.width(); ++x) dst[x] = src[x * scale];
  }
}

}  // namespace

void LinkTask::startKeyframe(const KeyframeJob& job) {
  // Smaller images only when even a slow stream of these would not fit the budget.
  const int scale = KeyframeScale::choose(config_.link.scale, scale_, rate_.budgetBps() / 8.0,
                                          wire_costs_);
  if (scale != scale_) {
    spdlog::info("link: keyframes at 1/{} of the size from keyframe {} (send budget {:.2f} "
                 "Mbit/s)",
                 scale, job.keyframe_id, rate_.budgetBps() * 1e-6);
    scale_ = scale;
  }
  ImageView<const uint16_t> depth = job.depth.view();
  if (scale_ > 1) {
    ImageView<uint16_t> small(scaled_.view().data(), camera_.width / scale_,
                              camera_.height / scale_);
    subsample(depth, scale_, small);
    depth = small;
  }
  depth_keyframe_t& m = message_;
  m.vehicle_id = config_.vehicle.id;
  link::fillKeyframe({job.utime, job.frame_id, job.keyframe_id, job.T_world_cam, job.tracking}, &m);
  const CodecResult r =
      link::encodeDepth(codec_, depth, camera_.scaled(scale_), depth_scale_m_, &m);
  if (!r.ok()) {
    ++counters_->keyframes_failed;
    spdlog::error("link: keyframe {} not encoded: {}", job.keyframe_id, toString(r.status));
    return;
  }
  // Redundancy for the loss the ground measured (a floor until it has).
  const link::LinkLoss loss{ground_status_heard_ ? ground_status_.link_loss : 0.0,
                            ground_status_heard_ ? std::max(1.0f, ground_status_.link_loss_run)
                                                 : 1.0};
  const int originals = chunks_.originalsPerGroup(m.getEncodedSize());
  const int recovery = link::recoveryChunks(originals, loss, config_.link.redundancy);
  const StatusOr<link::ChunkSpan> chunks = chunks_.encode(m, recovery);
  if (!chunks.ok()) {
    ++counters_->keyframes_failed;
    spdlog::error("link: keyframe {} not cut into chunks: {}", job.keyframe_id,
                  chunks.status().message());
    return;
  }
  pending_ = *chunks;
  next_chunk_ = 0;
  pending_keyframe_id_ = job.keyframe_id;
  redundancy_ = static_cast<float>(recovery) / static_cast<float>(originals);
  double& cost = wire_costs_[KeyframeScale::index(scale_)];
  cost = 0.0;
  for (const keyframe_chunk_t& c : pending_) cost += c.getEncodedSize();
}

void LinkTask::sendChunks() {
  while (sending()) {
    const keyframe_chunk_t& chunk = pending_.first[next_chunk_];
    if (!bucket_.take(chunk.getEncodedSize(), secondsSince(began_))) {
      limited_ = true;
      return;
    }
    if (!publishChunk(chunk)) {
      ++counters_->keyframes_failed;
      next_chunk_ = pending_.size();
      if (send_log_.allow(secondsSince(began_)))
        spdlog::warn("link: keyframe {} not sent: the network is down ({} more since the last "
                     "report)",
                     pending_keyframe_id_, send_log_.suppressed());
      return;
    }
    if (++next_chunk_ == pending_.size()) {
      ++counters_->keyframes_sent;
      last_keyframe_sent_ = pending_keyframe_id_;
    }
  }
}

bool LinkTask::publishChunk(const keyframe_chunk_t& chunk) {
  out_ = chunk;  // the block's capacity is kept: no allocation once it has grown
  // Numbered in the order they leave, resends included, so the ground's loss count from the
  // gaps sees no reordering that is not the network's.
  out_.sequence = next_sequence_++;
  out_.sent_utime = link::wallClockUtime();
  if (!publisher_.publish(link::Channel::kKeyframeChunk, out_)) return false;
  ++chunks_sent_;
  return true;
}

void LinkTask::watchSensor() {
  // Both on the steady clock's own epoch, as the capture thread stamps frames.
  const int64_t last_ns = counters_->last_frame_ns;
  const double now_s = std::chrono::duration<double>(Clock::now().time_since_epoch()).count();
  const double last_s = last_ns < 0 ? -1.0 : static_cast<double>(last_ns) * 1e-9;
  switch (watch_.update(now_s, last_s, counters_->sensor_waiting, counters_->capture_done)) {
    case SensorWatch::Change::kStalled:
      spdlog::warn("sensor: no depth frame for {:.1f} s (stall {})",
                   config_.source.watch.stall_timeout_s, watch_.stalls());
      break;
    case SensorWatch::Change::kResumed:
      spdlog::info("sensor: frames again after a {:.1f} s stall", watch_.lastStallS());
      break;
    default: break;
  }
}

namespace {

link::SensorState sensorState(SensorWatch::State state) {
  switch (state) {
    case SensorWatch::State::kStreaming: return link::SensorState::kStreaming;
    case SensorWatch::State::kWaiting: return link::SensorState::kWaiting;
    case SensorWatch::State::kStalled: return link::SensorState::kStalled;
    case SensorWatch::State::kEnded: return link::SensorState::kEnded;
  }
  return link::SensorState::kStreaming;
}

}  // namespace

void LinkTask::publishStatus(bool is_final) {
  const double elapsed_s = secondsSince(rate_window_start_);
  if (elapsed_s >= 1.0) {
    const auto rate = [elapsed_s](int64_t now, int64_t before) {
      return static_cast<float>(static_cast<double>(now - before) / elapsed_s);
    };
    depth_rate_hz_ = rate(counters_->frames_captured, captured_at_window_);
    odometry_rate_hz_ = rate(counters_->frames_processed, processed_at_window_);
    keyframe_rate_hz_ = rate(counters_->keyframes_sent, sent_at_window_);
    captured_at_window_ = counters_->frames_captured;
    processed_at_window_ = counters_->frames_processed;
    sent_at_window_ = counters_->keyframes_sent;
    rate_window_start_ = Clock::now();
  }
  link::DroneHealth h;
  h.utime = link::wallClockUtime();
  h.is_final = is_final;
  h.depth_rate_hz = depth_rate_hz_;
  h.odometry_rate_hz = odometry_rate_hz_;
  h.keyframe_rate_hz = keyframe_rate_hz_;
  h.frames_captured = counters_->frames_captured;
  h.queue_drops = capture_queue_->dropped();
  h.keyframes_sent = counters_->keyframes_sent;
  h.keyframes_dropped = counters_->keyframes_failed + keyframes_->dropped();
  h.last_keyframe_id = last_keyframe_sent_;
  h.send_budget_bps = static_cast<float>(rate_.budgetBps());
  h.redundancy = redundancy_;
  h.keyframe_scale = scale_;
  h.chunks_sent = chunks_sent_;
  h.chunks_resent = chunks_resent_;
  h.keyframes_skipped = keyframes_skipped_;
  h.tracking = counters_->tracking.load();
  const auto since = Clock::now() - last_ground_heard_;
  h.link = last_ground_heard_ == Clock::time_point()
               ? link::LinkState::kUnknown
               : (since <= std::chrono::duration<double>(config_.link.timeout_s)
                      ? link::LinkState::kUp
                      : link::LinkState::kStale);
  h.sensor = sensorState(watch_.state());
  h.sensor_connects = counters_->sensor_connects;
  h.sensor_stalls = watch_.stalls();
  h.frames_skipped = counters_->frames_skipped;
  h.frames_lost = counters_->frames_lost;
  h.rejects = rejects();
  h.corrections_accepted = accepted() - counters_->corrections_unknown;
  h.corrections_unknown_keyframe = counters_->corrections_unknown;
  h.commands_passed = commands_passed_;
  link::fillDroneStatus(h, &status_);
  publisher_.publish(link::Channel::kStatus, status_);  // the publisher logs a network going down
  // The flight stack's newest state, with the status: the Wi-Fi carries it at 10 Hz (about
  // 3 kbit/s), however fast the control task runs.
  if (flight_status_ != nullptr && flight_status_->fetch())
    publisher_.publish(link::Channel::kFlight, flight_status_->front());
}

}  // namespace kinfly::fw
