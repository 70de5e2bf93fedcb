// Kernels of the frozen-geometry tile rasterizer: projection + culling against requested tiles,
// binning into requested grid tiles, depth sort, per-pixel contribution lists.
//
// Numerical rules (gsplat 1.4.0 classic mode): pinhole projection with the Jacobian clamped at
// 1.3x the field of view, eps2d = 0.3 added to the 2D covariance, radius = ceil(3 sqrt(lambda_max)),
// near plane 0.01, 16-px tile membership on the full-image grid, pixel centres at +0.5,
// alpha = min(0.999, o exp(-sigma)), skip sigma < 0 or alpha < 1/255, stop before T <= 1e-4.
// The 2D covariance, its determinant and the exponent use the float32-stable forms of the
// reference (virgi_ns/raster/reference.py). Built without fast math and without FMA contraction
// (-fmad=false): exp is the accurate expf and every product is rounded as torch rounds it, so
// weights match the reference to float32 rounding.

#include <cub/cub.cuh>
#include <cuda_runtime.h>

#include <algorithm>

#include "kernels.h"
#include "launch.cuh"
#include "unit_pixel.cuh"

namespace virgi {

namespace {

constexpr float kNear = 0.01f;
constexpr float kFar = 1e10f;
constexpr float kEps2d = 0.3f;

// Tile rectangle [x0, x1) x [y0, y1) of a projected Gaussian on a gw x gh grid.
__device__ __forceinline__ void tile_rect(float mx, float my, float radius, int gw, int gh, int& x0,
                                          int& x1, int& y0, int& y1) {
  const float tr = radius / static_cast<float>(kTile);
  const float tx = mx / static_cast<float>(kTile);
  const float ty = my / static_cast<float>(kTile);
  x0 = static_cast<int>(fminf(fmaxf(floorf(tx - tr), 0.f), static_cast<float>(gw)));
  x1 = static_cast<int>(fminf(fmaxf(ceilf(tx + tr), 0.f), static_cast<float>(gw)));
  y0 = static_cast<int>(fminf(fmaxf(floorf(ty - tr), 0.f), static_cast<float>(gh)));
  y1 = static_cast<int>(fminf(fmaxf(ceilf(ty + tr), 0.f), static_cast<float>(gh)));
}

// One thread per Gaussian; loops over the requested views so the Gaussian's rotation is
// computed once. Only visible (view, Gaussian) pairs -- those touching a requested grid tile --
// are kept, as fid = v*N+g, count = requested tiles touched, rec0 = (mean2d.x, mean2d.y, depth,
// opacity), rec1 = (p, r, s, radius) where the Gaussian's exponent at offset (dx, dy) is
// sigma = 0.5 (p (dx - r dy)^2 + s dy^2), and pos = the slot itself (the values of the sort
// below, so that no separate arange is needed). Slots at or beyond cap are not written (the
// caller retries with the exact size); counters[kCtrVisible] counts the visible pairs,
// counters[kCtrIsect] their tile intersections.
//
// The append needs no block barrier per view: each warp stages its visible pairs in its own
// region of shared memory (kWarpStage records, four views of a full warp), counted by a
// warp-uniform register. When the block ends, one block scan of the warps' counts and one global
// atomic reserve the block's slots, and each warp copies its records out (coalesced). A warp
// whose region would overflow (more than four views' worth, as with whole images) first copies
// it out on its own, at slots reserved by one global atomic for the warp. The order of the
// compact arrays is therefore arbitrary (it was already arbitrary between blocks): the caller
// sorts them by fid, which is unique, so the sorted arrays are the same whatever the order.
//
// The 2D covariance is formed as the reference does, stable in float32 for very anisotropic
// Gaussians: A = J W R diag(s) (2x3), cov2d = A A^T + eps2d I, and its determinant by
// Cauchy-Binet (sum of squared 2x2 minors of A + eps2d (a0 + c0) + eps2d^2) instead of a c - b^2.
__global__ void __launch_bounds__(kThreads, 4)
    project_compact_kernel(int N, int Vr, const float* __restrict__ means,
                           const float* __restrict__ quats, const float* __restrict__ scales,
                           const float* __restrict__ opacities, const float* __restrict__ Ks,
                           const float* __restrict__ viewmats, const int* __restrict__ views,
                           const int* __restrict__ sat, int64_t cap, float4* __restrict__ rec0,
                           float4* __restrict__ rec1, int* __restrict__ counts,
                           int* __restrict__ fids, int* __restrict__ pos,
                           unsigned long long* __restrict__ counters) {
  constexpr int kWarps = kThreads / 32;
  constexpr int kWarpStage = 4 * 32;
  // 40 KB of staging per block: the registers (~80 per thread) already hold an SM to three
  // blocks, which leaves most of its 228 KB of shared memory / L1 as cache
  __shared__ float4 s_r0[kWarps * kWarpStage];
  __shared__ float4 s_r1[kWarps * kWarpStage];
  __shared__ int s_count[kWarps * kWarpStage];
  __shared__ int s_fid[kWarps * kWarpStage];
  __shared__ int s_warp_n[kWarps];
  __shared__ int s_warp_off[kWarps];
  __shared__ unsigned long long s_warp_isect[kWarps];
  __shared__ unsigned long long s_base;
  const int g = blockIdx.x * blockDim.x + threadIdx.x;
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  const bool live = g < N;
  const int stage0 = warp * kWarpStage;  // this warp's staging region
  int staged = 0;                        // records in it (the same in every lane)

  // Copies the warp's n staged records to the compact arrays from slot base (whole warp).
  auto copy_out = [&](int n, int64_t base) {
    for (int i = lane; i < n; i += 32) {
      const int64_t at = base + i;
      if (at < cap) {
        rec0[at] = s_r0[stage0 + i];
        rec1[at] = s_r1[stage0 + i];
        counts[at] = s_count[stage0 + i];
        fids[at] = s_fid[stage0 + i];
        pos[at] = static_cast<int>(at);
      }
    }
  };

  float px = 0.f, py = 0.f, pz = 0.f, opac = 0.f;
  float R[3][3] = {{0.f, 0.f, 0.f}, {0.f, 0.f, 0.f}, {0.f, 0.f, 0.f}};
  float s[3] = {0.f, 0.f, 0.f};
  if (live) {
    px = means[3 * g];
    py = means[3 * g + 1];
    pz = means[3 * g + 2];
    float qw = quats[4 * g], qx = quats[4 * g + 1], qy = quats[4 * g + 2], qz = quats[4 * g + 3];
    const float qn = fmaxf(sqrtf(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12f);
    qw /= qn;
    qx /= qn;
    qy /= qn;
    qz /= qn;
    // Rotation matrix, row-major R[i][j].
    R[0][0] = 1.f - 2.f * (qy * qy + qz * qz);
    R[0][1] = 2.f * (qx * qy - qw * qz);
    R[0][2] = 2.f * (qx * qz + qw * qy);
    R[1][0] = 2.f * (qx * qy + qw * qz);
    R[1][1] = 1.f - 2.f * (qx * qx + qz * qz);
    R[1][2] = 2.f * (qy * qz - qw * qx);
    R[2][0] = 2.f * (qx * qz - qw * qy);
    R[2][1] = 2.f * (qy * qz + qw * qx);
    R[2][2] = 1.f - 2.f * (qx * qx + qy * qy);
    s[0] = scales[3 * g];
    s[1] = scales[3 * g + 1];
    s[2] = scales[3 * g + 2];
    opac = opacities[g];
  }
  unsigned long long isect = 0;

  for (int v = 0; v < Vr; ++v) {
    const int* vt = views + v * kViewInts;
    const int cam = vt[0], W = vt[1], H = vt[2], gw = vt[3], gh = vt[4], sat_base = vt[6];
    const float* vm = viewmats + 16 * cam;
    const float* K = Ks + 9 * cam;
    int count = 0;
    float4 r0 = make_float4(0.f, 0.f, 0.f, 0.f), r1 = r0;

    const float x = vm[0] * px + vm[1] * py + vm[2] * pz + vm[3];
    const float y = vm[4] * px + vm[5] * py + vm[6] * pz + vm[7];
    const float z = vm[8] * px + vm[9] * py + vm[10] * pz + vm[11];
    if (live && z >= kNear && z <= kFar) {
      const float fx = K[0], fy = K[4], cx = K[2], cy = K[5];
      const float Wf = static_cast<float>(W), Hf = static_cast<float>(H);
      const float tan_fovx = 0.5f * Wf / fx, tan_fovy = 0.5f * Hf / fy;
      const float lim_x_pos = (Wf - cx) / fx + 0.3f * tan_fovx;
      const float lim_x_neg = cx / fx + 0.3f * tan_fovx;
      const float lim_y_pos = (Hf - cy) / fy + 0.3f * tan_fovy;
      const float lim_y_neg = cy / fy + 0.3f * tan_fovy;
      const float rz = 1.f / z, rz2 = rz * rz;
      const float tx = z * fminf(lim_x_pos, fmaxf(-lim_x_neg, x * rz));
      const float ty = z * fminf(lim_y_pos, fmaxf(-lim_y_neg, y * rz));
      // J = [[fx rz, 0, -fx tx rz2], [0, fy rz, -fy ty rz2]]
      const float j00 = fx * rz, j02 = -fx * tx * rz2, j11 = fy * rz, j12 = -fy * ty * rz2;
      float JW[2][3];
#pragma unroll
      for (int k = 0; k < 3; ++k) {
        JW[0][k] = j00 * vm[k] + j02 * vm[8 + k];
        JW[1][k] = j11 * vm[4 + k] + j12 * vm[8 + k];
      }
      const float mx = fx * x * rz + cx, my = fy * y * rz + cy;
      const int* st = sat + sat_base;
      const int w1 = gw + 1;
      float A[2][3];
#pragma unroll
      for (int i = 0; i < 2; ++i)
#pragma unroll
        for (int k = 0; k < 3; ++k)
          A[i][k] = (JW[i][0] * R[0][k] + JW[i][1] * R[1][k] + JW[i][2] * R[2][k]) * s[k];
      const float a0 = A[0][0] * A[0][0] + A[0][1] * A[0][1] + A[0][2] * A[0][2];
      const float c0 = A[1][0] * A[1][0] + A[1][1] * A[1][1] + A[1][2] * A[1][2];
      const float b = A[0][0] * A[1][0] + A[0][1] * A[1][1] + A[0][2] * A[1][2];
      const float m01 = A[0][0] * A[1][1] - A[0][1] * A[1][0];
      const float m02 = A[0][0] * A[1][2] - A[0][2] * A[1][0];
      const float m12 = A[0][1] * A[1][2] - A[0][2] * A[1][1];
      const float det0 = m01 * m01 + m02 * m02 + m12 * m12;
      const float a = a0 + kEps2d, c = c0 + kEps2d;
      const float det = det0 + kEps2d * (a0 + c0) + kEps2d * kEps2d;
      if (det > 0.f) {
        const float mid = 0.5f * (a + c);
        const float v1 = mid + sqrtf(fmaxf(mid * mid - det, 0.01f));
        const float radius = ceilf(3.f * sqrtf(v1));
        if (radius > 0.f && isfinite(radius) &&
            (mx + radius > 0.f) && (mx - radius < Wf) && (my + radius > 0.f) && (my - radius < Hf)) {
          // gsplat keeps integer radii (int32): beyond 2^31 the stored radius saturates.
          const float r_int = fminf(radius, 2147483648.f);
          int x0, x1, y0, y1;
          tile_rect(mx, my, r_int, gw, gh, x0, x1, y0, y1);
          if (x1 > x0 && y1 > y0) {
            count = st[y1 * w1 + x1] - st[y0 * w1 + x1] - st[y1 * w1 + x0] + st[y0 * w1 + x0];
          }
          if (count > 0) {
            r0 = make_float4(mx, my, z, opac);
            r1 = make_float4(c / det, b / c, 1.f / c, r_int);
          }
        }
      }
    }
    // Stage this view's visible pairs in the warp's region (no block barrier).
    const unsigned ballot = __ballot_sync(0xffffffffu, count > 0);
    const int n_new = __popc(ballot);
    if (staged + n_new > kWarpStage) {  // (warp-uniform) full: the warp copies its region out
      __syncwarp();                     // the lanes' staged records are visible to the warp
      unsigned long long base = 0;
      if (lane == 0) base = atomicAdd(counters + kCtrVisible, static_cast<unsigned long long>(staged));
      copy_out(staged, static_cast<int64_t>(__shfl_sync(0xffffffffu, base, 0)));
      __syncwarp();  // the region is read before it is written again
      staged = 0;
    }
    if (count > 0) {
      const int i = stage0 + staged + __popc(ballot & ((1u << lane) - 1u));
      s_r0[i] = r0;
      s_r1[i] = r1;
      s_count[i] = count;
      s_fid[i] = v * N + g;
      isect += count;
    }
    staged += n_new;
  }
  // End of the block: one scan of the warps' staged counts and one global atomic for the block's
  // slots (and one for its intersections, summed per warp by shuffles); then each warp copies
  // its region out.
#pragma unroll
  for (int off = 16; off > 0; off >>= 1) isect += __shfl_down_sync(0xffffffffu, isect, off);
  if (lane == 0) {
    s_warp_n[warp] = staged;
    s_warp_isect[warp] = isect;
  }
  __syncthreads();  // (also makes every warp's staged records visible)
  if (threadIdx.x == 0) {
    int total = 0;
    unsigned long long total_isect = 0;
#pragma unroll
    for (int w = 0; w < kWarps; ++w) {
      s_warp_off[w] = total;
      total += s_warp_n[w];
      total_isect += s_warp_isect[w];
    }
    s_base = total > 0 ? atomicAdd(counters + kCtrVisible, static_cast<unsigned long long>(total))
                       : 0ull;
    if (total_isect > 0) atomicAdd(counters + kCtrIsect, total_isect);
  }
  __syncthreads();
  copy_out(staged, static_cast<int64_t>(s_base) + s_warp_off[warp]);
}

// The compact arrays in fid order: out[i] = in[perm[i]] (fids are already sorted); the pair
// marks of the raster pass start at 0 here (one launch fewer than a separate fill). Also the
// depth sort's input (the depth's bits: depths are >= kNear > 0, so as ints they are
// non-negative and ordered like the floats; and the identity that the sort carries along) and
// what binning reads of a pair in one 16-byte record: (mean x, mean y, radius, view bits).
__global__ void gather_compact_kernel(int64_t n, int N, const int* __restrict__ perm,
                                      const float4* __restrict__ rec0_in,
                                      const float4* __restrict__ rec1_in,
                                      const int* __restrict__ counts_in, const int* __restrict__ fids,
                                      float4* __restrict__ rec0, float4* __restrict__ rec1,
                                      int* __restrict__ counts, uint8_t* __restrict__ mark,
                                      int* __restrict__ depth_key, int* __restrict__ iota,
                                      float4* __restrict__ bin_rec) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const int j = perm[i];
  const float4 r0 = rec0_in[j];
  const float4 r1 = rec1_in[j];
  rec0[i] = r0;
  rec1[i] = r1;
  counts[i] = counts_in[j];
  mark[i] = 0;
  depth_key[i] = __float_as_int(r0.z);
  iota[i] = static_cast<int>(i);
  bin_rec[i] = make_float4(r0.x, r0.y, r1.w, __int_as_float(fids[i] / N));
}

// Writes (slot, c) for every requested tile that visible pair c = order[i] touches, from
// cum_counts[i] - counts[i] on (counts and cum_counts in that order). order lists the fid-ordered
// pairs by depth (a stable sort, so equal depths keep the (view, Gaussian) order), and threads
// write their runs one after another; a stable sort by slot then leaves each slot's list in
// depth order.
__global__ void bin_kernel(int64_t n, const int* __restrict__ order, const int* __restrict__ counts,
                           const int64_t* __restrict__ cum_counts, const float4* __restrict__ bin_rec,
                           const int* __restrict__ views, const int* __restrict__ tile_slot,
                           int* __restrict__ keys, int* __restrict__ vals) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const int idx = order[i];
  const float4 br = bin_rec[idx];
  const int* vt = views + __float_as_int(br.w) * kViewInts;
  const int gw = vt[3], gh = vt[4];
  const int* ts = tile_slot + vt[5];
  int x0, x1, y0, y1;
  tile_rect(br.x, br.y, br.z, gw, gh, x0, x1, y0, y1);
  const int64_t end = cum_counts[i];
  int64_t out = end - counts[i];
  for (int y = y0; y < y1 && out < end; ++y) {
    for (int x = x0; x < x1; ++x) {
      const int slot = ts[y * gw + x];
      if (slot >= 0) {
        keys[out] = slot;
        vals[out] = idx;
        ++out;
      }
    }
  }
}

// ranges[2 s], ranges[2 s + 1]: start and end of slot s in the sorted slots (pre-zeroed).
__global__ void ranges_kernel(int64_t n, const int* __restrict__ slots, int* __restrict__ ranges) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const int slot = slots[i];
  if (i == 0 || slots[i - 1] != slot) ranges[2 * slot] = static_cast<int>(i);
  if (i == n - 1 || slots[i + 1] != slot) ranges[2 * slot + 1] = static_cast<int>(i + 1);
}

// transmittance = 1 everywhere, valid = the output pixel lies inside its view's image, no
// entries counted yet; and the request's small buffers zeroed (see launch_init_request).
__global__ void init_request_kernel(int64_t P, int item_w, int item_h, const int* __restrict__ items,
                                    const int* __restrict__ views, float* __restrict__ trans,
                                    bool* __restrict__ valid, int* __restrict__ px_count,
                                    int64_t n_zero, int* __restrict__ zero_ints,
                                    unsigned long long* __restrict__ counters,
                                    int64_t* __restrict__ offsets) {
  const int64_t p = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (p < n_zero) zero_ints[p] = 0;
  if (p < kNumCounters) counters[p] = 0ull;
  if (p == 0 && offsets != nullptr) offsets[0] = 0;
  if (p >= P) return;
  px_count[p] = 0;
  const int64_t per_item = static_cast<int64_t>(item_w) * item_h;
  const int item = static_cast<int>(p / per_item);
  const int rem = static_cast<int>(p - item * per_item);
  const int r = rem / item_w, c = rem - r * item_w;
  const int* it = items + item * kItemInts;
  const int* vt = views + it[0] * kViewInts;
  const int X = it[1] + c, Y = it[2] + r;
  valid[p] = X >= 0 && Y >= 0 && X < vt[1] && Y < vt[2];
  trans[p] = 1.f;
}

// One block of 16x16 threads per work unit (an item's overlap with one grid tile). Each thread
// owns one pixel and walks the tile's depth-sorted list. MODE kCount counts entries and writes
// the final transmittance (kCountMark also marks the visible pairs that contribute); kFill
// (after a count) writes the entries at the pixel's offset, marking when mark is not null;
// kSingle does both in one pass for small batches: entries go to a padded layout (slot
// p * pcap + k, the first pcap of each pixel) while the count and transmittance are written as
// in kCount. kCount and kSingle also raise *max_count (when not null) to the block's largest
// pixel count: one atomic per warp, so the host reads it with the request's other sizes.
template <int MODE>
__global__ void __launch_bounds__(kTile* kTile)
    raster_kernel(const int* __restrict__ units, const int* __restrict__ items,
                  const int* __restrict__ views, int item_w, int item_h,
                  const int* __restrict__ ranges, const int* __restrict__ sorted_vals,
                  const float4* __restrict__ rec0, const float4* __restrict__ rec1,
                  int* __restrict__ px_count, float* __restrict__ px_trans,
                  const int64_t* __restrict__ px_offsets, int2* __restrict__ out_entry,
                  uint8_t* __restrict__ mark, int pcap, int* __restrict__ keep_list,
                  int* __restrict__ keep_end, unsigned long long* __restrict__ max_count) {
  constexpr bool FILL = MODE == kFill || MODE == kSingle;
  constexpr bool MARK = MODE != kCount;
  constexpr bool KEEP = MODE == kCountMark;
  constexpr int B = kTile * kTile;
  __shared__ int s_id[B];
  __shared__ int s_used[B];
  __shared__ int s_keep[KEEP ? B : 1];
  __shared__ int s_keep_warp[KEEP ? B / 32 : 1];
  __shared__ float4 s_r0[B];
  __shared__ float4 s_r1[B];

  const UnitPixel px = unit_pixel(units, items, views, item_w, item_h);
  const int tid = threadIdx.x, slot = px.slot;
  const bool inside = px.inside;
  const int64_t p = px.p;

  const int start = ranges[2 * slot], end = ranges[2 * slot + 1];
  bool done = !inside;
  int64_t base = 0;
  int64_t n_out = 0;
  if (MODE == kFill && inside) {
    base = px_offsets[p];
    n_out = px_offsets[p + 1] - base;
    if (n_out == 0) done = true;
  }
  if (MODE == kSingle) {
    base = p * pcap;
    n_out = pcap;
  }
  float T = 1.f;
  int k = 0;
  // FILL: entries at even positions wait in registers for their odd neighbour, so most pairs of
  // entries leave in one 16-byte store (the packed array is 16-byte aligned).
  int2 pending = make_int2(0, 0);
  int64_t pending_at = -1;

  // FILL: a Gaussian used by any pixel of the batch is marked once per block (s_used), after
  // the batch, by the thread that loaded it.
  bool loaded = false;
  // KEEP (deferred lists, one unit per slot): the list elements that matter to some pixel of the
  // unit -- used, or stopping a pixel -- are copied in order to keep_list[start, keep_end[slot]);
  // the deferred composite walks only those, with the same per-pixel results.
  const bool keep_on = KEEP && keep_list != nullptr;
  int kept = 0, prev_j = 0;
  auto keep_batch = [&]() {
    const bool k_me = loaded && s_keep[tid];
    const unsigned bal = __ballot_sync(0xffffffffu, k_me);
    if ((tid & 31) == 0) s_keep_warp[tid >> 5] = __popc(bal);
    __syncthreads();
    int before = 0, total = 0;
#pragma unroll
    for (int w = 0; w < B / 32; ++w) {
      const int c = s_keep_warp[w];
      before += w < (tid >> 5) ? c : 0;
      total += c;
    }
    if (k_me) keep_list[start + kept + before + __popc(bal & ((1u << (tid & 31)) - 1u))] = prev_j;
    kept += total;
    __syncthreads();  // s_keep_warp is rewritten by the next batch
  };
  for (int b0 = start; b0 < end; b0 += B) {
    if (__syncthreads_count(done) == B) break;
    if (MARK && mark && loaded && s_used[tid]) mark[s_id[tid]] = 1;
    if (keep_on && b0 > start) keep_batch();
    const int j = b0 + tid;
    loaded = j < end;
    if (loaded) {
      const int f = sorted_vals[j];
      s_id[tid] = f;
      s_r0[tid] = rec0[f];
      s_r1[tid] = rec1[f];
      if (MARK) s_used[tid] = 0;
      if (KEEP) s_keep[tid] = 0;
      prev_j = j;
    }
    __syncthreads();
    const int nb = min(B, end - b0);
    for (int t = 0; t < nb && !done; ++t) {
      float alpha;
      if (!pixel_alpha(s_r0[t], s_r1[t], px, alpha)) continue;
      const float next_T = T * (1.f - alpha);
      if (next_T <= kTMin) {
        if (KEEP) s_keep[t] = 1;
        done = true;
        break;
      }
      if (FILL && k < n_out) {
        // packed (flat id, weight); split into the pair / weight arrays by split_kernel
        const int2 val = make_int2(s_id[t], __float_as_int(alpha * T));
        const int64_t e = base + k;
        if (e & 1) {
          if (pending_at == e - 1) {
            *reinterpret_cast<int4*>(out_entry + e - 1) = make_int4(pending.x, pending.y, val.x, val.y);
            pending_at = -1;
          } else {
            out_entry[e] = val;
          }
        } else {
          pending = val;
          pending_at = e;
        }
        s_used[t] = 1;
        if (k + 1 == n_out) {
          if (MODE == kFill) done = true;
          if (pending_at >= 0) out_entry[pending_at] = pending;
          pending_at = -1;
        }
      }
      if (MODE == kCountMark) s_used[t] = 1, s_keep[t] = 1;
      ++k;
      T = next_T;
    }
  }
  if (FILL && pending_at >= 0) out_entry[pending_at] = pending;  // a lone last entry
  if (MARK) {
    __syncthreads();
    if (mark && loaded && s_used[tid]) mark[s_id[tid]] = 1;
  }
  if (keep_on) {
    if (end > start) keep_batch();  // (every thread gets here: the loop exits uniformly)
    if (tid == 0) keep_end[slot] = start + kept;
  }
  if (MODE != kFill && inside) {
    px_count[p] = k;
    px_trans[p] = T;
  }
  if ((MODE == kCount || MODE == kSingle) && max_count != nullptr) {
    // (every thread gets here: the shuffles see the whole warp)
    int m = inside ? k : 0;
#pragma unroll
    for (int off = 16; off > 0; off >>= 1) m = max(m, __shfl_xor_sync(0xffffffffu, m, off));
    if ((tid & 31) == 0 && m > 0) atomicMax(max_count, static_cast<unsigned long long>(m));
  }
}

// The sizes the host reads after the raster pass, gathered next to the other counters.
__global__ void collect_sizes_kernel(const int64_t* __restrict__ entries,
                                     const int* __restrict__ pairs,
                                     unsigned long long* __restrict__ counters) {
  counters[kCtrEntries] = static_cast<unsigned long long>(*entries);
  counters[kCtrPairs] = pairs ? static_cast<unsigned long long>(*pairs) : 0ull;
}

// For every visible pair c marked as contributing, write the pair's view, Gaussian and depth
// at its rank (inclusive scan of the marks minus one).
__global__ void pairs_kernel(int64_t n, const uint8_t* __restrict__ mark,
                             const int* __restrict__ rank_incl, int N, const int* __restrict__ fids,
                             const int* __restrict__ views, const float4* __restrict__ rec0,
                             int64_t* __restrict__ pair_view, int64_t* __restrict__ pair_gaussian,
                             float* __restrict__ pair_depth) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n || !mark[i]) return;
  const int r = rank_incl[i] - 1;
  const int f = fids[i];
  const int v = f / N;
  pair_view[r] = views[v * kViewInts];  // the camera row is the view id
  pair_gaussian[r] = f - v * N;
  pair_depth[r] = rec0[i].z;
}

// Packed (flat id, weight bits) entries -> pair rank and weight arrays (coalesced).
__global__ void split_kernel(int64_t M, const int2* __restrict__ entry,
                             const int* __restrict__ rank_incl, int* __restrict__ pair,
                             float* __restrict__ weight) {
  const int64_t e = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (e >= M) return;
  const int2 v = entry[e];
  pair[e] = rank_incl[v.x] - 1;
  weight[e] = __int_as_float(v.y);
}

__global__ void list_pair_kernel(int64_t n, const int* __restrict__ sorted_vals,
                                 const uint8_t* __restrict__ mark, const int* __restrict__ rank_incl,
                                 int* __restrict__ list_pair) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const int f = sorted_vals[i];
  list_pair[i] = mark[f] ? rank_incl[f] - 1 : -1;
}

// pixel[e] for every entry: a warp owns 32 consecutive pixels, whose entries are one contiguous
// range; each lane finds its entry's pixel among the 32 offsets by a shuffle binary search, so
// the stores are coalesced.
// A warp's 32 consecutive pixels p0 .. p0 + 31 (fewer at the end of P) and their entries [start,
// end), grouped by pixel by offsets [P + 1]; my_off: this lane's pixel's first entry.
struct WarpPixels {
  int64_t p0, start, end, my_off;
};

// False where the whole warp lies past P (P rounds the grid up by less than one block): the warp
// returns together, as its shuffles need.
__device__ __forceinline__ bool warp_pixels(int64_t P, const int64_t* __restrict__ offsets,
                                            WarpPixels& w) {
  const int64_t p = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  w.p0 = p - (threadIdx.x & 31);
  if (w.p0 >= P) return false;
  w.my_off = offsets[p < P ? p : P];
  w.start = __shfl_sync(0xffffffffu, w.my_off, 0);
  w.end = offsets[w.p0 + 32 < P ? w.p0 + 32 : P];
  return true;
}

// The lane (pixel p0 + lane) whose entries hold entry e: a shuffle binary search among the warp's
// 32 first entries. Every lane of the warp calls it.
__device__ __forceinline__ int entry_lane(const WarpPixels& w, int64_t e) {
  int lo = 0;
#pragma unroll
  for (int step = 16; step > 0; step >>= 1) {
    const int64_t o = __shfl_sync(0xffffffffu, w.my_off, lo + step);
    if (o <= e) lo += step;
  }
  return lo;
}

__global__ void pixel_fill_kernel(int64_t P, const int64_t* __restrict__ offsets,
                                  int* __restrict__ pixel) {
  WarpPixels w;
  if (!warp_pixels(P, offsets, w)) return;
  for (int64_t b = w.start; b < w.end; b += 32) {
    const int64_t e = b + (threadIdx.x & 31);
    const int lo = entry_lane(w, e);
    if (e < w.end) pixel[e] = static_cast<int>(w.p0 + lo);
  }
}

// The single pass's padded entries -> pixel, pair rank and weight arrays grouped by pixel: as
// pixel_fill_kernel, each lane finds its entry's pixel among the warp's 32, then reads entry
// k = e - offsets[pixel] of that pixel's padded row.
__global__ void split_padded_kernel(int64_t P, int pcap, const int64_t* __restrict__ offsets,
                                    const int2* __restrict__ padded,
                                    const int* __restrict__ rank_incl, int* __restrict__ pixel,
                                    int* __restrict__ pair, float* __restrict__ weight) {
  WarpPixels w;
  if (!warp_pixels(P, offsets, w)) return;
  for (int64_t b = w.start; b < w.end; b += 32) {
    const int64_t e = b + (threadIdx.x & 31);
    const int lo = entry_lane(w, e);
    const int64_t first = __shfl_sync(0xffffffffu, w.my_off, lo);
    if (e < w.end) {
      const int64_t q = w.p0 + lo;
      const int2 v = padded[q * pcap + (e - first)];
      pixel[e] = static_cast<int>(q);
      pair[e] = rank_incl[v.x] - 1;
      weight[e] = __int_as_float(v.y);
    }
  }
}

// This thread's pixel and the part [start, end) of its tile's list (the kept elements where the
// lists name them) that a deferred walk reads.
struct DeferredWalk {
  UnitPixel px;
  int start, end;
};

// (The lists are read-only while a kernel walks them: __ldg keeps their loads on the read-only path, which
// the compiler cannot infer through the struct's pointers.)
__device__ __forceinline__ DeferredWalk deferred_walk(const DeferredLists& L) {
  DeferredWalk w;
  w.px = unit_pixel(L.units, L.items, L.views, L.item_w, L.item_h);
  w.start = __ldg(L.ranges + 2 * w.px.slot);
  w.end = L.keep_list ? __ldg(L.keep_end + w.px.slot) : __ldg(L.ranges + 2 * w.px.slot + 1);
  return w;
}

constexpr int kNoElement = -2;  // (pair ranks are >= -1)

// Each thread of the block loads the element b0 + threadIdx.x of the walk into shared memory (its
// projected Gaussian) and returns its pair rank, or kNoElement past the walk's end.
__device__ __forceinline__ int load_element(const DeferredLists& L, const DeferredWalk& w, int b0,
                                            float4* s_r0, float4* s_r1) {
  const int i = b0 + static_cast<int>(threadIdx.x);
  if (i >= w.end) return kNoElement;
  const int j = L.keep_list ? __ldg(L.keep_list + i) : i;
  const int f = __ldg(L.sorted_vals + j);
  s_r0[threadIdx.x] = __ldg(L.rec0 + f);
  s_r1[threadIdx.x] = __ldg(L.rec1 + f);
  return __ldg(L.list_pair + j);
}

// Deferred lists: the composite and its gradient walk the tile lists again instead of reading
// stored entries. Every per-element step below is the raster kernel's, operation for operation,
// so the weights (alpha T), the early stop and the final T are bit for bit those of the lists.
// list_pair[j] is the pair rank of sorted list element j (-1: it contributes nowhere).
//
// Forward: out[p] = sum alpha T colors[pair] + T_final background; pixels outside every unit
// (invalid ones) are written by the caller.
template <int D>
__global__ void __launch_bounds__(kTile* kTile)
    deferred_fwd_kernel(const DeferredLists L, const float* __restrict__ colors,
                        const float* __restrict__ background, float* __restrict__ out) {
  constexpr int B = kTile * kTile;
  __shared__ float4 s_r0[B];
  __shared__ float4 s_r1[B];
  __shared__ float s_c[B * D];
  const DeferredWalk w = deferred_walk(L);
  const UnitPixel& px = w.px;
  const int tid = threadIdx.x;
  bool done = !px.inside;
  float T = 1.f;
  float acc[D];
#pragma unroll
  for (int d = 0; d < D; ++d) acc[d] = 0.f;
  for (int b0 = w.start; b0 < w.end; b0 += B) {
    if (__syncthreads_count(done) == B) break;
    const int q = load_element(L, w, b0, s_r0, s_r1);
    if (q != kNoElement) {
#pragma unroll
      for (int d = 0; d < D; ++d) s_c[tid * D + d] = q >= 0 ? colors[static_cast<int64_t>(q) * D + d] : 0.f;
    }
    __syncthreads();
    const int nb = min(B, w.end - b0);
    for (int t = 0; t < nb && !done; ++t) {
      float alpha;
      if (!pixel_alpha(s_r0[t], s_r1[t], px, alpha)) continue;
      const float next_T = T * (1.f - alpha);
      if (next_T <= kTMin) {
        done = true;
        break;
      }
      const float wt = alpha * T;
#pragma unroll
      for (int d = 0; d < D; ++d) acc[d] += wt * s_c[t * D + d];
      T = next_T;
    }
  }
  if (px.inside) {
#pragma unroll
    for (int d = 0; d < D; ++d) out[px.p * D + d] = background ? acc[d] + T * background[d] : acc[d];
  }
}

// Backward: grad_colors[pair] += sum over the unit's pixels of alpha T grad[p]; the terms of list
// element t are summed per warp (shuffles), then per block (shared memory), and the block adds
// one global atomic per (element, channel).
template <int D>
__global__ void __launch_bounds__(kTile* kTile)
    deferred_bwd_kernel(const DeferredLists L, const float* __restrict__ grad,
                        float* __restrict__ grad_colors) {
  constexpr int B = kTile * kTile;
  __shared__ float4 s_r0[B];
  __shared__ float4 s_r1[B];
  __shared__ int s_q[B];
  __shared__ float s_acc[B * D];
  const DeferredWalk dw = deferred_walk(L);
  const UnitPixel& px = dw.px;
  const int tid = threadIdx.x;
  bool done = !px.inside;
  float T = 1.f;
  float gv[D];
#pragma unroll
  for (int d = 0; d < D; ++d) gv[d] = px.inside ? grad[px.p * D + d] : 0.f;
  for (int b0 = dw.start; b0 < dw.end; b0 += B) {
    if (__syncthreads_count(done) == B) break;
    const int q = load_element(L, dw, b0, s_r0, s_r1);
    s_q[tid] = q == kNoElement ? -1 : q;
    clear_element_sums<D>(s_acc);
    __syncthreads();
    const int nb = min(B, dw.end - b0);
    for (int t = 0; t < nb; ++t) {
      if (__all_sync(0xffffffffu, done)) break;
      float w = 0.f;
      float alpha;
      if (!done && pixel_alpha(s_r0[t], s_r1[t], px, alpha)) {
        const float next_T = T * (1.f - alpha);
        if (next_T <= kTMin) {
          done = true;
        } else {
          w = alpha * T;
          T = next_T;
        }
      }
      const unsigned bal = __ballot_sync(0xffffffffu, w != 0.f);
      if (bal == 0u) continue;
      if (__popc(bal) <= 2) {  // few lanes: shared atomics beat five shuffle rounds
        if (w != 0.f)
#pragma unroll
          for (int d = 0; d < D; ++d) atomicAdd(&s_acc[t * D + d], w * gv[d]);
        continue;
      }
      warp_sum_to_shared<D>(w, gv, s_acc, t);
    }
    __syncthreads();
    add_element_sums<D>(s_acc, s_q[tid], grad_colors);
  }
}

}  // namespace

cudaError_t launch_project_compact(int N, int Vr, const float* means, const float* quats,
                                   const float* scales, const float* opacities, const float* Ks,
                                   const float* viewmats, const int* views, const int* sat,
                                   int64_t cap, float4* rec0, float4* rec1, int* counts, int* fids,
                                   int* pos, unsigned long long* counters, cudaStream_t stream) {
  if (Vr == 0) return cudaSuccess;
  return launch_elements(project_compact_kernel, N, stream, N, Vr, means, quats, scales, opacities,
                         Ks, viewmats, views, sat, cap, rec0, rec1, counts, fids, pos, counters);
}

cudaError_t sort_ints(void* temp, size_t& temp_bytes, int64_t n, int end_bit, const int* keys_in,
                      int* keys_out, const int* vals_in, int* vals_out, cudaStream_t stream) {
  return cub::DeviceRadixSort::SortPairs(temp, temp_bytes, keys_in, keys_out, vals_in, vals_out,
                                         n, 0, end_bit, stream);
}

cudaError_t launch_gather_compact(int64_t n, int N, const int* perm, const float4* rec0_in,
                                  const float4* rec1_in, const int* counts_in, const int* fids,
                                  float4* rec0, float4* rec1, int* counts, uint8_t* mark,
                                  int* depth_key, int* iota, float4* bin_rec, cudaStream_t stream) {
  return launch_elements(gather_compact_kernel, n, stream, n, N, perm, rec0_in, rec1_in, counts_in,
                         fids, rec0, rec1, counts, mark, depth_key, iota, bin_rec);
}

cudaError_t launch_bin(int64_t n, const int* order, const int* counts, const int64_t* cum_counts,
                       const float4* bin_rec, const int* views, const int* tile_slot, int* keys,
                       int* vals, cudaStream_t stream) {
  return launch_elements(bin_kernel, n, stream, n, order, counts, cum_counts, bin_rec, views,
                         tile_slot, keys, vals);
}

cudaError_t launch_ranges(int64_t n, const int* slots, int* ranges, cudaStream_t stream) {
  return launch_elements(ranges_kernel, n, stream, n, slots, ranges);
}

cudaError_t launch_init_request(int64_t P, int item_w, int item_h, const int* items,
                                const int* views, float* trans, bool* valid, int* px_count,
                                int64_t n_zero, int* zero_ints, unsigned long long* counters,
                                int64_t* offsets, cudaStream_t stream) {
  // (launched even for P == 0: the counters must start at 0)
  const int64_t n = std::max(std::max(P, n_zero), static_cast<int64_t>(kNumCounters));
  return launch_elements(init_request_kernel, n, stream, P, item_w, item_h, items, views, trans,
                         valid, px_count, n_zero, zero_ints, counters, offsets);
}

cudaError_t launch_collect_sizes(const int64_t* entries, const int* pairs,
                                 unsigned long long* counters, cudaStream_t stream) {
  collect_sizes_kernel<<<1, 1, 0, stream>>>(entries, pairs, counters);
  return cudaGetLastError();
}

cudaError_t launch_raster(int mode, int num_units, const int* units, const int* items,
                          const int* views, int item_w, int item_h, const int* ranges,
                          const int* sorted_vals, const float4* rec0, const float4* rec1,
                          int* px_count, float* px_trans, const int64_t* px_offsets,
                          int2* out_entry, uint8_t* mark, int pcap, cudaStream_t stream,
                          int* keep_list, int* keep_end, unsigned long long* max_count) {
  if (num_units == 0) return cudaSuccess;
  return dispatch<kCount, kFill, kSingle, kCountMark>(mode, [&](auto m) {
    return launch_units(raster_kernel<decltype(m)::value>, num_units, stream, units, items, views,
                        item_w, item_h, ranges, sorted_vals, rec0, rec1, px_count, px_trans,
                        px_offsets, out_entry, mark, pcap, keep_list, keep_end, max_count);
  });
}

cudaError_t launch_split_padded(int64_t P, int pcap, const int64_t* offsets, const int2* padded,
                                const int* rank_incl, int* pixel, int* pair, float* weight,
                                cudaStream_t stream) {
  return launch_elements(split_padded_kernel, P, stream, P, pcap, offsets, padded, rank_incl, pixel,
                         pair, weight);
}

cudaError_t launch_pairs(int64_t n, const uint8_t* mark, const int* rank_incl, int N,
                         const int* fids, const int* views, const float4* rec0, int64_t* pair_view,
                         int64_t* pair_gaussian, float* pair_depth, cudaStream_t stream) {
  return launch_elements(pairs_kernel, n, stream, n, mark, rank_incl, N, fids, views, rec0,
                         pair_view, pair_gaussian, pair_depth);
}

cudaError_t launch_split(int64_t M, const int2* entry, const int* rank_incl, int* pair,
                         float* weight, cudaStream_t stream) {
  return launch_elements(split_kernel, M, stream, M, entry, rank_incl, pair, weight);
}

cudaError_t launch_list_pair(int64_t n, const int* sorted_vals, const uint8_t* mark,
                             const int* rank_incl, int* list_pair, cudaStream_t stream) {
  return launch_elements(list_pair_kernel, n, stream, n, sorted_vals, mark, rank_incl, list_pair);
}

cudaError_t launch_pixel_fill(int64_t P, const int64_t* offsets, int* pixel, cudaStream_t stream) {
  return launch_elements(pixel_fill_kernel, P, stream, P, offsets, pixel);
}

cudaError_t launch_deferred_forward(const DeferredLists& lists, int D, const float* colors,
                                    const float* background, float* out, cudaStream_t stream) {
  return dispatch<1, 2, 3, 4, 5, 6, 7, 8>(D, [&](auto d) {
    return launch_units(deferred_fwd_kernel<decltype(d)::value>, lists.num_units, stream, lists, colors,
                        background, out);
  });
}

cudaError_t launch_deferred_backward(const DeferredLists& lists, int D, const float* grad,
                                     float* grad_colors, cudaStream_t stream) {
  return dispatch<1, 2, 3, 4, 5, 6, 7, 8>(D, [&](auto d) {
    return launch_units(deferred_bwd_kernel<decltype(d)::value>, lists.num_units, stream, lists, grad,
                        grad_colors);
  });
}

}  // namespace virgi
