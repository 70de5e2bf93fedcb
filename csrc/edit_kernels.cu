// One step of an edit's pixel loss: for each pixel of the step's set, the composite of its entries
// (sum_k w_k colors[pair_k] + T * background), its weighted L1 error against the target, and the
// gradient of that loss back to the colours through the same entries. The gradient of an L1 loss
// is known as soon as the pixel is, so nothing but its sign is written per pixel.
//
// The step's pixel set is chosen on the device: set b = counter % num_sets covers rows
// [starts[b], starts[b + 1]) of the arrays ordered by set, and a last launch advances the
// counter. One recorded CUDA graph therefore replays every set in turn.
//
// The gradient reaches the colours in one of two ways:
// - scattered: the loss kernel adds each entry's term to its colour's row with a vector atomic, as
//   it reads the pixel (one atomic per entry);
// - gathered: the loss kernel writes each pixel's signs, and a second kernel sums the terms of
//   each colour over the set's entries sorted by Gaussian (built once per edit by
//   launch_edit_by_gaussian, the loss weight folded into each entry's weight): a warp takes 256
//   consecutive entries and adds one row per run of one Gaussian, so the atomics are a few per
//   warp instead of one per entry.

#include <cuda_runtime.h>

#include <climits>

#include "atomics.cuh"
#include "kernels.h"
#include "launch.cuh"

namespace virgi {

namespace {

constexpr int kGroup = 8;    // lanes per pixel: each reads every kGroup-th entry of the pixel's run
constexpr int kPerLane = 8;  // gathered gradient: consecutive entries per lane
constexpr int kChunk = 32 * kPerLane;  // entries per warp and pass

__device__ __forceinline__ float sign_of(float x) { return static_cast<float>((x > 0.f) - (x < 0.f)); }

// The set of row r: rows are ordered by set, starts [num_sets + 1] (few sets: a linear scan).
__device__ __forceinline__ int64_t set_of_row(const int64_t* starts, int64_t num_sets, int64_t r) {
  int64_t s = 0;
  while (s + 1 < num_sets && starts[s + 1] <= r) ++s;
  return s;
}

template <bool kScatter>
__global__ void __launch_bounds__(kThreads) edit_l1_kernel(
    const float* __restrict__ colors, const int* __restrict__ pair, const float* __restrict__ weight,
    const int64_t* __restrict__ offsets, const int64_t* __restrict__ rows,
    const int64_t* __restrict__ starts, const int64_t* __restrict__ counter, int64_t num_sets,
    const float* __restrict__ background, const float* __restrict__ target,
    const float* __restrict__ loss_weight, float* __restrict__ loss, float* __restrict__ grad_colors,
    char4* __restrict__ signs) {
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
    float s[3];
#pragma unroll
    for (int d = 0; d < 3; ++d) {
      const float err = acc[d] + background[r * 3 + d] - target[r * 3 + d];
      l += fabsf(err);
      s[d] = sign_of(err);
    }
    l = lane == 0 ? k * l : 0.f;
    if constexpr (kScatter) {
      for (int64_t e = e0 + lane; e < e1; e += kGroup) {
        const float w = weight[e];
        const float v[3] = {w * (k * s[0]), w * (k * s[1]), w * (k * s[2])};
        atomic_add_row4<3>(grad_colors + static_cast<int64_t>(pair[e]) * 4, v);
      }
    } else if (lane == 0) {
      signs[r] = make_char4(static_cast<signed char>(s[0]), static_cast<signed char>(s[1]),
                            static_cast<signed char>(s[2]), 0);
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

// The gathered gradient of the counter's set: its entries [t_start[set], t_start[set + 1]) sorted
// by Gaussian (t_gauss), each with its row and its weight times the row's loss weight / 3. Warps
// take chunks of kChunk entries in turn (chunks aligned to kPerLane entries); each lane sums its
// kPerLane consecutive entries, adding a row whenever its Gaussian changes, and the lanes' last
// runs are summed across the warp (a segmented scan: the keys ascend along the lanes), the last
// lane of each run adding it.
__global__ void __launch_bounds__(kThreads) edit_gather_kernel(
    const int64_t* __restrict__ t_start, const int64_t* __restrict__ counter, int64_t num_sets,
    const int* __restrict__ t_gauss, const int* __restrict__ t_row, const float* __restrict__ t_w,
    const char4* __restrict__ signs, float* __restrict__ grad_colors) {
  const int64_t set = counter[0] % num_sets;
  const int64_t e0 = t_start[set], e1 = t_start[set + 1];
  const int lane = threadIdx.x % 32;
  const int64_t warp = (static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x) / 32;
  const int64_t num_warps = static_cast<int64_t>(gridDim.x) * blockDim.x / 32;
  const int64_t first = e0 - e0 % kPerLane;
  for (int64_t c = first + warp * kChunk; c < e1; c += num_warps * kChunk) {
    const int64_t e = c + lane * kPerLane;
    int u[kPerLane], row[kPerLane];
    float w[kPerLane];
    if (e >= e0 && e + kPerLane <= e1) {  // 32-byte aligned runs of 8: vector loads
#pragma unroll
      for (int h = 0; h < kPerLane; h += 4) {
        const int4 a = *reinterpret_cast<const int4*>(t_gauss + e + h);
        const int4 b = *reinterpret_cast<const int4*>(t_row + e + h);
        const float4 f = *reinterpret_cast<const float4*>(t_w + e + h);
        u[h] = a.x, u[h + 1] = a.y, u[h + 2] = a.z, u[h + 3] = a.w;
        row[h] = b.x, row[h + 1] = b.y, row[h + 2] = b.z, row[h + 3] = b.w;
        w[h] = f.x, w[h + 1] = f.y, w[h + 2] = f.z, w[h + 3] = f.w;
      }
    } else {
#pragma unroll
      for (int j = 0; j < kPerLane; ++j) {
        const bool in = e + j >= e0 && e + j < e1;
        u[j] = in ? t_gauss[e + j] : -1;  // -1: no entry
        row[j] = in ? t_row[e + j] : 0;
        w[j] = in ? t_w[e + j] : 0.f;
      }
    }
    char4 sg[kPerLane];  // all loads before the first atomic (its asm is a memory barrier)
#pragma unroll
    for (int j = 0; j < kPerLane; ++j) sg[j] = u[j] < 0 ? make_char4(0, 0, 0, 0) : signs[row[j]];
    int key = e < e0 ? -1 : INT_MAX;  // lanes before or after the set's entries keep the keys sorted
    float acc[3] = {0.f, 0.f, 0.f};
#pragma unroll
    for (int j = 0; j < kPerLane; ++j) {
      if (u[j] < 0) continue;
      const char4 s = sg[j];
      if (u[j] != key) {
        if (key >= 0 && key != INT_MAX) atomic_add_row4<3>(grad_colors + static_cast<int64_t>(key) * 4, acc);
        key = u[j];
        acc[0] = acc[1] = acc[2] = 0.f;
      }
      acc[0] += w[j] * static_cast<float>(s.x);
      acc[1] += w[j] * static_cast<float>(s.y);
      acc[2] += w[j] * static_cast<float>(s.z);
    }
#pragma unroll
    for (int o = 1; o < 32; o <<= 1) {
      const int k_up = __shfl_up_sync(0xffffffffu, key, o);
      float a[3];
#pragma unroll
      for (int d = 0; d < 3; ++d) a[d] = __shfl_up_sync(0xffffffffu, acc[d], o);
      if (lane >= o && k_up == key)
#pragma unroll
        for (int d = 0; d < 3; ++d) acc[d] += a[d];
    }
    const int k_next = __shfl_down_sync(0xffffffffu, key, 1);
    if ((lane == 31 || k_next != key) && key >= 0 && key != INT_MAX)
      atomic_add_row4<3>(grad_colors + static_cast<int64_t>(key) * 4, acc);
  }
}

// Once per edit: the entries of every set's rows counted (count) or placed (fill) by bin
// set * U + Gaussian, kGroup lanes per row.
template <bool kFill>
__global__ void __launch_bounds__(kThreads) by_gaussian_kernel(
    const int* __restrict__ pair, const float* __restrict__ weight, const int64_t* __restrict__ offsets,
    const int64_t* __restrict__ rows, int64_t num_rows, const int64_t* __restrict__ starts,
    int64_t num_sets, const float* __restrict__ loss_weight, int64_t U, int* __restrict__ bins,
    int* __restrict__ t_gauss, int* __restrict__ t_row, float* __restrict__ t_w) {
  const int64_t r = (static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x) / kGroup;
  if (r >= num_rows) return;
  const int lane = threadIdx.x % kGroup;
  const int64_t px = rows[r], base = set_of_row(starts, num_sets, r) * U;
  const float k = loss_weight[r] / 3.f;
  for (int64_t e = offsets[px] + lane; e < offsets[px + 1]; e += kGroup) {
    const int u = pair[e];
    if constexpr (kFill) {
      const int slot = atomicAdd(bins + base + u, 1);  // bins: each bin's next free slot
      t_gauss[slot] = u;
      t_row[slot] = static_cast<int>(r);
      t_w[slot] = weight[e] * k;
    } else {
      atomicAdd(bins + base + u, 1);  // bins: counts
    }
  }
}

__global__ void advance_kernel(int64_t* counter) { counter[0] += 1; }

}  // namespace

cudaError_t launch_edit_l1(int64_t max_rows, const float* colors, const int* pair,
                           const float* weight, const int64_t* offsets, const int64_t* rows,
                           const int64_t* starts, int64_t* counter, int64_t num_sets,
                           const float* background, const float* target, const float* loss_weight,
                           const EditGather* gather, float* loss, float* grad_colors,
                           cudaStream_t stream) {
  cudaError_t err =
      gather == nullptr
          ? launch_elements(edit_l1_kernel<true>, max_rows * kGroup, stream, colors, pair, weight,
                            offsets, rows, starts, counter, num_sets, background, target,
                            loss_weight, loss, grad_colors, static_cast<char4*>(nullptr))
          : launch_elements(edit_l1_kernel<false>, max_rows * kGroup, stream, colors, pair, weight,
                            offsets, rows, starts, counter, num_sets, background, target,
                            loss_weight, loss, grad_colors, gather->signs);
  if (err != cudaSuccess) return err;
  if (gather != nullptr && gather->num_blocks > 0)
    edit_gather_kernel<<<gather->num_blocks, kThreads, 0, stream>>>(
        gather->t_start, counter, num_sets, gather->t_gauss, gather->t_row, gather->t_w,
        gather->signs, grad_colors);
  err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  advance_kernel<<<1, 1, 0, stream>>>(counter);
  return cudaGetLastError();
}

cudaError_t launch_edit_by_gaussian(bool fill, const int* pair, const float* weight,
                                    const int64_t* offsets, const int64_t* rows, int64_t num_rows,
                                    const int64_t* starts, int64_t num_sets,
                                    const float* loss_weight, int64_t U, int* bins, int* t_gauss,
                                    int* t_row, float* t_w, cudaStream_t stream) {
  return fill ? launch_elements(by_gaussian_kernel<true>, num_rows * kGroup, stream, pair, weight,
                                offsets, rows, num_rows, starts, num_sets, loss_weight, U, bins,
                                t_gauss, t_row, t_w)
              : launch_elements(by_gaussian_kernel<false>, num_rows * kGroup, stream, pair, weight,
                                offsets, rows, num_rows, starts, num_sets, loss_weight, U, bins,
                                t_gauss, t_row, t_w);
}

}  // namespace virgi
