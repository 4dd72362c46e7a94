// Linear blend skinning (recon/lbs.lbs_reference's blend and apply) in one pass per vertex, forward and backward.
//
// The torch version blends the control points' packed transforms with a sparse matmul, then applies them with
// ~25 element-wise operators over [B, N, 3, 3] and [B, N, 4, 4] temporaries: on the 23.5k-vertex demo fox that was
// 20 ms forward a quick-preset step (4 items) and about twice that backward. Here a vertex's 16 blended numbers stay
// in registers. Values agree with the reference to float rounding (the blend sums its knn terms in neighbour order,
// the sparse matmul in control-point order), tested in tests/test_skinning.py, with gradcheck in double precision.
//
// packed [B, K, 16] per control point: its rotation matrix (9, row-major), offset (3: T_k x = R_k x + offset_k) and
// unit quaternion (4, XYZW); x [1 | B, N, 3] rest positions; q_rest [N, 4] XYZW rest orientations; neighbours,
// weights [N, knn]. Out: positions [B, N, 3] = M x + b with (M, b) the weighted sums, rotations [B, N, 4] =
// q_rest's right-product matrix times the normalised weighted quaternion.
// Backward: the control points' gradients are summed per item b, its vertices in order (items split across threads,
// fixed order: a seeded run gives the same sums every run).

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include "parallel.h"

#include <cmath>

namespace {

using t2bs_splat::parallel_items;

// p (x) q = R(q) p (recon/lbs.quat_right_matrix), q and p XYZW: row i of R(q).
template <class T>
inline void right_matrix(const T* q, T R[16]) {
  const T x = q[0], y = q[1], z = q[2], w = q[3];
  const T r[16] = {w, z, -y, x, -z, w, x, y, y, -x, w, z, -x, -y, -z, w};
  for (int i = 0; i < 16; ++i) R[i] = r[i];
}

template <class T>
inline void blend(const T* packed_b, const int64_t* nb, const T* w, int64_t knn, T bl[16]) {
  for (int c = 0; c < 16; ++c) bl[c] = T(0);
  for (int64_t j = 0; j < knn; ++j) {
    const T* p = packed_b + 16 * nb[j];
    for (int c = 0; c < 16; ++c) bl[c] += w[j] * p[c];
  }
}

void check_inputs(const torch::Tensor& packed, const torch::Tensor& x, const torch::Tensor& q_rest,
                  const torch::Tensor& neighbours, const torch::Tensor& weights) {
  const auto dt = packed.scalar_type();
  TORCH_CHECK(dt == torch::kFloat32 || dt == torch::kFloat64, "packed must be float32 or float64");
  for (const auto* t : {&packed, &x, &q_rest, &weights})
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && t->scalar_type() == dt,
                "skinning inputs must be contiguous CPU tensors of one float dtype");
  TORCH_CHECK(packed.dim() == 3 && packed.size(2) == 16, "packed must be [B, K, 16]");
  TORCH_CHECK(x.dim() == 3 && x.size(2) == 3 && (x.size(0) == 1 || x.size(0) == packed.size(0)),
              "x must be [1 or B, N, 3]");
  const int64_t n = x.size(1);
  TORCH_CHECK(q_rest.dim() == 2 && q_rest.size(0) == n && q_rest.size(1) == 4, "q_rest must be [N, 4]");
  TORCH_CHECK(neighbours.scalar_type() == torch::kInt64 && neighbours.is_contiguous() && neighbours.dim() == 2 &&
                  neighbours.size(0) == n,
              "neighbours must be a contiguous int64 tensor [N, knn]");
  TORCH_CHECK(weights.dim() == 2 && weights.size(0) == n && weights.size(1) == neighbours.size(1),
              "weights must be [N, knn]");
  if (neighbours.numel()) {
    TORCH_CHECK(neighbours.min().item<int64_t>() >= 0 && neighbours.max().item<int64_t>() < packed.size(1),
                "neighbours index control points outside [0, ", packed.size(1), ")");
  }
}

}  // namespace

std::vector<torch::Tensor> skin_forward(torch::Tensor packed, torch::Tensor x, torch::Tensor q_rest,
                                        torch::Tensor neighbours, torch::Tensor weights) {
  check_inputs(packed, x, q_rest, neighbours, weights);
  const int64_t B = packed.size(0), K = packed.size(1), N = x.size(1), knn = neighbours.size(1);
  auto xt = torch::empty({B, N, 3}, packed.options()), qt = torch::empty({B, N, 4}, packed.options());
  AT_DISPATCH_FLOATING_TYPES(packed.scalar_type(), "skin_forward", [&] {
    const scalar_t *pp = packed.data_ptr<scalar_t>(), *px = x.data_ptr<scalar_t>(), *pq = q_rest.data_ptr<scalar_t>(),
                   *pw = weights.data_ptr<scalar_t>();
    const int64_t* pn = neighbours.data_ptr<int64_t>();
    scalar_t *ox = xt.data_ptr<scalar_t>(), *oq = qt.data_ptr<scalar_t>();
    const int64_t sx = x.size(0) > 1 ? N : 0, total = B * N, chunk = 1024;
    parallel_items((total + chunk - 1) / chunk, at::get_num_threads(), [&](int64_t ci, int) {
      scalar_t bl[16], R[16];
      for (int64_t i = ci * chunk, e = std::min(total, i + chunk); i < e; ++i) {
        const int64_t b = i / N, n = i % N;
        blend(pp + 16 * K * b, pn + knn * n, pw + knn * n, knn, bl);
        const scalar_t* xv = px + 3 * (b * sx + n);
        for (int r = 0; r < 3; ++r)
          ox[3 * i + r] = ((bl[3 * r] * xv[0] + bl[3 * r + 1] * xv[1]) + bl[3 * r + 2] * xv[2]) + bl[9 + r];
        const scalar_t* bq = bl + 12;
        const scalar_t len = std::sqrt((bq[0] * bq[0] + bq[1] * bq[1]) + (bq[2] * bq[2] + bq[3] * bq[3]));
        const scalar_t inv = scalar_t(1) / std::max(len, scalar_t(1e-12));
        right_matrix(pq + 4 * n, R);
        for (int r = 0; r < 4; ++r)
          oq[4 * i + r] = ((R[4 * r] * bq[0] + R[4 * r + 1] * bq[1]) + R[4 * r + 2] * bq[2] + R[4 * r + 3] * bq[3]) * inv;
      }
    });
  });
  return {xt, qt};
}

std::vector<torch::Tensor> skin_backward(torch::Tensor packed, torch::Tensor x, torch::Tensor q_rest,
                                         torch::Tensor neighbours, torch::Tensor weights, torch::Tensor g_xt,
                                         torch::Tensor g_qt) {
  check_inputs(packed, x, q_rest, neighbours, weights);
  const int64_t B = packed.size(0), K = packed.size(1), N = x.size(1), knn = neighbours.size(1);
  TORCH_CHECK(g_xt.sizes() == torch::IntArrayRef({B, N, 3}) && g_qt.sizes() == torch::IntArrayRef({B, N, 4}) &&
                  g_xt.is_contiguous() && g_qt.is_contiguous() && g_xt.scalar_type() == packed.scalar_type() &&
                  g_qt.scalar_type() == packed.scalar_type(),
              "the output gradients must be contiguous [B, N, 3] and [B, N, 4] of packed's dtype");
  auto g_packed = torch::zeros_like(packed);
  auto g_x = torch::empty({B, N, 3}, packed.options());  // per item; the caller sums a shared x's
  AT_DISPATCH_FLOATING_TYPES(packed.scalar_type(), "skin_backward", [&] {
    const scalar_t *pp = packed.data_ptr<scalar_t>(), *px = x.data_ptr<scalar_t>(), *pq = q_rest.data_ptr<scalar_t>(),
                   *pw = weights.data_ptr<scalar_t>(), *gx = g_xt.data_ptr<scalar_t>(), *gq = g_qt.data_ptr<scalar_t>();
    const int64_t* pn = neighbours.data_ptr<int64_t>();
    scalar_t *gp = g_packed.data_ptr<scalar_t>(), *ogx = g_x.data_ptr<scalar_t>();
    const int64_t sx = x.size(0) > 1 ? N : 0;
    parallel_items(B, at::get_num_threads(), [&](int64_t b, int) {
      scalar_t bl[16], R[16], g[16];
      const scalar_t* packed_b = pp + 16 * K * b;
      scalar_t* gp_b = gp + 16 * K * b;
      for (int64_t n = 0; n < N; ++n) {
        const int64_t i = b * N + n;
        blend(packed_b, pn + knn * n, pw + knn * n, knn, bl);
        const scalar_t* xv = px + 3 * (b * sx + n);
        const scalar_t* gxt = gx + 3 * i;
        // positions: xt_r = sum_c M[r][c] x_c + b_r
        for (int r = 0; r < 3; ++r) {
          for (int c = 0; c < 3; ++c) g[3 * r + c] = gxt[r] * xv[c];
          g[9 + r] = gxt[r];
        }
        for (int c = 0; c < 3; ++c)
          ogx[3 * i + c] = (bl[c] * gxt[0] + bl[3 + c] * gxt[1]) + bl[6 + c] * gxt[2];
        // rotations: qt = R (bq / max(|bq|, eps))
        const scalar_t* bq = bl + 12;
        const scalar_t len = std::sqrt((bq[0] * bq[0] + bq[1] * bq[1]) + (bq[2] * bq[2] + bq[3] * bq[3]));
        const scalar_t l = std::max(len, scalar_t(1e-12));
        right_matrix(pq + 4 * n, R);
        scalar_t g_qn[4];
        for (int c = 0; c < 4; ++c)
          g_qn[c] = (R[c] * gq[4 * i] + R[4 + c] * gq[4 * i + 1]) + R[8 + c] * gq[4 * i + 2] + R[12 + c] * gq[4 * i + 3];
        scalar_t dotv = 0;
        for (int c = 0; c < 4; ++c) dotv += g_qn[c] * bq[c];
        const bool through_norm = len >= scalar_t(1e-12) && len > scalar_t(0);
        for (int c = 0; c < 4; ++c) g[12 + c] = g_qn[c] / l - (through_norm ? bq[c] * dotv / (l * l * len) : scalar_t(0));
        // the blend: each neighbour's packed transform gets its weight's share
        const int64_t* nb = pn + knn * n;
        const scalar_t* w = pw + knn * n;
        for (int64_t j = 0; j < knn; ++j) {
          scalar_t* o = gp_b + 16 * nb[j];
          for (int c = 0; c < 16; ++c) o[c] += w[j] * g[c];
        }
      }
    }, /*fixed=*/true);
  });
  return {g_packed, g_x};
}
