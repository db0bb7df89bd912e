// PNG files at the edges of the engine: depth images in (TUM, 16-bit grey) and renders out
// (8-bit grey). libpng, not OpenCV: Debian's OpenCV image codecs drag GDAL, GDCM and poppler into
// every process that reads a PNG, which costs the drone about 40 MB of resident memory and its
// image hundreds of MB (docs/engine.md, "Dependencies"). Errors come back as a Status naming the
// file.
#pragma once

#include <cstdint>
#include <string>

#include "kinfly/core/image.h"
#include "kinfly/core/status.h"

namespace kinfly {

// Loads a 16-bit single-channel PNG into `out` (reallocated only when the size changes).
Status loadDepthPng(const std::string& path, Image<uint16_t>* out);

// Writes an 8-bit greyscale PNG.
Status writeGrayPng(const std::string& path, ImageView<const uint8_t> image);

}  // namespace kinfly
