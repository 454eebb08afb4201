// A parallel-for that the kernels use, and whose threads their host (torch, or a test) may supply.
//
// The kernels stay free of torch and of any OpenMP runtime. dyq splits a range into at most one chunk per
// thread (each at least grain_size long); a chunk runner runs the chunks. By default that is a persistent
// pool of std::threads (one per hardware thread). The torch extension installs a runner on torch's own
// intra-op threads (at::parallel_for) and sets the thread count source to at::get_num_threads: a model's
// forward then alternates dyq's kernels and torch's ops on one set of threads. Two pools on the same cores
// compete: after each op the other pool's threads still spin for their next job, and a control step of a
// 0.5 B Llama config on 2 cores ran its prefill 1.4x slower for it.
#pragma once

#include <cstdint>
#include <functional>

namespace dyq {

using RangeBody = std::function<void(int64_t begin, int64_t end)>;
using ParallelForBackend = void (*)(int64_t begin, int64_t end, int64_t grain_size, const RangeBody& body);

// Runs body over [begin, end) in chunks of at least grain_size, possibly in parallel. An exception thrown by
// body in any thread is rethrown to the caller after every chunk in flight has finished.
void parallel_for(int64_t begin, int64_t end, int64_t grain_size, const RangeBody& body);

// While one is alive with serial = true, the default pool runs this thread's parallel_for calls inline:
// for work so small that handing a share to another thread costs more than it saves. A backend set with
// set_parallel_backend still sees every call.
class SerialScope {
 public:
  explicit SerialScope(bool serial);
  ~SerialScope();
  SerialScope(const SerialScope&) = delete;
  SerialScope& operator=(const SerialScope&) = delete;

 private:
  bool serial_;
};

// Replaces parallel_for itself, chunking included (for tests); nullptr restores dyq's own.
void set_parallel_backend(ParallelForBackend backend);

// Runs task(c) once for every c in [0, chunks), on up to `chunks` threads at once, and returns when all
// have finished; an exception thrown by a task is rethrown to the caller. dyq calls it with at most as many
// chunks as the thread count source allows.
using ChunkTask = std::function<void(int64_t chunk)>;
using ChunkRunner = void (*)(int64_t chunks, const ChunkTask& task);

// Runs dyq's chunks on the host's threads instead of dyq's own pool; nullptr restores the pool.
void set_chunk_runner(ChunkRunner runner);

// Whether a chunk runner is installed (the kernels run on the host's threads).
bool runs_on_host_threads();

// How many threads a call may use (its most chunks, on the pool or a runner); nullptr means one per
// hardware thread.
using ThreadCountSource = int (*)();
void set_thread_count_source(ThreadCountSource source);

}  // namespace dyq
