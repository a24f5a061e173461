// EWA projection of 3D Gaussians into pinhole cameras: fused forward and backward kernels.
//
// Same maths as gdiff/splat/rasterize.py (covariance_3d + project_gaussians), which is the
// reference and documents the conventions:
//   R = rotation of the normalised quaternion (w, x, y, z), M = R diag(s), Sigma = M M^T
//   p = R_v mean + t_v (world-to-camera, OpenCV axes), z = p.z, zs = z if near <= z <= far else 1
//   J = [[fx/zs, 0, -fx tx/zs^2], [0, fy/zs, -fy ty/zs^2]], tx, ty = zs * (x/zs, y/zs) clamped
//       to 1.3x the field of view
//   cov2d = J R_v Sigma R_v^T J^T + eps2d I = [[a, b], [b, c]], det = a c - b^2
//   conic = (c, -b, a) / det (det replaced by 1 where culled), mean2d = (fx x/zs + cx, ...)
// The torch version builds ~100 small tensors per call and as many again in its backward pass;
// here every Gaussian is one loop body (its world covariance computed once for all cameras).
// Gaussians are independent, so the loops run on at::parallel_for and give the same result on
// any number of threads (each Gaussian's gradient sums over cameras in camera order).
//
// Only the gradients with respect to means, quats and scales are computed (the cameras are
// fixed data; rasterize.py uses the torch version when they require a gradient).
//
// The file also holds the mirror directions of gdiff/splat/reflection.py (reflect about each
// Gaussian's shortest axis), which need the same rotation of the quaternion and its gradient.

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

constexpr int64_t kGrain = 1024;

// Rotation matrix of quaternion q (w, x, y, z) normalised as torch's F.normalize (q / max(|q|,
// 1e-12)); also returns the normalised quaternion and the norm.
template <typename T>
inline void quat_rot(const T* q, T R[3][3], T qn[4], T& norm) {
  norm = gdiff_normalize::unit<4>(q, qn);
  const T w = qn[0], x = qn[1], y = qn[2], z = qn[3];
  R[0][0] = 1 - 2 * (y * y + z * z); R[0][1] = 2 * (x * y - w * z); R[0][2] = 2 * (x * z + w * y);
  R[1][0] = 2 * (x * y + w * z); R[1][1] = 1 - 2 * (x * x + z * z); R[1][2] = 2 * (y * z - w * x);
  R[2][0] = 2 * (x * z - w * y); R[2][1] = 2 * (y * z + w * x); R[2][2] = 1 - 2 * (x * x + y * y);
}

// Gradient gq [4] of the raw quaternion from the gradient gR of its rotation matrix
// (qn, norm: as returned by quat_rot).
template <typename T>
inline void quat_rot_backward(const T qn[4], T norm, const T gR[3][3], T* gq) {
  const T w = qn[0], x = qn[1], y = qn[2], z = qn[3];
  T g[4];
  g[0] = 2 * (-z * gR[0][1] + y * gR[0][2] + z * gR[1][0] - x * gR[1][2] - y * gR[2][0] +
              x * gR[2][1]);
  g[1] = 2 * (y * gR[0][1] + z * gR[0][2] + y * gR[1][0] - 2 * x * gR[1][1] - w * gR[1][2] +
              z * gR[2][0] + w * gR[2][1] - 2 * x * gR[2][2]);
  g[2] = 2 * (-2 * y * gR[0][0] + x * gR[0][1] + w * gR[0][2] + x * gR[1][0] + z * gR[1][2] -
              w * gR[2][0] + z * gR[2][1] - 2 * y * gR[2][2]);
  g[3] = 2 * (-2 * z * gR[0][0] - w * gR[0][1] + x * gR[0][2] + w * gR[1][0] -
              2 * z * gR[1][1] + y * gR[1][2] + x * gR[2][0] + y * gR[2][1]);
  gdiff_normalize::unit_backward<4>(qn, norm, g, gq);  // qn = q / max(|q|, 1e-12)
}

// Index of the smallest of s[0..2], the first one on ties (as torch.argmin).
template <typename T>
inline int argmin3(const T* s) {
  int k = 0;
  if (s[1] < s[k]) k = 1;
  if (s[2] < s[k]) k = 2;
  return k;
}

template <typename T>
inline void world_cov(const T R[3][3], const T* s, T M[3][3], T S[3][3]) {
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) M[i][j] = R[i][j] * s[j];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) S[i][j] = M[i][0] * M[j][0] + M[i][1] * M[j][1] + M[i][2] * M[j][2];
}

// Per-camera quantities shared by forward and backward.
template <typename T>
struct Cam {
  T R[3][3], t[3], fx, fy, cx, cy, lxp, lxn, lyp, lyn;
};

template <typename T>
std::vector<Cam<T>> read_cams(const at::Tensor& viewmats, const at::Tensor& Ks, int64_t W,
                              int64_t H) {
  const int64_t C = viewmats.size(0);
  auto v = viewmats.accessor<T, 3>();
  auto k = Ks.accessor<T, 3>();
  std::vector<Cam<T>> cams(C);
  for (int64_t c = 0; c < C; ++c) {
    Cam<T>& m = cams[c];
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) m.R[i][j] = v[c][i][j];
      m.t[i] = v[c][i][3];
    }
    m.fx = k[c][0][0]; m.fy = k[c][1][1]; m.cx = k[c][0][2]; m.cy = k[c][1][2];
    const T tfx = (T)0.5 * (T)W / m.fx, tfy = (T)0.5 * (T)H / m.fy;
    m.lxp = ((T)W - m.cx) / m.fx + (T)0.3 * tfx;
    m.lxn = m.cx / m.fx + (T)0.3 * tfx;
    m.lyp = ((T)H - m.cy) / m.fy + (T)0.3 * tfy;
    m.lyn = m.cy / m.fy + (T)0.3 * tfy;
  }
  return cams;
}

// Camera-frame covariance A = R_v S R_v^T.
template <typename T>
inline void cam_cov(const T Rv[3][3], const T S[3][3], T A[3][3]) {
  T RS[3][3];
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k) RS[i][k] = Rv[i][0] * S[0][k] + Rv[i][1] * S[1][k] + Rv[i][2] * S[2][k];
  for (int i = 0; i < 3; ++i)
    for (int l = 0; l < 3; ++l) A[i][l] = RS[i][0] * Rv[l][0] + RS[i][1] * Rv[l][1] + RS[i][2] * Rv[l][2];
}

// One Gaussian (world covariance S, mean mu) in one camera: the quantities the forward pass
// outputs and the backward pass differentiates.
template <typename T>
struct Projected {
  T x, y, z, zs, rx, ry, tx, ty;  // camera-frame position, safe depth, (clamped) x/z, y/z
  T j00, j02, j11, j12;           // Jacobian J = [[j00, 0, j02], [0, j11, j12]]
  T A[3][3];                      // camera-frame covariance R_v S R_v^T
  T a, b, c, det;                 // cov2d + eps2d I = [[a, b], [b, c]]
  bool in_range, ok;              // z within [near, far]; and det > 0
};

template <typename T>
inline void project_one(const Cam<T>& k, const T S[3][3], const T* mu, T eps, T near, T far,
                        Projected<T>& p) {
  p.x = k.R[0][0] * mu[0] + k.R[0][1] * mu[1] + k.R[0][2] * mu[2] + k.t[0];
  p.y = k.R[1][0] * mu[0] + k.R[1][1] * mu[1] + k.R[1][2] * mu[2] + k.t[1];
  p.z = k.R[2][0] * mu[0] + k.R[2][1] * mu[1] + k.R[2][2] * mu[2] + k.t[2];
  p.in_range = p.z >= near && p.z <= far;
  p.zs = p.in_range ? p.z : (T)1;
  p.rx = p.x / p.zs;
  p.ry = p.y / p.zs;
  p.tx = p.zs * std::min(std::max(p.rx, -k.lxn), k.lxp);
  p.ty = p.zs * std::min(std::max(p.ry, -k.lyn), k.lyp);
  p.j00 = k.fx / p.zs; p.j02 = -k.fx * p.tx / (p.zs * p.zs);
  p.j11 = k.fy / p.zs; p.j12 = -k.fy * p.ty / (p.zs * p.zs);
  cam_cov(k.R, S, p.A);
  const T(&A)[3][3] = p.A;
  const T u0 = p.j00 * A[0][0] + p.j02 * A[2][0], u1 = p.j00 * A[0][1] + p.j02 * A[2][1],
          u2 = p.j00 * A[0][2] + p.j02 * A[2][2];
  const T w1 = p.j11 * A[1][1] + p.j12 * A[2][1], w2 = p.j11 * A[1][2] + p.j12 * A[2][2];
  p.a = u0 * p.j00 + u2 * p.j02 + eps;
  p.b = u1 * p.j11 + u2 * p.j12;
  p.c = w1 * p.j11 + w2 * p.j12 + eps;
  p.det = p.a * p.c - p.b * p.b;
  p.ok = p.in_range && p.det > 0;
}

template <typename T>
std::vector<at::Tensor> forward_impl(const at::Tensor& means, const at::Tensor& quats,
                                     const at::Tensor& scales, const at::Tensor& viewmats,
                                     const at::Tensor& Ks, int64_t W, int64_t H, double near,
                                     double far, double eps2d, double radius_clip) {
  const int64_t N = means.size(0), C = viewmats.size(0);
  const auto opts = means.options();
  at::Tensor m2d = at::empty({C, N, 2}, opts), con = at::empty({C, N, 3}, opts);
  at::Tensor dep = at::empty({C, N}, opts), ext = at::empty({C, N, 2}, opts);
  at::Tensor rad = at::empty({C, N}, opts.dtype(at::kInt));
  at::Tensor vis = at::empty({C, N}, opts.dtype(at::kBool));
  const std::vector<Cam<T>> cams = read_cams<T>(viewmats, Ks, W, H);
  const T* mp = means.data_ptr<T>();
  const T* qp = quats.data_ptr<T>();
  const T* sp = scales.data_ptr<T>();
  T* m2 = m2d.data_ptr<T>();
  T* co = con.data_ptr<T>();
  T* de = dep.data_ptr<T>();
  T* ex = ext.data_ptr<T>();
  int32_t* ra = rad.data_ptr<int32_t>();
  bool* vi = vis.data_ptr<bool>();
  const T eps = (T)eps2d, Tn = (T)near, Tf = (T)far, clip = (T)radius_clip;
  at::parallel_for(0, N, kGrain, [&](int64_t b, int64_t e) {
    for (int64_t n = b; n < e; ++n) {
      T R[3][3], qn[4], qnorm, M[3][3], S[3][3];
      quat_rot(qp + 4 * n, R, qn, qnorm);
      world_cov(R, sp + 3 * n, M, S);
      const T* mu = mp + 3 * n;
      for (int64_t c = 0; c < C; ++c) {
        const Cam<T>& k = cams[c];
        const int64_t o = c * N + n;
        Projected<T> p;
        project_one(k, S, mu, eps, Tn, Tf, p);
        const T x = p.x, y = p.y, z = p.z, zs = p.zs, a = p.a, cc = p.c, bb = p.b, det = p.det;
        bool ok = p.ok;
        const T ds = ok ? det : (T)1;
        co[3 * o] = cc / ds; co[3 * o + 1] = -bb / ds; co[3 * o + 2] = a / ds;
        const T mx = k.fx * x / zs + k.cx, my = k.fy * y / zs + k.cy;
        m2[2 * o] = mx; m2[2 * o + 1] = my;
        de[o] = z;
        const T mid = (T)0.5 * (a + cc);
        const T lam = mid + std::sqrt(std::max(mid * mid - det, (T)0.1));
        const T radius = std::ceil((T)3 * std::sqrt(std::max(lam, (T)0)));
        ok = ok && radius > clip && mx + radius > 0 && mx - radius < (T)W && my + radius > 0 &&
             my - radius < (T)H;
        ra[o] = ok ? (int32_t)radius : 0;
        vi[o] = ok;
        ex[2 * o] = (T)3 * std::sqrt(std::max(a, (T)0));
        ex[2 * o + 1] = (T)3 * std::sqrt(std::max(cc, (T)0));
      }
    }
  });
  return {m2d, con, dep, rad, ext, vis};
}

template <typename T>
std::vector<at::Tensor> backward_impl(const at::Tensor& means, const at::Tensor& quats,
                                      const at::Tensor& scales, const at::Tensor& viewmats,
                                      const at::Tensor& Ks, int64_t W, int64_t H, double near,
                                      double far, double eps2d, const at::Tensor& g_m2d,
                                      const at::Tensor& g_con, const at::Tensor& g_dep) {
  const int64_t N = means.size(0), C = viewmats.size(0);
  at::Tensor gm = at::empty({N, 3}, means.options()), gq = at::empty({N, 4}, means.options()),
             gs = at::empty({N, 3}, means.options());
  const std::vector<Cam<T>> cams = read_cams<T>(viewmats, Ks, W, H);
  const T* mp = means.data_ptr<T>();
  const T* qp = quats.data_ptr<T>();
  const T* sp = scales.data_ptr<T>();
  const T* gm2 = g_m2d.data_ptr<T>();
  const T* gco = g_con.data_ptr<T>();
  const T* gde = g_dep.data_ptr<T>();
  T* gmp = gm.data_ptr<T>();
  T* gqp = gq.data_ptr<T>();
  T* gsp = gs.data_ptr<T>();
  const T eps = (T)eps2d, Tn = (T)near, Tf = (T)far;
  at::parallel_for(0, N, kGrain, [&](int64_t b, int64_t e) {
    for (int64_t n = b; n < e; ++n) {
      T R[3][3], qn[4], qnorm, M[3][3], S[3][3];
      const T* q = qp + 4 * n;
      const T* s = sp + 3 * n;
      quat_rot(q, R, qn, qnorm);
      world_cov(R, s, M, S);
      const T* mu = mp + 3 * n;
      T gS[3][3] = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}};
      T gmu[3] = {0, 0, 0};
      for (int64_t c = 0; c < C; ++c) {
        const Cam<T>& k = cams[c];
        const int64_t o = c * N + n;
        Projected<T> p;
        project_one(k, S, mu, eps, Tn, Tf, p);
        const T x = p.x, y = p.y, zs = p.zs, rx = p.rx, ry = p.ry, tx = p.tx, ty = p.ty;
        const T j00 = p.j00, j02 = p.j02, j11 = p.j11, j12 = p.j12;
        const T(&A)[3][3] = p.A;
        const T a = p.a, bb = p.b, cc = p.c;
        const bool in_range = p.in_range, ok = p.ok;
        const bool free_x = rx > -k.lxn && rx < k.lxp, free_y = ry > -k.lyn && ry < k.lyp;
        const T ds = ok ? p.det : (T)1;
        // conic = (cc, -bb, a) / ds
        const T gc0 = gco[3 * o], gc1 = gco[3 * o + 1], gc2 = gco[3 * o + 2];
        T ga = gc2 / ds, gb = -gc1 / ds, gcc = gc0 / ds;
        if (ok) {
          const T gdet = -(gc0 * cc - gc1 * bb + gc2 * a) / (ds * ds);
          ga += gdet * cc; gcc += gdet * a; gb += gdet * (-2 * bb);
        }
        // cov2d = J A J^T; G2 = [[ga, gb], [0, gcc]] (b is entry (0, 1) only)
        // dA = J^T G2 J ; dJ = (G2 + G2^T) J A
        const T J[2][3] = {{j00, 0, j02}, {0, j11, j12}};
        const T G2[2][2] = {{ga, gb}, {0, gcc}};
        T GJ[2][3];  // G2 J
        for (int i = 0; i < 2; ++i)
          for (int l = 0; l < 3; ++l) GJ[i][l] = G2[i][0] * J[0][l] + G2[i][1] * J[1][l];
        T gA[3][3];
        for (int i = 0; i < 3; ++i)
          for (int l = 0; l < 3; ++l) gA[i][l] = J[0][i] * GJ[0][l] + J[1][i] * GJ[1][l];
        const T Gs[2][2] = {{2 * ga, gb}, {gb, 2 * gcc}};
        T gJ[2][3];
        for (int i = 0; i < 2; ++i) {
          T JA[3];
          for (int l = 0; l < 3; ++l) JA[l] = 0;
          for (int m = 0; m < 2; ++m)
            for (int l = 0; l < 3; ++l)
              JA[l] += Gs[i][m] * (J[m][0] * A[0][l] + J[m][1] * A[1][l] + J[m][2] * A[2][l]);
          for (int l = 0; l < 3; ++l) gJ[i][l] = JA[l];
        }
        // dS = R_v^T dA R_v
        for (int j = 0; j < 3; ++j)
          for (int kk = 0; kk < 3; ++kk) {
            T acc = 0;
            for (int i = 0; i < 3; ++i)
              for (int l = 0; l < 3; ++l) acc += k.R[i][j] * gA[i][l] * k.R[l][kk];
            gS[j][kk] += acc;
          }
        // J entries -> zs, tx, ty
        const T zs2 = zs * zs, zs3 = zs2 * zs;
        T gzs = gJ[0][0] * (-k.fx / zs2) + gJ[0][2] * (2 * k.fx * tx / zs3) +
                gJ[1][1] * (-k.fy / zs2) + gJ[1][2] * (2 * k.fy * ty / zs3);
        const T gtx = gJ[0][2] * (-k.fx / zs2), gty = gJ[1][2] * (-k.fy / zs2);
        T gx = 0, gy = 0, gz = 0;
        if (free_x) gx += gtx; else gzs += gtx * std::min(std::max(rx, -k.lxn), k.lxp);
        if (free_y) gy += gty; else gzs += gty * std::min(std::max(ry, -k.lyn), k.lyp);
        // mean2d
        const T gu = gm2[2 * o], gv = gm2[2 * o + 1];
        gx += gu * k.fx / zs; gy += gv * k.fy / zs;
        gzs += -gu * k.fx * x / zs2 - gv * k.fy * y / zs2;
        if (in_range) gz += gzs;
        gz += gde[o];
        for (int j = 0; j < 3; ++j) gmu[j] += k.R[0][j] * gx + k.R[1][j] * gy + k.R[2][j] * gz;
      }
      for (int j = 0; j < 3; ++j) gmp[3 * n + j] = gmu[j];
      // S = M M^T -> dM = (gS + gS^T) M ; M = R diag(s)
      T gR[3][3];
      for (int j = 0; j < 3; ++j) gsp[3 * n + j] = 0;
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
          T gM = 0;
          for (int l = 0; l < 3; ++l) gM += (gS[i][l] + gS[l][i]) * M[l][j];
          gR[i][j] = gM * s[j];
          gsp[3 * n + j] += gM * R[i][j];
        }
      quat_rot_backward(qn, qnorm, gR, gqp + 4 * n);
    }
  });
  return {gm, gq, gs};
}

// Mirror directions (gdiff/splat/reflection.py: reflect(dirs, shortest_axis(quats, scales))):
//   d = dir / max(|dir|, 1e-12), n = column argmin(s) of R(q), r = d - 2 (d . n) n
// Column nv of R(q) along the smallest scale (its index is returned), with quat_rot's qn, norm.
template <typename T>
inline int shortest_axis(const T* q, const T* s, T qn[4], T& qnorm, T nv[3]) {
  T R[3][3];
  quat_rot(q, R, qn, qnorm);
  const int k = argmin3(s);
  for (int i = 0; i < 3; ++i) nv[i] = R[i][k];
  return k;
}

template <typename T>
at::Tensor reflect_forward_impl(const at::Tensor& dirs, const at::Tensor& quats,
                                const at::Tensor& scales) {
  const int64_t C = dirs.size(0), N = dirs.size(1);
  at::Tensor out = at::empty({C, N, 3}, dirs.options());
  const T* dp = dirs.data_ptr<T>();
  const T* qp = quats.data_ptr<T>();
  const T* sp = scales.data_ptr<T>();
  T* op = out.data_ptr<T>();
  at::parallel_for(0, N, kGrain, [&](int64_t b, int64_t e) {
    for (int64_t n = b; n < e; ++n) {
      T qn[4], qnorm, nv[3], d[3];
      const int k = shortest_axis(qp + 4 * n, sp + 3 * n, qn, qnorm, nv);
      for (int64_t c = 0; c < C; ++c) {
        const int64_t o = c * N + n;
        gdiff_normalize::unit<3>(dp + 3 * o, d);
        const T dot = d[0] * nv[0] + d[1] * nv[1] + d[2] * nv[2];
        for (int i = 0; i < 3; ++i) op[3 * o + i] = d[i] - 2 * dot * nv[i];
      }
    }
  });
  return out;
}

template <typename T>
std::vector<at::Tensor> reflect_backward_impl(const at::Tensor& dirs, const at::Tensor& quats,
                                              const at::Tensor& scales, const at::Tensor& grad) {
  const int64_t C = dirs.size(0), N = dirs.size(1);
  at::Tensor g_dirs = at::empty({C, N, 3}, dirs.options());
  at::Tensor g_quats = at::empty({N, 4}, dirs.options());
  const T* dp = dirs.data_ptr<T>();
  const T* qp = quats.data_ptr<T>();
  const T* sp = scales.data_ptr<T>();
  const T* gp = grad.data_ptr<T>();
  T* gdp = g_dirs.data_ptr<T>();
  T* gqp = g_quats.data_ptr<T>();
  at::parallel_for(0, N, kGrain, [&](int64_t b, int64_t e) {
    for (int64_t n = b; n < e; ++n) {
      T qn[4], qnorm, nv[3], d[3];
      const int k = shortest_axis(qp + 4 * n, sp + 3 * n, qn, qnorm, nv);
      T gn[3] = {0, 0, 0};
      for (int64_t c = 0; c < C; ++c) {
        const int64_t o = c * N + n;
        const T norm = gdiff_normalize::unit<3>(dp + 3 * o, d);
        const T* g = gp + 3 * o;
        const T dot = d[0] * nv[0] + d[1] * nv[1] + d[2] * nv[2];
        const T gdot = g[0] * nv[0] + g[1] * nv[1] + g[2] * nv[2];
        T gd[3];
        for (int i = 0; i < 3; ++i) {
          gd[i] = g[i] - 2 * gdot * nv[i];
          gn[i] += -2 * (dot * g[i] + gdot * d[i]);
        }
        gdiff_normalize::unit_backward<3>(d, norm, gd, gdp + 3 * o);
      }
      T gR[3][3] = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}};
      for (int i = 0; i < 3; ++i) gR[i][k] = gn[i];
      quat_rot_backward(qn, qnorm, gR, gqp + 4 * n);
    }
  });
  return {g_dirs, g_quats};
}

void check(const at::Tensor& t, const char* name, std::vector<int64_t> shape) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  TORCH_CHECK(t.dim() == (int64_t)shape.size(), name, " has the wrong number of dimensions");
  for (size_t i = 0; i < shape.size(); ++i)
    TORCH_CHECK(shape[i] < 0 || t.size(i) == shape[i], name, " has the wrong shape");
}

void check_inputs(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                  const at::Tensor& viewmats, const at::Tensor& Ks) {
  const int64_t N = means.size(0), C = viewmats.size(0);
  check(means, "means", {N, 3}); check(quats, "quats", {N, 4}); check(scales, "scales", {N, 3});
  check(viewmats, "viewmats", {C, 4, 4}); check(Ks, "Ks", {C, 3, 3});
  for (const at::Tensor* t : {&quats, &scales, &viewmats, &Ks})
    TORCH_CHECK(t->scalar_type() == means.scalar_type(), "all inputs must share one dtype");
}

std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                        at::Tensor viewmats, at::Tensor Ks, int64_t width,
                                        int64_t height, double near_plane, double far_plane,
                                        double eps2d, double radius_clip) {
  check_inputs(means, quats, scales, viewmats, Ks);
  std::vector<at::Tensor> res;
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "gdiff_project_forward", [&] {
    res = forward_impl<scalar_t>(means, quats, scales, viewmats, Ks, width, height, near_plane,
                                 far_plane, eps2d, radius_clip);
  });
  return res;
}

std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                         at::Tensor viewmats, at::Tensor Ks, int64_t width,
                                         int64_t height, double near_plane, double far_plane,
                                         double eps2d, at::Tensor grad_means2d,
                                         at::Tensor grad_conics, at::Tensor grad_depths) {
  check_inputs(means, quats, scales, viewmats, Ks);
  const int64_t N = means.size(0), C = viewmats.size(0);
  check(grad_means2d, "grad_means2d", {C, N, 2}); check(grad_conics, "grad_conics", {C, N, 3});
  check(grad_depths, "grad_depths", {C, N});
  std::vector<at::Tensor> res;
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "gdiff_project_backward", [&] {
    res = backward_impl<scalar_t>(means, quats, scales, viewmats, Ks, width, height, near_plane,
                                  far_plane, eps2d, grad_means2d, grad_conics, grad_depths);
  });
  return res;
}

void check_reflect(const at::Tensor& dirs, const at::Tensor& quats, const at::Tensor& scales) {
  const int64_t C = dirs.size(0), N = dirs.dim() == 3 ? dirs.size(1) : -1;
  check(dirs, "dirs", {C, N, 3}); check(quats, "quats", {N, 4}); check(scales, "scales", {N, 3});
  TORCH_CHECK(quats.scalar_type() == dirs.scalar_type() &&
              scales.scalar_type() == dirs.scalar_type(), "all inputs must share one dtype");
}

at::Tensor reflect_forward(at::Tensor dirs, at::Tensor quats, at::Tensor scales) {
  check_reflect(dirs, quats, scales);
  at::Tensor out;
  AT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "gdiff_reflect_forward", [&] {
    out = reflect_forward_impl<scalar_t>(dirs, quats, scales);
  });
  return out;
}

std::vector<at::Tensor> reflect_backward(at::Tensor dirs, at::Tensor quats, at::Tensor scales,
                                         at::Tensor grad) {
  check_reflect(dirs, quats, scales);
  check(grad, "grad", {dirs.size(0), dirs.size(1), 3});
  std::vector<at::Tensor> res;
  AT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "gdiff_reflect_backward", [&] {
    res = reflect_backward_impl<scalar_t>(dirs, quats, scales, grad);
  });
  return res;
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(gdiff_splat, m) {
  // mirror directions [C, N, 3] of dirs [C, N, 3] about the Gaussians' shortest axes
  m.def("reflect_forward", &reflect_forward);
  // (grad_dirs [C, N, 3], grad_quats [N, 4])
  m.def("reflect_backward", &reflect_backward);
  // (means2d, conics, depths, radii, extents, visible)
  m.def("project_forward", &project_forward);
  // (grad_means, grad_quats, grad_scales)
  m.def("project_backward", &project_backward);
}
