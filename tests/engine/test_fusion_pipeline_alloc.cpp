// "Nothing allocates per frame": counts every global operator new while the pipeline runs
// frames over a surface that is already allocated. This executable replaces the global
// allocation functions, which is why it is separate from test_fusion_pipeline.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdlib>
#include <new>
#include <vector>

#include "kinfly/pipeline/fusion_pipeline.h"
#include "kinfly/volume/tsdf_volume.h"
#include "test_util.h"

namespace {

std::atomic<bool> g_counting{false};
std::atomic<long> g_allocations{0};

void* countedAlloc(std::size_t size, std::size_t alignment) {
  if (g_counting.load(std::memory_order_relaxed)) {
    g_allocations.fetch_add(1, std::memory_order_relaxed);
  }
  if (size == 0) size = 1;
  if (alignment <= alignof(std::max_align_t)) return std::malloc(size);
  // aligned_alloc wants a size that is a multiple of the alignment.
  return std::aligned_alloc(alignment, (size + alignment - 1) / alignment * alignment);
}

void* countedAllocOrThrow(std::size_t size, std::size_t alignment) {
  void* p = countedAlloc(size, alignment);
  if (p == nullptr) throw std::bad_alloc();
  return p;
}

}  // namespace

void* operator new(std::size_t n) { return countedAllocOrThrow(n, 0); }
void* operator new[](std::size_t n) { return countedAllocOrThrow(n, 0); }
void* operator new(std::size_t n, const std::nothrow_t&) noexcept { return countedAlloc(n, 0); }
void* operator new[](std::size_t n, const std::nothrow_t&) noexcept { return countedAlloc(n, 0); }
void* operator new(std::size_t n, std::align_val_t a) {
  return countedAllocOrThrow(n, static_cast<std::size_t>(a));
}
void* operator new[](std::size_t n, std::align_val_t a) {
  return countedAllocOrThrow(n, static_cast<std::size_t>(a));
}
void* operator new(std::size_t n, std::align_val_t a, const std::nothrow_t&) noexcept {
  return countedAlloc(n, static_cast<std::size_t>(a));
}
void* operator new[](std::size_t n, std::align_val_t a, const std::nothrow_t&) noexcept {
  return countedAlloc(n, static_cast<std::size_t>(a));
}
void operator delete(void* p) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t) noexcept { std::free(p); }
void operator delete(void* p, const std::nothrow_t&) noexcept { std::free(p); }
void operator delete[](void* p, const std::nothrow_t&) noexcept { std::free(p); }
void operator delete(void* p, std::align_val_t) noexcept { std::free(p); }
void operator delete[](void* p, std::align_val_t) noexcept { std::free(p); }
void operator delete(void* p, std::size_t, std::align_val_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t, std::align_val_t) noexcept { std::free(p); }
void operator delete(void* p, std::align_val_t, const std::nothrow_t&) noexcept { std::free(p); }
void operator delete[](void* p, std::align_val_t, const std::nothrow_t&) noexcept {
  std::free(p);
}

namespace kinfly {
namespace {

TEST(AllocationCounter, SeesAllocations) {
  // The counter itself must work, or the zero below would prove nothing.
  g_allocations = 0;
  g_counting = true;
  // Through a volatile pointer, so the compiler cannot elide the new/delete pair.
  std::vector<int>* volatile v = new std::vector<int>(100);
  g_counting = false;
  delete v;
  EXPECT_GE(g_allocations.load(), 2);
}

// `gaps`: every other measured frame (the second, fourth, ...) comes after two that never came (the recovery path, its
// widened gates and its messages, must not allocate either). `dense`: into the drone's dense
// volume, which follows the camera (the frame's median depth each frame), not a hashed one.
// `model_level`: the model raycast at that level's resolution (the drone's 1).
void expectNoAllocationPerFrame(bool gaps, bool dense = false, int model_level = 0) {
  constexpr int kWarmUpFrames = 6;  // also enough intervals for the pipeline to know the rate
  constexpr int kMeasuredFrames = 10;
  constexpr int64_t kFrameUs = 33'333;
  const auto utime = [&](int k) {
    const int measured = std::max(k - kWarmUpFrames, 0);
    return kFrameUs * (k + (gaps ? 2 * ((measured + 1) / 2) : 0));
  };
  constexpr int kPoses = 3;
  const PinholeCamera camera = test::tumCamera();
  const SyntheticScene scene = SyntheticScene::cornerRoom();
  // The camera cycles through three poses a centimetre and half a degree apart, each always
  // seen through the same (noise-free) image: after one cycle every block the frames touch
  // exists, so steady state means no growth of the map either.
  std::vector<Image<uint16_t>> raw;
  std::vector<Image<float>> depth;
  for (int i = 0; i < kPoses; ++i) {
    const Pose T = test::makePose(Eigen::Vector3d(0.0, test::degToRad(0.5 * i), 0.0),
                                  Eigen::Vector3d(0.01 * i, 0.0, 0.0));
    depth.emplace_back(camera.width, camera.height);
    scene.renderDepth(camera, T, test::kRenderMaxDepthM, depth.back());
    raw.emplace_back(camera.width, camera.height);
    for (int p = 0; p < raw.back().numPixels(); ++p) {
      raw.back().data()[p] =
          static_cast<uint16_t>(std::lround(depth.back().data()[p] / test::kTumDepthScale));
    }
  }
  HashedVolume hashed(HashedVolume::Params{});
  DenseVolume::Params cube;
  cube.voxel_size_m = 0.02f;  // a 2.56 m cube
  cube.lookahead_m = 1.5f;
  DenseVolume dense_volume(cube);
  TsdfVolume* volume = dense ? static_cast<TsdfVolume*>(&dense_volume) : &hashed;
  FusionPipeline::Params params;
  if (dense) params.integrate.truncation_m = 4.f * cube.voxel_size_m;
  params.model_level = model_level;
  FusionPipeline pipeline(camera, params, volume);
  for (int k = 0; k < kWarmUpFrames; ++k) {
    const FrameResult r = pipeline.processFrame(raw[k % kPoses], utime(k));
    ASSERT_NE(r.status, TrackingStatus::kLost) << r.lost_reason;
  }

  std::vector<TrackingStatus> statuses(kMeasuredFrames);  // reserved before counting
  std::vector<int> missed(kMeasuredFrames);
  g_allocations = 0;
  g_counting = true;
  for (int k = 0; k < kMeasuredFrames; ++k) {
    const int frame = kWarmUpFrames + k;
    const FrameResult r = pipeline.processFrame(raw[frame % kPoses], utime(frame));
    statuses[k] = r.status;
    missed[k] = r.missed;
  }
  g_counting = false;
  EXPECT_EQ(g_allocations.load(), 0) << "heap allocations in " << kMeasuredFrames << " frames";
  for (int k = 0; k < kMeasuredFrames; ++k) {
    EXPECT_EQ(statuses[k], TrackingStatus::kOk) << k;
    EXPECT_EQ(missed[k], gaps && k % 2 == 1 ? 2 : 0) << k;
  }
}

TEST(FusionPipelineAllocation, NoHeapAllocationPerFrameAfterWarmUp) {
  expectNoAllocationPerFrame(/*gaps=*/false);
}

TEST(FusionPipelineAllocation, NoHeapAllocationPerFrameAfterGaps) {
  expectNoAllocationPerFrame(/*gaps=*/true);
}

TEST(FusionPipelineAllocation, NoHeapAllocationPerFrameInADenseVolume) {
  expectNoAllocationPerFrame(/*gaps=*/false, /*dense=*/true);
}

TEST(FusionPipelineAllocation, NoHeapAllocationPerFrameWithTheModelAtHalfResolution) {
  expectNoAllocationPerFrame(/*gaps=*/false, /*dense=*/true, /*model_level=*/1);
}

}  // namespace
}  // namespace kinfly
