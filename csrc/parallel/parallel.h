// A parallel-for that the kernels use, and that their host (torch, or a test) may replace.
//
// The kernels stay free of torch and of any OpenMP runtime: by default the work is split across
// std::threads; the torch extension installs at::parallel_for at load time so that dyq shares torch's
// thread pool and honours torch.set_num_threads.
#pragma once

#include <cstdint>
#include <functional>

namespace dyq {

using RangeBody = std::function<void(int64_t begin, int64_t end)>;
using ParallelForBackend = void (*)(int64_t begin, int64_t end, int64_t grain_size, const RangeBody& body);

// Runs body over [begin, end) in chunks of at least grain_size, possibly in parallel.
void parallel_for(int64_t begin, int64_t end, int64_t grain_size, const RangeBody& body);

// nullptr restores the default std::thread backend.
void set_parallel_backend(ParallelForBackend backend);

}  // namespace dyq
