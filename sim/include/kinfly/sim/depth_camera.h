// The simulated depth camera (docs/sim.md, "Depth camera"): each pixel's ray cast into the scene
// by Embree, then what a structured-light sensor (Kinect v1, Xtion) does to the depth: axial noise
// growing with the square of the range (the thesis's model, kinectNoiseSigmaM), disparity
// quantisation (the sensor measures disparity in 1/8 pixel steps, so depth comes in steps that
// grow with the square of the range too), no return at grazing incidence or outside the range.
// Raw depth as the OpenNI source gives it: uint16 in depth_scale_m units, 0 for no return.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "kinfly/core/camera.h"
#include "kinfly/core/image.h"
#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"
#include "kinfly/sim/random.h"
#include "kinfly/sim/ray_scene.h"

namespace kinfly::sim {

struct DepthCameraParams {
  // Kinect v1 at VGA, as its factory calibration is usually quoted (and ROS's openni driver):
  // fx = fy = 525 px, principal point at the centre.
  PinholeCamera camera{525.0f, 525.0f, 319.5f, 239.5f, 640, 480};
  double rate_hz = 30.0;              // [Hz] (0, 120] frames per second
  double latency_s = 0.03;            // [s] [0, 1] from capture to delivery
  double min_range_m = 0.5;           // [m] (0, max) nearer: no return
  double max_range_m = 4.5;           // [m] (min, 20] farther: no return
  double max_incidence_deg = 80.0;    // [deg] (0, 90] more grazing than this: no return
  bool noise = true;                  // false: exact depth (tests of the geometry alone)
  double baseline_m = 0.075;          // [m] (0, 1] projector to IR camera (Kinect v1)
  double disparity_focal_px = 580.0;  // [px] (0, 5000] the IR camera's focal length
  double disparity_step_px = 0.125;   // [px] [0, 1] disparity resolution; 0: not quantised
  double depth_scale_m = 0.001;       // [m] (0, 0.01] per raw unit (OpenNI: 1 mm)
  uint64_t seed = 3;
  // [1, 64] threads a frame's rays and its quantisation are split over; the frame is the same
  // for any count (the noise's deviates are drawn in one sequence, on one thread)
  int threads = 1;
  Status validate() const;
};

// std::round for the quantiser's numbers without a call into libm (std::round was 6 % of
// kinfly-sim's time in a VGA flight, by perf): the same for any x >= 0, and for x < 0 the same
// after the clamp to 0 that follows (both give a number <= 0). Truncating a double of magnitude
// below 2^52 is exact, and so is the difference to it.
double roundHalfUp(double x);

// The camera on the body: at the centre of mass, looking ahead (optical x right = body y, y down
// = body z, z ahead = body x), as kinfly-fw's estimator assumes by default.
Pose forwardBodyCam();

class DepthCamera {
 public:
  // scene outlives the camera; params valid.
  DepthCamera(const RayScene& scene, const DepthCameraParams& params);

  const DepthCameraParams& params() const { return params_; }

  // The frame seen from T_world_cam (optical frame: x right, y down, z forward) into raw, which
  // has the camera's size.
  void render(const Pose& T_world_cam, ImageView<uint16_t> raw);

 private:
  const RayScene& scene_;
  DepthCameraParams params_;
  NormalRandom random_;
  float min_cos_incidence_;
  std::vector<float> depth_m_;       // the frame's exact depths; 0: no return
  std::vector<size_t> first_noise_;  // a row's first deviate in noise_
  std::vector<double> noise_;
};

}  // namespace kinfly::sim
