// lanes: the mask tests that the four-lane kernels branch on.
#include <gtest/gtest.h>

#include "kinfly/core/lanes.h"

namespace kinfly {
namespace {

TEST(Lanes, NoneIsTrueOnlyWhenNoLaneIsSet) {
  EXPECT_TRUE(lanes::none(lanes::Ints{0, 0, 0, 0}));
  for (int l = 0; l < lanes::kWidth; ++l) {
    lanes::Ints mask = {0, 0, 0, 0};
    mask[l] = -1;
    EXPECT_FALSE(lanes::none(mask)) << "lane " << l;
  }
  EXPECT_FALSE(lanes::none(lanes::Ints{-1, -1, -1, -1}));
}

}  // namespace
}  // namespace kinfly
