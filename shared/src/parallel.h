// The engine's loops over rows, bands, chunks and blocks: OpenMP when more than one thread is
// asked for (omp_set_num_threads / OMP_NUM_THREADS), plain loops otherwise. With one thread no
// parallel region is entered at all: GNU OpenMP allocates and frees a team for every region a
// single thread enters, and the drone's one-thread odometry must not allocate per frame.
// Private to shared/src: the public headers stay free of OpenMP.
#pragma once

#include <omp.h>

namespace kinfly {

// False for one thread, or when the caller judges the work too small to share (`worth_it`).
inline bool useThreads(bool worth_it = true) { return worth_it && omp_get_max_threads() > 1; }

// body(i) for i in [0, n), split into equal contiguous parts (schedule(static)).
template <class Body>
void forEachStatic(int n, Body&& body) {
  if (!useThreads()) {
    for (int i = 0; i < n; ++i) body(i);
    return;
  }
#pragma omp parallel for schedule(static)
  for (int i = 0; i < n; ++i) body(i);
}

// body(i) for i in [0, n), handed out `chunk` at a time (schedule(dynamic)): for uneven work.
template <class Body>
void forEachDynamic(int n, int chunk, bool worth_it, Body&& body) {
  if (!useThreads(worth_it)) {
    for (int i = 0; i < n; ++i) body(i);
    return;
  }
#pragma omp parallel for schedule(dynamic, chunk)
  for (int i = 0; i < n; ++i) body(i);
}

// The sum of body(i) over [0, n), as forEachStatic / forEachDynamic split it.
template <class Body>
int sumStatic(int n, Body&& body) {
  int sum = 0;
  if (!useThreads()) {
    for (int i = 0; i < n; ++i) sum += body(i);
    return sum;
  }
#pragma omp parallel for schedule(static) reduction(+ : sum)
  for (int i = 0; i < n; ++i) sum += body(i);
  return sum;
}

template <class Body>
int sumDynamic(int n, int chunk, Body&& body) {
  int sum = 0;
  if (!useThreads()) {
    for (int i = 0; i < n; ++i) sum += body(i);
    return sum;
  }
#pragma omp parallel for schedule(dynamic, chunk) reduction(+ : sum)
  for (int i = 0; i < n; ++i) sum += body(i);
  return sum;
}

}  // namespace kinfly
