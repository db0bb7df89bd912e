#include "kinfly/io/png_io.h"

#include <png.h>

#include <cerrno>
#include <csetjmp>
#include <cstdio>
#include <cstring>
#include <memory>

namespace kinfly {

namespace {

// Larger images are refused before allocating: no depth sensor comes near, and width * height
// must fit the int pixel counts of Image.
constexpr png_uint_32 kMaxSidePx = 16384;

// libpng reports errors by calling onError, which must not return: it jumps back to the setjmp
// in the function that drives libpng, with the message kept here.
struct PngErrors {
  char message[200] = "libpng error";
  std::jmp_buf jump;
};

[[noreturn]] void onError(png_structp png, png_const_charp message) {
  auto* errors = static_cast<PngErrors*>(png_get_error_ptr(png));
  std::snprintf(errors->message, sizeof errors->message, "%s", message);
  std::longjmp(errors->jump, 1);
}
// Warnings are about ancillary chunks (colour profiles, text) that depth never depends on.
void onWarning(png_structp, png_const_charp) {}

struct FileCloser {
  void operator()(std::FILE* f) const { std::fclose(f); }
};
using File = std::unique_ptr<std::FILE, FileCloser>;

std::string openProblem(const std::string& path, const char* mode) {
  return path + ": cannot open for " + (mode[0] == 'r' ? "reading" : "writing") + " (" +
         std::strerror(errno) + ")";
}

// The libpng calls of a read, between setjmp and any longjmp: only plain locals live here, so the
// jump leaves nothing to destroy. *out is resized before the first row is read.
std::string readDepthRows(png_structp png, png_infop info, std::FILE* file, PngErrors* errors,
                          Image<uint16_t>* out) {
  if (setjmp(errors->jump)) return errors->message;
  png_init_io(png, file);
  png_set_sig_bytes(png, 8);
  png_read_info(png, info);
  const png_uint_32 width = png_get_image_width(png, info);
  const png_uint_32 height = png_get_image_height(png, info);
  const int bit_depth = png_get_bit_depth(png, info);
  const int channels = png_get_channels(png, info);
  if (bit_depth != 16 || channels != 1 || png_get_color_type(png, info) != PNG_COLOR_TYPE_GRAY) {
    char why[120];
    std::snprintf(why, sizeof why,
                  "depth must be a 16-bit single-channel PNG (got %d-bit, %d channel(s))",
                  bit_depth, channels);
    return why;
  }
  if (width > kMaxSidePx || height > kMaxSidePx) return "image larger than 16384 pixels a side";
  // PNG stores 16-bit samples big-endian.
  const uint16_t probe = 1;
  if (*reinterpret_cast<const uint8_t*>(&probe) == 1) png_set_swap(png);
  const int passes = png_set_interlace_handling(png);
  png_read_update_info(png, info);
  if (out->width() != static_cast<int>(width) || out->height() != static_cast<int>(height))
    *out = Image<uint16_t>(static_cast<int>(width), static_cast<int>(height));
  const ImageView<uint16_t> view = out->view();
  for (int pass = 0; pass < passes; ++pass)
    for (int y = 0; y < view.height(); ++y)
      png_read_row(png, reinterpret_cast<png_bytep>(view.row(y)), nullptr);
  png_read_end(png, nullptr);
  return {};
}

std::string writeGrayRows(png_structp png, png_infop info, std::FILE* file, PngErrors* errors,
                          ImageView<const uint8_t> image) {
  if (setjmp(errors->jump)) return errors->message;
  png_init_io(png, file);
  png_set_IHDR(png, info, static_cast<png_uint_32>(image.width()),
               static_cast<png_uint_32>(image.height()), 8, PNG_COLOR_TYPE_GRAY,
               PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
  png_write_info(png, info);
  for (int y = 0; y < image.height(); ++y)
    png_write_row(png, reinterpret_cast<png_const_bytep>(image.row(y)));
  png_write_end(png, nullptr);
  return {};
}

}  // namespace

Status loadDepthPng(const std::string& path, Image<uint16_t>* out) {
  const File file(std::fopen(path.c_str(), "rb"));
  if (!file) return Status::error(openProblem(path, "r"));
  png_byte signature[8];
  if (std::fread(signature, 1, sizeof signature, file.get()) != sizeof signature ||
      png_sig_cmp(signature, 0, sizeof signature) != 0)
    return Status::error(path + ": not a PNG file");
  PngErrors errors;
  png_structp png = png_create_read_struct(PNG_LIBPNG_VER_STRING, &errors, onError, onWarning);
  png_infop info = png ? png_create_info_struct(png) : nullptr;
  std::string why = info ? readDepthRows(png, info, file.get(), &errors, out)
                         : std::string("libpng could not start (out of memory)");
  png_destroy_read_struct(&png, &info, nullptr);
  return why.empty() ? Status() : Status::error(path + ": " + why);
}

Status writeGrayPng(const std::string& path, ImageView<const uint8_t> image) {
  File file(std::fopen(path.c_str(), "wb"));
  if (!file) return Status::error(openProblem(path, "w"));
  PngErrors errors;
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, &errors, onError, onWarning);
  png_infop info = png ? png_create_info_struct(png) : nullptr;
  std::string why = info ? writeGrayRows(png, info, file.get(), &errors, image)
                         : std::string("libpng could not start (out of memory)");
  png_destroy_write_struct(&png, &info);
  if (std::fclose(file.release()) != 0 && why.empty()) why = std::strerror(errno);
  return why.empty() ? Status() : Status::error(path + ": " + why);
}

}  // namespace kinfly
