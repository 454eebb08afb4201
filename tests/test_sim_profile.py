"""dyq profile / dyq calibrate: the replay restores the reference exactly, a full-precision perturbation
changes nothing, results are cached and resumed, calibration writes a config the dispatcher loads, and
bad command lines are refused clearly.

The policy is untrained, so it never lifts the cube: the task's success test is replaced by "reached
step SUCCESS_STEP", which makes every episode a successful reference of that length."""
import json

import numpy as np
import pytest
import torch

pytest.importorskip("robosuite")
pytest.importorskip("transformers")

import dyq  # noqa: E402
from dyq.analysis import dispatch_trace  # noqa: E402
from dyq.apps import cli  # noqa: E402
from dyq.sim import envs  # noqa: E402
from dyq.sim import profile as prof  # noqa: E402
from dyq.sim.rollout import PolicyRunner, run_episode  # noqa: E402
from sim_helpers import untrained_policy  # noqa: E402

TASK = "lift"
HORIZON = 20
SUCCESS_STEP = 15


@pytest.fixture(scope="module", autouse=True)
def short_successful_task():
    spec = envs.TASKS[TASK]
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(envs.TASKS, TASK, envs.TaskSpec(spec.env_name, HORIZON, spec.object_key, spec.yaw_period))
        patch.setattr(envs, "check_success", lambda env: env.timestep >= SUCCESS_STEP)
        yield


@pytest.fixture(scope="module")
def env():
    return envs.make_env(TASK, horizon=HORIZON)


@pytest.fixture(scope="module")
def policy(env):
    policy = untrained_policy(TASK, env)
    with torch.no_grad():  # bf16-exact, so the saved checkpoint is the same policy
        for p in policy.model.parameters():
            p.copy_(p.to(torch.bfloat16).float())
    return policy


@pytest.fixture(scope="module")
def runner(policy):
    return PolicyRunner(policy)


@pytest.fixture(scope="module")
def reference(runner, env):
    return prof.reference_episode(runner, TASK, prof.CALIBRATION_SEEDS[0], env)


@pytest.fixture(scope="module")
def checkpoint(policy, tmp_path_factory):
    return policy.save(tmp_path_factory.mktemp("policy") / "lift")


def test_reference_is_a_seeded_full_precision_episode(runner, env, reference):
    assert reference.success and reference.steps == SUCCESS_STEP
    again = prof.reference_episode(runner, TASK, reference.seed, env)
    np.testing.assert_array_equal(again.actions, reference.actions)
    np.testing.assert_array_equal(again.final_object, reference.final_object)
    assert np.all(np.abs(reference.actions) <= 1.0)
    assert prof.Reference.from_dict(json.loads(json.dumps(reference.to_dict()))).to_dict() == reference.to_dict()


def test_replay_restores_every_step_exactly(env, reference):
    for t in (0, 1, reference.steps // 2, reference.steps - 1):
        obs = prof.restore(env, reference, t)
        np.testing.assert_array_equal(envs.observation_vector(TASK, obs), reference.observations[t])
    obs = prof.restore(env, reference, reference.steps - 1)
    obs, _, _, _ = envs.step_env(env, reference.actions[-1])
    np.testing.assert_array_equal(obs["robot0_eef_pos"], reference.final_eef)
    np.testing.assert_array_equal(envs.object_pos(TASK, obs), reference.final_object)
    with pytest.raises(ValueError, match="t must be in"):
        prof.restore(env, reference, reference.steps)


def test_replay_refuses_a_reference_it_cannot_reproduce(env, reference):
    other = prof.Reference.from_dict(reference.to_dict())
    other.observations[3] += 1.0
    with pytest.raises(RuntimeError, match="did not reproduce"):
        prof.restore(env, other, 3)


def test_full_precision_perturbation_changes_nothing(runner, env, reference):
    for t in (0, reference.steps // 2):
        result = prof.perturb(runner, reference, t, 16, env)
        assert result.action_error == 0.0 and result.terminal_deviation == 0.0
        assert result.success == reference.success


def test_low_width_perturbation_error_is_the_teacher_forced_error(runner, env, reference):
    errors = prof.teacher_forced_errors(runner, reference, widths=(2,))[2]
    t = int(np.flatnonzero(errors > 0)[0])
    result = prof.perturb(runner, reference, t, 2, env)
    assert result.action_error == errors[t]
    assert result.terminal_deviation > 0.0 and result.simulated


def test_proxy_trace_is_what_the_dispatcher_saw(reference):
    trace = prof.proxy_trace(reference.actions)
    S, _ = dispatch_trace(reference.actions, dyq.DispatchConfig())
    np.testing.assert_array_equal(trace["fused_sensitivity"], S)
    assert np.isnan(trace["motion_fineness"][0]) and np.isfinite(trace["motion_fineness"][-1])


def test_proxy_trace_is_what_the_closed_loop_dispatcher_saw(runner, env):
    episode = run_episode(runner, TASK, "dyq", seed=7, env=env)
    trace = prof.proxy_trace(episode.actions, prime=prof._prime(runner))
    # The episode logs actions rounded to 6 decimals; the dispatcher saw them unrounded.
    np.testing.assert_allclose(trace["fused_sensitivity"], episode.sensitivity, rtol=1e-3, atol=1e-4)


def test_primed_proxy_trace_is_what_the_primed_closed_loop_dispatcher_saw(policy, env):
    pytest.importorskip("dyq.sim.dispatch_budget")  # checkpoints that prime the dispatcher
    prime = np.random.default_rng(1).uniform(-1, 1, size=(300, 7))
    primed = PolicyRunner(policy, None, (dyq.DispatchConfig(), prime))
    episode = run_episode(primed, TASK, "dyq", seed=7, env=env)
    trace = prof.proxy_trace(episode.actions, prime=prof._prime(primed))
    assert np.isfinite(trace["fused_sensitivity"][2]), "a primed dispatcher has no warm-up"
    np.testing.assert_allclose(trace["fused_sensitivity"], episode.sensitivity, rtol=1e-3, atol=1e-4)


def test_profile_is_resumed_from_its_cache(runner, env, tmp_path, monkeypatch):
    store = prof.Store(tmp_path, TASK, "digest")
    budget = prof.ProfileBudget(episodes=1, widths=(4,), strides=(7,))
    first = prof.profile(runner, TASK, store, budget, env, progress=False)
    assert [(r.t, r.act_bits) for r in first["records"]] == [(0, 4), (7, 4), (14, 4)]
    assert first["simulated"] + first["zero_error"] == 3

    def no_simulation(*args, **kwargs):
        raise AssertionError("a cached step was simulated again")

    monkeypatch.setattr(prof, "perturb", no_simulation)
    monkeypatch.setattr(prof, "reference_episode", no_simulation)
    again = prof.profile(runner, TASK, store, budget, env, progress=False)
    assert repr(again["records"]) == repr(first["records"])  # repr: NaN proxies of the warm-up compare equal


def test_profile_and_calibrate_commands_write_results_and_a_loadable_config(checkpoint, tmp_path):
    common = ["--checkpoint", str(checkpoint), "--cache", str(tmp_path / "cache"), "--figures", str(tmp_path),
              "--no-progress"]
    profile_json, config_json = tmp_path / "profile.json", tmp_path / "dispatch.json"
    assert cli.main(["profile", TASK, "--episodes", "2", "--stride", "2", "--widths", "4",
                     "--out", str(profile_json), *common]) == 0
    profiled = json.loads(profile_json.read_text())
    for key in ("pearson_motion_fineness", "pearson_angular_jerk", "pearson_fused", "spearman_motion_fineness",
                "spearman_angular_jerk", "spearman_fused", "episodes", "steps"):
        assert key in profiled
    assert profiled["seeds"] == [5000, 5001] and profiled["budget"] == {"episodes": 2, "widths": [4], "strides": [2]}
    assert (tmp_path / "profile_lift_fig2.png").stat().st_size > 0

    assert cli.main(["calibrate", TASK, "--episodes", "2", "--theta-fp", "0.2,0.9", "--profile", str(profile_json),
                     "--out", str(tmp_path / "calibration.json"), "--config-out", str(config_json), *common]) == 0
    config = dyq.DispatchConfig.load(config_json)
    calibration = json.loads((tmp_path / "calibration.json").read_text())
    assert config.theta_fp == calibration["theta_fp"]["theta_fp"] in (0.2, 0.9)
    assert config.theta_2_4 <= config.theta_4_8 <= config.theta_fp
    assert config.fusion_weight == calibration["lambda"]["value"] and config.delay_window == calibration["K"]["value"]
    assert [row["theta_fp"] for row in calibration["theta_fp"]["sweep"]] == [0.2, 0.9]
    assert (tmp_path / "calibration_lift_theta_fp.png").stat().st_size > 0
    run = prof.calibrated_run_config(TASK, config_json)
    assert run.name == "dyq_calibrated" and run.dispatch_config() == config
    # Checked against the checkpoint it was calibrated on, when the record sits beside the config.
    from dyq.sim.evaluate import checkpoint_digest

    digest = checkpoint_digest(checkpoint)
    assert calibration["checkpoint_digest"] == digest
    (tmp_path / "calibration_lift.json").write_text((tmp_path / "calibration.json").read_text())
    assert prof.calibrated_run_config(TASK, config_json, checkpoint_digest=digest).dispatch_config() == config
    with pytest.raises(ValueError, match="not on the evaluated checkpoint 000000000000"):
        prof.calibrated_run_config(TASK, config_json, checkpoint_digest="000000000000")


@pytest.mark.parametrize("argv, message", [
    (["profile", "stack"], "invalid choice: 'stack'"),
    (["profile", TASK, "--widths", "3"], "expected comma-separated widths"),
    (["profile", TASK, "--stride", "0"], "expected a stride >= 1"),
    (["profile", TASK, "--episodes", "x"], "expected an integer"),
    (["profile", TASK, "--checkpoint", "/no/such/folder"], "no such folder"),
    (["calibrate", TASK, "--theta-fp", "0.5,-1"], "expected comma-separated thresholds"),
    (["calibrate", TASK, "--profile", "/no/such/profile.json"], "no such file"),
])
def test_bad_arguments_are_refused_by_the_parser(argv, message, capsys):
    assert cli.main(argv) == 2  # the dyq command's one-line usage error (dyq.apps.usage)
    assert message in capsys.readouterr().err


def test_missing_inputs_are_reported(checkpoint, tmp_path, capsys, monkeypatch):
    def error(argv):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        return err

    assert "--stride must give one stride or one per width [4]" in error(["profile", TASK, "--widths", "4",
                                                                          "--stride", "1,2"])
    assert "has no policy.json" in error(["profile", TASK, "--checkpoint", str(tmp_path)])
    monkeypatch.setattr(prof, "RESULTS", tmp_path)  # where the default profile would be
    assert "run `dyq profile lift` first" in error(["calibrate", TASK, "--checkpoint", str(checkpoint)])
    with pytest.raises(FileNotFoundError, match="run `dyq calibrate lift` first"):
        prof.calibrated_run_config(TASK, tmp_path / "none.json")


def test_every_task_the_commands_take_has_a_profile_budget():
    # `dyq profile` and `dyq calibrate` take every task, the LIBERO suites included: each needs a budget.
    assert set(prof.PROFILE_BUDGETS) == set(envs.ALL_TASKS)
    for task, budget in prof.PROFILE_BUDGETS.items():
        assert budget.episodes >= 1 and all(width in prof.QUANTIZED_WIDTHS for width in budget.widths), task


def test_every_task_the_commands_take_has_a_success_tolerance():
    # `dyq calibrate` turns the measured sensitivity into Eq. 5's bound through the task's tolerance.
    assert set(prof.SUCCESS_TOLERANCE) == set(envs.ALL_TASKS)
    assert all(0 < tolerance < 0.1 for tolerance in prof.SUCCESS_TOLERANCE.values())
