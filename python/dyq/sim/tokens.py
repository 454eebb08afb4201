"""Tokens of the simulation policy: OpenVLA's action bins, and observations as tokens in the prefix.

Actions (as OpenVLA does): every action dimension is normalized by the 1st and 99th percentiles of the
training actions onto [-1, 1] (values outside are clipped), cut into 256 uniform bins, and each bin is one
token; decoding maps a token to its bin centre and back through the percentiles.

Observations: every dimension of the policy's observation vector is normalized by its training range
(minimum and maximum, widened by a margin so that states a little outside the demonstrations keep
distinct tokens) and cut into 256 bins; dimension ``d``'s bin ``i`` is its own token, so the embedding of
a token says both which quantity it is and its value.

Vocabulary, in this order: padding, BOS, one token per task, the observation tokens (dimension-major),
and the 256 action tokens last, as OpenVLA puts them at the end of its vocabulary.
"""
from __future__ import annotations

import dataclasses

import numpy as np

ACTION_DIMS = 7
BINS = 256
PAD, BOS = 0, 1


@dataclasses.dataclass
class BinTokenizer:
    """Uniform bins over ``[low, high]`` per dimension; ``encode`` gives bin indices in [0, bins)."""

    low: np.ndarray
    high: np.ndarray
    bins: int = BINS

    def __post_init__(self):
        self.low = np.asarray(self.low, dtype=np.float64)
        self.high = np.asarray(self.high, dtype=np.float64)
        if self.low.shape != self.high.shape or self.low.ndim != 1:
            raise ValueError(f"low and high must be 1-D of one shape, got {self.low.shape} and {self.high.shape}")
        if not (np.all(np.isfinite(self.low)) and np.all(np.isfinite(self.high))):
            raise ValueError("low and high must be finite")
        # A dimension that never varied in the data still needs a non-empty range.
        flat = self.high - self.low < 1e-6
        self.low = np.where(flat, self.low - 1e-3, self.low)
        self.high = np.where(flat, self.high + 1e-3, self.high)

    @property
    def dims(self) -> int:
        return self.low.shape[0]

    def normalize(self, values) -> np.ndarray:
        """Values mapped affinely so that ``low`` -> -1 and ``high`` -> +1, clipped to [-1, 1]."""
        values = np.asarray(values, dtype=np.float64)
        if values.shape[-1] != self.dims:
            raise ValueError(f"expected {self.dims} values in the last dimension, got shape {values.shape}")
        return np.clip(2.0 * (values - self.low) / (self.high - self.low) - 1.0, -1.0, 1.0)

    def encode(self, values) -> np.ndarray:
        normalized = self.normalize(values)
        index = np.floor((normalized + 1.0) * 0.5 * self.bins).astype(np.int64)
        return np.clip(index, 0, self.bins - 1)

    def decode(self, index) -> np.ndarray:
        """Bin centres, mapped back to the original units."""
        index = np.asarray(index)
        if np.any(index < 0) or np.any(index >= self.bins):
            raise ValueError(f"bin indices must lie in [0, {self.bins}), got {index}")
        normalized = -1.0 + (index + 0.5) * (2.0 / self.bins)
        return (normalized + 1.0) * 0.5 * (self.high - self.low) + self.low

    def to_dict(self) -> dict:
        return {"low": self.low.tolist(), "high": self.high.tolist(), "bins": self.bins}

    @classmethod
    def from_dict(cls, data: dict) -> "BinTokenizer":
        return cls(np.asarray(data["low"]), np.asarray(data["high"]), int(data.get("bins", BINS)))

    @classmethod
    def percentiles(cls, values, lower: float = 1.0, upper: float = 99.0) -> "BinTokenizer":
        """OpenVLA's action normalization: the 1st to 99th percentile of each dimension."""
        values = np.asarray(values, dtype=np.float64)
        return cls(np.percentile(values, lower, axis=0), np.percentile(values, upper, axis=0))

    @classmethod
    def range_with_margin(cls, values, margin: float = 0.1) -> "BinTokenizer":
        """Minimum to maximum of each dimension, widened by ``margin`` of the range on both sides."""
        values = np.asarray(values, dtype=np.float64)
        low, high = values.min(axis=0), values.max(axis=0)
        pad = margin * (high - low)
        return cls(low - pad, high + pad)


@dataclasses.dataclass
class Vocabulary:
    """Token ids of the policy's sequence ``[BOS, task, obs_1 .. obs_D, action_1 .. action_7]``."""

    tasks: tuple[str, ...]
    observation_dims: int
    bins: int = BINS

    @property
    def first_task(self) -> int:
        return 2

    @property
    def first_observation(self) -> int:
        return self.first_task + len(self.tasks)

    @property
    def first_action(self) -> int:
        return self.first_observation + self.observation_dims * self.bins

    @property
    def size(self) -> int:
        return self.first_action + self.bins

    @property
    def prefix_length(self) -> int:
        return 2 + self.observation_dims

    def prefix(self, task: str, observation_bins: np.ndarray) -> np.ndarray:
        """Token ids of the prompt for a batch (``[..., D]`` bin indices) or one observation."""
        if task not in self.tasks:
            raise ValueError(f"task must be one of {self.tasks}, got {task!r}")
        observation_bins = np.asarray(observation_bins, dtype=np.int64)
        if observation_bins.shape[-1] != self.observation_dims:
            raise ValueError(f"expected {self.observation_dims} observation bins, got shape {observation_bins.shape}")
        offsets = self.first_observation + self.bins * np.arange(self.observation_dims)
        head = np.broadcast_to(np.array([BOS, self.first_task + self.tasks.index(task)]),
                               observation_bins.shape[:-1] + (2,))
        return np.concatenate([head, observation_bins + offsets], axis=-1)

    def prefix_of_tasks(self, task_indices: np.ndarray, observation_bins: np.ndarray) -> np.ndarray:
        """:meth:`prefix` with the task given per row by its index into ``tasks``."""
        task_indices = np.asarray(task_indices, dtype=np.int64)
        observation_bins = np.asarray(observation_bins, dtype=np.int64)
        if np.any(task_indices < 0) or np.any(task_indices >= len(self.tasks)):
            raise ValueError(f"task indices must lie in [0, {len(self.tasks)}), got {task_indices}")
        if observation_bins.shape[-1] != self.observation_dims or observation_bins.shape[:-1] != task_indices.shape:
            raise ValueError(f"expected {self.observation_dims} observation bins per task index, got shapes "
                             f"{observation_bins.shape} and {task_indices.shape}")
        offsets = self.first_observation + self.bins * np.arange(self.observation_dims)
        head = np.stack([np.full_like(task_indices, BOS), self.first_task + task_indices], axis=-1)
        return np.concatenate([head, observation_bins + offsets], axis=-1)

    def action_tokens(self, action_bins: np.ndarray) -> np.ndarray:
        return np.asarray(action_bins, dtype=np.int64) + self.first_action

    def action_bins(self, action_tokens: np.ndarray) -> np.ndarray:
        bins = np.asarray(action_tokens, dtype=np.int64) - self.first_action
        if np.any(bins < 0) or np.any(bins >= self.bins):
            raise ValueError(f"not action tokens: {action_tokens}")
        return bins
