"""The simulation policy: action tokens, prompts, KV-cached greedy decoding, checkpoints and training."""
import json

import numpy as np
import pytest
import torch

pytest.importorskip("transformers")
pytest.importorskip("safetensors")

from dyq.errors import FileFormatError  # noqa: E402
from dyq.sim.policy import PolicyConfig, TokenPolicy  # noqa: E402
from dyq.sim.tokens import BINS, BinTokenizer, Vocabulary  # noqa: E402

OBS_DIMS = 9


def make_policy(seed=0, obs_dims=OBS_DIMS, layers=2):
    rng = np.random.default_rng(seed)
    observations = rng.normal(size=(200, obs_dims))
    actions = rng.uniform(-1.2, 1.2, size=(200, 7))
    config = PolicyConfig(task="lift", observation_names=[f"o{i}" for i in range(obs_dims)],
                          observation_tokenizer=BinTokenizer.range_with_margin(observations).to_dict(),
                          action_tokenizer=BinTokenizer.percentiles(actions).to_dict(),
                          hidden_size=128, intermediate_size=256, layers=layers, heads=2)
    torch.manual_seed(seed)
    return TokenPolicy(config), observations, actions


def test_action_tokens_round_trip_to_the_bin_centre():
    rng = np.random.default_rng(1)
    actions = rng.uniform(-1, 1, size=(1000, 7))
    tokenizer = BinTokenizer.percentiles(actions)
    np.testing.assert_allclose(tokenizer.low, np.percentile(actions, 1, axis=0))
    np.testing.assert_allclose(tokenizer.high, np.percentile(actions, 99, axis=0))
    inside = np.clip(actions, tokenizer.low, tokenizer.high)
    decoded = tokenizer.decode(tokenizer.encode(actions))
    width = (tokenizer.high - tokenizer.low) / BINS
    # Inside the percentiles the error is at most half a bin; outside, values clip to the edge bins.
    assert np.all(np.abs(decoded - inside) <= width / 2 + 1e-12)
    # Encoding a bin centre gives the same bin back.
    bins = rng.integers(0, BINS, size=(50, 7))
    np.testing.assert_array_equal(tokenizer.encode(tokenizer.decode(bins)), bins)


def test_bin_tokenizer_rejects_bad_shapes_and_indices():
    tokenizer = BinTokenizer(np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match="3 values"):
        tokenizer.encode(np.zeros(4))
    with pytest.raises(ValueError, match="bin indices"):
        tokenizer.decode(np.array([0, 256, 1]))
    with pytest.raises(ValueError, match="finite"):
        BinTokenizer(np.array([0.0, np.nan]), np.ones(2))


def test_a_constant_dimension_still_gets_a_range():
    tokenizer = BinTokenizer.range_with_margin(np.ones((10, 2)))
    assert np.all(tokenizer.high > tokenizer.low)
    assert tokenizer.encode(np.ones(2)).tolist() == [BINS // 2, BINS // 2]


def test_prompt_layout_puts_each_observation_dimension_in_its_own_bins():
    vocabulary = Vocabulary(tasks=("lift",), observation_dims=3)
    prompt = vocabulary.prefix("lift", np.array([0, 5, 255]))
    assert prompt.tolist() == [1, 2, 3, 3 + 256 + 5, 3 + 2 * 256 + 255]
    assert vocabulary.first_action == 3 + 3 * 256 and vocabulary.size == vocabulary.first_action + 256
    np.testing.assert_array_equal(vocabulary.action_bins(vocabulary.action_tokens([0, 7, 255])), [0, 7, 255])
    with pytest.raises(ValueError, match="task"):
        vocabulary.prefix("square", np.zeros(3, dtype=int))


def test_cached_greedy_decode_equals_decoding_without_a_cache():
    policy, observations, _ = make_policy()
    for observation in observations[:3]:
        bins = policy.decode(policy.prefill(observation))
        sequence = policy.prompt(observation)
        expected = []
        for _ in range(7):
            with torch.no_grad():
                logits = policy.model(input_ids=sequence).logits[0, -1]
            action_logits = logits[policy.vocabulary.first_action:]
            expected.append(int(action_logits.argmax()))
            sequence = torch.cat([sequence, torch.tensor([[expected[-1] + policy.vocabulary.first_action]])], 1)
        assert bins.tolist() == expected


def test_training_logits_match_the_decoding_positions():
    policy, observations, actions = make_policy()
    ids, targets = policy.sequences(observations[:4], actions[:4])
    assert ids.shape == (4, policy.vocabulary.prefix_length + 7) and targets.shape == (4, 7)
    with torch.no_grad():
        logits = policy.action_logits(ids)
        full = policy.model(input_ids=ids).logits
    p = policy.vocabulary.prefix_length
    torch.testing.assert_close(logits, full[:, p - 1: p + 6, policy.vocabulary.first_action:])


def test_checkpoint_round_trip_gives_identical_actions(tmp_path):
    policy, observations, _ = make_policy()
    # Round the weights to bf16 first: the checkpoint stores bf16, so the loaded policy matches exactly.
    with torch.no_grad():
        for p in policy.model.parameters():
            p.copy_(p.to(torch.bfloat16).float())
    policy.save(tmp_path / "ckpt")
    loaded = TokenPolicy.load(tmp_path / "ckpt")
    assert loaded.config == policy.config
    for observation in observations[:5]:
        np.testing.assert_array_equal(loaded.act(observation), policy.act(observation))


def test_loading_a_missing_checkpoint_names_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="policy.json"):
        TokenPolicy.load(tmp_path)


@pytest.mark.parametrize("damage", ["config not json", "config of unknown keys", "config of another policy",
                                    "weights not safetensors"])
def test_a_damaged_checkpoint_is_a_file_format_error_naming_it(tmp_path, damage):
    policy, _, _ = make_policy()
    checkpoint = policy.save(tmp_path / "ckpt")
    config_file = checkpoint / "policy.json"
    config = json.loads(config_file.read_text())
    if damage == "config not json":
        config_file.write_text(config_file.read_text()[:40])
    elif damage == "config of unknown keys":
        config_file.write_text(json.dumps({**config, "no_such_key": 1}))
    elif damage == "config of another policy":  # wider layers than the saved weights
        config_file.write_text(json.dumps({**config, "hidden_size": 2 * config["hidden_size"]}))
    else:
        (checkpoint / "model.safetensors").write_bytes(b"\x08\x00\x00\x00\x00\x00\x00\x00{}garbage")
    with pytest.raises(FileFormatError, match="ckpt"):
        TokenPolicy.load(checkpoint)


def test_widths_must_be_multiples_of_the_group_size():
    with pytest.raises(ValueError, match="hidden_size must be a multiple of 128"):
        PolicyConfig(task="lift", observation_names=["a"], observation_tokenizer={}, action_tokenizer={},
                     hidden_size=200)


def test_training_lowers_the_loss_and_resumes(tmp_path):
    h5py = pytest.importorskip("h5py")
    pytest.importorskip("tqdm")
    from dyq.sim.train import train

    rng = np.random.default_rng(0)
    path = tmp_path / "demos.hdf5"
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        for i in range(6):
            obs = rng.normal(size=(40, 4)).astype(np.float32)
            # A learnable rule: the action is a fixed function of the observation.
            actions = np.tanh(obs[:, [0, 1, 2, 3, 0, 1, 2]] * 2).astype(np.float32)
            demo = data.create_group(f"demo_{i}")
            demo.create_dataset("actions", data=actions)
            demo.create_group("obs").create_dataset("policy_vector", data=obs)
    kwargs = dict(steps=60, batch_size=32, lr=3e-3, hidden_size=128, intermediate_size=256, layers=1, heads=2,
                  save_every=30, validation_demos=1, progress=False)
    policy = train("lift", path, tmp_path / "a", **kwargs)
    first = policy.config.training["final_loss"]
    assert first < np.log(256) - 1.0  # well below a uniform guess over the 256 bins
    # Resuming a finished run changes nothing; a longer run continues from the saved state.
    resumed = train("lift", path, tmp_path / "a", **kwargs)
    for a, b in zip(policy.model.parameters(), resumed.model.parameters()):
        torch.testing.assert_close(a, b)


def _write_demos(h5py, path, observations, actions, names):
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["policy_vector_names"] = names
        for i, (obs, act) in enumerate(zip(observations, actions)):
            demo = data.create_group(f"demo_{i}")
            demo.create_dataset("actions", data=act)
            demo.create_group("obs").create_dataset("policy_vector", data=obs)


def test_demonstrations_from_several_files_are_their_concatenation(tmp_path):
    h5py = pytest.importorskip("h5py")
    from dyq.sim.train import load_demonstrations

    rng = np.random.default_rng(4)
    observations = [rng.normal(size=(int(rng.integers(5, 12)), 3)).astype(np.float32) for _ in range(5)]
    actions = [rng.normal(size=(len(o), 7)).astype(np.float32) for o in observations]
    names = ["a", "b", "c"]
    _write_demos(h5py, tmp_path / "one.hdf5", observations[:2], actions[:2], names)
    _write_demos(h5py, tmp_path / "two.hdf5", observations[2:], actions[2:], names)
    got_obs, got_act, got_names = load_demonstrations([tmp_path / "one.hdf5", tmp_path / "two.hdf5"])
    assert got_names == names and len(got_obs) == 5
    for got, want in zip(got_obs + got_act, observations + actions):
        np.testing.assert_array_equal(got, want)
    _write_demos(h5py, tmp_path / "other.hdf5", observations[:1], actions[:1], ["a", "b", "x"])
    with pytest.raises(ValueError, match="data: .*other.hdf5 has observations"):
        load_demonstrations([tmp_path / "one.hdf5", tmp_path / "other.hdf5"])
    with pytest.raises(ValueError, match="at least one"):
        load_demonstrations([])


def _damage_demonstrations(h5py, path, damage):
    """A demonstration file written by _write_demos, then damaged one way."""
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[:2000])
        return
    if damage == "not hdf5":
        path.write_bytes(np.random.default_rng(7).integers(0, 256, 3000, dtype=np.uint8).tobytes())
        return
    with h5py.File(path, "a") as f:
        data = f["data"]
        if damage == "no data group":
            del f["data"]
            f.create_group("other")
        elif damage == "demo without actions":
            del data["demo_1"]["actions"]
        elif damage == "demo without observations":
            del data["demo_0"]["obs"]["policy_vector"]
        elif damage == "a demo not numbered":
            data.move("demo_1", "demo_last")
        elif damage == "actions of 6 values":
            actions = data["demo_0"]["actions"][()]
            del data["demo_0"]["actions"]
            data["demo_0"].create_dataset("actions", data=actions[:, :6])
        elif damage == "fewer actions than observations":
            actions = data["demo_1"]["actions"][()]
            del data["demo_1"]["actions"]
            data["demo_1"].create_dataset("actions", data=actions[:-1])
        elif damage == "NaN in observations":
            data["demo_0"]["obs"]["policy_vector"][1, 2] = np.nan
        elif damage == "observations of another width":
            observations = data["demo_1"]["obs"]["policy_vector"][()]
            del data["demo_1"]["obs"]["policy_vector"]
            data["demo_1"]["obs"].create_dataset("policy_vector", data=observations[:, :2])
        elif damage == "names of another width":
            data.attrs["policy_vector_names"] = ["a", "b"]
        elif damage == "no demos":
            for name in list(data):
                del data[name]
        elif damage == "task names not json":
            data.attrs["task_names"] = "[lift"
        else:
            raise AssertionError(damage)


@pytest.mark.parametrize("damage", ["truncated", "not hdf5", "no data group", "demo without actions",
                                    "demo without observations", "a demo not numbered", "actions of 6 values",
                                    "fewer actions than observations", "NaN in observations",
                                    "observations of another width", "names of another width", "no demos",
                                    "task names not json"])
def test_a_damaged_demonstration_file_is_a_file_format_error_naming_it(tmp_path, damage):
    h5py = pytest.importorskip("h5py")
    from dyq.sim.train import load_demonstrations, task_names_of

    rng = np.random.default_rng(5)
    observations = [rng.normal(size=(int(rng.integers(5, 12)), 3)).astype(np.float32) for _ in range(3)]
    actions = [rng.normal(size=(len(o), 7)).astype(np.float32) for o in observations]
    path = tmp_path / "demos.hdf5"
    _write_demos(h5py, path, observations, actions, ["a", "b", "c"])
    got_obs, got_act, _ = load_demonstrations(path)  # intact, it loads
    np.testing.assert_array_equal(got_act[2], actions[2])
    _damage_demonstrations(h5py, path, damage)
    read = task_names_of if damage == "task names not json" else load_demonstrations
    with pytest.raises(FileFormatError, match="demos.hdf5"):
        read(path)


def test_train_reports_a_damaged_demonstration_file_in_one_line(tmp_path, capsys):
    h5py = pytest.importorskip("h5py")
    from dyq.apps.cli import main

    rng = np.random.default_rng(6)
    observations = [rng.normal(size=(8, 3)).astype(np.float32) for _ in range(3)]
    actions = [rng.normal(size=(8, 7)).astype(np.float32) for _ in range(3)]
    path = tmp_path / "demos.hdf5"
    _write_demos(h5py, path, observations, actions, ["a", "b", "c"])
    _damage_demonstrations(h5py, path, "truncated")
    assert main(["train", "lift", "--data", str(path), "--out", str(tmp_path / "out")]) != 0
    err = capsys.readouterr().err
    assert "demos.hdf5" in err and "not an HDF5 file" in err and "Traceback" not in err

