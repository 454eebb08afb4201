// From how many activation rows the AMX-INT8 tiles beat the AVX-512 VNNI row and panel kernels, the timing
// behind amx_min_rows (gemm/gemm_cpu_avx512.h). Built with the C++ tests (-DDYQ_BUILD_TESTS=ON), run by hand
// on a CPU with AMX:
//
//   build/ctest/dyq_bench_amx_threshold [results.json [threads]]
//
// Both paths run in one process on the same inputs, hot, alternating over nine rounds: the machine's drift
// reaches both alike (the Xeon with AMX measured moved 2x between states within minutes). Per round the
// ratio of their medians; the table and the JSON give the median of the rounds' ratios, the VNNI kernels'
// time over the tiles' (above 1: the tiles are faster), with its range.
//
// The kernels are called themselves, so this file is compiled as the AMX path's kernel files are: the path
// defined before the first include (cpu/isa_region.h).
#define DYQ_CPU_ISA_AVX512_AMX 1

#include <algorithm>
#include <array>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include "bench_util.h"
#include "cpu/cpu_isa.h"
#include "parallel/parallel.h"
#include "weight/weight_pack_cpu.h"
#include "gemm/gemm_cpu_avx512.h"

namespace {

namespace amx = dyq::cpu::avx512_amx;

using dyq::bench::median;

struct Row {
  int64_t m, n, k;
  int act_bits;
  double vnni_ms, tiles_ms, ratio, ratio_min, ratio_max;
};

template <int kBits>
Row time_both(int64_t m, int64_t n, int64_t k, int group_size, std::mt19937& rng) {
  std::normal_distribution<float> normal(0.0f, 1.0f);
  std::vector<float> weight(n * k), x(m * k), out(m * n);
  for (auto& w : weight) w = 0.02f * normal(rng);
  for (auto& v : x) v = normal(rng);
  std::vector<uint8_t> qweight(n * k / 2);
  std::vector<float> scales(n * dyq::group_count(k, group_size));
  dyq::cpu::quantize_weight(weight.data(), n, k, group_size, qweight.data(), scales.data());
  auto vnni = [&] {
    amx::vnni_gemm<kBits, float>(x.data(), qweight.data(), scales.data(), nullptr, m, n, k, group_size, out.data());
  };
  auto tiles = [&] {
    amx::amx_int8_gemm_at<kBits, float>(x.data(), qweight.data(), scales.data(), nullptr, m, n, k, group_size,
                                        out.data());
  };
  auto call_ms = [](auto&& call, int calls) {
    std::vector<double> times;
    for (int i = 0; i < calls; ++i) {
      const auto start = std::chrono::steady_clock::now();
      call();
      times.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count());
    }
    return median(times);
  };
  vnni();
  tiles();
  const int calls = static_cast<int>(std::clamp<int64_t>(int64_t{400000000} / (m * n * k), 5, 200));
  constexpr int kRounds = 9;
  std::vector<double> vnni_ms, tiles_ms, ratios;
  for (int round = 0; round < kRounds; ++round) {
    vnni_ms.push_back(call_ms(vnni, calls));
    tiles_ms.push_back(call_ms(tiles, calls));
    ratios.push_back(vnni_ms.back() / tiles_ms.back());
  }
  return {m, n, k, kBits, median(vnni_ms), median(tiles_ms), median(ratios),
          *std::min_element(ratios.begin(), ratios.end()), *std::max_element(ratios.begin(), ratios.end())};
}

unsigned g_threads = 1;
int thread_count() { return static_cast<int>(g_threads); }

}  // namespace

int main(int argc, char** argv) {
  const char* json_path = argc > 1 ? argv[1] : "bench_amx_threshold.json";
  g_threads = argc > 2 ? static_cast<unsigned>(std::atoi(argv[2])) : 1;
  bool amx_runs = false;  // listing the paths also requests the tile state from Linux
  for (const auto* path : dyq::cpu::runnable_cpu_paths()) amx_runs |= std::string(path->name) == "amx";
  if (!amx_runs) {
    std::printf("this CPU has no AMX-INT8 (or the OS did not grant the tile state): nothing to time\n");
    return 0;
  }
  dyq::set_thread_count_source(thread_count);
  constexpr int kGroup = 128;
  const std::array<std::array<int64_t, 2>, 3> shapes = {{{4096, 4096}, {4096, 11008}, {768, 256}}};
  std::mt19937 rng(0);
  std::vector<Row> rows;
  std::printf("VNNI row/panel kernels against the AMX-INT8 tiles, hot, %u thread(s), G = %d, median of 9 rounds\n"
              "%4s %6s %6s %8s %10s %10s %14s %14s\n",
              g_threads, kGroup, "M", "N", "K", "act_bits", "vnni ms", "tiles ms", "vnni / tiles", "rounds");
  for (int64_t m : {4, 8, 10, 12, 15, 16}) {
    for (auto [n, k] : shapes) {
      for (const Row& r : {time_both<4>(m, n, k, kGroup, rng), time_both<8>(m, n, k, kGroup, rng)}) {
        rows.push_back(r);
        std::printf("%4ld %6ld %6ld %8d %10.4f %10.4f %13.2fx %7.2f..%.2f\n", r.m, r.n, r.k, r.act_bits, r.vnni_ms,
                    r.tiles_ms, r.ratio, r.ratio_min, r.ratio_max);
      }
    }
  }
  FILE* json = std::fopen(json_path, "w");
  if (json == nullptr) return 1;
  std::fprintf(json,
               "{\"device\": \"cpu\", \"cpu_isa\": \"amx\", \"threads\": %u, \"group_size\": %d, \"dtype\": "
               "\"float32\", \"mode\": \"hot\", \"rounds\": 9, \"ratio\": \"median over the rounds of the VNNI "
               "kernels' median time over the tiles'\", \"amx_min_rows\": {\"2\": %ld, \"4\": %ld, \"8\": %ld}, "
               "\"rows\": [",
               g_threads, kGroup, static_cast<long>(amx::amx_min_rows(2)), static_cast<long>(amx::amx_min_rows(4)),
               static_cast<long>(amx::amx_min_rows(8)));
  for (size_t i = 0; i < rows.size(); ++i) {
    const Row& r = rows[i];
    std::fprintf(json,
                 "%s\n  {\"m\": %ld, \"n\": %ld, \"k\": %ld, \"act_bits\": %d, \"vnni_ms\": %.4f, \"tiles_ms\": %.4f, "
                 "\"vnni_over_tiles\": %.3f, \"vnni_over_tiles_min\": %.3f, \"vnni_over_tiles_max\": %.3f}",
                 i ? "," : "", r.m, r.n, r.k, r.act_bits, r.vnni_ms, r.tiles_ms, r.ratio, r.ratio_min, r.ratio_max);
  }
  std::fprintf(json, "\n]}\n");
  std::fclose(json);
  return 0;
}
