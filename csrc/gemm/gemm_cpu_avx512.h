// The AVX-512 (VNNI) GEMM behind dyq::cpu::gemm on CPUs that have it (docs/numerics.md, section 3).
//
// Both kernels stream each packed weight row once per tile of activation rows and never materialize
// unpacked weights in memory:
// - act_bits 2/4/8: a 64-byte load holds 128 columns of one weight row. Splitting it into low and high
//   nibbles gives the even and the odd columns as s8 codes, so the activation codes are stored in the
//   same even/odd order (DecodeBlock) and one vpdpbusd (u8 q_x times s8 q_w) per half forms exact
//   integer sums of 8 columns per int32 lane. Lane i covers columns 8i..8i+7, hence lies in a single
//   group for every group size: each lane carries its group's s_x, s_w and z_x, and the zero-point term
//   z_x * sum(q_w) is subtracted in fp32, which is exact because both are integers below 2^24.
// - act_bits 16: 16 packed bytes (32 columns) are widened to int32 lanes and mapped nibble -> fp32 code
//   with a 16-entry permute; x is stored as even/odd halves per 32 columns to match, and each group's
//   fp32 partial sum is scaled by s_w once.
// K need only be even: the row kernels mask the tail of each row (weight bytes past K load as 0, so the
// last group, which holds the remainder when G does not divide K, gets only its own columns), and the
// panel path runs on copies of x and the weights zero-padded to whole groups, which quantize and sum to
// the same numbers (zeros change neither a group's range nor its sums; docs/numerics.md, section 4).
#pragma once

#include <algorithm>
#include <new>
#include <cstring>
#include <type_traits>
#include <utility>
#include <vector>

#include "activation/act_quant_cpu_row.h"
#include "common/cpu_dtype.h"
#include "common/format.h"
#include "common/precision.h"
#include "common/scratch.h"
#include "cpu/isa_region.h"
#include "cpu/x86_ops.h"
#include "parallel/parallel.h"
// The AMX tile loop, and the order of the packed nibbles that the bf16 row kernels share with it.
#include "gemm/gemm_cpu_amx.h"

DYQ_ISA_BEGIN
namespace dyq::cpu::DYQ_ISA_NAMESPACE {

constexpr int64_t kBlockColumns = 128;  // columns in 64 bytes of packed weights
constexpr int64_t kChunkColumns = 32;   // act_bits 16: columns in 16 bytes of packed weights
constexpr int kMaxTileRows = 8;         // activation rows that share one pass over a weight row

inline __m512i even_byte_indices() {
  alignas(64) uint8_t idx[64];
  for (int i = 0; i < 64; ++i) idx[i] = static_cast<uint8_t>(2 * i);
  return _mm512_load_si512(idx);
}

// Columns rounded up to whole 128-column blocks (whole 64-byte loads of codes).
inline int64_t block_padded(int64_t k) { return (k + kBlockColumns - 1) / kBlockColumns * kBlockColumns; }

// Columns rounded up to whole 32-column chunks: the row pitch of the act_bits 16 operand.
inline int64_t chunk_padded(int64_t k) { return (k + kChunkColumns - 1) / kChunkColumns * kChunkColumns; }

// act_bits 16: x in fp32, each 32 columns stored as the 16 even then the 16 odd ones; rows of
// chunk_padded(k) values, zero past k.
template <typename Element>
std::vector<float> deinterleave_activations(const Element* x, int64_t m, int64_t k) {
  const int64_t pitch = chunk_padded(k);
  std::vector<float> deinterleaved(m * pitch);
  parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row(pitch, 0.0f);
    const __m512i even = _mm512_set_epi32(30, 28, 26, 24, 22, 20, 18, 16, 14, 12, 10, 8, 6, 4, 2, 0);
    const __m512i odd = _mm512_add_epi32(even, _mm512_set1_epi32(1));
    for (int64_t r = row_begin; r < row_end; ++r) {
      load_row_fp32(x + r * k, k, row.data());
      for (int64_t c = 0; c < pitch; c += kChunkColumns) {
        const __m512 first = _mm512_loadu_ps(row.data() + c);
        const __m512 second = _mm512_loadu_ps(row.data() + c + 16);
        _mm512_storeu_ps(&deinterleaved[r * pitch + c], _mm512_permutex2var_ps(first, even, second));
        _mm512_storeu_ps(&deinterleaved[r * pitch + c + 16], _mm512_permutex2var_ps(first, odd, second));
      }
    }
  });
  return deinterleaved;
}

// Splits 64 packed weight bytes into the s8 codes of their low nibbles (even columns) and high nibbles
// (odd columns), sign-extending with a 16-entry byte lookup.
inline void split_weight_nibbles(__m512i packed, __m512i& even, __m512i& odd) {
  const __m512i low_nibbles = _mm512_set1_epi8(0x0F);
  const __m512i nibble_values =
      broadcast_i32x4(_mm_setr_epi8(0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1));
  even = _mm512_shuffle_epi8(nibble_values, _mm512_and_si512(packed, low_nibbles));
  odd = _mm512_shuffle_epi8(nibble_values, _mm512_and_si512(_mm512_srli_epi16(packed, 4), low_nibbles));
}

// ---- row kernels for few activation rows (decode) ------------------------------------------------
//
// With one to seven activation rows the work is a stream over the packed weights, so the row kernels
// spend as few instructions as they can on each 64-byte load of a weight row. They read the codes
// offset by 8, u = q_w + 8 = nibble XOR 8 in [0, 15], which needs no sign-extending lookup: one XOR for
// the whole load, then a mask and a shift split it into the even and the odd columns. The offset comes
// back as a term of the activations alone: for the integer widths -8 * sum(q_x - z_x) over each lane's
// 8 columns, the integer that starts the lane's vpdpbusd sum, so that P is the P of docs/numerics.md
// bit for bit (a per-group correction in fp32 instead would cancel against the larger sums of a * u);
// for bf16, -24 * sum(x) per group (below).
// - act_bits 2/4: the activations are stored as a = q_x - z_x (|a| <= 15, an s8), and one vpdpbusd
//   (u8 u times s8 a) per half gives sum(a * u) per lane of 8 columns.
// - act_bits 8: q_x needs the u8 operand, so u takes the s8 one (it is below 16): sum(q_x * u), minus
//   z_x * sum(u) from one more vpdpbusd with z_x in every byte of the lane.
// Per weight row the products s_w * s_x of every group are formed once, 16 groups per instruction;
// inside the loop a lane's P is converted and multiplied by its group's product.

// 128 columns of one activation row for the integer row kernel.
struct alignas(64) DecodeBlock {
  uint8_t even_codes[64];  // columns 0, 2, ..., 126: a = q_x - z_x (act_bits 2/4, as s8) or q_x (8)
  uint8_t odd_codes[64];   // columns 1, 3, ..., 127
  int32_t offsets[16];     // -8 * sum of (q_x - z_x) over the lane's columns (0 past k)
};

// act_bits 8's form: z_x of each lane's group in each of its bytes (0 past k), for G below 128. Apart from
// the blocks, and for G = 128 one word per group instead, so that a row's blocks take 3 cache lines per
// 128 columns rather than 4: at K = 11008 and above a row's blocks no longer fit the L1 beside the weights
// streaming through it.
struct alignas(64) ZeroLanes {
  uint32_t bytes[16];
};

// An activation row as the integer row kernel reads it.
struct DecodeRow {
  const DecodeBlock* blocks;
  const float* scales;          // s_x per group (NaN for a non-finite group)
  const ZeroLanes* zero_lanes;  // per block, G < 128 (act_bits 8's form)
  const uint32_t* zero_words;   // per group, z_x in each byte (act_bits 8's form)
};

struct DecodeActivations {
  AlignedVector<DecodeBlock> blocks;    // [m][ceil(k / 128)]
  std::vector<float> scales;            // [m][groups]
  AlignedVector<ZeroLanes> zero_lanes;  // [m][ceil(k / 128)], act_bits 8's form with G < 128
  std::vector<uint32_t> zero_words;     // [m][groups], act_bits 8's form
  int64_t blocks_per_row = 0, groups = 0;
  DecodeRow row(int64_t r) const {
    return {blocks.data() + r * blocks_per_row, scales.data() + r * groups,
            zero_lanes.empty() ? nullptr : zero_lanes.data() + r * blocks_per_row,
            zero_words.empty() ? nullptr : zero_words.data() + r * groups};
  }
};

// `centred`: the codes stored as a = q_x - z_x, for decode_int_kernel<..., kWideCodes = false>; possible
// for act_bits 2 and 4 only.
template <typename Element>
DecodeActivations decode_activations(const Element* x, int64_t m, int64_t k, int group_size, int act_bits,
                                     bool centred) {
  DecodeActivations out;
  out.blocks_per_row = (k + kBlockColumns - 1) / kBlockColumns;
  out.groups = group_count(k, group_size);
  out.blocks.resize(m * out.blocks_per_row);
  out.scales.resize(m * out.groups);
  if (!centred) {
    out.zero_words.resize(m * out.groups);
    if (group_size < kBlockColumns) out.zero_lanes.resize(m * out.blocks_per_row);
  }
  const int group_shift = __builtin_ctz(group_size);  // group sizes are powers of two, at least 8 (a lane)
  std::vector<float> row(k);
  std::vector<uint8_t> codes(out.blocks_per_row * kBlockColumns, 0);  // zero past k
  std::vector<ActivationGroupParams> params(out.groups);
  const __m512i even = even_byte_indices();
  const __m512i odd = _mm512_add_epi8(even, _mm512_set1_epi8(1));
  for (int64_t r = 0; r < m; ++r) {
    quantize_activation_row(x + r * k, k, group_size, act_bits, row.data(), codes.data(), params.data());
    for (int64_t g = 0; g < out.groups; ++g) {
      out.scales[r * out.groups + g] = params[g].scale;
      if (!centred) out.zero_words[r * out.groups + g] = static_cast<uint32_t>(params[g].zero) * 0x01010101u;
    }
    for (int64_t t = 0; t < out.blocks_per_row; ++t) {
      DecodeBlock& block = out.blocks[r * out.blocks_per_row + t];
      // Per lane of 8 columns: its group's z_x, and how many of its columns lie before k.
      alignas(64) uint8_t centring[kBlockColumns];  // z_x of each column before k when centred, else 0
      int lane_zero[16], lane_columns[16];
      for (int lane = 0; lane < 16; ++lane) {
        const int64_t first = t * kBlockColumns + 8 * lane;
        lane_columns[lane] = static_cast<int>(std::clamp<int64_t>(k - first, 0, 8));
        lane_zero[lane] = lane_columns[lane] > 0 ? params[first >> group_shift].zero : 0;
        const uint64_t columns_mask =
            lane_columns[lane] == 8 ? ~uint64_t{0} : (uint64_t{1} << (8 * lane_columns[lane])) - 1;
        const uint64_t lane_bytes =
            centred ? (static_cast<uint64_t>(lane_zero[lane]) * 0x0101010101010101u) & columns_mask : 0;
        std::memcpy(centring + 8 * lane, &lane_bytes, 8);
        if (!out.zero_lanes.empty()) {
          out.zero_lanes[r * out.blocks_per_row + t].bytes[lane] = static_cast<uint32_t>(lane_zero[lane]) * 0x01010101u;
        }
      }
      const __m512i first = _mm512_loadu_si512(codes.data() + t * kBlockColumns);
      const __m512i second = _mm512_loadu_si512(codes.data() + t * kBlockColumns + 64);
      // Centred values a = q_x - z_x wrap into the s8 they are read as (|a| <= 15).
      const __m512i values_first = _mm512_sub_epi8(first, _mm512_load_si512(centring));
      const __m512i values_second = _mm512_sub_epi8(second, _mm512_load_si512(centring + 64));
      _mm512_store_si512(block.even_codes, _mm512_permutex2var_epi8(values_first, even, values_second));
      _mm512_store_si512(block.odd_codes, _mm512_permutex2var_epi8(values_first, odd, values_second));
      // sum(q_x) over each lane's 8 codes (zero past k) by a sum of absolute differences with 0.
      alignas(64) uint64_t code_sums[16];
      _mm512_store_si512(code_sums, _mm512_sad_epu8(first, _mm512_setzero_si512()));
      _mm512_store_si512(code_sums + 8, _mm512_sad_epu8(second, _mm512_setzero_si512()));
      for (int lane = 0; lane < 16; ++lane) {
        block.offsets[lane] = -8 * (static_cast<int32_t>(code_sums[lane]) - lane_columns[lane] * lane_zero[lane]);
      }
    }
  }
  return out;
}

// The offset codes u of one 64-byte load of a weight row: the even columns' and the odd columns' in
// bytes. The bytes past k (outside `bytes`) give u = 0, so that they add nothing to z_x * sum(u).
// The row kernels read each weight row once, front to back, and the rows one after another: a prefetch
// this far ahead of every 64-byte load keeps the next rows' bytes arriving while the current ones are
// multiplied (the hardware prefetchers alone left the cold decode at 60 % of the streaming bandwidth).
// Past the end of the weights it touches nothing: a prefetch does not fault. The distance and the cache
// level were tuned on the two CPUs measured, told apart by the path compiled for them: on the Xeon with
// AMX, 2 KiB ahead into L1; on an AMD EPYC (Zen 4, the avx512_bf16 path), where that left the integer
// kernels' cold decode at 11 GB/s on one thread (W4A16 at 18), 4 KiB ahead into L2 reached 18 to 21 GB/s
// (bench_linear.py, M = 1, cold), presumably as the faster integer kernels ran out of L1 fill buffers.
// Further ahead still paid on one thread there (C++ loop, alternating builds, cold 4096 x 4096 and
// 11008 x 4096): the rows kernels' sweep at least 16 KiB ahead rather than just over the next rows' bytes
// (8 KiB at K = 4096) took W4A8 from 23.5-24.8 to 26.4-28.5 GB/s, and W4A16's single stream 8 KiB ahead
// rather than 4 from 19-20 to 20.5-21 GB/s, about the streaming read's 24-26 GB/s in the same loop.
// The sweep takes that distance and level on the Xeon with AMX too, measured once its memory read 27 to 30
// GB/s on two threads: into L2 at least 16 KiB ahead rather than into L1 over the next rows' bytes, W4A8 on
// two threads went from 26.9 to 29.7 GB/s on 4096 x 4096, 26.1 to 28.5 on 11008 x 4096 and 26.8 to 30.4 on
// 4096 x 11008, on one thread from 14.0 to 15.5, 13.9 to 15.0 and 13.2 to 15.2 (C++ loop, cold, the two forms
// alternating in one process; into L2 over the next rows' bytes alone gave most of it); W4A16's sweep (K =
// 4096) 20.9 to 23.0 GB/s. Its single stream (K = 11008) stayed fastest 2 KiB ahead into L1: 8 KiB into L2
// took it from 24.5 to 21.9 GB/s.
constexpr int64_t kSweepAheadBytes = 16384;
constexpr _mm_hint kSweepHint = _MM_HINT_T1;
#if defined(DYQ_AVX512_HAS_AMX)
constexpr int64_t kWeightPrefetchBytes = 2048;
constexpr _mm_hint kWeightPrefetchHint = _MM_HINT_T0;
#else
constexpr int64_t kWeightPrefetchBytes = 8192;
constexpr _mm_hint kWeightPrefetchHint = _MM_HINT_T1;
#endif

// The prefetch helpers are always inlined: a prefetch has no effect GCC can see, so a helper left out of line
// is taken for a function without side effects, and its calls are deleted (the row kernels' loops of
// for_each_block lost every prefetch that way, and W4A16's cold decode half its speed).
template <bool kInOrder = false>
[[gnu::always_inline]] inline void prefetch_weights(const uint8_t* packed) {
  // An address, not a pointer into the weights: it may lie past their end.
  prefetch_line<kWeightPrefetchHint, kInOrder>(reinterpret_cast<uintptr_t>(packed) + kWeightPrefetchBytes);
}

inline void offset_weight_nibbles(const uint8_t* packed, __mmask64 bytes, bool full, __m512i& even, __m512i& odd) {
  const __m512i flip = _mm512_set1_epi8(static_cast<char>(0x88));
  const __m512i low_nibbles = _mm512_set1_epi8(0x0F);
  const __m512i u = full ? _mm512_xor_si512(_mm512_loadu_si512(packed), flip)
                         : _mm512_maskz_mov_epi8(bytes, _mm512_xor_si512(_mm512_maskz_loadu_epi8(bytes, packed), flip));
  even = _mm512_and_si512(u, low_nibbles);
  odd = _mm512_and_si512(_mm512_srli_epi16(u, 4), low_nibbles);
}

// products[r][g] = s_w[g] * s_x[r][g] for every group, zero past the last up to the pitch (a multiple of 16).
template <int kRows>
void group_products(const float* scales_row, int64_t groups, const DecodeRow* rows, float* products, int64_t pitch) {
  for (int r = 0; r < kRows; ++r) {
    for (int64_t g = 0; g < pitch; g += 16) {
      const __mmask16 lanes = groups - g >= 16 ? kAll16 : static_cast<__mmask16>((1u << (groups - g)) - 1);
      _mm512_store_ps(products + r * pitch + g, _mm512_mul_ps(_mm512_maskz_loadu_ps(lanes, scales_row + g),
                                                              _mm512_maskz_loadu_ps(lanes, rows[r].scales + g)));
    }
  }
}

// The row kernels' loop over the 128-column blocks of their weight rows: body(t, full, block_is_group) for
// every block t, `full` (std::true_type or std::false_type) false for the rows' last, partial block and
// `block_is_group` true where a block is one group (G = 128). Each combination runs in a loop of its own with
// both known at compile time: with the branches on them inside one loop, GCC stored every accumulator to the
// stack after every block (M = 1, one thread on the AMD EPYC, 4096 x 4096 in cache: the integer widths
// 0.270 -> 0.25 ms, W4A16 0.34 -> 0.30 to 0.32 ms; cold, within the benchmark's spread). Always inlined: a
// kernel that runs two loops of it (decode_int_kernel) otherwise got it out of line, with the accumulators
// in memory behind the body's references.
template <typename Body>
[[gnu::always_inline]] inline void for_each_block(int64_t k, int group_size, Body&& body) {
  const int64_t full_blocks = k / kBlockColumns;
  auto sweep = [&](auto block_is_group) {
    for (int64_t t = 0; t < full_blocks; ++t) body(t, std::true_type{}, block_is_group);
    if (k % kBlockColumns != 0) body(full_blocks, std::false_type{}, block_is_group);
  };
  if (group_size == kBlockColumns) {
    sweep(std::true_type{});
  } else {
    sweep(std::false_type{});
  }
}

// The lanes' values of a per-group array (scales, products) for block t: a broadcast when a block is one
// group (G = 128), else the block's groups spread over the lanes by `lane_group`. A full block's 128 / G
// groups come in one plain load of 8 or 16 bytes; only the rows' last, partial block masks its own. A
// masked load in the loop over the full blocks made GCC store the row kernels' accumulators to the stack
// after every block (it takes the load for one that may read them). M = 1, one thread on the AMD EPYC,
// 4096 x 4096 in cache: W4A16 at G = 64 0.336-0.346 -> 0.321 ms, at G = 32 0.355-0.362 -> 0.340-0.345
// (G = 128 0.288); the integer kernel, which had read a copy of its products padded with 16 zeros for an
// unmasked 64-byte load, A8 at G = 64 0.299 -> 0.292, at G = 32 0.330 -> 0.322.
template <typename BlockIsGroup, typename Full>
inline __m512 block_lanes(const float* per_group, int64_t t, BlockIsGroup, Full, int group_size, int64_t groups,
                          __m512i lane_group) {
  if constexpr (BlockIsGroup::value) return _mm512_set1_ps(per_group[t]);
  const int64_t per_block = kBlockColumns / group_size;
  const float* first = per_group + t * per_block;
  __m128 block_groups;
  if constexpr (Full::value) {
    block_groups = per_block == 2 ? _mm_castpd_ps(_mm_load_sd(reinterpret_cast<const double*>(first)))
                                  : _mm_loadu_ps(first);
  } else {
    const auto lanes = static_cast<__mmask8>((1u << std::min<int64_t>(per_block, groups - t * per_block)) - 1);
    block_groups = _mm_maskz_loadu_ps(lanes, first);
  }
  return permutexvar_ps(lane_group, _mm512_zextps128_ps512(block_groups));
}

inline int64_t sixteen_padded(int64_t count) { return (count + 15) / 16 * 16; }

// The prefetch that goes with reading block t of weight row c in a row kernel over kCols weight rows: one
// row is one stream, prefetched kWeightPrefetchBytes ahead; several rows, one sweep in memory order over
// the bytes after the call's own rows, at least kSweepAheadBytes ahead of the sweep's start. kInOrder:
// issued where the call stands in the kernel's code (prefetch_line).
template <int kCols, bool kInOrder = false>
[[gnu::always_inline]] inline void prefetch_block(const uint8_t* weight_rows, int64_t row_bytes, int64_t t, int c) {
  if constexpr (kCols == 1) {
    prefetch_weights<kInOrder>(weight_rows + t * (kBlockColumns / 2));
  } else {
    prefetch_next_rows<kSweepHint, kSweepAheadBytes, kInOrder>(weight_rows, kCols * row_bytes,
                                                               (t * kCols + c) * (kBlockColumns / 2));
  }
}

// Packed weights up to this size take act_bits 2 and 4 in the centred form of the row kernel, larger ones
// in act_bits 8's; both give the same integer P. The centred form spends two vpdpbusd per lane rather than
// three, and on weights in cache it was the faster (M = 1, one thread on the AMD EPYC, weights in L3: 15 %
// to 18 % faster than A8 on the Llama-7B shapes). Streamed from memory, as a model too large for the
// caches decodes, it was the slower: 23 against 25.5 to 26 GB/s on 4096 x 11008 in a C++ loop, and in a
// torch process 7 % to 30 % slower than A8 on each Llama-7B shape, where A8's form ties A8 (that virtual
// machine exposes no performance counters that could say why). Layers of a megabyte or less, such as the
// closed-loop policy's, are the ones a decode finds in cache.
constexpr int64_t kCentredDecodeMaxWeightBytes = int64_t{1} << 20;

// Weight rows that one call of a row kernel covers with kRows activation rows: a few at once share the
// activation loads, the per-call set-up and the horizontal sums, which for short weight rows cost more than
// their blocks (M = 1 of a 768 x 256 layer: 12.6 us one row at a time on the AMD EPYC, about 16 ns a row
// against 2.7 ns a 64-byte block).
constexpr int decode_columns(int rows) { return rows <= 2 ? 4 : rows <= 4 ? 2 : 1; }
// The same for the act_bits 16 row kernels where they share the activations: four weight rows' 16 vectors
// of bf16 weights and two activation rows' accumulators would not fit the 32 registers.
constexpr int fallback_decode_columns(int rows) { return rows == 1 ? 4 : rows <= 4 ? 2 : 1; }

// The 128-bit lanes of x and y that kSelector picks (vshuff32x4).
template <int kSelector>
inline __m512 shuffle_lanes(__m512 x, __m512 y) {
  return _mm512_maskz_shuffle_f32x4(kAll16, x, y, kSelector);
}

// The sums of the 16 lanes of each of a, b, c and d, in that order, added in reduce_lanes' order.
inline __m128 sum_lanes_of_four(__m512 a, __m512 b, __m512 c, __m512 d) {
  // 128-bit lanes of ab: a's lanes 0 + 2 and 1 + 3, then b's; of their sum below: a, b, c, d.
  const __m512 ab = _mm512_add_ps(shuffle_lanes<0x44>(a, b), shuffle_lanes<0xEE>(a, b));
  const __m512 cd = _mm512_add_ps(shuffle_lanes<0x44>(c, d), shuffle_lanes<0xEE>(c, d));
  __m512 sums = _mm512_add_ps(shuffle_lanes<0x88>(ab, cd), shuffle_lanes<0xDD>(ab, cd));
  sums = _mm512_add_ps(sums, _mm512_maskz_permute_ps(kAll16, sums, 0x4E));  // elements 0 + 2 and 1 + 3
  sums = _mm512_add_ps(sums, _mm512_maskz_permute_ps(kAll16, sums, 0xB1));  // then those two
  return _mm512_maskz_extractf32x4_ps(0xF, _mm512_maskz_compress_ps(0x1111, sums), 0);
}

// sums[c * kRows + r] = the lanes of acc[c][r] summed.
template <int kRows, int kCols>
void store_lane_sums(const __m512 (&acc)[kCols][kRows], float* sums) {
  if constexpr (kCols == 4) {
    for (int r = 0; r < kRows; ++r) {
      alignas(16) float four[4];
      _mm_store_ps(four, sum_lanes_of_four(acc[0][r], acc[1][r], acc[2][r], acc[3][r]));
      for (int c = 0; c < 4; ++c) sums[c * kRows + r] = four[c];
    }
  } else {
    for (int c = 0; c < kCols; ++c) {
      for (int r = 0; r < kRows; ++r) sums[c * kRows + r] = reduce_lanes<AddLanes>(acc[c][r]);
    }
  }
}

// One activation row against weight rows of at most this many groups of 128 (K <= 1024) forms each block's
// s_w * s_x in the loop, one multiply per block and weight row, rather than storing them all before the
// loop: on such short rows that set-up, and loading the products right after storing them, cost more than
// the blocks' own work. M = 1, in cache, on the AMD EPYC (a C++ loop over dyq::cpu::gemm, one process, the
// two forms alternating; outputs bit for bit the same; two runs), one thread: 768 x 256 1.47x to 1.75x
// faster at A8 and 1.57x to 1.62x at A4, 256 x 768 1.06x to 1.09x and 1.14x to 1.21x, 4096 x 1024 1.07x to
// 1.09x and 1.07x to 1.11x; two threads 1.17x to 1.22x, 1.03x to 1.17x and 1.07x to 1.10x. From K = 1536
// the two forms tie, and an earlier form of the loop multiply lost 7 % to 10 % at K = 2048 and 4096; at two
// activation rows and more, whose rows share each product, they tie on 768 x 256.
constexpr int64_t kInlineProductMaxGroups = 8;

// sums[c * kRows + r] = y[r] (without bias) of weight row c, for kCols consecutive weight rows (row c at
// weight_rows + c * k / 2, its scales at scales_rows + c * groups) and kRows integer activation rows.
template <int kRows, int kCols, bool kWideCodes>
void decode_int_kernel(const uint8_t* weight_rows, const float* scales_rows, int64_t k, int group_size,
                       const DecodeRow* rows, float* sums) {
  const int64_t groups = group_count(k, group_size);
  const int64_t pitch = sixteen_padded(groups);
  const int64_t row_bytes = k / 2;
  const bool inline_products = kRows == 1 && group_size == kBlockColumns && groups <= kInlineProductMaxGroups;
  float* products = nullptr;  // [c][r][group]
  if (!inline_products) {
    products = scratch_floats(kCols * kRows * pitch);
    for (int c = 0; c < kCols; ++c) {
      group_products<kRows>(scales_rows + c * groups, groups, rows, products + c * kRows * pitch, pitch);
    }
  }
  // Lane i covers columns 8i..8i+7 of the block: group i * 8 / group_size of it.
  const __m512i lane_group = srli_epi32(
      slli_epi32(_mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15), 3),
      __builtin_ctz(group_size));
  const __mmask64 tail_bytes = (__mmask64{1} << ((k % kBlockColumns) / 2)) - 1;
  __m512 acc[kCols][kRows];
  for (auto& column : acc) {
    for (__m512& value : column) value = _mm512_setzero_ps();
  }
  auto block = [&](int64_t t, auto full, auto block_is_group, auto products_inline) __attribute__((always_inline)) {
    __m512i even[kCols], odd[kCols];
    [[maybe_unused]] __m512i both[kCols];
    for (int c = 0; c < kCols; ++c) {
      const uint8_t* packed = weight_rows + c * row_bytes + t * (kBlockColumns / 2);
      prefetch_block<kCols>(weight_rows, row_bytes, t, c);
      offset_weight_nibbles(packed, tail_bytes, full, even[c], odd[c]);
      if constexpr (kWideCodes) both[c] = _mm512_add_epi8(even[c], odd[c]);  // u sums: below 31
    }
    for (int r = 0; r < kRows; ++r) {
      const DecodeBlock& block = rows[r].blocks[t];
      const __m512i a_even = _mm512_load_si512(block.even_codes), a_odd = _mm512_load_si512(block.odd_codes);
      const __m512i offsets = _mm512_load_si512(block.offsets);
      for (int c = 0; c < kCols; ++c) {
        __m512i dot;  // P of each lane
        if constexpr (kWideCodes) {
          dot = _mm512_dpbusd_epi32(_mm512_dpbusd_epi32(offsets, a_even, even[c]), a_odd, odd[c]);
          // z_x in every byte of every lane: the lanes past k (G = 128) multiply u = 0.
          const __m512i zero_bytes = decltype(block_is_group)::value
                                         ? _mm512_set1_epi32(static_cast<int>(rows[r].zero_words[t]))
                                         : _mm512_load_si512(rows[r].zero_lanes[t].bytes);
          dot = _mm512_sub_epi32(dot, _mm512_dpbusd_epi32(_mm512_setzero_si512(), zero_bytes, both[c]));
        } else {
          dot = _mm512_dpbusd_epi32(_mm512_dpbusd_epi32(offsets, even[c], a_even), odd[c], a_odd);
        }
        __m512 product;  // s_w * s_x of each lane's group
        if constexpr (decltype(products_inline)::value && decltype(block_is_group)::value) {
          product = _mm512_mul_ps(_mm512_set1_ps(scales_rows[c * groups + t]), _mm512_set1_ps(rows[r].scales[t]));
        } else {
          product = block_lanes(products + (c * kRows + r) * pitch, t, block_is_group, full, group_size, groups,
                                lane_group);
        }
        acc[c][r] = _mm512_fmadd_ps(cvtepi32_ps(dot), product, acc[c][r]);
      }
    }
  };
  auto sweep = [&](auto products_inline) __attribute__((always_inline)) {
    for_each_block(k, group_size, [&](int64_t t, auto full, auto block_is_group) __attribute__((always_inline)) {
      block(t, full, block_is_group, products_inline);
    });
  };
  if (inline_products) {
    sweep(std::true_type{});
  } else {
    sweep(std::false_type{});
  }
  store_lane_sums<kRows, kCols>(acc, sums);
}

// sums[c * kRows + r] = y[r] (without bias) of weight row c, for kCols consecutive weight rows (row c at
// weight_row + c * k / 2, its scales at scales_row + c * groups) and kRows fp32 activation rows. The group
// size is a template argument, so that a whole group's chunks run a loop of known length (the AMD EPYC
// forced to this path, 4096 x 4096 in cache: G = 32 0.735 -> 0.690 ms at M = 1 and 1.63-1.69 -> 1.37 at
// M = 3, G = 64 at M = 3 1.23 -> 1.18, G = 128 within 1 %; unrolled by a pragma, G = 128 was 2 % slower).
template <int kRows, int kCols, int kGroupSize>
void fp32_row_kernel(const uint8_t* weight_row, const float* scales_row, int64_t k, const float* const* rows,
                     float* sums) {
  const __m512 code_values = _mm512_setr_ps(0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1);
  const int64_t groups = group_count(k, kGroupSize), row_bytes = k / 2;
  __m512 acc[kCols * kRows];  // [c][r]
  for (int i = 0; i < kCols * kRows; ++i) acc[i] = _mm512_setzero_ps();
  __m512 group_acc[kCols * kRows];
  // Chunk by chunk, the row's last, partial one (full: false) apart, so that each loop has one path: with
  // the branch on it inside, GCC kept the accumulators on the stack, a load and a store around every
  // multiply-add.
  auto accumulate_chunk = [&](int64_t col, auto full) __attribute__((always_inline)) {
    __m512 even[kCols], odd[kCols];
    for (int c = 0; c < kCols; ++c) {
      const uint8_t* packed_row = weight_row + c * row_bytes;
      if constexpr (kCols > 1) {  // one sweep over the next rows, as in the other row kernels
        if (col % kBlockColumns == 0) prefetch_block<kCols>(weight_row, row_bytes, col / kBlockColumns, c);
      }
      __m128i packed;
      if constexpr (decltype(full)::value) {
        packed = _mm_loadu_si128(reinterpret_cast<const __m128i*>(packed_row + col / 2));
      } else {  // the bytes past k read as code 0
        alignas(16) uint8_t tail[16] = {};
        std::memcpy(tail, packed_row + col / 2, (k - col) / 2);
        packed = _mm_load_si128(reinterpret_cast<const __m128i*>(tail));
      }
      const __m512i bytes = cvtepu8_epi32(packed);
      // vpermps reads only the low 4 bits of each index: the low nibble, then the high one shifted down.
      even[c] = permutexvar_ps(bytes, code_values);
      odd[c] = permutexvar_ps(srli_epi32(bytes, 4), code_values);
    }
#pragma GCC unroll 8
    for (int r = 0; r < kRows; ++r) {
      const __m512 x_even = _mm512_loadu_ps(rows[r] + col), x_odd = _mm512_loadu_ps(rows[r] + col + 16);
#pragma GCC unroll 4
      for (int c = 0; c < kCols; ++c) {
        group_acc[c * kRows + r] = _mm512_fmadd_ps(even[c], x_even, group_acc[c * kRows + r]);
        group_acc[c * kRows + r] = _mm512_fmadd_ps(odd[c], x_odd, group_acc[c * kRows + r]);
      }
    }
  };
  // Group g: its chunks, then its scale on its sums.
  auto accumulate_group = [&](int64_t g, auto whole) __attribute__((always_inline)) {
    for (int i = 0; i < kCols * kRows; ++i) group_acc[i] = _mm512_setzero_ps();
    int64_t col = g * kGroupSize;
    if constexpr (decltype(whole)::value) {
      for (int step = 0; step < kGroupSize / kChunkColumns; ++step, col += kChunkColumns) {
        accumulate_chunk(col, std::true_type{});
      }
    } else {
      for (; col + kChunkColumns <= k; col += kChunkColumns) accumulate_chunk(col, std::true_type{});
      if (col < k) accumulate_chunk(col, std::false_type{});
    }
    for (int c = 0; c < kCols; ++c) {
      const __m512 scale = _mm512_set1_ps(scales_row[c * groups + g]);
      for (int r = 0; r < kRows; ++r) {
        acc[c * kRows + r] = _mm512_fmadd_ps(group_acc[c * kRows + r], scale, acc[c * kRows + r]);
      }
    }
  };
  const int64_t whole_groups = k / kGroupSize;
  for (int64_t g = 0; g < whole_groups; ++g) accumulate_group(g, std::true_type{});
  if (whole_groups < groups) accumulate_group(whole_groups, std::false_type{});
  for (int i = 0; i < kCols * kRows; ++i) sums[i] = reduce_lanes<AddLanes>(acc[i]);
}

#include "gemm/gemm_cpu_row_tiles.inc"

#if defined(DYQ_AVX512_HAS_BF16)
// The bf16 bit patterns of the 16 weight codes, indexed by nibble (exact: |q_w| <= 8).
inline __m512i bf16_code_table() {
  alignas(64) uint16_t table[32] = {};
  for (uint32_t nibble = 0; nibble < 16; ++nibble) {
    const float code = static_cast<float>(sign_extend_nibble(nibble));
    uint32_t bits;
    std::memcpy(&bits, &code, sizeof(bits));
    table[nibble] = static_cast<uint16_t>(bits >> 16);
  }
  return _mm512_load_si512(table);
}

// 16 dwords, each holding one packed weight byte in its low byte (columns 2c, 2c + 1), to bf16 pairs:
// the low nibble to the low word, the high nibble to the high word, then both through the code table.
inline __m512i bf16_code_pairs(__m512i bytes, __m512i table) {
  // (bytes | bytes << 12) & 0x000F000F: the low nibble in bits 0..3, the high one in bits 16..19.
  const __m512i nibbles = _mm512_ternarylogic_epi32(bytes, slli_epi32(bytes, 12), _mm512_set1_epi32(0x000F000F), 0xA8);
  return _mm512_permutexvar_epi16(nibbles, table);
}

inline __m512 dot_bf16_pairs(__m512 acc, __m512i a, __m512i b) {
  return _mm512_dpbf16_ps(acc, reinterpret_cast<__m512bh&>(a), reinterpret_cast<__m512bh&>(b));
}

// act_bits 16, row kernels: the offset codes u = q_w + 8 become bf16 weights w = 128 + u = 136 + q_w
// (exact): the word holding u in its low 4 bits under the bits 0x4300 is the bf16 number
// 2^7 * (1 + u / 128). A 16-bit word of packed bytes holds 4 columns, nibble p the column 4w + p of word w,
// so each nibble position p becomes one vector of 32 weights: shifted down by 4p (none for p = 0), masked
// to its nibble and flipped to u in one ternary logic ((shifted & 0xF) ^ 0x4308), the top one with a plain
// XOR, as its shift leaves nothing above it: 7 instructions for the 128 weights of one 64-byte load (4
// vdpbf16ps), no shuffles, against 8 with byte unpacks. On the AMD EPYC, where this kernel is bound by its
// instructions (one thread, C++ loop, alternating builds), that took M = 1 from 391 to 369 us on 4096 x
// 4096 in cache (6 %), from 12.0 to 10.7 us on the policy's 768 x 256 and 4 % off cold weights. Each
// block's four products then run as one chain into the block's scale: as two chains of two, their sum cost
// one more instruction a block (0.300 against 0.287 ms on 4096 x 4096 in cache, cold 1 % to 4 % slower;
// the weight rows of a call and the rows of a tile keep several chains in flight). Several weight
// rows per call share the activation loads where a row's activations would not stay in L1 or the per-call
// costs weigh (bf16_decode_shares_activations).
// Then sum(x * q_w) = sum(x * w) - 136 * sum(x), whose second term is the activations' own, once per
// group. The bias makes the terms up to 18 times larger than x * q_w (|w| <= 143 against |q_w| <= 8);
// each of the 16 lanes adds them in about K / 128 + 4 fp32 roundings of 2^-24, so at K = 11008 the error
// stays below 18 * 90 * 2^-24 (1e-4) of sum |x q_w|, far below the 2^-8 of rounding x to bf16.
//
// The activations are stored in the same order: in block t, vector v in 0..3 holds at word w the column
// 4 w + v, so that fp32 lane i of a dot product (words 2i, 2i + 1) holds columns 8i + v and 8i + 4 + v,
// of the 32-column chunk i / 4 only.
constexpr float kBf16DecodeBias = 136.0f;  // w - q_w

struct alignas(64) Bf16DecodeBlock {
  uint16_t words[4][32];
};

struct Bf16DecodeRow {
  const Bf16DecodeBlock* blocks;
  const float* offsets;  // -136 * sum over the group of x (x rounded to bf16)
};

struct Bf16DecodeActivations {
  AlignedVector<Bf16DecodeBlock> blocks;  // [m][ceil(k / 128)]
  std::vector<float> offsets;             // [m][groups]
  int64_t blocks_per_row = 0, groups = 0;
  Bf16DecodeRow row(int64_t r) const { return {blocks.data() + r * blocks_per_row, offsets.data() + r * groups}; }
};

template <typename Element>
Bf16DecodeActivations bf16_decode_activations(const Element* x, int64_t m, int64_t k, int group_size) {
  Bf16DecodeActivations out;
  out.blocks_per_row = (k + kBlockColumns - 1) / kBlockColumns;
  out.groups = group_count(k, group_size);
  out.blocks.resize(m * out.blocks_per_row);
  out.offsets.resize(m * out.groups);
  const int64_t pitch = out.blocks_per_row * kBlockColumns;
  std::vector<float> row(pitch, 0.0f);
  std::vector<uint16_t> rounded(pitch);
  for (int64_t r = 0; r < m; ++r) {
    load_row_fp32(x + r * k, k, row.data());
    for (int64_t c = 0; c < pitch; c += 16) {
      const __m256bh halves = _mm512_cvtneps_pbh(_mm512_loadu_ps(row.data() + c));
      std::memcpy(&rounded[c], &halves, sizeof(halves));
    }
    // Whole groups, 16 columns at a time: the columns past k are zeros (a group never ends past the pitch).
    for (int64_t g = 0; g < out.groups; ++g) {
      __m512 sum = _mm512_setzero_ps();
      for (int64_t c = g * group_size; c < (g + 1) * group_size; c += 16) {
        const __m256i words = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(rounded.data() + c));
        const __m512i bits = slli_epi32(_mm512_maskz_cvtepu16_epi32(kAll16, words), 16);
        // Subnormal bf16 values count as zero in vdpbf16ps, and so in this sum.
        const __mmask16 normal = _mm512_test_epi32_mask(bits, _mm512_set1_epi32(0x7F800000));
        sum = _mm512_add_ps(sum, _mm512_maskz_mov_ps(normal, _mm512_castsi512_ps(bits)));
      }
      out.offsets[r * out.groups + g] = -kBf16DecodeBias * reduce_lanes<AddLanes>(sum);
    }
    // The order of the weights' nibbles (gemm/gemm_cpu_amx.h).
    for (int64_t t = 0; t < out.blocks_per_row; ++t) {
      nibble_order_words(rounded.data() + t * kBlockColumns, out.blocks[r * out.blocks_per_row + t].words[0]);
    }
  }
  return out;
}

// Whether the bf16 row kernel takes several weight rows per call (fallback_decode_columns), which then share
// each block's activation loads, rather than one, which reads its weights as one stream. On the AMD EPYC
// (M = 1, one thread, N = 4096, weights rotated through four times the L3, C++ loop) one row per call was
// 4 % to 10 % faster from K = 6144 to 12288 (0.93 against 1.01 ms at K = 11008) and several rows faster
// beyond, where a row's bf16 activations (2 K bytes, 27 KiB at K = 13824) no longer stay in the 32 KiB L1
// beside the weights streaming through it: one row a call took 1.69 against 1.33 ms at K = 13824, 3.2
// against 1.47 ms at K = 16384 and 6.0 against 2.5 ms at K = 28672 (a third of the read's speed). At K =
// 4096 and below they tied cold (0.36 ms), and in cache several rows were faster: the policy's 768 x 256
// at M = 1 in 8 against 10 us, 4096 x 4096 at M = 2 to 4 by 10 % to 17 %.
// On the Xeon with AMX (48 KiB of L1), with each row's prefetch in its place (bf16_decode_kernel), several
// rows a call were as fast or faster at every K (M = 1, cold, C++ loop, the forms in turns): 4096 x 8192
// 27.2 against 25.1 GB/s on two threads, 4096 x 11008 31.6 against 30.3 and on one thread 16.0 against
// 13.4; from K = 13824 to 28672 within 2 % of one row a call (4096 x 16384 on two threads 29.1 against
// 30.7); in cache 4096 x 4096 0.446 against 0.481 ms on one thread. At M = 2 to 4 on 4096 x 11008 and 4096 x
// 8192, which took one row a call before, as fast or faster (M = 2, one thread: 2.35 against 2.83-2.97 ms).
#if defined(DYQ_AVX512_HAS_AMX)
inline bool bf16_decode_shares_activations(int64_t) { return true; }
#else
inline bool bf16_decode_shares_activations(int64_t k) { return k <= 4096 || k > 12288; }
#endif

// sums[c * kRows + r] = y[r] (without bias) of weight row c, for kCols consecutive weight rows (row c at
// weight_row + c * k / 2, its scales at scales_row + c * groups) and kRows bf16 activation rows.
template <int kRows, int kCols>
void bf16_decode_kernel(const uint8_t* weight_row, const float* scales_row, int64_t k, int group_size,
                        const Bf16DecodeRow* rows, float* sums) {
  const int64_t groups = group_count(k, group_size);
  const int64_t row_bytes = k / 2;
  // fp32 lane i holds columns of the block's 32-column chunk i / 4.
  const __m512i lane_group = srli_epi32(
      slli_epi32(_mm512_setr_epi32(0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3), 5), __builtin_ctz(group_size));
  const __m512i low_nibble = _mm512_set1_epi16(0x000F);
  const __m512i exponent_and_flip = _mm512_set1_epi16(0x4308);  // 2^7, and u = nibble XOR 8
  const __mmask64 tail_bytes = (__mmask64{1} << ((k % kBlockColumns) / 2)) - 1;
  // One activation row computes faster than the memory streams, and GCC 12 gathered a block's four prefetches
  // at the top of the loop, ahead of the rows' loads: issued each right before its row's load, the cold
  // decode on the Xeon with AMX (M = 1, C++ loop, the builds alternating in turns) took 4096 x 4096 from 21.0
  // to 29.0 GB/s on two threads and 10.8 to 15.0 on one, 11008 x 4096 on one from 10.6 to 14.3, 4096 x 13824
  // on two from 21.1 to 28.7; in cache 4096 x 4096 took 0.237 against 0.229 ms, and the policy's layers tied.
  // With two activation rows, bound by their products, the order cost 4 % (0.470 against 0.452 ms): there
  // GCC keeps its own.
  constexpr bool kPrefetchInOrder = kRows == 1;
  __m512 acc[kCols * kRows];  // [c][r]
  for (int i = 0; i < kCols * kRows; ++i) acc[i] = _mm512_setzero_ps();
  for_each_block(k, group_size, [&](int64_t t, auto full, auto block_is_group) __attribute__((always_inline)) {
    __m512i weights[kCols][4];
    __m512 scale[kCols];
    for (int c = 0; c < kCols; ++c) {
      const uint8_t* packed = weight_row + c * row_bytes + t * (kBlockColumns / 2);
      prefetch_block<kCols, kPrefetchInOrder>(weight_row, row_bytes, t, c);
      // Past k the weights do not matter: the activations there are zero.
      __m512i words = full ? _mm512_loadu_si512(packed) : _mm512_maskz_loadu_epi8(tail_bytes, packed);
      // One load in a register: GCC otherwise folds it into each shift, loading the 64 bytes four times.
      // Volatile where the prefetches are, so that each row's load stays right after its prefetch.
      if constexpr (kPrefetchInOrder) {
        asm volatile("" : "+v"(words));
      } else {
        asm("" : "+v"(words));
      }
      // (shifted & 0xF) ^ 0x4308 is ternary logic 0x6A on (shifted, low_nibble, exponent_and_flip).
      weights[c][0] = _mm512_ternarylogic_epi32(words, low_nibble, exponent_and_flip, 0x6A);
      weights[c][1] = _mm512_ternarylogic_epi32(_mm512_srli_epi16(words, 4), low_nibble, exponent_and_flip, 0x6A);
      weights[c][2] = _mm512_ternarylogic_epi32(_mm512_srli_epi16(words, 8), low_nibble, exponent_and_flip, 0x6A);
      weights[c][3] = _mm512_xor_si512(_mm512_srli_epi16(words, 12), exponent_and_flip);
      scale[c] = block_lanes(scales_row + c * groups, t, block_is_group, full, group_size, groups, lane_group);
    }
    // Unrolled, so that the accumulators stay registers (rolled, GCC kept those of 5 activation rows on the
    // stack, a load and a store around every multiply-add, 5 % slower).
#pragma GCC unroll 8
    for (int r = 0; r < kRows; ++r) {
      const Bf16DecodeBlock& block = rows[r].blocks[t];
#pragma GCC unroll 4
      for (int c = 0; c < kCols; ++c) {
        __m512 dot = _mm512_setzero_ps();
        for (int v = 0; v < 4; ++v) dot = dot_bf16_pairs(dot, _mm512_load_si512(block.words[v]), weights[c][v]);
        acc[c * kRows + r] = _mm512_fmadd_ps(dot, scale[c], acc[c * kRows + r]);
      }
    }
  });
  // Plus -136 * sum(x) of each group, scaled.
  for (int c = 0; c < kCols; ++c) {
    for (int r = 0; r < kRows; ++r) {
      __m512 correction = _mm512_setzero_ps();
      for (int64_t g = 0; g < groups; g += 16) {
        const __mmask16 lanes = groups - g >= 16 ? kAll16 : static_cast<__mmask16>((1u << (groups - g)) - 1);
        correction = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(lanes, scales_row + c * groups + g),
                                     _mm512_maskz_loadu_ps(lanes, rows[r].offsets + g), correction);
      }
      sums[c * kRows + r] = reduce_lanes<AddLanes>(acc[c * kRows + r]) + reduce_lanes<AddLanes>(correction);
    }
  }
}
#endif

// ---- panel path for many activation rows -------------------------------------------------------
//
// For larger m the work is bound by arithmetic, so the packed weights are rearranged once per call into
// panels of kPanelColumns weight rows by kPanelDepth columns, in which one vector holds the codes of the
// same columns of 16 weight rows: a micro-kernel step multiplies it with one broadcast activation dword,
// and 32 output columns x kPanelTileRows activation rows of accumulators stay in registers for a whole
// group, whose scales are then applied once.
//
// Packing reads 16 weight rows x 64 bytes (128 columns) and transposes them as a 16 x 16 matrix of
// dwords, so that vector q holds dword q of each row: columns 8q..8q+7 of 16 weight rows, the low
// nibbles the even columns, the high nibbles the odd ones. Each panel kind turns that vector into its
// steps (PanelKind::kSteps per 8 columns):
// - VnniPanel (act_bits 2/4/8): the s8 codes of the low and of the high nibbles, which vpdpbusd
//   multiplies with a broadcast dword of the activations' codes of the same columns (ActivationTiles),
//   four columns per lane; z_x * sum(q_w) is subtracted per group as in the row kernel.
// - Bf16Panel (act_bits 16, AVX512-BF16): the bf16 pairs of columns (8q + 2b, 8q + 2b + 1), which
//   vdpbf16ps multiplies with the broadcast bf16 pair of x at the same columns.
// - Fp32Panel (act_bits 16 elsewhere): the fp32 code of each of the 8 columns, one FMA with a broadcast x.
// The weights past k load as 0 and the activations past k are 0, so the last group, which holds the
// remainder when G does not divide k, gets only its own columns.
constexpr int64_t kPanelColumns = 32;  // two halves of 16 lanes
constexpr int kPanelTileRows = 8;       // 16 accumulators, 2 weight vectors, the broadcasts
constexpr int64_t kPanelDepth = 256;    // a multiple of 128, hence of every group size
constexpr int64_t kQuadColumns = 8;     // columns in one dword of packed weights

// Quads (8 columns) that `columns` columns span, the last one partial where 8 does not divide them.
inline int64_t quad_count(int64_t columns) { return (columns + kQuadColumns - 1) / kQuadColumns; }

// Activation rows as the panel kernels read them, kPanelTileRows rows at a time (a tile): for quad q
// (columns 8q..8q+7) and row r of tile t, the Kind::kSteps dwords that the kernel broadcasts at the steps
// of that quad, at words[((t * quads + q) * kPanelTileRows + r) * kSteps], so that one pointer and constant
// offsets reach every broadcast of a tile (with a pointer per activation row the compiler spilled them and
// copied accumulators between registers: 189 to 202 GMAC/s of the VNNI kernel on the AMD EPYC against 210
// with this layout, of a 234 peak). Columns past k are 0. Kinds with kGroupParams also keep each group's
// z_x and s_x of the tile's rows: params[((t * groups + g) * 2 + {0: z_x, 1: s_x}) * kPanelTileRows + r].
struct ActivationTiles {
  AlignedVector<int32_t> words;
  AlignedVector<float> params;
  int64_t quads = 0, groups = 0, steps = 0;
  const int32_t* tile_words(int64_t tile, int64_t quad) const {
    return words.data() + (tile * quads + quad) * kPanelTileRows * steps;
  }
  const float* tile_params(int64_t tile, int64_t group) const {
    return params.data() + (tile * groups + group) * 2 * kPanelTileRows;
  }
};

// Kind::row_words writes the words of row r of a tile, the kSteps dwords of quad q at words + q * quad_stride
// (zero past k; a kind with kTileWords writes the whole tile's in tile_words instead), and for VnniPanel its
// groups' z_x and s_x at zeros[g * pitch] and scales[g * pitch], with
// this scratch; kinds with kGroupParams read the codes and parameters that activation_tiles has quantized
// into it for the whole tile (quantize_activation_rows: the groups of several rows overlap there).
// Kinds without quantization convert one row at a time and take no codes.
struct TileScratch {
  TileScratch(int64_t k, int group_size, bool quantized)
      : codes_pitch(block_padded(k)),
        groups(group_count(k, group_size)),
        rows(quantized ? rows_fp32_floats(kPanelTileRows, k) + 64 : sixteen_padded(k) + 64, 0.0f),
        codes(quantized ? kPanelTileRows * codes_pitch : 0, 0),
        params(quantized ? kPanelTileRows * groups : 0) {}
  int64_t codes_pitch, groups;
  std::vector<float> rows;                    // x in fp32: the tile's rows, or one row zero past k
  AlignedVector<uint8_t> codes;               // q_x of row r at r * codes_pitch, zero past k
  std::vector<ActivationGroupParams> params;  // (s_x, z_x) of row r's groups at r * groups
};

struct VnniPanel {
  static constexpr int64_t kDepth = kPanelDepth;  // columns per packed slice
  static constexpr int kSteps = 2;
  static constexpr bool kWeightSums = true;
  static constexpr bool kScaledSteps = false;  // steps of the codes (scales in the epilogue)
  static constexpr bool kGroupParams = true;
  static constexpr bool kTileWords = true;  // tile_words, then row_words for the parameters
  using Accumulator = __m512i;
  static const char* name() { return "vnni"; }
  static void steps(__m512i quad, __m512i* out) { split_weight_nibbles(quad, out[0], out[1]); }
  // Step 0 of a quad: the codes of its even columns, step 1 of its odd ones, in the order of the weight
  // nibbles (split_weight_nibbles). The codes of the whole tile at once (tile_words), then each row's
  // groups' parameters (row_words).
  // The words of one tile from the codes of its `rows` rows in the scratch (0 for the rows past them): per 8
  // quads (64 columns), each row's 64 codes, their bytes put in step order, are one row of an 8 x 8 matrix
  // of quadwords (a quad's two steps), which a transpose turns into the 8 quads' lines of the tile (one
  // 64-byte line per quad, the rows' quadwords in row order). One store per quad and tile replaced 8-byte
  // copies per quad and row, with the same words: 256 rows at W4A8 on the AMD EPYC, one thread, in cache
  // (C++ loop, builds alternating), the policy's 256 x 256 layer 101 to 102 against 104 us, its 768 x 256
  // and 256 x 768 1 % to 2 % faster; two threads on 256 x 256 and 64 rows of 4096 x 4096 within 1 %.
  static void tile_words(const TileScratch& scratch, int rows, int64_t quads, int32_t* words) {
    const __m512i even_then_odd = broadcast_i32x4(_mm_setr_epi8(0, 2, 4, 6, 1, 3, 5, 7, 8, 10, 12, 14, 9, 11, 13, 15));
    for (int64_t q = 0; q < quads; q += 8) {
      __m512i v[kPanelTileRows];  // row r: quadword j is quad q + j
      for (int r = 0; r < kPanelTileRows; ++r) {
        v[r] = r < rows ? _mm512_shuffle_epi8(_mm512_load_si512(scratch.codes.data() + r * scratch.codes_pitch + 8 * q),
                                              even_then_odd)
                        : _mm512_setzero_si512();
      }
      // t[2i + h], 128-bit lane L: quad 2L + h of rows 2i and 2i + 1.
      __m512i t[kPanelTileRows];
      for (int i = 0; i < 4; ++i) {
        t[2 * i] = unpacklo_epi64(v[2 * i], v[2 * i + 1]);
        t[2 * i + 1] = unpackhi_epi64(v[2 * i], v[2 * i + 1]);
      }
      // u[4i + 2h + e]: lanes 0 and 2 quad 2e + h, lanes 1 and 3 quad 4 + 2e + h, each lane two rows: rows
      // 4i, 4i + 1 in lanes 0 and 1, rows 4i + 2, 4i + 3 in lanes 2 and 3.
      __m512i u[kPanelTileRows];
      for (int i = 0; i < 2; ++i) {
        for (int h = 0; h < 2; ++h) {
          u[4 * i + 2 * h] = shuffle_i64x2<0x88>(t[4 * i + h], t[4 * i + 2 + h]);      // lanes 0, 2 of each
          u[4 * i + 2 * h + 1] = shuffle_i64x2<0xDD>(t[4 * i + h], t[4 * i + 2 + h]);  // lanes 1, 3
        }
      }
      // Rows 0-3 of a quad in u[2h + e], rows 4-7 in u[4 + 2h + e]: lanes 0 and 2 of both make quad
      // 2e + h's line, lanes 1 and 3 quad 4 + 2e + h's.
      for (int h = 0; h < 2; ++h) {
        for (int e = 0; e < 2; ++e) {
          const __m512i low = u[2 * h + e], high = u[4 + 2 * h + e];
          const int64_t first = q + 2 * e + h, second = q + 4 + 2 * e + h;
          if (first < quads) {
            _mm512_store_si512(words + first * kPanelTileRows * kSteps, shuffle_i64x2<0x88>(low, high));
          }
          if (second < quads) {
            _mm512_store_si512(words + second * kPanelTileRows * kSteps, shuffle_i64x2<0xDD>(low, high));
          }
        }
      }
    }
  }
  template <typename Element>
  static void row_words(const Element*, int64_t, int, int, TileScratch& scratch, int r, int32_t*, int64_t,
                        float* zeros, float* scales, int64_t pitch) {
    const ActivationGroupParams* params = scratch.params.data() + r * scratch.groups;
    for (int64_t g = 0; g < scratch.groups; ++g) {
      zeros[g * pitch] = static_cast<float>(params[g].zero);
      scales[g * pitch] = params[g].scale;
    }
  }
  static Accumulator zero() { return _mm512_setzero_si512(); }
  static Accumulator madd(Accumulator acc, __m512i activations, __m512i weights) {
    return _mm512_dpbusd_epi32(acc, activations, weights);
  }
  // total += s_x s_w (P - z_x sum q_w) for activation row r of a tile; params: the tile's of the group.
  static __m512 scaled(Accumulator acc, const float* params, int r, __m512 weight_scales, __m512 weight_sums) {
    const __m512 partial = _mm512_fnmadd_ps(weight_sums, _mm512_set1_ps(params[r]), cvtepi32_ps(acc));
    return _mm512_mul_ps(partial, _mm512_mul_ps(weight_scales, _mm512_set1_ps(params[kPanelTileRows + r])));
  }
};

#if defined(DYQ_AVX512_HAS_BF16)
struct Bf16Panel {
  static constexpr int64_t kDepth = kPanelDepth;  // columns per packed slice
  static constexpr int kSteps = 4;
  static constexpr bool kWeightSums = false;
  static constexpr bool kScaledSteps = false;  // steps of the codes (scales in the epilogue)
  static constexpr bool kGroupParams = false;
  static constexpr bool kTileWords = false;  // row_words writes each row's words
  using Accumulator = __m512;
  static const char* name() { return "bf16"; }
  static void steps(__m512i quad, __m512i* out) {
    const __m512i table = bf16_code_table();
    const __m512i low_byte = _mm512_set1_epi32(0xFF);
    for (int b = 0; b < 4; ++b) out[b] = bf16_code_pairs(_mm512_and_si512(srli_epi32(quad, 8 * b), low_byte), table);
  }
  // x rounded to bf16 (to nearest even) in column order: step b of a quad is the pair of its columns
  // 2b, 2b + 1, as in the steps of the weights.
  template <typename Element>
  static void row_words(const Element* x, int64_t k, int, int, TileScratch& scratch, int, int32_t* words,
                        int64_t quad_stride, float*, float*, int64_t) {
    load_row_fp32(x, k, scratch.rows.data());
    const int64_t quads = quad_count(k);
    for (int64_t q = 0; q < quads; q += 2) {
      const __m256i rounded =
          reinterpret_cast<__m256i>(_mm512_cvtneps_pbh(_mm512_loadu_ps(scratch.rows.data() + 8 * q)));
      _mm_storeu_si128(reinterpret_cast<__m128i*>(words + q * quad_stride), _mm256_castsi256_si128(rounded));
      if (q + 1 < quads) {
        _mm_storeu_si128(reinterpret_cast<__m128i*>(words + (q + 1) * quad_stride),
                         _mm256_extracti128_si256(rounded, 1));
      }
    }
  }
  static Accumulator zero() { return _mm512_setzero_ps(); }
  static Accumulator madd(Accumulator acc, __m512i activations, __m512i weights) {
    return dot_bf16_pairs(acc, activations, weights);
  }
  static __m512 scaled(Accumulator acc, const float*, int, __m512 weight_scales, __m512) {
    return _mm512_mul_ps(acc, weight_scales);
  }
};

// Bf16Panel's layout, of the dequantized weights w = bf16(q_w s_w) (the product in fp32, rounded to nearest
// even by vcvtne2ps2bf16, which reads a product below fp32's normal range as 0): no scale is left to apply
// per group, so the accumulators run across a slice of kDepthColumns columns (docs/numerics.md, section
// 3). The vdpbf16ps panel of many rows reads it in deep slices (use_dequantized_panel); the AMX-BF16 tiles
// unpack the same values row by row (gemm/gemm_cpu_amx.h, AmxBf16Panel).
template <int64_t kDepthColumns>
struct DequantizedBf16Panel : Bf16Panel {
  static constexpr int64_t kDepth = kDepthColumns;
  static constexpr bool kScaledSteps = true;
  static const char* name() { return "bf16-dequantized"; }
  // `scales`: s_w of the 16 rows, for the quad's group. vpermps reads only an index's low 4 bits, so one
  // shift puts a nibble where it looks up its code.
  static void steps(__m512i quad, __m512 scales, __m512i* out) {
    alignas(64) static constexpr float kCodes[16] = {0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1};
    const __m512 codes = _mm512_load_ps(kCodes);
    // Dword i of the result: word i (the even column) and word 16 + i (the odd one) of vcvtne2ps2bf16's.
    const __m512i interleave = _mm512_set_epi16(31, 15, 30, 14, 29, 13, 28, 12, 27, 11, 26, 10, 25, 9, 24, 8, 23, 7,
                                                22, 6, 21, 5, 20, 4, 19, 3, 18, 2, 17, 1, 16, 0);
    for (int b = 0; b < 4; ++b) {
      const __m512 even = _mm512_mul_ps(_mm512_maskz_permutexvar_ps(kAll16, srli_epi32(quad, 8 * b), codes), scales);
      const __m512 odd = _mm512_mul_ps(_mm512_maskz_permutexvar_ps(kAll16, srli_epi32(quad, 8 * b + 4), codes), scales);
      const __m512i words = reinterpret_cast<__m512i>(_mm512_cvtne2ps_pbh(odd, even));
      out[b] = _mm512_permutexvar_epi16(interleave, words);
    }
  }
  static __m512 scaled(Accumulator acc, const float*, int, __m512, __m512) { return acc; }
};
#endif

struct Fp32Panel {
  static constexpr int64_t kDepth = kPanelDepth;  // columns per packed slice
  static constexpr int kSteps = 8;
  static constexpr bool kWeightSums = false;
  static constexpr bool kScaledSteps = false;  // steps of the codes (scales in the epilogue)
  static constexpr bool kGroupParams = false;
  static constexpr bool kTileWords = false;  // row_words writes each row's words
  using Accumulator = __m512;
  static const char* name() { return "fp32"; }
  static void steps(__m512i quad, __m512i* out) {
    // Nibble j of a dword is column 8q + j: shifted to the top, then arithmetically back down.
    for (int j = 0; j < 8; ++j) out[j] = _mm512_castps_si512(cvtepi32_ps(srai_epi32(slli_epi32(quad, 28 - 4 * j), 28)));
  }
  // x in fp32, column order: step j of a quad is its column j.
  template <typename Element>
  static void row_words(const Element* x, int64_t k, int, int, TileScratch& scratch, int, int32_t* words,
                        int64_t quad_stride, float*, float*, int64_t) {
    load_row_fp32(x, k, scratch.rows.data());
    const int64_t quads = quad_count(k);
    for (int64_t q = 0; q < quads; ++q) {
      _mm256_storeu_ps(reinterpret_cast<float*>(words + q * quad_stride), _mm256_loadu_ps(scratch.rows.data() + 8 * q));
    }
  }
  static Accumulator zero() { return _mm512_setzero_ps(); }
  static Accumulator madd(Accumulator acc, __m512i activations, __m512i weights) {
    return _mm512_fmadd_ps(_mm512_castsi512_ps(activations), _mm512_castsi512_ps(weights), acc);
  }
  static __m512 scaled(Accumulator acc, const float*, int, __m512 weight_scales, __m512) {
    return _mm512_mul_ps(acc, weight_scales);
  }
};

// The m rows of x as ActivationTiles for the panels of Kind.
template <typename Kind, typename Element>
ActivationTiles activation_tiles(const Element* x, int64_t m, int64_t k, int group_size, int act_bits) {
  ActivationTiles tiles;
  tiles.quads = quad_count(k);
  tiles.groups = group_count(k, group_size);
  tiles.steps = Kind::kSteps;
  const int64_t count = (m + kPanelTileRows - 1) / kPanelTileRows;
  tiles.words.resize(count * tiles.quads * kPanelTileRows * Kind::kSteps);
  if constexpr (Kind::kGroupParams) tiles.params.resize(count * tiles.groups * 2 * kPanelTileRows);
  parallel_for(0, count, 1, [&](int64_t first, int64_t last) {
    TileScratch scratch(k, group_size, Kind::kGroupParams);
    for (int64_t t = first; t < last; ++t) {
      const int rows = static_cast<int>(std::min<int64_t>(kPanelTileRows, m - t * kPanelTileRows));
      if constexpr (Kind::kGroupParams) {
        quantize_activation_rows(x + t * kPanelTileRows * k, rows, k, group_size, act_bits, scratch.rows.data(),
                                 scratch.codes.data(), scratch.codes_pitch, scratch.params.data());
      }
      if constexpr (Kind::kTileWords) {  // the tile's words at once; row_words then the parameters only
        Kind::tile_words(scratch, rows, tiles.quads, tiles.words.data() + t * tiles.quads * kPanelTileRows * Kind::kSteps);
      }
      for (int r = 0; r < rows; ++r) {
        float* zeros = nullptr;
        if constexpr (Kind::kGroupParams) zeros = tiles.params.data() + t * tiles.groups * 2 * kPanelTileRows + r;
        Kind::row_words(x + (t * kPanelTileRows + r) * k, k, group_size, act_bits, scratch, r,
                        tiles.words.data() + (t * tiles.quads * kPanelTileRows + r) * Kind::kSteps,
                        kPanelTileRows * Kind::kSteps, zeros, zeros != nullptr ? zeros + kPanelTileRows : nullptr,
                        2 * kPanelTileRows);
      }
    }
  });
  return tiles;
}

template <typename Kind>
struct WeightPanel {
  static constexpr int64_t kQuads = Kind::kDepth / kQuadColumns;
  static constexpr int64_t kGroups = Kind::kDepth / 32;  // at the smallest group size
  AlignedVector<int32_t> steps = AlignedVector<int32_t>(kQuads * Kind::kSteps * kPanelColumns);  // [quad][step][32]
  AlignedVector<float> scales = AlignedVector<float>(kGroups * kPanelColumns);       // [group][32]
  AlignedVector<float> weight_sums = AlignedVector<float>(kGroups * kPanelColumns);  // [group][32], VnniPanel

  // Columns [col_begin, col_begin + depth) of weight rows [row_begin, row_begin + 32); rows past n and
  // columns past k read as 0.
  void pack(const uint8_t* qweight, const float* all_scales, int64_t n, int64_t k, int group_size, int64_t row_begin,
            int64_t col_begin, int64_t depth) {
    const int64_t groups = group_count(k, group_size);
    const int64_t quads = quad_count(depth);
    const int64_t quads_per_group = group_size / kQuadColumns;
    const int64_t first_group = col_begin / group_size;
    const int64_t panel_groups = group_count(depth, group_size);
    for (int64_t j = 0; j < kPanelColumns; ++j) {
      const int64_t row = row_begin + j;
      for (int64_t g = 0; g < panel_groups; ++g) {
        scales[g * kPanelColumns + j] = row < n ? all_scales[row * groups + first_group + g] : 0.0f;
      }
    }
    const __m512i ones = _mm512_set1_epi8(1);
    for (int half = 0; half < 2; ++half) {
      // A running sum per step, so that consecutive vpdpbusd do not wait on each other (one chain of them set
      // the pace of the whole packing); the group being summed, counted rather than divided out per quad.
      __m512i sums[Kind::kSteps] = {};
      int64_t sum_group = 0, quads_in_sums = 0;
      for (int64_t block = 0; block * kBlockColumns < depth; ++block) {
        const int64_t column = col_begin + block * kBlockColumns;
        const int64_t bytes = std::min<int64_t>(64, (k - column) / 2);
        const __mmask64 byte_mask = bytes >= 64 ? ~__mmask64{0} : (__mmask64{1} << bytes) - 1;
        __m512i rows[16];
        const int64_t first_row = row_begin + 16 * half;
        const uint8_t* block_bytes = qweight + first_row * (k / 2) + column / 2;
        if (bytes >= 64 && first_row + 16 <= n) {
          // Sixteen whole rows: plain loads, no branch per row.
          for (int i = 0; i < 16; ++i) rows[i] = _mm512_loadu_si512(block_bytes + i * (k / 2));
        } else {
          for (int i = 0; i < 16; ++i) {
            rows[i] = first_row + i < n ? _mm512_maskz_loadu_epi8(byte_mask, block_bytes + i * (k / 2))
                                        : _mm512_setzero_si512();
          }
        }
        // The same rows' bytes 256 columns on (the next slice's at the usual depth): 32 rows 2 KiB or more
        // apart, each read 128 bytes at a time, are streams the hardware prefetchers do not follow.
        if (column + kPanelDepth < k) {
          for (int i = 0; i < 16 && first_row + i < n; ++i) {
            _mm_prefetch(reinterpret_cast<const char*>(block_bytes + i * (k / 2) + kPanelDepth / 2), _MM_HINT_T0);
          }
        }
        transpose_16x16_dwords(rows);
        for (int64_t q = 0; q < 16 && block * 16 + q < quads; ++q) {
          const int64_t quad = block * 16 + q;
          __m512i quad_steps[Kind::kSteps];
          if constexpr (Kind::kScaledSteps) {
            Kind::steps(rows[q], _mm512_load_ps(&scales[quad / quads_per_group * kPanelColumns + 16 * half]), quad_steps);
          } else {
            Kind::steps(rows[q], quad_steps);
          }
          for (int s = 0; s < Kind::kSteps; ++s) {
            _mm512_store_si512(&steps[(quad * Kind::kSteps + s) * kPanelColumns + 16 * half], quad_steps[s]);
            if constexpr (Kind::kWeightSums) sums[s] = _mm512_dpbusd_epi32(sums[s], ones, quad_steps[s]);
          }
          if constexpr (Kind::kWeightSums) {
            if (++quads_in_sums == quads_per_group || quad + 1 == quads) {
              __m512i group_sum = sums[0];
              for (int s = 1; s < Kind::kSteps; ++s) group_sum = _mm512_add_epi32(group_sum, sums[s]);
              _mm512_store_ps(&weight_sums[sum_group * kPanelColumns + 16 * half], cvtepi32_ps(group_sum));
              for (__m512i& sum : sums) sum = _mm512_setzero_si512();
              ++sum_group, quads_in_sums = 0;
            }
          }
        }
      }
    }
  }
};

// The contribution of the panel's `depth` columns for the first kRows rows of a tile (PanelSums says where
// it goes); words and params: the tile's at the panel's first quad and first group. Returns the output
// lanes that came out inf or NaN (none where nothing was stored in the output).
template <typename Kind, int kRows, typename Element>
unsigned panel_kernel(const WeightPanel<Kind>& panel, const int32_t* words, const float* params, int64_t depth,
                       int group_size, const PanelSums<Element, kPanelColumns>& sums) {
  using Accumulator = typename Kind::Accumulator;
  constexpr int kSteps = Kind::kSteps;
  const int64_t quads = quad_count(depth);
  // Steps that carry their scales leave none to apply per group: one sum spans the depth.
  const int64_t quads_per_group = Kind::kScaledSteps ? quads : group_size / kQuadColumns;
  unsigned nonfinite = 0;
  for (int64_t first = 0, group = 0; first < quads; first += quads_per_group, ++group) {
    Accumulator acc[kRows][2];
    for (int r = 0; r < kRows; ++r) acc[r][0] = acc[r][1] = Kind::zero();
    const int64_t last = std::min(first + quads_per_group, quads);
    const int32_t* steps = &panel.steps[first * kSteps * kPanelColumns];
    const int32_t* quad_words = words + first * kPanelTileRows * kSteps;
    for (int64_t quad = first; quad < last; ++quad) {
      for (int s = 0; s < kSteps; ++s) {
        const __m512i low = _mm512_load_si512(steps + s * kPanelColumns);
        const __m512i high = _mm512_load_si512(steps + s * kPanelColumns + 16);
        for (int r = 0; r < kRows; ++r) {
          const __m512i activations = _mm512_set1_epi32(quad_words[r * kSteps + s]);
          acc[r][0] = Kind::madd(acc[r][0], activations, low);
          acc[r][1] = Kind::madd(acc[r][1], activations, high);
        }
      }
      steps += kSteps * kPanelColumns;
      quad_words += kPanelTileRows * kSteps;
    }
    // The totals stay in memory: keeping them in registers too would make the compiler spill the inner loop.
    // Unrolled, so that the accumulators stay registers (rolled, the compiler kept them on the stack and
    // stored all 16 after every quad: W4A16 on 4096 x 4096 at 256 rows took 49 ms against 41).
    const float* group_params = params + group * 2 * kPanelTileRows;
    const bool add_totals = !(sums.first_slice && first == 0), to_output = sums.out != nullptr && last == quads;
    sums.for_group(add_totals, to_output, [&](auto add, auto store_output) __attribute__((always_inline)) {
#pragma GCC unroll 2
      for (int h = 0; h < 2; ++h) {
        const __m512 weight_scales = _mm512_load_ps(&panel.scales[group * kPanelColumns + 16 * h]);
        const __m512 weight_sums = _mm512_load_ps(&panel.weight_sums[group * kPanelColumns + 16 * h]);
#pragma GCC unroll 8
        for (int r = 0; r < kRows; ++r) {
          nonfinite |= sums.finish(r, 16 * h, Kind::scaled(acc[r][h], group_params, r, weight_scales, weight_sums),
                                   add, store_output);
        }
      }
    });
  }
  return nonfinite;
}

// Threads split the panels; each packs a panel's depth slice once and runs it against every tile of
// activation rows. Returns whether every output is finite.
template <typename Kind, typename Element>
bool run_panels(const ActivationTiles& tiles, const uint8_t* qweight, const float* scales, const Element* bias,
                int64_t m, int64_t n, int64_t k, int group_size, Element* out) {
  const int64_t panels = (n + kPanelColumns - 1) / kPanelColumns;
  FiniteOutputs finite;
  parallel_for(0, panels, 1, [&](int64_t panel_begin, int64_t panel_end) {
    WeightPanel<Kind> panel;
    AlignedVector<float> totals(m * kPanelColumns);  // [m][32]
    for (int64_t p = panel_begin; p < panel_end; ++p) {
      const int64_t weight_row = p * kPanelColumns;
      const int64_t columns = std::min(kPanelColumns, n - weight_row);
      unsigned nonfinite = 0;
      for (int64_t col = 0; col < k; col += Kind::kDepth) {
        const int64_t depth = std::min(Kind::kDepth, k - col);
        const bool to_output = columns == kPanelColumns && col + depth == k;
        panel.pack(qweight, scales, n, k, group_size, weight_row, col, depth);
        for (int64_t row = 0; row < m; row += kPanelTileRows) {
          const int64_t tile = row / kPanelTileRows;
          const int rows = static_cast<int>(std::min<int64_t>(kPanelTileRows, m - row));
          const PanelSums<Element, kPanelColumns> sums{totals.data() + row * kPanelColumns, col == 0,
                                                       to_output ? out + row * n + weight_row : nullptr, n,
                                                       bias != nullptr ? bias + weight_row : nullptr};
          dispatch_tile_rows<kPanelTileRows>(rows, [&](auto tile_rows) {
            nonfinite |= panel_kernel<Kind, decltype(tile_rows)::value>(
                panel, tiles.tile_words(tile, col / kQuadColumns),
                Kind::kGroupParams ? tiles.tile_params(tile, col / group_size) : nullptr, depth, group_size, sums);
          });
        }
      }
      finite.note(nonfinite == 0);
      if (columns < kPanelColumns || k == 0) {
        finite.note(store_panel_totals<kPanelColumns>(totals.data(), m, n, k, weight_row, columns, bias, out));
      }
    }
  });
  return finite.all();
}

// The panel path: the activation rows as tiles (once per thread where split_panel_rows splits them), then
// the panels. Returns whether every output is finite.
template <typename Kind, typename Element>
bool panel_gemm(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m,
                int64_t n, int64_t k, int group_size, int act_bits, Element* out) {
  return split_panel_rows(m, n, k, kPanelTileRows, kPanelRowSplitRatio, [&](int64_t row_begin, int64_t rows) {
    const ActivationTiles tiles = activation_tiles<Kind>(x + row_begin * k, rows, k, group_size, act_bits);
    return run_panels<Kind>(tiles, qweight, scales, bias, rows, n, k, group_size, out + row_begin * n);
  });
}

// Whether m activation rows take the panel path rather than the row kernels, which need no packing but pay
// per weight row and per activation row. On the AMD EPYC (alternating runs, 1 and 2 threads) the panels
// were faster from 5 rows on at the integer widths (1.35x to 2.3x at 5 rows) and from 6 at W4A16, on the
// Llama-7B and the policy's shapes alike, and, for weight rows of at most 256 columns, whose per-row
// costs outweigh their few blocks, from 2 rows on (1.1x to 2.2x). No AMX CPU was measured.
inline bool use_panels(int64_t m, int64_t k, int act_bits) {
  if (k <= 2 * kBlockColumns) return m >= 2;
  return m >= (act_bits == kFallbackBits ? 6 : 5);
}

#if defined(DYQ_AVX512_HAS_BF16)
// W4A16 on vdpbf16ps: the panels of many rows multiply by the dequantized weights (DequantizedBf16Panel),
// whose sums need no scale per group and so run across slices of kDequantizedPanelDepth columns (64 KiB of
// packed pairs, read from L2), rather than by the exact codes, whose epilogue scales and stores 16
// accumulators per group. The packing costs about twice as much, paid once per weight, the epilogues once
// per row tile. On the AMD EPYC (one thread, G = 128, in cache) 4096 x 4096 at 256 rows took 39.2-39.5
// against 41.1-41.7 ms (torch's bf16 linear 39.7), at 64 rows 10.9 against 11.4, 4096 x 11008 at 16 rows
// 9.7 against 10.0; on the policy's 256- and 768-column layers the exact panel stayed as fast or faster up
// to 128 rows, and the dequantized one won from 256 (768 x 256: 0.47 against 0.51 ms). Depths of 512 and
// 2048 columns were no faster than 1024.
constexpr int64_t kDequantizedPanelDepth = 1024;

inline bool use_dequantized_panel(int64_t m, int64_t k) {
  return m >= (k > 2 * kBlockColumns ? 32 : 256);
}
#endif

#if defined(DYQ_AVX512_HAS_AMX)
// From this many activation rows on, the AMX tiles (gemm/gemm_cpu_amx.h). The tile loop's cost hardly
// depends on the rows up to 16 (its work on every weight dominates), the row and panel kernels' grows with
// them. W4A16 goes to it from 4 rows: on the Intel Xeon with AMX (Emerald Rapids, hot weights, C++ loop, the
// two alternating in one process) its tiles took 1.8 to 2.2 ms on 4096 x 4096 from 1 to 6 rows on one thread
// (3.0 to 3.9 ms on 11008 x 4096 and 4096 x 11008), where the bf16 dot products of the AVX-512 row kernels,
// which cost twice as many cycles there as on the AMD EPYC, grow with the rows: 0.79 ms at 1 row, 2.0 at 3,
// 2.6 at 4 (1.6 to 1.8, 4.2 and 5.6 to 5.7 ms); on two threads, and on the policy's 256- and 768-column
// layers, the same way. At 3 rows the two were within 15 % either way. The integer widths, by
// bench/bench_amx_threshold.cpp (the VNNI kernels against the int8 tiles with the weights as A, in one process,
// median of nine rounds' ratios; bench/results/amx_threshold_1thread.json and _2threads.json): W4A4's centered
// tiles (W4A2 runs the same loop) were 0.85x to 1.21x the kernels' speed at 8 rows and 1.02x to 1.42x at 10,
// on 4096 x 4096, 4096 x 11008 and the policy's 768 x 256, one and two threads; W4A8's, which at 16 rows or
// fewer also multiply the zero tiles, 0.86x to 1.12x at 10 and 0.95x to 1.17x at 12, 0.89x to 1.23x from 15
// on. At 4 rows the row kernels won at every width (1.1x to 1.9x).
constexpr int64_t kAmxMinRowsCentered = 10;  // act_bits 2 and 4
constexpr int64_t kAmxMinRowsInt8 = 12;      // act_bits 8
constexpr int64_t kAmxFallbackMinRows = 4;   // act_bits 16
inline int64_t amx_min_rows(int act_bits) {
  if (act_bits == kFallbackBits) return kAmxFallbackMinRows;
  return act_bits == 8 ? kAmxMinRowsInt8 : kAmxMinRowsCentered;
}
static_assert(kBlockColumns == kAmxLoadColumns, "the bf16 row kernels' blocks are nibble_order_words' loads");
#endif

// out = x W^T (+ bias) at an integer kBits on the AVX-512 VNNI row or panel kernels; returns whether every
// output is finite.
template <int kBits, typename Element>
bool vnni_gemm(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m, int64_t n,
               int64_t k, int group_size, Element* out) {
  if (use_panels(m, k, kBits)) {
    return panel_gemm<VnniPanel>(x, qweight, scales, bias, m, n, k, group_size, kBits, out);
  }
  const bool centred = kBits != 8 && n * (k / 2) <= kCentredDecodeMaxWeightBytes;
  const DecodeActivations activations = decode_activations(x, m, k, group_size, kBits, centred);
  return run_tiles<kMaxTileRows, decode_columns>(
      qweight, scales, bias, m, n, k, group_size, out, [&](int64_t r) { return activations.row(r); },
      [&](auto tile_rows, auto tile_columns, const uint8_t* weight_rows, const float* scales_rows,
          const DecodeRow* rows, float* sums) {
        constexpr int kRows = decltype(tile_rows)::value, kCols = decltype(tile_columns)::value;
        if (centred) {
          decode_int_kernel<kRows, kCols, false>(weight_rows, scales_rows, k, group_size, rows, sums);
        } else {
          decode_int_kernel<kRows, kCols, true>(weight_rows, scales_rows, k, group_size, rows, sums);
        }
      });
}

#if defined(DYQ_AVX512_HAS_AMX)
// The same on the AMX-INT8 tiles: the centered kind at act_bits 2 and 4, the u8 codes at 8.
template <int kBits, typename Element>
bool amx_int8_gemm_at(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m,
                      int64_t n, int64_t k, int group_size, Element* out) {
  using Kind = std::conditional_t<(kBits <= 4), AmxInt8Centered, AmxInt8>;
  return split_panel_rows(m, n, k, kAmxTileRows, kAmxRowSplitRatio, [&](int64_t row_begin, int64_t rows) {
    return amx_int8_gemm<NativeTiles, Kind, AmxInt8Panel<Kind>>(x + row_begin * k, qweight, scales, bias, rows, n, k,
                                                                group_size, kBits, out + row_begin * n);
  });
}
#endif

// out = x W^T (+ bias) at kBits; returns whether every output is finite.
template <int kBits, typename Element>
bool gemm_typed(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m, int64_t n,
                int64_t k, int group_size, Element* out) {
  if constexpr (ActivationTraits<kBits>::kQuantized) {
#if defined(DYQ_AVX512_HAS_AMX)
    if (m >= amx_min_rows(kBits)) return amx_int8_gemm_at<kBits>(x, qweight, scales, bias, m, n, k, group_size, out);
#endif
    return vnni_gemm<kBits>(x, qweight, scales, bias, m, n, k, group_size, out);
  } else {
#if defined(DYQ_AVX512_HAS_AMX)
    if (m >= amx_min_rows(kBits)) {
      return split_panel_rows(m, n, k, kAmxTileRows, kAmxRowSplitRatio, [&](int64_t row_begin, int64_t rows) {
        return amx_bf16_gemm<NativeTiles, AmxBf16Panel>(x + row_begin * k, qweight, scales, bias, rows, n, k,
                                                        group_size, out + row_begin * n);
      });
    }
#endif
#if defined(DYQ_AVX512_HAS_BF16)
    if (use_panels(m, k, kBits)) {
      if (use_dequantized_panel(m, k)) {
        return panel_gemm<DequantizedBf16Panel<kDequantizedPanelDepth>>(x, qweight, scales, bias, m, n, k, group_size,
                                                                        kBits, out);
      }
      return panel_gemm<Bf16Panel>(x, qweight, scales, bias, m, n, k, group_size, kBits, out);
    }
    const Bf16DecodeActivations activations = bf16_decode_activations(x, m, k, group_size);
    const auto row_kernel = [&](auto tile_rows, auto tile_columns, const uint8_t* weight_row, const float* scales_row,
                                const Bf16DecodeRow* rows, float* sums) {
      bf16_decode_kernel<decltype(tile_rows)::value, decltype(tile_columns)::value>(weight_row, scales_row, k,
                                                                                    group_size, rows, sums);
    };
    const auto activation_row = [&](int64_t r) { return activations.row(r); };
    if (bf16_decode_shares_activations(k)) {
      return run_tiles<kMaxTileRows, fallback_decode_columns>(qweight, scales, bias, m, n, k, group_size, out,
                                                              activation_row, row_kernel);
    }
    return run_tiles<kMaxTileRows>(qweight, scales, bias, m, n, k, group_size, out, activation_row, row_kernel);
#else
    if (use_panels(m, k, kBits)) {
      return panel_gemm<Fp32Panel>(x, qweight, scales, bias, m, n, k, group_size, kBits, out);
    }
    const std::vector<float> activations = deinterleave_activations(x, m, k);
    const int64_t pitch = chunk_padded(k);
    const auto row_kernel = [&](auto tile_rows, auto tile_columns, const uint8_t* weight_row, const float* scales_row,
                                const float* const* rows, float* sums) {
      dispatch_group_size(group_size, [&](auto group) {
        fp32_row_kernel<decltype(tile_rows)::value, decltype(tile_columns)::value, decltype(group)::value>(
            weight_row, scales_row, k, rows, sums);
      });
    };
    const auto activation_row = [&](int64_t r) { return activations.data() + r * pitch; };
    // Several weight rows per call at every K: on the AMD EPYC with this path forced (DYQ_CPU_ISA=avx512;
    // M = 1, cold, 4096 rows, one thread) 0.80 against 0.89 ms at K = 4096, 2.23 against 3.20 at 11008 and
    // 3.5 against 5.1 at 16384 (fp32 activations, 4 bytes a column, leave L1 from K = 8192 on); in cache
    // 4096 x 4096 at M = 2 to 4 1.4x to 1.6x faster, and no slower anywhere.
    return run_tiles<kMaxTileRows, fallback_decode_columns>(qweight, scales, bias, m, n, k, group_size, out,
                                                            activation_row, row_kernel);
#endif
  }
}

inline const char* gemm_kernel(int64_t m, int64_t k, int, int act_bits) {
  const bool panel = use_panels(m, k, act_bits);
#if defined(DYQ_AVX512_HAS_AMX)
  if (m >= amx_min_rows(act_bits)) return act_bits != kFallbackBits ? DYQ_ISA_NAME "/tiles-amx-int8" : DYQ_ISA_NAME "/tiles-amx-bf16-dequantized";
#endif
  if (act_bits != kFallbackBits) return panel ? DYQ_ISA_NAME "/panel-vnni" : DYQ_ISA_NAME "/rows-vnni";
#if defined(DYQ_AVX512_HAS_BF16)
  if (panel && use_dequantized_panel(m, k)) return DYQ_ISA_NAME "/panel-bf16-dequantized";
  return panel ? DYQ_ISA_NAME "/panel-bf16" : DYQ_ISA_NAME "/rows-bf16";
#else
  return panel ? DYQ_ISA_NAME "/panel-fp32" : DYQ_ISA_NAME "/rows-fp32";
#endif
}

}  // namespace dyq::cpu::DYQ_ISA_NAMESPACE
DYQ_ISA_END
