// kinfly-flight-lqr: the attitude LQR of the default vehicle and parameters (docs/flight.md) as
// JSON: A, B, Q, R of the discretised model, the Riccati solution P and the gain K, row-major, at
// full double precision, so that tests/firmware/test_flight_lqr.py can solve the same equation
// with SciPy and compare. Exit 1 when the design fails.
#include <cstdio>

#include "kinfly/flight/attitude_controller.h"

namespace {

template <class Matrix>
void printMatrix(const char* name, const Matrix& m, bool last = false) {
  std::printf("  \"%s\": [", name);
  for (int r = 0; r < m.rows(); ++r) {
    std::printf("%s[", r ? ", " : "");
    for (int c = 0; c < m.cols(); ++c) std::printf("%s%.17g", c ? ", " : "", m(r, c));
    std::printf("]");
  }
  std::printf("]%s\n", last ? "" : ",");
}

}  // namespace

int main() {
  const kinfly::flight::VehicleParams vehicle_params;
  const kinfly::flight::LqrAttitudeParams lqr_params;
  const kinfly::Status valid = vehicle_params.validate();
  if (!valid.ok()) {
    std::fprintf(stderr, "kinfly-flight-lqr: %s\n", valid.message().c_str());
    return 1;
  }
  const kinfly::flight::Vehicle vehicle(vehicle_params);
  const auto design = kinfly::flight::designAttitudeLqr(lqr_params, vehicle);
  if (!design.ok()) {
    std::fprintf(stderr, "kinfly-flight-lqr: %s\n", design.status().message().c_str());
    return 1;
  }
  std::printf("{\n  \"control_rate_hz\": %.17g,\n  \"doubling_steps\": %d,\n",
              lqr_params.control_rate_hz, design->doubling_steps);
  std::printf("  \"closed_loop_spectral_radius\": %.17g,\n", design->closed_loop_spectral_radius);
  printMatrix("A", design->A);
  printMatrix("B", design->B);
  printMatrix("Q", design->Q);
  printMatrix("R", design->R);
  printMatrix("P", design->P);
  printMatrix("K", design->K, true);
  std::printf("}\n");
  return 0;
}
