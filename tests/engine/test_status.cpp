// The error convention (core/status.h): a Status is ok until made an error, keeps its message,
// and a StatusOr holds either a value (converted where the value type allows, as a source opener
// returns a derived source) or the error that says why there is none.
#include <gtest/gtest.h>

#include <memory>
#include <string>
#include <utility>

#include "kinfly/core/status.h"

namespace kinfly {
namespace {

struct Base {
  virtual ~Base() = default;
  virtual int id() const { return 0; }
};
struct Derived : Base {
  int id() const override { return 7; }
};

StatusOr<std::unique_ptr<Base>> make(bool succeed) {
  if (!succeed) return Status::error("no device");
  return std::make_unique<Derived>();
}

Status firstStep(int x) {
  if (x < 0) return Status::error("x must be >= 0 (got " + std::to_string(x) + ")");
  return Status();
}

StatusOr<int> twice(int x) {
  if (Status valid = firstStep(x); !valid.ok()) return valid;
  return 2 * x;
}

TEST(Status, OkByDefaultAndAnErrorKeepsItsMessage) {
  const Status ok;
  EXPECT_TRUE(ok.ok());
  EXPECT_TRUE(ok.message().empty());
  const Status error = Status::error("odometry.voxel_m must be in (0, 0.2] (got 0.5)");
  EXPECT_FALSE(error.ok());
  EXPECT_EQ(error.message(), "odometry.voxel_m must be in (0, 0.2] (got 0.5)");
}

TEST(StatusOr, HoldsAValueConvertedToItsType) {
  StatusOr<std::unique_ptr<Base>> made = make(true);
  ASSERT_TRUE(made.ok());
  EXPECT_TRUE(made.status().ok());
  EXPECT_EQ((*made)->id(), 7);
  std::unique_ptr<Base> taken = std::move(made).value();
  EXPECT_EQ(taken->id(), 7);
}

TEST(StatusOr, HoldsTheErrorWhenThereIsNoValue) {
  const StatusOr<std::unique_ptr<Base>> made = make(false);
  EXPECT_FALSE(made.ok());
  EXPECT_EQ(made.status().message(), "no device");
}

TEST(StatusOr, PassesAnErrorOnUnchanged) {
  const StatusOr<int> good = twice(4);
  ASSERT_TRUE(good.ok());
  EXPECT_EQ(*good, 8);
  const StatusOr<int> bad = twice(-3);
  ASSERT_FALSE(bad.ok());
  EXPECT_EQ(bad.status().message(), "x must be >= 0 (got -3)");
}

}  // namespace
}  // namespace kinfly
