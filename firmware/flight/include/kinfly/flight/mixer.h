// From the wanted collective thrust and body moments to rotor speed commands. Where the rotors
// cannot give all of it, the wrench gives way as autopilots let it (PX4's sequential
// desaturation without airmode): yaw first, then the collective thrust; roll and pitch keep
// their moments unless even zero yaw and any thrust cannot hold them. The cut is reported so
// that the rate controller's integrators stop winding up on the axes that were cut.
#pragma once

#include <array>

#include "kinfly/flight/vehicle.h"

namespace kinfly::flight {

struct MixerSaturation {
  // Per body axis (roll, pitch, yaw): the demanded moment was cut while positive / negative.
  std::array<bool, 3> moment_cut_positive{};
  std::array<bool, 3> moment_cut_negative{};
  double roll_pitch_kept = 1.0;  // [-] [0, 1] fraction of the roll and pitch moments given
  double yaw_kept = 1.0;         // [-] [0, 1] fraction of the yaw moment given
  double thrust_change_n = 0.0;  // [N] given minus demanded collective thrust
  bool any() const;
};

struct MixerOutput {
  Vector4d rotor_speed_rad_s = Vector4d::Zero();  // commands, always within the vehicle's limits
  Wrench achieved;                                // what these speeds give at steady state
  MixerSaturation saturation;
};

// Works on squared rotor speeds, where the allocation is linear; stateless.
class Mixer {
 public:
  // Keeps a reference: the vehicle outlives the mixer (both live as long as the control task).
  explicit Mixer(const Vehicle& vehicle);
  MixerOutput mix(const Wrench& demanded) const;

 private:
  const Vehicle& vehicle_;
  double speed_sq_min_;
  double speed_sq_max_;
};

}  // namespace kinfly::flight
