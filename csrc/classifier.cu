// The gradient of the staged recipe's classifier, one step in two kernels (virgi_ns.edit.fitting's
// classifier_gradients is the same in torch, the reference these kernels match). Over S samples x [S, D]
// with labels y [S], the head
//
//   pre   = W1 x + b1            W1 [W, D]
//   logit = w2 . relu(pre) + b2
//   loss  = mean binary cross-entropy of logit against y
//
// and the gradient, flat: [dW1 (W x D, row-major) | db1 (W) | dw2 (W) | db2 (1)]. Through torch a
// step is a dozen kernels, and its products' outputs make round trips through memory; here a fixed grid
// of blocks takes tiles of kTileSamples samples, each tile's forward and backward in shared memory and
// registers, each block summing its tiles in order into one row of `partials`, and the second kernel
// adds the rows up in a fixed order: no atomics, so every run of a step gives the same sums.

#include <cuda_runtime.h>

#include "kernels.h"

namespace virgi {

namespace {

constexpr int kTileSamples = 64;  // samples per tile
constexpr int kThreadsPerBlock = 256;
constexpr int kBlocks = 256;  // the partials kernel's fixed grid: each block sums every kBlocks-th tile, in order
constexpr int kPreRows = 4, kPreCols = 4;  // a thread's register tile of pre: 4 samples x 4 hidden units
constexpr int kPreThreadsPerRow = 16;      // threads across 64 hidden units (kPreCols each, 16 apart)
constexpr int kGradRows = 4, kGradCols = 8;  // a thread's register tile of W1's gradient: 4 units x 8 inputs
constexpr int kSumColumns = 32;  // gradient entries per block of the sum kernel
constexpr int kSumRows = kThreadsPerBlock / kSumColumns;  // partial rows each column's threads split

__device__ __forceinline__ float sigmoid(float x) { return 1.f / (1.f + expf(-x)); }

__device__ __forceinline__ float warp_sum(float v) {
#pragma unroll
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(0xffffffffu, v, o);
  return v;
}

// Rows of shared memory are padded by one float where a warp reads down a column (W1 transposed,
// the samples' inputs), so that its lanes hit different banks.
__global__ void __launch_bounds__(kThreadsPerBlock) classifier_partials_kernel(
    const float* __restrict__ x, const float* __restrict__ y, int S, int D, int W,
    const float* __restrict__ w1, const float* __restrict__ b1, const float* __restrict__ w2,
    const float* __restrict__ b2, float* __restrict__ partials) {
  extern __shared__ float smem[];
  const int Wp = W + 1, Dp = D + 1;
  float* w1t = smem;                   // [D][Wp], W1 transposed
  float* xs = w1t + D * Wp;            // [kTileSamples][Dp], the tile's inputs
  float* hs = xs + kTileSamples * Dp;  // [kTileSamples][W]: pre, then the gradient to pre
  float* dl = hs + kTileSamples * W;   // [kTileSamples]: the gradient to the logit
  const int tid = threadIdx.x;
  for (int i = tid; i < W * D; i += blockDim.x) {
    const int j = i / D, k = i - j * D;
    w1t[k * Wp + j] = w1[i];
  }
  // this thread's share of the sums over the block's samples: W1's gradient at units 4 jt + r and
  // inputs kt + Kq c; b1's and w2's at unit tid; b2's on thread 0
  const int Kq = (D + kGradCols - 1) / kGradCols;
  const int jt = tid / Kq, kt = tid - jt * Kq;
  const bool owner = jt * kGradRows < W;
  float gw1[kGradRows][kGradCols] = {};
  float gb1 = 0.f, gw2 = 0.f, gb2 = 0.f;
  const int ts = tid / kPreThreadsPerRow, tj = tid % kPreThreadsPerRow;
  const int tiles = (S + kTileSamples - 1) / kTileSamples;
  for (int tile = blockIdx.x; tile < tiles; tile += gridDim.x) {
    const int64_t s0 = static_cast<int64_t>(tile) * kTileSamples;
    const int n = static_cast<int>(min(static_cast<int64_t>(kTileSamples), S - s0));
    __syncthreads();  // the last tile's reads are done
    for (int i = tid; i < kTileSamples * D; i += blockDim.x) {
      const int s = i / D, k = i - s * D;
      xs[s * Dp + k] = s < n ? x[s0 * D + i] : 0.f;
    }
    __syncthreads();
    for (int jb = 0; jb < W; jb += kPreThreadsPerRow * kPreCols) {
      float acc[kPreRows][kPreCols] = {};
      for (int k = 0; k < D; ++k) {
        float a[kPreRows], b[kPreCols];
#pragma unroll
        for (int r = 0; r < kPreRows; ++r) a[r] = xs[(ts + 16 * r) * Dp + k];
#pragma unroll
        for (int c = 0; c < kPreCols; ++c) {
          const int j = jb + tj + kPreThreadsPerRow * c;
          b[c] = j < W ? w1t[k * Wp + j] : 0.f;
        }
#pragma unroll
        for (int r = 0; r < kPreRows; ++r)
#pragma unroll
          for (int c = 0; c < kPreCols; ++c) acc[r][c] = __fmaf_rn(a[r], b[c], acc[r][c]);
      }
#pragma unroll
      for (int r = 0; r < kPreRows; ++r)
#pragma unroll
        for (int c = 0; c < kPreCols; ++c) {
          const int j = jb + tj + kPreThreadsPerRow * c;
          if (j < W) hs[(ts + 16 * r) * W + j] = acc[r][c] + b1[j];
        }
    }
    __syncthreads();
    const int warp = tid / 32, lane = tid % 32;
    for (int s = warp; s < kTileSamples; s += blockDim.x / 32) {
      float v = 0.f;
      for (int j = lane; j < W; j += 32) v += fmaxf(hs[s * W + j], 0.f) * w2[j];
      v = warp_sum(v);
      if (lane == 0) dl[s] = s < n ? (sigmoid(v + b2[0]) - y[s0 + s]) / static_cast<float>(S) : 0.f;
    }
    __syncthreads();
    if (tid < W) {
      float g = 0.f;
      for (int s = 0; s < kTileSamples; ++s) g += dl[s] * fmaxf(hs[s * W + tid], 0.f);
      gw2 += g;
    }
    if (tid == 0) {
      float g = 0.f;
      for (int s = 0; s < kTileSamples; ++s) g += dl[s];
      gb2 += g;
    }
    __syncthreads();  // every read of relu(pre) is done: hs becomes the gradient to pre
    for (int i = tid; i < kTileSamples * W; i += blockDim.x) {
      const int s = i / W, j = i - s * W;
      hs[i] = hs[i] > 0.f ? dl[s] * w2[j] : 0.f;
    }
    __syncthreads();
    if (tid < W) {
      float g = 0.f;
      for (int s = 0; s < kTileSamples; ++s) g += hs[s * W + tid];
      gb1 += g;
    }
    if (owner) {
      for (int s = 0; s < kTileSamples; ++s) {
        float h[kGradRows], v[kGradCols];
#pragma unroll
        for (int r = 0; r < kGradRows; ++r) {
          const int j = jt * kGradRows + r;
          h[r] = j < W ? hs[s * W + j] : 0.f;
        }
#pragma unroll
        for (int c = 0; c < kGradCols; ++c) {
          const int k = kt + Kq * c;
          v[c] = k < D ? xs[s * Dp + k] : 0.f;
        }
#pragma unroll
        for (int r = 0; r < kGradRows; ++r)
#pragma unroll
          for (int c = 0; c < kGradCols; ++c) gw1[r][c] = __fmaf_rn(h[r], v[c], gw1[r][c]);
      }
    }
  }
  float* out = partials + static_cast<int64_t>(blockIdx.x) * (W * D + 2 * W + 1);
  if (owner) {
#pragma unroll
    for (int r = 0; r < kGradRows; ++r)
#pragma unroll
      for (int c = 0; c < kGradCols; ++c) {
        const int j = jt * kGradRows + r, k = kt + Kq * c;
        if (j < W && k < D) out[j * D + k] = gw1[r][c];
      }
  }
  if (tid < W) {
    out[W * D + tid] = gb1;
    out[W * D + W + tid] = gw2;
  }
  if (tid == 0) out[W * D + 2 * W] = gb2;
}

// grads[p] = the sum over the rows of partials [rows, P] of column p: each of kSumRows threads per
// column adds every kSumRows-th row in order, then one thread adds their sums in order.
__global__ void __launch_bounds__(kThreadsPerBlock) classifier_sum_kernel(const float* __restrict__ partials,
                                                                          int rows, int P,
                                                                          float* __restrict__ grads) {
  __shared__ float part[kSumRows][kSumColumns];
  const int c = threadIdx.x % kSumColumns, r = threadIdx.x / kSumColumns;
  const int p = blockIdx.x * kSumColumns + c;
  float g = 0.f;
  if (p < P)
    for (int b = r; b < rows; b += kSumRows) g += partials[static_cast<int64_t>(b) * P + p];
  part[r][c] = g;
  __syncthreads();
  if (r == 0 && p < P) {
    float total = 0.f;
#pragma unroll
    for (int t = 0; t < kSumRows; ++t) total += part[t][c];
    grads[p] = total;
  }
}

}  // namespace

int64_t classifier_shared_bytes(int D, int W) {
  return static_cast<int64_t>(D * (W + 1) + kTileSamples * (D + 1 + W + 1)) * sizeof(float);
}

bool classifier_takes(int D, int W) {
  const int owners = (W + kGradRows - 1) / kGradRows * ((D + kGradCols - 1) / kGradCols);
  return D > 0 && W > 0 && W <= kThreadsPerBlock && owners <= kThreadsPerBlock;
}

int64_t classifier_partial_rows(int64_t S) {
  const int64_t tiles = (S + kTileSamples - 1) / kTileSamples;
  return tiles < kBlocks ? tiles : kBlocks;
}

cudaError_t launch_classifier_gradients(const float* x, const float* y, int S, int D, int W,
                                        const float* w1, const float* b1, const float* w2,
                                        const float* b2, float* partials, float* grads,
                                        cudaStream_t stream) {
  if (S == 0) return cudaSuccess;
  const int rows = static_cast<int>(classifier_partial_rows(S));
  const int P = W * D + 2 * W + 1;
  const int64_t bytes = classifier_shared_bytes(D, W);
  if (bytes > 48 * 1024) {
    // opting in is no stream work and is not recorded: the eager step before any recording sets it
    cudaStreamCaptureStatus capturing = cudaStreamCaptureStatusNone;
    cudaError_t err = cudaStreamIsCapturing(stream, &capturing);
    if (err == cudaSuccess && capturing == cudaStreamCaptureStatusNone)
      err = cudaFuncSetAttribute(classifier_partials_kernel, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                 static_cast<int>(bytes));
    if (err != cudaSuccess) return err;
  }
  classifier_partials_kernel<<<rows, kThreadsPerBlock, bytes, stream>>>(x, y, S, D, W, w1, b1, w2, b2, partials);
  const cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  classifier_sum_kernel<<<(P + kSumColumns - 1) / kSumColumns, kThreadsPerBlock, 0, stream>>>(partials, rows, P,
                                                                                               grads);
  return cudaGetLastError();
}

}  // namespace virgi
