// The vectorized fp32 -> bf16 writer of the CPU paths with bf16 instructions (store_row_from_fp32 in
// activation/act_quant_cpu_row.h, compiled here in the avx512_bf16 region, the same source as the amx path's)
// against from_float bit for bit: vcvtneps2bf16 where a vector holds neither a NaN nor a denormal, the
// integer rounding otherwise. Random bit patterns reach every exponent, both signs, NaN payloads and
// denormals; ties and the values that round up to infinity are added by hand.
#if defined(__x86_64__) || defined(_M_X64)
#define DYQ_CPU_ISA_AVX512_BF16 1

#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "activation/act_quant_cpu_row.h"
#include "common/cpu_dtype.h"
#include "cpu/cpu_isa.h"
#include "cpu/isa_region.h"

// The writer is always inlined: it is called from a function of its own instruction set.
DYQ_ISA_BEGIN
namespace dyq::cpu::avx512_bf16 {
bool store_bf16_row(const float* values, int64_t count, Eigen::bfloat16* out) {
  return store_row_from_fp32<Eigen::bfloat16>(values, nullptr, count, out);
}
}  // namespace dyq::cpu::avx512_bf16
DYQ_ISA_END

namespace {

bool cpu_has_bf16_path() {
  for (const auto* path : dyq::cpu::runnable_cpu_paths()) {
    if (std::string(path->name) == "avx512_bf16") return true;
  }
  return false;
}

float from_bits(uint32_t bits) {
  float value;
  std::memcpy(&value, &bits, sizeof value);
  return value;
}

uint16_t bits_of(Eigen::bfloat16 value) {
  uint16_t bits;
  std::memcpy(&bits, &value, sizeof bits);
  return bits;
}

TEST(StoreBf16, VectorizedWriterMatchesFromFloatBitForBit) {
  if (!cpu_has_bf16_path()) GTEST_SKIP() << "this CPU has no AVX512-BF16";
  std::mt19937 rng(2027);
  std::vector<float> values;
  for (int i = 0; i < 1 << 16; ++i) values.push_back(from_bits(rng()));
  // Vectors without NaN or denormal take vcvtneps2bf16: ties to even (bit 16 clear and set), the largest
  // finite values, which round to infinity, and ordinary normals.
  for (uint32_t high : {0x3F80u, 0x3F81u, 0xC2F3u, 0x0081u, 0x7F7Eu, 0xFF7Fu}) {
    for (uint32_t low : {0x8000u, 0x7FFFu, 0x8001u, 0x0000u}) values.push_back(from_bits(high << 16 | low));
  }
  values.push_back(from_bits(0x7F7FFFFFu));  // FLT_MAX: to +inf
  values.push_back(INFINITY);
  values.push_back(-0.0f);
  // Denormals (read as 0 by the instruction) and NaNs with payloads, alone in otherwise normal vectors.
  for (uint32_t special : {0x00000001u, 0x807FFFFFu, 0x00008000u, 0x00018000u, 0x7F800001u, 0xFFC12345u}) {
    for (int i = 0; i < 15; ++i) values.push_back(1.0f + static_cast<float>(i) / 64.0f);
    values.push_back(from_bits(special));
  }
  for (size_t begin = 0; begin < values.size(); begin += 48) {
    const int64_t count = static_cast<int64_t>(std::min<size_t>(48, values.size() - begin));
    std::vector<Eigen::bfloat16> out(count);
    const bool finite = dyq::cpu::avx512_bf16::store_bf16_row(values.data() + begin, count, out.data());
    bool expected_finite = true;
    for (int64_t i = 0; i < count; ++i) {
      const Eigen::bfloat16 expected = dyq::cpu::from_float<Eigen::bfloat16>(values[begin + i]);
      ASSERT_EQ(bits_of(out[i]), bits_of(expected)) << "fp32 bits " << std::hex << [&] {
        uint32_t bits;
        std::memcpy(&bits, &values[begin + i], sizeof bits);
        return bits;
      }();
      expected_finite &= std::isfinite(static_cast<float>(expected));
    }
    ASSERT_EQ(finite, expected_finite) << "values from " << begin;
  }
}

}  // namespace
#endif
