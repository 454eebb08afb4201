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
from dyq.sim.policy import TokenPolicy  # noqa: E402
from dyq.sim.rollout import (InvertedLadderDispatcher, PolicyRunner, RunConfig, make_schedule, run_config,  # noqa: E402
                             run_episode)
from sim_helpers import untrained_policy  # noqa: E402

TASK = "lift"
HORIZON = 25


@pytest.fixture(scope="module")
def env():
    return envs.make_env(TASK, horizon=HORIZON)


@pytest.fixture(scope="module")
def policy(env):
    return untrained_policy(TASK, env)


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
        if episode["config"].startswith(("dyq", "random")):  # the prefill runs at b*_{t-1}
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
    assert episode.cpu_isa == dyq.cpu_info()["isa"]


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
    fresh = run_episode(runner, TASK, "dyq", seed=3)  # in a new environment
    for other in (again, fresh):
        assert first.actions == other.actions and first.bits == other.bits
        assert first.final_eef == other.final_eef


def test_widths_run_in_a_worker_process_equal_the_widths_chosen(policy, tmp_path):
    """The evaluation's own worker path (spawned process, policy loaded from a checkpoint)."""
    with torch.no_grad():
        for p in policy.model.parameters():
            p.copy_(p.to(torch.bfloat16).float())
    checkpoint = policy.save(tmp_path / "policy")
    digest = evaluate.checkpoint_digest(checkpoint)
    jobs = [(TASK, run_config(config), 5, str(checkpoint),
             str(evaluate.cache_path(tmp_path / "cache", TASK, config, 5, digest)), None) for config in ("w4a2", "w4a8", "dyq")]
    evaluate.run_grid(jobs, workers=2, progress=False)
    for job in jobs:
        episode = evaluate._read_episode(evaluate.cache_path(tmp_path / "cache", TASK, job[1].name, 5, digest))
        assert_kernels_ran_the_published_widths(episode)
    # The same episode in this process gives the same actions (the worker's copy is the same policy);
    # here the horizon is the test's shorter one, the worker ran the task's own.
    local = run_episode(PolicyRunner(TokenPolicy.load(checkpoint)), TASK, "w4a8", seed=5)
    cached = evaluate._read_episode(evaluate.cache_path(tmp_path / "cache", TASK, "w4a8", 5, digest))
    assert cached["actions"][: local.steps] == local.actions


def test_cache_names_follow_the_dispatcher_each_configuration_runs(policy, tmp_path):
    from dyq.sim import dispatch_budget

    checkpoint = policy.save(tmp_path / "policy")
    names = {c: evaluate.config_cache_name(run_config(c), checkpoint)
             for c in ("fp32", "w4a2", "dyq", "dyq_no_hysteresis", "dyq_inverted", "random_schedule", "random_runs")}
    assert names["fp32"] == "fp32" and names["w4a2"] == "w4a2"  # no dispatcher: the name alone
    digest = names["dyq"].split("@")[1]
    assert names["dyq"] == f"dyq@{digest}" and len(digest) == 8
    # Another config, or the reversed ladder, is another folder; a schedule is keyed by the dyq it copies.
    assert len({names["dyq"].split("@")[1], names["dyq_no_hysteresis"].split("@")[1],
                names["dyq_inverted"].split("@")[1]}) == 3
    assert names["random_schedule"] == f"random_schedule@{digest}" and names["random_runs"] == f"random_runs@{digest}"
    # A new width budget beside the same weights moves every dispatcher-driven folder.
    config, prime = dispatch_budget.budget_dispatch([np.tile(np.linspace(-1, 1, 7), (40, 1)) * np.linspace(1, 0, 40)[:, None]])
    dispatch_budget.save(checkpoint, config.replace(theta_fp=config.theta_fp + 0.1), prime, source="test")
    assert evaluate.config_cache_name(run_config("dyq"), checkpoint) != names["dyq"]
    assert evaluate.config_cache_name(run_config("fp32"), checkpoint) == "fp32"


def test_calibrated_configuration_is_per_task():
    with pytest.raises(ValueError, match="per task"):
        run_config("dyq_calibrated")
    with pytest.raises(ValueError, match="dyq_calibrated"):
        run_config("dyq_calibrate")  # the known names, the calibrated one included


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


@pytest.mark.parametrize("content", ["{truncated", "[1, 2]", '{"tasks": 3}'])
def test_a_results_file_dyq_did_not_write_is_refused_naming_it(tmp_path, content):
    out = tmp_path / "closed_loop.json"
    out.write_text(content)
    row = evaluate.summarize([{"seed": 0, "success": True, "steps": 1, "bits": [16], "latency_ms": [1.0],
                               "prefill_kernel_bits": [{}], "decode_kernel_bits": [{}]}])
    with pytest.raises(dyq.FileFormatError, match="closed_loop.json"):
        evaluate.update_results(out, TASK, [0], "ckpt", "abc", {"fp32": row})
    assert out.read_text() == content  # left as it was


@pytest.mark.parametrize("content", [b"not gzip at all", b"\x1f\x8b\x08\x00truncated"])
def test_a_damaged_episode_record_is_refused_naming_it(tmp_path, content):
    path = tmp_path / "episode.json.gz"
    path.write_bytes(content)
    with pytest.raises(dyq.FileFormatError, match="episode.json.gz"):
        evaluate._read_episode(path)


def test_a_row_on_fewer_seeds_keeps_the_seeds_of_the_rows_on_more(tmp_path):
    out = tmp_path / "closed_loop.json"
    row = evaluate.summarize([{"seed": 0, "success": True, "steps": 1, "bits": [16], "latency_ms": [1.0],
                               "prefill_kernel_bits": [{}], "decode_kernel_bits": [{}]}])
    evaluate.update_results(out, TASK, list(range(100)), "ckpt", "abc", {"fp32": row})
    data = evaluate.update_results(out, TASK, list(range(50)), "ckpt", "abc", {"dyq": row})
    assert data["tasks"][TASK]["seeds"] == list(range(100))
    data = evaluate.update_results(out, TASK, [7], "ckpt", "def", {"w4a8": row})  # another policy
    assert data["tasks"][TASK]["seeds"] == [7]


def cpu_info_on(isa: str):
    """dyq.cpu_info as on a machine whose CPU path is `isa` (the rest as here)."""
    info = {**dyq.cpu_info(), "isa": isa}
    return lambda: dict(info)


def test_each_row_records_the_cpu_path_it_ran_on(tmp_path, monkeypatch):
    out = tmp_path / "closed_loop.json"
    row = evaluate.summarize([{"seed": 0, "success": True, "steps": 1, "bits": [16], "latency_ms": [1.0],
                               "prefill_kernel_bits": [{}], "decode_kernel_bits": [{}]}])
    # A file written when the path was recorded once per task: its rows keep that value.
    out.write_text(json.dumps({"tasks": {TASK: {"configs": {"fp32": row}, "cpu_isa": "avx512_bf16",
                                                "checkpoint_digest": "abc"}}}))
    monkeypatch.setattr(dyq, "cpu_info", cpu_info_on("avx2"))
    data = evaluate.update_results(out, TASK, [0], "ckpt", "abc", {"dyq": row})
    configs = data["tasks"][TASK]["configs"]
    assert (configs["fp32"]["cpu_isa"], configs["dyq"]["cpu_isa"]) == ("avx512_bf16", "avx2")
    assert "cpu_isa" not in data["tasks"][TASK]
    assert "CPU kernel path per row: fp32 avx512_bf16, dyq avx2." in evaluate.markdown_table(data)
    rerun = evaluate.summarize([{"seed": 0, "success": True, "steps": 1, "bits": [16], "latency_ms": [1.0],
                                 "prefill_kernel_bits": [{}], "decode_kernel_bits": [{}], "cpu_isa": "avx2"}])
    data = evaluate.update_results(out, TASK, [0], "ckpt", "abc", {"fp32": rerun})  # fp32 run again here
    assert "CPU kernel path per row" not in evaluate.markdown_table(data)  # one path: nothing to say


def test_a_row_takes_its_cpu_path_from_its_episodes_not_from_the_machine_that_summarizes(tmp_path, monkeypatch):
    out = tmp_path / "closed_loop.json"
    monkeypatch.setattr(dyq, "cpu_info", cpu_info_on("avx2"))

    def episode(seed, isa=None):
        return {"seed": seed, "success": True, "steps": 1, "bits": [16], "latency_ms": [1.0],
                "prefill_kernel_bits": [{}], "decode_kernel_bits": [{}], **({"cpu_isa": isa} if isa else {})}

    recorded = evaluate.summarize([episode(0, "amx"), episode(1, "avx512")])
    assert recorded["cpu_isa"] == "amx+avx512"
    data = evaluate.update_results(out, TASK, [0, 1], "ckpt", "abc", {"w4a8": recorded})
    assert data["tasks"][TASK]["configs"]["w4a8"]["cpu_isa"] == "amx+avx512"
    # Episodes cached before they recorded the path: a new row takes this machine's, and re-summarizing
    # it elsewhere keeps what it was written with.
    unrecorded = evaluate.summarize([episode(0), episode(1, "amx")])
    assert "cpu_isa" not in unrecorded
    data = evaluate.update_results(out, TASK, [0, 1], "ckpt", "abc", {"fp32": unrecorded})
    assert data["tasks"][TASK]["configs"]["fp32"]["cpu_isa"] == "avx2"
    monkeypatch.setattr(dyq, "cpu_info", cpu_info_on("avx512_bf16"))
    data = evaluate.update_results(out, TASK, [0, 1], "ckpt", "abc", {"fp32": unrecorded, "w4a8": recorded})
    configs = data["tasks"][TASK]["configs"]
    assert (configs["fp32"]["cpu_isa"], configs["w4a8"]["cpu_isa"]) == ("avx2", "amx+avx512")


def test_checkpoints_are_named_the_same_wherever_dyq_is_installed(tmp_path, monkeypatch):
    assert evaluate.checkpoint_label(evaluate.default_checkpoint("lift")) == "dyq/sim/policies/lift"
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine").mkdir()
    assert evaluate.checkpoint_label("mine") == "mine"
    assert evaluate.checkpoint_label("/") == "/"


def test_table_states_whether_the_target_is_met(tmp_path):
    def row(successes, low_share):
        episodes = [{"seed": s, "success": s < successes, "steps": 10,
                     "bits": [2] * int(10 * low_share) + [16] * (10 - int(10 * low_share)), "latency_ms": [1.0] * 10,
                     "prefill_kernel_bits": [{}] * 10, "decode_kernel_bits": [{}] * 10} for s in range(10)]
        return evaluate.summarize(episodes)

    out = tmp_path / "closed_loop.json"
    data = evaluate.update_results(out, TASK, list(range(10)), "ckpt", "abc",
                                   {"fp32": row(8, 0.0), "dyq": row(8, 0.7), "dyq_calibrated": row(6, 0.9)})
    table = evaluate.markdown_table(data)
    assert "dyq keeps 100 % of fp32's success rate with 70 % of its steps below 8 bits" in table
    assert "with 70 % of its steps below 8 bits (target: 99.5 % with 60 %): met on these 10 seeds" in table
    assert "dyq_calibrated keeps 75 % of fp32's success rate with 90 %" in table and "not met" in table
    assert {(c["config"], c["against"]) for c in data["tasks"][TASK]["comparisons"]} >= {
        ("dyq_calibrated", "fp32"), ("dyq_calibrated", "dyq"), ("dyq", "fp32")}


def test_random_schedules_keep_dyq_statistics():
    dyq_bits = [16] * 10 + [8] * 3 + [2] * 20 + [4] * 5 + [2] * 7
    shares = make_schedule("shares", dyq_bits, seed=3, length=4000)
    assert set(shares) == {2, 4, 8, 16}
    for width in (2, 4, 8, 16):
        assert abs(shares.count(width) / 4000 - dyq_bits.count(width) / len(dyq_bits)) < 0.03
    assert make_schedule("shares", dyq_bits, seed=3, length=50) == shares[:50]
    assert make_schedule("shares", dyq_bits, seed=4, length=50) != shares[:50]
    runs = make_schedule("runs", dyq_bits, seed=3, length=len(dyq_bits))
    assert sorted(runs) == sorted(dyq_bits) and runs != dyq_bits
    longer = make_schedule("runs", dyq_bits, seed=3, length=3 * len(dyq_bits))
    assert longer[: len(dyq_bits)] == runs and len(longer) == 3 * len(dyq_bits)
    with pytest.raises(ValueError, match="schedule kind"):
        make_schedule("bogus", dyq_bits, 0, 10)
    with pytest.raises(ValueError, match="dyq_bits"):
        make_schedule("runs", [], 0, 10)


def test_inverted_ladder_reverses_phi():
    config = dyq.DispatchConfig()
    normal, inverted = dyq.KinematicDispatcher(config), InvertedLadderDispatcher(config)
    for s in (0.0, 0.1, 0.2, 0.4, 0.9):
        assert inverted.allocate(s) == {2: 16, 4: 8, 8: 4, 16: 2}[normal.allocate(s)]


def test_schedule_episode_runs_the_schedule(runner, env):
    schedule = make_schedule("runs", [2, 2, 8, 8, 8, 16, 4, 4], seed=0, length=HORIZON)
    episode = run_episode(runner, TASK, "random_runs", seed=1, env=env, schedule=schedule)
    assert episode.bits == schedule[: episode.steps]
    assert_kernels_ran_the_published_widths(episode.to_dict())
    with pytest.raises(ValueError, match="needs a schedule"):
        run_episode(runner, TASK, "random_schedule", seed=1, env=env)


def test_smoothquant_configuration_calibrates_on_training_data(policy, env):
    rng = np.random.default_rng(5)
    first = envs.observation_vector(TASK, envs.reset_env(env, 0))
    calibration = (first + rng.normal(scale=0.05, size=(32, first.shape[0])), rng.uniform(-1, 1, size=(32, 7)))
    smoothed = PolicyRunner(policy, calibration)
    episode = run_episode(smoothed, TASK, "smoothquant_w4a4", seed=1, env=env)
    assert set(episode.bits) == {4}
    assert_kernels_ran_the_published_widths(episode.to_dict())
    # Different weights from round-to-nearest, the same float function before quantization.
    a = smoothed.quantized_policy("smoothquant").model.model.layers[0].self_attn.q_proj
    b = smoothed.quantized_policy("rtn").model.model.layers[0].self_attn.q_proj
    assert not torch.equal(a.scales, b.scales)
    with pytest.raises(ValueError, match="calibration data"):
        PolicyRunner(policy).quantized_policy("smoothquant")


@pytest.mark.parametrize("method", ["mse", "awq", "gptq"])
def test_weight_method_configurations_share_one_weight_set(policy, env, method):
    rng = np.random.default_rng(6)
    first = envs.observation_vector(TASK, envs.reset_env(env, 0))
    calibration = (first + rng.normal(scale=0.05, size=(32, first.shape[0])), rng.uniform(-1, 1, size=(32, 7)))
    runner = PolicyRunner(policy, calibration)
    episode = run_episode(runner, TASK, f"{method}_w4a2", seed=1, env=env)
    assert set(episode.bits) == {2}
    assert_kernels_ran_the_published_widths(episode.to_dict())
    # The static rows and DyQ of one method run the very same INT4 model; its scales are not rtn's.
    assert runner.policy_for(run_config(f"{method}_w4a8")) is runner.policy_for(run_config(f"{method}_dyq"))
    a = runner.quantized_policy(method).model.model.layers[0].mlp.down_proj
    b = runner.quantized_policy("rtn").model.model.layers[0].mlp.down_proj
    assert not torch.equal(a.scales, b.scales)
    if method in ("awq", "gptq"):
        with pytest.raises(ValueError, match="calibration data"):
            PolicyRunner(policy).quantized_policy(method)
    with pytest.raises(ValueError, match="weights must be one of"):
        runner.quantized_policy("spinquant")


def test_every_weight_method_is_compared_against_round_to_nearest():
    from dyq.sim import rollout

    assert evaluate.WEIGHT_METHODS == rollout.WEIGHT_METHODS
    assert {(f"{m}_w4a2", "w4a2") for m in rollout.WEIGHT_METHODS} <= set(evaluate.COMPARISONS)


def test_summarize_only_names_the_figure_after_its_table_and_skips_a_task_without_episodes(tmp_path):
    import subprocess
    import sys

    cache, docs = tmp_path / "cache", tmp_path / "docs"
    docs.mkdir()
    command = [sys.executable, "-m", "dyq", "eval", "--tasks", "lift", "--configs", "fp32", "--episodes", "1",
               "--summarize-only", "--no-progress", "--cache", str(cache), "--out", str(tmp_path / "r.json"),
               "--table", str(docs / "closed_loop_perturbed.md")]
    first = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True)
    assert first.returncode == 0, first.stderr[-2000:]  # nothing cached yet: a table, no figure
    assert not list(docs.glob("figures/*.png"))
    digest = evaluate.checkpoint_digest(evaluate.default_checkpoint("lift"))
    evaluate._write_episode(evaluate.cache_path(cache, "lift", "fp32", 0, digest),
                            {"seed": 0, "success": True, "steps": 1, "bits": [16], "latency_ms": [1.0],
                             "prefill_kernel_bits": [{}], "decode_kernel_bits": [{}]})
    second = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True)
    assert second.returncode == 0, second.stderr[-2000:]
    # Rows written to another table must not overwrite the official table's figure, closed_loop_lift.png.
    assert [p.name for p in docs.glob("figures/*.png")] == ["closed_loop_perturbed_lift.png"]
    # The table names the JSON it was written from (relative to the working directory it lies under).
    assert "Written by `dyq eval` from `r.json`;" in (docs / "closed_loop_perturbed.md").read_text()
    assert "from `bench/results/closed_loop.json`" in evaluate.markdown_table({"tasks": {}})


@pytest.mark.parametrize("argv, message", [
    (["--tasks", "lift,stack"], "argument --tasks: unknown 'stack'; choose comma-separated names from lift,"),
    (["--tasks", "lift", "--configs", "fp32,w4a3"], "--configs: unknown configuration 'w4a3'"),
    (["--tasks", "lift", "--configs", ","], "--configs ',' names no configuration"),
    (["--tasks", "lift", "--checkpoint", "lift"], "argument --checkpoint: expected NAME=DIR, got 'lift'"),
    (["--tasks", "lift", "--checkpoint", "stack=."], "unknown 'stack' in 'stack=.'"),
    (["--tasks", "lift", "--checkpoint", "square=."], "'square' is not evaluated (tasks: ['lift'])"),
    (["--tasks", "lift", "--checkpoint", "lift={empty}"], "has no policy.json: train one with `dyq train lift`"),
])
def test_eval_refuses_bad_tasks_configs_and_checkpoints_in_one_line(argv, message, tmp_path, capsys):
    from dyq.apps import cli

    argv = [a.format(empty=tmp_path) for a in argv]
    assert cli.main(["eval", *argv, "--cache", str(tmp_path / "cache"), "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and message in err, err
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())
