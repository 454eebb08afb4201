// Cache-line aligned storage and a per-thread scratch buffer for the CPU kernels. Plain C++ (no
// intrinsics), so that it serves every instruction-set path from outside their target regions.
#pragma once

#include <cstddef>
#include <cstdint>
#include <new>
#include <vector>

namespace dyq::cpu {

// Cache-line aligned storage, so that full-vector loads never split a line.
template <typename T>
struct CacheLineAllocator {
  using value_type = T;
  CacheLineAllocator() = default;
  template <typename U>
  CacheLineAllocator(const CacheLineAllocator<U>&) {}
  T* allocate(size_t count) { return static_cast<T*>(::operator new(count * sizeof(T), std::align_val_t{64})); }
  void deallocate(T* p, size_t) { ::operator delete(p, std::align_val_t{64}); }
  bool operator==(const CacheLineAllocator&) const { return true; }
  bool operator!=(const CacheLineAllocator&) const { return false; }
};
template <typename T>
using AlignedVector = std::vector<T, CacheLineAllocator<T>>;

// A per-thread buffer of at least `count` floats, cache-line aligned, kept between calls (a row kernel's
// per-call products; one user at a time on a thread).
inline float* scratch_floats(int64_t count) {
  static thread_local AlignedVector<float> buffer;
  if (static_cast<int64_t>(buffer.size()) < count) buffer.resize(count);
  return buffer.data();
}

}  // namespace dyq::cpu
