// Dynamic activation quantization with packed output (docs/numerics.md, section 2).
#include "activation/act_quant_cpu.h"

#include <vector>

#include "activation/act_quant_cpu_row.h"
#include "parallel/parallel.h"

namespace dyq::cpu {
namespace {

constexpr int64_t kRowGrain = 4;

template <typename Element>
void quantize_rows(const Element* x, int64_t m, int64_t k, int group_size, int act_bits, uint8_t* packed,
                   float* scales, uint8_t* zeros) {
  const int64_t groups = k / group_size;
  const int64_t packed_row_bytes = packed_activation_bytes(k, act_bits);
  const int64_t group_bytes = packed_activation_bytes(group_size, act_bits);
  const int codes_per_byte = 8 / act_bits;
  parallel_for(0, m, kRowGrain, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row_fp32(k);
    std::vector<uint8_t> group_codes(group_size);
    for (int64_t row = row_begin; row < row_end; ++row) {
      uint8_t* packed_row = packed + row * packed_row_bytes;
      quantize_activation_row(x + row * k, k, group_size, act_bits, row_fp32.data(), group_codes.data(),
                              [&](int64_t g, ActivationGroupParams params, const uint8_t* codes) {
                                scales[row * groups + g] = params.scale;
                                zeros[row * groups + g] = static_cast<uint8_t>(params.zero);
                                uint8_t* out = packed_row + g * group_bytes;
                                for (int64_t byte = 0; byte < group_bytes; ++byte) {
                                  uint32_t packed_byte = 0;
                                  for (int i = 0; i < codes_per_byte; ++i) {
                                    packed_byte |= uint32_t{codes[byte * codes_per_byte + i]} << (i * act_bits);
                                  }
                                  out[byte] = static_cast<uint8_t>(packed_byte);
                                }
                              });
    }
  });
}

}  // namespace

void quantize_activations(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size, int act_bits,
                          uint8_t* packed, float* scales, uint8_t* zeros) {
  dispatch_element_type(dtype, [&](auto element) {
    using Element = decltype(element);
    quantize_rows(static_cast<const Element*>(x), m, k, group_size, act_bits, packed, scales, zeros);
  });
}

}  // namespace dyq::cpu
