// Default std::thread backend of dyq::parallel_for, replaceable by the host (docs: parallel.h).
#include "parallel/parallel.h"

#include <algorithm>
#include <atomic>
#include <thread>
#include <vector>

namespace dyq {
namespace {

std::atomic<ParallelForBackend> g_backend{nullptr};

// A body that calls parallel_for again runs its inner range inline instead of oversubscribing.
thread_local bool t_inside_parallel_region = false;

void thread_parallel_for(int64_t begin, int64_t end, int64_t grain_size, const RangeBody& body) {
  const int64_t range = end - begin;
  const int64_t grain = std::max<int64_t>(grain_size, 1);
  const int64_t threads = std::max<int64_t>(std::thread::hardware_concurrency(), 1);
  const int64_t chunks = std::min(threads, range / grain);
  if (chunks <= 1 || t_inside_parallel_region) {
    body(begin, end);
    return;
  }
  // Contiguous chunks of nearly equal size, each at least `grain` long; the caller runs the first.
  const int64_t base = range / chunks;
  const int64_t extra = range % chunks;
  auto chunk_begin = [&](int64_t c) { return begin + c * base + std::min(c, extra); };
  auto run_chunk = [&](int64_t c) {
    t_inside_parallel_region = true;
    body(chunk_begin(c), chunk_begin(c + 1));
    t_inside_parallel_region = false;
  };
  std::vector<std::thread> workers;
  workers.reserve(chunks - 1);
  for (int64_t c = 1; c < chunks; ++c) workers.emplace_back(run_chunk, c);
  run_chunk(0);
  for (auto& worker : workers) worker.join();
}

}  // namespace

void parallel_for(int64_t begin, int64_t end, int64_t grain_size, const RangeBody& body) {
  if (end <= begin) return;
  const ParallelForBackend backend = g_backend.load(std::memory_order_acquire);
  if (backend != nullptr) {
    backend(begin, end, grain_size, body);
  } else {
    thread_parallel_for(begin, end, grain_size, body);
  }
}

void set_parallel_backend(ParallelForBackend backend) { g_backend.store(backend, std::memory_order_release); }

}  // namespace dyq
