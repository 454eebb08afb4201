// The entry points of one path's kernels. Each cpu/kernels_<isa>.cpp includes this last, after the
// header that defines the path's gemm_typed (and, through it, quantize_activation_row), and so defines
// dyq::cpu::<isa>::kernels, the entry of the dispatch table (cpu/cpu_isa.cpp). The entry points are
// baseline code outside the target region: they only choose the element type and width, then call in.
#pragma once

#include <cstdint>
#include <vector>

#include "common/cpu_dtype.h"
#include "common/precision.h"
#include "cpu/cpu_isa.h"
#include "cpu/isa_region.h"
#include "parallel/parallel.h"

namespace dyq::cpu::DYQ_ISA_NAMESPACE {
namespace {

// The canonical packed layout: code i of each byte in bits [i * b, (i + 1) * b).
template <int kBits>
void pack_codes(const uint8_t* codes, int64_t count, uint8_t* packed) {
  constexpr int kCodesPerByte = ActivationTraits<kBits>::kCodesPerByte;
  for (int64_t byte = 0; byte < count / kCodesPerByte; ++byte) {
    uint32_t packed_byte = 0;
    for (int i = 0; i < kCodesPerByte; ++i) packed_byte |= uint32_t{codes[byte * kCodesPerByte + i]} << (i * kBits);
    packed[byte] = static_cast<uint8_t>(packed_byte);
  }
}

template <int kBits, typename Element>
void quantize_rows(const Element* x, int64_t m, int64_t k, int group_size, uint8_t* packed, float* scales,
                   uint8_t* zeros) {
  const int64_t groups = k / group_size;
  const int64_t packed_row_bytes = packed_activation_bytes(k, kBits);
  parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row_fp32(k);
    std::vector<uint8_t> codes(k);
    std::vector<ActivationGroupParams> params(groups);
    for (int64_t row = row_begin; row < row_end; ++row) {
      quantize_activation_row(x + row * k, k, group_size, kBits, row_fp32.data(), codes.data(), params.data());
      pack_codes<kBits>(codes.data(), k, packed + row * packed_row_bytes);
      for (int64_t g = 0; g < groups; ++g) {
        scales[row * groups + g] = params[g].scale;
        zeros[row * groups + g] = static_cast<uint8_t>(params[g].zero);
      }
    }
  });
}

void quantize_activations(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size, int act_bits,
                          uint8_t* packed, float* scales, uint8_t* zeros) {
  dispatch_element_type(dtype, [&](auto element) {
    using Element = decltype(element);
    dispatch_act_bits(
        act_bits,
        [&](auto bits) {
          constexpr int kBits = decltype(bits)::value;
          if constexpr (ActivationTraits<kBits>::kQuantized) {
            quantize_rows<kBits>(static_cast<const Element*>(x), m, k, group_size, packed, scales, zeros);
          }
        },
        [] {});
  });
}

void gemm(const void* x, ScalarType dtype, const uint8_t* qweight, const float* scales, const void* bias, int64_t m,
          int64_t n, int64_t k, int group_size, int act_bits, void* out) {
  if (m == 0 || n == 0) return;
  dispatch_element_type(dtype, [&](auto element) {
    using Element = decltype(element);
    dispatch_act_bits(
        act_bits,
        [&](auto bits) {
          gemm_typed<decltype(bits)::value>(static_cast<const Element*>(x), qweight, scales,
                                            static_cast<const Element*>(bias), m, n, k, group_size,
                                            static_cast<Element*>(out));
        },
        [] {});
  });
}

}  // namespace

extern const CpuKernelSet kernels = {gemm, quantize_activations};

}  // namespace dyq::cpu::DYQ_ISA_NAMESPACE
