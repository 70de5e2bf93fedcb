// The two heads an edit trains, forward and backward written out around two cuBLAS products, so a
// step's elementwise work is two kernels instead of dozens of autograd ones. Per Gaussian u
// (virgi_ns.edit.heads says the same in torch, the reference these kernels match):
//
//   pre    = x W1^T + b1                   (cuBLAS, before the forward kernel)
//   alpha  = sigmoid(relu(pre) . w2 + b2)  segmentation
//   c_dp   = Wd h_diff + bd                the copied last diffuse layer; h_diff = x[:, hd_offset:]
//   colour = sigmoid(alpha c_dp + (1 - alpha) c_d + k c_s)
//
// The backward kernel takes the loss's gradient to the colours and writes, per Gaussian, the
// gradient to pre and to c_dp (one row [S + 4], the last entry 0 so that rows stay 16-byte
// aligned, for one cuBLAS product with x giving W1's and Wd's gradients), and sums the gradients
// of b1, w2, b2 and bd over the Gaussians. One warp per Gaussian: the lanes read a row's entries
// side by side.

#include <cuda_runtime.h>

#include "kernels.h"

namespace virgi {

namespace {

constexpr int kWarps = 8;  // warps per block
constexpr int kMaxPerLane = kMaxHeadsWidth / 32;

__device__ __forceinline__ float sigmoid(float x) { return 1.f / (1.f + expf(-x)); }

__device__ __forceinline__ float warp_sum(float v) {
#pragma unroll
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(0xffffffffu, v, o);
  return v;
}

// The copied layer's product wd h over h_diff's H entries at one Gaussian, summed across the warp
// (every lane gets it); its bias is added by write_colours.
__device__ __forceinline__ void warp_layer(const float* __restrict__ h, int H, const float* __restrict__ wd,
                                           int lane, float c[3]) {
  c[0] = c[1] = c[2] = 0.f;
  for (int j = lane; j < H; j += 32) {
    const float v = h[j];
#pragma unroll
    for (int d = 0; d < 3; ++d) c[d] += wd[d * H + j] * v;
  }
#pragma unroll
  for (int d = 0; d < 3; ++d) c[d] = warp_sum(c[d]);
}

// Gaussian u's layer output cdp = c + bd and its colour under alpha a, from one lane.
__device__ __forceinline__ void write_colours(int64_t u, float a, const float c[3], const float* __restrict__ bd,
                                              const float* __restrict__ cd, const float* __restrict__ cs, float k,
                                              float* __restrict__ cdp, float* __restrict__ colors) {
#pragma unroll
  for (int d = 0; d < 3; ++d) {
    const float layer = c[d] + bd[d];
    cdp[u * 3 + d] = layer;
    colors[u * 3 + d] = sigmoid(a * layer + (1.f - a) * cd[u * 3 + d] + k * cs[u * 3 + d]);
  }
}

__global__ void __launch_bounds__(kWarps * 32) heads_forward_kernel(
    const float* __restrict__ pre, const float* __restrict__ x, int64_t U, int S, int Dx,
    int hd_offset, int H, const float* __restrict__ w2, const float* __restrict__ b2,
    const float* __restrict__ wd, const float* __restrict__ bd, const float* __restrict__ cd,
    const float* __restrict__ cs, float k, float* __restrict__ colors, float* __restrict__ alpha,
    float* __restrict__ cdp) {
  const int lane = threadIdx.x % 32;
  const int64_t warps = static_cast<int64_t>(gridDim.x) * kWarps;
  for (int64_t u = static_cast<int64_t>(blockIdx.x) * kWarps + threadIdx.x / 32; u < U; u += warps) {
    const float* p = pre + u * S;
    float logit = 0.f, c[3];
    for (int j = lane; j < S; j += 32) logit += fmaxf(p[j], 0.f) * w2[j];
    warp_layer(x + u * Dx + hd_offset, H, wd, lane, c);
    logit = warp_sum(logit);
    if (lane == 0) {
      const float a = sigmoid(logit + b2[0]);
      alpha[u] = a;
      write_colours(u, a, c, bd, cd, cs, k, cdp, colors);
    }
  }
}

__global__ void __launch_bounds__(kWarps * 32) heads_backward_kernel(
    const float* __restrict__ grad_colors, const float* __restrict__ colors,
    const float* __restrict__ alpha, const float* __restrict__ cdp, const float* __restrict__ cd,
    const float* __restrict__ pre, const float* __restrict__ w2, int64_t U, int S,
    float* __restrict__ grad_rows, float* __restrict__ sums) {
  extern __shared__ float block_sums[];  // [2 S + 4]: b1, w2, b2, bd
  const int n_sums = 2 * S + 4;
  for (int i = threadIdx.x; i < n_sums; i += blockDim.x) block_sums[i] = 0.f;
  __syncthreads();
  const int lane = threadIdx.x % 32;
  const int64_t warps = static_cast<int64_t>(gridDim.x) * kWarps;
  float g_b1[kMaxPerLane] = {}, g_w2[kMaxPerLane] = {};
  float g_b2 = 0.f, g_bd = 0.f;  // g_bd: channel `lane` (lanes 0-2)
  for (int64_t u = static_cast<int64_t>(blockIdx.x) * kWarps + threadIdx.x / 32; u < U; u += warps) {
    const float a = alpha[u];
    float dz[3], d_alpha = 0.f;
#pragma unroll
    for (int d = 0; d < 3; ++d) {
      const float c = colors[u * 3 + d];
      dz[d] = grad_colors[u * 4 + d] * c * (1.f - c);
      d_alpha += dz[d] * (cdp[u * 3 + d] - cd[u * 3 + d]);
    }
    const float d_logit = d_alpha * a * (1.f - a);
    const float* p = pre + u * S;
    float* row = grad_rows + u * (S + 4);
#pragma unroll
    for (int t = 0; t < kMaxPerLane; ++t) {
      const int j = lane + 32 * t;
      if (j < S) {
        const float v = p[j];
        const float d_pre = v > 0.f ? d_logit * w2[j] : 0.f;
        row[j] = d_pre;
        g_b1[t] += d_pre;
        g_w2[t] += d_logit * fmaxf(v, 0.f);
      }
    }
    if (lane < 3) {
      const float d_layer = a * dz[lane];
      row[S + lane] = d_layer;
      g_bd += d_layer;
    } else if (lane == 3) {
      row[S + 3] = 0.f;
    }
    g_b2 += d_logit;
  }
#pragma unroll
  for (int t = 0; t < kMaxPerLane; ++t) {
    const int j = lane + 32 * t;
    if (j < S) {
      atomicAdd(block_sums + j, g_b1[t]);
      atomicAdd(block_sums + S + j, g_w2[t]);
    }
  }
  if (lane == 0) atomicAdd(block_sums + 2 * S, g_b2);
  if (lane < 3) atomicAdd(block_sums + 2 * S + 1 + lane, g_bd);
  __syncthreads();
  for (int i = threadIdx.x; i < n_sums; i += blockDim.x) atomicAdd(sums + i, block_sums[i]);
}

// The staged recipe's step, the segmentation fixed: the copied layer alone, alpha [U] given. Forward
// as heads_forward_kernel without the segmentation; backward per Gaussian: grad_rows [U, 4] = the
// gradient to cdp, then 0, and sums [4] += its sums (bd's), then 0.
__global__ void __launch_bounds__(kWarps * 32) layer_forward_kernel(
    const float* __restrict__ alpha, const float* __restrict__ x, int64_t U, int Dx, int hd_offset,
    int H, const float* __restrict__ wd, const float* __restrict__ bd, const float* __restrict__ cd,
    const float* __restrict__ cs, float k, float* __restrict__ colors, float* __restrict__ cdp) {
  const int lane = threadIdx.x % 32;
  const int64_t warps = static_cast<int64_t>(gridDim.x) * kWarps;
  for (int64_t u = static_cast<int64_t>(blockIdx.x) * kWarps + threadIdx.x / 32; u < U; u += warps) {
    float c[3];
    warp_layer(x + u * Dx + hd_offset, H, wd, lane, c);
    if (lane == 0) write_colours(u, alpha[u], c, bd, cd, cs, k, cdp, colors);
  }
}

__global__ void __launch_bounds__(kWarps * 32) layer_backward_kernel(
    const float* __restrict__ grad_colors, const float* __restrict__ colors,
    const float* __restrict__ alpha, int64_t U, float* __restrict__ grad_rows, float* __restrict__ sums) {
  __shared__ float block_sums[3];
  if (threadIdx.x < 3) block_sums[threadIdx.x] = 0.f;
  __syncthreads();
  float g[3] = {0.f, 0.f, 0.f};
  const int64_t stride = static_cast<int64_t>(gridDim.x) * blockDim.x;
  for (int64_t u = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x; u < U; u += stride) {
    const float a = alpha[u];
#pragma unroll
    for (int d = 0; d < 3; ++d) {
      const float c = colors[u * 3 + d];
      const float d_layer = a * grad_colors[u * 4 + d] * c * (1.f - c);
      grad_rows[u * 4 + d] = d_layer;
      g[d] += d_layer;
    }
    grad_rows[u * 4 + 3] = 0.f;
  }
#pragma unroll
  for (int d = 0; d < 3; ++d) g[d] = warp_sum(g[d]);
  if (threadIdx.x % 32 == 0)
    for (int d = 0; d < 3; ++d) atomicAdd(block_sums + d, g[d]);
  __syncthreads();
  if (threadIdx.x < 3) atomicAdd(sums + threadIdx.x, block_sums[threadIdx.x]);
}

// One warp per Gaussian, up to `cap` blocks; past that each warp loops over its share. The backward
// caps its blocks: each block ends with 2 S + 4 atomics on the same few addresses.
unsigned blocks_for_warps(int64_t U, int64_t cap) {
  const int64_t want = (U + kWarps - 1) / kWarps;
  return static_cast<unsigned>(want < cap ? want : cap);
}

}  // namespace

cudaError_t launch_heads_forward(const float* pre, const float* x, int64_t U, int S, int Dx,
                                 int hd_offset, int H, const float* w2, const float* b2,
                                 const float* wd, const float* bd, const float* cd, const float* cs,
                                 float k, float* colors, float* alpha, float* cdp,
                                 cudaStream_t stream) {
  if (U == 0) return cudaSuccess;
  heads_forward_kernel<<<blocks_for_warps(U, 1 << 20), kWarps * 32, 0, stream>>>(
      pre, x, U, S, Dx, hd_offset, H, w2, b2, wd, bd, cd, cs, k, colors, alpha, cdp);
  return cudaGetLastError();
}

cudaError_t launch_heads_backward(const float* grad_colors, const float* colors, const float* alpha,
                                  const float* cdp, const float* cd, const float* pre,
                                  const float* w2, int64_t U, int S, float* grad_rows, float* sums,
                                  cudaStream_t stream) {
  if (U == 0) return cudaSuccess;
  heads_backward_kernel<<<blocks_for_warps(U, 2048), kWarps * 32, (2 * S + 4) * sizeof(float), stream>>>(
      grad_colors, colors, alpha, cdp, cd, pre, w2, U, S, grad_rows, sums);
  return cudaGetLastError();
}

cudaError_t launch_layer_forward(const float* alpha, const float* x, int64_t U, int Dx, int hd_offset, int H,
                                 const float* wd, const float* bd, const float* cd, const float* cs, float k,
                                 float* colors, float* cdp, cudaStream_t stream) {
  if (U == 0) return cudaSuccess;
  layer_forward_kernel<<<blocks_for_warps(U, 1 << 20), kWarps * 32, 0, stream>>>(alpha, x, U, Dx, hd_offset, H, wd,
                                                                              bd, cd, cs, k, colors, cdp);
  return cudaGetLastError();
}

cudaError_t launch_layer_backward(const float* grad_colors, const float* colors, const float* alpha, int64_t U,
                                  float* grad_rows, float* sums, cudaStream_t stream) {
  if (U == 0) return cudaSuccess;
  const int64_t want = (U + kWarps * 32 - 1) / (kWarps * 32);
  layer_backward_kernel<<<static_cast<unsigned>(want < 2048 ? want : 2048), kWarps * 32, 0, stream>>>(
      grad_colors, colors, alpha, U, grad_rows, sums);
  return cudaGetLastError();
}

}  // namespace virgi
