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
// and the rate of independent 512-bit multiply-adds (no tiles): the vector work the epilogue's time follows;
// and as many vector operations as the epilogue's beside tile products that read no memory, against either
// alone: how much vector work the CPU runs while the tiles multiply, per kind of operation (multiply-adds of
// 512 and 256 bits, multiplies, conversions, fp32 adds, integer adds).
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
#include <utility>
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

// Vector operations beside the tile products: 16 independent chains of one operation on 512-bit (Zmm) or
// 256-bit (Ymm) vectors, per round kOps of them, with kTiles also 8 tile products on operands already in the
// tiles (the four C tiles twice each, as a group of the loop takes them). ns per round. On the Xeon with AMX
// measured, the tile products leave the multiplier class (multiply-adds, multiplies, conversions) one of its
// two 512-bit ports, while fp32 adds and integer adds keep both (docs/cpu_performance.md).
struct Zmm {
  using Vector = __m512;
  static constexpr const char* kName = "512-bit multiply-add";
  static Vector start(int i) { return _mm512_set1_ps(1.0f + 1e-7f * static_cast<float>(i)); }
  static Vector step(Vector v) { return _mm512_fmadd_ps(v, _mm512_set1_ps(0.9999999f), _mm512_set1_ps(1e-9f)); }
};
struct Ymm {
  using Vector = __m256;
  static constexpr const char* kName = "256-bit multiply-add";
  static Vector start(int i) { return _mm256_set1_ps(1.0f + 1e-7f * static_cast<float>(i)); }
  static Vector step(Vector v) { return _mm256_fmadd_ps(v, _mm256_set1_ps(0.9999999f), _mm256_set1_ps(1e-9f)); }
};
// The epilogue's other operation classes, 512-bit: a multiply (by a factor that keeps the values normal), an
// fp32 add, an int32-to-fp32 conversion (of the bits: the loop only times it) and an integer add.
struct ZmmMultiply : Zmm {
  static constexpr const char* kName = "512-bit multiply";
  static Vector step(Vector v) { return _mm512_mul_ps(v, _mm512_set1_ps(0.9999999f)); }
};
struct ZmmAdd : Zmm {
  static constexpr const char* kName = "512-bit fp32 add";
  static Vector step(Vector v) { return _mm512_add_ps(v, _mm512_set1_ps(1e-9f)); }
};
struct ZmmConvert : Zmm {
  static constexpr const char* kName = "512-bit int32 -> fp32";
  static Vector step(Vector v) { return amx::cvtepi32_ps(_mm512_castps_si512(v)); }
};
struct ZmmIntegerAdd : Zmm {
  static constexpr const char* kName = "512-bit int32 add";
  static Vector step(Vector v) {
    __m512i sum = _mm512_add_epi32(_mm512_castps_si512(v), _mm512_set1_epi32(1));
    asm("" : "+v"(sum));  // so that the compiler cannot fold a chain's adds into one
    return _mm512_castsi512_ps(sum);
  }
};

template <typename Width, int kOps, bool kTiles>
__attribute__((noinline)) double beside_tiles_ns(amx::NativeTiles& tiles, int64_t rounds) {
  constexpr int kChains = 16;
  typename Width::Vector chains[kChains];
  for (int c = 0; c < kChains; ++c) chains[c] = Width::start(c);
  const auto start = std::chrono::steady_clock::now();
  for (int64_t r = 0; r < rounds; ++r) {
    if constexpr (kTiles) {
      for (int twice = 0; twice < 2; ++twice) {
        tiles.dpbsud<0, 4, 6>();
        tiles.dpbsud<2, 5, 6>();
        tiles.dpbsud<1, 4, 7>();
        tiles.dpbsud<3, 5, 7>();
      }
    }
#pragma GCC unroll 64
    for (int i = 0; i < kOps / kChains; ++i) {
#pragma GCC unroll 16
      for (int c = 0; c < kChains; ++c) chains[c] = Width::step(chains[c]);
    }
    // Keeps the chains in registers and the loop from being folded.
#pragma GCC unroll 16
    for (int c = 0; c < kChains; ++c) asm volatile("" : "+v"(chains[c]));
  }
  return std::chrono::duration<double, std::nano>(std::chrono::steady_clock::now() - start).count() /
         static_cast<double>(rounds);
}

// The tile products alone, the vector operations alone and both in one loop, ns per round of 8 products.
struct Beside {
  const char* name;
  int ops;
  double tiles, vectors, both;
};

// One kind of operation's rounds: its name and count per round, and the times of each round.
struct BesideTimes {
  const char* name = nullptr;
  int ops = 0;
  std::vector<double> tiles, vectors, both;
};

// As many vector operations per 8 tile products as the epilogue's at G = 128: 256 of 16 floats (512 of 8).
constexpr int kBesideZmmOps = 256, kBesideYmmOps = 512;

struct Medians {
  double products, stores, epilogue, alone, fma;
  std::vector<Beside> beside;
};

// One round of Op beside the tiles: the products alone, the operations alone, then both.
template <typename Op, int kOps>
void time_beside(amx::NativeTiles& tiles, int64_t rounds, BesideTimes& times) {
  times.name = Op::kName;
  times.ops = kOps;
  times.tiles.push_back(beside_tiles_ns<Op, 0, true>(tiles, rounds));
  times.vectors.push_back(beside_tiles_ns<Op, kOps, false>(tiles, rounds));
  times.both.push_back(beside_tiles_ns<Op, kOps, true>(tiles, rounds));
}

constexpr int kRounds = 15;

Medians time_parts(Operands& o) {
  amx::NativeTiles tiles;
  tiles.configure(kStepBytes);
  constexpr int kPasses = 400;
  std::vector<double> products, stores, epilogue, alone, fma;
  BesideTimes beside[6];  // one per kind of operation, in the order timed below
  constexpr int64_t kBesideRounds = 100000;
  for (int round = 0; round < kRounds; ++round) {
    products.push_back(ns_per_product<Variant::kProducts>(tiles, o, kPasses));
    stores.push_back(ns_per_product<Variant::kStores>(tiles, o, kPasses));
    epilogue.push_back(ns_per_product<Variant::kEpilogue>(tiles, o, kPasses));
    alone.push_back(epilogue_ns_per_group(o, kPasses));
    fma.push_back(fma_per_ns(2000000));
    // Operands in the tiles: the products of the rounds below read no memory.
    tiles.load<4>(o.panel, kStepBytes);
    tiles.load<5>(o.panel + kTileBytes, kStepBytes);
    tiles.load<6>(o.b_tiles[0], 64);
    tiles.load<7>(o.b_tiles[0] + kTileBytes, 64);
    time_beside<Zmm, kBesideZmmOps>(tiles, kBesideRounds, beside[0]);
    time_beside<Ymm, kBesideYmmOps>(tiles, kBesideRounds, beside[1]);
    time_beside<ZmmMultiply, kBesideZmmOps>(tiles, kBesideRounds, beside[2]);
    time_beside<ZmmConvert, kBesideZmmOps>(tiles, kBesideRounds, beside[3]);
    time_beside<ZmmAdd, kBesideZmmOps>(tiles, kBesideRounds, beside[4]);
    time_beside<ZmmIntegerAdd, kBesideZmmOps>(tiles, kBesideRounds, beside[5]);
  }
  tiles.release();
  std::vector<Beside> beside_medians;
  for (const BesideTimes& times : beside) {
    beside_medians.push_back({times.name, times.ops, median(times.tiles), median(times.vectors), median(times.both)});
  }
  return {median(products), median(stores), median(epilogue), median(alone), median(fma), beside_medians};
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
  std::printf("\nVector operations beside the tile products (operands in the tiles), ns per 8 products and 4096 "
              "lanes of the operation\n%-24s %10s %10s %10s %12s\n",
              "operation", "tiles", "vectors", "both", "both / sum");
  for (const Beside& b : r.beside) {
    std::printf("%-24s %10.2f %10.2f %10.2f %12.2f\n", b.name, b.tiles, b.vectors, b.both, b.both / (b.tiles + b.vectors));
  }
  FILE* json = std::fopen(json_path, "w");
  if (json == nullptr) return 1;
  std::fprintf(json,
               "{\"device\": \"cpu\", \"cpu\": \"%s\", \"compiler\": \"%s\", \"cpu_isa\": \"amx\", "
               "\"threads\": 1, \"group_size\": 128, \"act_bits\": 8, \"rounds\": %d, "
               "\"statistic\": \"median over the rounds\", \"products_ns_per_product\": %.3f, "
               "\"with_stores_ns_per_product\": %.3f, \"with_epilogue_ns_per_product\": %.3f, "
               "\"epilogue_alone_ns_per_group\": %.3f, \"tile_products_per_group\": %g, "
               "\"epilogue_vector_ops_per_group\": %g, \"fma512_per_ns\": %.3f, "
               "\"beside_tiles\": {\"products_per_round\": 8, \"lanes_per_round\": 4096",
               dyq::bench::cpu_model().c_str(), __VERSION__, kRounds, products_ns, stores_ns, epilogue_ns, alone_ns,
               kProductsPerGroup, kEpilogueVectorOps, fma_rate);
  for (const Beside& b : r.beside) {
    std::fprintf(json, ", \"%s\": {\"ops_per_round\": %d, \"tiles_ns\": %.3f, \"vectors_ns\": %.3f, \"both_ns\": %.3f}",
                 b.name, b.ops, b.tiles, b.vectors, b.both);
  }
  std::fprintf(json, "}}\n");
  std::fclose(json);
  return 0;
}
