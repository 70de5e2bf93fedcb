// Device pieces shared by every kernel that walks a work unit's depth-sorted tile list (the raster
// passes, the deferred composite and its gradient, the per-tile colour backward). One definition
// keeps their pixel bookkeeping and their per-element arithmetic identical, which the deferred
// lists rely on: the walks must reproduce the count pass's weights bit for bit.
#pragma once

#include <cuda_runtime.h>

#include <cstdint>

#include "kernels.h"

namespace virgi {

constexpr float kAlphaMin = 1.f / 255.f;
constexpr float kAlphaMax = 0.999f;
constexpr float kTMin = 1e-4f;

// The pixel that thread threadIdx.x owns in work unit blockIdx.x (an item's overlap with one
// 16-px grid tile): its output index p (meaningful when inside), and the offsets from the centre
// of the tile's first pixel and the pixel within the tile (the reference's order of operations).
struct UnitPixel {
  int item, slot;
  bool inside;
  int64_t p;
  float tcx, tcy, flx, fly;
};

__device__ __forceinline__ UnitPixel unit_pixel(const int* units, const int* items, const int* views,
                                                int item_w, int item_h) {
  const int* u = units + blockIdx.x * kUnitInts;  // (read-only in every kernel: __ldg)
  const int item = __ldg(u), slot = __ldg(u + 1), gx = __ldg(u + 2), gy = __ldg(u + 3);
  const int* it = items + item * kItemInts;
  const int* vt = views + __ldg(it) * kViewInts;
  const int ix0 = __ldg(it + 1), iy0 = __ldg(it + 2), W = __ldg(vt + 1), H = __ldg(vt + 2);
  const int lx = threadIdx.x % kTile, ly = threadIdx.x / kTile;
  const int X = gx * kTile + lx, Y = gy * kTile + ly;
  UnitPixel px;
  px.item = item;
  px.slot = slot;
  px.inside = X >= max(ix0, 0) && X < min(ix0 + item_w, W) && Y >= max(iy0, 0) &&
              Y < min(iy0 + item_h, H);
  px.p = (static_cast<int64_t>(item) * item_h + (Y - iy0)) * item_w + (X - ix0);
  px.tcx = static_cast<float>(gx * kTile) + 0.5f;
  px.tcy = static_cast<float>(gy * kTile) + 0.5f;
  px.flx = static_cast<float>(lx);
  px.fly = static_cast<float>(ly);
  return px;
}

// alpha = min(0.999, o exp(-sigma)) of a projected Gaussian (rec0 m, rec1 q) at the pixel;
// false where the element is skipped (sigma < 0 or alpha < 1/255).
__device__ __forceinline__ bool pixel_alpha(const float4& m, const float4& q, const UnitPixel& px,
                                            float& alpha) {
  const float dx = (m.x - px.tcx) - px.flx, dy = (m.y - px.tcy) - px.fly;
  const float e = dx - q.y * dy;
  const float sigma = 0.5f * (q.x * e * e + q.z * dy * dy);
  alpha = fminf(kAlphaMax, m.w * expf(-sigma));
  return !(sigma < 0.f || alpha < kAlphaMin);
}

// The per-tile colour gradients (composite_bwd_tile_kernel, deferred_bwd_kernel) sum the terms
// of each list element of a batch over the block, in shared memory acc[element * D + d]: thread
// tid clears the sums of element tid before the batch,
template <int D>
__device__ __forceinline__ void clear_element_sums(float* acc) {
#pragma unroll
  for (int d = 0; d < D; ++d) acc[threadIdx.x * D + d] = 0.f;
}

// for each element t the warp's lanes' terms w * g[d] are summed by shuffles and lane 0 adds
// them to the block's sums,
template <int D>
__device__ __forceinline__ void warp_sum_to_shared(float w, const float (&g)[D], float* acc, int t) {
  float v[D];
#pragma unroll
  for (int d = 0; d < D; ++d) v[d] = w * g[d];
#pragma unroll
  for (int off = 16; off > 0; off >>= 1)
#pragma unroll
    for (int d = 0; d < D; ++d) v[d] += __shfl_down_sync(0xffffffffu, v[d], off);
  if ((threadIdx.x & 31) == 0)
#pragma unroll
    for (int d = 0; d < D; ++d) atomicAdd(&acc[t * D + d], v[d]);
}

// then, after the batch, thread tid adds the block's sums of element tid to the gradient row of
// its pair q (one global atomic per non-zero channel; nothing where q < 0: no pair).
template <int D>
__device__ __forceinline__ void add_element_sums(const float* acc, int q, float* grad_colors) {
  if (q >= 0) {
#pragma unroll
    for (int d = 0; d < D; ++d) {
      const float v = acc[threadIdx.x * D + d];
      if (v != 0.f) atomicAdd(grad_colors + static_cast<int64_t>(q) * D + d, v);
    }
  }
}

}  // namespace virgi
