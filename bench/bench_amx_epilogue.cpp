// What the AMX-INT8 tile loop of amx_int8_gemm (gemm/gemm_cpu_amx.h) spends per tile product, part by part,
// and how fast the CPU runs vector arithmetic beside it. Built with the C++ tests (-DDYQ_BUILD_TESTS=ON), run
// by hand on a CPU with AMX:
//
//   build/ctest/dyq_bench_amx_epilogue [results.json]
//
// One thread, everything in L1 or in the tile registers, the loop's own pattern at G = 128: per group of
// 128 columns and block of 32 x 32 outputs, the four C tiles cleared, two steps of two A and two B tile loads
// and four products, then the C tiles stored and the previous group's integer sums scaled into the fp32
// totals by the loop's own epilogue (add_group_to_totals, act_bits 8: a conversion, the z_x sum q_w term,
// the scale product and the multiply-add, four vector operations per 16 outputs). The variants add those
// parts one at a time:
// - products: the clears, tile loads and products alone;
// - + stores: and the C tiles' stores;
// - + epilogue: and the epilogue, as the loop runs (both after the group's products are issued);
// - epilogue alone: the epilogue without any tile work, per group;
// and the rate of independent 512-bit multiply-adds (no tiles): the vector work the epilogue's time follows.
// All run in one process, alternating over rounds (the Xeon with AMX measured moved 2x to 3x between states
// within minutes); the table and the JSON give the median of the rounds.
#define DYQ_CPU_ISA_AVX512_AMX 1

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "bench_util.h"
#include "cpu/cpu_isa.h"
#include "gemm/gemm_cpu_avx512.h"

// The timed code in the AMX path's target region, as the kernels are compiled.
DYQ_ISA_BEGIN
namespace {

namespace amx = dyq::cpu::avx512_amx;

constexpr int kBlocks = 8;         // activation blocks of 32 rows, as 256 rows make
constexpr int kGroupsPerRun = 2;   // a slice of 256 columns
constexpr int kStepBytes = 64;
constexpr int kTileBytes = 1024;

using dyq::bench::median;

struct Operands {
  alignas(64) uint8_t panel[kGroupsPerRun * 2 * 2 * kTileBytes];   // [step][half] A tiles
  alignas(64) uint8_t b_tiles[kBlocks][kGroupsPerRun * 2 * 2 * kTileBytes];  // [block][step][half]
  alignas(64) uint32_t sums[2][amx::kAmxPanelColumns][amx::kAmxRowBlock];
  alignas(64) float totals[kBlocks][amx::kAmxPanelColumns * amx::kAmxRowBlock];
  alignas(64) float zeros[amx::kAmxRowBlock], row_scales[amx::kAmxRowBlock];
  alignas(64) float weight_scales[amx::kAmxPanelColumns], weight_sums[amx::kAmxPanelColumns];
};

enum class Variant { kProducts, kStores, kEpilogue };

// One pass over the blocks and groups of a slice; returns the tile products issued.
template <Variant kVariant>
int64_t tile_pass(amx::NativeTiles& tiles, Operands& o, int& buffer, float*& pending) {
  int64_t products = 0;
  for (int block = 0; block < kBlocks; ++block) {
    const uint8_t* b_tile = o.b_tiles[block];
    for (int group = 0; group < kGroupsPerRun; ++group) {
      amx::zero_block_tiles(tiles, true);
      for (int s = 2 * group; s < 2 * group + 2; ++s, b_tile += 2 * kTileBytes) {
        tiles.load<6>(b_tile, 64);
        tiles.load<4>(o.panel + (2 * s) * kTileBytes, kStepBytes);
        tiles.dpbsud<0, 4, 6>();
        tiles.load<5>(o.panel + (2 * s + 1) * kTileBytes, kStepBytes);
        tiles.dpbsud<2, 5, 6>();
        tiles.load<7>(b_tile + kTileBytes, 64);
        tiles.dpbsud<1, 4, 7>();
        tiles.dpbsud<3, 5, 7>();
        products += 4;
      }
      if constexpr (kVariant == Variant::kEpilogue) {
        if (pending != nullptr) {
          amx::add_group_to_totals<amx::AmxInt8, true>(o.sums[buffer ^ 1], o.zeros, o.row_scales, o.weight_scales,
                                                       o.weight_sums, false, pending);
        }
        pending = o.totals[block];
      }
      if constexpr (kVariant != Variant::kProducts) amx::move_block_tiles<true>(tiles, o.sums[buffer], true);
      buffer ^= 1;
    }
  }
  return products;
}

// ns per tile product of `passes` passes.
template <Variant kVariant>
double ns_per_product(amx::NativeTiles& tiles, Operands& o, int passes) {
  int buffer = 0;
  float* pending = nullptr;
  int64_t products = 0;
  const auto start = std::chrono::steady_clock::now();
  for (int p = 0; p < passes; ++p) products += tile_pass<kVariant>(tiles, o, buffer, pending);
  const double ns = std::chrono::duration<double, std::nano>(std::chrono::steady_clock::now() - start).count();
  return ns / static_cast<double>(products);
}

// ns per group of 32 x 32 outputs of the epilogue alone.
double epilogue_ns_per_group(Operands& o, int passes) {
  const auto start = std::chrono::steady_clock::now();
  for (int p = 0; p < passes; ++p) {
    for (int block = 0; block < kBlocks; ++block) {
      for (int group = 0; group < kGroupsPerRun; ++group) {
        amx::add_group_to_totals<amx::AmxInt8, true>(o.sums[group], o.zeros, o.row_scales, o.weight_scales,
                                                     o.weight_sums, false, o.totals[block]);
      }
    }
  }
  const double ns = std::chrono::duration<double, std::nano>(std::chrono::steady_clock::now() - start).count();
  return ns / (static_cast<double>(passes) * kBlocks * kGroupsPerRun);
}

// Independent 512-bit multiply-adds per ns: twelve chains, more than the latency times the units' count.
__attribute__((noinline)) double fma_per_ns(int64_t iterations) {
  __m512 chains[12];
  for (int i = 0; i < 12; ++i) chains[i] = _mm512_set1_ps(1.0f + 1e-7f * static_cast<float>(i));
  const __m512 factor = _mm512_set1_ps(0.9999999f), addend = _mm512_set1_ps(1e-9f);
  const auto start = std::chrono::steady_clock::now();
  for (int64_t i = 0; i < iterations; ++i) {
#pragma GCC unroll 12
    for (int c = 0; c < 12; ++c) chains[c] = _mm512_fmadd_ps(chains[c], factor, addend);
    // Keeps the chains in registers and the loop from being folded.
    asm volatile("" : "+v"(chains[0]), "+v"(chains[1]), "+v"(chains[2]), "+v"(chains[3]), "+v"(chains[4]),
                 "+v"(chains[5]), "+v"(chains[6]), "+v"(chains[7]), "+v"(chains[8]), "+v"(chains[9]),
                 "+v"(chains[10]), "+v"(chains[11]));
  }
  const double ns = std::chrono::duration<double, std::nano>(std::chrono::steady_clock::now() - start).count();
  return 12.0 * static_cast<double>(iterations) / ns;
}

struct Medians {
  double products, stores, epilogue, alone, fma;
};

constexpr int kRounds = 15;

Medians time_parts(Operands& o) {
  amx::NativeTiles tiles;
  tiles.configure(kStepBytes);
  constexpr int kPasses = 400;
  std::vector<double> products, stores, epilogue, alone, fma;
  for (int round = 0; round < kRounds; ++round) {
    products.push_back(ns_per_product<Variant::kProducts>(tiles, o, kPasses));
    stores.push_back(ns_per_product<Variant::kStores>(tiles, o, kPasses));
    epilogue.push_back(ns_per_product<Variant::kEpilogue>(tiles, o, kPasses));
    alone.push_back(epilogue_ns_per_group(o, kPasses));
    fma.push_back(fma_per_ns(2000000));
  }
  tiles.release();
  return {median(products), median(stores), median(epilogue), median(alone), median(fma)};
}

}  // namespace
DYQ_ISA_END

int main(int argc, char** argv) {
  const char* json_path = argc > 1 ? argv[1] : "bench_amx_epilogue.json";
  bool amx_runs = false;  // listing the paths also requests the tile state from Linux
  for (const auto* path : dyq::cpu::runnable_cpu_paths()) amx_runs |= std::string(path->name) == "amx";
  if (!amx_runs) {
    std::printf("this CPU has no AMX-INT8 (or the OS did not grant the tile state): nothing to time\n");
    return 0;
  }
  auto operands = std::make_unique<Operands>();
  Operands& o = *operands;
  std::mt19937 rng(0);
  std::uniform_int_distribution<int> code(-8, 7), byte(0, 255);
  for (auto& b : o.panel) b = static_cast<uint8_t>(code(rng));
  for (auto& block : o.b_tiles) {
    for (auto& b : block) b = static_cast<uint8_t>(byte(rng));
  }
  std::uniform_real_distribution<float> positive(0.5f, 2.0f);
  for (int i = 0; i < amx::kAmxRowBlock; ++i) o.zeros[i] = 128.0f, o.row_scales[i] = positive(rng);
  for (int i = 0; i < amx::kAmxPanelColumns; ++i) o.weight_scales[i] = positive(rng), o.weight_sums[i] = 3.0f;
  std::memset(o.sums, 0, sizeof(o.sums));
  std::memset(o.totals, 0, sizeof(o.totals));

  const Medians r = time_parts(o);
  // The epilogue of one group: 64 vectors of 16 outputs, four vector operations each, for 8 tile products.
  constexpr double kProductsPerGroup = 8.0, kEpilogueVectorOps = 64.0 * 4.0;
  const double products_ns = r.products, stores_ns = r.stores, epilogue_ns = r.epilogue;
  const double alone_ns = r.alone, fma_rate = r.fma;
  std::printf("The AMX-INT8 tile loop's parts (G = 128, 32 x 32 blocks, one thread, in L1), median of %d rounds\n"
              "%-34s %10.2f ns per tile product\n%-34s %10.2f ns per tile product\n%-34s %10.2f ns per tile "
              "product\n%-34s %10.2f ns per group (%.2f ns per tile product)\n"
              "%-34s %10.2f per ns (the epilogue's %g vector operations a group in %.1f ns at that rate)\n",
              kRounds, "products", products_ns, "+ C tile stores", stores_ns, "+ epilogue (the loop)", epilogue_ns,
              "epilogue alone", alone_ns, alone_ns / kProductsPerGroup, "512-bit multiply-adds", fma_rate,
              kEpilogueVectorOps, kEpilogueVectorOps / fma_rate);
  FILE* json = std::fopen(json_path, "w");
  if (json == nullptr) return 1;
  std::fprintf(json,
               "{\"device\": \"cpu\", \"cpu\": \"%s\", \"compiler\": \"%s\", \"cpu_isa\": \"amx\", "
               "\"threads\": 1, \"group_size\": 128, \"act_bits\": 8, \"rounds\": %d, "
               "\"statistic\": \"median over the rounds\", \"products_ns_per_product\": %.3f, "
               "\"with_stores_ns_per_product\": %.3f, \"with_epilogue_ns_per_product\": %.3f, "
               "\"epilogue_alone_ns_per_group\": %.3f, \"tile_products_per_group\": %g, "
               "\"epilogue_vector_ops_per_group\": %g, \"fma512_per_ns\": %.3f}\n",
               dyq::bench::cpu_model().c_str(), __VERSION__, kRounds, products_ns, stores_ns, epilogue_ns, alone_ns,
               kProductsPerGroup, kEpilogueVectorOps, fma_rate);
  std::fclose(json);
  return 0;
}
