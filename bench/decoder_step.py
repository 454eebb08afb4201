"""One OpenVLA-style control step of a Llama-shaped decoder in plain torch, for the GPU benchmark.

A GPU machine may lack transformers, so bench_cuda.py times this decoder instead of a Hugging Face model: RMS
norms, rotary positions, grouped scaled dot-product attention over a preallocated KV cache, a SiLU-gated MLP,
an LM head; every projection an ``nn.Linear`` that ``dyq.quantize_model`` converts (the LM head stays in
float, as quantize_model leaves it by default). A step is a prefill of ``prompt`` tokens and ``decoded``
greedily decoded tokens, each one forward over the cache, as ``dyq.sim.policy`` runs one.
"""
from __future__ import annotations

import torch
from torch import nn

# About 0.5 B parameters (bench_policy_step.py's "0.5b"): hidden 1280, 20 layers, MLP 3456, 32000 tokens.
HALF_BILLION = {"hidden": 1280, "layers": 20, "heads": 20, "mlp": 3456, "vocab": 32000}


class Block(nn.Module):
    def __init__(self, hidden: int, heads: int, mlp: int):
        super().__init__()
        self.heads, self.head_dim = heads, hidden // heads
        self.attention_norm, self.mlp_norm = nn.RMSNorm(hidden), nn.RMSNorm(hidden)
        self.q_proj, self.k_proj, self.v_proj, self.o_proj = (nn.Linear(hidden, hidden, bias=False) for _ in range(4))
        self.gate_proj, self.up_proj = nn.Linear(hidden, mlp, bias=False), nn.Linear(hidden, mlp, bias=False)
        self.down_proj = nn.Linear(mlp, hidden, bias=False)

    def forward(self, x, cos, sin, cache, start: int):
        b, t, _ = x.shape
        h = self.attention_norm(x)
        q, k, v = (p(h).view(b, t, self.heads, self.head_dim).transpose(1, 2) for p in (self.q_proj, self.k_proj,
                                                                                       self.v_proj))
        q, k = rotate(q, cos, sin), rotate(k, cos, sin)
        keys, values = cache
        keys[:, :, start:start + t], values[:, :, start:start + t] = k, v
        attention = nn.functional.scaled_dot_product_attention(
            q, keys[:, :, :start + t], values[:, :, :start + t], is_causal=start == 0)
        x = x + self.o_proj(attention.transpose(1, 2).reshape(b, t, -1))
        h = self.mlp_norm(x)
        return x + self.down_proj(nn.functional.silu(self.gate_proj(h)) * self.up_proj(h))


def rotate(x, cos, sin):
    half = x.shape[-1] // 2
    return x * cos + torch.cat((-x[..., half:], x[..., :half]), dim=-1) * sin


class Decoder(nn.Module):
    def __init__(self, hidden: int, layers: int, heads: int, mlp: int, vocab: int, max_positions: int = 512):
        super().__init__()
        self.embed = nn.Embedding(vocab, hidden)
        self.blocks = nn.ModuleList(Block(hidden, heads, mlp) for _ in range(layers))
        self.norm = nn.RMSNorm(hidden)
        self.lm_head = nn.Linear(hidden, vocab, bias=False)
        head_dim = hidden // heads
        inverse = 1.0 / (10000 ** (torch.arange(0, head_dim, 2).float() / head_dim))
        angles = torch.outer(torch.arange(max_positions).float(), inverse).repeat(1, 2)
        self.register_buffer("cos", angles.cos(), persistent=False)
        self.register_buffer("sin", angles.sin(), persistent=False)

    def new_cache(self, batch: int = 1):
        block = self.blocks[0]
        shape = (batch, block.heads, self.cos.shape[0], block.head_dim)
        like = self.embed.weight
        return [(like.new_zeros(shape), like.new_zeros(shape)) for _ in self.blocks]

    def forward(self, ids, cache, start: int):
        x = self.embed(ids)
        t = ids.shape[1]
        cos, sin = (table[start:start + t].to(x.dtype) for table in (self.cos, self.sin))
        for block, layer_cache in zip(self.blocks, cache):
            x = block(x, cos, sin, layer_cache, start)
        return self.lm_head(self.norm(x[:, -1:]))  # the last position's logits only


@torch.inference_mode()
def control_step(model: Decoder, prompt_ids: torch.Tensor, decoded: int = 7) -> torch.Tensor:
    cache = model.new_cache(prompt_ids.shape[0])
    token = model(prompt_ids, cache, 0).argmax(-1)
    tokens = [token]
    position = prompt_ids.shape[1]
    for _ in range(decoded - 1):
        token = model(token, cache, position).argmax(-1)
        tokens.append(token)
        position += 1
    return torch.cat(tokens, dim=1)
