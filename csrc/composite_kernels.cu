// Fused compositing of contribution lists: images = sum_k w_k colors[pair_k] (+ T background),
// and its gradient to the colours. Entries are grouped by pixel, so the forward pass is a
// segmented sum with one thread per pixel (no atomics); the backward pass scatters
// w * d_image into the pair colours with one atomic per entry and channel -- one 16-byte vector
// atomic per entry for 3 or 4 channels on sm_90 -- (neighbouring entries belong to one pixel and
// so to distinct pairs: there are no runs of equal pairs to sum first, and the atomics rarely
// collide).

#include <cuda_runtime.h>

#include "atomics.cuh"
#include "kernels.h"
#include "launch.cuh"
#include "unit_pixel.cuh"

namespace virgi {

namespace {

// D > 0: channel count known at compile time; D == 0: d_rt channels.
template <int D>
__global__ void composite_fwd_kernel(int64_t P, int d_rt, const float* __restrict__ colors,
                                     const int* __restrict__ pair, const float* __restrict__ weight,
                                     const int64_t* __restrict__ offsets,
                                     const float* __restrict__ trans,
                                     const float* __restrict__ background, float* __restrict__ out) {
  const int64_t p = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (p >= P) return;
  const int64_t e0 = offsets[p], e1 = offsets[p + 1];
  const float t = trans[p];
  if constexpr (D > 0) {
    float acc[D];
#pragma unroll
    for (int d = 0; d < D; ++d) acc[d] = 0.f;
    for (int64_t e = e0; e < e1; ++e) {
      const float w = weight[e];
      const float* c = colors + static_cast<int64_t>(pair[e]) * D;
#pragma unroll
      for (int d = 0; d < D; ++d) acc[d] += w * c[d];
    }
#pragma unroll
    for (int d = 0; d < D; ++d) out[p * D + d] = background ? acc[d] + t * background[d] : acc[d];
  } else {
    for (int d = 0; d < d_rt; ++d) {
      float acc = 0.f;
      for (int64_t e = e0; e < e1; ++e)
        acc += weight[e] * colors[static_cast<int64_t>(pair[e]) * d_rt + d];
      out[p * d_rt + d] = background ? acc + t * background[d] : acc;
    }
  }
}

// D > 0: channel count known at compile time; D == 0: d_rt channels. For D = 3 and 4 the
// gradient rows hold 4 floats (the caller pads 3 channels to 4), so each entry adds one vector.
template <int D>
__global__ void composite_bwd_kernel(int64_t M, int d_rt, const float* __restrict__ grad,
                                     const int* __restrict__ pixel, const int* __restrict__ pair,
                                     const float* __restrict__ weight,
                                     float* __restrict__ grad_colors) {
  const int64_t e = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (e >= M) return;
  const float w = weight[e];
  const int64_t px = pixel[e];
  const int64_t q = pair[e];
  if constexpr (D == 3 || D == 4) {
    float v[D];
#pragma unroll
    for (int d = 0; d < D; ++d) v[d] = w * grad[px * D + d];
    atomic_add_row4<D>(grad_colors + q * 4, v);
  } else if constexpr (D > 0) {
#pragma unroll
    for (int d = 0; d < D; ++d) atomicAdd(grad_colors + q * D + d, w * grad[px * D + d]);
  } else {
    for (int d = 0; d < d_rt; ++d) atomicAdd(grad_colors + q * d_rt + d, w * grad[px * d_rt + d]);
  }
}

// Per work unit (16x16 grid tile of one item), as the rasterizer's pass: each thread owns a
// pixel and steps through its entries while the block walks the tile's depth-sorted list in
// batches; the terms of list element t are summed per warp (shuffles), then per block (shared
// memory), and the block adds one atomic per (list element, channel) to the pair's gradient: a
// Gaussian covering many pixels costs one global atomic per tile instead of one per pixel.
template <int D>
__global__ void __launch_bounds__(kTile* kTile)
    composite_bwd_tile_kernel(const int* __restrict__ units, const int* __restrict__ items,
                              const int* __restrict__ views, int item_w, int item_h,
                              const int* __restrict__ ranges, const int* __restrict__ list_pair,
                              const int64_t* __restrict__ offsets, const int* __restrict__ pair,
                              const float* __restrict__ weight, const float* __restrict__ grad,
                              float* __restrict__ grad_colors) {
  constexpr int B = kTile * kTile;
  __shared__ int s_pair[B];
  __shared__ float s_acc[B * D];
  const UnitPixel px = unit_pixel(units, items, views, item_w, item_h);
  const int tid = threadIdx.x, slot = px.slot;
  const bool inside = px.inside;
  int64_t e = 0, e_end = 0;
  int q = -1;
  float gv[D];
#pragma unroll
  for (int d = 0; d < D; ++d) gv[d] = 0.f;
  if (inside) {
    const int64_t p = px.p;
    e = offsets[p];
    e_end = offsets[p + 1];
    if (e < e_end) q = pair[e];
#pragma unroll
    for (int d = 0; d < D; ++d) gv[d] = grad[p * D + d];
  }
  bool done = e >= e_end;
  const int start = ranges[2 * slot], end = ranges[2 * slot + 1];
  for (int b0 = start; b0 < end; b0 += B) {
    if (__syncthreads_count(done) == B) break;
    const int j = b0 + tid;
    s_pair[tid] = j < end ? list_pair[j] : -1;
    clear_element_sums<D>(s_acc);
    __syncthreads();
    const int nb = min(B, end - b0);
    // The warp steps through the batch together: lanes whose next entry is element t add their
    // term, the warp sums it by shuffles and one lane adds it to shared memory.
    for (int t = 0; t < nb; ++t) {
      if (__all_sync(0xffffffffu, done)) break;
      const bool hit = !done && s_pair[t] == q;
      if (!__any_sync(0xffffffffu, hit)) continue;
      warp_sum_to_shared<D>(hit ? weight[e] : 0.f, gv, s_acc, t);
      if (hit) {
        if (++e == e_end) done = true;
        else q = pair[e];
      }
    }
    __syncthreads();
    add_element_sums<D>(s_acc, s_pair[tid], grad_colors);
  }
}

// Each pixel's pair of largest weight, among equals the largest pair index; -1 where no entry has a
// weight >= 0. One thread per pixel over its entries (no atomics).
__global__ void heaviest_pair_kernel(int64_t P, const int* __restrict__ pair, const float* __restrict__ weight,
                                     const int64_t* __restrict__ offsets, int64_t* __restrict__ out) {
  const int64_t p = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (p >= P) return;
  float best = 0.f;
  int64_t arg = -1;
  for (int64_t e = offsets[p]; e < offsets[p + 1]; ++e) {
    const float w = weight[e];
    const int64_t u = pair[e];
    if (w > best || (w == best && u > arg)) {
      best = w;
      arg = u;
    }
  }
  out[p] = arg;
}

}  // namespace

cudaError_t launch_composite_forward(int64_t P, int D, const float* colors, const int* pair,
                                     const float* weight, const int64_t* offsets,
                                     const float* trans, const float* background, float* out,
                                     cudaStream_t stream) {
  const auto run = [&](auto d) {
    return launch_elements(composite_fwd_kernel<decltype(d)::value>, P, stream, P, D, colors, pair,
                           weight, offsets, trans, background, out);
  };
  // 1, 3 and 4 channels are compiled for; other counts take the kernel with a runtime count
  return D == 1 || D == 3 || D == 4 ? dispatch<1, 3, 4>(D, run)
                                    : run(std::integral_constant<int, 0>{});
}

cudaError_t launch_composite_backward(int64_t M, int D, const float* grad, const int* pixel,
                                      const int* pair, const float* weight, float* grad_colors,
                                      cudaStream_t stream) {
  const auto run = [&](auto d) {
    return launch_elements(composite_bwd_kernel<decltype(d)::value>, M, stream, M, D, grad, pixel,
                           pair, weight, grad_colors);
  };
  // 1, 3 and 4 channels are compiled for; other counts take the kernel with a runtime count
  return D == 1 || D == 3 || D == 4 ? dispatch<1, 3, 4>(D, run)
                                    : run(std::integral_constant<int, 0>{});
}

cudaError_t launch_composite_backward_tiles(int num_units, int D, const int* units,
                                            const int* items, const int* views, int item_w,
                                            int item_h, const int* ranges, const int* list_pair,
                                            const int64_t* offsets, const int* pair,
                                            const float* weight, const float* grad,
                                            float* grad_colors, cudaStream_t stream) {
  if (num_units == 0) return cudaSuccess;
  return dispatch<1, 3, 4>(D, [&](auto d) {
    return launch_units(composite_bwd_tile_kernel<decltype(d)::value>, num_units, stream, units,
                        items, views, item_w, item_h, ranges, list_pair, offsets, pair, weight, grad,
                        grad_colors);
  });
}

cudaError_t launch_heaviest_pair(int64_t P, const int* pair, const float* weight, const int64_t* offsets,
                                  int64_t* out, cudaStream_t stream) {
  return launch_elements(heaviest_pair_kernel, P, stream, P, pair, weight, offsets, out);
}

}  // namespace virgi
