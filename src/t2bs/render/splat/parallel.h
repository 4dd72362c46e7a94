// Thread pool helper shared by the splat kernels (kernel.cpp: compositing, projection.cpp: projection).
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <thread>
#include <vector>

namespace t2bs_splat {

// Run fn(item, thread) for item in [0, n) on nthreads threads pulling items from an atomic
// counter (dynamic schedule), or, with ``fixed``, thread t taking items t, t + nthreads, ... in
// order: callers that sum into per-thread buffers need the same items in the same buffer every
// run, or the float sums (and a seeded training run) change from run to run.
// Plain std::threads rather than an OpenMP team: the machines this runs on are often
// oversubscribed, and OpenMP's spinning barriers then burn the time slices the other worker
// needs (measured: 2 OpenMP threads were ~2x slower than 1 under load).
template <class F>
void parallel_items(int64_t n, int nthreads, F&& fn, bool fixed = false) {
  nthreads = (int)std::max<int64_t>(1, std::min<int64_t>(nthreads, n));
  if (nthreads == 1) {
    for (int64_t i = 0; i < n; ++i) fn(i, 0);
    return;
  }
  std::atomic<int64_t> next{0};
  auto worker = [&](int tid) {
    if (fixed) {
      for (int64_t i = tid; i < n; i += nthreads) fn(i, tid);
      return;
    }
    for (int64_t i; (i = next.fetch_add(1, std::memory_order_relaxed)) < n;) fn(i, tid);
  };
  std::vector<std::thread> pool;
  pool.reserve(nthreads - 1);
  for (int t = 1; t < nthreads; ++t) pool.emplace_back(worker, t);
  worker(0);
  for (auto& th : pool) th.join();
}

}  // namespace t2bs_splat
