// Face Gaussians (recon/gaussians.face_gaussians_reference) in one pass per triangle, forward and hand-written backward.
//
// The torch version runs ~45 element-wise operators over [B, F, ...] tensors each way (gathers, crosses, norms, the
// four Shepperd formulas and their selection): on the facecap quick preset's 8042 triangles x 4 (view, time) pairs a
// training step spent ~7 ms forward and ~12 ms backward there, a sixth of the step. Here every triangle is ~150 flops
// in registers. The same rules as the reference (clamps, the argmax's first maximum, the chosen formula alone carrying
// the gradient, torch's half-and-half gradient of minimum at a tie); values agree to float rounding, tested in
// tests/test_face_gaussians.py against the reference and by gradcheck in double precision.
//
// Backward: per item b of the batch, the triangles in order, each adding its corners' gradients into that item's
// vertex gradients; the items are split across threads (fixed order: a seeded run gives the same sums every run).

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include "parallel.h"

#include <cmath>

namespace {

using t2bs_splat::parallel_items;

template <class T>
struct V3 {
  T x, y, z;
};
template <class T>
inline V3<T> operator+(V3<T> a, V3<T> b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
template <class T>
inline V3<T> operator-(V3<T> a, V3<T> b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
template <class T>
inline V3<T> operator*(V3<T> a, T s) { return {a.x * s, a.y * s, a.z * s}; }
template <class T>
inline T dot(V3<T> a, V3<T> b) { return (a.x * b.x + a.y * b.y) + a.z * b.z; }
template <class T>
inline V3<T> cross(V3<T> a, V3<T> b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

// What the forward of one triangle computes, kept for its backward.
template <class T>
struct Face {
  V3<T> p[3], c, e1, e2, nr, n, u, w, d[3];
  T ln, lu, a[3], b[3], su2, sw2, su, sw, k;
  T m[9];      // the rotation's columns u, w, n as a row-major matrix m[3 * row + col]
  int best;    // which of Shepperd's four formulas
  T arg, s;    // its square root's argument and 2 x sqrt(arg) (4 x the big component)
  T qr[4];     // the chosen formula's quaternion (x, y, z, w) before normalising
  T qn;        // its norm
  T scale[3];  // the outputs before their 1e-6 floor
};

template <class T>
inline T eps_norm() { return T(1e-12); }

// Shepperd's formulas, as recon/gaussians.frame_quat: numerators of (x, y, z, w) as m[i] + sign * m[j]; the big
// component (index ``big``) is s / 4.
struct Formula {
  int big;
  int i[4], j[4];
  float sign[4];
};
constexpr Formula FORMULAS[4] = {
    {3, {7, 2, 3, 0}, {5, 6, 1, 0}, {-1, -1, -1, 0}},   // 1 + trace: (m21 - m12, m02 - m20, m10 - m01, s/4)
    {0, {0, 1, 2, 7}, {0, 3, 6, 5}, {0, 1, 1, -1}},     // 1 + 2 m00 - trace: (s/4, m01 + m10, m02 + m20, m21 - m12)
    {1, {1, 0, 5, 2}, {3, 0, 7, 6}, {1, 0, 1, -1}},     // 1 + 2 m11 - trace: (m01 + m10, s/4, m12 + m21, m02 - m20)
    {2, {2, 5, 0, 3}, {6, 7, 0, 1}, {1, 1, 0, -1}},     // 1 + 2 m22 - trace: (m02 + m20, m12 + m21, s/4, m10 - m01)
};

template <class T>
void face_forward(const T* x, const int64_t* tri, T log_scale, T flatness, Face<T>& f, T* mean, T* quat, T* scale) {
  for (int k = 0; k < 3; ++k) f.p[k] = {x[3 * tri[k]], x[3 * tri[k] + 1], x[3 * tri[k] + 2]};
  const V3<T> sum = f.p[0] + f.p[1] + f.p[2];
  f.c = {sum.x / T(3), sum.y / T(3), sum.z / T(3)};
  f.e1 = f.p[1] - f.p[0];
  f.e2 = f.p[2] - f.p[0];
  f.nr = cross(f.e1, f.e2);
  f.ln = std::sqrt(dot(f.nr, f.nr));
  f.n = f.nr * (T(1) / std::max(f.ln, eps_norm<T>()));
  f.lu = std::sqrt(dot(f.e1, f.e1));
  f.u = f.e1 * (T(1) / std::max(f.lu, eps_norm<T>()));
  f.w = cross(f.n, f.u);
  f.su2 = f.sw2 = T(0);
  for (int k = 0; k < 3; ++k) {
    f.d[k] = f.p[k] - f.c;
    f.a[k] = dot(f.d[k], f.u);
    f.b[k] = dot(f.d[k], f.w);
    f.su2 += f.a[k] * f.a[k];
    f.sw2 += f.b[k] * f.b[k];
  }
  f.su2 /= T(3);
  f.sw2 /= T(3);
  f.su = std::sqrt(std::max(f.su2, eps_norm<T>()));
  f.sw = std::sqrt(std::max(f.sw2, eps_norm<T>()));
  f.k = std::exp(log_scale);
  f.scale[0] = f.su * f.k;
  f.scale[1] = f.sw * f.k;
  f.scale[2] = flatness * std::min(f.su, f.sw) * f.k;
  for (int i = 0; i < 3; ++i) scale[i] = std::max(f.scale[i], T(1e-6));
  for (int i = 0; i < 3; ++i) mean[i] = (&f.c.x)[i];

  const V3<T> cols[3] = {f.u, f.w, f.n};
  for (int r = 0; r < 3; ++r)
    for (int col = 0; col < 3; ++col) f.m[3 * r + col] = (&cols[col].x)[r];
  const T trace = f.m[0] + f.m[4] + f.m[8];
  const T keys[4] = {trace, f.m[0], f.m[4], f.m[8]};
  f.best = 0;
  for (int i = 1; i < 4; ++i)
    if (keys[i] > keys[f.best]) f.best = i;  // the first maximum, as torch.argmax
  f.arg = f.best == 0 ? T(1) + trace : T(1) + T(2) * keys[f.best] - trace;
  f.s = T(2) * std::sqrt(std::max(f.arg, T(1e-8)));
  const Formula& fm = FORMULAS[f.best];
  for (int i = 0; i < 4; ++i)
    f.qr[i] = i == fm.big ? T(0.25) * f.s : (f.m[fm.i[i]] + T(fm.sign[i]) * f.m[fm.j[i]]) / f.s;
  f.qn = std::sqrt((f.qr[0] * f.qr[0] + f.qr[1] * f.qr[1]) + (f.qr[2] * f.qr[2] + f.qr[3] * f.qr[3]));
  for (int i = 0; i < 4; ++i) quat[i] = f.qr[i] / f.qn;
}

// The gradient of v / max(|v|, eps) (``len`` = |v|) given the output's gradient g, as torch's norm, clamp_min and
// division backward give it: the norm's path is cut when the clamp holds.
template <class T>
inline V3<T> normalised_backward(V3<T> v, T len, V3<T> g) {
  const T l = std::max(len, eps_norm<T>());
  V3<T> out = g * (T(1) / l);
  if (len >= eps_norm<T>() && len > T(0)) out = out - v * (dot(g, v) / (l * l * len));
  return out;
}

template <class T>
void face_backward(const Face<T>& f, T flatness, const T* g_mean, const T* g_quat, const T* g_scale, T* gx,
                   const int64_t* tri) {
  // the scales: max(., 1e-6) passes the gradient where its input is >= the floor (torch's clamp_min)
  T g_su = 0, g_sw = 0;
  if (f.scale[0] >= T(1e-6)) g_su += g_scale[0] * f.k;
  if (f.scale[1] >= T(1e-6)) g_sw += g_scale[1] * f.k;
  if (f.scale[2] >= T(1e-6)) {
    const T g_min = g_scale[2] * f.k * flatness;
    if (f.su == f.sw) {
      g_su += g_min / T(2);
      g_sw += g_min / T(2);
    } else if (f.su < f.sw) {
      g_su += g_min;
    } else {
      g_sw += g_min;
    }
  }
  const T g_su2 = f.su2 >= eps_norm<T>() ? g_su * T(0.5) / f.su : T(0);
  const T g_sw2 = f.sw2 >= eps_norm<T>() ? g_sw * T(0.5) / f.sw : T(0);
  V3<T> g_u{0, 0, 0}, g_w{0, 0, 0}, g_n{0, 0, 0}, g_d[3];
  for (int k = 0; k < 3; ++k) {
    const T ga = g_su2 * T(2) * f.a[k] / T(3), gb = g_sw2 * T(2) * f.b[k] / T(3);
    g_d[k] = f.u * ga + f.w * gb;
    g_u = g_u + f.d[k] * ga;
    g_w = g_w + f.d[k] * gb;
  }

  // the quaternion: normalised, then the chosen formula
  T g_qr[4];
  const T qg = (f.qr[0] * g_quat[0] + f.qr[1] * g_quat[1]) + (f.qr[2] * g_quat[2] + f.qr[3] * g_quat[3]);
  for (int i = 0; i < 4; ++i) g_qr[i] = (g_quat[i] - f.qr[i] * qg / (f.qn * f.qn)) / f.qn;
  const Formula& fm = FORMULAS[f.best];
  T g_m[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
  T g_s = 0;
  for (int i = 0; i < 4; ++i) {
    if (i == fm.big) {
      g_s += T(0.25) * g_qr[i];
      continue;
    }
    const T num = f.m[fm.i[i]] + T(fm.sign[i]) * f.m[fm.j[i]];
    g_s -= g_qr[i] * num / (f.s * f.s);
    g_m[fm.i[i]] += g_qr[i] / f.s;
    g_m[fm.j[i]] += T(fm.sign[i]) * g_qr[i] / f.s;
  }
  if (f.arg >= T(1e-8)) {
    const T g_arg = g_s / std::sqrt(f.arg);  // d(2 sqrt(a)) / da
    // arg = 1 + trace, or 1 + 2 m_big - trace
    const int diag[3] = {0, 4, 8};
    const T sign = f.best == 0 ? T(1) : T(-1);
    for (int i = 0; i < 3; ++i) g_m[diag[i]] += sign * g_arg;
    if (f.best) g_m[diag[f.best - 1]] += T(2) * g_arg;
  }
  // m's columns are u, w, n
  g_u = g_u + V3<T>{g_m[0], g_m[3], g_m[6]};
  g_w = g_w + V3<T>{g_m[1], g_m[4], g_m[7]};
  g_n = g_n + V3<T>{g_m[2], g_m[5], g_m[8]};

  // w = n x u
  g_n = g_n + cross(f.u, g_w);
  g_u = g_u + cross(g_w, f.n);
  // u = e1 / |e1|, n = nr / |nr|, nr = e1 x e2
  V3<T> g_e1 = normalised_backward(f.e1, f.lu, g_u);
  const V3<T> g_nr = normalised_backward(f.nr, f.ln, g_n);
  g_e1 = g_e1 + cross(f.e2, g_nr);
  const V3<T> g_e2 = cross(g_nr, f.e1);
  // d_k = p_k - c, c = the corners' mean
  V3<T> g_c{g_mean[0], g_mean[1], g_mean[2]};
  for (int k = 0; k < 3; ++k) g_c = g_c - g_d[k];
  V3<T> g_p[3];
  for (int k = 0; k < 3; ++k) g_p[k] = g_d[k] + g_c * T(1.0 / 3.0);
  g_p[0] = g_p[0] - g_e1 - g_e2;
  g_p[1] = g_p[1] + g_e1;
  g_p[2] = g_p[2] + g_e2;
  for (int k = 0; k < 3; ++k) {
    T* o = gx + 3 * tri[k];
    o[0] += g_p[k].x;
    o[1] += g_p[k].y;
    o[2] += g_p[k].z;
  }
}

void check_inputs(const torch::Tensor& x, const torch::Tensor& faces, const torch::Tensor& log_scale) {
  TORCH_CHECK(x.device().is_cpu() && x.is_contiguous() && x.dim() == 3 && x.size(2) == 3,
              "x must be a contiguous CPU tensor [B, N, 3]");
  TORCH_CHECK(x.scalar_type() == torch::kFloat32 || x.scalar_type() == torch::kFloat64, "x must be float32 or 64");
  TORCH_CHECK(faces.scalar_type() == torch::kInt64 && faces.is_contiguous() && faces.dim() == 2 && faces.size(1) == 3,
              "faces must be a contiguous int64 tensor [F, 3]");
  TORCH_CHECK(log_scale.scalar_type() == x.scalar_type() && log_scale.is_contiguous() && log_scale.dim() == 1 &&
                  log_scale.size(0) == faces.size(0),
              "face_log_scale must be [F], of x's dtype");
  if (faces.numel()) {
    const auto lo = faces.min().item<int64_t>(), hi = faces.max().item<int64_t>();
    TORCH_CHECK(lo >= 0 && hi < x.size(1), "faces index vertices outside [0, ", x.size(1), ")");
  }
}

}  // namespace

std::vector<torch::Tensor> faces_forward(torch::Tensor x, torch::Tensor faces, torch::Tensor log_scale,
                                         double flatness) {
  check_inputs(x, faces, log_scale);
  const int64_t B = x.size(0), N = x.size(1), F = faces.size(0);
  auto opts = x.options();
  auto mean = torch::empty({B, F, 3}, opts), quat = torch::empty({B, F, 4}, opts), scale = torch::empty({B, F, 3}, opts);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "faces_forward", [&] {
    const scalar_t* px = x.data_ptr<scalar_t>();
    const scalar_t* pl = log_scale.data_ptr<scalar_t>();
    const int64_t* pf = faces.data_ptr<int64_t>();
    scalar_t *pm = mean.data_ptr<scalar_t>(), *pq = quat.data_ptr<scalar_t>(), *ps = scale.data_ptr<scalar_t>();
    const int64_t total = B * F, chunk = 2048;
    parallel_items((total + chunk - 1) / chunk, at::get_num_threads(), [&](int64_t ci, int) {
      Face<scalar_t> f;
      for (int64_t i = ci * chunk, e = std::min(total, i + chunk); i < e; ++i) {
        const int64_t b = i / F, j = i % F;
        face_forward<scalar_t>(px + 3 * N * b, pf + 3 * j, pl[j], (scalar_t)flatness, f, pm + 3 * i, pq + 4 * i,
                               ps + 3 * i);
      }
    });
  });
  return {mean, quat, scale};
}

torch::Tensor faces_backward(torch::Tensor x, torch::Tensor faces, torch::Tensor log_scale, double flatness,
                             torch::Tensor g_mean, torch::Tensor g_quat, torch::Tensor g_scale) {
  check_inputs(x, faces, log_scale);
  const int64_t B = x.size(0), N = x.size(1), F = faces.size(0);
  for (auto* g : {&g_mean, &g_quat, &g_scale})
    TORCH_CHECK(g->scalar_type() == x.scalar_type() && g->is_contiguous() && g->size(0) == B && g->size(1) == F,
                "the output gradients must be contiguous [B, F, k] of x's dtype");
  auto gx = torch::zeros_like(x);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "faces_backward", [&] {
    const scalar_t* px = x.data_ptr<scalar_t>();
    const scalar_t* pl = log_scale.data_ptr<scalar_t>();
    const int64_t* pf = faces.data_ptr<int64_t>();
    const scalar_t *gm = g_mean.data_ptr<scalar_t>(), *gq = g_quat.data_ptr<scalar_t>(),
                   *gs = g_scale.data_ptr<scalar_t>();
    scalar_t* pg = gx.data_ptr<scalar_t>();
    // one item per thread at a time, its triangles in order: every vertex sum has a fixed order
    parallel_items(B, at::get_num_threads(), [&](int64_t b, int) {
      Face<scalar_t> f;
      scalar_t m[3], q[4], s[3];
      for (int64_t j = 0; j < F; ++j) {
        const int64_t i = b * F + j;
        face_forward<scalar_t>(px + 3 * N * b, pf + 3 * j, pl[j], (scalar_t)flatness, f, m, q, s);
        face_backward<scalar_t>(f, (scalar_t)flatness, gm + 3 * i, gq + 4 * i, gs + 3 * i, pg + 3 * N * b, pf + 3 * j);
      }
    }, /*fixed=*/true);
  });
  return gx;
}
