#include "kinfly/flight/riccati.h"

#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <string>

namespace kinfly::flight {

StatusOr<RiccatiSolution> solveDiscreteRiccati(const Eigen::MatrixXd& A, const Eigen::MatrixXd& B,
                                               const Eigen::MatrixXd& Q, const Eigen::MatrixXd& R,
                                               double relative_tolerance, int max_steps) {
  const Eigen::Index n = A.rows();
  const Eigen::Index m = B.cols();
  if (A.cols() != n || B.rows() != n || Q.rows() != n || Q.cols() != n || R.rows() != m ||
      R.cols() != m)
    return Status::error("the Riccati matrices' sizes disagree: A " + std::to_string(A.rows()) +
                         "x" + std::to_string(A.cols()) + ", B " + std::to_string(B.rows()) +
                         "x" + std::to_string(B.cols()) + ", Q " + std::to_string(Q.rows()) +
                         "x" + std::to_string(Q.cols()) + ", R " + std::to_string(R.rows()) +
                         "x" + std::to_string(R.cols()));
  const Eigen::MatrixXd identity = Eigen::MatrixXd::Identity(n, n);
  Eigen::MatrixXd a = A;
  Eigen::MatrixXd g = B * R.inverse() * B.transpose();
  Eigen::MatrixXd h = Q;
  RiccatiSolution solution;
  for (int step = 1; step <= max_steps; ++step) {
    const Eigen::PartialPivLU<Eigen::MatrixXd> w(identity + g * h);
    const Eigen::MatrixXd w_inv_a = w.solve(a);
    const Eigen::MatrixXd h_next = h + a.transpose() * h * w_inv_a;
    g += a * w.solve(g) * a.transpose();
    a = a * w_inv_a;
    const double change = (h_next - h).norm();
    h = 0.5 * (h_next + h_next.transpose());  // P is symmetric; rounding is not
    if (!h.allFinite()) break;
    if (change <= relative_tolerance * h.norm()) {
      solution.P = h;
      solution.doubling_steps = step;
      const Eigen::MatrixXd s = R + B.transpose() * h * B;
      solution.K = s.ldlt().solve(B.transpose() * h * A);
      const Eigen::MatrixXd residual =
          A.transpose() * h * A - A.transpose() * h * B * solution.K + Q - h;
      if (residual.norm() > 1e3 * relative_tolerance * h.norm()) break;
      solution.closed_loop_spectral_radius =
          Eigen::EigenSolver<Eigen::MatrixXd>(A - B * solution.K, false)
              .eigenvalues()
              .cwiseAbs()
              .maxCoeff();
      if (!(solution.closed_loop_spectral_radius < 1.0)) break;
      return solution;
    }
  }
  return Status::error("the discrete Riccati equation has no stabilising solution within " +
                       std::to_string(max_steps) +
                       " doubling steps (is (A, B) stabilisable, Q >= 0, R > 0?)");
}

}  // namespace kinfly::flight
