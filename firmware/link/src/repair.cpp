#include "kinfly/link/repair.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace kinfly::link {

Status RepairScheduler::Params::validate() const {
  if (max_asks < 1 || max_asks > 16) return Status::error("max_asks must be in [1, 16]");
  if (!(retry_s >= 0.01 && retry_s <= 10.0))
    return Status::error("retry_s must be in [0.01, 10] s");
  return {};
}

RepairScheduler::RepairScheduler(const Params& params) : params_(params) {
  if (const Status valid = params.validate(); !valid.ok()) throw std::invalid_argument(valid.message());
}

bool RepairScheduler::Asked::is(const chunk_request_t& request) const {
  return keyframe_id == request.keyframe_id && utime == request.utime && group == request.group;
}

RepairScheduler::Asked* RepairScheduler::find(const chunk_request_t& request) {
  const auto it = std::find_if(asked_.begin(), asked_.end(),
                               [&](const Asked& a) { return a.is(request); });
  return it == asked_.end() ? nullptr : &*it;
}

int RepairScheduler::due(const ChunkAssembler& assembler, bool include_newest, int64_t now_us,
                         std::vector<chunk_request_t>* out) {
  // Forgotten only once the assembler no longer holds its group incomplete (completed, given up,
  // a restarted drone's): the newest keyframe's too, which include_newest may leave out.
  const int held = assembler.repairRequests(true, &incomplete_);
  const auto still_held = [&](const Asked& a) {
    return std::any_of(incomplete_.begin(), incomplete_.begin() + held,
                       [&](const chunk_request_t& r) { return a.is(r); });
  };
  asked_.erase(std::remove_if(asked_.begin(), asked_.end(),
                              [&](const Asked& a) { return !still_held(a); }),
               asked_.end());
  const auto retry_us = static_cast<int64_t>(std::llround(params_.retry_s * 1e6));
  int n = 0;
  for (int i = 0; i < held; ++i) {
    const chunk_request_t& request = incomplete_[static_cast<size_t>(i)];
    if (!include_newest && request.keyframe_id == assembler.newestKeyframeId()) continue;
    Asked* a = find(request);
    if (a == nullptr) {
      a = &asked_.emplace_back(Asked{request.utime, request.keyframe_id, request.group, 0, 0});
    } else if (a->asks >= params_.max_asks || now_us - a->last_us < retry_us) {
      continue;
    }
    ++a->asks;
    a->last_us = now_us;
    if (static_cast<size_t>(n) == out->size()) out->emplace_back();
    (*out)[static_cast<size_t>(n++)] = request;
    ++requests_;
  }
  return n;
}

bool RepairScheduler::asked(int64_t utime, int64_t keyframe_id) const {
  return std::any_of(asked_.begin(), asked_.end(), [&](const Asked& a) {
    return a.keyframe_id == keyframe_id && a.utime == utime;
  });
}

}  // namespace kinfly::link
