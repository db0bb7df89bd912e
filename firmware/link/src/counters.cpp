#include "kinfly/link/counters.h"

namespace kinfly::link {

void RejectCounters::count(Verdict verdict) {
  switch (verdict) {
    case Verdict::kAccepted: return;
    case Verdict::kWrongVehicle: ++wrong_vehicle; return;
    case Verdict::kWrongKey: ++wrong_key; return;
    case Verdict::kBadMac: ++bad_mac; return;
    case Verdict::kStale: ++stale; return;
    case Verdict::kReplayed: ++replayed; return;
    case Verdict::kDuplicate: return;  // not a rejection: CorrectionReceiver counts copies
  }
}

void RejectCounters::count(DecodeStatus status) {
  if (status != DecodeStatus::kOk) ++malformed;
}

RejectCounters& RejectCounters::operator+=(const RejectCounters& other) {
  unsigned_messages += other.unsigned_messages;
  wrong_key += other.wrong_key;
  bad_mac += other.bad_mac;
  stale += other.stale;
  replayed += other.replayed;
  malformed += other.malformed;
  unknown_channel += other.unknown_channel;
  wrong_vehicle += other.wrong_vehicle;
  return *this;
}

int64_t RejectCounters::total() const {
  return unsigned_messages + wrong_key + bad_mac + stale + replayed + malformed + unknown_channel +
         wrong_vehicle;
}

void RejectCounters::writeTo(drone_status_t* status) const {
  status->rejected_unsigned = unsigned_messages;
  status->rejected_wrong_key = wrong_key;
  status->rejected_bad_mac = bad_mac;
  status->rejected_stale = stale;
  status->rejected_replayed = replayed;
  status->rejected_malformed = malformed;
  status->rejected_unknown_channel = unknown_channel;
  status->rejected_wrong_vehicle = wrong_vehicle;
}

}  // namespace kinfly::link
