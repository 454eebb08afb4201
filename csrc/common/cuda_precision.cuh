// The activation bit-width as the CUDA kernels receive it. Host-includable (no device code), so the
// torch glue can build one.
#pragma once

#include <cstdint>

namespace dyq::cuda {

// A device-visible int32 read when the kernel runs (the precision flag: mapped pinned host memory or
// device memory), raised to at least `bits` (a layer's floor, min_act_bits; 2 for none), or, when `flag`
// is null, the fixed `bits`. A kernel that reads a value outside {2, 4, 8, 16} writes NaN to its whole
// output (it cannot raise without a host synchronization); the floor does not hide such a value.
struct Precision {
  const int32_t* flag;
  int bits;
};

inline Precision fixed_precision(int bits) { return Precision{nullptr, bits}; }
inline Precision flag_precision(const int32_t* device_visible_flag, int min_bits = 2) {
  return Precision{device_visible_flag, min_bits};
}

}  // namespace dyq::cuda
