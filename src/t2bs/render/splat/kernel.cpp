// Fused CPU Gaussian-splat compositing: exact tile binning, forward and hand-written backward.
//
// Inputs are the projected 2D Gaussians of reference.project_gaussians ([C, N, ...] float32).
// The per-pixel rules mirror reference.composite (same float operation order, compiled with
// -ffp-contract=off so no FMA changes the d2 threshold decision):
//   d2 = (a*dx*dx + c*dy*dy) + (2*b)*dx*dy, touch iff d2 <= d2max,
//   alpha = min(0.99, o * exp(-0.5 * d2)), stop before T * (1 - alpha) < 1e-4.
// Four pixels of a row are composited at once (vector extensions), with every float operation, std::exp and the
// order of every sum as the one-pixel loop had them: the same bits as before (session 44).
//
// Layout: each (camera, tile) is one work item (thread pool, dynamic schedule). Per tile, Gaussians
// are visited front to back and each one only touches the pixels of its own bounding box inside
// the tile (most footprints are a few pixels wide at the resolutions VCDGS uses), so the cost
// is ~ the number of (pixel, Gaussian) pairs actually inside footprints. Per-Gaussian gradients
// are summed over a tile's pixels in registers and then added to a per-thread buffer, which are
// reduced at the end (no atomics).

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include "parallel.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <numeric>
#include <vector>

namespace {

using t2bs_splat::parallel_items;

constexpr float ALPHA_MAX = 0.99f;
constexpr float T_STOP = 1e-4f;

// Four pixels of a row at once (GCC/Clang vector extensions: SSE2 on x86-64, NEON on arm64; no -march flag).
typedef float v4f __attribute__((vector_size(16)));
typedef int32_t v4i __attribute__((vector_size(16)));
const v4f ZERO = {0.f, 0.f, 0.f, 0.f};
const v4i LANE_INDEX = {0, 1, 2, 3};
const v4f LANE_CENTRE = {0.5f, 1.5f, 2.5f, 3.5f};  // pixel centres x + 0.5 of the four lanes

inline bool any_lane(v4i m) { return (m[0] | m[1] | m[2] | m[3]) != 0; }

inline void accumulate(float* dst, v4f v) {  // dst[0..3] += v
  v4f d;
  std::memcpy(&d, dst, 16);
  d += v;
  std::memcpy(dst, &d, 16);
}

// std::exp of the lanes in ``on`` (0 elsewhere), one lane at a time: the reference's exp to the bit. A four-lane
// polynomial exp (Cephes' expf, within 2 ulp) was 1.3x faster still, but its last bits sent facecap's chaotic fit
// elsewhere (its wide mouth 0.196 -> 0.248 of the rigid oracle; session 44), so every result stays as it was.
inline v4f exp_lanes(v4f x, v4i on) {
  v4f e = ZERO;
  for (int l = 0; l < 4; ++l)
    if (on[l]) e[l] = std::exp(x[l]);
  return e;
}

struct Gauss {
  float mx, my;        // mean, pixels
  float ca, cb, cc;    // conic [[a, b], [b, c]]
  float cb2;           // 2 * b, exactly as the reference computes it
  float o, d2m;        // opacity, squared Mahalanobis extent
  float r, g, b, z;    // colour, camera depth
  int x0, x1, y0, y1;  // inclusive pixel box (clamped to the image); x0 > x1 = empty
};

// The colour and depth sums of four pixels from p on, each lane weighted by w: what a Gaussian adds in front of
// the pixels it touches (the forward's accumulation, the backward's running sum behind the current Gaussian).
inline void add_colour(float* R, float* G, float* B, float* D, int p, v4f w, const Gauss& g) {
  accumulate(R + p, w * g.r);
  accumulate(G + p, w * g.g);
  accumulate(B + p, w * g.b);
  accumulate(D + p, w * g.z);
}

struct Inputs {
  int C, N, W, H, tile, ntx, nty, ntiles;
  std::vector<Gauss> gs;  // [C * N]
};

Inputs pack(const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& opac,
            const torch::Tensor& colors, const torch::Tensor& depths, const torch::Tensor& d2max,
            const torch::Tensor& radii, const torch::Tensor& valid, int W, int H, int tile) {
  TORCH_CHECK(tile >= 1 && tile <= 32, "tile size must be in [1, 32] (per-tile pixel state lives on the stack)");
  for (const torch::Tensor* t : {&means2d, &conics, &opac, &colors, &depths, &d2max, &radii})
    TORCH_CHECK(t->scalar_type() == torch::kFloat32 && t->is_contiguous() && t->device().is_cpu(),
                "splat kernel inputs must be contiguous float32 CPU tensors");
  TORCH_CHECK(valid.scalar_type() == torch::kBool && valid.is_contiguous(), "valid must be a contiguous bool tensor");
  Inputs in;
  in.C = means2d.size(0);
  in.N = means2d.size(1);
  in.W = W;
  in.H = H;
  in.tile = tile;
  in.ntx = (W + tile - 1) / tile;
  in.nty = (H + tile - 1) / tile;
  in.ntiles = in.ntx * in.nty;
  const int64_t total = (int64_t)in.C * in.N;
  in.gs.resize(total);
  const float* m = means2d.data_ptr<float>();
  const float* cn = conics.data_ptr<float>();
  const float* op = opac.data_ptr<float>();
  const float* col = colors.data_ptr<float>();
  const float* dep = depths.data_ptr<float>();
  const float* dm = d2max.data_ptr<float>();
  const float* rad = radii.data_ptr<float>();
  const bool* val = valid.data_ptr<bool>();
  const int64_t chunk = 8192;
  parallel_items((total + chunk - 1) / chunk, at::get_num_threads(), [&](int64_t ci, int) {
    for (int64_t i = ci * chunk, e = std::min(total, i + chunk); i < e; ++i) {
      Gauss& g = in.gs[i];
      g.mx = m[2 * i];
      g.my = m[2 * i + 1];
      g.ca = cn[3 * i];
      g.cb = cn[3 * i + 1];
      g.cc = cn[3 * i + 2];
      g.cb2 = 2.0f * g.cb;
      g.o = op[i];
      g.d2m = dm[i];
      g.r = col[3 * i];
      g.g = col[3 * i + 1];
      g.b = col[3 * i + 2];
      g.z = dep[i];
      g.x0 = 1;
      g.x1 = 0;
      g.y0 = 1;
      g.y1 = 0;
      if (!val[i]) continue;
      // Pixel centres j + 0.5 inside [mx - rx, mx + rx] (radii carry a 1 px safety margin).
      // Clamp in float before converting so far-away footprints cannot overflow int.
      auto lo = [](float v, int n) { return (int)std::ceil(std::min(std::max(v, -2.0f), (float)n + 2.0f)); };
      auto hi = [](float v, int n) { return (int)std::floor(std::min(std::max(v, -2.0f), (float)n + 2.0f)); };
      g.x0 = std::max(0, lo(g.mx - rad[2 * i] - 0.5f, W));
      g.x1 = std::min(W - 1, hi(g.mx + rad[2 * i] - 0.5f, W));
      g.y0 = std::max(0, lo(g.my - rad[2 * i + 1] - 0.5f, H));
      g.y1 = std::min(H - 1, hi(g.my + rad[2 * i + 1] - 0.5f, H));
    }
  });
  return in;
}


// The visible Gaussians of one camera front to back, ties by index: what torch.sort(stable=True) gives on depth.
// A stable LSD radix sort (11-bit digits) of each depth's bits mapped to an unsigned order (positive floats keep
// theirs; negative ones flip), started from index order: equal depths keep their index order.
std::vector<int32_t> depth_order(const Gauss* gs, int N) {
  std::vector<int32_t> a, b;
  std::vector<uint32_t> ka, kb;
  a.reserve(N);
  ka.reserve(N);
  for (int i = 0; i < N; ++i)
    if (gs[i].x0 <= gs[i].x1 && gs[i].y0 <= gs[i].y1) {
      uint32_t u;
      std::memcpy(&u, &gs[i].z, 4);
      u = (u & 0x80000000u) ? ~u : (u | 0x80000000u);
      a.push_back(i);
      ka.push_back(u);
    }
  const size_t n = a.size();
  b.resize(n);
  kb.resize(n);
  for (int shift = 0; shift < 32; shift += 11) {
    size_t count[2049] = {0};
    for (size_t j = 0; j < n; ++j) count[((ka[j] >> shift) & 2047u) + 1]++;
    for (int d = 0; d < 2048; ++d) count[d + 1] += count[d];
    for (size_t j = 0; j < n; ++j) {
      const size_t dst = count[(ka[j] >> shift) & 2047u]++;
      b[dst] = a[j];
      kb[dst] = ka[j];
    }
    a.swap(b);
    ka.swap(kb);
  }
  return a;
}

// Per-tile lists of every overlapping Gaussian, front to back: sort each camera's Gaussians
// once by (depth, index) -- identical to torch.sort(stable=True); a radix sort, 2.5x faster than
// std::sort's comparisons -- then a counting sort into tiles keeps that order.
// Returns offsets [C * ntiles + 1] into ids.
void bin(const Inputs& in, std::vector<int64_t>& offsets, std::vector<int32_t>& ids) {
  const int C = in.C, N = in.N, T = in.ntiles, tile = in.tile;
  std::vector<std::vector<int32_t>> per_cam(C);
  std::vector<int64_t> counts((int64_t)C * T + 1, 0);
  parallel_items(C, at::get_num_threads(), [&](int64_t c, int) {
    const Gauss* gs = in.gs.data() + (int64_t)c * N;
    std::vector<int32_t> order = depth_order(gs, N);
    int64_t* cnt = counts.data() + 1 + (int64_t)c * T;
    for (int32_t i : order) {
      const Gauss& g = gs[i];
      for (int ty = g.y0 / tile; ty <= g.y1 / tile; ++ty)
        for (int tx = g.x0 / tile; tx <= g.x1 / tile; ++tx) cnt[ty * in.ntx + tx]++;
    }
    per_cam[c] = std::move(order);
  });
  std::partial_sum(counts.begin(), counts.end(), counts.begin());
  offsets = counts;
  ids.assign(offsets.back(), 0);
  parallel_items(C, at::get_num_threads(), [&](int64_t c, int) {
    const Gauss* gs = in.gs.data() + (int64_t)c * N;
    std::vector<int64_t> fill(offsets.begin() + (int64_t)c * T, offsets.begin() + (int64_t)(c + 1) * T);
    for (int32_t i : per_cam[c]) {
      const Gauss& g = gs[i];
      for (int ty = g.y0 / tile; ty <= g.y1 / tile; ++ty)
        for (int tx = g.x0 / tile; tx <= g.x1 / tile; ++tx) ids[fill[ty * in.ntx + tx]++] = i;
    }
  });
}

}  // namespace

// Returns acc_rgb [C,H,W,3], alpha [C,H,W], acc_depth [C,H,W], T_final [C,H,W],
// last [C,H,W] int32 (per pixel: index in its tile list where compositing stopped, exclusive),
// offsets [C*ntiles+1] int64, ids [pairs] int32.
std::vector<torch::Tensor> splat_forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                         torch::Tensor colors, torch::Tensor depths, torch::Tensor d2max,
                                         torch::Tensor radii, torch::Tensor valid, int64_t W, int64_t H,
                                         int64_t tile) {
  Inputs in = pack(means2d, conics, opac, colors, depths, d2max, radii, valid, W, H, tile);
  std::vector<int64_t> offsets;
  std::vector<int32_t> ids;
  bin(in, offsets, ids);
  const int C = in.C, N = in.N;
  auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  auto acc_rgb = torch::zeros({C, H, W, 3}, f32);
  auto alpha = torch::empty({C, H, W}, f32);
  auto acc_depth = torch::zeros({C, H, W}, f32);
  auto T_final = torch::empty({C, H, W}, f32);
  auto last = torch::empty({C, H, W}, torch::TensorOptions().dtype(torch::kInt32));
  float* o_rgb = acc_rgb.data_ptr<float>();
  float* o_a = alpha.data_ptr<float>();
  float* o_d = acc_depth.data_ptr<float>();
  float* o_T = T_final.data_ptr<float>();
  int32_t* o_last = last.data_ptr<int32_t>();
  const int64_t items = (int64_t)C * in.ntiles;

  parallel_items(items, at::get_num_threads(), [&](int64_t item, int) {
    const int c = item / in.ntiles, t = item % in.ntiles;
    const int tx0 = (t % in.ntx) * tile, ty0 = (t / in.ntx) * tile;
    const int tx1 = std::min<int>(tx0 + tile, W) - 1, ty1 = std::min<int>(ty0 + tile, H) - 1;
    const int tw = tx1 - tx0 + 1, th = ty1 - ty0 + 1, npix = tw * th;
    // Pixel state, padded by one group of lanes: a row's last group may read (never change) up to 3 pixels past it.
    float T[1024 + 4], R[1024 + 4], G[1024 + 4], B[1024 + 4], D[1024 + 4];
    float live[1024 + 4];  // 1 while the pixel composites, 0 once it stopped (and in the padding)
    int32_t lst[1024];
    const int64_t beg = offsets[item], end = offsets[item + 1];
    for (int p = 0; p < npix + 4; ++p) {
      T[p] = 1.f; R[p] = G[p] = B[p] = D[p] = 0.f; live[p] = p < npix ? 1.f : 0.f;
      if (p < npix) lst[p] = (int32_t)(end - beg);
    }
    int ndone = 0;
    const Gauss* gs = in.gs.data() + (int64_t)c * N;
    for (int64_t k = beg; k < end && ndone < npix; ++k) {
      const Gauss& g = gs[ids[k]];
      const int x0 = std::max(g.x0, tx0), x1 = std::min(g.x1, tx1);
      const int y0 = std::max(g.y0, ty0), y1 = std::min(g.y1, ty1);
      for (int y = y0; y <= y1; ++y) {
        const float dy = ((float)y + 0.5f) - g.my;
        const float cdy = g.cc * dy * dy;
        for (int x = x0; x <= x1; x += 4) {  // four pixels of the row at once: the lanes past x1 are masked off
          const int p = (y - ty0) * tw + (x - tx0);
          v4f alive, Tv;
          std::memcpy(&alive, live + p, 16);
          alive = (LANE_INDEX < std::min(4, x1 - x + 1)) ? alive : ZERO;
          const v4f dx = ((float)x + LANE_CENTRE) - g.mx;
          const v4f d2 = (g.ca * dx * dx + cdy) + g.cb2 * dx * dy;
          const v4i touch = (d2 <= g.d2m) & (alive > 0.f);
          if (!any_lane(touch)) continue;
          std::memcpy(&Tv, T + p, 16);
          v4f a = g.o * exp_lanes(-0.5f * d2, touch);
          a = a < ALPHA_MAX ? a : ALPHA_MAX;
          const v4f Tn = Tv * (1.f - a);
          const v4i stop = touch & (Tn < T_STOP);
          const v4i add = touch & ~stop;
          const v4f w = add ? a * Tv : ZERO;
          add_colour(R, G, B, D, p, w, g);
          Tv = add ? Tn : Tv;
          std::memcpy(T + p, &Tv, 16);
          if (any_lane(stop))
            for (int l = 0; l < 4; ++l)
              if (stop[l]) {
                live[p + l] = 0.f;
                lst[p + l] = (int32_t)(k - beg);
                ++ndone;
              }
        }
      }
    }
    for (int y = ty0; y <= ty1; ++y)
      for (int x = tx0; x <= tx1; ++x) {
        const int p = (y - ty0) * tw + (x - tx0);
        const int64_t q = ((int64_t)c * H + y) * W + x;
        o_rgb[3 * q] = R[p];
        o_rgb[3 * q + 1] = G[p];
        o_rgb[3 * q + 2] = B[p];
        o_d[q] = D[p];
        o_T[q] = T[p];
        o_a[q] = 1.f - T[p];
        o_last[q] = lst[p];
      }
  });
  auto t_off = torch::from_blob(offsets.data(), {(int64_t)offsets.size()}, torch::kInt64).clone();
  auto t_ids = torch::from_blob(ids.data(), {(int64_t)ids.size()}, torch::kInt32).clone();
  return {acc_rgb, alpha, acc_depth, T_final, last, t_off, t_ids};
}

// Returns grads [C, N, 10]: (mean x, mean y, conic a, b, c, opacity, r, g, b, depth).
torch::Tensor splat_backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                             torch::Tensor colors, torch::Tensor depths, torch::Tensor d2max,
                             torch::Tensor radii, torch::Tensor valid, int64_t W, int64_t H, int64_t tile,
                             torch::Tensor offsets_t, torch::Tensor ids_t, torch::Tensor T_final,
                             torch::Tensor last, torch::Tensor g_rgb, torch::Tensor g_alpha,
                             torch::Tensor g_depth) {
  Inputs in = pack(means2d, conics, opac, colors, depths, d2max, radii, valid, W, H, tile);
  const int C = in.C, N = in.N;
  const int64_t* offsets = offsets_t.data_ptr<int64_t>();
  const int32_t* ids = ids_t.data_ptr<int32_t>();
  const float* Tf = T_final.data_ptr<float>();
  const int32_t* lastp = last.data_ptr<int32_t>();
  const float* gR = g_rgb.data_ptr<float>();
  const float* gA = g_alpha.data_ptr<float>();
  const float* gD = g_depth.data_ptr<float>();
  const int nthreads = std::max(1, at::get_num_threads());
  const int64_t gsize = (int64_t)C * N * 10;
  std::vector<float> bufs((int64_t)nthreads * gsize, 0.f);
  const int64_t items = (int64_t)C * in.ntiles;

  parallel_items(items, nthreads, [&](int64_t item, int tid) {
    float* buf = bufs.data() + (int64_t)tid * gsize;
    const int c = item / in.ntiles, t = item % in.ntiles;
    const int tx0 = (t % in.ntx) * tile, ty0 = (t / in.ntx) * tile;
    const int tx1 = std::min<int>(tx0 + tile, W) - 1, ty1 = std::min<int>(ty0 + tile, H) - 1;
    const int tw = tx1 - tx0 + 1;
    const int64_t beg = offsets[item];
    float T[1024 + 4], Tfin[1024 + 4], Rr[1024 + 4], Rg[1024 + 4], Rb[1024 + 4], RD[1024 + 4];
    float gr[1024 + 4], gg[1024 + 4], gb[1024 + 4], ga[1024 + 4], gd[1024 + 4];
    int32_t lst[1024 + 4];
    const int npix = tw * (ty1 - ty0 + 1);
    for (int p = npix; p < npix + 4; ++p) {  // padding a row's last group of lanes may read (masked off, unchanged)
      T[p] = Tfin[p] = 1.f;
      Rr[p] = Rg[p] = Rb[p] = RD[p] = gr[p] = gg[p] = gb[p] = ga[p] = gd[p] = 0.f;
      lst[p] = 0;
    }
    int maxlast = 0;
    for (int y = ty0; y <= ty1; ++y)
      for (int x = tx0; x <= tx1; ++x) {
        const int p = (y - ty0) * tw + (x - tx0);
        const int64_t q = ((int64_t)c * H + y) * W + x;
        T[p] = Tfin[p] = Tf[q];
        Rr[p] = Rg[p] = Rb[p] = RD[p] = 0.f;
        gr[p] = gR[3 * q];
        gg[p] = gR[3 * q + 1];
        gb[p] = gR[3 * q + 2];
        ga[p] = gA[q];
        gd[p] = gD[q];
        lst[p] = lastp[q];
        maxlast = std::max(maxlast, (int)lst[p]);
      }
    const Gauss* gs = in.gs.data() + (int64_t)c * N;
    for (int k = maxlast - 1; k >= 0; --k) {
      const int32_t gi = ids[beg + k];
      const Gauss& g = gs[gi];
      const int x0 = std::max(g.x0, tx0), x1 = std::min(g.x1, tx1);
      const int y0 = std::max(g.y0, ty0), y1 = std::min(g.y1, ty1);
      // This Gaussian's gradient summed over its pixels, pixel by pixel in row order as the scalar loop did (the
      // terms come four lanes at a time; summed lane-wise, their float sums changed the last bits: session 44).
      float d_mx = 0, d_my = 0, d_ca = 0, d_cb = 0, d_cc = 0, d_o = 0, d_r = 0, d_g = 0, d_b = 0, d_z = 0;
      bool any = false;
      for (int y = y0; y <= y1; ++y) {
        const float dy = ((float)y + 0.5f) - g.my;
        const float cdy = g.cc * dy * dy;
        for (int x = x0; x <= x1; x += 4) {
          const int p = (y - ty0) * tw + (x - tx0);
          v4i stopped_at;
          std::memcpy(&stopped_at, lst + p, 16);
          const v4f dx = ((float)x + LANE_CENTRE) - g.mx;
          const v4f d2 = (g.ca * dx * dx + cdy) + g.cb2 * dx * dy;
          const v4i on = (LANE_INDEX < std::min(4, x1 - x + 1)) & (k < stopped_at) & (d2 <= g.d2m);
          if (!any_lane(on)) continue;
          any = true;
          v4f Tv, Tfv, vr, vg, vb, vd, va, vR, vG, vB, vD;
          std::memcpy(&Tv, T + p, 16);
          std::memcpy(&Tfv, Tfin + p, 16);
          std::memcpy(&vr, gr + p, 16);
          std::memcpy(&vg, gg + p, 16);
          std::memcpy(&vb, gb + p, 16);
          std::memcpy(&vd, gd + p, 16);
          std::memcpy(&va, ga + p, 16);
          std::memcpy(&vR, Rr + p, 16);
          std::memcpy(&vG, Rg + p, 16);
          std::memcpy(&vB, Rb + p, 16);
          std::memcpy(&vD, RD + p, 16);
          const v4f Gv = exp_lanes(-0.5f * d2, on);
          const v4f raw = g.o * Gv;
          const v4f a = raw < ALPHA_MAX ? raw : ALPHA_MAX;
          const v4f inv = 1.f / (1.f - a);
          const v4f Ti = Tv * inv;  // transmittance in front of this Gaussian
          const v4f w = on ? a * Ti : ZERO;
          const v4f dLda = vr * (g.r * Ti - vR * inv) + vg * (g.g * Ti - vG * inv) + vb * (g.b * Ti - vB * inv) +
                           vd * (g.z * Ti - vD * inv) + va * Tfv * inv;
          add_colour(Rr, Rg, Rb, RD, p, w, g);
          Tv = on ? Ti : Tv;
          std::memcpy(T + p, &Tv, 16);
          const v4i below_cap = on & (raw <= ALPHA_MAX);  // a clamped alpha passes no gradient to o or the conic
          const v4f dd2 = dLda * (-0.5f * raw);
          const v4f e_o = dLda * Gv, e_mx = dd2 * (2.f * g.ca * dx + g.cb2 * dy);
          const v4f e_my = dd2 * (g.cb2 * dx + 2.f * g.cc * dy), e_ca = dd2 * dx * dx;
          const v4f e_cb = dd2 * 2.f * dx * dy, e_cc = dd2 * dy * dy;
          const v4f e_r = vr * w, e_g = vg * w, e_b = vb * w, e_z = vd * w;
          for (int l = 0; l < 4; ++l) {
            if (!on[l]) continue;
            d_r += e_r[l];
            d_g += e_g[l];
            d_b += e_b[l];
            d_z += e_z[l];
            if (!below_cap[l]) continue;
            d_o += e_o[l];
            d_mx -= e_mx[l];
            d_my -= e_my[l];
            d_ca += e_ca[l];
            d_cb += e_cb[l];
            d_cc += e_cc[l];
          }
        }
      }
      if (any) {
        float* o = buf + ((int64_t)c * N + gi) * 10;
        o[0] += d_mx; o[1] += d_my; o[2] += d_ca; o[3] += d_cb; o[4] += d_cc;
        o[5] += d_o; o[6] += d_r; o[7] += d_g; o[8] += d_b; o[9] += d_z;
      }
    }
  }, /*fixed=*/true);  // per-thread sums: the same items in the same buffer every run
  auto out = torch::empty({C, N, 10}, torch::TensorOptions().dtype(torch::kFloat32));
  float* po = out.data_ptr<float>();
  const int64_t rchunk = 1 << 16;
  parallel_items((gsize + rchunk - 1) / rchunk, nthreads, [&](int64_t ci, int) {
    for (int64_t i = ci * rchunk, e = std::min(gsize, i + rchunk); i < e; ++i) {
      float s = 0.f;
      for (int th = 0; th < nthreads; ++th) s += bufs[(int64_t)th * gsize + i];
      po[i] = s;
    }
  });
  return out;
}

// projection.cpp
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor opac, torch::Tensor viewmats, torch::Tensor Ks,
                                           int64_t W, int64_t H, double near, double lowpass);
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                            torch::Tensor viewmats, torch::Tensor Ks, int64_t W, int64_t H,
                                            double near, double lowpass, torch::Tensor g_means2d,
                                            torch::Tensor g_conics, torch::Tensor g_depths);

// faces.cpp
std::vector<torch::Tensor> faces_forward(torch::Tensor x, torch::Tensor faces, torch::Tensor log_scale,
                                         double flatness);
torch::Tensor faces_backward(torch::Tensor x, torch::Tensor faces, torch::Tensor log_scale, double flatness,
                             torch::Tensor g_mean, torch::Tensor g_quat, torch::Tensor g_scale);

// skinning.cpp
std::vector<torch::Tensor> skin_forward(torch::Tensor packed, torch::Tensor x, torch::Tensor q_rest,
                                        torch::Tensor neighbours, torch::Tensor weights);
std::vector<torch::Tensor> skin_backward(torch::Tensor packed, torch::Tensor x, torch::Tensor q_rest,
                                         torch::Tensor neighbours, torch::Tensor weights, torch::Tensor g_xt,
                                         torch::Tensor g_qt);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("project_forward", &project_forward, "EWA projection of 3D Gaussians forward (CPU)");
  m.def("project_backward", &project_backward, "EWA projection of 3D Gaussians backward (CPU)");
  m.def("forward", &splat_forward, "Gaussian splat compositing forward (CPU)");
  m.def("backward", &splat_backward, "Gaussian splat compositing backward (CPU)");
  m.def("faces_forward", &faces_forward, "face Gaussians from triangle corners, forward (CPU)");
  m.def("faces_backward", &faces_backward, "face Gaussians from triangle corners, backward (CPU)");
  m.def("skin_forward", &skin_forward, "linear blend skinning of positions and rotations, forward (CPU)");
  m.def("skin_backward", &skin_backward, "linear blend skinning of positions and rotations, backward (CPU)");
}
