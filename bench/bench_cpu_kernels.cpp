// Timing of dyq::cpu::gemm on the Llama layer shapes, for every act_bits. Not built by default:
//
//   c++ -O2 -std=c++17 -I csrc -I /usr/include/eigen3 bench/bench_cpu_kernels.cpp
//       build/ctest/libdyq_cpu_kernels.a -lpthread -o /tmp/bench_cpu_kernels
//   [DYQ_CPU_ISA=avx512|avx2|portable] /tmp/bench_cpu_kernels [results.json]
//
// Prints a table (median wall time, and process CPU time divided by the thread count, which stays
// meaningful on a shared machine) and writes the same rows as JSON.
#include <sys/mman.h>
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <random>
#include <thread>
#include <vector>

#include "gemm/gemm_cpu.h"
#include "weight/weight_pack_cpu.h"

namespace {

double process_cpu_ms() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return (usage.ru_utime.tv_sec + usage.ru_stime.tv_sec) * 1e3 + (usage.ru_utime.tv_usec + usage.ru_stime.tv_usec) / 1e3;
}

struct Row {
  int64_t m, n, k;
  int act_bits;
  double median_ms, cpu_per_thread_ms;
};

}  // namespace

int main(int argc, char** argv) {
  const char* json_path = argc > 1 ? argv[1] : "bench_cpu_kernels.json";
  constexpr int kGroupSize = 128;
  constexpr size_t kHugePageBytes = size_t{2} << 20;
  const unsigned threads = std::max(1u, std::thread::hardware_concurrency());
  std::mt19937 rng(0);
  std::normal_distribution<float> normal(0.0f, 1.0f);
  std::vector<Row> rows;
  std::printf("%6s %6s %6s %8s %12s %14s\n", "M", "N", "K", "act_bits", "median ms", "cpu/thread ms");
  for (auto [n, k] : {std::pair<int64_t, int64_t>{4096, 4096}, {11008, 4096}, {4096, 11008}}) {
    std::vector<float> weight(n * k);
    for (auto& w : weight) w = 0.02f * normal(rng);
    // On 2 MiB pages, as a DyQLinear keeps its packed weights on Linux (python/dyq/core/host_memory.py): a
    // std::vector's 16-byte alignment splits the kernels' 64-byte loads across cache lines (4 % to 6 % slower
    // decode on the AMD EPYC), and 4 KiB pages cost the decode a TLB miss every 4 KiB.
    const size_t qweight_bytes = (n * k / 2 + kHugePageBytes - 1) / kHugePageBytes * kHugePageBytes;
    std::unique_ptr<uint8_t, decltype(&std::free)> qweight_storage(
        static_cast<uint8_t*>(std::aligned_alloc(kHugePageBytes, qweight_bytes)), &std::free);
    madvise(qweight_storage.get(), qweight_bytes, MADV_HUGEPAGE);  // before the first write; advice only
    uint8_t* const qweight = qweight_storage.get();
    std::vector<float> scales(n * k / kGroupSize);
    dyq::cpu::quantize_weight(weight.data(), n, k, kGroupSize, qweight, scales.data());
    for (int64_t m : {1, 16, 256}) {
      std::vector<float> x(m * k), out(m * n);
      for (auto& v : x) v = normal(rng);
      for (int act_bits : {2, 4, 8, 16}) {
        auto run = [&] {
          dyq::cpu::gemm(x.data(), dyq::ScalarType::kFloat32, qweight, scales.data(), nullptr, m, n, k,
                         kGroupSize, act_bits, out.data());
        };
        run();  // warm-up
        const int reps = m == 256 ? 3 : 20;
        std::vector<double> times;
        const double cpu_start = process_cpu_ms();
        for (int i = 0; i < reps; ++i) {
          const auto start = std::chrono::steady_clock::now();
          run();
          times.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count());
        }
        const double cpu_per_thread = (process_cpu_ms() - cpu_start) / reps / threads;
        std::sort(times.begin(), times.end());
        rows.push_back({m, n, k, act_bits, times[times.size() / 2], cpu_per_thread});
        std::printf("%6ld %6ld %6ld %8d %12.3f %14.3f\n", m, n, k, act_bits, rows.back().median_ms, cpu_per_thread);
      }
    }
  }
  FILE* json = std::fopen(json_path, "w");
  if (json == nullptr) return 1;
  std::fprintf(json, "{\"device\": \"cpu\", \"threads\": %u, \"group_size\": %d, \"dtype\": \"float32\", \"rows\": [",
               threads, kGroupSize);
  for (size_t i = 0; i < rows.size(); ++i) {
    const Row& r = rows[i];
    std::fprintf(json, "%s\n  {\"m\": %ld, \"n\": %ld, \"k\": %ld, \"act_bits\": %d, \"median_ms\": %.4f, \"cpu_per_thread_ms\": %.4f}",
                 i ? "," : "", r.m, r.n, r.k, r.act_bits, r.median_ms, r.cpu_per_thread_ms);
  }
  std::fprintf(json, "\n]}\n");
  std::fclose(json);
  return 0;
}
