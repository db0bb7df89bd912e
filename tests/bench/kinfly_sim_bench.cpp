// kinfly-sim's own speed without the drone's programs (docs/sim.md, "Measured"): the world's work
// for each simulated second (1000 steps of RK4 dynamics, Dryden wind and the IMU, 30 depth frames
// rendered by Embree with the Kinect noise and encoded for the link) against the wall clock, on
// one core at 320x240 and 640x480, and at 640x480 with the frame split over two threads (as
// kinfly-sim renders on this machine, where kinfly-fw waits in the lockstep). The camera flies a
// circle through the furnished room, so the rendered views vary as a flight's do. Prints JSON;
// never fails on a time.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <tuple>
#include <vector>

#include "kinfly/codec/depth_codec.h"
#include "kinfly/sim/depth_camera.h"
#include "kinfly/sim/imu_model.h"
#include "kinfly/sim/multirotor.h"
#include "kinfly/sim/wind.h"

namespace {

using namespace kinfly;
using namespace kinfly::sim;
using Clock = std::chrono::steady_clock;

constexpr double kSimulatedS = 20.0;
constexpr double kImuHz = 1000.0;
constexpr double kCameraHz = 30.0;
constexpr double kCircleRadiusM = 1.0;
constexpr double kCirclePeriodS = 20.0;

struct Figures {
  double real_time_factor;
  double render_ms_median;
  double step_us_mean;
};

Figures fly(const RayScene& rays, int downsample, int threads) {
  DepthCameraParams camera_params;
  camera_params.camera = camera_params.camera.scaled(downsample);
  camera_params.threads = threads;
  DepthCamera camera(rays, camera_params);
  DepthCodec codec{DepthCodec::Params()};
  std::vector<uint8_t> encoded;
  Image<uint16_t> raw(camera_params.camera.width, camera_params.camera.height);
  Multirotor drone(MultirotorParams{});
  drone.placeHovering({0.0, 0.0, -1.0}, 0.0);
  WindParams wind_params;
  wind_params.turbulence_w20_m_s = 5.0;
  Wind wind(wind_params);
  ImuModel imu{ImuParams{}};
  const Vector4d hover = Vector4d::Constant(drone.hoverRotorSpeedRadS());
  std::vector<double> render_ms;
  double step_s = 0.0;
  const int steps = static_cast<int>(kSimulatedS * kImuHz);
  const int steps_per_frame = static_cast<int>(kImuHz / kCameraHz);
  const Clock::time_point start = Clock::now();
  for (int i = 0; i < steps; ++i) {
    const double t_s = i / kImuHz;
    const Clock::time_point step_start = Clock::now();
    const Eigen::Vector3d air = wind.step(t_s, 1.0 / kImuHz, 1.0, drone.state().v_world_m_s);
    drone.step(hover, air, 1.0 / kImuHz);
    imu.sample(drone.state().omega_body_rad_s, drone.specificForceBodyMS2());
    step_s += std::chrono::duration<double>(Clock::now() - step_start).count();
    if (i % steps_per_frame != 0) continue;
    // The camera on the circle, looking along it (optical z along the body's x).
    const double angle = 2.0 * M_PI * t_s / kCirclePeriodS;
    Pose T_world_body = Pose::Identity();
    T_world_body.linear() =
        Eigen::AngleAxisd(angle + M_PI / 2.0, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    Pose T_world_cam = T_world_body * forwardBodyCam();
    T_world_cam.translation() =
        Eigen::Vector3d(kCircleRadiusM * std::cos(angle), kCircleRadiusM * std::sin(angle), -1.0);
    const Clock::time_point render_start = Clock::now();
    camera.render(T_world_cam, raw);
    codec.encode(raw, &encoded);
    render_ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - render_start).count());
  }
  const double wall_s = std::chrono::duration<double>(Clock::now() - start).count();
  std::sort(render_ms.begin(), render_ms.end());
  return {kSimulatedS / wall_s, render_ms[render_ms.size() / 2], step_s / steps * 1e6};
}

}  // namespace

int main() {
  const Scene scene = furnishedRoom();
  auto rays = RayScene::create(scene);
  if (!rays.ok()) {
    std::fprintf(stderr, "kinfly-sim-bench: %s\n", rays.status().message().c_str());
    return 1;
  }
  const Figures qvga = fly(*rays.value(), 2, 1);
  const Figures vga = fly(*rays.value(), 1, 1);
  const Figures vga_2 = fly(*rays.value(), 1, 2);
  std::printf("{\n  \"simulated_s\": %.0f,\n", kSimulatedS);
  for (const auto& [name, f, last] : {std::tuple{"qvga", qvga, false}, {"vga", vga, false},
                                      {"vga_2_threads", vga_2, true}}) {
    std::printf("  \"%s\": {\"real_time_factor\": %.2f, \"frame_render_encode_ms_median\": %.2f, "
                "\"step_us_mean\": %.2f}%s\n",
                name, f.real_time_factor, f.render_ms_median, f.step_us_mean, last ? "" : ",");
  }
  std::printf("}\n");
  return 0;
}
