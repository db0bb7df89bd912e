// The discrete algebraic Riccati equation
//   P = A'PA - A'PB (R + B'PB)^-1 B'PA + Q
// by the structure-preserving doubling algorithm (Chu, Fan, Lin, "A structure-preserving doubling
// algorithm for discrete-time algebraic Riccati equations", 2005): each step doubles the horizon
// of the Riccati recursion, so the slow modes of a 1 kHz discretisation (eigenvalues near 1) cost
// tens of steps where the plain recursion takes thousands.
#pragma once

#include <Eigen/Core>

#include "kinfly/core/status.h"

namespace kinfly::flight {

struct RiccatiSolution {
  Eigen::MatrixXd P;  // N x N
  Eigen::MatrixXd K;  // M x N: (R + B'PB)^-1 B'PA, u = -K x
  int doubling_steps = 0;
  double closed_loop_spectral_radius = 0.0;  // of A - B K: below 1 for the stabilising P
};

// A (N x N), B (N x M), Q (N x N), R (M x M). Fails when the sizes disagree, the doubling does
// not settle within max_steps, P does not satisfy the equation to relative_tolerance, or the P
// found does not stabilise A - B K (the equation then has other, non-stabilising solutions: an
// unstabilisable pair, a Q that does not see an unstable mode). Dynamic sizes on purpose: it
// runs once at start, and Eigen's fixed-size eigen solver took minutes to compile.
StatusOr<RiccatiSolution> solveDiscreteRiccati(const Eigen::MatrixXd& A, const Eigen::MatrixXd& B,
                                               const Eigen::MatrixXd& Q, const Eigen::MatrixXd& R,
                                               double relative_tolerance = 1e-10,
                                               int max_steps = 100);

}  // namespace kinfly::flight
