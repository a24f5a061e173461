// Bilinear look-up of HexPlane feature planes for many points (forward and backward).
//
// Same maths as torch.nn.functional.grid_sample(mode="bilinear", padding_mode="border",
// align_corners=True) on each plane, which gdiff/splat/deform.py uses as the reference:
//   plane p samples axes (a_p, b_p) of the normalised coordinates c [N, 4] in [-1, 1];
//   ix = (c[a] + 1) / 2 * (W_p - 1), iy = (c[b] + 1) / 2 * (H_p - 1), clamped to the plane;
//   the four neighbouring texels are blended with the bilinear weights.
// All planes live in one channels-last table [R, F]: plane p's texel (x, y) is row
// offset_p + y * W_p + x. The samples of the planes of one level are multiplied (HexPlane). Channels-last makes each texel's F features one contiguous read,
// where grid_sample on [1, F, H, W] strides over F planes; that is what makes this faster.
// For training, the forward pass also returns every plane's samples, which the backward pass
// reads instead of sampling the table again.
// The backward pass scatters into dense gradient tables, one per fixed part of the points,
// added in a fixed order, so the result is the same for any thread count.

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

struct Corners {
  int64_t row[4];
  float w[4];
};

// texel rows and weights of point coords (u along W, v along H) on one W x H plane
inline Corners corners(float u, float v, int64_t W, int64_t H, int64_t offset) {
  float ix = (u + 1.f) * 0.5f * (float)(W - 1);
  float iy = (v + 1.f) * 0.5f * (float)(H - 1);
  ix = std::min(std::max(ix, 0.f), (float)(W - 1));
  iy = std::min(std::max(iy, 0.f), (float)(H - 1));
  const int64_t x0 = std::min<int64_t>((int64_t)std::floor(ix), std::max<int64_t>(W - 2, 0));
  const int64_t y0 = std::min<int64_t>((int64_t)std::floor(iy), std::max<int64_t>(H - 2, 0));
  const int64_t x1 = std::min<int64_t>(x0 + 1, W - 1), y1 = std::min<int64_t>(y0 + 1, H - 1);
  const float fx = std::min(std::max(ix - (float)x0, 0.f), 1.f);
  const float fy = std::min(std::max(iy - (float)y0, 0.f), 1.f);
  Corners c;
  c.row[0] = offset + y0 * W + x0; c.w[0] = (1.f - fx) * (1.f - fy);
  c.row[1] = offset + y0 * W + x1; c.w[1] = fx * (1.f - fy);
  c.row[2] = offset + y1 * W + x0; c.w[2] = (1.f - fx) * fy;
  c.row[3] = offset + y1 * W + x1; c.w[3] = fx * fy;
  return c;
}

void check(const at::Tensor& t, const char* name, int64_t dim, at::ScalarType type) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  TORCH_CHECK(t.dim() == dim, name, " must have ", dim, " dimensions");
  TORCH_CHECK(t.scalar_type() == type, name, " has the wrong dtype");
}

}  // namespace

// Sample plane p of point n into s[F].
inline void sample(const float* T, const float* C, const int64_t* pl, int64_t n, int64_t F,
                   float* s, Corners& c) {
  c = corners(C[n * 4 + pl[0]], C[n * 4 + pl[1]], pl[2], pl[3], pl[4]);
  const float* t0 = T + c.row[0] * F;
  const float* t1 = T + c.row[1] * F;
  const float* t2 = T + c.row[2] * F;
  const float* t3 = T + c.row[3] * F;
  for (int64_t f = 0; f < F; ++f)
    s[f] = c.w[0] * t0[f] + c.w[1] * t1[f] + c.w[2] * t2[f] + c.w[3] * t3[f];
}

// table [R, F] float32, coords [N, 4] float32 in [-1, 1], planes [P, 5] int64 rows
// (axis a, axis b, W, H, row offset), P = levels x group: the planes of a level are
// consecutive and their samples are multiplied -> features [N, levels, F]
// The samples of every plane go to S [N, P, F] when S is given (training: the backward pass
// reads them there instead of sampling the table again).
static at::Tensor forward_impl(const at::Tensor& table, const at::Tensor& coords,
                               const at::Tensor& planes, int64_t group, float* S) {
  check(table, "table", 2, at::kFloat);
  check(coords, "coords", 2, at::kFloat);
  check(planes, "planes", 2, at::kLong);
  const int64_t N = coords.size(0), P = planes.size(0), F = table.size(1);
  TORCH_CHECK(coords.size(1) == 4 && planes.size(1) == 5, "coords [N, 4], planes [P, 5]");
  TORCH_CHECK(group > 0 && P % group == 0, "planes must be whole groups");
  const int64_t L = P / group;
  at::Tensor out = at::empty({N, L, F}, table.options());
  const float* T = table.data_ptr<float>();
  const float* C = coords.data_ptr<float>();
  const int64_t* PL = planes.data_ptr<int64_t>();
  float* O = out.data_ptr<float>();
  at::parallel_for(0, N, 256, [=](int64_t begin, int64_t end) {
    // captured by value: locals the compiler knows no store aliases (faster inner loops)
    std::vector<float> buf(F);
    Corners c;
    for (int64_t n = begin; n < end; ++n) {
      for (int64_t l = 0; l < L; ++l) {
        float* o = O + (n * L + l) * F;
        for (int64_t f = 0; f < F; ++f) o[f] = 1.f;
        for (int64_t p = l * group; p < (l + 1) * group; ++p) {
          float* s = S ? S + (n * P + p) * F : buf.data();
          sample(T, C, PL + p * 5, n, F, s, c);
          for (int64_t f = 0; f < F; ++f) o[f] *= s[f];
        }
      }
    }
  });
  return out;
}

at::Tensor hexplane_forward(at::Tensor table, at::Tensor coords, at::Tensor planes,
                            int64_t group) {
  return forward_impl(table, coords, planes, group, nullptr);
}

// The same features [N, levels, F] and every plane's samples [N, P, F], for
// hexplane_backward.
std::tuple<at::Tensor, at::Tensor> hexplane_forward_samples(at::Tensor table, at::Tensor coords,
                                                            at::Tensor planes, int64_t group) {
  at::Tensor samples = at::empty({coords.size(0), planes.size(0), table.size(1)},
                                 table.options());
  at::Tensor out = forward_impl(table, coords, planes, group, samples.data_ptr<float>());
  return {out, samples};
}

// grad_out [N, levels, F] -> grad_table [rows, F] (product rule with prefix / suffix
// products of the group's samples: no division, exact for zero samples).
// The points are cut into a fixed number of contiguous parts (set by N alone, at most
// kParts); each part scatters into its own gradient table, in point order, on whichever
// thread runs it, and the tables are then added in part order. The result is therefore the
// same for any number of threads (deterministic, as training resume needs).
constexpr int64_t kParts = 4;

// samples: the forward pass's samples of every plane [N, P, F] (hexplane_forward_samples);
// rows: the table's row count. The corners are found again, the table is not read.
at::Tensor hexplane_backward(at::Tensor samples, at::Tensor grad_out, at::Tensor coords,
                             at::Tensor planes, int64_t group, int64_t rows) {
  check(samples, "samples", 3, at::kFloat);
  check(grad_out, "grad_out", 3, at::kFloat);
  check(coords, "coords", 2, at::kFloat);
  check(planes, "planes", 2, at::kLong);
  const int64_t N = coords.size(0), P = planes.size(0), F = grad_out.size(2);
  const int64_t L = P / group;
  TORCH_CHECK(group > 0 && P % group == 0 && grad_out.size(0) == N && grad_out.size(1) == L,
              "grad_out [N, levels, F], planes whole groups");
  TORCH_CHECK(samples.size(0) == N && samples.size(1) == P && samples.size(2) == F,
              "samples [N, P, F]");
  const int64_t parts = std::max<int64_t>(1, std::min<int64_t>(kParts, N / 4096));
  const float* S = samples.data_ptr<float>();
  at::Tensor acc = at::empty({parts, rows, F}, samples.options());  // zeroed by its part below
  const float* G = grad_out.data_ptr<float>();
  const float* C = coords.data_ptr<float>();
  const int64_t* PL = planes.data_ptr<int64_t>();
  float* A = acc.data_ptr<float>();
  at::parallel_for(0, parts, 1, [=](int64_t pb, int64_t pe) {
    std::vector<float> pre((group + 1) * F), suf((group + 1) * F);
    std::vector<Corners> cs(group);
    for (int64_t part = pb; part < pe; ++part) {
      float* R = A + part * rows * F;
      std::fill(R, R + rows * F, 0.f);
      for (int64_t n = part * N / parts; n < (part + 1) * N / parts; ++n) {
        for (int64_t l = 0; l < L; ++l) {
          const float* g = G + (n * L + l) * F;
          const float* s = S + (n * P + l * group) * F;  // this level's samples
          for (int64_t q = 0; q < group; ++q) {
            const int64_t* pl = PL + (l * group + q) * 5;
            cs[q] = corners(C[n * 4 + pl[0]], C[n * 4 + pl[1]], pl[2], pl[3], pl[4]);
          }
          for (int64_t f = 0; f < F; ++f) { pre[f] = 1.f; suf[group * F + f] = 1.f; }
          for (int64_t q = 0; q < group; ++q)
            for (int64_t f = 0; f < F; ++f) pre[(q + 1) * F + f] = pre[q * F + f] * s[q * F + f];
          for (int64_t q = group - 1; q >= 0; --q)
            for (int64_t f = 0; f < F; ++f) suf[q * F + f] = suf[(q + 1) * F + f] * s[q * F + f];
          for (int64_t q = 0; q < group; ++q) {
            const Corners& c = cs[q];
            for (int k = 0; k < 4; ++k) {
              float* r = R + c.row[k] * F;
              const float w = c.w[k];
              for (int64_t f = 0; f < F; ++f)
                r[f] += w * g[f] * pre[q * F + f] * suf[(q + 1) * F + f];
            }
          }
        }
      }
    }
  });
  // part tables added in part order (elementwise: the same for any thread count)
  const int64_t total = rows * F;
  at::parallel_for(0, total, 1 << 14, [=](int64_t b, int64_t e) {
    for (int64_t part = 1; part < parts; ++part) {
      const float* Rp = A + part * total;
      for (int64_t i = b; i < e; ++i) A[i] += Rp[i];
    }
  });
  return acc[0];
}

TORCH_LIBRARY_FRAGMENT(gdiff_splat, m) {
  m.def("hexplane_forward", &hexplane_forward);
  m.def("hexplane_forward_samples", &hexplane_forward_samples);
  m.def("hexplane_backward", &hexplane_backward);
}
