// Owning images and cheap non-owning views (after nvblox Image/ImageView).
// Kernels take views; owners are allocated once at construction and never per frame.
#pragma once

#include <cassert>
#include <cstddef>
#include <vector>

namespace kinfly {

template <typename T>
class ImageView {
 public:
  ImageView() = default;
  ImageView(T* data, int width, int height) : data_(data), width_(width), height_(height) {}

  int width() const { return width_; }
  int height() const { return height_; }
  int numPixels() const { return width_ * height_; }
  bool empty() const { return numPixels() == 0; }
  T* data() const { return data_; }
  T* row(int y) const { return data_ + static_cast<std::ptrdiff_t>(y) * width_; }
  T& operator()(int x, int y) const {
    assert(x >= 0 && x < width_ && y >= 0 && y < height_);
    return data_[static_cast<std::ptrdiff_t>(y) * width_ + x];
  }
  bool inside(int x, int y) const { return x >= 0 && y >= 0 && x < width_ && y < height_; }
  // A view of const elements converts implicitly, so read-only kernels accept either.
  operator ImageView<const T>() const { return {data_, width_, height_}; }

 private:
  T* data_ = nullptr;
  int width_ = 0;
  int height_ = 0;
};

template <typename T>
class Image {
 public:
  Image() = default;
  // Value-initialised pixels: zero for arithmetic types; Eigen vectors are left unset, so give
  // them an explicit fill where the contents are read before being written.
  Image(int width, int height) : width_(width), height_(height), data_(static_cast<size_t>(width) * height) {}
  Image(int width, int height, const T& fill)
      : width_(width), height_(height), data_(static_cast<size_t>(width) * height, fill) {}
  // Copies are explicit (copyFrom) so a per-frame deep copy never hides in an assignment.
  Image(const Image&) = delete;
  Image& operator=(const Image&) = delete;
  Image(Image&&) noexcept = default;
  Image& operator=(Image&&) noexcept = default;

  // Copies pixel data; both images must already have the same size (no reallocation).
  void copyFrom(ImageView<const T> src) {
    assert(src.width() == width_ && src.height() == height_);
    std::copy(src.data(), src.data() + src.numPixels(), data_.begin());
  }
  void fill(const T& value) { std::fill(data_.begin(), data_.end(), value); }

  int width() const { return width_; }
  int height() const { return height_; }
  int numPixels() const { return width_ * height_; }
  T* data() { return data_.data(); }
  const T* data() const { return data_.data(); }
  T& operator()(int x, int y) { return view()(x, y); }
  const T& operator()(int x, int y) const { return view()(x, y); }

  ImageView<T> view() { return {data_.data(), width_, height_}; }
  ImageView<const T> view() const { return {data_.data(), width_, height_}; }
  operator ImageView<T>() { return view(); }
  operator ImageView<const T>() const { return view(); }

 private:
  int width_ = 0;
  int height_ = 0;
  std::vector<T> data_;
};

}  // namespace kinfly
