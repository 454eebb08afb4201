// The activation bit-width as the CUDA kernels receive it. Host-includable (no device code), so the
// torch glue can build one.
#pragma once

#include <cstdint>

namespace dyq::cuda {

// A device-visible int32 read when the kernel runs (the precision flag: mapped pinned host memory or
// device memory), or, when `flag` is null, the fixed `bits`. A kernel that reads a value outside
// {2, 4, 8, 16} writes NaN to its whole output (it cannot raise without a host synchronization).
struct Precision {
  const int32_t* flag;
  int bits;
};

inline Precision fixed_precision(int bits) { return Precision{nullptr, bits}; }
inline Precision flag_precision(const int32_t* device_visible_flag) { return Precision{device_visible_flag, 0}; }

}  // namespace dyq::cuda
