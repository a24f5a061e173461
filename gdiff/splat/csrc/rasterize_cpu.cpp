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
// shared among std::threads (at::get_num_threads() of them). Gradients are accumulated in
// kGradParts buffers, a number that does not depend on the threads: part p holds the tiles
// p, p + kGradParts, ... in that order, and the parts are added in part order at the end, so
// the gradients are bitwise the same on every run and for any number of threads (--cores 1
// and --cores 8 alike). The backward pass uses at most kGradParts threads.
//
// Compiled with -ffp-contract=off so that sigma rounds exactly as in the torch path.
//
// With AVX2 and FMA (the build uses -march=native) the float forward and backward passes run
// 8 pixels of a tile row at once (forward_tile_f32, backward_tile_f32); the scalar loops stay
// for double and for other CPUs. Per pixel they compute the same values in the same order (the
// exp is bitwise that of glibc's expf, see exp8), so the forward outputs are bitwise those of
// the scalar loop; the backward sums each Gaussian's gradient over its pixels in 8 per-lane
// partial sums, which changes only the rounding of those sums.

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
#include <memory>
#include <thread>
#include <type_traits>
#include <vector>

#if defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>
#define GDIFF_RASTER_SIMD 1
#else
#define GDIFF_RASTER_SIMD 0
#endif

namespace {

constexpr double kSigmaMax = 4.5;
constexpr double kAlphaMax = 0.99;
constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kTMin = 1e-4;

// Run fn(task, thread_id) for task in [0, n_tasks) on up to n_threads threads. Tasks are
// handed out as threads free up (tiles have very uneven cost), so a kernel must not let its
// results depend on which thread ran a task: thread_id only picks scratch space.
template <typename F>
void run_tasks(int64_t n_tasks, int n_threads, F fn) {
  n_threads = std::max(1, std::min<int>(n_threads, (int)std::max<int64_t>(n_tasks, 1)));
  std::atomic<int64_t> next{0};
  auto worker = [&](int tid) {
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

// Gradient accumulation buffers of the backward pass (see the file comment): fixed, so the
// order in which each gradient is summed is the same for any number of threads.
constexpr int64_t kGradParts = 8;

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

#if GDIFF_RASTER_SIMD
// ---------------------------------------------------------------- 8-lane float kernels (AVX2)
//
// Inside a tile the per-pixel state is held as structure of arrays: one float (or int32) per
// tile pixel, row-major with row stride `tile`, each array padded by 8 so that a chunk of 8
// pixels starting anywhere in the tile can be loaded and stored whole. A Gaussian's clipped
// box is covered, row by row, by chunks starting at its first column x0 (x0, x0 + 8, ...);
// lanes past x1, lanes of pixels already finished and lanes failing the tests keep their old
// state through blends (lanes past the end of a row belong to the next row or the padding and
// are written back unchanged). All arithmetic is the scalar loop's, operation by operation
// (separate multiplies and adds, no FMA), so each pixel's values round the same.

// bits of 2^(i/32) minus i << 47: adding k << 47 for k = 32 e + i gives 2^(e + i/32)
alignas(32) const uint64_t kExp2Table[32] = {
    0x3ff0000000000000, 0x3fefd9b0d3158574, 0x3fefb5586cf9890f, 0x3fef9301d0125b51,
    0x3fef72b83c7d517b, 0x3fef54873168b9aa, 0x3fef387a6e756238, 0x3fef1e9df51fdee1,
    0x3fef06fe0a31b715, 0x3feef1a7373aa9cb, 0x3feedea64c123422, 0x3feece086061892d,
    0x3feebfdad5362a27, 0x3feeb42b569d4f82, 0x3feeab07dd485429, 0x3feea47eb03a5585,
    0x3feea09e667f3bcd, 0x3fee9f75e8ec5f74, 0x3feea11473eb0187, 0x3feea589994cce13,
    0x3feeace5422aa0db, 0x3feeb737b0cdc5e5, 0x3feec49182a3f090, 0x3feed503b23e255d,
    0x3feee89f995ad3ad, 0x3feeff76f2fb5e47, 0x3fef199bdd85529c, 0x3fef3720dcef9069,
    0x3fef5818dcfba487, 0x3fef7c97337b9b5f, 0x3fefa4afa2a490da, 0x3fefd0765b6e4540};

// exp of 4 doubles (for arguments converted from float): x 32/ln2 = k + r with integer k and
// |r| <= 1/2, exp(x) = 2^(k/32) 2^(r/32) with a cubic for 2^(r/32). This is the algorithm and
// the constants of glibc's expf (since 2.28, from Arm's optimized-routines), so rounding the
// result to float gives glibc's expf bit for bit: checked on every float in [-4.6, 0], the
// range used here (arguments -sigma in [-4.5, 0]).
inline __m256d exp4_pd(__m256d x) {
  const __m256d inv_ln2_n = _mm256_set1_pd(0x1.71547652b82fep+0 * 32);
  const __m256d shift = _mm256_set1_pd(0x1.8p+52);  // adding it rounds to an integer
  const __m256d kd_shifted = _mm256_fmadd_pd(inv_ln2_n, x, shift);
  const __m256i ki = _mm256_castpd_si256(kd_shifted);  // k in the low bits
  const __m256d kd = _mm256_sub_pd(kd_shifted, shift);
  const __m256d r = _mm256_fmsub_pd(inv_ln2_n, x, kd);
  const __m256i idx = _mm256_and_si256(ki, _mm256_set1_epi64x(31));
  const __m256i t = _mm256_add_epi64(
      _mm256_i64gather_epi64(reinterpret_cast<const long long*>(kExp2Table), idx, 8),
      _mm256_slli_epi64(ki, 47));
  const __m256d s = _mm256_castsi256_pd(t);
  const __m256d c0 = _mm256_set1_pd(0x1.c6af84b912394p-5 / 32 / 32 / 32);
  const __m256d c1 = _mm256_set1_pd(0x1.ebfce50fac4f3p-3 / 32 / 32);
  const __m256d c2 = _mm256_set1_pd(0x1.62e42ff0c52d6p-1 / 32);
  const __m256d z = _mm256_fmadd_pd(c0, r, c1);
  const __m256d y = _mm256_fmadd_pd(z, _mm256_mul_pd(r, r),
                                    _mm256_fmadd_pd(c2, r, _mm256_set1_pd(1.0)));
  return _mm256_mul_pd(y, s);
}

// std::exp of 8 floats in [-4.6, 0] (see exp4_pd). The argument is first clamped to [-10, 0]
// (NaN passes through) so that lanes outside the range, whose results are discarded, stay
// finite.
inline __m256 exp8(__m256 x) {
  x = _mm256_max_ps(_mm256_set1_ps(-10.f), _mm256_min_ps(_mm256_setzero_ps(), x));
  const __m256d lo = exp4_pd(_mm256_cvtps_pd(_mm256_castps256_ps128(x)));
  const __m256d hi = exp4_pd(_mm256_cvtps_pd(_mm256_extractf128_ps(x, 1)));
  return _mm256_set_m128(_mm256_cvtpd_ps(hi), _mm256_cvtpd_ps(lo));
}

// Sum of the 8 lanes in a fixed order.
inline float hsum8(__m256 v) {
  __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
  s = _mm_add_ps(s, _mm_movehl_ps(s, s));
  s = _mm_add_ss(s, _mm_movehdup_ps(s));
  return _mm_cvtss_f32(s);
}

inline bool none(__m256 m) { return _mm256_movemask_ps(m) == 0; }

// A Gaussian's data as the tile loops read it: its unclipped pixel box (box_range), conic,
// opacity, s_max and, for D <= 5, its colour, in one cache line. The tile lists visit the
// Gaussians in depth order, scattered in memory: one line per visit (prefetched a few
// Gaussians ahead) instead of one per input tensor, and box and s_max (a log) are computed
// once per Gaussian instead of once per tile.
struct alignas(64) PackedSplat {
  float mx, my, a, b, cc, op, s_max;
  int32_t x0, x1, y0, y1;
  float col[5];
};
constexpr int64_t kPackedColors = 5;
constexpr int64_t kPrefetch = 8;  // Gaussians ahead

struct PackedSplats {
  std::unique_ptr<PackedSplat[]> rec;  // one per Gaussian listed in some tile, by index
  std::vector<int32_t> at;             // per tile-list entry (as ids): its Gaussian's record
};

// Records of the Gaussians listed in the tile lists (offsets off, ids; C cameras, nt tiles
// each), in index order.
PackedSplats pack_splats(const float* M, const float* Q, const float* F, const float* O,
                         const float* E, int64_t C, int64_t N, int64_t D, int64_t nt,
                         const int64_t* off, const int32_t* ids, int nth) {
  std::vector<int32_t> slot(C * N, -1);
  for (int64_t c = 0; c < C; ++c)
    for (int64_t e = off[c * nt]; e < off[(c + 1) * nt]; ++e) slot[c * N + ids[e]] = 0;
  int32_t n_used = 0;
  for (int32_t& v : slot)
    if (v == 0) v = n_used++;
  PackedSplats P{std::unique_ptr<PackedSplat[]>(new PackedSplat[n_used]),
                 std::vector<int32_t>(off[C * nt])};
  for (int64_t c = 0; c < C; ++c)
    for (int64_t e = off[c * nt]; e < off[(c + 1) * nt]; ++e) P.at[e] = slot[c * N + ids[e]];
  const int64_t block = 4096;
  run_tasks((C * N + block - 1) / block, nth, [&](int64_t task, int) {
    for (int64_t g = task * block; g < std::min(C * N, (task + 1) * block); ++g) {
      if (slot[g] < 0) continue;
      PackedSplat& p = P.rec[slot[g]];
      int64_t x0, x1, y0, y1;
      box_range<float>(M[g * 2], E[g * 2], x0, x1);
      box_range<float>(M[g * 2 + 1], E[g * 2 + 1], y0, y1);
      p.mx = M[g * 2]; p.my = M[g * 2 + 1];
      p.a = Q[g * 3]; p.b = Q[g * 3 + 1]; p.cc = Q[g * 3 + 2]; p.op = O[g];
      p.s_max = std::min((float)kSigmaMax, sigma_reach(p.op));
      p.x0 = (int32_t)x0; p.x1 = (int32_t)x1; p.y0 = (int32_t)y0; p.y1 = (int32_t)y1;
      for (int64_t d = 0; d < kPackedColors; ++d) p.col[d] = d < D ? F[g * D + d] : 0.f;
    }
  });
  return P;
}

// What the tile loops need to find Gaussian k of a tile list: its index g0 + ids[k] (g0 = c N
// for camera c), its record S[at[k]], its colour, and the tile rectangle.
struct TileArgs {
  const PackedSplat* S;
  const int32_t* at;
  const float* F;
  const int32_t* ids;
  int64_t g0, D, tile, px0, py0, tw, th;
  void prefetch(int64_t k) const {
    _mm_prefetch(reinterpret_cast<const char*>(S + at[k]), _MM_HINT_T0);
    if (D > kPackedColors)
      _mm_prefetch(reinterpret_cast<const char*>(F + (g0 + ids[k]) * D), _MM_HINT_T0);
  }
};

// Gaussian k of the tile list with its box clipped to the tile; false if it reaches no pixel
// of the tile (the scalar loops' tests).
struct Splat {
  int64_t g, x0, x1, y0, y1;
  float mx, my, a, b, cc, op, s_max;
  const float* col;
};

inline bool splat_in_tile(const TileArgs& A, int64_t k, Splat& s) {
  s.g = A.g0 + A.ids[k];
  const PackedSplat& p = A.S[A.at[k]];
  s.x0 = std::max<int64_t>(p.x0, A.px0); s.x1 = std::min<int64_t>(p.x1, A.px0 + A.tw - 1);
  s.y0 = std::max<int64_t>(p.y0, A.py0); s.y1 = std::min<int64_t>(p.y1, A.py0 + A.th - 1);
  if (s.x0 > s.x1 || s.y0 > s.y1) return false;
  s.mx = p.mx; s.my = p.my; s.a = p.a; s.b = p.b; s.cc = p.cc; s.op = p.op; s.s_max = p.s_max;
  s.col = A.D <= kPackedColors ? p.col : A.F + s.g * A.D;
  return s.s_max >= 0;
}

// Chunk of 8 pixels (x, y) .. (x + 7, y): column mask (x + l <= x1) and the per-column terms.
struct Chunk {
  __m256 colm, dx, adx, adxdx, bdx;
  Chunk(const Splat& s, int64_t x) {
    const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    colm = _mm256_castsi256_ps(
        _mm256_cmpgt_epi32(_mm256_set1_epi32((int32_t)(s.x1 - x + 1)), lane));
    const __m256 xc = _mm256_add_ps(
        _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32((int32_t)x), lane)),
        _mm256_set1_ps(0.5f));  // (float)i + 0.5f
    dx = _mm256_sub_ps(_mm256_set1_ps(s.mx), xc);
    adx = _mm256_mul_ps(_mm256_set1_ps(s.a), dx);
    adxdx = _mm256_mul_ps(adx, dx);
    bdx = _mm256_mul_ps(_mm256_set1_ps(s.b), dx);
  }
};

// sigma = 0.5 (a dx dx + cc dy dy) + b dx dy, rounded as in the scalar loop; dy of row y.
inline __m256 chunk_sigma(const Splat& s, const Chunk& ch, float dy) {
  const float ccdydy = s.cc * dy * dy;
  return _mm256_add_ps(
      _mm256_mul_ps(_mm256_set1_ps(0.5f), _mm256_add_ps(ch.adxdx, _mm256_set1_ps(ccdydy))),
      _mm256_mul_ps(ch.bdx, _mm256_set1_ps(dy)));
}

// Lanes of m that pass the sigma tests (a NaN sigma passes, as in the scalar loop).
inline __m256 sigma_pass(__m256 m, __m256 sigma, const Splat& s) {
  const __m256 out = _mm256_or_ps(_mm256_cmp_ps(sigma, _mm256_set1_ps(s.s_max), _CMP_GT_OQ),
                                  _mm256_cmp_ps(sigma, _mm256_setzero_ps(), _CMP_LT_OQ));
  return _mm256_andnot_ps(out, m);
}

inline __m256 negate(__m256 v) { return _mm256_xor_ps(v, _mm256_set1_ps(-0.f)); }

// acc += v in the lanes of m (the other lanes add +0, whatever v holds there)
inline void add_masked(__m256& acc, __m256 m, __m256 v) {
  acc = _mm256_add_ps(acc, _mm256_and_ps(m, v));
}

// Forward pass of one tile, Gaussians ids[kb:ke] in depth order (see forward_impl for the
// scalar loop it mirrors). Writes the tile's pixels of out, T_final and last (image row stride
// W, pixel index pix0 of the tile's first pixel).
void forward_tile_f32(const TileArgs& A, int64_t kb, int64_t ke, std::vector<float>& fbuf,
                      std::vector<int32_t>& ibuf, float* out, float* Tf, int32_t* last,
                      int64_t W, int64_t pix0) {
  const int64_t D = A.D, tile = A.tile, PS = tile * tile + 8;
  fbuf.assign(PS * (D + 1), 0.f);
  float* T = fbuf.data();  // transmittance
  float* acc = T + PS;     // channel d at acc + d PS
  std::fill(T, T + PS, 1.f);
  ibuf.assign(2 * PS, -1);
  int32_t* live = ibuf.data();  // -1 while the pixel is not done, else 0
  int32_t* lastk = live + PS;
  const __m256 one = _mm256_set1_ps(1.f), amax = _mm256_set1_ps((float)kAlphaMax),
               amin = _mm256_set1_ps((float)kAlphaMin), tmin = _mm256_set1_ps((float)kTMin);
  int64_t n_done = 0;
  const int64_t n_pix = A.tw * A.th;
  Splat s;
  for (int64_t k = kb; k < ke && n_done < n_pix; ++k) {
    if (k + kPrefetch < ke) A.prefetch(k + kPrefetch);
    if (!splat_in_tile(A, k, s)) continue;
    const float* col = s.col;
    const __m256 op = _mm256_set1_ps(s.op);
    const __m256i kv = _mm256_set1_epi32((int32_t)k);
    for (int64_t x = s.x0; x <= s.x1; x += 8) {
      const Chunk ch(s, x);
      for (int64_t y = s.y0; y <= s.y1; ++y) {
        const int64_t q = (y - A.py0) * tile + (x - A.px0);
        __m256i lv = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(live + q));
        __m256 m = _mm256_and_ps(ch.colm, _mm256_castsi256_ps(lv));
        if (none(m)) continue;
        const float dy = s.my - ((float)y + 0.5f);
        const __m256 sigma = chunk_sigma(s, ch, dy);
        m = sigma_pass(m, sigma, s);
        if (none(m)) continue;
        // min(raw, 0.99) keeps 0.99 for a NaN raw, as std::min(0.99, raw)
        const __m256 alpha = _mm256_min_ps(_mm256_mul_ps(op, exp8(negate(sigma))), amax);
        m = _mm256_andnot_ps(_mm256_cmp_ps(alpha, amin, _CMP_LT_OQ), m);
        const __m256 Tq = _mm256_loadu_ps(T + q);
        const __m256 nT = _mm256_mul_ps(Tq, _mm256_sub_ps(one, alpha));
        const __m256 stop = _mm256_and_ps(m, _mm256_cmp_ps(nT, tmin, _CMP_LE_OQ));
        n_done += __builtin_popcount(_mm256_movemask_ps(stop));
        lv = _mm256_andnot_si256(_mm256_castps_si256(stop), lv);
        _mm256_storeu_si256(reinterpret_cast<__m256i*>(live + q), lv);
        const __m256 blend = _mm256_andnot_ps(stop, m);
        const __m256 w = _mm256_mul_ps(alpha, Tq);
        for (int64_t d = 0; d < D; ++d) {
          float* ad = acc + d * PS + q;
          const __m256 v = _mm256_loadu_ps(ad);
          _mm256_storeu_ps(ad, _mm256_blendv_ps(
              v, _mm256_add_ps(v, _mm256_mul_ps(w, _mm256_set1_ps(col[d]))), blend));
        }
        _mm256_storeu_ps(T + q, _mm256_blendv_ps(Tq, nT, blend));
        __m256i* lk = reinterpret_cast<__m256i*>(lastk + q);
        _mm256_storeu_si256(lk, _mm256_blendv_epi8(_mm256_loadu_si256(lk), kv,
                                                   _mm256_castps_si256(blend)));
      }
    }
  }
  for (int64_t j = 0; j < A.th; ++j) {
    for (int64_t i = 0; i < A.tw; ++i) {
      const int64_t q = j * tile + i, pix = pix0 + j * W + i;
      for (int64_t d = 0; d < D; ++d) out[pix * D + d] = acc[d * PS + q];
      Tf[pix] = T[q];
      last[pix] = lastk[q];
    }
  }
}

// Backward pass of one tile (see backward_impl for the scalar loop it mirrors): Gaussians from
// ids[kmax] down to ids[k0]; gradients added to the records `mine` (its part's buffer).
void backward_tile_f32(const TileArgs& A, int64_t k0, int64_t kmax, const float* Tf,
                       const int32_t* LK, const float* GO, const float* GA, int64_t W,
                       int64_t pix0, float* mine, int64_t stride, bool absgrad,
                       std::vector<float>& fbuf, std::vector<int32_t>& ibuf) {
  const int64_t D = A.D, tile = A.tile, PS = tile * tile + 8;
  fbuf.assign(PS * (3 + 2 * D) + 8 * D, 0.f);
  float* T = fbuf.data();  // transmittance behind the Gaussians still to visit
  float* Tfin = T + PS;
  float* ga = Tfin + PS;
  float* S = ga + PS;       // channel d at S + d PS: colour accumulated behind
  float* go = S + D * PS;   // channel d at go + d PS: grad_out
  float* gc = go + D * PS;  // per-lane colour gradient sums of the current Gaussian, 8 per d
  ibuf.assign(PS, -1);
  int32_t* lastk = ibuf.data();
  std::fill(T, T + PS, 1.f);
  std::fill(Tfin, Tfin + PS, 1.f);
  for (int64_t j = 0; j < A.th; ++j) {
    for (int64_t i = 0; i < A.tw; ++i) {
      const int64_t q = j * tile + i, pix = pix0 + j * W + i;
      T[q] = Tfin[q] = Tf[pix];
      lastk[q] = LK[pix];
      ga[q] = GA[pix];
      for (int64_t d = 0; d < D; ++d) go[d * PS + q] = GO[pix * D + d];
    }
  }
  const __m256 one = _mm256_set1_ps(1.f), half = _mm256_set1_ps(0.5f),
               amax = _mm256_set1_ps((float)kAlphaMax), amin = _mm256_set1_ps((float)kAlphaMin),
               zero = _mm256_setzero_ps(), sign = _mm256_set1_ps(-0.f);
  Splat s;
  for (int64_t k = kmax; k >= k0; --k) {
    if (k - kPrefetch >= k0) {
      A.prefetch(k - kPrefetch);
      const char* r = reinterpret_cast<const char*>(mine + (A.g0 + A.ids[k - kPrefetch]) * stride);
      _mm_prefetch(r, _MM_HINT_T0);
      _mm_prefetch(r + stride * sizeof(float) - 1, _MM_HINT_T0);
    }
    if (!splat_in_tile(A, k, s)) continue;
    const float* col = s.col;
    const __m256 op = _mm256_set1_ps(s.op);
    const __m256i km1 = _mm256_set1_epi32((int32_t)(k - 1));
    __m256 gm0 = zero, gm1 = zero, gq0 = zero, gq1 = zero, gq2 = zero, gop = zero,
           gab0 = zero, gab1 = zero;
    std::fill(gc, gc + 8 * D, 0.f);
    bool touched = false;
    for (int64_t x = s.x0; x <= s.x1; x += 8) {
      const Chunk ch(s, x);
      for (int64_t y = s.y0; y <= s.y1; ++y) {
        const int64_t q = (y - A.py0) * tile + (x - A.px0);
        const __m256i lk = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(lastk + q));
        __m256 m = _mm256_and_ps(ch.colm, _mm256_castsi256_ps(_mm256_cmpgt_epi32(lk, km1)));
        if (none(m)) continue;
        const float dy = s.my - ((float)y + 0.5f);
        const __m256 sigma = chunk_sigma(s, ch, dy);
        m = sigma_pass(m, sigma, s);
        if (none(m)) continue;
        touched = true;
        const __m256 gauss = exp8(negate(sigma));
        const __m256 raw = _mm256_mul_ps(op, gauss);
        const __m256 alpha = _mm256_min_ps(raw, amax);
        m = _mm256_andnot_ps(_mm256_cmp_ps(alpha, amin, _CMP_LT_OQ), m);
        const __m256 inv1m = _mm256_div_ps(one, _mm256_sub_ps(one, alpha));
        const __m256 Tq = _mm256_loadu_ps(T + q);
        const __m256 Ti = _mm256_mul_ps(Tq, inv1m);
        const __m256 w = _mm256_mul_ps(alpha, Ti);
        __m256 dL_dalpha = zero;
        for (int64_t d = 0; d < D; ++d) {
          const __m256 god = _mm256_loadu_ps(go + d * PS + q);
          float* Sd = S + d * PS + q;
          const __m256 Sq = _mm256_loadu_ps(Sd);
          const __m256 cd = _mm256_set1_ps(col[d]);
          float* gcd = gc + 8 * d;
          __m256 gcv = _mm256_loadu_ps(gcd);
          add_masked(gcv, m, _mm256_mul_ps(w, god));
          _mm256_storeu_ps(gcd, gcv);
          dL_dalpha = _mm256_add_ps(dL_dalpha, _mm256_mul_ps(god, _mm256_sub_ps(
              _mm256_mul_ps(cd, Ti), _mm256_mul_ps(Sq, inv1m))));
          _mm256_storeu_ps(Sd, _mm256_blendv_ps(Sq, _mm256_add_ps(Sq, _mm256_mul_ps(cd, w)), m));
        }
        dL_dalpha = _mm256_add_ps(dL_dalpha, _mm256_mul_ps(
            _mm256_mul_ps(_mm256_loadu_ps(ga + q), _mm256_loadu_ps(Tfin + q)), inv1m));
        _mm256_storeu_ps(T + q, _mm256_blendv_ps(Tq, Ti, m));
        // clamped alpha: no gradient through it (a NaN raw passes, as in the scalar loop)
        const __m256 mg = _mm256_andnot_ps(_mm256_cmp_ps(raw, amax, _CMP_GE_OQ), m);
        const __m256 dL_dsigma = _mm256_mul_ps(negate(alpha), dL_dalpha);
        add_masked(gop, mg, _mm256_mul_ps(gauss, dL_dalpha));
        const __m256 vdy = _mm256_set1_ps(dy);
        const __m256 gmx =
            _mm256_mul_ps(dL_dsigma, _mm256_add_ps(ch.adx, _mm256_set1_ps(s.b * dy)));
        const __m256 gmy =
            _mm256_mul_ps(dL_dsigma, _mm256_add_ps(ch.bdx, _mm256_set1_ps(s.cc * dy)));
        add_masked(gm0, mg, gmx);
        add_masked(gm1, mg, gmy);
        add_masked(gab0, mg, _mm256_andnot_ps(sign, gmx));  // |gmx|
        add_masked(gab1, mg, _mm256_andnot_ps(sign, gmy));
        const __m256 hs = _mm256_mul_ps(dL_dsigma, half);
        add_masked(gq0, mg, _mm256_mul_ps(_mm256_mul_ps(hs, ch.dx), ch.dx));
        add_masked(gq1, mg, _mm256_mul_ps(_mm256_mul_ps(dL_dsigma, ch.dx), vdy));
        add_masked(gq2, mg, _mm256_mul_ps(_mm256_mul_ps(hs, vdy), vdy));
      }
    }
    if (!touched) continue;
    float* r = mine + s.g * stride;
    r[0] += hsum8(gm0); r[1] += hsum8(gm1);
    r[2] += hsum8(gq0); r[3] += hsum8(gq1); r[4] += hsum8(gq2);
    r[5] += hsum8(gop);
    for (int64_t d = 0; d < D; ++d) r[6 + d] += hsum8(_mm256_loadu_ps(gc + 8 * d));
    if (absgrad) { r[6 + D] += hsum8(gab0); r[7 + D] += hsum8(gab1); }
  }
}
#endif  // GDIFF_RASTER_SIMD

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

// One Gaussian as the scalar loops read it in a tile: mean, conic, opacity, s_max and its
// 3-sigma box clipped to the tile [x0, x1] x [y0, y1].
template <typename scalar_t>
struct TileSplat {
  scalar_t mx, my, a, b, cc, op, s_max;
  int64_t x0, x1, y0, y1;
};

// Gaussian g (index into the [C*N] arrays) in the tile at (px0, py0) of tw x th pixels;
// false when its box misses the tile or its opacity reaches no pixel (s_max < 0).
template <typename scalar_t>
inline bool tile_splat(const scalar_t* M, const scalar_t* Q, const scalar_t* O,
                       const scalar_t* E, int64_t g, int64_t px0, int64_t py0, int64_t tw,
                       int64_t th, TileSplat<scalar_t>& s) {
  s.mx = M[g * 2]; s.my = M[g * 2 + 1];
  box_range<scalar_t>(s.mx, E[g * 2], s.x0, s.x1);
  box_range<scalar_t>(s.my, E[g * 2 + 1], s.y0, s.y1);
  s.x0 = std::max(s.x0, px0); s.x1 = std::min(s.x1, px0 + tw - 1);
  s.y0 = std::max(s.y0, py0); s.y1 = std::min(s.y1, py0 + th - 1);
  if (s.x0 > s.x1 || s.y0 > s.y1) return false;
  s.a = Q[g * 3]; s.b = Q[g * 3 + 1]; s.cc = Q[g * 3 + 2]; s.op = O[g];
  s.s_max = std::min((scalar_t)kSigmaMax, sigma_reach(s.op));
  return s.s_max >= 0;
}

// The scalar compositing loop of one tile, shared by the forward pass and rasterize_weights:
// Gaussians ids[kb:ke] (indices within the camera, offset by base) front to back, each over
// its box clipped to the tile; T [tile*tile] transmittance and done flags per tile pixel,
// row stride tile. For every pixel a Gaussian is blended into, blend(q, g, k, w) gets the tile
// pixel q, the Gaussian's index g (base included), its list position k and the weight
// w = alpha T before T is updated. A pixel stops (done) before the Gaussian that would bring
// T to <= 1e-4; the loop ends when all tw x th pixels have.
template <typename scalar_t, typename Blend>
inline void composite_tile(const scalar_t* M, const scalar_t* Q, const scalar_t* O,
                           const scalar_t* E, const int32_t* ids, int64_t kb, int64_t ke,
                           int64_t base, int64_t tile, int64_t px0, int64_t py0, int64_t tw,
                           int64_t th, scalar_t* T, uint8_t* done, Blend&& blend) {
  int64_t n_done = 0;
  const int64_t n_pix = tw * th;
  for (int64_t k = kb; k < ke && n_done < n_pix; ++k) {
    const int64_t g = base + ids[k];
    TileSplat<scalar_t> sp;
    if (!tile_splat(M, Q, O, E, g, px0, py0, tw, th, sp)) continue;
    const scalar_t mx = sp.mx, my = sp.my, a = sp.a, b = sp.b, cc = sp.cc, op = sp.op;
    const scalar_t s_max = sp.s_max;
    const int64_t x0 = sp.x0, x1 = sp.x1, y0 = sp.y0, y1 = sp.y1;
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
        blend(q, g, k, alpha * T[q]);
        T[q] = nT;
      }
    }
  }
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
#if GDIFF_RASTER_SIMD
  std::vector<std::vector<int32_t>> iscratch(nth);
  PackedSplats packed;
  if constexpr (std::is_same<scalar_t, float>::value)
    packed = pack_splats(M, Q, F, O, E, C, N, D, nt, off, ids, nth);
#endif

  run_tasks(C * nt, nth, [&](int64_t task, int tid) {
    const int64_t c = task / nt, t = task % nt;
    const int64_t px0 = (t % tx_n) * tile, py0 = (t / tx_n) * tile;
    const int64_t tw = std::min(tile, W - px0), th = std::min(tile, H - py0);
    std::vector<scalar_t>& buf = scratch[tid];
#if GDIFF_RASTER_SIMD
    if constexpr (std::is_same<scalar_t, float>::value) {
      const TileArgs A{packed.rec.get(), packed.at.data(), F, ids, c * N, D, tile, px0,
                        py0, tw, th};
      forward_tile_f32(A, off[c * nt + t], off[c * nt + t + 1], buf, iscratch[tid], out_p,
                       Tf_p, last_p, W, (c * H + py0) * W + px0);
      return;
    }
#endif
    buf.assign(P * (D + 1), 0);
    scalar_t* acc = buf.data();
    scalar_t* T = acc + P * D;
    std::vector<int32_t> lastk(P, -1);
    std::vector<uint8_t> done(P, 0);
    for (int64_t q = 0; q < P; ++q) T[q] = 1;
    composite_tile(M, Q, O, E, ids, off[c * nt + t], off[c * nt + t + 1], c * N, tile, px0,
                   py0, tw, th, T, done.data(), [&](int64_t q, int64_t g, int64_t k, scalar_t w) {
                     const scalar_t* col = F + g * D;
                     scalar_t* aq = acc + q * D;
                     for (int64_t d = 0; d < D; ++d) aq[d] += w * col[d];
                     lastk[q] = (int32_t)k;
                   });
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
  const int64_t n_tasks = C * nt;
  const int64_t parts = std::max<int64_t>(1, std::min<int64_t>(kGradParts, n_tasks));
  const int nth = (int)std::min<int64_t>(num_threads(), parts);
  const int64_t G = C * N;
  const int64_t stride = 2 + 3 + 1 + D + (absgrad ? 2 : 0);  // per-Gaussian gradient record
  at::Tensor acc_all = at::zeros({parts, G, stride}, means2d.options());
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
#if GDIFF_RASTER_SIMD
  std::vector<std::vector<scalar_t>> scratch(nth);
  std::vector<std::vector<int32_t>> iscratch(nth);
  PackedSplats packed;
  if constexpr (std::is_same<scalar_t, float>::value)
    packed = pack_splats(M, Q, F, O, E, C, N, D, nt, off, ids, nth);
#endif

  // part p runs its tasks p, p + parts, ... in order into its own buffer; any thread may
  // take a part (dynamic), the sums do not depend on which
  run_tasks(parts, nth, [&](int64_t part, int tid) {
    for (int64_t task = part; task < n_tasks; task += parts) {
      const int64_t c = task / nt, t = task % nt;
      const int64_t px0 = (t % tx_n) * tile, py0 = (t / tx_n) * tile;
      const int64_t tw = std::min(tile, W - px0), th = std::min(tile, H - py0);
      scalar_t* mine = ACC + part * G * stride;
#if GDIFF_RASTER_SIMD
      if constexpr (std::is_same<scalar_t, float>::value) {
        const int64_t pix0 = (c * H + py0) * W + px0;
        int64_t kmax = -1;
        for (int64_t j = 0; j < th; ++j)
          for (int64_t i = 0; i < tw; ++i) kmax = std::max<int64_t>(kmax, LK[pix0 + j * W + i]);
        const TileArgs A{packed.rec.get(), packed.at.data(), F, ids, c * N, D, tile, px0,
                          py0, tw, th};
        backward_tile_f32(A, off[c * nt + t], kmax, Tf, LK, GO, GA, W, pix0, mine, stride,
                          absgrad, scratch[tid], iscratch[tid]);
        continue;
      }
#endif
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
        const int64_t g = c * N + ids[k];
        TileSplat<scalar_t> sp;
        if (!tile_splat(M, Q, O, E, g, px0, py0, tw, th, sp)) continue;
        const scalar_t mx = sp.mx, my = sp.my, a = sp.a, b = sp.b, cc = sp.cc, op = sp.op;
        const scalar_t s_max = sp.s_max;
        const int64_t x0 = sp.x0, x1 = sp.x1, y0 = sp.y0, y1 = sp.y1;
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
    }
  });
  // the parts added in part order, element by element (the same sums for any threads)
  at::Tensor total = at::empty({G, stride}, means2d.options());
  scalar_t* TOT = total.data_ptr<scalar_t>();
  const int64_t n_el = G * stride;
  at::parallel_for(0, n_el, 1 << 14, [=](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i) {
      scalar_t v = ACC[i];
      for (int64_t p = 1; p < parts; ++p) v += ACC[p * n_el + i];
      TOT[i] = v;
    }
  });
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
    composite_tile(M, Q, O, E, ids, off[t], off[t + 1], 0, tile, px0, py0, tw, th, T.data(),
                   done.data(), [&](int64_t q, int64_t g, int64_t, scalar_t w) {
                     pq.push_back((int32_t)q);
                     pg.push_back((int32_t)g);
                     pw.push_back((float)w);
                   });
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
