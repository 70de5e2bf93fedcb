// Frozen-geometry tile rasterizer: kernel launchers (plain CUDA, no torch headers, so the .cu
// files compile quickly). Each launcher returns the launch's cudaError_t.
//
// Pipeline (extension.cpp, rasterize_contributions):
//   host plan   -> requested views, their requested 16-px grid tiles ("slots"), work units
//   project     -> each Gaussian projected once per requested view; culled when its 3-sigma
//                  tile rectangle holds no requested grid tile (summed-area table lookup); the
//                  visible (view, Gaussian) pairs are appended to compact arrays, which are then
//                  sorted by v*N+g, so no later pass scans views x N
//   sort + bin  -> the visible pairs sorted by depth (stable, ties in v*N+g order); their requested
//                  tiles written in that order, then a stable radix sort by slot: each slot's
//                  list by depth
//   rasterize   -> per pixel, walk the tile's list twice: count, then fill contribution lists
//                  grouped by pixel in compositing order
#pragma once

#include <cuda_runtime.h>

#include <cstddef>
#include <cstdint>

namespace virgi {

// Number of ints per row of the packed host tables (see extension.cpp).
constexpr int kViewInts = 8;  // view id, W, H, gw, gh, tile_base, sat_base, pad
constexpr int kItemInts = 4;  // view row, x0, y0, pad
constexpr int kUnitInts = 4;  // item, slot, gx, gy
constexpr int kTile = 16;     // grid tile size (pixels), as gsplat's default

// The request's counters: one small int64 device array, zeroed by launch_init_request, filled
// by the kernels and read back to the host in one copy where the host needs sizes.
enum Counter : int {
  kCtrVisible = 0,   // visible (view, Gaussian) pairs (projection)
  kCtrIsect = 1,     // their tile intersections (projection)
  kCtrMaxCount = 2,  // the largest entry count of a pixel (count / single raster pass)
  kCtrEntries = 3,   // entries M and contributing pairs U (launch_collect_sizes)
  kCtrPairs = 4,
  kNumCounters = 8,  // slots 5-7 spare
};

// Start of a request: transmittance = 1, valid = inside its image and px_count = 0 for each of
// the P pixels; also zeroes zero_ints[0, n_zero) (the slot ranges), counters[0, kNumCounters)
// and offsets[0] (when not null), so that no separate fills are launched.
cudaError_t launch_init_request(int64_t P, int item_w, int item_h, const int* items,
                                const int* views, float* trans, bool* valid, int* px_count,
                                int64_t n_zero, int* zero_ints, unsigned long long* counters,
                                int64_t* offsets, cudaStream_t stream);
// counters[kCtrVisible] += visible pairs, counters[kCtrIsect] += their tile intersections
// (pre-zeroed); records at compact slots >= cap are dropped (the caller retries with
// cap >= counters[kCtrVisible]). pos[c] = c for every written slot c (the identity permutation
// that the sort by fid carries along).
cudaError_t launch_project_compact(int N, int Vr, const float* means, const float* quats,
                                   const float* scales, const float* opacities, const float* Ks,
                                   const float* viewmats, const int* views, const int* sat,
                                   int64_t cap, float4* rec0, float4* rec1, int* counts, int* fids,
                                   int* pos, unsigned long long* counters, cudaStream_t stream);
// A stable radix sort on key bits [0, end_bit). With temp == nullptr, writes the scratch size
// needed to temp_bytes and sorts nothing.
cudaError_t sort_ints(void* temp, size_t& temp_bytes, int64_t n, int end_bit, const int* keys_in,
                      int* keys_out, const int* vals_in, int* vals_out, cudaStream_t stream);
// out[i] = in[perm[i]] for the records and counts; also zeroes mark[0, n) (the pair marks) and
// writes the depth sort's input (depth_key[i] = the bits of pair i's depth, iota[i] = i) and
// bin_rec[i] = (mean x, mean y, radius, view fids[i] / N as int bits), what binning reads.
cudaError_t launch_gather_compact(int64_t n, int N, const int* perm, const float4* rec0_in,
                                  const float4* rec1_in, const int* counts_in, const int* fids,
                                  float4* rec0, float4* rec1, int* counts, uint8_t* mark,
                                  int* depth_key, int* iota, float4* bin_rec, cudaStream_t stream);
// (slot, pair) for every requested tile of the pairs order[0, n), laid out one pair after another
// (counts and their inclusive scan cum_counts are in that order).
cudaError_t launch_bin(int64_t n, const int* order, const int* counts, const int64_t* cum_counts,
                       const float4* bin_rec, const int* views, const int* tile_slot, int* keys,
                       int* vals, cudaStream_t stream);
cudaError_t launch_ranges(int64_t n, const int* slots, int* ranges, cudaStream_t stream);
// Raster modes: count entries per pixel (+ final T; kCountMark also marks contributing pairs);
// fill them at the pixel offsets (marking unless mark is null); or both in one pass into a
// padded [P, pcap] layout (entries past pcap are counted, not written). kCount and kSingle
// raise *max_count (when not null) to the largest count of a pixel.
constexpr int kCount = 0, kFill = 1, kSingle = 2, kCountMark = 3;
cudaError_t launch_raster(int mode, int num_units, const int* units, const int* items,
                          const int* views, int item_w, int item_h, const int* ranges,
                          const int* sorted_vals, const float4* rec0, const float4* rec1,
                          int* px_count, float* px_trans, const int64_t* px_offsets,
                          int2* out_entry, uint8_t* mark, int pcap, cudaStream_t stream,
                          int* keep_list = nullptr, int* keep_end = nullptr,
                          unsigned long long* max_count = nullptr);
// counters[kCtrEntries] = *entries (the last pixel offset), counters[kCtrPairs] = *pairs (the
// last inclusive pair rank; 0 when pairs is null): one launch, so that the sizes the host needs
// come back in one copy.
cudaError_t launch_collect_sizes(const int64_t* entries, const int* pairs,
                                 unsigned long long* counters, cudaStream_t stream);
cudaError_t launch_split_padded(int64_t P, int pcap, const int64_t* offsets, const int2* padded,
                                const int* rank_incl, int* pixel, int* pair, float* weight,
                                cudaStream_t stream);
cudaError_t launch_pairs(int64_t n, const uint8_t* mark, const int* rank_incl, int N,
                         const int* fids, const int* views, const float4* rec0, int64_t* pair_view,
                         int64_t* pair_gaussian, float* pair_depth, cudaStream_t stream);
cudaError_t launch_split(int64_t M, const int2* entry, const int* rank_incl, int* pair,
                         float* weight, cudaStream_t stream);
cudaError_t launch_pixel_fill(int64_t P, const int64_t* offsets, int* pixel, cudaStream_t stream);

// out[P] = each pixel's pair of largest weight (among equals the largest index), -1 where none.
cudaError_t launch_heaviest_pair(int64_t P, const int* pair, const float* weight, const int64_t* offsets,
                                  int64_t* out, cudaStream_t stream);
// images[P, D] = sum over each pixel's entries of weight * colors[pair] (+ T * background).
cudaError_t launch_composite_forward(int64_t P, int D, const float* colors, const int* pair,
                                     const float* weight, const int64_t* offsets,
                                     const float* trans, const float* background, float* out,
                                     cudaStream_t stream);
// grad_colors (pre-zeroed) += weight * grad_images[pixel] for every entry; its rows hold 4 floats
// for D = 3 and 4 (the caller pads 3 channels: one 16-byte vector atomic per entry), D otherwise.
cudaError_t launch_composite_backward(int64_t M, int D, const float* grad, const int* pixel,
                                      const int* pair, const float* weight, float* grad_colors,
                                      cudaStream_t stream);

// The same gradient per work unit, from the tile lists (D in {1, 3, 4}); list_pair[i] is the
// pair rank of sorted list element i, -1 where that Gaussian contributes nowhere.
cudaError_t launch_composite_backward_tiles(int num_units, int D, const int* units,
                                            const int* items, const int* views, int item_w,
                                            int item_h, const int* ranges, const int* list_pair,
                                            const int64_t* offsets, const int* pair,
                                            const float* weight, const float* grad,
                                            float* grad_colors, cudaStream_t stream);
// A request's deferred tile lists, as the deferred composite and its gradient walk them: the work
// units with their items and views (item_w x item_h pixels an item), each grid tile's range of its
// depth-sorted list (ranges), every list element's Gaussian (sorted_vals) and pair rank (list_pair,
// -1: it contributes nowhere), the projected Gaussians (rec0, rec1), and keep_list / keep_end (from a
// kCountMark pass, or null: the whole lists) naming the list elements that matter to a unit's pixels.
struct DeferredLists {
  int num_units;
  const int* units;
  const int* items;
  const int* views;
  int item_w, item_h;
  const int* ranges;
  const int* sorted_vals;
  const int* list_pair;
  const float4* rec0;
  const float4* rec1;
  const int* keep_list;
  const int* keep_end;
};
// Deferred lists (D in 1..8): the composite and its gradient straight from the tile lists,
// weights recomputed as the raster pass computes them. The forward writes the pixels of the
// units only; grad_colors [U, D] is pre-zeroed.
cudaError_t launch_deferred_forward(const DeferredLists& lists, int D, const float* colors,
                                    const float* background, float* out, cudaStream_t stream);
cudaError_t launch_deferred_backward(const DeferredLists& lists, int D, const float* grad,
                                     float* grad_colors, cudaStream_t stream);
cudaError_t launch_list_pair(int64_t n, const int* sorted_vals, const uint8_t* mark,
                             const int* rank_incl, int* list_pair, cudaStream_t stream);

// The gathered gradient's inputs for launch_edit_l1: the loss kernel writes each row's signs
// (signs [rows], char4), then the set's entries sorted by Gaussian (t_start [num_sets + 1]; t_gauss,
// t_row, t_w: each entry's Gaussian, row, and weight x loss_weight[row] / 3, from
// launch_edit_by_gaussian) are summed into grad_colors by num_blocks blocks.
struct EditGather {
  const int64_t* t_start;
  const int* t_gauss;
  const int* t_row;
  const float* t_w;
  int num_blocks;
  char4* signs;
};

// One step of an edit's weighted L1 pixel loss (edit_kernels.cu): for the pixel set
// counter % num_sets (rows [starts[set], starts[set + 1]) of rows / background / target /
// loss_weight, rows naming the view's pixels whose entries start at offsets[row]), loss[0] (pre-
// zeroed) += sum of loss_weight * mean_c |composite + background - target|, and grad_colors
// [U, 4] (pre-zeroed) += that loss's gradient to colors [U, 3], scattered by one atomic per entry,
// or gathered per Gaussian with gather (not null); then counter += 1. max_rows: the largest set.
cudaError_t launch_edit_l1(int64_t max_rows, const float* colors, const int* pair,
                           const float* weight, const int64_t* offsets, const int64_t* rows,
                           const int64_t* starts, int64_t* counter, int64_t num_sets,
                           const float* background, const float* target, const float* loss_weight,
                           const EditGather* gather, float* loss, float* grad_colors,
                           cudaStream_t stream);
// Once per edit, for the gathered step: each entry of every set's rows by bin set * U + Gaussian.
// fill = false: bins [num_sets * U] (pre-zeroed) += the bins' counts; fill = true: bins holds each
// bin's first free slot (advanced here) and t_gauss, t_row, t_w are written at the slots.
cudaError_t launch_edit_by_gaussian(bool fill, const int* pair, const float* weight,
                                    const int64_t* offsets, const int64_t* rows, int64_t num_rows,
                                    const int64_t* starts, int64_t num_sets,
                                    const float* loss_weight, int64_t U, int* bins, int* t_gauss,
                                    int* t_row, float* t_w, cudaStream_t stream);

// The heads an edit trains (edit_heads.cu), per Gaussian u of U. Forward: from pre = x W1^T + b1
// [U, S], alpha[u] = sigmoid(relu(pre[u]) . w2 + b2), cdp[u] = wd h + bd with h = x[u, hd_offset :
// hd_offset + H] (x [U, Dx], wd [3, H]), colors[u] = sigmoid(alpha cdp + (1 - alpha) cd + k cs).
// Backward: from the loss's gradient to the colours (grad_colors [U, 4], the last column padding),
// grad_rows [U, S + 4] = the gradients to pre and to cdp, then 0; sums [2 S + 4] (pre-zeroed) += the
// gradients of b1 [S], w2 [S], b2 [1], bd [3]. S <= kMaxHeadsWidth.
constexpr int kMaxHeadsWidth = 256;
cudaError_t launch_heads_forward(const float* pre, const float* x, int64_t U, int S, int Dx,
                                 int hd_offset, int H, const float* w2, const float* b2,
                                 const float* wd, const float* bd, const float* cd, const float* cs,
                                 float k, float* colors, float* alpha, float* cdp,
                                 cudaStream_t stream);
cudaError_t launch_heads_backward(const float* grad_colors, const float* colors, const float* alpha,
                                  const float* cdp, const float* cd, const float* pre,
                                  const float* w2, int64_t U, int S, float* grad_rows, float* sums,
                                  cudaStream_t stream);

// The staged recipe's step (edit_heads.cu), the segmentation fixed at alpha [U]: forward as the
// heads' without the segmentation (colors and cdp [U, 3]); backward from grad_colors [U, 4],
// grad_rows [U, 4] = the gradient to cdp, then 0, and sums [4] (pre-zeroed) += its sums over U.
cudaError_t launch_layer_forward(const float* alpha, const float* x, int64_t U, int Dx, int hd_offset, int H,
                                 const float* wd, const float* bd, const float* cd, const float* cs, float k,
                                 float* colors, float* cdp, cudaStream_t stream);
cudaError_t launch_layer_backward(const float* grad_colors, const float* colors, const float* alpha, int64_t U,
                                  float* grad_rows, float* sums, cudaStream_t stream);

// The staged classifier's gradient (classifier.cu): over x [S, D] and labels y [S], the gradient of
// the mean binary cross-entropy of w2 . relu(W1 x + b1) + b2 (W1 [W, D]), written to grads [W D + 2 W
// + 1] as [dW1 | db1 | dw2 | db2], through partials [classifier_partial_rows(S), W D + 2 W + 1]. The
// first kernel takes classifier_shared_bytes(D, W) of shared memory (opted into past 48 KiB) and
// heads for which classifier_takes(D, W).
int64_t classifier_shared_bytes(int D, int W);
bool classifier_takes(int D, int W);
int64_t classifier_partial_rows(int64_t S);
cudaError_t launch_classifier_gradients(const float* x, const float* y, int S, int D, int W,
                                        const float* w1, const float* b1, const float* w2,
                                        const float* b2, float* partials, float* grads,
                                        cudaStream_t stream);

}  // namespace virgi
