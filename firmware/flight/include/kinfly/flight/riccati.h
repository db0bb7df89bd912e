// The discrete algebraic Riccati equation
//   P = A'PA - A'PB (R + B'PB)^-1 B'PA + Q
// by the structure-preserving doubling algorithm (Chu, Fan, Lin, "A structure-preserving doubling
// algorithm for discrete-time algebraic Riccati equations", 2005): each step doubles the horizon
// of the Riccati recursion, so the slow modes of a 1 kHz discretisation (eigenvalues near 1) cost
// tens of steps where the plain recursion takes thousands.
#pragma once

#include <Eigen/Core>
#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <string>

#include "kinfly/core/status.h"

namespace kinfly::flight {

template <int N, int M>
struct RiccatiSolution {
  Eigen::Matrix<double, N, N> P;
  Eigen::Matrix<double, M, N> K;  // (R + B'PB)^-1 B'PA: u = -K x
  int doubling_steps = 0;
  double closed_loop_spectral_radius = 0.0;  // of A - B K: below 1 for the stabilising P
};

// Fails when the doubling does not settle within max_steps, P does not satisfy the equation to
// relative_tolerance, or the P found does not stabilise A - B K (the equation then has other,
// non-stabilising solutions: an unstabilisable pair, a Q that does not see an unstable mode).
template <int N, int M>
StatusOr<RiccatiSolution<N, M>> solveDiscreteRiccati(const Eigen::Matrix<double, N, N>& A,
                                                     const Eigen::Matrix<double, N, M>& B,
                                                     const Eigen::Matrix<double, N, N>& Q,
                                                     const Eigen::Matrix<double, M, M>& R,
                                                     double relative_tolerance = 1e-10,
                                                     int max_steps = 100) {
  using MatrixN = Eigen::Matrix<double, N, N>;
  const MatrixN identity = MatrixN::Identity();
  MatrixN a = A;
  MatrixN g = B * R.inverse() * B.transpose();
  MatrixN h = Q;
  RiccatiSolution<N, M> solution;
  for (int step = 1; step <= max_steps; ++step) {
    const Eigen::PartialPivLU<MatrixN> w(identity + g * h);
    const MatrixN w_inv_a = w.solve(a);
    const MatrixN h_next = h + a.transpose() * h * w_inv_a;
    g += a * w.solve(g) * a.transpose();
    a = a * w_inv_a;
    const double change = (h_next - h).norm();
    h = 0.5 * (h_next + h_next.transpose());  // P is symmetric; rounding is not
    if (!h.allFinite()) break;
    if (change <= relative_tolerance * h.norm()) {
      solution.P = h;
      solution.doubling_steps = step;
      const Eigen::Matrix<double, M, M> s = R + B.transpose() * h * B;
      solution.K = s.ldlt().solve(B.transpose() * h * A);
      const MatrixN residual =
          A.transpose() * h * A - A.transpose() * h * B * solution.K + Q - h;
      if (residual.norm() > 1e3 * relative_tolerance * h.norm()) break;
      solution.closed_loop_spectral_radius =
          Eigen::EigenSolver<MatrixN>(A - B * solution.K, false).eigenvalues().cwiseAbs().maxCoeff();
      if (!(solution.closed_loop_spectral_radius < 1.0)) break;
      return solution;
    }
  }
  return Status::error("the discrete Riccati equation has no stabilising solution within " +
                       std::to_string(max_steps) +
                       " doubling steps (is (A, B) stabilisable, Q >= 0, R > 0?)");
}

}  // namespace kinfly::flight
