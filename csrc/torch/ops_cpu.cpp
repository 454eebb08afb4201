// CPU registrations of the dyq operators: validation (checks.h), then the torch-free kernels.
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <new>

#include "activation/act_quant_cpu.h"
#include "activation/hadamard_cpu.h"
#include "activation/rms_norm_cpu.h"
#include "gemm/gemm_cpu.h"
#include "parallel/parallel.h"
#include "torch/checks.h"
#include "torch/gemm_op.h"
#include "weight/weight_pack_cpu.h"

namespace dyq {
namespace {

int torch_thread_count() { return at::get_num_threads(); }

// at::parallel_for is a header template: with torch's OpenMP backend it runs in parallel only where this
// file is compiled with OpenMP (CMakeLists.txt does so where torch ships its libgomp); otherwise it would
// be a serial loop, and dyq keeps its own pool.
#if defined(_OPENMP) || AT_PARALLEL_NATIVE
#define DYQ_RUNS_ON_TORCH_THREADS 1
void run_on_torch_threads(int64_t chunks, const ChunkTask& task) {
  at::parallel_for(0, chunks, 1, [&](int64_t begin, int64_t end) {
    for (int64_t chunk = begin; chunk < end; ++chunk) task(chunk);
  });
}
#else
#define DYQ_RUNS_ON_TORCH_THREADS 0
#endif

// dyq's kernels use as many threads as torch's intra-op pool (torch.set_num_threads), and, where this
// build can, those very threads (parallel.h says why).
[[maybe_unused]] const bool kThreadsInstalled = [] {
  set_thread_count_source(&torch_thread_count);
#if DYQ_RUNS_ON_TORCH_THREADS
  set_chunk_runner(&run_on_torch_threads);
#endif
  return true;
}();

// Runs a CPU kernel; an allocation failure inside it (in any worker thread: parallel_for rethrows it
// here) becomes a Python exception that says what ran out, instead of escaping as std::bad_alloc.
template <typename Kernel>
bool with_cpu_errors(Kernel&& kernel) {
  try {
    return kernel();
  } catch (const std::bad_alloc&) {
    TORCH_CHECK(false, "dyq: out of memory in a CPU kernel (scratch buffers of the call could not be allocated)");
  }
}

std::tuple<at::Tensor, at::Tensor> quantize_weight_cpu(const at::Tensor& weight, int64_t group_size) {
  const auto [n, k] = check_quantize_weight_args(weight, group_size);
  const at::Tensor w = weight.to(at::kFloat).contiguous();
  at::Tensor qweight = at::empty({n, k / 2}, weight.options().dtype(at::kByte));
  at::Tensor scales = at::empty({n, group_count(k, group_size)}, weight.options().dtype(at::kFloat));
  const bool finite = with_cpu_errors([&] {
    return cpu::quantize_weight(w.const_data_ptr<float>(), n, k, static_cast<int>(group_size),
                                qweight.mutable_data_ptr<uint8_t>(), scales.mutable_data_ptr<float>());
  });
  TORCH_CHECK(finite, non_finite_weight_message(weight));
  return {qweight, scales};
}

at::Tensor dequantize_weight_cpu(const at::Tensor& qweight, const at::Tensor& scales, int64_t group_size) {
  check_dequantize_weight(qweight, scales, group_size);
  const int64_t n = qweight.size(0), k = qweight.size(1) * 2;
  at::Tensor out = at::empty({n, k}, scales.options());
  with_cpu_errors([&] {
    cpu::dequantize_weight(qweight.const_data_ptr<uint8_t>(), scales.const_data_ptr<float>(), n, k,
                           static_cast<int>(group_size), out.mutable_data_ptr<float>());
    return true;
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> quantize_activations_cpu(const at::Tensor& x, int64_t group_size,
                                                                        int64_t act_bits) {
  auto [packed, scales, zeros] = activation_quantization_outputs(x, group_size, act_bits);
  const int64_t k = x.size(-1);
  const at::Tensor xc = x.contiguous();
  const int64_t m = k == 0 ? 0 : xc.numel() / k;
  if (m > 0) {
    with_cpu_errors([&] {
      cpu::quantize_activations(xc.const_data_ptr(), to_dyq_dtype(x.scalar_type()), m, k,
                                static_cast<int>(group_size), static_cast<int>(act_bits),
                                packed.mutable_data_ptr<uint8_t>(), scales.mutable_data_ptr<float>(),
                                zeros.mutable_data_ptr<uint8_t>());
      return true;
    });
  }
  return {packed, scales, zeros};
}

at::Tensor hadamard_transform_cpu(const at::Tensor& x, const at::Tensor& signs, const at::Tensor& left) {
  at::Tensor out = hadamard_transform_output(x, signs, left);
  const int64_t n = x.size(-1);
  const at::Tensor xc = x.contiguous();
  with_cpu_errors([&] {
    cpu::hadamard_transform(xc.const_data_ptr(), to_dyq_dtype(x.scalar_type()), signs.const_data_ptr<float>(),
                            left.const_data_ptr<float>(), xc.numel() / n, n, left.size(0), out.mutable_data_ptr());
    return true;
  });
  return out;
}

at::Tensor rms_norm_cpu(const at::Tensor& x, const at::Tensor& weight, double eps) {
  at::Tensor out = rms_norm_output(x, weight, eps);
  const int64_t n = x.size(-1);
  const at::Tensor xc = x.contiguous();
  const at::Tensor weight_c = weight.contiguous();
  with_cpu_errors([&] {
    cpu::rms_norm(xc.const_data_ptr(), to_dyq_dtype(x.scalar_type()), weight_c.const_data_ptr(), xc.numel() / n, n,
                  static_cast<float>(eps), out.mutable_data_ptr());
    return true;
  });
  return out;
}

struct CpuGemm {
  using Precision = int64_t;  // the CPU kernels take the width itself

  static Precision fixed(int64_t act_bits) { return act_bits; }

  static std::pair<Precision, int64_t> from_flag(const at::Tensor& flag, const at::Tensor&, int64_t min_bits) {
    TORCH_CHECK(flag.device().is_cpu(), "dyq: act_bits_flag must be a CPU (host) tensor for CPU inputs, got ",
                flag.device());
    // The one int32 read in place (check_flag_tensor: int32, one element): item() would be a dispatcher call.
    const int64_t flag_bits = *flag.const_data_ptr<int32_t>();
    TORCH_CHECK(is_valid_act_bits(flag_bits), "dyq: act_bits_flag holds ", flag_bits, "; expected ",
                registered_act_bits_text());
    const int64_t act_bits = std::max(flag_bits, min_bits);
    return {act_bits, act_bits};
  }

  static void run(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales, int64_t group_size,
                  Precision act_bits, const std::optional<at::Tensor>& bias, at::Tensor& out) {
    const int64_t n = qweight.size(0), k = qweight.size(1) * 2;
    const at::Tensor xc = x.contiguous();
    const at::Tensor bias_c = bias.has_value() ? bias->contiguous() : at::Tensor();
    const bool in_range = with_cpu_errors([&] {
      return cpu::gemm(xc.const_data_ptr(), to_dyq_dtype(x.scalar_type()), qweight.const_data_ptr<uint8_t>(),
                       scales.const_data_ptr<float>(), bias_c.defined() ? bias_c.const_data_ptr() : nullptr,
                       out.numel() / n, n, k, static_cast<int>(group_size), static_cast<int>(act_bits),
                       out.mutable_data_ptr());
    });
    TORCH_CHECK(in_range, "dyq: x W^T is out of the range of ", x.scalar_type(),
                      " (finite inputs whose product overflows the output dtype)");
  }
};

at::Tensor gemm_cpu(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales, int64_t group_size,
                    int64_t act_bits, const std::optional<at::Tensor>& bias) {
  return gemm_op<CpuGemm>(x, qweight, scales, group_size, fixed_act_bits(act_bits), bias);
}

at::Tensor gemm_with_flag_cpu(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales,
                              int64_t group_size, const at::Tensor& act_bits_flag,
                              const std::optional<at::Tensor>& bias, int64_t min_act_bits) {
  return gemm_op<CpuGemm>(x, qweight, scales, group_size, flag_act_bits(act_bits_flag, min_act_bits), bias);
}

}  // namespace
}  // namespace dyq

TORCH_LIBRARY_IMPL(dyq, CPU, m) {
  m.impl("quantize_weight", &dyq::quantize_weight_cpu);
  m.impl("dequantize_weight", &dyq::dequantize_weight_cpu);
  m.impl("quantize_activations", &dyq::quantize_activations_cpu);
  m.impl("gemm", &dyq::gemm_cpu);
  m.impl("gemm_with_flag", &dyq::gemm_with_flag_cpu);
  m.impl("hadamard_transform", &dyq::hadamard_transform_cpu);
  m.impl("rms_norm", &dyq::rms_norm_cpu);
}
