// Vector atomics shared by the kernel files.
#pragma once

#include <cuda_runtime.h>

namespace virgi {

// row[0, D) += v for a 16-byte aligned row of 4 floats (D = 3 or 4): one vector reduction on
// sm_90 (one atomic operation in L2 instead of D), D scalar atomics on older GPUs. Either way
// each component is added as a scalar atomicAdd adds it (round to nearest); only the order of
// the additions to one value varies from run to run.
template <int D>
__device__ __forceinline__ void atomic_add_row4(float* row, const float (&v)[D]) {
  static_assert(D == 3 || D == 4, "rows of 4 floats");
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  float4 x = make_float4(v[0], v[1], v[2], 0.f);
  if constexpr (D == 4) x.w = v[3];
  asm volatile("red.global.add.v4.f32 [%0], {%1, %2, %3, %4};" ::"l"(row), "f"(x.x), "f"(x.y),
               "f"(x.z), "f"(x.w)
               : "memory");
#else
#pragma unroll
  for (int d = 0; d < D; ++d) atomicAdd(row + d, v[d]);
#endif
}

}  // namespace virgi
