// The gradient of the staged recipe's classifier, one step in two kernels (virgi_ns.edit.fitting's
// classifier_gradients is the same in torch, the reference these kernels match). Over S samples x [S, D]
// with labels y [S], the head
//
//   pre   = W1 x + b1            W1 [W, D]
//   logit = w2 . relu(pre) + b2
//   loss  = mean binary cross-entropy of logit against y
//
// and the gradient, flat: [dW1 (W x D, row-major) | db1 (W) | dw2 (W) | db2 (1)]. Through torch a
// step is a dozen small kernels; here each block takes kTileSamples samples, computes their forward and
// backward in shared memory and writes its partial sums to one row of `partials`, and the second kernel
// adds the rows up in a fixed order: no atomics, so every replay of a step gives the same sums.

#include <cuda_runtime.h>

#include "kernels.h"

namespace virgi {

namespace {

constexpr int kTileSamples = 32;  // samples per block of the partials kernel
constexpr int kThreadsPerBlock = 256;
constexpr int kSumColumns = 32;  // gradient entries per block of the sum kernel
constexpr int kSumRows = kThreadsPerBlock / kSumColumns;  // partial rows each column's threads split

__device__ __forceinline__ float sigmoid(float x) { return 1.f / (1.f + expf(-x)); }

__device__ __forceinline__ float warp_sum(float v) {
#pragma unroll
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(0xffffffffu, v, o);
  return v;
}

__global__ void __launch_bounds__(kThreadsPerBlock) classifier_partials_kernel(
    const float* __restrict__ x, const float* __restrict__ y, int S, int D, int W,
    const float* __restrict__ w1, const float* __restrict__ b1, const float* __restrict__ w2,
    const float* __restrict__ b2, float* __restrict__ partials) {
  extern __shared__ float smem[];
  const int Wp = W + 1;                    // padded row: the transposed writes hit different banks
  float* w1t = smem;                       // [D][Wp], W1 transposed
  float* xs = w1t + D * Wp;                // [kTileSamples][D]
  float* hs = xs + kTileSamples * D;       // [kTileSamples][W]: pre, then the gradient to pre
  float* dl = hs + kTileSamples * W;       // [kTileSamples]: the gradient to the logit
  const int tid = threadIdx.x;
  const int64_t s0 = static_cast<int64_t>(blockIdx.x) * kTileSamples;
  const int n = static_cast<int>(min(static_cast<int64_t>(kTileSamples), S - s0));
  for (int i = tid; i < W * D; i += blockDim.x) {
    const int j = i / D, k = i - j * D;
    w1t[k * Wp + j] = w1[i];
  }
  for (int i = tid; i < kTileSamples * D; i += blockDim.x) xs[i] = i / D < n ? x[s0 * D + i] : 0.f;
  __syncthreads();
  for (int i = tid; i < kTileSamples * W; i += blockDim.x) {
    const int s = i / W, j = i - s * W;
    const float* xr = xs + s * D;
    float acc = 0.f;
    for (int k = 0; k < D; ++k) acc += xr[k] * w1t[k * Wp + j];
    hs[i] = acc + b1[j];
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
  float* out = partials + static_cast<int64_t>(blockIdx.x) * (W * D + 2 * W + 1);
  for (int j = tid; j < W; j += blockDim.x) {
    float g = 0.f;
    for (int s = 0; s < kTileSamples; ++s) g += dl[s] * fmaxf(hs[s * W + j], 0.f);
    out[W * D + W + j] = g;
  }
  if (tid == 0) {
    float g = 0.f;
    for (int s = 0; s < kTileSamples; ++s) g += dl[s];
    out[W * D + 2 * W] = g;
  }
  __syncthreads();  // every read of relu(pre) is done: hs becomes the gradient to pre
  for (int i = tid; i < kTileSamples * W; i += blockDim.x) {
    const int s = i / W, j = i - s * W;
    hs[i] = hs[i] > 0.f ? dl[s] * w2[j] : 0.f;
  }
  __syncthreads();
  for (int j = tid; j < W; j += blockDim.x) {
    float g = 0.f;
    for (int s = 0; s < kTileSamples; ++s) g += hs[s * W + j];
    out[W * D + j] = g;
  }
  for (int i = tid; i < W * D; i += blockDim.x) {
    const int j = i / D, k = i - j * D;
    float g = 0.f;
    for (int s = 0; s < kTileSamples; ++s) g += hs[s * W + j] * xs[s * D + k];
    out[i] = g;
  }
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
  return static_cast<int64_t>(D * (W + 1) + kTileSamples * (D + W + 1)) * sizeof(float);
}

int64_t classifier_partial_rows(int64_t S) { return (S + kTileSamples - 1) / kTileSamples; }

cudaError_t launch_classifier_gradients(const float* x, const float* y, int S, int D, int W,
                                        const float* w1, const float* b1, const float* w2,
                                        const float* b2, float* partials, float* grads,
                                        cudaStream_t stream) {
  if (S == 0) return cudaSuccess;
  const int rows = static_cast<int>(classifier_partial_rows(S));
  const int P = W * D + 2 * W + 1;
  classifier_partials_kernel<<<rows, kThreadsPerBlock, classifier_shared_bytes(D, W), stream>>>(
      x, y, S, D, W, w1, b1, w2, b2, partials);
  const cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  classifier_sum_kernel<<<(P + kSumColumns - 1) / kSumColumns, kThreadsPerBlock, 0, stream>>>(partials, rows, P,
                                                                                               grads);
  return cudaGetLastError();
}

}  // namespace virgi
