// torch.nn.functional.normalize (x / max(|x|, 1e-12)) of small vectors and its backward, for
// the kernels of gdiff.splat (quaternions, viewing directions).
#pragma once

#include <algorithm>
#include <cmath>

namespace gdiff_normalize {

// u = d / max(|d|, 1e-12) for d of length K; returns |d|.
template <int K, typename T>
inline T unit(const T* d, T* u) {
  T sq = 0;
  for (int i = 0; i < K; ++i) sq += d[i] * d[i];
  const T norm = std::sqrt(sq);
  const T den = std::max(norm, (T)1e-12);
  for (int i = 0; i < K; ++i) u[i] = d[i] / den;
  return norm;
}

// Gradient gd of d from the gradient gu of u = unit(d) (u and norm as unit returned them).
template <int K, typename T>
inline void unit_backward(const T* u, T norm, const T* gu, T* gd) {
  if (norm > (T)1e-12) {
    T dot = 0;
    for (int i = 0; i < K; ++i) dot += u[i] * gu[i];
    for (int i = 0; i < K; ++i) gd[i] = (gu[i] - u[i] * dot) / norm;
  } else {
    for (int i = 0; i < K; ++i) gd[i] = gu[i] / (T)1e-12;
  }
}

}  // namespace gdiff_normalize
