"""Input builders and tolerances shared by the tests."""
import math

import torch

import dyq
from dyq import reference

DTYPES = (torch.float32, torch.bfloat16, torch.float16)
# Relative rounding of one output element in each dtype (half an ulp), plus fp32 accumulation slack.
OUTPUT_RTOL = {torch.float32: 2e-6, torch.bfloat16: 2**-8, torch.float16: 2**-11}
# fp16 flushes tiny results to its subnormal grid (2^-24).
OUTPUT_ATOL = {torch.float32: 1e-30, torch.bfloat16: 1e-30, torch.float16: 2**-24}


def random_weight(n, k, gen, dtype=torch.float32):
    """Weights shaped like a trained layer's: roughly Gaussian with a few larger entries per row."""
    w = torch.randn(n, k, generator=gen) * 0.02
    spikes = torch.rand(n, k, generator=gen) < 0.01
    w = torch.where(spikes, w * 8, w)
    return w.to(dtype)


def random_activations(shape, gen, dtype=torch.float32):
    """Activations with outlier channels, as transformer hidden states have."""
    x = torch.randn(*shape, generator=gen)
    k = shape[-1]
    outliers = torch.randperm(k, generator=gen)[: max(1, k // 64)]
    x[..., outliers] *= 10
    return x.to(dtype)


def assert_gemm_close(out, x, qweight, scales, group_size, act_bits, bias=None):
    """out must equal the float64 reference to within the rounding of fp32 sums and of the output dtype."""
    expected = reference.gemm(x, qweight, scales, group_size, act_bits, bias)
    bound = reference.gemm_error_bound(x, qweight, scales, group_size, act_bits, bias)
    rtol = OUTPUT_RTOL[out.dtype]
    # fp32 sums: a few ulps of sum|terms|; the final rounding to out.dtype: rtol of |expected|.
    tolerance = 4e-7 * bound * 8 + rtol * expected.abs() + OUTPUT_ATOL[out.dtype]
    rows = math.prod(x.shape[:-1])  # not x.reshape(-1, k): that is ambiguous for an empty x with k = 0
    if act_bits == 16 and out.device.type == "cpu" and bf16_fallback(rows, x.shape[-1], group_size):
        # The CPU's bf16 dot products round x to bf16 (docs/numerics.md, section 3): at most 2^-8 of
        # each term; the AMX tiles round the dequantized weights too: 2^-7 + 2^-16.
        if "dequantized" in dyq.cpu_gemm_kernel(rows, x.shape[-1], group_size, 16):
            tolerance = tolerance + (2.0**-7 + 2.0**-16) * bound
        else:
            tolerance = tolerance + 2.0**-8 * bound
    diff = (out.double() - expected).abs()
    finite = torch.isfinite(expected)
    assert torch.equal(torch.isfinite(out), finite), "non-finite entries differ from the reference"
    worst = (diff[finite] / tolerance[finite]).max().item() if finite.any() else 0.0
    assert worst <= 1.0, f"max error / tolerance = {worst:.3g}"


def bf16_fallback(m, k, group_size):
    """Whether the CPU's W4A16 GEMM for an [m, k] input runs on bf16 dot products (x rounded to bf16)."""
    return "bf16" in dyq.cpu_gemm_kernel(m, k, group_size, 16)


def hf_quantizer_unavailable() -> str | None:
    """Why dyq.DyQConfig cannot run with the transformers installed (its tests then skip), or None: it needs
    transformers' custom-quantizer hooks (4.49 on), and on 4.x accelerate, which loading a quantized
    checkpoint imports."""
    import importlib.util

    from packaging.version import Version

    import transformers

    version = Version(transformers.__version__)
    if version < Version("4.49"):
        return f"dyq.DyQConfig needs transformers >= 4.49 (installed: {version})"
    if version.major == 4 and importlib.util.find_spec("accelerate") is None:
        return "transformers 4.x loads quantized checkpoints through accelerate, which is not installed"
    return None
