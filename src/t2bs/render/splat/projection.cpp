// Fused CPU EWA projection of 3D Gaussians into C cameras, forward and hand-written backward.
//
// The same rules and float operations as reference.project_gaussians (see its docstring): camera
// point p = R m + t; x/z, y/z clamped to 1.3x the half field of view for the Jacobian; rows of J W
// times M = R(q) S give the 2D covariance plus the caller's low-pass (px^2); conic = its inverse. The torch
// version runs ~60 element-wise ops per pass over [C, N] tensors (each a full memory sweep), this
// one a single pass; results agree to float rounding (the camera point comes from a BLAS matmul in
// torch, a plain dot product here), tested in tests/test_splat.py.
//
// Gaussian inputs are [1, N, k] (one set shared by every camera) or [C, N, k]; gradients are
// returned per camera [C, N, k] and summed over cameras by the caller for shared sets, so every
// sum has a fixed order (deterministic for a seed). Camera matrices get no gradient here (the
// caller uses the autograd projection when they need one).

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include "parallel.h"

#include <cmath>
#include <limits>
#include <vector>

namespace {

using t2bs_splat::parallel_items;

constexpr float EXTENT_SIGMA2 = 9.0f;
constexpr float ALPHA_MIN = 1.0f / 255.0f;

struct Camera {
  float R[9], t[3], fx, fy, cx, cy, lim_xp, lim_xn, lim_yp, lim_yn;
};

std::vector<Camera> cameras(const torch::Tensor& viewmats, const torch::Tensor& Ks, int64_t W, int64_t H) {
  const int64_t C = viewmats.size(0);
  const float* vm = viewmats.data_ptr<float>();
  const float* k = Ks.data_ptr<float>();
  std::vector<Camera> cams(C);
  for (int64_t c = 0; c < C; ++c) {
    Camera& cam = cams[c];
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) cam.R[3 * i + j] = vm[16 * c + 4 * i + j];
      cam.t[i] = vm[16 * c + 4 * i + 3];
    }
    cam.fx = k[9 * c];
    cam.fy = k[9 * c + 4];
    cam.cx = k[9 * c + 2];
    cam.cy = k[9 * c + 5];
    const float tan_x = 0.5f * (float)W / cam.fx, tan_y = 0.5f * (float)H / cam.fy;
    cam.lim_xp = ((float)W - cam.cx) / cam.fx + 0.3f * tan_x;
    cam.lim_xn = cam.cx / cam.fx + 0.3f * tan_x;
    cam.lim_yp = ((float)H - cam.cy) / cam.fy + 0.3f * tan_y;
    cam.lim_yn = cam.cy / cam.fy + 0.3f * tan_y;
  }
  return cams;
}

// Everything the forward computes for one (camera, Gaussian), kept for the backward.
struct Proj {
  float x, y, z, inv_z, u, v;
  bool in_front, u_free, v_free, ok_det;
  float qn[4], qnorm;  // unit quaternion (w, x, y, z) and the input's norm
  float Rq[9], s[3], M[9];
  float T0[3], T1[3], P0[3], P1[3];
  float sa, sb, sc, inv_det;
};

void project_one(const Camera& cam, const float* m, const float* q, const float* s, float near, float lowpass,
                 Proj& p) {
  const float* R = cam.R;
  p.x = (R[0] * m[0] + R[1] * m[1] + R[2] * m[2]) + cam.t[0];
  p.y = (R[3] * m[0] + R[4] * m[1] + R[5] * m[2]) + cam.t[1];
  p.z = (R[6] * m[0] + R[7] * m[1] + R[8] * m[2]) + cam.t[2];
  p.in_front = p.z > near;
  p.inv_z = 1.0f / (p.in_front ? p.z : 1.0f);
  const float xr = p.x * p.inv_z, yr = p.y * p.inv_z;
  p.u = std::min(cam.lim_xp, std::max(-cam.lim_xn, xr));
  p.v = std::min(cam.lim_yp, std::max(-cam.lim_yn, yr));
  p.u_free = xr > -cam.lim_xn && xr < cam.lim_xp;
  p.v_free = yr > -cam.lim_yn && yr < cam.lim_yp;

  p.qnorm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  const float inv_n = 1.0f / std::max(p.qnorm, 1e-12f);
  for (int i = 0; i < 4; ++i) p.qn[i] = q[i] * inv_n;
  const float w = p.qn[0], x = p.qn[1], y = p.qn[2], z = p.qn[3];
  float* Rq = p.Rq;
  Rq[0] = 1 - 2 * (y * y + z * z); Rq[1] = 2 * (x * y - w * z);     Rq[2] = 2 * (x * z + w * y);
  Rq[3] = 2 * (x * y + w * z);     Rq[4] = 1 - 2 * (x * x + z * z); Rq[5] = 2 * (y * z - w * x);
  Rq[6] = 2 * (x * z - w * y);     Rq[7] = 2 * (y * z + w * x);     Rq[8] = 1 - 2 * (x * x + y * y);
  for (int j = 0; j < 3; ++j) p.s[j] = s[j];
  for (int i = 0; i < 9; ++i) p.M[i] = Rq[i] * p.s[i % 3];

  const float a0 = cam.fx * p.inv_z, a2 = -cam.fx * p.u * p.inv_z;
  const float b1 = cam.fy * p.inv_z, b2 = -cam.fy * p.v * p.inv_z;
  for (int k = 0; k < 3; ++k) {
    p.T0[k] = a0 * R[k] + a2 * R[6 + k];
    p.T1[k] = b1 * R[3 + k] + b2 * R[6 + k];
  }
  for (int j = 0; j < 3; ++j) {
    p.P0[j] = (p.T0[0] * p.M[j] + p.T0[1] * p.M[3 + j]) + p.T0[2] * p.M[6 + j];
    p.P1[j] = (p.T1[0] * p.M[j] + p.T1[1] * p.M[3 + j]) + p.T1[2] * p.M[6 + j];
  }
  p.sa = ((p.P0[0] * p.P0[0] + p.P0[1] * p.P0[1]) + p.P0[2] * p.P0[2]) + lowpass;
  p.sb = (p.P0[0] * p.P1[0] + p.P0[1] * p.P1[1]) + p.P0[2] * p.P1[2];
  p.sc = ((p.P1[0] * p.P1[0] + p.P1[1] * p.P1[1]) + p.P1[2] * p.P1[2]) + lowpass;
  const float det = p.sa * p.sc - p.sb * p.sb;
  p.ok_det = det > 0;
  p.inv_det = 1.0f / (p.ok_det ? det : 1.0f);
}

void check(const torch::Tensor& t, const char* name, int64_t last) {
  TORCH_CHECK(t.scalar_type() == torch::kFloat32 && t.is_contiguous() && t.device().is_cpu(),
              name, " must be a contiguous float32 CPU tensor");
  TORCH_CHECK(t.dim() == 3 && t.size(2) == last, name, " must be [1 or C, N, ", last, "]");
}

// Run fn(i, camera, projection) for every (camera, Gaussian) pair i = c * N + n, in parallel: the
// loop, the input checks and the shared-set strides that forward and backward both need.
template <class F>
void for_each_projected(const torch::Tensor& means, const torch::Tensor& quats, const torch::Tensor& scales,
                        const torch::Tensor& viewmats, const torch::Tensor& Ks, int64_t W, int64_t H, double near,
                        double lowpass, F&& fn) {
  check(means, "means", 3);
  check(quats, "quats", 4);
  check(scales, "scales", 3);
  const int64_t C = viewmats.size(0), N = means.size(1);
  const auto cams = cameras(viewmats, Ks, W, H);
  const float *pm = means.data_ptr<float>(), *pq = quats.data_ptr<float>(), *ps = scales.data_ptr<float>();
  const int64_t sm = means.size(0) > 1 ? N : 0, sq = quats.size(0) > 1 ? N : 0, ss = scales.size(0) > 1 ? N : 0;
  const int64_t total = C * N, chunk = 4096;
  const float fnear = (float)near, flowpass = (float)lowpass;
  parallel_items((total + chunk - 1) / chunk, at::get_num_threads(), [&](int64_t ci, int) {
    Proj p;
    for (int64_t i = ci * chunk, e = std::min(total, i + chunk); i < e; ++i) {
      const int64_t c = i / N, n = i % N;
      project_one(cams[c], pm + 3 * (c * sm + n), pq + 4 * (c * sq + n), ps + 3 * (c * ss + n), fnear, flowpass, p);
      fn(i, cams[c], p);
    }
  });
}

}  // namespace

// Returns means2d [C,N,2], conics [C,N,3], depths [C,N], d2max [C,N], radii [C,N,2], valid [C,N] bool.
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor opac, torch::Tensor viewmats, torch::Tensor Ks,
                                           int64_t W, int64_t H, double near, double lowpass) {
  const int64_t C = viewmats.size(0), N = means.size(1);
  TORCH_CHECK(opac.scalar_type() == torch::kFloat32 && opac.is_contiguous() && opac.size(0) == C && opac.size(1) == N,
              "opacities must be a contiguous float32 [C, N] tensor");
  auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  auto means2d = torch::empty({C, N, 2}, f32), conics = torch::empty({C, N, 3}, f32);
  auto depths = torch::empty({C, N}, f32), d2max = torch::empty({C, N}, f32), radii = torch::empty({C, N, 2}, f32);
  auto valid = torch::empty({C, N}, torch::TensorOptions().dtype(torch::kBool));
  const float* po = opac.data_ptr<float>();
  float *o_m = means2d.data_ptr<float>(), *o_c = conics.data_ptr<float>(), *o_z = depths.data_ptr<float>();
  float *o_d = d2max.data_ptr<float>(), *o_r = radii.data_ptr<float>();
  bool* o_v = valid.data_ptr<bool>();
  const auto each = [&](int64_t i, const Camera& cam, const Proj& p) {
    const float ca = p.sc * p.inv_det, cb = -p.sb * p.inv_det, cc = p.sa * p.inv_det;
    const float mx = cam.fx * p.x * p.inv_z + cam.cx, my = cam.fy * p.y * p.inv_z + cam.cy;
    o_c[3 * i] = ca; o_c[3 * i + 1] = cb; o_c[3 * i + 2] = cc;
    o_m[2 * i] = mx; o_m[2 * i + 1] = my;
    o_z[i] = p.z;
    const float o = po[i];
    float dm = std::min(2.0f * std::log(std::max(o * 255.0f, 1e-30f)), EXTENT_SIGMA2);
    if (!(o >= ALPHA_MIN)) dm = 0.0f;
    o_d[i] = dm;
    const float dmc = std::max(dm, 0.0f);
    const float rx = std::sqrt(dmc * std::max(p.sa, 0.0f)) + 1.0f, ry = std::sqrt(dmc * std::max(p.sc, 0.0f)) + 1.0f;
    const bool finite = std::isfinite(mx) && std::isfinite(my) && std::isfinite(rx) && std::isfinite(ry) &&
                        std::isfinite(ca) && std::isfinite(cb) && std::isfinite(cc);
    const bool overlaps = (mx + rx > 0) && (mx - rx < (float)W) && (my + ry > 0) && (my - ry < (float)H);
    const bool ok = p.in_front && p.ok_det && (o >= ALPHA_MIN) && finite && overlaps;
    o_v[i] = ok;
    o_r[2 * i] = ok ? rx : 0.0f;
    o_r[2 * i + 1] = ok ? ry : 0.0f;
  };
  for_each_projected(means, quats, scales, viewmats, Ks, W, H, near, lowpass, each);
  return {means2d, conics, depths, d2max, radii, valid};
}

// Gradients of (means2d, conics, depths) -> per camera [C,N,3] means, [C,N,4] quats, [C,N,3] scales.
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                            torch::Tensor viewmats, torch::Tensor Ks, int64_t W, int64_t H,
                                            double near, double lowpass, torch::Tensor g_means2d,
                                            torch::Tensor g_conics, torch::Tensor g_depths) {
  const int64_t C = viewmats.size(0), N = means.size(1);
  for (const torch::Tensor* t : {&g_means2d, &g_conics, &g_depths})
    TORCH_CHECK(t->scalar_type() == torch::kFloat32 && t->is_contiguous() && t->size(0) == C && t->size(1) == N,
                "projection gradients must be contiguous float32 [C, N, ...] tensors");
  auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  auto gm = torch::empty({C, N, 3}, f32), gq = torch::empty({C, N, 4}, f32), gs = torch::empty({C, N, 3}, f32);
  const float *g2 = g_means2d.data_ptr<float>(), *gc = g_conics.data_ptr<float>(), *gz_in = g_depths.data_ptr<float>();
  float *o_m = gm.data_ptr<float>(), *o_q = gq.data_ptr<float>(), *o_s = gs.data_ptr<float>();
  const auto each = [&](int64_t i, const Camera& cam, const Proj& p) {
    const float* R = cam.R;
    // conic = (sc, -sb, sa) / det with det = sa sc - sb^2 (inv_det is a constant 1 where det <= 0).
    const float gA = gc[3 * i], gB = gc[3 * i + 1], gC = gc[3 * i + 2];
    float gsa = gC * p.inv_det, gsb = -gB * p.inv_det, gsc = gA * p.inv_det;
    if (p.ok_det) {
      const float g_inv = gA * p.sc - gB * p.sb + gC * p.sa;
      const float g_det = -g_inv * p.inv_det * p.inv_det;
      gsa += g_det * p.sc;
      gsc += g_det * p.sa;
      gsb += -2.0f * g_det * p.sb;
    }
    float gP0[3], gP1[3];
    for (int j = 0; j < 3; ++j) {
      gP0[j] = 2.0f * gsa * p.P0[j] + gsb * p.P1[j];
      gP1[j] = 2.0f * gsc * p.P1[j] + gsb * p.P0[j];
    }
    // P0_j = sum_k T0_k M_kj (same for P1 with T1).
    float gT0[3], gT1[3], gM[9];
    for (int k = 0; k < 3; ++k) {
      gT0[k] = gP0[0] * p.M[3 * k] + gP0[1] * p.M[3 * k + 1] + gP0[2] * p.M[3 * k + 2];
      gT1[k] = gP1[0] * p.M[3 * k] + gP1[1] * p.M[3 * k + 1] + gP1[2] * p.M[3 * k + 2];
      for (int j = 0; j < 3; ++j) gM[3 * k + j] = p.T0[k] * gP0[j] + p.T1[k] * gP1[j];
    }
    // M_kj = Rq_kj s_j.
    float gRq[9], g_s[3] = {0.f, 0.f, 0.f};
    for (int k = 0; k < 9; ++k) {
      gRq[k] = gM[k] * p.s[k % 3];
      g_s[k % 3] += gM[k] * p.Rq[k];
    }
    // T0 = a0 R_row0 + a2 R_row2, T1 = b1 R_row1 + b2 R_row2.
    float ga0 = 0.f, ga2 = 0.f, gb1 = 0.f, gb2 = 0.f;
    for (int k = 0; k < 3; ++k) {
      ga0 += gT0[k] * R[k];
      ga2 += gT0[k] * R[6 + k];
      gb1 += gT1[k] * R[3 + k];
      gb2 += gT1[k] * R[6 + k];
    }
    const float gmx = g2[2 * i], gmy = g2[2 * i + 1];
    float g_inv_z = cam.fx * ga0 - cam.fx * p.u * ga2 + cam.fy * gb1 - cam.fy * p.v * gb2
                    + cam.fx * p.x * gmx + cam.fy * p.y * gmy;
    const float gu = -cam.fx * p.inv_z * ga2, gv = -cam.fy * p.inv_z * gb2;
    float gx = cam.fx * p.inv_z * gmx, gy = cam.fy * p.inv_z * gmy, gz = gz_in[i];
    if (p.u_free) { gx += gu * p.inv_z; g_inv_z += gu * p.x; }
    if (p.v_free) { gy += gv * p.inv_z; g_inv_z += gv * p.y; }
    if (p.in_front) gz += -g_inv_z * p.inv_z * p.inv_z;
    // p = R m + t.
    float* om = o_m + 3 * i;
    for (int j = 0; j < 3; ++j) om[j] = R[j] * gx + R[3 + j] * gy + R[6 + j] * gz;
    for (int j = 0; j < 3; ++j) o_s[3 * i + j] = g_s[j];
    // Rotation matrix of the unit quaternion (w, x, y, z), then its normalisation.
    const float w = p.qn[0], x = p.qn[1], y = p.qn[2], z = p.qn[3];
    const float* g = gRq;
    float gq_[4];
    gq_[0] = 2.f * (-z * g[1] + y * g[2] + z * g[3] - x * g[5] - y * g[6] + x * g[7]);
    gq_[1] = 2.f * (y * g[1] + z * g[2] + y * g[3] - 2.f * x * g[4] - w * g[5] + z * g[6] + w * g[7] - 2.f * x * g[8]);
    gq_[2] = 2.f * (-2.f * y * g[0] + x * g[1] + w * g[2] + x * g[3] + z * g[5] - w * g[6] + z * g[7] - 2.f * y * g[8]);
    gq_[3] = 2.f * (-2.f * z * g[0] - w * g[1] + x * g[2] + w * g[3] - 2.f * z * g[4] + y * g[5] + x * g[6] + y * g[7]);
    float* oq = o_q + 4 * i;
    if (p.qnorm > 1e-12f) {
      const float dot = gq_[0] * w + gq_[1] * x + gq_[2] * y + gq_[3] * z;
      for (int k = 0; k < 4; ++k) oq[k] = (gq_[k] - p.qn[k] * dot) / p.qnorm;
    } else {
      for (int k = 0; k < 4; ++k) oq[k] = gq_[k] * 1e12f;
    }
  };
  for_each_projected(means, quats, scales, viewmats, Ks, W, H, near, lowpass, each);
  return {gm, gq, gs};
}
