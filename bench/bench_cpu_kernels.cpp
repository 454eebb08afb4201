// Timing of dyq::cpu::gemm on the Llama layer shapes, for every act_bits, with nothing of torch around it.
// Built with the C++ tests (-DDYQ_BUILD_TESTS=ON), run by hand:
//
//   cmake -S . -B build/ctest -G Ninja -DDYQ_BUILD_PYTHON=OFF -DDYQ_BUILD_TESTS=ON && cmake --build build/ctest
//   [DYQ_CPU_ISA=avx512|avx_vnni|avx2|portable] build/ctest/dyq_bench_cpu_kernels [results.json [threads [G]]]
//
// G, the weights' group size: 128 (the default), 64 or 32.
// Hot: M = 1, 16 and 256 on one copy of the weights. Prints a table (median wall time, and process CPU
// time divided by the thread count, which stays meaningful on a shared machine).
// Cold decode: M = 1 over as many copies of the weights as fill four times the last-level cache, called in
// turn, as bandwidth (packed weights and scales over the time), against a streaming read of 1 GiB on as many
// threads: the kernels' own share of the memory's speed, which bench_linear.py measures through torch (its
// per-call costs included), and beside it the speed of the same call hot (timed earlier in the run, the
// weights in the caches as far as they fit): where that is not well above the read, the kernel's own work per
// byte limits the cold decode as much as the memory does (one core of the AMD EPYC). Each shape runs in
// rounds: a read, then a stretch of calls of every width, in an order shuffled per round; a width's share is
// the median over the rounds of its speed over the round's read, so that the drift of a shared machine
// reaches the read and the decode it is compared with alike, and no width always runs first. (With one read
// before and after each shape and each width's calls in one stretch, the one-thread shares of three runs on
// the AMD EPYC spread over 71 % to 94 % at the integer widths; of five runs in rounds, over 78 % to 87 %.)
// Both tables go to the JSON.
#include <sys/mman.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "bench_util.h"
#include "cpu/cpu_isa.h"
#include "gemm/gemm_cpu.h"
#include "parallel/parallel.h"
#include "weight/weight_pack_cpu.h"

namespace {

using dyq::bench::cpu_model;
using dyq::bench::median;

constexpr size_t kHugePageBytes = size_t{2} << 20;

double process_cpu_ms() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return (usage.ru_utime.tv_sec + usage.ru_stime.tv_sec) * 1e3 + (usage.ru_utime.tv_usec + usage.ru_stime.tv_usec) / 1e3;
}

// On 2 MiB pages, as a DyQLinear keeps its packed weights on Linux (python/dyq/core/host_memory.py): a
// std::vector's 16-byte alignment splits the kernels' 64-byte loads across cache lines (4 % to 6 % slower
// decode on the AMD EPYC), and 4 KiB pages cost the decode a TLB miss every 4 KiB.
using HugeBuffer = std::unique_ptr<uint8_t, decltype(&std::free)>;
HugeBuffer huge_buffer(size_t bytes) {
  const size_t rounded = (bytes + kHugePageBytes - 1) / kHugePageBytes * kHugePageBytes;
  HugeBuffer buffer(static_cast<uint8_t*>(std::aligned_alloc(kHugePageBytes, rounded)), &std::free);
  if (buffer == nullptr) {
    std::fprintf(stderr, "out of memory for %zu bytes\n", rounded);
    std::exit(1);
  }
  madvise(buffer.get(), rounded, MADV_HUGEPAGE);  // before the first write; advice only
  return buffer;
}

// The largest cache cpu0 reports in sysfs, as bench_linear.py reads it (sysconf's figure on the AMD EPYC
// virtual machine was ten times its 32 MiB L3); 32 MiB where there is none.
int64_t last_level_cache_bytes() {
  int64_t largest = 0;
  for (int index = 0; index < 8; ++index) {
    const std::string path = "/sys/devices/system/cpu/cpu0/cache/index" + std::to_string(index) + "/size";
    FILE* file = std::fopen(path.c_str(), "r");
    if (file == nullptr) continue;
    long value = 0;
    char unit = 0;
    if (std::fscanf(file, "%ld%c", &value, &unit) >= 1) {
      const int64_t scale = unit == 'K'   ? int64_t{1} << 10
                            : unit == 'M' ? int64_t{1} << 20
                            : unit == 'G' ? int64_t{1} << 30
                                          : 1;
      largest = std::max<int64_t>(largest, value * scale);
    }
    std::fclose(file);
  }
  return largest > 0 ? largest : int64_t{32} << 20;
}

unsigned g_threads = 1;
int thread_count() { return static_cast<int>(g_threads); }

// Sums a share of the streaming read's buffer as 64-bit words, eight independent sums over each cache line,
// with kPrefetch 16 KiB ahead into L2 as the row kernels' sweep does (a prefetch does not fault past the end).
template <bool kPrefetch>
uint64_t summed_words(const uint8_t* data, size_t bytes) {
  const auto* words = reinterpret_cast<const uint64_t*>(data);
  uint64_t sums[8] = {};
  for (size_t i = 0; i < bytes / 8; i += 8) {
    if constexpr (kPrefetch) __builtin_prefetch(data + i * 8 + 16384, 0, 2);
    for (int j = 0; j < 8; ++j) sums[j] += words[i + j];
  }
  uint64_t total = 0;
  for (uint64_t sum : sums) total += sum;
  return total;
}

template <bool kPrefetch>
double summed_read_gbps(const uint8_t* data, size_t bytes) {
  std::vector<uint64_t> sums(g_threads);
  const auto start = std::chrono::steady_clock::now();
  std::vector<std::thread> workers;
  for (unsigned t = 0; t < g_threads; ++t) {
    workers.emplace_back([&, t] {
      const size_t begin = bytes * t / g_threads / 64 * 64, end = bytes * (t + 1) / g_threads / 64 * 64;
      sums[t] = summed_words<kPrefetch>(data + begin, end - begin);
    });
  }
  for (auto& worker : workers) worker.join();
  const double gbps = bytes / std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() / 1e9;
  for (uint64_t sum : sums) {
    if (sum != 0) std::printf("the streaming read summed bytes it should not have\n");
  }
  return gbps;
}

// GB/s of a read of `bytes` zero bytes on g_threads threads: the machine's streaming read, against which the
// cold decode's share is taken, so the faster of two plain reads, a sum with and without software prefetches
// (which paid on one machine and not on the other). On the Intel Xeon with AMX (2 cores, huge pages, one
// process) the one with read 17.8 to 20.4 GB/s on one thread and 34 to 35 on two, the one without 16.6 to 17.6
// and 30 to 33; glibc's memchr, which this benchmark used before, 12 and 23, and the cold decode's W4A8 then
// read 112 % to 138 % of it. On the AMD EPYC a loop of plain loads had read faster without prefetches.
double stream_read_gbps(const uint8_t* data, size_t bytes) {
  return std::max(summed_read_gbps<true>(data, bytes), summed_read_gbps<false>(data, bytes));
}

struct Row {
  std::string mode;
  int64_t m, n, k;
  int act_bits;
  double median_ms, cpu_per_thread_ms, gbps, stream_gbps;
  double share = 0.0, share_min = 0.0, share_max = 0.0;  // cold: over the rounds
  double hot_gbps = 0.0;  // cold: the same call's bytes over its hot time at M = 1
};

}  // namespace

int main(int argc, char** argv) {
  const char* json_path = argc > 1 ? argv[1] : "bench_cpu_kernels.json";
  g_threads = argc > 2 ? static_cast<unsigned>(std::atoi(argv[2])) : std::max(1u, std::thread::hardware_concurrency());
  if (g_threads == 0) {
    std::fprintf(stderr, "threads must be at least 1, got %s\n", argv[2]);
    return 1;
  }
  dyq::set_thread_count_source(thread_count);
  const int group_size = argc > 3 ? std::atoi(argv[3]) : 128;
  if (group_size != 32 && group_size != 64 && group_size != 128) {
    std::fprintf(stderr, "group size must be 32, 64 or 128, got %s\n", argv[3]);
    return 1;
  }
  std::mt19937 rng(0);
  std::normal_distribution<float> normal(0.0f, 1.0f);
  std::vector<Row> rows;
  // Llama-7B's layers, and Llama-13B's down projection, whose K = 13824 is past the bf16 row kernels'
  // switch to several weight rows per call.
  const std::pair<int64_t, int64_t> shapes[] = {{4096, 4096}, {11008, 4096}, {4096, 11008}, {5120, 13824}};

  std::printf("hot, %u thread(s), G = %d\n%6s %6s %6s %8s %12s %14s\n", g_threads, group_size, "M", "N", "K",
              "act_bits", "median ms", "cpu/thread ms");
  for (auto [n, k] : shapes) {
    std::vector<float> weight(n * k);
    for (auto& w : weight) w = 0.02f * normal(rng);
    HugeBuffer qweight = huge_buffer(n * k / 2);
    std::vector<float> scales(n * k / group_size);
    dyq::cpu::quantize_weight(weight.data(), n, k, group_size, qweight.get(), scales.data());
    for (int64_t m : {1, 16, 256}) {
      std::vector<float> x(m * k), out(m * n);
      for (auto& v : x) v = normal(rng);
      for (int act_bits : {2, 4, 8, 16}) {
        auto run = [&] {
          dyq::cpu::gemm(x.data(), dyq::ScalarType::kFloat32, qweight.get(), scales.data(), nullptr, m, n, k,
                         group_size, act_bits, out.data());
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
        const double cpu_per_thread = (process_cpu_ms() - cpu_start) / reps / g_threads;
        std::sort(times.begin(), times.end());
        rows.push_back({"hot", m, n, k, act_bits, times[times.size() / 2], cpu_per_thread, 0.0, 0.0});
        std::printf("%6ld %6ld %6ld %8d %12.3f %14.3f\n", m, n, k, act_bits, rows.back().median_ms, cpu_per_thread);
      }
    }
  }

  const size_t stream_bytes = size_t{1} << 30;
  HugeBuffer stream = huge_buffer(stream_bytes);
  std::memset(stream.get(), 0, stream_bytes);
  stream_read_gbps(stream.get(), stream_bytes);  // the first reads after the writes ran slower
  const int64_t cache_bytes = last_level_cache_bytes();
  constexpr int kColdRounds = 9, kCallsPerRound = 24;
  std::mt19937 order_rng(1);
  std::printf("\ncold decode (M = 1), %u thread(s), copies over 4 x %ld MiB of last-level cache, %d rounds of a "
              "read and %d calls of each width\n%6s %6s %8s %10s %8s %14s %8s %20s %10s\n",
              g_threads, static_cast<long>(cache_bytes >> 20), kColdRounds, kCallsPerRound, "N", "K", "act_bits",
              "median ms", "GB/s", "stream GB/s", "share", "rounds' shares", "hot GB/s");
  for (auto [n, k] : shapes) {
    const int64_t weight_bytes = n * k / 2, scale_bytes = n * (k / group_size) * int64_t{sizeof(float)};
    const int copies = static_cast<int>(std::max<int64_t>(2, (4 * cache_bytes + weight_bytes + scale_bytes - 1) /
                                                                 (weight_bytes + scale_bytes)));
    std::vector<HugeBuffer> qweights;
    std::vector<HugeBuffer> scales;
    for (int c = 0; c < copies; ++c) {
      qweights.push_back(huge_buffer(weight_bytes));
      scales.push_back(huge_buffer(scale_bytes));
      if (c == 0) {
        std::vector<float> weight(n * k);
        for (auto& w : weight) w = 0.02f * normal(rng);
        dyq::cpu::quantize_weight(weight.data(), n, k, group_size, qweights[0].get(),
                                  reinterpret_cast<float*>(scales[0].get()));
      } else {
        std::memcpy(qweights[c].get(), qweights[0].get(), weight_bytes);
        std::memcpy(scales[c].get(), scales[0].get(), scale_bytes);
      }
    }
    std::vector<float> x(k), out(n);
    for (auto& v : x) v = normal(rng);
    auto call = [&](int copy, int act_bits) {
      dyq::cpu::gemm(x.data(), dyq::ScalarType::kFloat32, qweights[copy].get(),
                     reinterpret_cast<const float*>(scales[copy].get()), nullptr, 1, n, k, group_size, act_bits,
                     out.data());
    };
    for (int c = 0; c < copies; ++c) call(c, 8);  // a first, untimed pass over the copies
    int widths[] = {2, 4, 8, 16};
    std::vector<double> reads, times[4], shares[4];  // per round; times and shares by width (index of 2, 4, ..)
    int copy = 0;
    for (int round = 0; round < kColdRounds; ++round) {
      const double read = stream_read_gbps(stream.get(), stream_bytes);
      reads.push_back(read);
      std::shuffle(std::begin(widths), std::end(widths), order_rng);
      for (int act_bits : widths) {
        std::vector<double> call_ms;
        for (int i = 0; i < kCallsPerRound; ++i, copy = (copy + 1) % copies) {
          const auto start = std::chrono::steady_clock::now();
          call(copy, act_bits);
          call_ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count());
        }
        const int w = __builtin_ctz(act_bits) - 1;
        times[w].push_back(median(call_ms));
        shares[w].push_back((weight_bytes + scale_bytes) / times[w].back() / 1e6 / read);
      }
    }
    for (int w = 0; w < 4; ++w) {
      const double ms = median(times[w]);
      Row row{"cold", 1, n, k, 2 << w, ms, 0.0, (weight_bytes + scale_bytes) / ms / 1e6, median(reads)};
      row.share = median(shares[w]);
      row.share_min = *std::min_element(shares[w].begin(), shares[w].end());
      row.share_max = *std::max_element(shares[w].begin(), shares[w].end());
      for (const Row& hot : rows) {
        if (hot.mode == "hot" && hot.m == 1 && hot.n == n && hot.k == k && hot.act_bits == row.act_bits) {
          row.hot_gbps = (weight_bytes + scale_bytes) / hot.median_ms / 1e6;
        }
      }
      rows.push_back(row);
      std::printf("%6ld %6ld %8d %10.3f %8.1f %14.1f %7.0f%% %13.0f%% to %.0f%% %10.1f\n", n, k, row.act_bits, ms,
                  row.gbps, row.stream_gbps, 100.0 * row.share, 100.0 * row.share_min, 100.0 * row.share_max,
                  row.hot_gbps);
    }
  }

  FILE* json = std::fopen(json_path, "w");
  if (json == nullptr) return 1;
  const dyq::cpu::CpuPath& path = dyq::cpu::active_cpu_path();
  std::fprintf(json,
               "{\"device\": \"cpu\", \"cpu\": \"%s\", \"cpu_isa\": \"%s\", \"threads\": %u, \"group_size\": %d, "
               "\"dtype\": \"float32\", \"last_level_cache_bytes\": %ld, \"stream_read_bytes\": %zu, "
               "\"stream_read\": \"the faster of two sums of 64-bit words, with and without prefetches 16 KiB ahead\", "
               "\"cold_rounds\": %d, \"cold_calls_per_round\": %d, \"cold_share\": \"median over the rounds of "
               "the width's GB/s over the round's read\", \"rows\": [",
               cpu_model().c_str(), path.name, g_threads, group_size, static_cast<long>(cache_bytes), stream_bytes,
               kColdRounds, kCallsPerRound);
  for (size_t i = 0; i < rows.size(); ++i) {
    const Row& r = rows[i];
    std::fprintf(json,
                 "%s\n  {\"mode\": \"%s\", \"m\": %ld, \"n\": %ld, \"k\": %ld, \"act_bits\": %d, \"kernel\": \"%s\", "
                 "\"median_ms\": %.4f",
                 i ? "," : "", r.mode.c_str(), r.m, r.n, r.k, r.act_bits,
                 path.kernels->gemm_kernel(r.m, r.k, group_size, r.act_bits), r.median_ms);
    if (r.mode == "hot") {
      std::fprintf(json, ", \"cpu_per_thread_ms\": %.4f}", r.cpu_per_thread_ms);
    } else {
      std::fprintf(json,
                   ", \"gbps\": %.2f, \"stream_read_gbps\": %.2f, \"share_of_read\": %.3f, "
                   "\"share_of_read_min\": %.3f, \"share_of_read_max\": %.3f, \"hot_gbps\": %.2f}",
                   r.gbps, r.stream_gbps, r.share, r.share_min, r.share_max, r.hot_gbps);
    }
  }
  std::fprintf(json, "\n]}\n");
  std::fclose(json);
  return 0;
}
