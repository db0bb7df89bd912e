// Four-lane helpers for the per-pixel and per-voxel kernels of preprocessing, tracking,
// integration and the raycaster's trilinear samples.
#pragma once

#include <cmath>
#include <cstring>

namespace kinfly {

// Four pixels or points at a time, one per lane of an SSE or NEON register, through the GCC/Clang
// vector extensions. The per-pixel kernels of preprocessing and tracking are written once, as
// templates over float (one pixel) and Floats (four along a row), so that vector loops and scalar
// border loops share them. The compiler's own vectoriser cannot do this: the kernels are full of
// selects, and under IEEE trapping semantics it may not compute a side that scalar code skips.
namespace lanes {
typedef float Floats __attribute__((vector_size(16)));
typedef int Ints __attribute__((vector_size(16)));  // lane masks: -1 true, 0 false
constexpr int kWidth = 4;

inline Floats splat(float s) { return Floats{s, s, s, s}; }
// Lanes picked from a (indices 0-3) and b (4-7).
template <int I0, int I1, int I2, int I3>
inline Floats shuffle(Floats a, Floats b) {
#if defined(__clang__)
  return __builtin_shufflevector(a, b, I0, I1, I2, I3);
#else
  return __builtin_shuffle(a, b, Ints{I0, I1, I2, I3});
#endif
}
// One bit per lane of a mask, lane 0 in bit 0.
inline int bits(Ints mask) { return (mask[0] & 1) | (mask[1] & 2) | (mask[2] & 4) | (mask[3] & 8); }
// No lane true: one instruction on SSE (the lanes' sign bits).
inline bool none(Ints mask) {
#if defined(__SSE__)
  return __builtin_ia32_movmskps(reinterpret_cast<Floats>(mask)) == 0;
#else
  return (mask[0] | mask[1] | mask[2] | mask[3]) == 0;
#endif
}

// One value, or four consecutive ones.
template <typename T>
T load(const float* p);
template <>
inline float load<float>(const float* p) {
  return *p;
}
template <>
inline Floats load<Floats>(const float* p) {
  Floats v;
  std::memcpy(&v, p, sizeof v);
  return v;
}
// p[0], or p[0], p[2], p[4], p[6].
template <typename T>
T loadEveryOther(const float* p);
template <>
inline float loadEveryOther<float>(const float* p) {
  return *p;
}
template <>
inline Floats loadEveryOther<Floats>(const float* p) {
  return shuffle<0, 2, 4, 6>(load<Floats>(p), load<Floats>(p + kWidth));
}
inline void store(float* p, float v) { *p = v; }
inline void store(float* p, Floats v) { std::memcpy(p, &v, sizeof v); }
inline void store(int* p, Ints v) { std::memcpy(p, &v, sizeof v); }
// Pixel coordinate x, or x .. x + 3.
template <typename T>
T coordinate(int x);
template <>
inline float coordinate<float>(int x) {
  return static_cast<float>(x);
}
template <>
inline Floats coordinate<Floats>(int x) {
  const float f = static_cast<float>(x);
  return Floats{f, f + 1.f, f + 2.f, f + 3.f};
}

// a < b ? a : b, NaN giving b: one instruction on SSE, whose minimum is defined this way.
inline float min(float a, float b) { return a < b ? a : b; }
inline Floats min(Floats a, Floats b) {
#if defined(__SSE__)
  return __builtin_ia32_minps(a, b);
#else
  return a < b ? a : b;
#endif
}
inline float abs(float x) { return std::fabs(x); }
inline Floats abs(Floats x) {
  return reinterpret_cast<Floats>(reinterpret_cast<Ints>(x) & 0x7fffffff);
}
inline float sqrt(float x) { return std::sqrt(x); }
inline Floats sqrt(Floats x) {
  for (int l = 0; l < kWidth; ++l) x[l] = std::sqrt(x[l]);  // vectorised by the compiler
  return x;
}
inline int truncate(float x) { return static_cast<int>(x); }
inline Ints truncate(Floats x) { return __builtin_convertvector(x, Ints); }
inline float toFloat(int x) { return static_cast<float>(x); }
inline Floats toFloat(Ints x) { return __builtin_convertvector(x, Floats); }
// floorToInt (core/numeric.h) in each lane.
inline Ints floorToInt(Floats x) {
  const Ints i = truncate(x);
  return i + (toFloat(i) > x);  // true lanes are -1
}
inline float lookup(const float* table, int i) { return table[i]; }
// table[i[0]] .. table[i[3]], with the indices in memory: SSE2 has no gather, and moving each
// index out of a register takes more instructions than storing all four and loading each.
inline Floats lookup(const float* table, const int* i) {
  return Floats{table[i[0]], table[i[1]], table[i[2]], table[i[3]]};
}
// A scalar function applied lane by lane; for short functions the compiler vectorises it.
template <typename F>
Floats lanewise(F f, Floats x) {
  for (int l = 0; l < kWidth; ++l) x[l] = f(x[l]);
  return x;
}
}  // namespace lanes

}  // namespace kinfly
