// Tensor-core and asynchronous-copy instructions used by the prefill GEMM, as thin inline-PTX wrappers.
//
// Fragment layouts (PTX ISA, "Matrix fragments for mma.m16n8k*"), with g = lane / 4, t = lane % 4:
//   m16n8k32 u8.s8  A: a0 = row g,   k 4t..4t+3      a1 = row g+8, k 4t..4t+3
//                      a2 = row g,   k 4t+16..4t+19  a3 = row g+8, k 4t+16..4t+19   (4 bytes per reg)
//                   B: b0 = col g,   k 4t..4t+3      b1 = col g,   k 4t+16..4t+19
//   m16n8k64 u4.s4  as above with 8 nibbles per register: k 8t..8t+7 and 8t+32..8t+39.
//   m16n8k16 bf16   as above with 2 halves per register: k 2t, 2t+1 and 2t+8, 2t+9.
//   C (all three):  c0, c1 = row g, cols 2t, 2t+1;  c2, c3 = row g+8, cols 2t, 2t+1.
// So in every shape a thread's A registers (per row) and B registers cover the same two k-chunks,
// "chunk 0" (a0/a1 with b0) and "chunk 1" (a2/a3 with b1). A dot product does not care which physical
// columns a k index stands for, as long as A and B agree; the GEMM assigns each thread's two chunks to
// physical columns that it can load with one aligned shared-memory access (see gemm_prefill_cuda.cu).
#pragma once

#include <cstdint>

namespace dyq::cuda {

__device__ __forceinline__ void mma_m16n8k32_u8s8(int (&c)[4], const uint32_t (&a)[4], uint32_t b0, uint32_t b1) {
  asm("mma.sync.aligned.m16n8k32.row.col.s32.u8.s8.s32 {%0,%1,%2,%3}, {%4,%5,%6,%7}, {%8,%9}, {%0,%1,%2,%3};\n"
      : "+r"(c[0]), "+r"(c[1]), "+r"(c[2]), "+r"(c[3])
      : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b0), "r"(b1));
}

// Native INT4 tensor cores exist on sm_80 / sm_86 / sm_89 only; sm_90 emulates this instruction.
__device__ __forceinline__ void mma_m16n8k64_u4s4(int (&c)[4], const uint32_t (&a)[4], uint32_t b0, uint32_t b1) {
  asm("mma.sync.aligned.m16n8k64.row.col.s32.u4.s4.s32 {%0,%1,%2,%3}, {%4,%5,%6,%7}, {%8,%9}, {%0,%1,%2,%3};\n"
      : "+r"(c[0]), "+r"(c[1]), "+r"(c[2]), "+r"(c[3])
      : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b0), "r"(b1));
}

__device__ __forceinline__ void mma_m16n8k16_bf16(float (&c)[4], const uint32_t (&a)[4], uint32_t b0, uint32_t b1) {
  asm("mma.sync.aligned.m16n8k16.row.col.f32.bf16.bf16.f32 {%0,%1,%2,%3}, {%4,%5,%6,%7}, {%8,%9}, {%0,%1,%2,%3};\n"
      : "+f"(c[0]), "+f"(c[1]), "+f"(c[2]), "+f"(c[3])
      : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b0), "r"(b1));
}

// 16 bytes global -> shared, bypassing L1; bytes past `src_bytes` (0..16) are zero-filled, so tails of
// rows and tiles need no separate path.
__device__ __forceinline__ void cp_async_16(void* smem_dst, const void* gmem_src, int src_bytes) {
  const uint32_t dst = static_cast<uint32_t>(__cvta_generic_to_shared(smem_dst));
  asm volatile("cp.async.cg.shared.global [%0], [%1], 16, %2;\n" ::"r"(dst), "l"(gmem_src), "r"(src_bytes)
               : "memory");
}

__device__ __forceinline__ void cp_async_commit() { asm volatile("cp.async.commit_group;\n" ::: "memory"); }

template <int kPendingGroups>
__device__ __forceinline__ void cp_async_wait() {
  asm volatile("cp.async.wait_group %0;\n" ::"n"(kPendingGroups) : "memory");
}

}  // namespace dyq::cuda
