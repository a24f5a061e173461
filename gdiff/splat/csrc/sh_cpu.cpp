// View-dependent colour from spherical harmonics: fused forward and backward kernels.
//
// Same maths, basis order and constants as gdiff/splat/sh.py (sh_to_color), the reference:
//   d = dir / max(|dir|, 1e-12),  colour = max(sum_k basis_k(d) coeff_k + 0.5, 0)
// for coeffs [N, K, 3] (the first (degree + 1)^2 used) seen along dirs [C, N, 3]. The torch
// version evaluates 16 basis functions as separate tensors (and as many again for the
// gradient); here each (camera, Gaussian) is one loop body. Gaussians are independent, so the
// loops run on at::parallel_for and sum each Gaussian's coefficient gradient over the cameras
// in camera order: the same result on any number of threads.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "normalize.h"

namespace {

constexpr double C0 = 0.28209479177387814;
constexpr double C1 = 0.4886025119029199;
constexpr double C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                          -1.0925484305920792, 0.5462742152960396};
constexpr double C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                          0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                          -0.5900435899266435};

// Basis values b[0..n) at the unit direction (x, y, z); with grad, also db/dx, db/dy, db/dz.
template <typename T>
inline void basis(int degree, T x, T y, T z, T* b, T* bx, T* by, T* bz) {
  b[0] = (T)C0;
  if (bx) { bx[0] = 0; by[0] = 0; bz[0] = 0; }
  if (degree < 1) return;
  b[1] = -(T)C1 * y; b[2] = (T)C1 * z; b[3] = -(T)C1 * x;
  if (bx) {
    bx[1] = 0; by[1] = -(T)C1; bz[1] = 0;
    bx[2] = 0; by[2] = 0; bz[2] = (T)C1;
    bx[3] = -(T)C1; by[3] = 0; bz[3] = 0;
  }
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z;
  b[4] = (T)C2[0] * x * y;
  b[5] = (T)C2[1] * y * z;
  b[6] = (T)C2[2] * ((T)2 * zz - xx - yy);
  b[7] = (T)C2[3] * x * z;
  b[8] = (T)C2[4] * (xx - yy);
  if (bx) {
    bx[4] = (T)C2[0] * y; by[4] = (T)C2[0] * x; bz[4] = 0;
    bx[5] = 0; by[5] = (T)C2[1] * z; bz[5] = (T)C2[1] * y;
    bx[6] = -(T)2 * (T)C2[2] * x; by[6] = -(T)2 * (T)C2[2] * y; bz[6] = (T)4 * (T)C2[2] * z;
    bx[7] = (T)C2[3] * z; by[7] = 0; bz[7] = (T)C2[3] * x;
    bx[8] = (T)2 * (T)C2[4] * x; by[8] = -(T)2 * (T)C2[4] * y; bz[8] = 0;
  }
  if (degree < 3) return;
  b[9] = (T)C3[0] * y * ((T)3 * xx - yy);
  b[10] = (T)C3[1] * x * y * z;
  b[11] = (T)C3[2] * y * ((T)4 * zz - xx - yy);
  b[12] = (T)C3[3] * z * ((T)2 * zz - (T)3 * xx - (T)3 * yy);
  b[13] = (T)C3[4] * x * ((T)4 * zz - xx - yy);
  b[14] = (T)C3[5] * z * (xx - yy);
  b[15] = (T)C3[6] * x * (xx - (T)3 * yy);
  if (bx) {
    bx[9] = (T)C3[0] * (T)6 * x * y; by[9] = (T)C3[0] * ((T)3 * xx - (T)3 * yy); bz[9] = 0;
    bx[10] = (T)C3[1] * y * z; by[10] = (T)C3[1] * x * z; bz[10] = (T)C3[1] * x * y;
    bx[11] = (T)C3[2] * (-(T)2 * x * y);
    by[11] = (T)C3[2] * ((T)4 * zz - xx - (T)3 * yy);
    bz[11] = (T)C3[2] * (T)8 * y * z;
    bx[12] = (T)C3[3] * (-(T)6 * x * z);
    by[12] = (T)C3[3] * (-(T)6 * y * z);
    bz[12] = (T)C3[3] * ((T)6 * zz - (T)3 * xx - (T)3 * yy);
    bx[13] = (T)C3[4] * ((T)4 * zz - (T)3 * xx - yy);
    by[13] = (T)C3[4] * (-(T)2 * x * y);
    bz[13] = (T)C3[4] * (T)8 * x * z;
    bx[14] = (T)C3[5] * (T)2 * x * z; by[14] = -(T)C3[5] * (T)2 * y * z; bz[14] = (T)C3[5] * (xx - yy);
    bx[15] = (T)C3[6] * ((T)3 * xx - (T)3 * yy); by[15] = (T)C3[6] * (-(T)6 * x * y); bz[15] = 0;
  }
}

template <typename T>
at::Tensor forward_impl(const at::Tensor& coeffs, const at::Tensor& dirs, int64_t degree) {
  const int64_t N = coeffs.size(0), K = coeffs.size(1), C = dirs.size(0);
  const int nb = (int)((degree + 1) * (degree + 1));
  at::Tensor out = at::empty({C, N, 3}, coeffs.options());
  const T* cp = coeffs.data_ptr<T>();
  const T* dp = dirs.data_ptr<T>();
  T* op = out.data_ptr<T>();
  at::parallel_for(0, N, 1024, [&](int64_t b, int64_t e) {
    T bs[16], u[3];
    for (int64_t n = b; n < e; ++n) {
      const T* cf = cp + n * K * 3;
      for (int64_t c = 0; c < C; ++c) {
        const int64_t o = c * N + n;
        gdiff_normalize::unit<3>(dp + 3 * o, u);
        basis<T>((int)degree, u[0], u[1], u[2], bs, nullptr, nullptr, nullptr);
        for (int ch = 0; ch < 3; ++ch) {
          T acc = 0;
          for (int k = 0; k < nb; ++k) acc += bs[k] * cf[k * 3 + ch];
          op[3 * o + ch] = std::max(acc + (T)0.5, (T)0);
        }
      }
    }
  });
  return out;
}

template <typename T>
std::vector<at::Tensor> backward_impl(const at::Tensor& coeffs, const at::Tensor& dirs,
                                      int64_t degree, const at::Tensor& grad) {
  const int64_t N = coeffs.size(0), K = coeffs.size(1), C = dirs.size(0);
  const int nb = (int)((degree + 1) * (degree + 1));
  at::Tensor gc = at::empty({N, K, 3}, coeffs.options());  // every entry written below
  at::Tensor gd = at::empty({C, N, 3}, coeffs.options());
  const T* cp = coeffs.data_ptr<T>();
  const T* dp = dirs.data_ptr<T>();
  const T* gp = grad.data_ptr<T>();
  T* gcp = gc.data_ptr<T>();
  T* gdp = gd.data_ptr<T>();
  at::parallel_for(0, N, 1024, [&](int64_t b, int64_t e) {
    T bs[16], bx[16], by[16], bz[16], u[3];
    for (int64_t n = b; n < e; ++n) {
      const T* cf = cp + n * K * 3;
      T* gcf = gcp + n * K * 3;
      std::fill(gcf, gcf + K * 3, (T)0);
      for (int64_t c = 0; c < C; ++c) {
        const int64_t o = c * N + n;
        const T norm = gdiff_normalize::unit<3>(dp + 3 * o, u);
        basis<T>((int)degree, u[0], u[1], u[2], bs, bx, by, bz);
        T g[3];
        for (int ch = 0; ch < 3; ++ch) {
          T acc = 0;
          for (int k = 0; k < nb; ++k) acc += bs[k] * cf[k * 3 + ch];
          // clamp_min passes the gradient where its input is >= the bound
          g[ch] = acc + (T)0.5 >= (T)0 ? gp[3 * o + ch] : (T)0;
        }
        T gu[3] = {0, 0, 0};
        for (int k = 0; k < nb; ++k) {
          T gb = 0;
          for (int ch = 0; ch < 3; ++ch) {
            gcf[k * 3 + ch] += bs[k] * g[ch];
            gb += cf[k * 3 + ch] * g[ch];
          }
          gu[0] += gb * bx[k]; gu[1] += gb * by[k]; gu[2] += gb * bz[k];
        }
        gdiff_normalize::unit_backward<3>(u, norm, gu, gdp + 3 * o);  // u = d / max(|d|, 1e-12)
      }
    }
  });
  return {gc, gd};
}

void check(const at::Tensor& coeffs, const at::Tensor& dirs, int64_t degree) {
  TORCH_CHECK(degree >= 0 && degree <= 3, "sh degree must be in 0..3");
  TORCH_CHECK(coeffs.device().is_cpu() && dirs.device().is_cpu(), "sh: CPU tensors only");
  TORCH_CHECK(coeffs.is_contiguous() && dirs.is_contiguous(), "sh: contiguous tensors only");
  TORCH_CHECK(coeffs.dim() == 3 && coeffs.size(2) == 3 && coeffs.size(1) >= (degree + 1) * (degree + 1),
              "sh: coeffs must be [N, K, 3] with K >= (degree + 1)^2");
  TORCH_CHECK(dirs.dim() == 3 && dirs.size(1) == coeffs.size(0) && dirs.size(2) == 3,
              "sh: dirs must be [C, N, 3]");
  TORCH_CHECK(coeffs.scalar_type() == dirs.scalar_type(), "sh: coeffs and dirs share one dtype");
}

at::Tensor sh_forward(at::Tensor coeffs, at::Tensor dirs, int64_t degree) {
  check(coeffs, dirs, degree);
  at::Tensor out;
  AT_DISPATCH_FLOATING_TYPES(coeffs.scalar_type(), "gdiff_sh_forward", [&] {
    out = forward_impl<scalar_t>(coeffs, dirs, degree);
  });
  return out;
}

std::vector<at::Tensor> sh_backward(at::Tensor coeffs, at::Tensor dirs, int64_t degree,
                                    at::Tensor grad) {
  check(coeffs, dirs, degree);
  TORCH_CHECK(grad.is_contiguous() && grad.sizes() == dirs.sizes(), "sh: grad must be [C, N, 3]");
  std::vector<at::Tensor> res;
  AT_DISPATCH_FLOATING_TYPES(coeffs.scalar_type(), "gdiff_sh_backward", [&] {
    res = backward_impl<scalar_t>(coeffs, dirs, degree, grad);
  });
  return res;
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(gdiff_splat, m) {
  // colours [C, N, 3]
  m.def("sh_forward", &sh_forward);
  // (grad_coeffs [N, K, 3], grad_dirs [C, N, 3])
  m.def("sh_backward", &sh_backward);
}
