"""How :func:`dyq.quantize_model` chooses a layer's INT4 codes and scales (``method=``).

Every method writes the format of docs/numerics.md section 1 unchanged (symmetric codes in [-8, 7], one
fp32 scale per row and group, the last group of a row holding the remainder), so the kernels run its
output as they run round-to-nearest's; only the choice of scale, and through it of the codes, differs.

* ``"rtn"``: round-to-nearest from the group's absmax, the kernels' own ``quantize_weight``.
* ``"mse"``: per-group clipping search. For each group the scale ``s = c * absmax / 7`` is tried for every
  clipping ratio ``c`` of :data:`CLIP_RATIOS`; the codes are ``clamp(rne(W / s), -8, 7)`` and the ratio with
  the smallest squared error ``sum_k h_k (W_k - s q_k)^2`` is kept (``h = 1``: plain weight MSE).
  Clipping the few largest weights of a group buys a finer step for all the others.
* ``"awq"``: activation-aware scaling (AWQ, Lin et al. 2024), then the clipping search weighted by the
  calibration activations' mean square ``h_k = E[x_k^2]`` (the diagonal of the layer's Hessian
  ``X^T X``, so the error weighted is the output's, to first order). The scaling multiplies input
  channel k of the layers that read one activation by ``s_k = mean|x_k|^alpha`` (normalised to geometric
  mean 1) and divides the activation by s where it is produced (the RMSNorm weight before q/k/v and
  gate/up, the rows of up_proj before down_proj, the rows of v_proj before o_proj when every head has
  its own value head; see :func:`dyq.smoothing.llama_scale_groups`), which leaves the float model's
  function unchanged. ``alpha`` is searched on :data:`ALPHAS`; the objective is the layers' output error
  with round-to-nearest weights *and* activations fake-quantized at every width of ``calibration_bits``
  (the reference's Eq. 2), ``mean_b log ||X W^T - Q_b(X / s) Q_w(W diag s)^T||^2``: the log makes each width
  count by its relative error, so the one frozen weight set is chosen for all widths the dispatcher may
  pick, not for the one with the largest absolute error. ``alpha = 0`` (no scaling) is a candidate, so on
  the calibration batch the search never does worse than round-to-nearest. Layers with no foldable
  producer (o_proj under grouped-query attention, any non-Llama layer) get the weighted clipping only.
* ``"gptq"``: error-compensating rounding (GPTQ, Frantar et al. 2023). Per layer, the Hessian of the output
  error ``H = 2 X^T X / n`` of the calibration tokens' inputs to that layer, damped by :data:`GPTQ_DAMPING`
  of its mean diagonal; the columns are quantized in order, in blocks of :data:`GPTQ_BLOCK`, and each
  column's rounding error, divided by the diagonal of the upper Cholesky factor U of ``H^-1``
  (``H^-1 = U^T U``), is subtracted from the columns not yet quantized along U's row: the optimal update of
  the remaining weights for the output error ``||X W^T - X Wq^T||^2``. A group's scale is fixed when the
  column loop enters it, by the clipping search (weighted by ``diag H``) on the group's weights *as the
  earlier columns' errors have updated them*. X is the layer's input in the **float** model (one forward
  pass, every layer observed at once, activations unquantized): the Hessian does not depend on the width
  the dispatcher later picks, so the one weight set serves every width, and no layer waits for the
  quantization of the ones before it (the "sequential" variant of the paper's reference, which feeds each
  block the outputs of the already quantized blocks, would have to choose one activation width for them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import torch
from torch import nn

from . import reference
from .precision import check_bits

METHODS = ("rtn", "mse", "awq", "gptq")
CALIBRATED_METHODS = ("awq", "gptq")
# Clipping ratios tried by the "mse" search, largest first so that a tie keeps the larger (absmax) scale.
CLIP_RATIOS = tuple(round(1.0 - 0.02 * i, 2) for i in range(26))  # 1.00, 0.98, ..., 0.50
ALPHAS = tuple(i / 10 for i in range(11))                            # 0.0, 0.1, ..., 1.0
DEFAULT_CALIBRATION_BITS = (16, 8, 4, 2)
# Rows of X kept per scale group for the alpha search (the statistics use every calibration token).
SEARCH_TOKENS = 256
GPTQ_DAMPING = 0.01  # added to H's diagonal, as a share of its mean diagonal (the paper's 1 %)
GPTQ_BLOCK = 128     # columns per lazy-update block (a multiple of every group size)
MSE_BLOCK_ELEMENTS = 1 << 16  # weights per block of rows in the clipping search (256 KiB in fp32)


def check_method(method) -> str:
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    return method


def clipped_weight(weight: torch.Tensor, group_size: int, channel_weight: torch.Tensor | None = None,
                   ratios: Sequence[float] = CLIP_RATIOS) -> tuple[torch.Tensor, torch.Tensor]:
    """The "mse" search: (codes int8 [N, K], scales float32 [N, ceil(K/G)]) minimising, per group,
    ``sum_k h_k (W_k - s q_k)^2`` over ``s = c * absmax / 7``, ``c`` in ``ratios`` (``h = channel_weight``, [K],
    or 1). An all-zero group gets scale 1 and codes 0, as in round-to-nearest."""
    if weight.dim() != 2:
        raise ValueError(f"weight must be 2-D [out_features, in_features], got shape {tuple(weight.shape)}")
    if not torch.isfinite(weight).all():
        raise ValueError("weight contains NaN or Inf")
    k = weight.shape[1]
    if channel_weight is None:
        h = torch.ones(1, 1, 1, dtype=torch.float64)
    else:
        if channel_weight.shape != (k,):
            raise ValueError(f"channel_weight must have shape [in_features = {k}], got {tuple(channel_weight.shape)}")
        h = reference._grouped(channel_weight.detach().double().cpu().clamp(min=0)[None], group_size)
    # Blocks of rows whose temporaries stay in the caches: each ratio makes several passes over them, which over
    # the whole of an 11008 x 4096 layer ran at the memory's speed (16 s against 2.1 s in blocks of 16 rows on
    # the 2-core EPYC; blocks of 4 rows spent 6.5 s in per-op costs, of 64 rows 5.2 s). Rows are independent:
    # the result is the same, bit for bit.
    rows = max(1, MSE_BLOCK_ELEMENTS // max(k, 1))
    blocks = [_clipped_rows(weight[start:start + rows], group_size, h, ratios)
              for start in range(0, weight.shape[0], rows)] or [_clipped_rows(weight, group_size, h, ratios)]
    return torch.cat([codes for codes, _ in blocks]), torch.cat([scales for _, scales in blocks])


def _clipped_rows(weight: torch.Tensor, group_size: int, h: torch.Tensor, ratios: Sequence[float]
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """clipped_weight of some rows, h already grouped ([1, Gs, G] or [1, 1, 1])."""
    k = weight.shape[1]
    w = reference._grouped(weight.detach().float().cpu(), group_size)                # [N, Gs, G]
    absmax = w.abs().amax(dim=-1)
    empty = absmax / 7 == 0
    best_error = torch.full(absmax.shape, math.inf, dtype=torch.float64)
    best_scale = torch.ones_like(absmax)
    for ratio in ratios:
        scale = (ratio * absmax) / 7
        scale = torch.where(scale == 0, torch.ones_like(scale), scale)
        codes = torch.round(w / scale[..., None]).clamp(reference.WEIGHT_QMIN, reference.WEIGHT_QMAX)
        error = (((w - scale[..., None] * codes).double() ** 2) * h).sum(dim=-1)
        better = error < best_error
        best_error = torch.where(better, error, best_error)
        best_scale = torch.where(better, scale, best_scale)
    best_scale = torch.where(empty, torch.ones_like(best_scale), best_scale)
    codes = torch.round(w / best_scale[..., None]).clamp(reference.WEIGHT_QMIN, reference.WEIGHT_QMAX)
    codes = torch.where(empty[..., None], torch.zeros_like(codes), codes)
    return reference._ungrouped(codes, k).to(torch.int8), best_scale


def packed_clipped_weight(weight: torch.Tensor, group_size: int, channel_weight: torch.Tensor | None = None
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """(qweight uint8 [N, K/2], scales) of :func:`clipped_weight`, in the packed layout of docs/numerics.md."""
    codes, scales = clipped_weight(weight, group_size, channel_weight)
    return reference.pack_int4(codes), scales


def _rtn_dequantized(weight: torch.Tensor, group_size: int) -> torch.Tensor:
    codes, scales = reference.quantize_weight(weight, group_size)
    grouped = reference._grouped(codes.float(), group_size) * scales[..., None]
    return reference._ungrouped(grouped, weight.shape[1])


def _fake_quantized_activations(x: torch.Tensor, group_size: int, act_bits: int) -> torch.Tensor:
    if act_bits == 16:
        return x
    codes, scales, zeros = reference.quantize_activations(x, group_size, act_bits)
    grouped = reference._grouped(codes.float(), group_size) - zeros.float()[..., None]
    return reference._ungrouped(grouped * scales[..., None], x.shape[-1])


def awq_objective(x: torch.Tensor, weights: Sequence[torch.Tensor], scales: torch.Tensor, group_size: int,
                  calibration_bits: Sequence[int]) -> float:
    """``mean_b log sum_W ||x W^T - Q_b(x / s) Q_w(W diag s)^T||^2`` (the "awq" alpha search's objective)."""
    reference_out = [x @ w.T for w in weights]
    quantized = [_rtn_dequantized(w * scales, group_size) for w in weights]
    total = 0.0
    for bits in calibration_bits:
        xq = _fake_quantized_activations(x / scales, group_size, bits)
        error = sum(((xq @ wq.T - y) ** 2).sum().item() for wq, y in zip(quantized, reference_out))
        total += math.log(max(error, 1e-300))
    return total / len(calibration_bits)


def awq_channel_scales(mean_abs: torch.Tensor, alpha: float) -> torch.Tensor:
    """``s_k = mean|x_k|^alpha``, divided by its geometric mean so that the weights' overall range stays put."""
    scales = mean_abs.double().clamp(min=1e-5) ** alpha
    return (scales / scales.log().mean().exp()).float()


def search_awq_scales(x: torch.Tensor, mean_abs: torch.Tensor, weights: Sequence[torch.Tensor], group_size: int,
                      calibration_bits: Sequence[int], alphas: Sequence[float] = ALPHAS) -> tuple[torch.Tensor, float]:
    """(s, alpha) minimising :func:`awq_objective` over ``alphas``; ties keep the smaller alpha."""
    weights = [w.detach().float() for w in weights]
    best = (math.inf, None, None)
    for alpha in alphas:
        scales = awq_channel_scales(mean_abs, alpha)
        value = awq_objective(x, weights, scales, group_size, calibration_bits)
        if value < best[0]:
            best = (value, scales, alpha)
    return best[1], best[2]


def gptq_weight(weight: torch.Tensor, hessian: torch.Tensor, group_size: int, damping: float = GPTQ_DAMPING,
                block: int = GPTQ_BLOCK) -> tuple[torch.Tensor, torch.Tensor]:
    """The "gptq" rounding of one layer: (codes int8 [N, K], scales float32 [N, ceil(K/G)]), computed in float64.

    ``hessian`` [K, K] is ``2 X^T X / n`` of the layer's inputs (any positive multiple gives the same result:
    the damping is relative). A column that no token reaches (``H[k, k] = 0``) is set to zero and takes no
    error. ``block`` is rounded up to a multiple of the group size so that a group never straddles blocks."""
    if weight.dim() != 2:
        raise ValueError(f"weight must be 2-D [out_features, in_features], got shape {tuple(weight.shape)}")
    n, k = weight.shape
    if hessian.shape != (k, k):
        raise ValueError(f"hessian must have shape [in_features, in_features] = [{k}, {k}], got {tuple(hessian.shape)}")
    if not torch.isfinite(weight).all():
        raise ValueError("weight contains NaN or Inf")
    if not torch.isfinite(hessian).all():
        raise ValueError("hessian contains NaN or Inf")
    if not damping > 0:
        raise ValueError(f"damping must be > 0, got {damping!r}")
    w = weight.detach().double().cpu().clone()
    h = hessian.detach().double().cpu().clone()
    h = (h + h.T) / 2
    if (h.diagonal() < 0).any():
        raise ValueError("hessian is not positive semi-definite (a negative diagonal entry); "
                         "pass 2 X^T X / n of the layer's inputs")
    dead = h.diagonal() == 0
    h[dead, :] = 0
    h[:, dead] = 0
    h[dead, dead] = 1
    w[:, dead] = 0
    h.diagonal().add_(damping * h.diagonal().mean())
    factor, info = torch.linalg.cholesky_ex(h)
    if info != 0:
        raise ValueError("hessian is not positive semi-definite (its damped Cholesky factorisation failed); "
                         "pass 2 X^T X / n of the layer's inputs")
    upper = torch.linalg.cholesky(torch.cholesky_inverse(factor), upper=True)  # H^-1 = U^T U
    channel_weight = h.diagonal().float()
    block = -(-block // group_size) * group_size
    codes = torch.zeros(n, k, dtype=torch.float64)
    scales = torch.ones(n, -(-k // group_size), dtype=torch.float32)
    for start in range(0, k, block):
        end = min(start + block, k)
        w_block, u_block = w[:, start:end].clone(), upper[start:end, start:end]
        errors = torch.zeros(n, end - start, dtype=torch.float64)
        for i in range(end - start):
            column = start + i
            if column % group_size == 0:  # entering a group: its scale from the weights as updated so far
                stop = min(i + group_size, end - start)
                _, group_scale = clipped_weight(w_block[:, i:stop], group_size, channel_weight[column:start + stop])
                scales[:, column // group_size] = group_scale[:, 0]
            scale = scales[:, column // group_size].double()
            q = torch.round(w_block[:, i] / scale).clamp(reference.WEIGHT_QMIN, reference.WEIGHT_QMAX)
            codes[:, column] = q
            error = (w_block[:, i] - scale * q) / u_block[i, i]
            w_block[:, i:] -= error[:, None] * u_block[i, i:][None, :]
            errors[:, i] = error
        w[:, end:] -= errors @ upper[start:end, end:]
    return codes.to(torch.int8), scales


@torch.no_grad()
def collect_hessians(model: nn.Module, calibration) -> dict[int, torch.Tensor]:
    """``2 X^T X / n`` (float64 [K, K]) of every ``nn.Linear`` of ``model`` (keyed by ``id``) over the
    calibration data, from the inputs of the model as it is (float, unquantized)."""
    sums: dict[int, list] = {}

    def add(key: int, inputs: torch.Tensor) -> None:
        x = inputs.detach().reshape(-1, inputs.shape[-1]).float().cpu()
        entry = sums.setdefault(key, [0, 0.0])
        entry[0] += x.shape[0]
        entry[1] = entry[1] + (x.T @ x).double()

    _observe_linear_inputs(model, calibration, add)
    return {key: 2 * total / count for key, (count, total) in sums.items()}


# ---- calibration: what the layers read ------------------------------------------------------------------

@dataclass
class InputStatistics:
    """Per input channel sums over the calibration tokens of one linear layer, and a sample of its rows."""

    count: int = 0
    sum_abs: torch.Tensor | None = None
    sum_square: torch.Tensor | None = None
    rows: list[torch.Tensor] = field(default_factory=list)

    def add(self, x: torch.Tensor, keep_rows: bool) -> None:
        x = x.detach().reshape(-1, x.shape[-1]).float().cpu()
        abs_sum, square_sum = x.abs().sum(dim=0).double(), (x.double() ** 2).sum(dim=0)
        self.sum_abs = abs_sum if self.sum_abs is None else self.sum_abs + abs_sum
        self.sum_square = square_sum if self.sum_square is None else self.sum_square + square_sum
        self.count += x.shape[0]
        if keep_rows:
            self.rows.append(x)

    @property
    def mean_abs(self) -> torch.Tensor:
        return (self.sum_abs / self.count).float()

    @property
    def mean_square(self) -> torch.Tensor:
        return (self.sum_square / self.count).float()

    def sample(self, tokens: int, seed: int = 0) -> torch.Tensor:
        rows = torch.cat(self.rows)
        if rows.shape[0] > tokens:
            rows = rows[torch.randperm(rows.shape[0], generator=torch.Generator().manual_seed(seed))[:tokens]]
        return rows


class NonFiniteCalibration(ValueError):
    """The calibration data gave a linear layer NaN or Inf inputs, which no scale or clip search survives."""


def run_calibration(model: nn.Module, calibration) -> None:
    """Run ``model`` on the calibration data: a callable (called with no argument), a tensor (``model(t)``), a
    dict (``model(**d)``), or a list or tuple of tensors and dicts (each run in turn)."""
    if calibration is None:
        raise ValueError("calibration must be given for a calibrated method: a tensor of inputs (e.g. token ids "
                         "[batch, seq]), a dict of model keyword arguments, a list of those, or a callable")
    if callable(calibration) and not isinstance(calibration, nn.Module):
        calibration()
        return
    batches = list(calibration) if isinstance(calibration, (list, tuple)) else [calibration]
    if not batches:
        raise ValueError("calibration is empty: pass at least one batch")
    for i, batch in enumerate(batches):
        where = "calibration" + (f"[{i}]" if isinstance(calibration, (list, tuple)) else "")
        if isinstance(batch, torch.Tensor):
            if batch.numel() == 0:
                raise ValueError(f"{where} is an empty tensor of shape {tuple(batch.shape)}")
            call = lambda: model(batch)  # noqa: E731
        elif isinstance(batch, dict):
            call = lambda: model(**batch)  # noqa: E731
        else:
            raise TypeError(f"{where} must be a tensor or a dict of keyword arguments, got {type(batch).__name__}")
        try:
            call()
        except NonFiniteCalibration:
            raise
        except (RuntimeError, ValueError, IndexError, TypeError) as err:
            raise ValueError(f"{where} does not fit the model ({type(model).__name__} raised: {err})") from err


@torch.no_grad()
def collect_input_statistics(model: nn.Module, calibration, keep_rows_of: set[int]) -> dict[int, InputStatistics]:
    """InputStatistics of every ``nn.Linear`` of ``model`` (keyed by ``id``) over the calibration data; the
    rows themselves are kept for the layers in ``keep_rows_of``."""
    statistics: dict[int, InputStatistics] = {}
    _observe_linear_inputs(model, calibration,
                           lambda key, x: statistics.setdefault(key, InputStatistics()).add(x, key in keep_rows_of))
    return statistics


def _observe_linear_inputs(model: nn.Module, calibration, observe) -> None:
    """Run the calibration data through ``model`` with ``observe(id(layer), input)`` called on the input
    of every ``nn.Linear``; an error if no such layer ran."""
    seen = set()
    hooks = []

    def hook_of(key: int, name: str):
        def hook(_module, inputs):
            seen.add(key)
            if not torch.isfinite(inputs[0]).all():
                raise NonFiniteCalibration(f"the calibration data gives layer {name!r} NaN or Inf inputs; "
                                           "calibrate on data whose activations are finite")
            observe(key, inputs[0])
        return hook

    for name, module in model.named_modules():
        if isinstance(module, nn.Linear):
            hooks.append(module.register_forward_pre_hook(hook_of(id(module), name)))
    try:
        run_calibration(model, calibration)
    finally:
        for hook in hooks:
            hook.remove()
    if not seen:
        raise ValueError("calibration ran no nn.Linear of the model: nothing to calibrate")


def check_calibration_bits(calibration_bits) -> tuple[int, ...]:
    if isinstance(calibration_bits, int) or not calibration_bits:
        raise ValueError(f"calibration_bits must be a non-empty sequence of widths from {DEFAULT_CALIBRATION_BITS}, "
                         f"got {calibration_bits!r}")
    return tuple(check_bits(b, "calibration_bits") for b in calibration_bits)


@torch.no_grad()
def awq_prepare(model: nn.Module, calibration, group_size: int, calibration_bits: Sequence[int],
                targets: Callable[[nn.Linear], bool]) -> dict[int, torch.Tensor]:
    """Search and fold the AWQ scales of ``model`` in place (float function unchanged); returns, for every
    linear layer, the mean square of its input after the folding (the clipping search's channel weights).
    ``targets(linear)`` says whether a layer will be quantized: a scale group is folded only if all its
    readers will be."""
    from ..smoothing import llama_scale_groups

    groups = [g for g in llama_scale_groups(model, strict=False) if all(targets(r) for r in g.readers)]
    statistics = collect_input_statistics(model, calibration, {id(g.readers[0]) for g in groups})
    channel_weight = {key: s.mean_square for key, s in statistics.items()}
    for group in groups:
        observed = statistics.get(id(group.readers[0]))
        if observed is None:
            continue  # the calibration never reached this layer: leave it unscaled
        x = observed.sample(SEARCH_TOKENS)
        scales, _ = search_awq_scales(x, observed.mean_abs, [r.weight for r in group.readers], group_size,
                                      calibration_bits)
        group.fold(scales)
        for reader in group.readers:
            if id(reader) in channel_weight:
                channel_weight[id(reader)] = channel_weight[id(reader)] / scales.double().pow(2).float()
    return channel_weight
