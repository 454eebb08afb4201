// The CPU element types behind dyq::ScalarType, and conversions to and from fp32 (exact widening,
// round-half-to-even narrowing, as torch converts).
#pragma once

#include <Eigen/Core>

#include "common/format.h"

namespace dyq::cpu {

template <typename Element>
inline float to_float(Element v) {
  return static_cast<float>(v);
}

template <typename Element>
inline Element from_float(float v) {
  return static_cast<Element>(v);
}

// Calls fn with a value of the C++ element type of `dtype` (its value is unused; its type selects).
template <typename Fn>
decltype(auto) dispatch_element_type(ScalarType dtype, Fn&& fn) {
  switch (dtype) {
    case ScalarType::kBFloat16:
      return fn(Eigen::bfloat16());
    case ScalarType::kFloat16:
      return fn(Eigen::half());
    case ScalarType::kFloat32:
    default:
      return fn(float());
  }
}

}  // namespace dyq::cpu
