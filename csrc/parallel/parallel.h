// A parallel-for that the kernels use, and that their host (torch, or a test) may replace.
//
// The kernels stay free of torch and of any OpenMP runtime: by default the work is split across a
// persistent pool of std::threads (one per hardware thread). The torch extension sets the thread count
// source to at::get_num_threads, so that dyq honours torch.set_num_threads. (at::parallel_for itself is
// a header template whose OpenMP pragmas would compile to a serial loop in a library built without
// -fopenmp, and linking a second OpenMP runtime beside torch's is worse.)
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

// Replaces the default pool (for tests and embedders); nullptr restores it.
void set_parallel_backend(ParallelForBackend backend);

// How many threads the default pool may use per call; nullptr means one per hardware thread.
using ThreadCountSource = int (*)();
void set_thread_count_source(ThreadCountSource source);

}  // namespace dyq
