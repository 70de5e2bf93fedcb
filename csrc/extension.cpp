// Torch side of the tile rasterizer and the Python bindings: plans a request (requested views,
// requested grid tiles, work units) on the CPU, uploads it in one copy, runs the kernels of
// raster_kernels.cu / composite_kernels.cu and wraps their outputs as tensors.

#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/extension.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cstdint>
#include <cstdlib>
#include <limits>
#include <optional>
#include <vector>

#include "kernels.h"

#define VIRGI_CUDA_CHECK(expr)                                                      \
  do {                                                                              \
    const cudaError_t err_ = (expr);                                                \
    TORCH_CHECK(err_ == cudaSuccess, #expr, " failed: ", cudaGetErrorString(err_)); \
  } while (0)

namespace virgi {

namespace {

// The request, laid out as int tables for the kernels (offsets into one uploaded buffer).
struct Plan {
  std::vector<int> buf;
  int64_t views_at = 0, items_at = 0, units_at = 0, slots_at = 0, sat_at = 0;
  int num_views = 0, num_items = 0, num_units = 0, num_slots = 0;
  int64_t total_tiles = 0;  // grid tiles of the requested views
};

// Visible (view, Gaussian) pairs per (view, Gaussian) over the request's share of grid tiles,
// learned from earlier calls; sizes the compact arrays (an overflow costs a second projection).
std::atomic<double> g_visible_per_share{4.0};

// Entries per pixel that the single pass reserves (learned: 1.25 x the largest count seen), and
// the most memory its padded layout may take; larger requests use two passes.
std::atomic<double> g_entries_cap{64.0};
constexpr int64_t kSinglePassBytes = int64_t{768} << 20;

Plan make_plan(const torch::Tensor& widths, const torch::Tensor& heights,
               const torch::Tensor& item_views, const torch::Tensor& item_x0,
               const torch::Tensor& item_y0, int item_w, int item_h) {
  auto wa = widths.accessor<int64_t, 1>();
  auto ha = heights.accessor<int64_t, 1>();
  auto iv = item_views.accessor<int64_t, 1>();
  auto ix = item_x0.accessor<int64_t, 1>();
  auto iy = item_y0.accessor<int64_t, 1>();
  const int V = static_cast<int>(widths.size(0));
  const int T = static_cast<int>(item_views.size(0));

  // Requested views, ascending; row[v] = its position among them.
  std::vector<int> row(V, -1);
  for (int i = 0; i < T; ++i) {
    TORCH_CHECK(iv[i] >= 0 && iv[i] < V, "request names view ", iv[i], " of ", V);
    row[iv[i]] = 0;
  }
  std::vector<int> vr_ids;
  for (int v = 0; v < V; ++v)
    if (row[v] >= 0) {
      row[v] = static_cast<int>(vr_ids.size());
      vr_ids.push_back(v);
    }
  const int Vr = static_cast<int>(vr_ids.size());

  std::vector<int> views(static_cast<size_t>(Vr) * kViewInts);
  int64_t total_tiles = 0, total_sat = 0;
  for (int r = 0; r < Vr; ++r) {
    const int v = vr_ids[r];
    const int64_t W = wa[v], H = ha[v];
    TORCH_CHECK(W > 0 && H > 0 && W < (1 << 24) && H < (1 << 24), "bad image size for view ", v);
    const int gw = static_cast<int>((W + kTile - 1) / kTile);
    const int gh = static_cast<int>((H + kTile - 1) / kTile);
    int* vt = views.data() + r * kViewInts;
    vt[0] = v;
    vt[1] = static_cast<int>(W);
    vt[2] = static_cast<int>(H);
    vt[3] = gw;
    vt[4] = gh;
    vt[5] = static_cast<int>(total_tiles);
    vt[6] = static_cast<int>(total_sat);
    vt[7] = 0;
    total_tiles += static_cast<int64_t>(gw) * gh;
    total_sat += static_cast<int64_t>(gw + 1) * (gh + 1);
  }
  TORCH_CHECK(total_tiles + total_sat < std::numeric_limits<int>::max() / 2, "request too large");

  std::vector<int> items(static_cast<size_t>(T) * kItemInts);
  std::vector<int> tile_slot(total_tiles, -1);
  std::vector<int> units;
  int num_slots = 0;
  for (int i = 0; i < T; ++i) {
    const int r = row[iv[i]];
    const int* vt = views.data() + r * kViewInts;
    TORCH_CHECK(std::abs(ix[i]) < (1 << 24) && std::abs(iy[i]) < (1 << 24), "tile origin too far");
    int* it = items.data() + i * kItemInts;
    it[0] = r;
    it[1] = static_cast<int>(ix[i]);
    it[2] = static_cast<int>(iy[i]);
    it[3] = 0;
    const int x0 = std::max(it[1], 0), x1 = std::min(it[1] + item_w, vt[1]);
    const int y0 = std::max(it[2], 0), y1 = std::min(it[2] + item_h, vt[2]);
    if (x1 <= x0 || y1 <= y0) continue;
    for (int gy = y0 / kTile; gy <= (y1 - 1) / kTile; ++gy) {
      for (int gx = x0 / kTile; gx <= (x1 - 1) / kTile; ++gx) {
        int& s = tile_slot[vt[5] + static_cast<int64_t>(gy) * vt[3] + gx];
        if (s < 0) s = num_slots++;
        units.insert(units.end(), {i, s, gx, gy});
      }
    }
  }

  // Summed-area table of requested tiles per view: counts requested tiles in any rectangle.
  std::vector<int> sat(total_sat, 0);
  for (int r = 0; r < Vr; ++r) {
    const int* vt = views.data() + r * kViewInts;
    const int gw = vt[3], gh = vt[4], w1 = gw + 1;
    int* st = sat.data() + vt[6];
    const int* ts = tile_slot.data() + vt[5];
    for (int y = 0; y < gh; ++y)
      for (int x = 0; x < gw; ++x)
        st[(y + 1) * w1 + x + 1] = (ts[y * gw + x] >= 0) + st[y * w1 + x + 1] +
                                   st[(y + 1) * w1 + x] - st[y * w1 + x];
  }

  Plan plan;
  plan.num_views = Vr;
  plan.num_items = T;
  plan.num_units = static_cast<int>(units.size() / kUnitInts);
  plan.num_slots = num_slots;
  plan.total_tiles = total_tiles;
  auto append = [&](const std::vector<int>& v, int64_t& at) {
    at = static_cast<int64_t>(plan.buf.size());
    plan.buf.insert(plan.buf.end(), v.begin(), v.end());
    while (plan.buf.size() % 4) plan.buf.push_back(0);  // keep 16-byte alignment
  };
  append(views, plan.views_at);
  append(items, plan.items_at);
  append(units, plan.units_at);
  append(tile_slot, plan.slots_at);
  append(sat, plan.sat_at);
  if (plan.buf.empty()) plan.buf.assign(4, 0);  // an empty request still uploads something
  return plan;
}

// counters[first, first + n) on the host: one copy into pinned memory and one wait for the
// stream (a host<->device synchronisation: the caller needs these sizes to allocate).
std::vector<int64_t> read_counters(const torch::Tensor& counters, int first, int n,
                                   cudaStream_t stream) {
  auto host = torch::empty({n}, torch::TensorOptions().dtype(torch::kInt64).pinned_memory(true));
  VIRGI_CUDA_CHECK(cudaMemcpyAsync(host.data_ptr<int64_t>(), counters.data_ptr<int64_t>() + first,
                                   n * sizeof(int64_t), cudaMemcpyDeviceToHost, stream));
  VIRGI_CUDA_CHECK(cudaStreamSynchronize(stream));
  const int64_t* h = host.data_ptr<int64_t>();
  return std::vector<int64_t>(h, h + n);
}

// ------------------------------------------------------------------ bindings' boilerplate
// Each binding checks its tensors, makes their device current (OnDevice: the guard and that
// device's current stream, on which every kernel of the call runs) and hands typed pointers to
// the launchers of kernels.h.

void check_input(const torch::Tensor& t, const char* name, int64_t cols) {
  TORCH_CHECK(t.is_cuda(), name, " must be on a CUDA device");
  TORCH_CHECK(t.scalar_type() == torch::kFloat32, name, " must be float32");
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  if (cols > 0) TORCH_CHECK(t.dim() == 2 && t.size(1) == cols, name, " must have ", cols, " columns");
}

void check_f32(const torch::Tensor& t, const char* name) {
  TORCH_CHECK(t.is_cuda() && t.is_contiguous() && t.scalar_type() == torch::kFloat32, name,
              " must be a contiguous float32 CUDA tensor");
}

void check_i32(const torch::Tensor& t, const char* name) {
  TORCH_CHECK(t.is_cuda() && t.is_contiguous() && t.scalar_type() == torch::kInt32, name,
              " must be a contiguous int32 CUDA tensor");
}

void check_i64(const torch::Tensor& t, const char* name) {
  TORCH_CHECK(t.is_cuda() && t.is_contiguous() && t.scalar_type() == torch::kInt64, name,
              " must be a contiguous int64 CUDA tensor");
}

struct OnDevice {
  c10::cuda::CUDAGuard guard;
  cudaStream_t stream;
  explicit OnDevice(const torch::Tensor& t)
      : guard(t.device()), stream(c10::cuda::getCurrentCUDAStream()) {}
};

// Records of four floats ([n, 4] float32) and entries of two ints ([n, 2] int32).
float4* float4_ptr(const torch::Tensor& t) { return reinterpret_cast<float4*>(t.data_ptr<float>()); }
int2* int2_ptr(const torch::Tensor& t) { return reinterpret_cast<int2*>(t.data_ptr<int>()); }

// The background (one value per channel, checked), or null when it is empty (none).
const float* background_ptr(const torch::Tensor& background, int D) {
  if (background.numel() == 0) return nullptr;
  check_f32(background, "background");
  TORCH_CHECK(background.numel() == D, "background must hold one value per channel");
  return background.data_ptr<float>();
}

// A request's work units, from its uploaded plan and the offsets in meta.
struct Units {
  const int* units;
  const int* items;
  const int* views;
  int num_units, item_w, item_h;
};

Units units_of(const torch::Tensor& plan, const torch::Tensor& meta) {
  TORCH_CHECK(plan.is_cuda() && plan.scalar_type() == torch::kInt32, "plan must be int32 on the GPU");
  TORCH_CHECK(meta.device().is_cpu() && meta.scalar_type() == torch::kInt64 && meta.numel() == 6,
              "meta must be 6 cpu int64");
  auto m = meta.accessor<int64_t, 1>();
  const int* pl = plan.data_ptr<int>();
  return {pl + m[0], pl + m[1], pl + m[2], static_cast<int>(m[3]), static_cast<int>(m[4]),
          static_cast<int>(m[5])};
}

// The kept elements of deferred lists (keep_list, keep_end), or nulls when none were kept (the
// walks then cover the whole lists).
struct Kept {
  const int* list;
  const int* end;
};

Kept kept_of(const torch::Tensor& keep_list, const torch::Tensor& keep_end) {
  if (keep_list.numel() == 0) return {nullptr, nullptr};
  return {keep_list.data_ptr<int>(), keep_end.data_ptr<int>()};
}

// The deferred lists a request's count pass left (see DeferredLists), for the deferred composite and
// its gradient.
DeferredLists deferred_lists(const torch::Tensor& plan, const torch::Tensor& meta,
                             const torch::Tensor& ranges, const torch::Tensor& sorted_vals,
                             const torch::Tensor& list_pair, const torch::Tensor& rec0,
                             const torch::Tensor& rec1, const torch::Tensor& keep_list,
                             const torch::Tensor& keep_end) {
  check_i32(list_pair, "list_pair");
  check_i32(sorted_vals, "sorted_vals");
  const Units u = units_of(plan, meta);
  const Kept kept = kept_of(keep_list, keep_end);
  return {u.num_units, u.units, u.items, u.views, u.item_w, u.item_h, ranges.data_ptr<int>(),
          sorted_vals.data_ptr<int>(), list_pair.data_ptr<int>(), float4_ptr(rec0), float4_ptr(rec1),
          kept.list, kept.end};
}

}  // namespace

// capacity: size of the compact visible-pair arrays to try first (-1: estimate; tests force an
// overflow and its retry with a small value). single_pass: -1 chooses by size; 0 forces two
// passes; n > 0 forces one pass with n (even) entries reserved per pixel (tests). deferred: only
// the count pass runs (it also marks the contributing pairs); pixel, pair, weight and
// pixel_offsets come back empty, and the state to rebuild them (materialize_lists) or to
// composite straight from the tile lists (deferred_composite_*) comes back instead.
// Returns {pixel i32[M], pair i32[M], weight f32[M], transmittance f32[P], valid bool[P],
//          pixel_offsets i64[P+1], pair_view i64[U], pair_gaussian i64[U], pair_depth f32[U],
//          and the tile lists for composite_backward_tiles: plan i32 (device), meta i64[6] (cpu:
//          units/items/views offsets in plan, number of units, item width, height),
//          ranges i32[2S], list_pair i32[n_isect],
//          and for deferred lists (else empty): px_count i32[P], sorted_vals i32[n_isect],
//          rec0 f32[Uc,4], rec1 f32[Uc,4], rank i32[Uc], keep_list i32[n_isect or 0],
//          keep_end i32[S or 0]}.
std::vector<torch::Tensor> rasterize_contributions(
    torch::Tensor means, torch::Tensor quats, torch::Tensor scales, torch::Tensor opacities,
    torch::Tensor Ks, torch::Tensor viewmats, torch::Tensor widths, torch::Tensor heights,
    torch::Tensor item_views, torch::Tensor item_x0, torch::Tensor item_y0, int64_t item_w,
    int64_t item_h, int64_t capacity, int64_t single_pass, bool deferred) {
  check_input(means, "means", 3);
  check_input(quats, "quats", 4);
  check_input(scales, "scales", 3);
  check_input(opacities, "opacities", 0);
  check_input(Ks, "Ks", 0);
  check_input(viewmats, "viewmats", 0);
  TORCH_CHECK(widths.device().is_cpu() && widths.scalar_type() == torch::kInt64, "widths: cpu int64");
  TORCH_CHECK(heights.device().is_cpu() && heights.scalar_type() == torch::kInt64, "heights: cpu int64");
  TORCH_CHECK(item_views.device().is_cpu() && item_x0.device().is_cpu() && item_y0.device().is_cpu(),
              "request tensors must be on the CPU");
  TORCH_CHECK(item_w > 0 && item_h > 0 && item_w < (1 << 24) && item_h < (1 << 24), "bad item size");
  const OnDevice on(means);
  const cudaStream_t stream = on.stream;
  const int64_t N64 = means.size(0);
  const auto f32 = means.options();
  const auto i32 = f32.dtype(torch::kInt32);
  const auto i64 = f32.dtype(torch::kInt64);

  const int iw = static_cast<int>(item_w), ih = static_cast<int>(item_h);
  Plan plan = make_plan(widths.contiguous(), heights.contiguous(), item_views.contiguous(),
                        item_x0.contiguous(), item_y0.contiguous(), iw, ih);
  const int N = static_cast<int>(N64);
  const int Vr = plan.num_views;
  const int64_t VN = static_cast<int64_t>(Vr) * N;
  TORCH_CHECK(VN < std::numeric_limits<int>::max(), "views x Gaussians must stay below 2^31");
  const int64_t P = static_cast<int64_t>(plan.num_items) * item_w * item_h;
  TORCH_CHECK(P < std::numeric_limits<int>::max(), "requested pixels must stay below 2^31");

  auto host = torch::from_blob(plan.buf.data(), {static_cast<int64_t>(plan.buf.size())},
                               torch::TensorOptions().dtype(torch::kInt32))
                  .pin_memory();
  auto dev = host.to(means.device(), /*non_blocking=*/true);
  const int* dbuf = dev.data_ptr<int>();
  const int* d_views = dbuf + plan.views_at;
  const int* d_items = dbuf + plan.items_at;
  const int* d_units = dbuf + plan.units_at;
  const int* d_slots = dbuf + plan.slots_at;
  const int* d_sat = dbuf + plan.sat_at;

  // The per-pixel outputs, the slot ranges, the pixel offsets and the counters are initialised
  // by one kernel (instead of a fill launch each).
  auto transmittance = torch::empty({P}, f32);
  auto valid = torch::empty({P}, f32.dtype(torch::kBool));
  auto px_count = torch::empty({P}, i32);
  auto ranges = torch::empty({2 * static_cast<int64_t>(std::max(plan.num_slots, 1))}, i32);
  auto offsets = torch::empty({deferred ? 0 : P + 1}, i64);
  auto counters = torch::empty({kNumCounters}, i64);
  auto* d_counters = reinterpret_cast<unsigned long long*>(counters.data_ptr<int64_t>());
  VIRGI_CUDA_CHECK(launch_init_request(P, iw, ih, d_items, d_views, transmittance.data_ptr<float>(),
                                       valid.data_ptr<bool>(), px_count.data_ptr<int>(),
                                       ranges.numel(), ranges.data_ptr<int>(), d_counters,
                                       deferred ? nullptr : offsets.data_ptr<int64_t>(), stream));

  // Project every Gaussian once per requested view; keep the visible pairs (those touching a
  // requested grid tile) in compact arrays. Their number is known only after the projection:
  // the arrays get a capacity from the request's share of grid tiles and a learned ratio, and
  // the projection reruns with the exact size when they overflow.
  const int64_t total_tiles = plan.total_tiles;
  const double share = total_tiles > 0 ? static_cast<double>(plan.num_slots) / total_tiles : 1.0;
  int64_t cap = capacity >= 0 ? capacity
                              : static_cast<int64_t>(std::min(1.0, share * g_visible_per_share.load()) *
                                                     static_cast<double>(VN)) + 4096;
  cap = std::max<int64_t>(std::min(cap, VN), 1);
  torch::Tensor c_rec0, c_rec1, c_counts, c_fids, c_pos;
  int64_t Uc = 0, n_isect = 0;
  for (int attempt = 0; attempt < 2; ++attempt) {
    c_rec0 = torch::empty({cap, 4}, f32);
    c_rec1 = torch::empty({cap, 4}, f32);
    c_counts = torch::empty({cap}, i32);
    c_fids = torch::empty({cap}, i32);
    c_pos = torch::empty({cap}, i32);
    if (attempt > 0) counters.narrow(0, kCtrVisible, 2).zero_();
    VIRGI_CUDA_CHECK(launch_project_compact(
        N, Vr, means.data_ptr<float>(), quats.data_ptr<float>(), scales.data_ptr<float>(),
        opacities.data_ptr<float>(), Ks.data_ptr<float>(), viewmats.data_ptr<float>(), d_views,
        d_sat, cap, float4_ptr(c_rec0), float4_ptr(c_rec1), c_counts.data_ptr<int>(),
        c_fids.data_ptr<int>(), c_pos.data_ptr<int>(), d_counters, stream));
    // synchronisation 1 of 2 (must stay): the compact arrays, the sorts (cub takes host sizes)
    // and the tile keys are sized by these two counts
    const auto t = read_counters(counters, kCtrVisible, 2, stream);
    Uc = t[0];
    n_isect = t[1];
    if (Uc <= cap) break;
    cap = Uc;
  }
  if (capacity < 0 && VN > 0 && share > 0.0) {
    // learn how many visible pairs a share of requested tiles brings (with a margin)
    const double seen = static_cast<double>(Uc) / static_cast<double>(VN) / share;
    // (a slow decay, so that alternating small and large requests do not overflow in turn)
    g_visible_per_share = std::max(1.25 * seen, 0.95 * g_visible_per_share.load());
  }
  TORCH_CHECK(n_isect < std::numeric_limits<int>::max(), "too many tile intersections");

  // The compact arrays in (view, Gaussian) order: ties in depth keep that order in the depth
  // sort below, and the contributing pairs come out ascending in v*N+g.
  auto fids = torch::empty({Uc}, i32);
  auto cnts = torch::empty({Uc}, i32);
  auto rec0 = torch::empty({Uc, 4}, f32);
  auto rec1 = torch::empty({Uc, 4}, f32);
  auto mark = torch::empty({std::max<int64_t>(Uc, 1)}, f32.dtype(torch::kUInt8));  // zeroed by the gather
  // a stable radix sort of (int key, int value) pairs on key bits [0, end_bit)
  auto sort_by = [&](int64_t n, int end_bit, const torch::Tensor& k_in, torch::Tensor& k_out,
                     const torch::Tensor& v_in, torch::Tensor& v_out) {
    size_t bytes = 0;
    VIRGI_CUDA_CHECK(sort_ints(nullptr, bytes, n, end_bit, k_in.data_ptr<int>(), k_out.data_ptr<int>(),
                               v_in.data_ptr<int>(), v_out.data_ptr<int>(), stream));
    auto scratch = torch::empty({static_cast<int64_t>(bytes) + 1}, f32.dtype(torch::kUInt8));
    VIRGI_CUDA_CHECK(sort_ints(scratch.data_ptr(), bytes, n, end_bit, k_in.data_ptr<int>(),
                               k_out.data_ptr<int>(), v_in.data_ptr<int>(), v_out.data_ptr<int>(), stream));
  };
  // by_depth: the fid-ordered pairs listed by depth, ties in fid order
  auto by_depth = torch::empty({Uc}, i32);
  torch::Tensor bin_rec;
  if (Uc > 0) {
    auto perm = torch::empty({Uc}, i32);
    int fid_bits = 1;
    while ((int64_t{1} << fid_bits) < VN) ++fid_bits;
    sort_by(Uc, fid_bits, c_fids, fids, c_pos, perm);
    auto depth_key = torch::empty({Uc}, i32);
    auto iota = torch::empty({Uc}, i32);
    bin_rec = torch::empty({Uc, 4}, f32);
    VIRGI_CUDA_CHECK(launch_gather_compact(
        Uc, N, perm.data_ptr<int>(), float4_ptr(c_rec0), float4_ptr(c_rec1),
        c_counts.data_ptr<int>(), fids.data_ptr<int>(), float4_ptr(rec0), float4_ptr(rec1),
        cnts.data_ptr<int>(), mark.data_ptr<uint8_t>(), depth_key.data_ptr<int>(),
        iota.data_ptr<int>(), float4_ptr(bin_rec), stream));
    // depth bits are non-negative ints (depth >= the near plane > 0): 31 key bits
    auto depth_sorted = torch::empty_like(depth_key);
    sort_by(Uc, 31, depth_key, depth_sorted, iota, by_depth);
  }
  c_rec0 = c_rec1 = c_counts = c_fids = c_pos = torch::Tensor();
  const float4* r0 = float4_ptr(rec0);
  const float4* r1 = float4_ptr(rec1);

  // Bin into requested tiles in depth order, then a stable sort by slot: each slot's list comes
  // out by depth, ties in (view, Gaussian) order. (Two short sorts: the depth sort runs over the
  // visible pairs, fewer than their tile intersections, and the slot sort needs a few bits.)
  auto sorted_vals = torch::empty({n_isect}, i32);
  if (n_isect > 0) {
    auto counts_by_depth = cnts.index_select(0, by_depth);
    auto cum = torch::cumsum(counts_by_depth, 0, torch::kInt64);
    auto keys = torch::empty({n_isect}, i32);
    auto vals = torch::empty({n_isect}, i32);
    VIRGI_CUDA_CHECK(launch_bin(Uc, by_depth.data_ptr<int>(), counts_by_depth.data_ptr<int>(),
                                cum.data_ptr<int64_t>(), float4_ptr(bin_rec), d_views, d_slots,
                                keys.data_ptr<int>(), vals.data_ptr<int>(), stream));
    auto slots_sorted = torch::empty_like(keys);
    int slot_bits = 1;
    while ((int64_t{1} << slot_bits) < plan.num_slots) ++slot_bits;
    sort_by(n_isect, slot_bits, keys, slots_sorted, vals, sorted_vals);
    VIRGI_CUDA_CHECK(launch_ranges(n_isect, slots_sorted.data_ptr<int>(), ranges.data_ptr<int>(), stream));
  }

  // Small batches: one pass writes counts, transmittance and the entries into a padded
  // [P, pcap] layout (pcap learned from earlier calls); a pixel with more entries than pcap
  // sends the request down the two-pass path (count, then fill at exact offsets).
  int pcap = 2 * ((static_cast<int>(g_entries_cap.load()) + 1) / 2);
  const bool single = !deferred && (single_pass >= 0 ? single_pass > 0
                                                     : P * pcap * 8 <= kSinglePassBytes && P * pcap < (int64_t{1} << 31));
  if (single_pass > 0) pcap = std::max(2, static_cast<int>(single_pass) & ~1);
  torch::Tensor padded, keep_list, keep_end;
  if (single) {
    padded = torch::empty({P * pcap, 2}, i32);
    VIRGI_CUDA_CHECK(launch_raster(kSingle, plan.num_units, d_units, d_items, d_views, iw, ih,
                                   ranges.data_ptr<int>(), sorted_vals.data_ptr<int>(), r0, r1,
                                   px_count.data_ptr<int>(), transmittance.data_ptr<float>(),
                                   nullptr, int2_ptr(padded), mark.data_ptr<uint8_t>(), pcap,
                                   stream, nullptr, nullptr, d_counters + kCtrMaxCount));
  } else {
    // deferred lists keep, per unit, the list elements that matter to its pixels (when every
    // slot has one unit, as for whole images: the kept elements then fit the slot's range)
    const bool keep = deferred && plan.num_units == plan.num_slots && n_isect > 0;
    keep_list = torch::empty({keep ? n_isect : 0}, i32);
    keep_end = torch::empty({keep ? plan.num_slots : 0}, i32);
    VIRGI_CUDA_CHECK(launch_raster(deferred ? kCountMark : kCount, plan.num_units, d_units, d_items,
                                   d_views, iw, ih, ranges.data_ptr<int>(),
                                   sorted_vals.data_ptr<int>(), r0, r1, px_count.data_ptr<int>(),
                                   transmittance.data_ptr<float>(), nullptr, nullptr,
                                   deferred ? mark.data_ptr<uint8_t>() : nullptr, 0, stream,
                                   keep ? keep_list.data_ptr<int>() : nullptr,
                                   keep ? keep_end.data_ptr<int>() : nullptr,
                                   deferred ? nullptr : d_counters + kCtrMaxCount));
  }
  auto meta = torch::tensor({plan.units_at, plan.items_at, plan.views_at,
                             static_cast<int64_t>(plan.num_units), item_w, item_h},
                            torch::TensorOptions().dtype(torch::kInt64));
  // The U contributing (view, Gaussian) pairs (the marked ones, ascending in view * N + gaussian:
  // the compact arrays' order) as views, Gaussians and depths, written when fill says so; and the
  // first n elements of the tile lists as pair ranks. rank: the marks' inclusive scan.
  auto pairs_of = [&](int64_t U, const torch::Tensor& rank, bool fill) {
    std::array<torch::Tensor, 3> out{torch::empty({U}, i64), torch::empty({U}, i64),
                                     torch::empty({U}, f32)};
    if (fill)
      VIRGI_CUDA_CHECK(launch_pairs(Uc, mark.data_ptr<uint8_t>(), rank.data_ptr<int>(), N,
                                    fids.data_ptr<int>(), d_views, r0, out[0].data_ptr<int64_t>(),
                                    out[1].data_ptr<int64_t>(), out[2].data_ptr<float>(), stream));
    return out;
  };
  auto list_pair_of = [&](int64_t n, const torch::Tensor& rank) {
    auto out = torch::empty({n}, i32);
    if (n > 0)
      VIRGI_CUDA_CHECK(launch_list_pair(n, sorted_vals.data_ptr<int>(), mark.data_ptr<uint8_t>(),
                                        rank.data_ptr<int>(), out.data_ptr<int>(), stream));
    return out;
  };
  if (deferred) {
    // Pairs and the tile lists as pair ranks; the entries themselves are not stored.
    int64_t U = 0;
    torch::Tensor rank = torch::empty({0}, i32);
    if (Uc > 0) {
      rank = torch::cumsum(mark.narrow(0, 0, Uc), 0, torch::kInt32);
      U = rank[-1].item<int>();
    }
    const auto pairs = pairs_of(U, rank, U > 0);
    auto list_pair = list_pair_of(n_isect, rank);
    auto none_i = torch::empty({0}, i32);
    return {none_i, none_i, torch::empty({0}, f32), transmittance, valid, torch::empty({0}, i64),
            pairs[0], pairs[1], pairs[2], dev, meta, ranges, list_pair,
            px_count, sorted_vals, rec0, rec1, rank, keep_list, keep_end};
  }
  int64_t M = 0, max_count = 0;
  // After one pass the marks are complete unless a pixel overflowed the padded layout: the pair
  // ranks then come back with the entry count in one synchronisation instead of two.
  torch::Tensor rank;
  int64_t U_single = -1;
  if (P > 0) {
    // offsets[0] = 0 (init kernel); the scan writes the rest in place
    auto tail = offsets.narrow(0, 1, P);
    torch::cumsum_out(tail, px_count, 0, torch::kInt64);
    const bool ranked = single && Uc > 0;
    if (ranked) rank = torch::cumsum(mark.narrow(0, 0, Uc), 0, torch::kInt32);
    VIRGI_CUDA_CHECK(launch_collect_sizes(offsets.data_ptr<int64_t>() + P,
                                          ranked ? rank.data_ptr<int>() + (Uc - 1) : nullptr,
                                          d_counters, stream));
    // synchronisation 2 of 2 (must stay): M and U size the returned lists, and the largest
    // count decides whether the padded layout held every entry
    const auto t = read_counters(counters, kCtrMaxCount, 3, stream);
    max_count = t[0];
    M = t[1];
    if (ranked) U_single = t[2];
  }
  if (single_pass < 0 && P > 0 && P * 64 * 8 <= kSinglePassBytes) {  // small requests only
    g_entries_cap = std::min(std::max(1.25 * static_cast<double>(max_count), 0.95 * g_entries_cap.load()),
                             4096.0);
  }
  const bool padded_ok = single && max_count <= pcap;

  // Two passes: the entries, grouped by pixel in compositing order, as packed (flat id, weight).
  torch::Tensor packed;
  if (!padded_ok) {
    padded = torch::Tensor();
    packed = torch::empty({M, 2}, i32);
    VIRGI_CUDA_CHECK(launch_raster(kFill, plan.num_units, d_units, d_items, d_views, iw, ih,
                                   ranges.data_ptr<int>(), sorted_vals.data_ptr<int>(), r0, r1,
                                   nullptr, nullptr, offsets.data_ptr<int64_t>(),
                                   int2_ptr(packed), mark.data_ptr<uint8_t>(), 0, stream));
  }

  // Distinct (view, Gaussian) pairs, ascending in view * N + gaussian (the compact arrays are
  // in that order), each entry's pair rank and weight, and each entry's pixel.
  int64_t U = 0;
  if (M > 0) {
    if (padded_ok && U_single >= 0) {
      U = U_single;
    } else {
      rank = torch::cumsum(mark.narrow(0, 0, Uc), 0, torch::kInt32);
      U = rank[-1].item<int>();
    }
  }
  const auto pairs = pairs_of(U, rank, M > 0);
  auto pixel = torch::empty({M}, i32);
  auto pair = torch::empty({M}, i32);
  auto weight = torch::empty({M}, f32);
  if (M > 0) {
    if (padded_ok) {
      VIRGI_CUDA_CHECK(launch_split_padded(P, pcap, offsets.data_ptr<int64_t>(), int2_ptr(padded),
                                           rank.data_ptr<int>(), pixel.data_ptr<int>(),
                                           pair.data_ptr<int>(), weight.data_ptr<float>(), stream));
    } else {
      VIRGI_CUDA_CHECK(launch_split(M, int2_ptr(packed), rank.data_ptr<int>(),
                                    pair.data_ptr<int>(), weight.data_ptr<float>(), stream));
      VIRGI_CUDA_CHECK(launch_pixel_fill(P, offsets.data_ptr<int64_t>(), pixel.data_ptr<int>(), stream));
    }
  }
  // The tile lists as pair ranks, for the per-tile gradient of the fused composite.
  auto list_pair = list_pair_of(M > 0 ? n_isect : 0, rank);
  // (The pinned host buffer's allocator waits on the upload's event before reusing it.)
  auto none_i = torch::empty({0}, i32);
  auto none_f = torch::empty({0, 4}, f32);
  return {pixel,    pair,     weight, transmittance, valid,  offsets, pairs[0],
          pairs[1], pairs[2], dev,    meta,          ranges, list_pair,
          none_i,   none_i,   none_f, none_f,        none_i, none_i,  none_i};
}

// Each pixel's pair of largest weight [P] (int64; among equals the largest pair, -1 where none).
torch::Tensor heaviest_pair(torch::Tensor pair, torch::Tensor weight, torch::Tensor pixel_offsets) {
  check_i32(pair, "pair");
  check_f32(weight, "weight");
  check_i64(pixel_offsets, "pixel_offsets");
  TORCH_CHECK(pixel_offsets.dim() == 1 && pixel_offsets.numel() >= 1, "pixel_offsets must hold P + 1 entries");
  TORCH_CHECK(pair.numel() == weight.numel(), "pair and weight must hold one value per entry");
  const OnDevice on(weight);
  const int64_t P = pixel_offsets.numel() - 1;
  auto out = torch::empty({P}, pixel_offsets.options());
  VIRGI_CUDA_CHECK(launch_heaviest_pair(P, pair.data_ptr<int>(), weight.data_ptr<float>(),
                                        pixel_offsets.data_ptr<int64_t>(), out.data_ptr<int64_t>(), on.stream));
  return out;
}

// Images [P, D] = sum over each pixel's entries of weight * colors[pair] (+ T * background).
torch::Tensor composite_forward(torch::Tensor colors, torch::Tensor pair, torch::Tensor weight,
                                torch::Tensor pixel_offsets, torch::Tensor transmittance,
                                torch::Tensor background) {
  check_f32(colors, "colors");
  check_i32(pair, "pair");
  check_f32(weight, "weight");
  check_f32(transmittance, "transmittance");
  TORCH_CHECK(pixel_offsets.is_cuda() && pixel_offsets.scalar_type() == torch::kInt64,
              "pixel_offsets must be int64 on the GPU");
  TORCH_CHECK(colors.dim() == 2, "colors must be [U, D]");
  const OnDevice on(colors);
  const int64_t P = transmittance.size(0);
  TORCH_CHECK(pixel_offsets.numel() == P + 1, "pixel_offsets must hold P + 1 entries");
  const int D = static_cast<int>(colors.size(1));
  const float* bg = background_ptr(background, D);
  auto out = torch::empty({P, D}, colors.options());
  VIRGI_CUDA_CHECK(launch_composite_forward(P, D, colors.data_ptr<float>(), pair.data_ptr<int>(),
                                            weight.data_ptr<float>(),
                                            pixel_offsets.data_ptr<int64_t>(),
                                            transmittance.data_ptr<float>(), bg,
                                            out.data_ptr<float>(), on.stream));
  return out;
}

// d colors [U, D] from d images [P, D].
torch::Tensor composite_backward(torch::Tensor grad_images, torch::Tensor pixel, torch::Tensor pair,
                                 torch::Tensor weight, int64_t num_pairs) {
  check_f32(grad_images, "grad_images");
  check_i32(pixel, "pixel");
  check_i32(pair, "pair");
  check_f32(weight, "weight");
  const OnDevice on(grad_images);
  const int64_t M = weight.size(0);
  const int D = static_cast<int>(grad_images.size(1));
  // 3 channels accumulate in rows of 4 (one vector atomic per entry), then drop the padding
  const int64_t row = D == 3 ? 4 : D;
  auto grad_colors = torch::zeros({num_pairs, row}, grad_images.options());
  VIRGI_CUDA_CHECK(launch_composite_backward(M, D, grad_images.data_ptr<float>(),
                                             pixel.data_ptr<int>(), pair.data_ptr<int>(),
                                             weight.data_ptr<float>(),
                                             grad_colors.data_ptr<float>(), on.stream));
  return row == D ? grad_colors : grad_colors.narrow(1, 0, D).contiguous();
}

// d colors [U, D] from d images [P, D], per tile from the rasterizer's tile lists.
torch::Tensor composite_backward_tiles(torch::Tensor grad_images, torch::Tensor pixel_offsets,
                                       torch::Tensor pair, torch::Tensor weight, int64_t num_pairs,
                                       torch::Tensor plan, torch::Tensor meta, torch::Tensor ranges,
                                       torch::Tensor list_pair) {
  check_f32(grad_images, "grad_images");
  check_i32(pair, "pair");
  check_f32(weight, "weight");
  check_i32(plan, "plan");
  check_i32(ranges, "ranges");
  check_i32(list_pair, "list_pair");
  const Units u = units_of(plan, meta);
  const OnDevice on(grad_images);
  const int D = static_cast<int>(grad_images.size(1));
  TORCH_CHECK(D == 1 || D == 3 || D == 4, "composite_backward_tiles handles 1, 3 or 4 channels");
  auto grad_colors = torch::zeros({num_pairs, D}, grad_images.options());
  if (weight.numel() == 0) return grad_colors;
  VIRGI_CUDA_CHECK(launch_composite_backward_tiles(
      u.num_units, D, u.units, u.items, u.views, u.item_w, u.item_h, ranges.data_ptr<int>(),
      list_pair.data_ptr<int>(), pixel_offsets.data_ptr<int64_t>(), pair.data_ptr<int>(),
      weight.data_ptr<float>(), grad_images.data_ptr<float>(), grad_colors.data_ptr<float>(),
      on.stream));
  return grad_colors;
}

// Deferred lists -> {pixel i32[M], pair i32[M], weight f32[M], pixel_offsets i64[P+1]}: the fill
// pass of the two-pass path, from the state rasterize_contributions(deferred) returned.
std::vector<torch::Tensor> materialize_lists(torch::Tensor plan, torch::Tensor meta,
                                             torch::Tensor ranges, torch::Tensor sorted_vals,
                                             torch::Tensor rec0, torch::Tensor rec1,
                                             torch::Tensor px_count, torch::Tensor rank) {
  const OnDevice on(px_count);
  const cudaStream_t stream = on.stream;
  const Units u = units_of(plan, meta);
  const int64_t P = px_count.size(0);
  const auto i32 = px_count.options();
  auto offsets = torch::zeros({P + 1}, i32.dtype(torch::kInt64));
  int64_t M = 0;
  if (P > 0) {
    offsets.narrow(0, 1, P).copy_(torch::cumsum(px_count, 0, torch::kInt64));
    M = offsets[P].item<int64_t>();
  }
  auto pixel = torch::empty({M}, i32);
  auto pair = torch::empty({M}, i32);
  auto weight = torch::empty({M}, i32.dtype(torch::kFloat32));
  if (M > 0) {
    auto packed = torch::empty({M, 2}, i32);
    VIRGI_CUDA_CHECK(launch_raster(kFill, u.num_units, u.units, u.items, u.views, u.item_w, u.item_h,
                                   ranges.data_ptr<int>(), sorted_vals.data_ptr<int>(),
                                   float4_ptr(rec0), float4_ptr(rec1), nullptr, nullptr,
                                   offsets.data_ptr<int64_t>(), int2_ptr(packed), nullptr, 0,
                                   stream));
    VIRGI_CUDA_CHECK(launch_split(M, int2_ptr(packed), rank.data_ptr<int>(), pair.data_ptr<int>(),
                                  weight.data_ptr<float>(), stream));
    VIRGI_CUDA_CHECK(launch_pixel_fill(P, offsets.data_ptr<int64_t>(), pixel.data_ptr<int>(), stream));
  }
  return {pixel, pair, weight, offsets};
}

// Images [P, D] straight from deferred lists (D in 1..8).
torch::Tensor deferred_composite_forward(torch::Tensor colors, torch::Tensor background,
                                         torch::Tensor plan, torch::Tensor meta,
                                         torch::Tensor ranges, torch::Tensor sorted_vals,
                                         torch::Tensor list_pair, torch::Tensor rec0,
                                         torch::Tensor rec1, torch::Tensor transmittance,
                                         torch::Tensor keep_list, torch::Tensor keep_end) {
  check_f32(colors, "colors");
  check_f32(transmittance, "transmittance");
  TORCH_CHECK(colors.dim() == 2 && colors.size(1) >= 1 && colors.size(1) <= 8,
              "deferred composite takes [U, D] colours with D in 1..8");
  const OnDevice on(colors);
  const DeferredLists lists =
      deferred_lists(plan, meta, ranges, sorted_vals, list_pair, rec0, rec1, keep_list, keep_end);
  const int D = static_cast<int>(colors.size(1));
  const float* bg = background_ptr(background, D);
  // pixels of no unit (outside their image) keep T = 1: the background
  torch::Tensor out = bg ? transmittance.unsqueeze(1) * background.reshape({1, D})
                         : torch::zeros({transmittance.size(0), D}, colors.options());
  VIRGI_CUDA_CHECK(
      launch_deferred_forward(lists, D, colors.data_ptr<float>(), bg, out.data_ptr<float>(), on.stream));
  return out;
}

// d colors [U, D] from d images [P, D], straight from deferred lists.
torch::Tensor deferred_composite_backward(torch::Tensor grad_images, int64_t num_pairs,
                                          torch::Tensor plan, torch::Tensor meta,
                                          torch::Tensor ranges, torch::Tensor sorted_vals,
                                          torch::Tensor list_pair, torch::Tensor rec0,
                                          torch::Tensor rec1, torch::Tensor keep_list,
                                          torch::Tensor keep_end) {
  check_f32(grad_images, "grad_images");
  const OnDevice on(grad_images);
  const DeferredLists lists =
      deferred_lists(plan, meta, ranges, sorted_vals, list_pair, rec0, rec1, keep_list, keep_end);
  const int D = static_cast<int>(grad_images.size(1));
  TORCH_CHECK(D >= 1 && D <= 8, "deferred composite takes D in 1..8");
  auto grad_colors = torch::zeros({num_pairs, D}, grad_images.options());
  if (num_pairs == 0) return grad_colors;
  VIRGI_CUDA_CHECK(launch_deferred_backward(lists, D, grad_images.data_ptr<float>(),
                                            grad_colors.data_ptr<float>(), on.stream));
  return grad_colors;
}

// The checks both edit-step bindings make of the arguments they share.
void check_edit_step(const torch::Tensor& colors, const torch::Tensor& pair,
                     const torch::Tensor& weight, const torch::Tensor& pixel_offsets,
                     const torch::Tensor& rows, const torch::Tensor& starts,
                     const torch::Tensor& counter, const torch::Tensor& background,
                     const torch::Tensor& target, const torch::Tensor& loss_weight) {
  check_input(colors, "colors", 3);
  check_i32(pair, "pair");
  check_f32(weight, "weight");
  check_f32(background, "background");
  check_f32(target, "target");
  check_f32(loss_weight, "loss_weight");
  check_i64(pixel_offsets, "pixel_offsets");
  check_i64(rows, "rows");
  check_i64(starts, "starts");
  check_i64(counter, "counter");
  const int64_t R = rows.numel();
  TORCH_CHECK(background.numel() == 3 * R && target.numel() == 3 * R && loss_weight.numel() == R,
              "background and target must be [R, 3] and loss_weight [R] for R rows");
  TORCH_CHECK(starts.numel() >= 2 && counter.numel() == 1, "starts needs num_sets + 1 entries, counter one");
  TORCH_CHECK(pair.numel() == weight.numel(), "pair and weight must have one entry each");
}

// One step of an edit's weighted L1 pixel loss for the pixel set counter % num_sets, and its
// gradient to the colours; advances the counter. The gradient is scattered by one atomic per entry,
// or, given t_start, t_gauss, t_row and t_w (edit_by_gaussian's), gathered per Gaussian. Returns
// {loss [1], grad_colors [U, 4]} (the fourth column is padding).
std::vector<torch::Tensor> edit_l1_step(
    torch::Tensor colors, torch::Tensor pair, torch::Tensor weight, torch::Tensor pixel_offsets,
    torch::Tensor rows, torch::Tensor starts, torch::Tensor counter, torch::Tensor background,
    torch::Tensor target, torch::Tensor loss_weight, int64_t max_rows,
    std::optional<torch::Tensor> t_start, std::optional<torch::Tensor> t_gauss,
    std::optional<torch::Tensor> t_row, std::optional<torch::Tensor> t_w) {
  check_edit_step(colors, pair, weight, pixel_offsets, rows, starts, counter, background, target,
                  loss_weight);
  const bool gathered = t_start.has_value();
  TORCH_CHECK(t_gauss.has_value() == gathered && t_row.has_value() == gathered &&
                  t_w.has_value() == gathered,
              "t_start, t_gauss, t_row and t_w: all four or none");
  const OnDevice on(colors);
  auto loss = torch::zeros({1}, colors.options());
  auto grad_colors = torch::zeros({colors.size(0), 4}, colors.options());
  torch::Tensor signs;
  EditGather gather{};
  if (gathered) {
    check_i64(*t_start, "t_start");
    check_i32(*t_gauss, "t_gauss");
    check_i32(*t_row, "t_row");
    check_f32(*t_w, "t_w");
    TORCH_CHECK(t_start->numel() == starts.numel(), "t_start needs num_sets + 1 entries, as starts");
    TORCH_CHECK(t_gauss->numel() == t_row->numel() && t_row->numel() == t_w->numel(),
                "t_gauss, t_row and t_w must have one entry each");
    signs = torch::empty({rows.numel(), 4}, colors.options().dtype(torch::kInt8));
    gather = {t_start->data_ptr<int64_t>(), t_gauss->data_ptr<int>(), t_row->data_ptr<int>(),
              t_w->data_ptr<float>(), 8 * at::cuda::getCurrentDeviceProperties()->multiProcessorCount,
              reinterpret_cast<char4*>(signs.data_ptr<int8_t>())};
  }
  VIRGI_CUDA_CHECK(launch_edit_l1(max_rows, colors.data_ptr<float>(), pair.data_ptr<int>(),
                                  weight.data_ptr<float>(), pixel_offsets.data_ptr<int64_t>(),
                                  rows.data_ptr<int64_t>(), starts.data_ptr<int64_t>(),
                                  counter.data_ptr<int64_t>(), starts.numel() - 1,
                                  background.data_ptr<float>(), target.data_ptr<float>(),
                                  loss_weight.data_ptr<float>(), gathered ? &gather : nullptr,
                                  loss.data_ptr<float>(), grad_colors.data_ptr<float>(), on.stream));
  return {loss, grad_colors};
}

// The gathered edit step's entries (kernels.h, launch_edit_by_gaussian): every set's entries
// sorted by Gaussian, built once per edit. Returns {t_start [num_sets + 1] int64, t_gauss [nnz]
// int32, t_row [nnz] int32, t_w [nnz] float32 (the entry's weight x its row's loss_weight / 3)}.
std::vector<torch::Tensor> edit_by_gaussian(torch::Tensor pair, torch::Tensor weight,
                                            torch::Tensor pixel_offsets, torch::Tensor rows,
                                            torch::Tensor starts, torch::Tensor loss_weight,
                                            int64_t U) {
  check_i32(pair, "pair");
  check_f32(weight, "weight");
  check_f32(loss_weight, "loss_weight");
  check_i64(pixel_offsets, "pixel_offsets");
  check_i64(rows, "rows");
  check_i64(starts, "starts");
  const int64_t R = rows.numel(), nnz = pair.numel(), S = starts.numel() - 1;
  TORCH_CHECK(S >= 1 && loss_weight.numel() == R && weight.numel() == nnz,
              "starts needs num_sets + 1 entries, loss_weight one per row, weight one per entry");
  constexpr int64_t kMax = std::numeric_limits<int>::max();
  TORCH_CHECK(S * U < kMax && nnz < kMax && R < kMax, "too many entries, rows or bins for int32 indices");
  const OnDevice on(pair);
  const auto i32 = pair.options();
  auto bins = torch::zeros({S * U}, i32);
  VIRGI_CUDA_CHECK(launch_edit_by_gaussian(false, pair.data_ptr<int>(), weight.data_ptr<float>(),
                                           pixel_offsets.data_ptr<int64_t>(), rows.data_ptr<int64_t>(),
                                           R, starts.data_ptr<int64_t>(), S,
                                           loss_weight.data_ptr<float>(), U, bins.data_ptr<int>(),
                                           nullptr, nullptr, nullptr, on.stream));
  auto bin_start = torch::zeros({S * U + 1}, pixel_offsets.options());
  bin_start.slice(0, 1).copy_(bins.cumsum(0));
  bins.copy_(bin_start.slice(0, 0, S * U));  // each bin's first free slot
  auto t_gauss = torch::empty({nnz}, i32);
  auto t_row = torch::empty({nnz}, i32);
  auto t_w = torch::empty({nnz}, weight.options());
  VIRGI_CUDA_CHECK(launch_edit_by_gaussian(true, pair.data_ptr<int>(), weight.data_ptr<float>(),
                                           pixel_offsets.data_ptr<int64_t>(), rows.data_ptr<int64_t>(),
                                           R, starts.data_ptr<int64_t>(), S,
                                           loss_weight.data_ptr<float>(), U, bins.data_ptr<int>(),
                                           t_gauss.data_ptr<int>(), t_row.data_ptr<int>(),
                                           t_w.data_ptr<float>(), on.stream));
  auto t_start = bin_start.index_select(0, torch::arange(S + 1, pixel_offsets.options()) * U);
  return {t_start, t_gauss, t_row, t_w};
}

// What the copied layer's forward reads (both forwards): x [U, Dx] with h_diff at columns hd_offset..
// hd_offset + H, wd [3, H], bd [3], cd and cs [U, 3]. Returns H.
int64_t check_layer_inputs(const torch::Tensor& x, const torch::Tensor& wd, const torch::Tensor& bd,
                           const torch::Tensor& cd, const torch::Tensor& cs, int64_t U, int64_t hd_offset) {
  check_f32(x, "x");
  check_f32(wd, "wd");
  check_f32(bd, "bd");
  check_input(cd, "cd", 3);
  check_input(cs, "cs", 3);
  TORCH_CHECK(x.dim() == 2 && wd.dim() == 2 && wd.size(0) == 3, "x must be [U, Dx], wd [3, H]");
  TORCH_CHECK(x.size(0) == U && cd.size(0) == U && cs.size(0) == U, "x, cd and cs need one row per Gaussian");
  TORCH_CHECK(bd.numel() == 3, "bd must be [3]");
  const int64_t H = wd.size(1);
  TORCH_CHECK(hd_offset >= 0 && hd_offset + H <= x.size(1), "h_diff (columns hd_offset + H) must lie inside x");
  return H;
}

// The edit heads' forward (kernels.h, launch_heads_forward): pre [U, S] = x W1^T + b1, x [U, Dx]
// with h_diff at columns hd_offset.., w2 [S], b2 [1], wd [3, H], bd [3], cd and cs [U, 3]. Returns
// {colors [U, 3], alpha [U], cdp [U, 3]}.
std::vector<torch::Tensor> edit_heads_forward(torch::Tensor pre, torch::Tensor x, torch::Tensor w2,
                                              torch::Tensor b2, torch::Tensor wd, torch::Tensor bd,
                                              torch::Tensor cd, torch::Tensor cs, double k,
                                              int64_t hd_offset) {
  check_f32(pre, "pre");
  check_f32(w2, "w2");
  check_f32(b2, "b2");
  TORCH_CHECK(pre.dim() == 2, "pre must be [U, S]");
  const int64_t U = pre.size(0), S = pre.size(1);
  const int64_t H = check_layer_inputs(x, wd, bd, cd, cs, U, hd_offset), Dx = x.size(1);
  TORCH_CHECK(w2.numel() == S && b2.numel() == 1, "w2 must be [S], b2 [1]");
  const OnDevice on(pre);
  auto colors = torch::empty({U, 3}, pre.options());
  auto alpha = torch::empty({U}, pre.options());
  auto cdp = torch::empty({U, 3}, pre.options());
  VIRGI_CUDA_CHECK(launch_heads_forward(
      pre.data_ptr<float>(), x.data_ptr<float>(), U, static_cast<int>(S), static_cast<int>(Dx),
      static_cast<int>(hd_offset), static_cast<int>(H), w2.data_ptr<float>(), b2.data_ptr<float>(),
      wd.data_ptr<float>(), bd.data_ptr<float>(), cd.data_ptr<float>(), cs.data_ptr<float>(),
      static_cast<float>(k), colors.data_ptr<float>(), alpha.data_ptr<float>(), cdp.data_ptr<float>(),
      on.stream));
  return {colors, alpha, cdp};
}

// The edit heads' backward (kernels.h, launch_heads_backward) from grad_colors [U, 4] and the
// forward's colors, alpha, cdp, with cd, pre and w2. Returns {grad_rows [U, S + 4], sums [2 S + 4]}.
std::vector<torch::Tensor> edit_heads_backward(torch::Tensor grad_colors, torch::Tensor colors,
                                               torch::Tensor alpha, torch::Tensor cdp,
                                               torch::Tensor cd, torch::Tensor pre, torch::Tensor w2) {
  check_input(grad_colors, "grad_colors", 4);
  check_input(colors, "colors", 3);
  check_input(cdp, "cdp", 3);
  check_input(cd, "cd", 3);
  check_f32(alpha, "alpha");
  check_f32(pre, "pre");
  check_f32(w2, "w2");
  TORCH_CHECK(pre.dim() == 2, "pre must be [U, S]");
  const int64_t U = pre.size(0), S = pre.size(1);
  TORCH_CHECK(S <= kMaxHeadsWidth, "the segmentation head is at most ", kMaxHeadsWidth, " wide, got ", S);
  TORCH_CHECK(grad_colors.size(0) == U && colors.size(0) == U && cdp.size(0) == U && cd.size(0) == U &&
                  alpha.numel() == U && w2.numel() == S,
              "every input needs one row per Gaussian, and w2 one entry per hidden unit");
  const OnDevice on(pre);
  auto grad_rows = torch::empty({U, S + 4}, pre.options());
  auto sums = torch::zeros({2 * S + 4}, pre.options());
  VIRGI_CUDA_CHECK(launch_heads_backward(
      grad_colors.data_ptr<float>(), colors.data_ptr<float>(), alpha.data_ptr<float>(),
      cdp.data_ptr<float>(), cd.data_ptr<float>(), pre.data_ptr<float>(), w2.data_ptr<float>(), U,
      static_cast<int>(S), grad_rows.data_ptr<float>(), sums.data_ptr<float>(), on.stream));
  return {grad_rows, sums};
}

// The staged recipe's copied layer (kernels.h, launch_layer_forward): alpha [U], x [U, Dx] with h_diff
// at columns hd_offset.., wd [3, H], bd [3], cd and cs [U, 3]. Returns {colors [U, 3], cdp [U, 3]}.
std::vector<torch::Tensor> edit_layer_forward(torch::Tensor alpha, torch::Tensor x, torch::Tensor wd,
                                              torch::Tensor bd, torch::Tensor cd, torch::Tensor cs, double k,
                                              int64_t hd_offset) {
  check_f32(alpha, "alpha");
  const int64_t U = alpha.numel();
  const int64_t H = check_layer_inputs(x, wd, bd, cd, cs, U, hd_offset);
  const int64_t Dx = x.size(1);
  const OnDevice on(x);
  auto colors = torch::empty({U, 3}, x.options());
  auto cdp = torch::empty({U, 3}, x.options());
  VIRGI_CUDA_CHECK(launch_layer_forward(alpha.data_ptr<float>(), x.data_ptr<float>(), U, static_cast<int>(Dx),
                                        static_cast<int>(hd_offset), static_cast<int>(H), wd.data_ptr<float>(),
                                        bd.data_ptr<float>(), cd.data_ptr<float>(), cs.data_ptr<float>(),
                                        static_cast<float>(k), colors.data_ptr<float>(), cdp.data_ptr<float>(),
                                        on.stream));
  return {colors, cdp};
}

// The staged recipe's copied layer's backward (kernels.h, launch_layer_backward) from grad_colors
// [U, 4] and the forward's colors, with alpha [U]. Returns {grad_rows [U, 4], sums [4]}.
std::vector<torch::Tensor> edit_layer_backward(torch::Tensor grad_colors, torch::Tensor colors, torch::Tensor alpha) {
  check_input(grad_colors, "grad_colors", 4);
  check_input(colors, "colors", 3);
  check_f32(alpha, "alpha");
  const int64_t U = colors.size(0);
  TORCH_CHECK(grad_colors.size(0) == U && alpha.numel() == U, "every input needs one row per Gaussian");
  const OnDevice on(colors);
  auto grad_rows = torch::empty({U, 4}, colors.options());
  auto sums = torch::zeros({4}, colors.options());
  VIRGI_CUDA_CHECK(launch_layer_backward(grad_colors.data_ptr<float>(), colors.data_ptr<float>(),
                                         alpha.data_ptr<float>(), U, grad_rows.data_ptr<float>(),
                                         sums.data_ptr<float>(), on.stream));
  return {grad_rows, sums};
}

// Whether classifier_gradients takes a head of W hidden units over D inputs on the device: the kernel
// takes its shape and a block's shared memory fits the device's opt-in limit.
bool classifier_fits(int64_t D, int64_t W, int64_t device) {
  if (D <= 0 || W <= 0 || D > (int64_t{1} << 20) || W > (int64_t{1} << 20)) return false;
  if (!classifier_takes(static_cast<int>(D), static_cast<int>(W))) return false;
  int optin = 0;
  VIRGI_CUDA_CHECK(cudaDeviceGetAttribute(&optin, cudaDevAttrMaxSharedMemoryPerBlockOptin, static_cast<int>(device)));
  return classifier_shared_bytes(static_cast<int>(D), static_cast<int>(W)) <= optin;
}

// The staged classifier's gradient (kernels.h, launch_classifier_gradients): x [S, D], y [S] (or
// [S, 1]), w1 [W, D], b1 [W], w2 [1, W], b2 [1]. Returns grads [W D + 2 W + 1]: dW1, db1, dw2, db2.
torch::Tensor classifier_gradients(torch::Tensor x, torch::Tensor y, torch::Tensor w1, torch::Tensor b1,
                                   torch::Tensor w2, torch::Tensor b2) {
  check_f32(x, "x");
  check_f32(y, "y");
  check_f32(w1, "w1");
  check_f32(b1, "b1");
  check_f32(w2, "w2");
  check_f32(b2, "b2");
  TORCH_CHECK(x.dim() == 2 && w1.dim() == 2 && w1.size(1) == x.size(1), "x must be [S, D] and w1 [W, D]");
  const int64_t S = x.size(0), D = x.size(1), W = w1.size(0);
  TORCH_CHECK(y.numel() == S && b1.numel() == W && w2.numel() == W && b2.numel() == 1,
              "y must hold one label per sample, b1 and w2 one entry per hidden unit, b2 one");
  const OnDevice on(x);
  TORCH_CHECK(S < (int64_t{1} << 31) && classifier_fits(D, W, x.get_device()),
              "the classifier's head is too large for the written-out step (", W, " x ", D, ")");
  // every entry is written by the sum kernel, which runs wherever there is a sample
  auto grads = S == 0 ? torch::zeros({W * D + 2 * W + 1}, x.options()) : torch::empty({W * D + 2 * W + 1}, x.options());
  auto partials = torch::empty({classifier_partial_rows(S), W * D + 2 * W + 1}, x.options());
  VIRGI_CUDA_CHECK(launch_classifier_gradients(
      x.data_ptr<float>(), y.data_ptr<float>(), static_cast<int>(S), static_cast<int>(D), static_cast<int>(W),
      w1.data_ptr<float>(), b1.data_ptr<float>(), w2.data_ptr<float>(), b2.data_ptr<float>(),
      partials.data_ptr<float>(), grads.data_ptr<float>(), on.stream));
  return grads;
}

}  // namespace virgi

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "virgi-ns frozen-geometry tile rasterizer";
  m.def("rasterize_contributions", &virgi::rasterize_contributions,
        "Contribution lists of N Gaussians for a request of equally sized items");
  m.def("composite_forward", &virgi::composite_forward, "Segmented sum of weighted pair colours");
  m.def("heaviest_pair", &virgi::heaviest_pair, "Each pixel's pair of largest weight");
  m.def("composite_backward", &virgi::composite_backward, "Gradient of composite_forward to colours");
  m.def("composite_backward_tiles", &virgi::composite_backward_tiles,
        "Gradient of composite_forward to colours, per tile from the tile lists");
  m.def("materialize_lists", &virgi::materialize_lists, "Entries of deferred lists");
  m.def("deferred_composite_forward", &virgi::deferred_composite_forward,
        "Composite straight from deferred tile lists");
  m.def("deferred_composite_backward", &virgi::deferred_composite_backward,
        "Gradient of deferred_composite_forward to colours");
  m.def("edit_l1_step", &virgi::edit_l1_step,
        "One step of an edit's weighted L1 pixel loss and its gradient to the colours, scattered, or "
        "gathered over the entries sorted by Gaussian (edit_by_gaussian's) where given");
  m.def("edit_by_gaussian", &virgi::edit_by_gaussian,
        "An edit's pixel sets' entries sorted by Gaussian, for edit_l1_step's gathered gradient");
  m.def("edit_heads_forward", &virgi::edit_heads_forward, "The edit heads' colours from pre = x W1^T + b1");
  m.def("edit_heads_backward", &virgi::edit_heads_backward,
        "The edit heads' gradients from the loss's gradient to the colours");
  m.def("edit_layer_forward", &virgi::edit_layer_forward,
        "The staged recipe's colours from the copied layer, the segmentation fixed");
  m.def("edit_layer_backward", &virgi::edit_layer_backward,
        "The staged recipe's gradient to the copied layer's output from the loss's gradient to the colours");
  m.def("classifier_fits", &virgi::classifier_fits,
        "Whether classifier_gradients takes a head of W hidden units over D inputs on a device");
  m.def("classifier_gradients", &virgi::classifier_gradients,
        "The staged classifier's gradient of its mean binary cross-entropy, flat");
}
