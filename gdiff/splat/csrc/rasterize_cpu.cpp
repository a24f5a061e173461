// Tile-based CPU rasterization of projected 2D Gaussians: forward and backward kernels.
//
// Same maths as gdiff/splat/rasterize.py (rasterize_torch), which is the reference:
//   sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,  d = mean2d - pixel centre (i + 0.5, j + 0.5)
//   a Gaussian touches a pixel iff sigma <= 4.5 (3-sigma ellipse)
//   alpha = min(0.99, opacity exp(-sigma)); alpha < 1/255 skipped
//   front-to-back in depth order; a pixel stops before the Gaussian that brings T to <= 1e-4
//   out = sum_i c_i alpha_i T_i (no background), render alpha = 1 - T_final
// The image is cut into square tiles; each Gaussian is listed (in depth order) in the tiles its
// 3-sigma bounding box overlaps. Inside a tile the loop runs over Gaussians and, for each, over
// the pixels of its bounding box, so small Gaussians cost only their footprint. Tiles are
// shared among std::threads (at::get_num_threads() of them); gradients are accumulated in
// per-thread buffers and summed at the end, with a fixed tile-to-thread split so that they
// are the same on every run (see run_tasks).
//
// Compiled with -ffp-contract=off so that sigma rounds exactly as in the torch path.

// Only the ATen headers in use are included (not <torch/extension.h>): it halves compile time.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/full.h>
#include <ATen/ops/ones.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

namespace {

constexpr double kSigmaMax = 4.5;
constexpr double kAlphaMax = 0.99;
constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kTMin = 1e-4;

// Run fn(task, thread_id) for task in [0, n_tasks) on up to at::get_num_threads() threads.
// Dynamic: tasks are handed out as threads free up (tiles have very uneven cost); for kernels
// whose per-thread results do not depend on which thread ran a task (the forward pass).
// Static (dynamic = false): thread k runs tasks k, k + n, k + 2n, ... in order, so per-thread
// sums are formed in the same order on every run with the same thread count (the backward
// pass: training and its resume from a checkpoint are then bitwise reproducible).
template <typename F>
void run_tasks(int64_t n_tasks, int n_threads, F fn, bool dynamic = true) {
  n_threads = std::max(1, std::min<int>(n_threads, (int)std::max<int64_t>(n_tasks, 1)));
  std::atomic<int64_t> next{0};
  const int nt = n_threads;
  auto worker = [&](int tid) {
    if (!dynamic) {
      for (int64_t t = tid; t < n_tasks; t += nt) fn(t, tid);
      return;
    }
    for (int64_t t = next.fetch_add(1); t < n_tasks; t = next.fetch_add(1)) fn(t, tid);
  };
  if (n_threads == 1) {
    worker(0);
    return;
  }
  std::vector<std::thread> pool;
  pool.reserve(n_threads - 1);
  for (int i = 1; i < n_threads; ++i) pool.emplace_back(worker, i);
  worker(0);
  for (auto& th : pool) th.join();
}

int num_threads() { return std::max(1, at::get_num_threads()); }

// Pixel index range [lo, hi] of the 3-sigma box of a Gaussian along one axis (not clipped).
// Clamped to +-1e9 before the cast so huge or NaN values stay defined (and off the image).
template <typename scalar_t>
inline void box_range(scalar_t m, scalar_t e, int64_t& lo, int64_t& hi) {
  const double lim = 1e9;
  lo = (int64_t)std::fmax(-lim, std::fmin(lim, (double)std::floor(m - e - (scalar_t)0.5)));
  hi = (int64_t)std::fmax(-lim, std::fmin(lim, (double)std::ceil(m + e - (scalar_t)0.5)));
  if (std::isnan((double)m) || std::isnan((double)e)) { lo = 1; hi = 0; }
}

// Largest sigma at which a Gaussian of opacity op can still reach alpha >= 1/255: ln(255 op)
// (above it op exp(-sigma) < 1/255), with 1e-3 of slack so that the test only skips pixels
// the exact alpha test would reject anyway; it saves their exp. Negative: no pixel reached.
template <typename scalar_t>
inline scalar_t sigma_reach(scalar_t op) {
  return (scalar_t)(std::log(std::max((double)op, 1e-30) / kAlphaMin) + 1e-3);
}

struct Bins {
  at::Tensor offsets;  // [C * n_tiles + 1] int64: list of tile t is ids[offsets[t]:offsets[t+1]]
  at::Tensor ids;      // [total] int32 Gaussian index within its camera, in depth order
};

template <typename scalar_t>
Bins bin_gaussians(const at::Tensor& means2d, const at::Tensor& extents,
                   const at::Tensor& visible, const at::Tensor& order, int64_t W, int64_t H,
                   int64_t tile) {
  const int64_t C = means2d.size(0), N = means2d.size(1);
  const int64_t tx_n = (W + tile - 1) / tile, ty_n = (H + tile - 1) / tile, nt = tx_n * ty_n;
  auto m = means2d.accessor<scalar_t, 3>();
  auto e = extents.accessor<scalar_t, 3>();
  auto v = visible.accessor<bool, 2>();
  auto o = order.accessor<int64_t, 2>();
  at::Tensor offsets = at::zeros({C * nt + 1}, at::kLong);
  int64_t* off = offsets.data_ptr<int64_t>();
  // tile rectangle per (camera, Gaussian); empty rectangles have x0 > x1
  std::vector<int32_t> rect(C * N * 4);
  for (int64_t c = 0; c < C; ++c) {
    for (int64_t n = 0; n < N; ++n) {
      int32_t* r = &rect[(c * N + n) * 4];
      r[0] = 1; r[1] = 0; r[2] = 1; r[3] = 0;
      if (!v[c][n]) continue;
      int64_t x0, x1, y0, y1;
      box_range<scalar_t>(m[c][n][0], e[c][n][0], x0, x1);
      box_range<scalar_t>(m[c][n][1], e[c][n][1], y0, y1);
      x0 = std::max<int64_t>(x0, 0); y0 = std::max<int64_t>(y0, 0);
      x1 = std::min<int64_t>(x1, W - 1); y1 = std::min<int64_t>(y1, H - 1);
      if (x0 > x1 || y0 > y1) continue;
      r[0] = (int32_t)(x0 / tile); r[1] = (int32_t)(x1 / tile);
      r[2] = (int32_t)(y0 / tile); r[3] = (int32_t)(y1 / tile);
      for (int64_t ty = r[2]; ty <= r[3]; ++ty)
        for (int64_t tx = r[0]; tx <= r[1]; ++tx) off[c * nt + ty * tx_n + tx + 1] += 1;
    }
  }
  for (int64_t t = 0; t < C * nt; ++t) off[t + 1] += off[t];
  at::Tensor ids = at::empty({off[C * nt]}, at::kInt);
  int32_t* id = ids.data_ptr<int32_t>();
  std::vector<int64_t> fill(off, off + C * nt);
  for (int64_t c = 0; c < C; ++c) {
    for (int64_t k = 0; k < N; ++k) {
      const int64_t n = o[c][k];
      const int32_t* r = &rect[(c * N + n) * 4];
      for (int64_t ty = r[2]; ty <= r[3]; ++ty)
        for (int64_t tx = r[0]; tx <= r[1]; ++tx) id[fill[c * nt + ty * tx_n + tx]++] = (int32_t)n;
    }
  }
  return {offsets, ids};
}

template <typename scalar_t>
std::vector<at::Tensor> forward_impl(const at::Tensor& means2d, const at::Tensor& conics,
                                        const at::Tensor& colors, const at::Tensor& opacities,
                                        const at::Tensor& extents, const at::Tensor& visible,
                                        const at::Tensor& order, int64_t W, int64_t H,
                                        int64_t tile) {
  const int64_t C = means2d.size(0), N = means2d.size(1), D = colors.size(2);
  Bins bins = bin_gaussians<scalar_t>(means2d, extents, visible, order, W, H, tile);
  const int64_t tx_n = (W + tile - 1) / tile, ty_n = (H + tile - 1) / tile, nt = tx_n * ty_n;
  auto opts = means2d.options();
  at::Tensor out = at::zeros({C, H, W, D}, opts);
  at::Tensor T_final = at::ones({C, H, W}, opts);
  at::Tensor last = at::full({C, H, W}, -1, at::kInt);
  const scalar_t* M = means2d.data_ptr<scalar_t>();
  const scalar_t* Q = conics.data_ptr<scalar_t>();
  const scalar_t* F = colors.data_ptr<scalar_t>();
  const scalar_t* O = opacities.data_ptr<scalar_t>();
  const scalar_t* E = extents.data_ptr<scalar_t>();
  const int64_t* off = bins.offsets.data_ptr<int64_t>();
  const int32_t* ids = bins.ids.data_ptr<int32_t>();
  scalar_t* out_p = out.data_ptr<scalar_t>();
  scalar_t* Tf_p = T_final.data_ptr<scalar_t>();
  int32_t* last_p = last.data_ptr<int32_t>();
  const int nth = num_threads();
  const int64_t P = tile * tile;
  std::vector<std::vector<scalar_t>> scratch(nth);

  run_tasks(C * nt, nth, [&](int64_t task, int tid) {
    const int64_t c = task / nt, t = task % nt;
    const int64_t px0 = (t % tx_n) * tile, py0 = (t / tx_n) * tile;
    const int64_t tw = std::min(tile, W - px0), th = std::min(tile, H - py0);
    std::vector<scalar_t>& buf = scratch[tid];
    buf.assign(P * (D + 1), 0);
    scalar_t* acc = buf.data();
    scalar_t* T = acc + P * D;
    std::vector<int32_t> lastk(P, -1);
    std::vector<uint8_t> done(P, 0);
    for (int64_t q = 0; q < P; ++q) T[q] = 1;
    int64_t n_done = 0;
    const int64_t n_pix = tw * th;
    for (int64_t k = off[c * nt + t]; k < off[c * nt + t + 1] && n_done < n_pix; ++k) {
      const int64_t g = (int64_t)c * N + ids[k];
      const scalar_t mx = M[g * 2], my = M[g * 2 + 1];
      int64_t x0, x1, y0, y1;
      box_range<scalar_t>(mx, E[g * 2], x0, x1);
      box_range<scalar_t>(my, E[g * 2 + 1], y0, y1);
      x0 = std::max(x0, px0); x1 = std::min(x1, px0 + tw - 1);
      y0 = std::max(y0, py0); y1 = std::min(y1, py0 + th - 1);
      if (x0 > x1 || y0 > y1) continue;
      const scalar_t a = Q[g * 3], b = Q[g * 3 + 1], cc = Q[g * 3 + 2], op = O[g];
      const scalar_t s_max = std::min((scalar_t)kSigmaMax, sigma_reach(op));
      if (!(s_max >= 0)) continue;
      const scalar_t* col = F + g * D;
      for (int64_t j = y0; j <= y1; ++j) {
        const scalar_t dy = my - ((scalar_t)j + (scalar_t)0.5);
        for (int64_t i = x0; i <= x1; ++i) {
          const int64_t q = (j - py0) * tile + (i - px0);
          if (done[q]) continue;
          const scalar_t dx = mx - ((scalar_t)i + (scalar_t)0.5);
          const scalar_t sigma = (scalar_t)0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy;
          if (sigma > s_max || sigma < 0) continue;
          const scalar_t alpha = std::min((scalar_t)kAlphaMax, op * std::exp(-sigma));
          if (alpha < (scalar_t)kAlphaMin) continue;
          const scalar_t nT = T[q] * (1 - alpha);
          if (nT <= (scalar_t)kTMin) {
            done[q] = 1;
            ++n_done;
            continue;
          }
          const scalar_t w = alpha * T[q];
          scalar_t* aq = acc + q * D;
          for (int64_t d = 0; d < D; ++d) aq[d] += w * col[d];
          T[q] = nT;
          lastk[q] = (int32_t)k;
        }
      }
    }
    for (int64_t j = 0; j < th; ++j) {
      for (int64_t i = 0; i < tw; ++i) {
        const int64_t q = j * tile + i;
        const int64_t pix = (c * H + py0 + j) * W + px0 + i;
        std::copy(acc + q * D, acc + q * D + D, out_p + pix * D);
        Tf_p[pix] = T[q];
        last_p[pix] = lastk[q];
      }
    }
  });
  at::Tensor alpha = T_final.neg().add_(1).unsqueeze(-1);
  return {out, alpha, T_final, last, bins.offsets, bins.ids};
}

template <typename scalar_t>
std::vector<at::Tensor> backward_impl(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& colors,
    const at::Tensor& opacities, const at::Tensor& extents, const at::Tensor& offsets,
    const at::Tensor& ids_t, const at::Tensor& T_final, const at::Tensor& last,
    const at::Tensor& grad_out, const at::Tensor& grad_alpha, int64_t W, int64_t H,
    int64_t tile, bool absgrad) {
  const int64_t C = means2d.size(0), N = means2d.size(1), D = colors.size(2);
  const int64_t tx_n = (W + tile - 1) / tile, ty_n = (H + tile - 1) / tile, nt = tx_n * ty_n;
  const int nth = num_threads();
  const int64_t G = C * N;
  const int64_t stride = 2 + 3 + 1 + D + (absgrad ? 2 : 0);  // per-Gaussian gradient record
  at::Tensor acc_all = at::zeros({nth, G, stride}, means2d.options());
  const scalar_t* M = means2d.data_ptr<scalar_t>();
  const scalar_t* Q = conics.data_ptr<scalar_t>();
  const scalar_t* F = colors.data_ptr<scalar_t>();
  const scalar_t* O = opacities.data_ptr<scalar_t>();
  const scalar_t* E = extents.data_ptr<scalar_t>();
  const int64_t* off = offsets.data_ptr<int64_t>();
  const int32_t* ids = ids_t.data_ptr<int32_t>();
  const scalar_t* Tf = T_final.data_ptr<scalar_t>();
  const int32_t* LK = last.data_ptr<int32_t>();
  const scalar_t* GO = grad_out.data_ptr<scalar_t>();
  const scalar_t* GA = grad_alpha.data_ptr<scalar_t>();
  scalar_t* ACC = acc_all.data_ptr<scalar_t>();
  const int64_t P = tile * tile;

  run_tasks(C * nt, nth, [&](int64_t task, int tid) {
    const int64_t c = task / nt, t = task % nt;
    const int64_t px0 = (t % tx_n) * tile, py0 = (t / tx_n) * tile;
    const int64_t tw = std::min(tile, W - px0), th = std::min(tile, H - py0);
    scalar_t* mine = ACC + (int64_t)tid * G * stride;
    std::vector<scalar_t> T(P, 1), Tfin(P, 1), S(P * D, 0), go(P * D, 0), ga(P, 0);
    std::vector<int32_t> lastk(P, -1);
    int64_t kmax = -1;
    for (int64_t j = 0; j < th; ++j) {
      for (int64_t i = 0; i < tw; ++i) {
        const int64_t q = j * tile + i;
        const int64_t pix = (c * H + py0 + j) * W + px0 + i;
        T[q] = Tfin[q] = Tf[pix];
        lastk[q] = LK[pix];
        kmax = std::max<int64_t>(kmax, LK[pix]);
        std::copy(GO + pix * D, GO + pix * D + D, go.data() + q * D);
        ga[q] = GA[pix];
      }
    }
    const int64_t k0 = off[c * nt + t];
    for (int64_t k = kmax; k >= k0; --k) {
      const int64_t n = ids[k];
      const int64_t g = c * N + n;
      const scalar_t mx = M[g * 2], my = M[g * 2 + 1];
      int64_t x0, x1, y0, y1;
      box_range<scalar_t>(mx, E[g * 2], x0, x1);
      box_range<scalar_t>(my, E[g * 2 + 1], y0, y1);
      x0 = std::max(x0, px0); x1 = std::min(x1, px0 + tw - 1);
      y0 = std::max(y0, py0); y1 = std::min(y1, py0 + th - 1);
      if (x0 > x1 || y0 > y1) continue;
      const scalar_t a = Q[g * 3], b = Q[g * 3 + 1], cc = Q[g * 3 + 2], op = O[g];
      const scalar_t s_max = std::min((scalar_t)kSigmaMax, sigma_reach(op));
      if (!(s_max >= 0)) continue;
      const scalar_t* col = F + g * D;
      scalar_t gm[2] = {0, 0}, gq[3] = {0, 0, 0}, gop = 0, gabs[2] = {0, 0};
      scalar_t* gcol = mine + g * stride + 6;
      for (int64_t j = y0; j <= y1; ++j) {
        const scalar_t dy = my - ((scalar_t)j + (scalar_t)0.5);
        for (int64_t i = x0; i <= x1; ++i) {
          const int64_t q = (j - py0) * tile + (i - px0);
          if (k > lastk[q]) continue;
          const scalar_t dx = mx - ((scalar_t)i + (scalar_t)0.5);
          const scalar_t sigma = (scalar_t)0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy;
          if (sigma > s_max || sigma < 0) continue;
          const scalar_t gauss = std::exp(-sigma);
          const scalar_t raw = op * gauss;
          const scalar_t alpha = std::min((scalar_t)kAlphaMax, raw);
          if (alpha < (scalar_t)kAlphaMin) continue;
          const scalar_t inv1m = 1 / (1 - alpha);
          const scalar_t Ti = T[q] * inv1m;  // transmittance in front of this Gaussian
          const scalar_t w = alpha * Ti;
          scalar_t* Sq = S.data() + q * D;
          const scalar_t* gq_out = go.data() + q * D;
          scalar_t dL_dalpha = 0;
          for (int64_t d = 0; d < D; ++d) {
            gcol[d] += w * gq_out[d];
            dL_dalpha += gq_out[d] * (col[d] * Ti - Sq[d] * inv1m);
            Sq[d] += col[d] * w;
          }
          dL_dalpha += ga[q] * Tfin[q] * inv1m;  // render alpha = 1 - T_final
          T[q] = Ti;
          if (raw >= (scalar_t)kAlphaMax) continue;  // clamped: no gradient through alpha
          const scalar_t dL_dsigma = -alpha * dL_dalpha;
          gop += gauss * dL_dalpha;
          const scalar_t gmx = dL_dsigma * (a * dx + b * dy);
          const scalar_t gmy = dL_dsigma * (b * dx + cc * dy);
          gm[0] += gmx;
          gm[1] += gmy;
          gabs[0] += std::abs(gmx);
          gabs[1] += std::abs(gmy);
          gq[0] += dL_dsigma * (scalar_t)0.5 * dx * dx;
          gq[1] += dL_dsigma * dx * dy;
          gq[2] += dL_dsigma * (scalar_t)0.5 * dy * dy;
        }
      }
      scalar_t* r = mine + g * stride;
      r[0] += gm[0]; r[1] += gm[1];
      r[2] += gq[0]; r[3] += gq[1]; r[4] += gq[2];
      r[5] += gop;
      if (absgrad) { r[6 + D] += gabs[0]; r[7 + D] += gabs[1]; }
    }
  }, /*dynamic=*/false);
  at::Tensor total = acc_all.sum(0);  // [G, stride]
  at::Tensor g_m = total.narrow(1, 0, 2).reshape({C, N, 2});
  at::Tensor g_q = total.narrow(1, 2, 3).reshape({C, N, 3});
  at::Tensor g_o = total.narrow(1, 5, 1).reshape({C, N});
  at::Tensor g_c = total.narrow(1, 6, D).reshape({C, N, D});
  at::Tensor g_abs = absgrad ? total.narrow(1, 6 + D, 2).reshape({C, N, 2})
                                : at::zeros({0}, means2d.options());
  return {g_m, g_q, g_c, g_o, g_abs};
}


// The compositing weights w = alpha_i T_i of every (pixel, Gaussian) pair the forward pass
// blends (same tests, same order, same early stop), for one camera: the sparse [H*W, N]
// matrix that maps per-Gaussian features to the image when the geometry is fixed. Returned
// row-compressed: counts [H*W] int32 pairs per pixel (row-major), gid [P] int32 and weight
// [P] pixel by pixel (front to back within a pixel), alpha [H*W] = 1 - T_final. With
// tolerance > 0 each pixel drops its smallest weights (ties: the front one first) as long as
// their sum stays <= tolerance; alpha still counts them.
template <typename scalar_t>
std::vector<at::Tensor> weights_impl(const at::Tensor& means2d, const at::Tensor& conics,
                                     const at::Tensor& opacities, const at::Tensor& extents,
                                     const at::Tensor& visible, const at::Tensor& order,
                                     int64_t W, int64_t H, int64_t tile, double tolerance) {
  const int64_t N = means2d.size(1);
  Bins bins = bin_gaussians<scalar_t>(means2d, extents, visible, order, W, H, tile);
  const int64_t tx_n = (W + tile - 1) / tile, ty_n = (H + tile - 1) / tile, nt = tx_n * ty_n;
  at::Tensor counts = at::zeros({H * W}, at::kInt);
  at::Tensor alpha = at::zeros({H * W}, at::kFloat);
  const scalar_t* M = means2d.data_ptr<scalar_t>();
  const scalar_t* Q = conics.data_ptr<scalar_t>();
  const scalar_t* O = opacities.data_ptr<scalar_t>();
  const scalar_t* E = extents.data_ptr<scalar_t>();
  const int64_t* off = bins.offsets.data_ptr<int64_t>();
  const int32_t* ids = bins.ids.data_ptr<int32_t>();
  int32_t* cnt_p = counts.data_ptr<int32_t>();
  float* alpha_p = alpha.data_ptr<float>();
  const int64_t P = tile * tile;
  // per tile: its pairs grouped by tile pixel (front to back within a pixel)
  std::vector<std::vector<int32_t>> tile_gid(nt);
  std::vector<std::vector<float>> tile_w(nt);

  run_tasks(nt, num_threads(), [&](int64_t t, int) {
    const int64_t px0 = (t % tx_n) * tile, py0 = (t / tx_n) * tile;
    const int64_t tw = std::min(tile, W - px0), th = std::min(tile, H - py0);
    std::vector<scalar_t> T(P, 1);
    std::vector<uint8_t> done(P, 0);
    std::vector<int32_t> pq, pg;  // pairs in traversal order: tile pixel, Gaussian
    std::vector<float> pw;
    int64_t n_done = 0;
    const int64_t n_pix = tw * th;
    for (int64_t k = off[t]; k < off[t + 1] && n_done < n_pix; ++k) {
      const int64_t g = ids[k];
      const scalar_t mx = M[g * 2], my = M[g * 2 + 1];
      int64_t x0, x1, y0, y1;
      box_range<scalar_t>(mx, E[g * 2], x0, x1);
      box_range<scalar_t>(my, E[g * 2 + 1], y0, y1);
      x0 = std::max(x0, px0); x1 = std::min(x1, px0 + tw - 1);
      y0 = std::max(y0, py0); y1 = std::min(y1, py0 + th - 1);
      if (x0 > x1 || y0 > y1) continue;
      const scalar_t a = Q[g * 3], b = Q[g * 3 + 1], cc = Q[g * 3 + 2], op = O[g];
      const scalar_t s_max = std::min((scalar_t)kSigmaMax, sigma_reach(op));
      if (!(s_max >= 0)) continue;
      for (int64_t j = y0; j <= y1; ++j) {
        const scalar_t dy = my - ((scalar_t)j + (scalar_t)0.5);
        for (int64_t i = x0; i <= x1; ++i) {
          const int64_t q = (j - py0) * tile + (i - px0);
          if (done[q]) continue;
          const scalar_t dx = mx - ((scalar_t)i + (scalar_t)0.5);
          const scalar_t sigma = (scalar_t)0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy;
          if (sigma > s_max || sigma < 0) continue;
          const scalar_t al = std::min((scalar_t)kAlphaMax, op * std::exp(-sigma));
          if (al < (scalar_t)kAlphaMin) continue;
          const scalar_t nT = T[q] * (1 - al);
          if (nT <= (scalar_t)kTMin) {
            done[q] = 1;
            ++n_done;
            continue;
          }
          pq.push_back((int32_t)q);
          pg.push_back((int32_t)g);
          pw.push_back((float)(al * T[q]));
          T[q] = nT;
        }
      }
    }
    // stable counting sort of the pairs by tile pixel
    std::vector<int64_t> start(P + 1, 0);
    for (int32_t q : pq) ++start[q + 1];
    for (int64_t q = 0; q < P; ++q) start[q + 1] += start[q];
    std::vector<int32_t>& og = tile_gid[t];
    std::vector<float>& ow = tile_w[t];
    og.resize(pq.size());
    ow.resize(pq.size());
    std::vector<int64_t> fill(start.begin(), start.end() - 1);
    for (size_t p = 0; p < pq.size(); ++p) {
      const int64_t d = fill[pq[p]]++;
      og[d] = pg[p];
      ow[d] = pw[p];
    }
    std::vector<int64_t> kept(P, 0);
    if (tolerance > 0) {  // drop each pixel's faintest pairs, compacting the runs in place
      std::vector<int32_t> idx;
      std::vector<uint8_t> drop;
      int64_t dst = 0;
      for (int64_t q = 0; q < P; ++q) {
        const int64_t b = start[q], n = start[q + 1] - b;
        idx.resize(n);
        drop.assign(n, 0);
        for (int64_t u = 0; u < n; ++u) idx[u] = (int32_t)u;
        std::stable_sort(idx.begin(), idx.end(),
                         [&](int32_t u, int32_t v) { return ow[b + u] < ow[b + v]; });
        double sum = 0;
        for (int64_t u = 0; u < n; ++u) {
          sum += (double)ow[b + idx[u]];
          if (sum > tolerance) break;
          drop[idx[u]] = 1;
        }
        for (int64_t u = 0; u < n; ++u) {
          if (drop[u]) continue;
          og[dst] = og[b + u];
          ow[dst] = ow[b + u];
          ++dst;
          ++kept[q];
        }
      }
      og.resize(dst);
      ow.resize(dst);
    } else {
      for (int64_t q = 0; q < P; ++q) kept[q] = start[q + 1] - start[q];
    }
    for (int64_t j = 0; j < th; ++j) {
      for (int64_t i = 0; i < tw; ++i) {
        const int64_t q = j * tile + i;
        const int64_t pix = (py0 + j) * W + px0 + i;
        cnt_p[pix] = (int32_t)kept[q];
        alpha_p[pix] = (float)(1 - T[q]);
      }
    }
  });
  // pixel-major offsets, then every tile copies its runs into place
  std::vector<int64_t> pix_off(H * W + 1, 0);
  for (int64_t p = 0; p < H * W; ++p) pix_off[p + 1] = pix_off[p] + cnt_p[p];
  at::Tensor gid = at::empty({pix_off[H * W]}, at::kInt);
  at::Tensor weight = at::empty({pix_off[H * W]}, at::kFloat);
  int32_t* gid_p = gid.data_ptr<int32_t>();
  float* w_p = weight.data_ptr<float>();
  run_tasks(nt, num_threads(), [&](int64_t t, int) {
    const int64_t px0 = (t % tx_n) * tile, py0 = (t / tx_n) * tile;
    const int64_t tw = std::min(tile, W - px0), th = std::min(tile, H - py0);
    int64_t src = 0;
    for (int64_t j = 0; j < th; ++j) {
      for (int64_t i = 0; i < tw; ++i) {
        const int64_t pix = (py0 + j) * W + px0 + i;
        const int64_t n = cnt_p[pix];
        std::copy(tile_gid[t].begin() + src, tile_gid[t].begin() + src + n, gid_p + pix_off[pix]);
        std::copy(tile_w[t].begin() + src, tile_w[t].begin() + src + n, w_p + pix_off[pix]);
        src += n;
      }
    }
    std::vector<int32_t>().swap(tile_gid[t]);
    std::vector<float>().swap(tile_w[t]);
  });
  (void)N;
  return {counts, gid, weight, alpha};
}

void check(const at::Tensor& t, const char* name, int64_t dim) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  TORCH_CHECK(t.dim() == dim, name, " must have ", dim, " dimensions");
}

}  // namespace

std::vector<at::Tensor> rasterize_forward(at::Tensor means2d, at::Tensor conics,
                                             at::Tensor colors, at::Tensor opacities,
                                             at::Tensor extents, at::Tensor visible,
                                             at::Tensor order, int64_t width, int64_t height,
                                             int64_t tile) {
  check(means2d, "means2d", 3); check(conics, "conics", 3); check(colors, "colors", 3);
  check(opacities, "opacities", 2); check(extents, "extents", 3); check(visible, "visible", 2);
  check(order, "order", 2);
  TORCH_CHECK(visible.scalar_type() == at::kBool && order.scalar_type() == at::kLong,
              "visible must be bool and order int64");
  std::vector<at::Tensor> res;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "gdiff_rasterize_forward", [&] {
    res = forward_impl<scalar_t>(means2d, conics, colors, opacities, extents, visible, order,
                                 width, height, tile);
  });
  return res;
}

std::vector<at::Tensor> rasterize_backward(
    at::Tensor means2d, at::Tensor conics, at::Tensor colors, at::Tensor opacities,
    at::Tensor extents, at::Tensor offsets, at::Tensor ids, at::Tensor T_final,
    at::Tensor last, at::Tensor grad_out, at::Tensor grad_alpha, int64_t width,
    int64_t height, int64_t tile, bool absgrad) {
  check(grad_out, "grad_out", 4); check(grad_alpha, "grad_alpha", 4);
  std::vector<at::Tensor> res;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "gdiff_rasterize_backward", [&] {
    res = backward_impl<scalar_t>(means2d, conics, colors, opacities, extents, offsets, ids,
                                  T_final, last, grad_out, grad_alpha, width, height, tile,
                                  absgrad);
  });
  return res;
}

std::vector<at::Tensor> rasterize_weights(at::Tensor means2d, at::Tensor conics,
                                          at::Tensor opacities, at::Tensor extents,
                                          at::Tensor visible, at::Tensor order, int64_t width,
                                          int64_t height, int64_t tile, double tolerance) {
  check(means2d, "means2d", 3); check(conics, "conics", 3); check(opacities, "opacities", 2);
  check(extents, "extents", 3); check(visible, "visible", 2); check(order, "order", 2);
  TORCH_CHECK(means2d.size(0) == 1, "rasterize_weights takes one camera");
  TORCH_CHECK(visible.scalar_type() == at::kBool && order.scalar_type() == at::kLong,
              "visible must be bool and order int64");
  std::vector<at::Tensor> res;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "gdiff_rasterize_weights", [&] {
    res = weights_impl<scalar_t>(means2d, conics, opacities, extents, visible, order, width,
                                 height, tile, tolerance);
  });
  return res;
}

TORCH_LIBRARY(gdiff_splat, m) {
  // (out, alpha, T_final, last, tile_offsets, tile_ids)
  m.def("rasterize_forward", &rasterize_forward);
  // (grad_means2d, grad_conics, grad_colors, grad_opacities, absgrad_means2d)
  m.def("rasterize_backward", &rasterize_backward);
  // (counts [H*W], gid [P], weight [P], alpha [H*W]) of one camera
  m.def("rasterize_weights", &rasterize_weights);
}
