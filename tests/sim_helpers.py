"""A policy for the simulation tests: untrained, but with tokenizers that span a task's real observations,
so that its actions vary from step to step."""
import numpy as np
import torch

from dyq.sim import envs
from dyq.sim.policy import PolicyConfig, TokenPolicy
from dyq.sim.tokens import BinTokenizer


def untrained_policy(task: str, env) -> TokenPolicy:
    rng = np.random.default_rng(0)
    first = envs.observation_vector(task, envs.reset_env(env, 0))
    observations = first + rng.normal(scale=0.05, size=(64, first.shape[0]))
    actions = rng.uniform(-1, 1, size=(64, 7))
    config = PolicyConfig(task=task, observation_names=envs.observation_names(task),
                          observation_tokenizer=BinTokenizer.range_with_margin(observations).to_dict(),
                          action_tokenizer=BinTokenizer.percentiles(actions).to_dict(),
                          hidden_size=128, intermediate_size=256, layers=2, heads=2)
    torch.manual_seed(0)
    return TokenPolicy(config)
