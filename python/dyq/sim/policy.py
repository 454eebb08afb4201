"""The simulation policy: an OpenVLA-shaped Hugging Face Llama over observation and action tokens.

One control step is what OpenVLA does: a **prefill** of the prompt ``[BOS, task, obs_1 .. obs_D]``
(OpenVLA's is BOS, 256 image patch tokens and the instruction), then **7 action tokens decoded
greedily** with a KV cache, each restricted to the 256 action bins, de-tokenized through the training
actions' 1st/99th percentiles (:mod:`dyq.sim.tokens`). The model is a plain ``LlamaForCausalLM`` built
from a config whose widths are multiples of the INT4 group size, so ``dyq.quantize_model`` converts every
projection of every layer; embeddings and the LM head stay in full precision.

A **multi-task** policy (the LIBERO suites: one policy for ten tasks) lists its tasks in ``tasks``; its
observation vector then starts with the task's index (``observation_names[0] == "task_index"``), which
becomes the prompt's task token (a task id, as OpenVLA's instruction tokens tell it the task) instead of a
binned value, and the observation tokenizer covers the remaining dimensions.

A checkpoint is a folder with ``model.safetensors`` (bf16 by default: a few MB) and ``policy.json``
(the Llama config, the tokenizers' ranges, the observation names and how it was trained).
"""
from __future__ import annotations

import copy
import dataclasses
import functools
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import FileFormatError
from .tokens import ACTION_DIMS, BINS, BinTokenizer, Vocabulary

CHECKPOINT_FILE = "model.safetensors"
TASK_INDEX = "task_index"
CONFIG_FILE = "policy.json"


def forward_keywords(parameters) -> tuple[str, str | None]:
    """(the KV cache's keyword, the kept logits' keyword or None) of a causal LM's forward with ``parameters``."""
    logits = next((name for name in ("logits_to_keep", "num_logits_to_keep") if name in parameters), None)
    return ("cache" if "cache" in parameters else "past_key_values"), logits


@functools.lru_cache(maxsize=None)
def _forward_keywords() -> tuple[str, str | None]:
    """forward_keywords of the installed transformers (read once: cached_forward runs on every decoded token)."""
    import inspect

    from transformers import LlamaForCausalLM

    return forward_keywords(inspect.signature(LlamaForCausalLM.forward).parameters)


def cache_keyword() -> str:
    """transformers 5 renamed the KV-cache argument and output from ``past_key_values`` to ``cache``."""
    return _forward_keywords()[0]


def cached_forward(model, input_ids: torch.Tensor, cache=None, **inputs) -> tuple[Any, Any]:
    """One forward of ``model`` that extends the KV cache ``cache`` (None: a new one) and computes the logits of
    the last position only; returns the output and the cache to pass to the next call. Written for every
    transformers from 4.40 on: the cache is the argument and output ``cache`` in transformers 5
    (``past_key_values`` before), a ``DynamicCache`` that grows in place where transformers makes one, tuples
    that each call returns anew in 4.4x; the logits kept are ``logits_to_keep`` (``num_logits_to_keep`` in
    4.45 to 4.49; before that every position's logits are computed, and the caller reads the last)."""
    keyword, logits = _forward_keywords()
    keywords = {"use_cache": True, **({keyword: cache} if cache is not None else {}),
                **({logits: 1} if logits is not None else {})}
    out = model(input_ids=input_ids, **inputs, **keywords)
    return out, out[keyword]


@dataclasses.dataclass
class PolicyConfig:
    """Everything needed to rebuild a policy besides its weights.

    ``hidden_size`` and ``intermediate_size`` are multiples of 128, the default INT4 group size.
    """

    task: str
    observation_names: list[str]
    observation_tokenizer: dict
    action_tokenizer: dict
    hidden_size: int = 256
    intermediate_size: int = 768
    layers: int = 4
    heads: int = 4
    training: dict = dataclasses.field(default_factory=dict)
    tasks: list[str] = dataclasses.field(default_factory=list)  # multi-task: the task-id tokens' tasks

    def __post_init__(self):
        if self.tasks and (not self.observation_names or self.observation_names[0] != TASK_INDEX):
            raise ValueError(f"a multi-task policy's first observation must be {TASK_INDEX!r}, "
                             f"got {self.observation_names[:1]}")
        for name in ("hidden_size", "intermediate_size"):
            value = getattr(self, name)
            if value % 128:
                raise ValueError(f"{name} must be a multiple of 128 (the INT4 group size), got {value}")
        if self.hidden_size % self.heads:
            raise ValueError(f"hidden_size {self.hidden_size} must be a multiple of heads {self.heads}")

    @property
    def multi_task(self) -> bool:
        return bool(self.tasks)

    @property
    def binned_observations(self) -> int:
        """Observation dimensions that become binned tokens (all but the task index of a multi-task one)."""
        return len(self.observation_names) - int(self.multi_task)

    @property
    def vocabulary(self) -> Vocabulary:
        return Vocabulary(tasks=tuple(self.tasks) if self.tasks else (self.task,),
                          observation_dims=self.binned_observations)

    def llama_config(self):
        from transformers import LlamaConfig

        vocabulary = self.vocabulary
        return LlamaConfig(
            vocab_size=vocabulary.size,
            hidden_size=self.hidden_size,
            intermediate_size=self.intermediate_size,
            num_hidden_layers=self.layers,
            num_attention_heads=self.heads,
            num_key_value_heads=self.heads,
            max_position_embeddings=vocabulary.prefix_length + ACTION_DIMS + 8,
            bos_token_id=1,
            eos_token_id=None,
            pad_token_id=0,
            tie_word_embeddings=False,
        )

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "PolicyConfig":
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - fields
        if unknown:
            raise ValueError(f"unknown policy config keys: {sorted(unknown)}")
        return cls(**data)


class TokenPolicy:
    """A trained (or freshly built) policy: observation vector in, 7-D action out.

    ``prefill`` and ``decode`` are the two phases of a control step, so that
    :class:`dyq.DyQRuntime` can dispatch beside the prefill and publish the bit-width before the decode;
    ``act`` runs both.
    """

    def __init__(self, config: PolicyConfig, model: torch.nn.Module | None = None):
        from transformers import LlamaForCausalLM

        self.config = config
        self.vocabulary = config.vocabulary
        self.observation_tokenizer = BinTokenizer.from_dict(config.observation_tokenizer)
        self.action_tokenizer = BinTokenizer.from_dict(config.action_tokenizer)
        if self.observation_tokenizer.dims != config.binned_observations:
            raise ValueError("observation tokenizer and observation_names disagree on the dimension count")
        if self.action_tokenizer.dims != ACTION_DIMS:
            raise ValueError(f"the action tokenizer must have {ACTION_DIMS} dimensions")
        self.model = model if model is not None else LlamaForCausalLM(config.llama_config())
        self.model.eval()
        self._action_slice = slice(self.vocabulary.first_action, self.vocabulary.first_action + BINS)

    # -- one control step ---------------------------------------------------------------------

    def _prefix(self, observations: np.ndarray) -> np.ndarray:
        """Prompt token ids of one observation ``[D]`` or a batch ``[N, D]``."""
        observations = np.asarray(observations)
        if observations.shape[-1] != len(self.config.observation_names):
            raise ValueError(f"expected {len(self.config.observation_names)} observation values, "
                             f"got shape {observations.shape}")
        if not self.config.multi_task:
            return self.vocabulary.prefix(self.config.task, self.observation_tokenizer.encode(observations))
        index = observations[..., 0]
        if np.any(index != np.round(index)) or np.any(index < 0) or np.any(index >= len(self.config.tasks)):
            raise ValueError(f"task_index must be an integer in [0, {len(self.config.tasks)}), got {index}")
        return self.vocabulary.prefix_of_tasks(index.astype(np.int64),
                                               self.observation_tokenizer.encode(observations[..., 1:]))

    def prompt(self, observation: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(self._prefix(observation)).reshape(1, -1)

    @torch.inference_mode()
    def prefill(self, observation: np.ndarray) -> tuple[Any, int]:
        """Runs the prompt through the model; returns the KV cache and the first action bin."""
        out, cache = cached_forward(self.model, self.prompt(observation))
        return cache, int(out.logits[0, -1, self._action_slice].argmax())

    @torch.inference_mode()
    def decode(self, prefilled: tuple[Any, int]) -> np.ndarray:
        """Greedily decodes the remaining action tokens; returns the 7 action bins."""
        cache, first = prefilled
        bins = [first]
        position = self.vocabulary.prefix_length
        for _ in range(ACTION_DIMS - 1):
            token = torch.tensor([[bins[-1] + self.vocabulary.first_action]])
            out, cache = cached_forward(self.model, token, cache, position_ids=torch.tensor([[position]]))
            position += 1
            bins.append(int(out.logits[0, -1, self._action_slice].argmax()))
        return np.asarray(bins, dtype=np.int64)

    def action(self, bins: np.ndarray) -> np.ndarray:
        """De-tokenized action in the environment's units (float64, 7-D)."""
        return self.action_tokenizer.decode(bins)

    def act(self, observation: np.ndarray) -> np.ndarray:
        return self.action(self.decode(self.prefill(observation)))

    # -- training-time sequences ----------------------------------------------------------------

    def sequences(self, observations: np.ndarray, actions: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Token ids ``[N, P + 7]`` of whole steps and the action bins ``[N, 7]`` they should decode."""
        prefix = self._prefix(observations)
        action_bins = self.action_tokenizer.encode(actions)
        ids = np.concatenate([prefix, self.vocabulary.action_tokens(action_bins)], axis=1)
        return torch.from_numpy(ids), torch.from_numpy(action_bins)

    def action_logits(self, ids: torch.Tensor) -> torch.Tensor:
        """Logits over the 256 action bins at the 7 positions that predict the action tokens."""
        p = self.vocabulary.prefix_length
        hidden = self.model.model(input_ids=ids).last_hidden_state[:, p - 1: p - 1 + ACTION_DIMS]
        return self.model.lm_head(hidden)[..., self._action_slice]

    # -- copies, saving and loading --------------------------------------------------------------

    def copy(self) -> "TokenPolicy":
        return TokenPolicy(self.config, copy.deepcopy(self.model))

    def save(self, directory: str | os.PathLike, dtype: torch.dtype = torch.bfloat16) -> Path:
        from safetensors.torch import save_file

        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        tensors = {k: v.detach().to(dtype).contiguous() for k, v in self.model.state_dict().items()}
        save_file(tensors, str(directory / CHECKPOINT_FILE))
        (directory / CONFIG_FILE).write_text(json.dumps(self.config.to_dict(), indent=1) + "\n")
        return directory

    @classmethod
    def load(cls, directory: str | os.PathLike) -> "TokenPolicy":
        """Loads a checkpoint written by :meth:`save`; weights are computed in fp32."""
        from safetensors.torch import load_file

        directory = Path(directory)
        for name in (CONFIG_FILE, CHECKPOINT_FILE):
            if not (directory / name).is_file():
                raise FileNotFoundError(f"policy checkpoint {directory} has no {name}")
        try:
            config = PolicyConfig.from_dict(json.loads((directory / CONFIG_FILE).read_text()))
        except (ValueError, TypeError) as error:  # not JSON, or not a policy's config
            raise FileFormatError(f"policy checkpoint {directory}: {CONFIG_FILE} is not a policy config written "
                                  f"by dyq train: {error}") from None
        policy = cls(config)
        try:
            tensors = load_file(str(directory / CHECKPOINT_FILE))
        except Exception as error:  # safetensors raises its own error types for a truncated or foreign file
            raise FileFormatError(f"policy checkpoint {directory}: {CHECKPOINT_FILE} is not a safetensors file "
                                  f"of tensors: {error}") from None
        state = {k: v.float() for k, v in tensors.items()}
        try:
            missing, unexpected = policy.model.load_state_dict(state, strict=False)
        except RuntimeError as error:  # a tensor of another shape
            raise FileFormatError(f"checkpoint {directory} does not match its config: {error}") from None
        # lm_head and embeddings are separate parameters (untied); rotary buffers are not saved.
        missing = [k for k in missing if "rotary_emb" not in k]
        if missing or unexpected:
            raise FileFormatError(f"checkpoint {directory} does not match its config: missing {missing}, "
                                  f"unexpected {unexpected}")
        policy.model.eval()
        return policy
