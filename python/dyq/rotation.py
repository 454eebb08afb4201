"""Orthogonal (Hadamard) rotations that remove activation outliers before INT4, as QuaRot does.

A few channels of a Llama's hidden state are tens of times larger than the rest; per-token activation
quantization gives them the group's range and every other channel loses its resolution, which is what
breaks A4 and A2. Multiplying the activation by an orthogonal matrix R whose entries all have magnitude
``1/sqrt(n)`` (a normalised Hadamard matrix with random signs) spreads each outlier over every channel,
and ``x W^T = (x R)(W R)^T`` keeps the product exact. :func:`rotate_llama` applies three rotations to a
Hugging Face Llama model, in place, before :func:`dyq.quantize_model`:

1. **The residual stream** (size d = hidden_size), folded into the weights. The RMSNorm weights are first
   folded into the layers that read the norm (q/k/v, gate/up, lm_head), leaving norms without a weight, so
   that ``norm(h R) = norm(h) R`` (an orthogonal R keeps ``mean(h^2)``). Then the embedding becomes ``E R``,
   every layer that reads the stream (q, k, v, gate, up, lm_head) ``W R``, and every layer that writes it
   (o, down) ``R^T W``. The embedding and the LM head, tied in many small models, are untied, since they
   now hold different matrices (``E R`` and ``E diag(g) R``).
2. **Each attention head's values** (size head_dim), folded: v_proj's rows per value head become
   ``H^T W`` and o_proj's columns per query head ``W H``; the same H for every head keeps grouped-query
   attention exact.
3. **down_proj's input** (size intermediate_size), online: ``silu(gate) * up`` is not linear in the
   weights, so the rotation runs at run time (:class:`OnlineRotation`, a forward pre-hook of down_proj)
   and down_proj's weight becomes ``W R``. For ``n = m * p`` it is the op ``dyq.ops.hadamard_transform``:
   a fast Walsh-Hadamard butterfly for the power-of-two factor and a small dense product for the Paley
   one, ``(log2 p + m) * n`` operations per token against ``n * d`` for the layer itself.

**Sizes that are not powers of two.** :func:`hadamard_matrix` builds a Hadamard matrix of order
``n = 2^k * m`` as the Kronecker product of Sylvester's ``H_{2^k}`` with a Paley matrix of order m: Paley I
for ``m = q + 1``, q a prime power = 3 mod 4 (12, 20, 24, 28, 44, 60, ...), Paley II for ``m = 2 (q + 1)``, q a
prime power = 1 mod 4 (12, 20, 28, 36, 52, 60, ...), over the finite field GF(q) (prime fields tried first).
SmolLM's 576 = 16 * 36, 960 = 16 * 60 and 1536 = 128 * 12 are covered, and Llama-2-7B's (and OpenVLA's)
intermediate 11008 = 32 * 344, 344 = 7^3 + 1: the dense factor has order 344, where prime fields alone
leave 11008 = 2 * 5504 and a dense factor that costs more than down_proj itself.
When no such split exists, the documented fallback is a random orthogonal matrix (the Q of a seeded
Gaussian's QR decomposition): as orthogonal and as exact, with outliers spread only in expectation.

The rotated float model computes the same function up to floating-point rounding (tested).
"""
from __future__ import annotations

import math

import torch
from torch import nn

from .core import ops

# The dtypes dyq.ops.hadamard_transform takes; others (float64) run the two matrix products in torch.
_KERNEL_DTYPES = (torch.float32, torch.bfloat16, torch.float16)


# ---- Hadamard matrices ----------------------------------------------------------------------------------

def _is_prime(q: int) -> bool:
    return q >= 2 and all(q % f for f in range(2, math.isqrt(q) + 1))


def _prime_power(q: int) -> tuple[int, int] | None:
    """(r, k) with q = r^k, r prime and k >= 1, or None."""
    for r in range(2, math.isqrt(q) + 1):
        if q % r == 0:
            k = 0
            while q % r == 0:
                q, k = q // r, k + 1
            return (r, k) if q == 1 else None
    return (q, 1) if q >= 2 else None


def _poly_mod(g: list[int], f: list[int], r: int) -> list[int]:
    """The remainder of g modulo the monic f over GF(r): coefficient lists, lowest degree first; the
    remainder has len(f) - 1 coefficients."""
    g = list(g) + [0] * max(0, len(f) - 1 - len(g))
    k = len(f) - 1
    for d in range(len(g) - 1, k - 1, -1):  # x^d = x^(d-k) (x^k - f): cancel the leading term
        c = g[d]
        if c:
            for i in range(k + 1):
                g[d - k + i] = (g[d - k + i] - c * f[i]) % r
    return g[:k]


def _irreducible(r: int, k: int) -> list[int]:
    """The first monic polynomial of degree k over GF(r) (coefficients in counting order) with no factor of
    degree 1 .. k/2, i.e. irreducible; GF(r^k) is GF(r)[x] modulo it."""
    def poly(index: int, degree: int) -> list[int]:
        return [(index // r ** i) % r for i in range(degree)] + [1]

    for index in range(r ** k):
        g = poly(index, k)
        if all(any(_poly_mod(g, poly(i, d), r)) for d in range(1, k // 2 + 1) for i in range(r ** d)):
            return g
    raise AssertionError(f"no irreducible polynomial of degree {k} over GF({r})")  # one always exists


def _jacobsthal(q: int) -> torch.Tensor:
    """Q[i, j] = chi(x_j - x_i) over the field GF(q), q = r^k a prime power, chi its quadratic character and
    x_i the element whose polynomial coefficients are the base-r digits of i (for a prime q, the integers
    mod q)."""
    r, k = _prime_power(q)
    weights = [r ** d for d in range(k)]
    digits = torch.tensor([[(i // w) % r for w in weights] for i in range(q)], dtype=torch.int64)
    modulus = _irreducible(r, k) if k > 1 else [0, 1]  # GF(r) itself: x mod x, the constants

    def square(a: list[int]) -> list[int]:
        return _poly_mod([sum(a[i] * a[j - i] for i in range(len(a)) if 0 <= j - i < len(a)) % r
                          for j in range(2 * k - 1)], modulus, r)

    squares = {sum(c * w for c, w in zip(square(a), weights)) for a in digits[1:].tolist()}
    chi = torch.tensor([0] + [1 if a in squares else -1 for a in range(1, q)], dtype=torch.float64)
    difference = (digits[None, :, :] - digits[:, None, :]) % r  # x_j - x_i, digit by digit
    index = (difference * torch.tensor(weights)).sum(-1)
    return chi[index]


# The constructions of hadamard_factors: 1 takes Paley's matrices over prime fields only; 2 (the current)
# also over prime-power fields (11008 = 32 * (7^3 + 1) instead of 2 * 5504). A saved rotated model records
# its construction, so that its run-time rotation is rebuilt as the one its weights were folded with.
HADAMARD_CONSTRUCTION = 2
HADAMARD_CONSTRUCTIONS = (1, 2)


def _paley(m: int, prime_powers: bool = True) -> torch.Tensor | None:
    """A Hadamard matrix of order m by Paley's first or second construction, or None. Prime fields are
    tried before prime-power ones, so an order that has both keeps the prime field's matrix."""
    if m % 4 != 0:
        return None
    fields = [_is_prime] + ([lambda q: _prime_power(q) is not None] if prime_powers else [])
    for is_field in fields:
        q = m - 1
        if is_field(q) and q % 4 == 3:
            s = torch.zeros(m, m, dtype=torch.float64)
            s[0, 1:] = 1
            s[1:, 0] = -1
            s[1:, 1:] = _jacobsthal(q)
            return s + torch.eye(m, dtype=torch.float64)
        q = m // 2 - 1
        if is_field(q) and q % 4 == 1:
            c = torch.zeros(q + 1, q + 1, dtype=torch.float64)
            c[0, 1:] = 1
            c[1:, 0] = 1
            c[1:, 1:] = _jacobsthal(q)
            one = torch.tensor([[1.0, 1.0], [1.0, -1.0]], dtype=torch.float64)
            other = torch.tensor([[1.0, -1.0], [-1.0, -1.0]], dtype=torch.float64)
            return torch.kron(c, one) + torch.kron(torch.eye(q + 1, dtype=torch.float64), other)
    return None


def _sylvester(p: int) -> torch.Tensor:
    h = torch.ones(1, 1, dtype=torch.float64)
    while h.shape[0] < p:
        h = torch.cat([torch.cat([h, h], 1), torch.cat([h, -h], 1)], 0)
    return h


def _check_construction(construction: int) -> None:
    if construction not in HADAMARD_CONSTRUCTIONS:
        raise ValueError(f"construction must be one of {HADAMARD_CONSTRUCTIONS}, got {construction!r}")


def hadamard_factors(n: int, construction: int = HADAMARD_CONSTRUCTION) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(A [m, m], B [p, p]), +-1 Hadamard matrices with ``n = m * p`` (B Sylvester's, the largest power of
    two that leaves a Paley order m), or None if this construction has no matrix of order n.
    ``construction`` (:data:`HADAMARD_CONSTRUCTIONS`) selects the Paley fields: 1 prime fields only, 2 also
    prime powers."""
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n must be an int >= 1, got {n!r}")
    _check_construction(construction)
    p = 1 << ((n & -n).bit_length() - 1)  # the largest power of two dividing n
    while p >= 1:
        m = n // p
        a = torch.ones(1, 1, dtype=torch.float64) if m == 1 else _paley(m, prime_powers=construction >= 2)
        if a is not None:
            return a, _sylvester(p)
        p //= 2
    return None


def hadamard_matrix(n: int, construction: int = HADAMARD_CONSTRUCTION) -> torch.Tensor | None:
    """A +-1 matrix H of order n with ``H H^T = n I`` (float64), or None (see :func:`hadamard_factors`)."""
    factors = hadamard_factors(n, construction)
    return None if factors is None else torch.kron(*factors)


def _walsh_hadamard(y: torch.Tensor) -> torch.Tensor:
    """``y H_p`` over the last dimension (p a power of two), H_p Sylvester's +-1 matrix, unnormalized.
    Sylvester's matrices are Kronecker powers of H_2, so ``H_p = H_a (x) H_b`` for ``p = a b`` and, with y
    viewed as [a, b], ``y H_p = H_a Y H_b``: two batched products with matrices of order about sqrt(p),
    ``(a + b) p`` multiply-adds per row (128 p for p = 4096) where the dense H_p takes ``p^2``."""
    p = y.shape[-1]
    a = 1 << ((p.bit_length() - 1) // 2)
    b = p // a
    view = y.reshape(*y.shape[:-1], a, b)
    return (_sylvester(a).to(y) @ view @ _sylvester(b).to(y)).reshape(y.shape)


class OnlineRotation(nn.Module):
    """``x -> x R`` with ``R = diag(signs) (A kron B)``, A [m, m] and B [p, p] orthogonal: ``A^T X B`` on x
    viewed as [..., m, p]. With the Hadamard factors (B Sylvester's, p a power of two) and x in float32,
    bfloat16 or float16 this is :func:`dyq.ops.hadamard_transform` (the butterfly for B, ``(log2 p + m) n``
    operations, computed in float32, output in x's dtype); otherwise torch products in x's dtype (float64
    when folding weights): ``A^T`` and, for B, two Sylvester factors of order about ``sqrt(p)``
    (:func:`_walsh_hadamard`), or B itself for the random fallback. All compute :meth:`matrix`'s R, so
    weights folded with it stay exact.

    The fallback for sizes without a Hadamard construction is ``A`` a random orthogonal matrix, ``p = 1``.
    The buffers are float64 (cast to the input's dtype when applied) and not persistent: they are rebuilt from
    the size, seed and construction that ``dyq_config.json`` records.
    """

    def __init__(self, size: int, seed: int = 0, construction: int = HADAMARD_CONSTRUCTION) -> None:
        super().__init__()
        gen = torch.Generator().manual_seed(seed)
        factors = hadamard_factors(size, construction)
        if factors is None:
            left, _ = torch.linalg.qr(torch.randn(size, size, generator=gen, dtype=torch.float64))
            right = torch.ones(1, 1, dtype=torch.float64)
        else:
            left, right = (f / math.sqrt(f.shape[0]) for f in factors)
        signs = torch.randint(0, 2, (size,), generator=gen, dtype=torch.float64) * 2 - 1
        self.size, self.seed = size, seed
        self.hadamard = factors is not None
        self.register_buffer("signs", signs, persistent=False)
        self.register_buffer("left", left, persistent=False)
        self.register_buffer("right", right, persistent=False)

    def matrix(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """The dense R [n, n] (for folding into weights)."""
        return (self.signs.double()[:, None] * torch.kron(self.left.double(), self.right.double())).to(dtype)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] != self.size:
            raise ValueError(f"OnlineRotation of size {self.size} got x of shape {tuple(x.shape)}")
        if self.hadamard and x.dtype in _KERNEL_DTYPES:
            return ops.hadamard_transform(x, self.signs.float(), self.left.float())
        m, p = self.left.shape[0], self.right.shape[0]
        y = (x * self.signs.to(x.dtype)).reshape(*x.shape[:-1], m, p)
        if self.hadamard:  # H_p factored (_walsh_hadamard): about (m + 2 sqrt(p)) n operations per row
            y = _walsh_hadamard(y) * (1.0 / math.sqrt(p))
        else:
            y = y @ self.right.to(x.dtype)
        return (self.left.T.to(x.dtype) @ y).reshape(x.shape)

    def extra_repr(self) -> str:
        kind = "hadamard" if self.hadamard else "random orthogonal"
        factors = f"({self.left.shape[0]}, {self.right.shape[0]})"
        return f"size={self.size}, factors={factors}, {kind}, seed={self.seed}"


# ---- folding into a Llama model ---------------------------------------------------------------------------

def _decoder_layers(model: nn.Module):
    inner = getattr(model, "model", None)
    layers = getattr(inner, "layers", None)
    needed = ("embed_tokens", "norm")
    if layers is None or not all(hasattr(inner, a) for a in needed) or not hasattr(model, "lm_head"):
        raise ValueError("model must be a Hugging Face Llama-style causal LM (model.model.embed_tokens, "
                         f".layers, .norm and model.lm_head), got {type(model).__name__}")
    for layer in layers:
        if not all(hasattr(layer, a) for a in ("self_attn", "mlp", "input_layernorm", "post_attention_layernorm")):
            raise ValueError(f"decoder layer {type(layer).__name__} is not Llama-style (self_attn, mlp, two norms)")
        if getattr(layer.mlp, "down_proj", None) is None or not isinstance(layer.mlp.down_proj, nn.Linear):
            raise ValueError("rotate_llama must run before quantize_model (down_proj must be an nn.Linear)")
    return inner, layers


def _fold_norm(norm: nn.Module, readers: list[nn.Linear]) -> None:
    """RMSNorm(h) * g feeding W equals RMSNorm(h) feeding W diag(g): move g into the readers, set it to 1."""
    g = norm.weight.detach().double()
    for reader in readers:
        reader.weight.copy_(reader.weight.double() * g)
    norm.weight.fill_(1.0)


# Folding applies R to the rows (W R) or the columns (R^T W = (W^T R)^T) of a weight through the rotation's
# factored form in float64 (OnlineRotation.forward), never as the dense [n, n] matrix: for a 7B Llama's
# 4096 and 11008 that is 128 and 344 + 12 multiply-adds per element instead of n.
def _rotate_input(linear: nn.Linear, rotation: OnlineRotation) -> None:
    linear.weight.copy_(rotation(linear.weight.double()))


def _rotate_output(linear: nn.Linear, rotation: OnlineRotation) -> None:
    linear.weight.copy_(rotation(linear.weight.double().T).T)
    if linear.bias is not None:
        linear.bias.copy_(rotation(linear.bias.double()))


def attach_online_rotations(model: nn.Module, seed: int, construction: int = HADAMARD_CONSTRUCTION) -> OnlineRotation:
    """Give every decoder layer's down_proj the run-time rotation of its input (as a forward pre-hook; the
    module is held as ``mlp.down_proj_rotation``). Used by :func:`rotate_llama` and when loading."""
    _, layers = _decoder_layers_any(model)
    rotation = OnlineRotation(layers[0].mlp.down_proj.in_features, seed + 2, construction)
    for layer in layers:
        layer.mlp.down_proj_rotation = rotation
        layer.mlp.down_proj.register_forward_pre_hook(lambda _module, inputs, r=rotation: (r(inputs[0]),))
    return rotation


def _decoder_layers_any(model: nn.Module):
    inner = getattr(model, "model", None)
    layers = getattr(inner, "layers", None)
    if not layers:
        raise ValueError(f"model must be a Hugging Face Llama-style causal LM, got {type(model).__name__}")
    return inner, layers


def untie_lm_head(model: nn.Module) -> None:
    """Give the LM head its own weight (a rotated model's head and embedding differ)."""
    inner, _ = _decoder_layers_any(model)
    if model.lm_head.weight is inner.embed_tokens.weight:
        model.lm_head.weight = nn.Parameter(inner.embed_tokens.weight.detach().clone(),
                                            requires_grad=inner.embed_tokens.weight.requires_grad)
    if getattr(model, "config", None) is not None:
        model.config.tie_word_embeddings = False
        # transformers 5 ties through this table as well; a rotated model must not be re-tied on load.
        if isinstance(getattr(model, "_tied_weights_keys", None), dict):
            model._tied_weights_keys = {}


@torch.no_grad()
def rotate_llama(model: nn.Module, seed: int = 0, construction: int = HADAMARD_CONSTRUCTION) -> dict:
    """Rotate a float Llama model in place (module docstring); returns the description that
    ``dyq.save_quantized`` records (``{"kind": "hadamard", "seed": seed, "construction": 2}``, the
    construction of :func:`hadamard_factors`; an older one is kept for reproducing an old model)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {seed!r}")
    _check_construction(construction)
    if getattr(model, "dyq_rotation", None) is not None:
        raise ValueError("the model is already rotated (model.dyq_rotation is set)")
    inner, layers = _decoder_layers(model)
    untie_lm_head(model)
    hidden = inner.embed_tokens.weight.shape[1]
    residual = OnlineRotation(hidden, seed, construction)
    for layer in layers:
        attn, mlp = layer.self_attn, layer.mlp
        _fold_norm(layer.input_layernorm, [attn.q_proj, attn.k_proj, attn.v_proj])
        _fold_norm(layer.post_attention_layernorm, [mlp.gate_proj, mlp.up_proj])
    _fold_norm(inner.norm, [model.lm_head])

    inner.embed_tokens.weight.copy_(residual(inner.embed_tokens.weight.double()))
    _rotate_input(model.lm_head, residual)
    head_dim = layers[0].self_attn.head_dim
    head = OnlineRotation(head_dim, seed + 1, construction).matrix()
    for layer in layers:
        attn, mlp = layer.self_attn, layer.mlp
        for reader in (attn.q_proj, attn.k_proj, attn.v_proj, mlp.gate_proj, mlp.up_proj):
            _rotate_input(reader, residual)
        for writer in (attn.o_proj, mlp.down_proj):
            _rotate_output(writer, residual)
        # Values per head: v' = v H (rows of each value head's block), o reads a' = a H per query head.
        v = attn.v_proj.weight.double().reshape(-1, head_dim, hidden)
        attn.v_proj.weight.copy_(torch.einsum("ji,gjd->gid", head, v).reshape(-1, hidden))
        if attn.v_proj.bias is not None:
            attn.v_proj.bias.copy_((attn.v_proj.bias.double().reshape(-1, head_dim) @ head).reshape(-1))
        o = attn.o_proj.weight.double().reshape(hidden, -1, head_dim)
        attn.o_proj.weight.copy_((o @ head).reshape(hidden, -1))
    online = attach_online_rotations(model, seed, construction)
    for layer in layers:
        _rotate_input(layer.mlp.down_proj, online)
    model.dyq_rotation = {"kind": "hadamard", "seed": seed, "construction": construction}
    return model.dyq_rotation
