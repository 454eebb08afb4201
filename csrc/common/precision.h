// The precision registry: the one list of activation bit-widths and group sizes, the traits of each
// width, and the helper that turns a run-time width into a compile-time one.
//
// Every layer reads this file instead of spelling the widths out: the torch argument checks and their
// messages, the CPU and CUDA kernels (through dispatch_act_bits), and Python (dyq._C exports the lists,
// python/dyq/core/precision.py reads them). Adding a width is one entry in RegisteredActivationBits plus
// the kernels' handling of its traits; the reference (python/dyq/core/reference.py) keeps formulas of its
// own, and tests/test_precision_registry.py checks that the two agree.
//
// Header-only, torch-free, usable from host and device code.
#pragma once

#include <cstdint>
#include <type_traits>

#include "common/format.h"

namespace dyq {

template <int... kValues>
struct IntList {
  static constexpr int kSize = sizeof...(kValues);
  static constexpr int kValuesArray[kSize] = {kValues...};
};

// Activation bit-widths, ascending. kFallbackBits (16) is the unquantized BF16 path; the others quantize
// x per token and group to unsigned codes (Eq. 2).
using RegisteredActivationBits = IntList<2, 4, 8, kFallbackBits>;
// Group sizes of weights and activations along K: powers of two that hold whole 8-element runs and
// whole 16-byte weight loads (see the kernels' layout comments).
using RegisteredGroupSizes = IntList<32, 64, 128>;

constexpr int kNumActivationWidths = RegisteredActivationBits::kSize;

// Which tensor-core instruction a width's integer or floating-point product runs on (gemm_prefill_cuda.cu).
enum class MmaKind { kU8S8, kU4S4, kBf16 };

// What the kernels need to know about one width.
template <int kBits>
struct ActivationTraits {
  static constexpr int kBitsValue = kBits;
  static constexpr bool kQuantized = kBits != kFallbackBits;
  static_assert(!kQuantized || (kBits <= 8 && 8 % kBits == 0), "quantized codes must tile a byte");
  static constexpr int kCodesPerByte = kQuantized ? 8 / kBits : 0;
  static constexpr int kLevels = kQuantized ? (1 << kBits) - 1 : 0;  // 2^b - 1 of Eq. 2
  // With native INT4 tensor cores (sm_80 / sm_86 / sm_89) codes of at most 4 bits run as u4 against the
  // s4 weights (a k64 step, so the group must hold 64 columns); everything else quantized runs as u8.s8.
  static constexpr MmaKind kMmaWithInt4Cores = !kQuantized ? MmaKind::kBf16 : (kBits <= 4 ? MmaKind::kU4S4 : MmaKind::kU8S8);
  static constexpr MmaKind kMmaWithoutInt4Cores = !kQuantized ? MmaKind::kBf16 : MmaKind::kU8S8;
};

namespace detail {

template <typename Fn, typename Invalid, int kFirst, int... kRest>
DYQ_HOST_DEVICE decltype(auto) dispatch_int(int value, IntList<kFirst, kRest...>, Fn&& fn, Invalid&& invalid) {
  if (value == kFirst) return fn(std::integral_constant<int, kFirst>());
  if constexpr (sizeof...(kRest) > 0) {
    return dispatch_int(value, IntList<kRest...>(), static_cast<Fn&&>(fn), static_cast<Invalid&&>(invalid));
  } else {
    return invalid();
  }
}

template <int... kValues>
DYQ_HOST_DEVICE constexpr bool contains(IntList<kValues...>, int64_t value) {
  return ((value == kValues) || ...);
}

template <int... kValues>
DYQ_HOST_DEVICE constexpr int index_of(IntList<kValues...>, int64_t value) {
  int index = 0, found = -1;
  ((found = (found < 0 && value == kValues) ? index : found, ++index), ...);
  return found;
}

}  // namespace detail

DYQ_HOST_DEVICE constexpr bool is_valid_act_bits(int64_t act_bits) {
  return detail::contains(RegisteredActivationBits(), act_bits);
}

DYQ_HOST_DEVICE constexpr bool is_valid_group_size(int64_t group_size) {
  return detail::contains(RegisteredGroupSizes(), group_size);
}

// Position of a registered width in RegisteredActivationBits (-1 for any other value).
DYQ_HOST_DEVICE constexpr int act_bits_index(int64_t act_bits) {
  return detail::index_of(RegisteredActivationBits(), act_bits);
}

// Calls fn(std::integral_constant<int, b>) for the registered width b == act_bits, or invalid() when
// act_bits is not registered; both must return the same type.
template <typename Fn, typename Invalid>
DYQ_HOST_DEVICE decltype(auto) dispatch_act_bits(int act_bits, Fn&& fn, Invalid&& invalid) {
  return detail::dispatch_int(act_bits, RegisteredActivationBits(), static_cast<Fn&&>(fn),
                              static_cast<Invalid&&>(invalid));
}

}  // namespace dyq
