// Launch set-ups shared by the kernel files: one thread per element (kThreads per block) or one
// block of kTile x kTile threads per work unit, nothing launched for an empty range, and the
// launch's error returned; and the dispatch of a runtime channel count (or mode) to a kernel
// template's compile-time one.
#pragma once

#include <cuda_runtime.h>

#include <cstdint>
#include <type_traits>

#include "kernels.h"

namespace virgi {

constexpr int kThreads = 256;  // threads per block of the one-thread-per-element kernels

inline unsigned blocks_for(int64_t n) {
  return static_cast<unsigned>((n + kThreads - 1) / kThreads);
}

// kernel<<<ceil(n / kThreads), kThreads, 0, stream>>>(args...), or nothing when n == 0.
template <typename... Params, typename... Args>
cudaError_t launch_elements(void (*kernel)(Params...), int64_t n, cudaStream_t stream,
                            Args... args) {
  if (n == 0) return cudaSuccess;
  kernel<<<blocks_for(n), kThreads, 0, stream>>>(args...);
  return cudaGetLastError();
}

// kernel<<<num_units, kTile * kTile, 0, stream>>>(args...): one block per work unit, one thread
// per pixel of its 16-px grid tile; nothing when num_units == 0.
template <typename... Params, typename... Args>
cudaError_t launch_units(void (*kernel)(Params...), int num_units, cudaStream_t stream,
                         Args... args) {
  if (num_units == 0) return cudaSuccess;
  kernel<<<num_units, kTile * kTile, 0, stream>>>(args...);
  return cudaGetLastError();
}

// launch(std::integral_constant<int, V>{}) for the V of Vs equal to value; cudaErrorInvalidValue
// when none is.
template <int... Vs, typename Launch>
cudaError_t dispatch(int value, Launch&& launch) {
  cudaError_t err = cudaErrorInvalidValue;
  (void)((value == Vs && ((err = launch(std::integral_constant<int, Vs>{})), true)) || ...);
  return err;
}

}  // namespace virgi
