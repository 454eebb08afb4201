"""DyQ in the closed loop: widths run equal widths chosen (in worker processes too), seeded episodes
reproduce exactly, the evaluation grid caches and summarizes."""
import json

import numpy as np
import pytest
import torch

pytest.importorskip("robosuite")
pytest.importorskip("transformers")

import dyq  # noqa: E402
from dyq.sim import envs  # noqa: E402
from dyq.sim import evaluate  # noqa: E402
from dyq.sim.policy import PolicyConfig, TokenPolicy  # noqa: E402
from dyq.sim.rollout import PolicyRunner, RunConfig, run_episode  # noqa: E402
from dyq.sim.tokens import BinTokenizer  # noqa: E402

TASK = "lift"
HORIZON = 25


@pytest.fixture(scope="module")
def env():
    return envs.make_env(TASK, horizon=HORIZON)


@pytest.fixture(scope="module")
def policy(env):
    """An untrained policy whose tokenizers span the task's real observations (its actions vary)."""
    rng = np.random.default_rng(0)
    first = envs.observation_vector(TASK, envs.reset_env(env, 0))
    observations = first + rng.normal(scale=0.05, size=(64, first.shape[0]))
    actions = rng.uniform(-1, 1, size=(64, 7))
    config = PolicyConfig(task=TASK, observation_names=envs.observation_names(TASK),
                          observation_tokenizer=BinTokenizer.range_with_margin(observations).to_dict(),
                          action_tokenizer=BinTokenizer.percentiles(actions).to_dict(),
                          hidden_size=128, intermediate_size=256, layers=2, heads=2)
    torch.manual_seed(0)
    return TokenPolicy(config)


@pytest.fixture(scope="module")
def runner(policy):
    return PolicyRunner(policy)


@pytest.fixture(autouse=True)
def short_horizon(monkeypatch):
    spec = envs.TASKS[TASK]
    monkeypatch.setitem(envs.TASKS, TASK, envs.TaskSpec(spec.env_name, HORIZON, spec.object_key, spec.yaw_period))


def assert_kernels_ran_the_published_widths(episode, first_prefill_bits=16):
    previous = first_prefill_bits
    for t, (bits, prefill, decode) in enumerate(zip(episode["bits"], episode["prefill_kernel_bits"],
                                                     episode["decode_kernel_bits"])):
        assert set(decode) == {str(bits)}, f"step {t}: decode chose {bits}, kernels ran {decode}"
        if episode["config"] == "dyq":  # the prefill runs at b*_{t-1}
            assert set(prefill) == {str(previous)}, f"step {t}: prefill expected {previous}, ran {prefill}"
        else:
            assert set(prefill) == {str(bits)}
        previous = bits


def test_dyq_episode_runs_every_gemm_at_the_width_it_published(runner, env):
    # A dispatcher that leaves warm-up quickly and moves across the ladder on this policy's actions.
    config = RunConfig("dyq", "dyq", dispatch=dict(warmup=2, theta_2_4=0.3, theta_4_8=0.45, theta_fp=0.6))
    episode = run_episode(runner, TASK, config, seed=1, env=env)
    assert episode.steps == HORIZON
    assert_kernels_ran_the_published_widths(episode.to_dict())
    assert len(set(episode.bits)) >= 2, episode.bits
    warm = [s for s in episode.sensitivity if np.isfinite(s)]
    assert warm and all(s >= 0 for s in warm)
    assert all(np.all(np.abs(a) <= 1) for a in episode.actions)


def test_static_and_float_configurations(runner, env):
    for name, bits in (("w4a4", 4), ("w4a2", 2)):
        episode = run_episode(runner, TASK, name, seed=2, env=env)
        assert set(episode.bits) == {bits}
        assert_kernels_ran_the_published_widths(episode.to_dict())
    episode = run_episode(runner, TASK, "fp32", seed=2, env=env)
    assert all(not d and not p for d, p in zip(episode.decode_kernel_bits, episode.prefill_kernel_bits))


def test_a_seeded_episode_reproduces_exactly(runner, env):
    first = run_episode(runner, TASK, "dyq", seed=3, env=env)
    run_episode(runner, TASK, "w4a2", seed=4, env=env)  # something else in between
    again = run_episode(runner, TASK, "dyq", seed=3, env=env)
    assert first.actions == again.actions and first.bits == again.bits
    assert first.final_eef == again.final_eef


def test_widths_run_in_a_worker_process_equal_the_widths_chosen(policy, tmp_path):
    """The evaluation's own worker path (spawned process, policy loaded from a checkpoint)."""
    with torch.no_grad():
        for p in policy.model.parameters():
            p.copy_(p.to(torch.bfloat16).float())
    checkpoint = policy.save(tmp_path / "policy")
    digest = evaluate.checkpoint_digest(checkpoint)
    jobs = [(TASK, config, 5, str(checkpoint), str(evaluate.cache_path(tmp_path / "cache", TASK, config, 5, digest)))
            for config in ("w4a2", "w4a8", "dyq")]
    evaluate.run_grid(jobs, workers=2, progress=False)
    for job in jobs:
        episode = evaluate._read_episode(evaluate.cache_path(tmp_path / "cache", TASK, job[1], 5, digest))
        assert_kernels_ran_the_published_widths(episode)
    # The same episode in this process gives the same actions (the worker's copy is the same policy);
    # here the horizon is the test's shorter one, the worker ran the task's own.
    local = run_episode(PolicyRunner(TokenPolicy.load(checkpoint)), TASK, "w4a8", seed=5)
    cached = evaluate._read_episode(evaluate.cache_path(tmp_path / "cache", TASK, "w4a8", 5, digest))
    assert cached["actions"][: local.steps] == local.actions


def test_summary_counts_success_widths_and_runs():
    episodes = [
        {"seed": 0, "success": True, "steps": 3, "bits": [16, 2, 2], "latency_ms": [1.0, 2.0, 3.0],
         "prefill_kernel_bits": [{"16": 4}, {"16": 4}, {"2": 4}], "decode_kernel_bits": [{"16": 6}, {"2": 6}, {"2": 6}]},
        {"seed": 1, "success": False, "steps": 2, "bits": [16, 8], "latency_ms": [5.0, 6.0],
         "prefill_kernel_bits": [{"16": 4}, {"16": 4}], "decode_kernel_bits": [{"16": 6}, {"4": 6}]},
    ]
    row = evaluate.summarize(episodes)
    assert row["episodes"] == 2 and row["successes"] == 1
    assert row["bits_share"] == {"2": 0.4, "4": 0.0, "8": 0.2, "16": 0.4}
    assert row["share_below_8"] == pytest.approx(0.4)
    assert row["mean_bits"] == pytest.approx((16 + 2 + 2 + 16 + 8) / 5)
    assert row["steps_with_mismatched_kernel_bits"] == 1  # seed 1 chose 8 but ran 4
    assert row["per_seed"]["0"]["bits_runs"] == "16x1 2x2"
    lo, hi = row["wilson95"]
    assert lo < 0.5 < hi
    assert row["latency_ms"]["median"] == 3.0


def test_results_merge_keeps_other_rows(tmp_path, monkeypatch):
    out = tmp_path / "closed_loop.json"
    row = evaluate.summarize([{"seed": 0, "success": True, "steps": 1, "bits": [16], "latency_ms": [1.0],
                               "prefill_kernel_bits": [{}], "decode_kernel_bits": [{}]}])
    evaluate.update_results(out, TASK, [0], "ckpt", "abc", {"fp32": row})
    data = evaluate.update_results(out, TASK, [0], "ckpt", "abc", {"dyq": row})
    assert set(data["tasks"][TASK]["configs"]) == {"fp32", "dyq"}
    assert data["tasks"][TASK]["comparisons"][0]["config"] == "dyq"
    # A retrained checkpoint drops the rows of the old one.
    data = evaluate.update_results(out, TASK, [0], "ckpt", "def", {"w4a8": row})
    assert set(data["tasks"][TASK]["configs"]) == {"w4a8"}
    assert json.loads(out.read_text()) == data
    assert "| w4a8 |" in evaluate.markdown_table(data)
