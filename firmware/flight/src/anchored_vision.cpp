#include "kinfly/flight/anchored_vision.h"

namespace kinfly::flight {

AnchoredVision::Inputs AnchoredVision::take(const AnchoredPose& pose) {
  Inputs in;
  if (seen_ && pose.reset_counter != reset_counter_) {
    // The estimator's "odom" is the map: its coordinates jumped by the change of the anchor since
    // the last pose it saw (the refinements in between included).
    OdomReset reset = template_;
    reset.utime = pose.utime;
    reset.T_odomNew_odomOld = pose.T_map_odom * T_map_odom_.inverse();
    reset.reset_counter = pose.reset_counter;
    in.reset = reset;
  }
  seen_ = true;
  reset_counter_ = pose.reset_counter;
  T_map_odom_ = pose.T_map_odom;
  in.vision = {pose.utime, pose.T_map_odom * pose.T_odom_cam, pose.weak};
  for (int i = 0; i < pose.weak.count; ++i)
    in.vision.weak.d[i].head<3>() = pose.T_map_odom.linear() * pose.weak.d[i].head<3>();
  return in;
}

}  // namespace kinfly::flight
