// Thread pool helper shared by the splat kernels (kernel.cpp: compositing, projection.cpp: projection).
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <thread>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace t2bs_splat {

// Run fn(item, thread) for item in [0, n) on nthreads threads pulling items from an atomic
// counter (dynamic schedule), or, with ``fixed``, thread t of a team of k taking items t, t + k, ...
// in order: callers that sum into per-thread buffers need the same items in the same buffer every
// run, or the float sums (and a seeded training run) change from run to run.
//
// The threads are torch's own OpenMP team when the kernel is built with OpenMP (the extension
// links the libgomp torch already loaded, so there is one team): between the training step's
// torch operators those threads are awake, and a kernel that spawned its own std::threads instead
// waited ~3 ms for a core per call (libgomp's default spin-wait holds it), so the second thread
// added almost nothing (facecap quick: compositing 18 ms forward on 2 threads, 17.5 on 1; on the
// team 9.4 ms; docs/BENCHMARKS.md, issue 36). Without OpenMP, plain std::threads.
template <class F>
void parallel_items(int64_t n, int nthreads, F&& fn, bool fixed = false) {
  nthreads = (int)std::max<int64_t>(1, std::min<int64_t>(nthreads, n));
  if (nthreads == 1) {
    for (int64_t i = 0; i < n; ++i) fn(i, 0);
    return;
  }
  std::atomic<int64_t> next{0};
  auto worker = [&](int tid, int team) {
    if (fixed) {
      for (int64_t i = tid; i < n; i += team) fn(i, tid);
      return;
    }
    for (int64_t i; (i = next.fetch_add(1, std::memory_order_relaxed)) < n;) fn(i, tid);
  };
#ifdef _OPENMP
  // The team may be smaller than asked (called inside another parallel region: 1); every item is still run, by
  // the threads there are, and thread ids stay below nthreads (the callers' per-thread buffers).
#pragma omp parallel num_threads(nthreads)
  worker(omp_get_thread_num(), omp_get_num_threads());
#else
  std::vector<std::thread> pool;
  pool.reserve(nthreads - 1);
  for (int t = 1; t < nthreads; ++t) pool.emplace_back(worker, t, nthreads);
  worker(0, nthreads);
  for (auto& th : pool) th.join();
#endif
}

}  // namespace t2bs_splat
