// SE3 helpers (core/se3.h): exact rotations from the ICP twist, inverse and composition in the
// T_a_b convention, TUM (x, y, z, w) quaternion order and normalisation, projection back onto
// SO(3), and the rotation angle, all against closed-form answers.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <random>

#include "kinfly/core/se3.h"
#include "test_util.h"

namespace kinfly {
namespace {

// Double-precision products and inverses of a few well-conditioned matrices round at ~1e-16
// per operation; 1e-12 allows a few hundred of them and nothing a wrong sign or order would give.
constexpr double kExactTol = 1e-12;
// A seed shared by the random-pose tests, so a failure reproduces.
constexpr uint32_t kSeed = 1311;

Pose randomPose(std::mt19937* rng) {
  std::uniform_real_distribution<double> angle(0.0, test::kPi * 0.95);
  std::uniform_real_distribution<double> metres(0.1, 3.0);
  return test::randomOffset(rng, metres(*rng), angle(*rng));
}

TEST(Se3, ExpTwistOfZeroIsIdentity) {
  const Pose T = expTwist(Eigen::Matrix<double, 6, 1>::Zero());
  EXPECT_TRUE(T.matrix().isApprox(Eigen::Matrix4d::Identity(), kExactTol));
}

TEST(Se3, ExpTwistIsTheExactRotationAndTheGivenTranslation) {
  std::mt19937 rng(kSeed);
  std::normal_distribution<double> n01(0.0, 1.0);
  for (int trial = 0; trial < 20; ++trial) {
    const Eigen::Vector3d axis = Eigen::Vector3d(n01(rng), n01(rng), n01(rng)).normalized();
    const double angle = 0.05 * (trial + 1);  // up to 1 rad: well past small angles
    const Eigen::Vector3d t(n01(rng), n01(rng), n01(rng));
    Eigen::Matrix<double, 6, 1> xi;
    xi << axis * angle, t;
    const Pose T = expTwist(xi);
    EXPECT_TRUE(T.linear().isApprox(Eigen::AngleAxisd(angle, axis).matrix(), kExactTol));
    EXPECT_TRUE(T.translation().isApprox(t, kExactTol));
    EXPECT_LT(test::orthonormalityError(T), kExactTol);
    EXPECT_NEAR(rotationAngleRad(T), angle, kExactTol);
    // The rotation axis is fixed by the rotation.
    EXPECT_TRUE((T.linear() * axis).isApprox(axis, kExactTol));
  }
}

TEST(Se3, InverseUndoesAndComposesInTheNamedOrder) {
  std::mt19937 rng(kSeed);
  std::normal_distribution<double> n01(0.0, 1.0);
  for (int trial = 0; trial < 20; ++trial) {
    const Pose T_a_b = randomPose(&rng), T_b_c = randomPose(&rng);
    const Eigen::Vector3d p_c(n01(rng), n01(rng), n01(rng));
    EXPECT_TRUE((T_a_b * T_a_b.inverse()).matrix().isApprox(Eigen::Matrix4d::Identity(),
                                                            kExactTol));
    // p_a = T_a_b * p_b = T_a_b * (T_b_c * p_c) = (T_a_b * T_b_c) * p_c.
    const Pose T_a_c = T_a_b * T_b_c;
    EXPECT_TRUE((T_a_c * p_c).isApprox(T_a_b * (T_b_c * p_c), kExactTol));
    // (T_a_b T_b_c)^-1 = T_b_c^-1 T_a_b^-1, and the inverse maps back.
    EXPECT_TRUE(T_a_c.inverse().matrix().isApprox((T_b_c.inverse() * T_a_b.inverse()).matrix(),
                                                  kExactTol));
    EXPECT_TRUE((T_a_c.inverse() * (T_a_c * p_c)).isApprox(p_c, kExactTol));
    // The inverse turns by the same angle.
    EXPECT_NEAR(rotationAngleRad(T_a_b.inverse()), rotationAngleRad(T_a_b), kExactTol);
  }
}

TEST(Se3, TumOrderIsXyzThenW) {
  // 90 degrees about z: q = (0, 0, sin 45, cos 45) in TUM's (x, y, z, w) order maps x to y.
  const double s = std::sqrt(0.5);
  const Pose T = poseFromTum({1.0, 2.0, 3.0, 0.0, 0.0, s, s});
  EXPECT_TRUE(T.translation().isApprox(Eigen::Vector3d(1.0, 2.0, 3.0), kExactTol));
  EXPECT_TRUE((T.linear() * Eigen::Vector3d::UnitX()).isApprox(Eigen::Vector3d::UnitY(),
                                                               kExactTol));
  EXPECT_NEAR(rotationAngleRad(T), test::kPi / 2, kExactTol);
}

TEST(Se3, TumRoundTripAndNormalisation) {
  std::mt19937 rng(kSeed);
  for (int trial = 0; trial < 20; ++trial) {
    const Pose T = randomPose(&rng);
    const std::array<double, 7> tum = poseToTum(T);
    const Eigen::Vector4d q(tum[3], tum[4], tum[5], tum[6]);
    EXPECT_NEAR(q.norm(), 1.0, kExactTol) << "a written quaternion is unit";
    EXPECT_TRUE(poseFromTum(tum).matrix().isApprox(T.matrix(), kExactTol));
    // A reader normalises: files written with few digits, or scaled, give the same rotation.
    std::array<double, 7> scaled = tum;
    for (int i = 3; i < 7; ++i) scaled[i] *= 2.5;
    const Pose T_scaled = poseFromTum(scaled);
    EXPECT_TRUE(T_scaled.matrix().isApprox(T.matrix(), kExactTol));
    EXPECT_LT(test::orthonormalityError(T_scaled), kExactTol);
    // q and -q are the same rotation.
    std::array<double, 7> negated = tum;
    for (int i = 3; i < 7; ++i) negated[i] = -negated[i];
    EXPECT_TRUE(poseFromTum(negated).matrix().isApprox(T.matrix(), kExactTol));
  }
}

TEST(Se3, OrthonormalizedProjectsBackOntoRotations) {
  std::mt19937 rng(kSeed);
  std::normal_distribution<double> n01(0.0, 1.0);
  // Drift of the size a few thousand chained float-rounded products would leave.
  constexpr double kDrift = 1e-6;
  for (int trial = 0; trial < 20; ++trial) {
    const Pose T = randomPose(&rng);
    Pose drifted = T;
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) drifted.linear()(i, j) += kDrift * n01(rng);
    ASSERT_GT(test::orthonormalityError(drifted), 100 * kExactTol);
    const Pose fixed = orthonormalized(drifted);
    EXPECT_LT(test::orthonormalityError(fixed), kExactTol);
    EXPECT_NEAR(fixed.linear().determinant(), 1.0, kExactTol);
    // The nearest rotation moves by about the drift, no more (10x: a Frobenius norm of nine
    // entries against each entry's size).
    EXPECT_LT((fixed.linear() - T.linear()).norm(), 10 * kDrift);
    EXPECT_TRUE(fixed.translation().isApprox(drifted.translation(), kExactTol));
  }
}

TEST(Se3, RotationAngleIsExactAtSmallAndLargeAngles) {
  const Eigen::Vector3d axis = Eigen::Vector3d(1.0, -2.0, 0.5).normalized();
  for (double angle : {0.0, 1e-9, 1e-6, 0.01, 0.5, 2.0, test::kPi - 1e-6, test::kPi}) {
    Pose T = Pose::Identity();
    T.linear() = Eigen::AngleAxisd(angle, axis).matrix();
    // The atan2 form keeps relative precision at small angles, where acos of the trace would
    // return 0 below ~1e-8 rad; near pi both sine and cosine parts are still well defined.
    EXPECT_NEAR(rotationAngleRad(T), angle, std::max(1e-15, 1e-9 * angle)) << angle;
  }
  // Angles beyond pi come back as their complement: the result lies in [0, pi].
  Pose T = Pose::Identity();
  T.linear() = Eigen::AngleAxisd(1.5 * test::kPi, axis).matrix();
  EXPECT_NEAR(rotationAngleRad(T), 0.5 * test::kPi, kExactTol);
}

TEST(Se3, IsFiniteCatchesNaNAndInfinity) {
  Pose T = Pose::Identity();
  EXPECT_TRUE(isFinite(T));
  T.translation().x() = std::numeric_limits<double>::quiet_NaN();
  EXPECT_FALSE(isFinite(T));
  T = Pose::Identity();
  T.linear()(1, 2) = std::numeric_limits<double>::infinity();
  EXPECT_FALSE(isFinite(T));
}

}  // namespace
}  // namespace kinfly
