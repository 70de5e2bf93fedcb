// One step of an edit's pixel loss in one kernel: for each pixel of the step's set, the composite
// of its entries (sum_k w_k colors[pair_k] + T * background), its weighted L1 error against the
// target, and the gradient of that loss scattered back to the colours through the same entries.
// The gradient of an L1 loss is known as soon as the pixel is, so nothing is written per pixel
// and every entry is read by the same lanes twice (the second time from cache).
//
// The step's pixel set is chosen on the device: set b = counter % num_sets covers rows
// [starts[b], starts[b + 1]) of the arrays ordered by set, and a second launch advances the
// counter. One recorded CUDA graph therefore replays every set in turn.

#include <cuda_runtime.h>

#include "atomics.cuh"
#include "kernels.h"
#include "launch.cuh"

namespace virgi {

namespace {

constexpr int kGroup = 8;  // lanes per pixel: each reads every kGroup-th entry of the pixel's run

__device__ __forceinline__ float sign_of(float x) { return static_cast<float>((x > 0.f) - (x < 0.f)); }

__global__ void __launch_bounds__(kThreads) edit_l1_kernel(
    const float* __restrict__ colors, const int* __restrict__ pair, const float* __restrict__ weight,
    const int64_t* __restrict__ offsets, const int64_t* __restrict__ rows,
    const int64_t* __restrict__ starts, const int64_t* __restrict__ counter, int64_t num_sets,
    const float* __restrict__ background, const float* __restrict__ target,
    const float* __restrict__ loss_weight, float* __restrict__ loss, float* __restrict__ grad_colors) {
  const int64_t set = counter[0] % num_sets;
  const int64_t r0 = starts[set], n = starts[set + 1] - r0;
  const int64_t i = (static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x) / kGroup;
  const int lane = threadIdx.x % kGroup;
  const bool active = i < n;  // a whole group is active or not: the shuffles below see all lanes
  const int64_t r = r0 + i;
  int64_t e0 = 0, e1 = 0;
  if (active) {
    const int64_t px = rows[r];
    e0 = offsets[px];
    e1 = offsets[px + 1];
  }
  float acc[3] = {0.f, 0.f, 0.f};
  for (int64_t e = e0 + lane; e < e1; e += kGroup) {
    const float w = weight[e];
    const float* c = colors + static_cast<int64_t>(pair[e]) * 3;
#pragma unroll
    for (int d = 0; d < 3; ++d) acc[d] += w * c[d];
  }
#pragma unroll
  for (int o = kGroup / 2; o > 0; o >>= 1)
#pragma unroll
    for (int d = 0; d < 3; ++d) acc[d] += __shfl_xor_sync(0xffffffffu, acc[d], o, kGroup);
  float l = 0.f;
  if (active) {
    // loss = sum over the set's pixels of loss_weight * mean over channels of |image - target|
    const float k = loss_weight[r] / 3.f;
    float g[3];
#pragma unroll
    for (int d = 0; d < 3; ++d) {
      const float err = acc[d] + background[r * 3 + d] - target[r * 3 + d];
      l += fabsf(err);
      g[d] = k * sign_of(err);
    }
    l = lane == 0 ? k * l : 0.f;
    for (int64_t e = e0 + lane; e < e1; e += kGroup) {
      const float w = weight[e];
      const float v[3] = {w * g[0], w * g[1], w * g[2]};
      atomic_add_row4<3>(grad_colors + static_cast<int64_t>(pair[e]) * 4, v);
    }
  }
  // the block's loss: warp sums, then one atomic per block
  __shared__ float warp_sums[kThreads / 32];
#pragma unroll
  for (int o = 16; o > 0; o >>= 1) l += __shfl_down_sync(0xffffffffu, l, o);
  if (threadIdx.x % 32 == 0) warp_sums[threadIdx.x / 32] = l;
  __syncthreads();
  if (threadIdx.x == 0) {
    float s = 0.f;
    for (int w = 0; w < kThreads / 32; ++w) s += warp_sums[w];
    atomicAdd(loss, s);
  }
}

__global__ void advance_kernel(int64_t* counter) { counter[0] += 1; }

}  // namespace

cudaError_t launch_edit_l1(int64_t max_rows, const float* colors, const int* pair,
                           const float* weight, const int64_t* offsets, const int64_t* rows,
                           const int64_t* starts, int64_t* counter, int64_t num_sets,
                           const float* background, const float* target, const float* loss_weight,
                           float* loss, float* grad_colors, cudaStream_t stream) {
  cudaError_t err = launch_elements(edit_l1_kernel, max_rows * kGroup, stream, colors, pair, weight,
                                    offsets, rows, starts, counter, num_sets, background, target,
                                    loss_weight, loss, grad_colors);
  if (err != cudaSuccess) return err;
  advance_kernel<<<1, 1, 0, stream>>>(counter);
  return cudaGetLastError();
}

}  // namespace virgi
