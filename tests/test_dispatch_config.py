import dataclasses
import json
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dyq.control.dispatch import DispatchConfig, ProxyWeight, paper_ladder, paper_proxies
from dyq.errors import FileFormatError


def test_defaults_follow_the_paper_where_it_gives_values():
    config = DispatchConfig()
    assert config.macro_window == 10 and config.micro_window == 5
    assert config.theta_fp == 0.5
    assert config.percentile == 95.0
    assert config.theta_2_4 <= config.theta_4_8 <= config.theta_fp
    assert config.hysteresis == "counter"  # Algorithm 1 is the deployed form


def test_save_and_load_round_trip(tmp_path):
    config = DispatchConfig(fusion_weight=0.3, delay_window=5, hysteresis="window", xyz_slice=(1, 4), rot_slice=(4, 7))
    path = tmp_path / "cfg.json"
    config.save(path)
    assert DispatchConfig.load(path) == config
    assert json.loads(path.read_text())["xyz_slice"] == [1, 4]


def test_paper_symbols_are_accepted_as_keys():
    config = DispatchConfig.from_dict(
        {"lambda": 0.7, "K": 4, "W_macro": 12, "W_micro": 3, "theta_2|4": 0.1, "theta_4|8": 0.2, "theta_fp": 0.4}
    )
    assert (config.fusion_weight, config.delay_window, config.macro_window, config.micro_window) == (0.7, 4, 12, 3)
    assert (config.theta_2_4, config.theta_4_8, config.theta_fp) == (0.1, 0.2, 0.4)


def test_unknown_key_is_rejected_naming_it():
    with pytest.raises(ValueError, match="unknown config key 'lamda'"):
        DispatchConfig.from_dict({"lamda": 0.5})


def test_a_field_given_twice_is_rejected():
    with pytest.raises(ValueError, match="given twice"):
        DispatchConfig.from_dict({"K": 3, "delay_window": 4})


@pytest.mark.parametrize("content", [b"{not json", b"\x1f\x8b\x08 a gzip file"])
def test_invalid_json_file_is_rejected(tmp_path, content):
    path = tmp_path / "bad.json"
    path.write_bytes(content)
    with pytest.raises(FileFormatError, match="not valid JSON"):
        DispatchConfig.load(path)


def test_config_is_immutable():
    with pytest.raises(dataclasses.FrozenInstanceError):
        DispatchConfig().theta_fp = 0.9


def test_replace_validates_again():
    assert DispatchConfig().replace(delay_window=7).delay_window == 7
    with pytest.raises(ValueError, match="delay_window"):
        DispatchConfig().replace(delay_window=0)


BAD_VALUES = [
    ({"fusion_weight": -0.1}, ValueError, r"fusion_weight \(lambda\) must be in \[0, 1\]"),
    ({"fusion_weight": 1.5}, ValueError, r"fusion_weight \(lambda\) must be in \[0, 1\]"),
    ({"fusion_weight": math.nan}, ValueError, "fusion_weight must be finite"),
    ({"theta_2_4": 0.4, "theta_4_8": 0.3}, ValueError, "theta_2_4 <= theta_4_8 <= theta_fp"),
    ({"theta_4_8": 0.6, "theta_fp": 0.5}, ValueError, "theta_2_4 <= theta_4_8 <= theta_fp"),
    ({"theta_2_4": -0.1}, ValueError, "0 <= theta_2_4"),
    ({"theta_fp": math.inf}, ValueError, "theta_fp must be finite"),
    ({"theta_fp": "0.5"}, TypeError, "theta_fp must be a real number"),
    ({"delay_window": 0}, ValueError, "delay_window must be an int in \\[1, "),
    ({"delay_window": 2.0}, TypeError, "delay_window must be an int"),
    ({"delay_window": True}, TypeError, "delay_window must be an int"),
    ({"macro_window": 0}, ValueError, "macro_window must be an int in \\[1, "),
    ({"micro_window": -1}, ValueError, "micro_window must be an int in \\[1, "),
    ({"percentile": 0.0}, ValueError, r"percentile must be in \(0, 100\]"),
    ({"percentile": 100.5}, ValueError, r"percentile must be in \(0, 100\]"),
    ({"percentile": 10**400}, ValueError, "percentile must be finite, got an int beyond float64's range"),
    ({"history": 0}, ValueError, "history must be an int in \\[1, "),
    ({"warmup": 0}, ValueError, "warmup must be an int in \\[1, "),
    ({"history": 8, "warmup": 9}, ValueError, r"warmup must be <= history \(8\)"),
    ({"ladder": ((0.4, 2), (0.3, 4))}, ValueError, "ladder thresholds must be >= 0 and ascending"),
    ({"hysteresis": "sliding"}, ValueError, "hysteresis must be one of"),
    ({"input": "joints"}, ValueError, "input must be one of"),
    ({"xyz_slice": (3, 3)}, ValueError, "xyz_slice must satisfy 0 <= start < stop"),
    ({"rot_slice": (-1, 2)}, ValueError, r"rot_slice\[0\] must be an int in \[0, 4095\]"),
    ({"rot_slice": (3, 4, 5)}, TypeError, r"rot_slice must be a pair \(start, stop\)"),
    ({"xyz_slice": "0:3"}, TypeError, r"xyz_slice must be a pair \(start, stop\)"),
]


@pytest.mark.parametrize("changes, error, message", BAD_VALUES)
def test_bad_configuration_is_rejected_naming_the_argument(changes, error, message):
    with pytest.raises(error, match=message):
        DispatchConfig(**changes)


@pytest.mark.parametrize("changes, error, message", BAD_VALUES)
def test_bad_configuration_file_is_rejected_too(tmp_path, changes, error, message):
    # In a file, every bad value is the file's fault: a FileFormatError naming it, whatever from_dict raises.
    data = {**DispatchConfig().to_dict(), **changes}
    data = {k: list(v) if isinstance(v, tuple) else v for k, v in data.items()}
    path = tmp_path / "cfg.json"
    path.write_text(json.dumps(data))  # NaN and Infinity are written as JSON extensions
    with pytest.raises(FileFormatError, match=message) as raised:
        DispatchConfig.load(path)
    assert str(path) in str(raised.value)


def test_min_length_covers_both_slices():
    assert DispatchConfig().min_length == 6
    assert DispatchConfig(xyz_slice=(0, 3), rot_slice=(6, 10)).min_length == 10


valid_configs = st.builds(
    lambda lam, thresholds, k, macro, micro, pct, history, warm, mode, kind: DispatchConfig(
        fusion_weight=lam,
        theta_2_4=thresholds[0],
        theta_4_8=thresholds[1],
        theta_fp=thresholds[2],
        delay_window=k,
        macro_window=macro,
        micro_window=micro,
        percentile=pct,
        history=history,
        warmup=min(warm, history),
        hysteresis=mode,
        input=kind,
    ),
    st.floats(0, 1),
    st.lists(st.floats(0, 10), min_size=3, max_size=3).map(sorted),
    st.integers(1, 20),
    st.integers(1, 50),
    st.integers(1, 50),
    st.floats(0.1, 100),
    st.integers(1, 4096),
    st.integers(1, 100),
    st.sampled_from(["window", "counter", "none"]),
    st.sampled_from(["action", "pose"]),
)


@given(valid_configs)
def test_any_valid_config_survives_json(config):
    assert DispatchConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config


def test_the_default_is_the_paper_pair_and_ladder():
    config = DispatchConfig()
    assert config.proxies == (ProxyWeight("motion_fineness", 0.5, 10), ProxyWeight("angular_jerk", 0.5, 5))
    assert config.ladder == ((0.15, 2), (0.3, 4), (0.5, 8)) and config.is_paper_form


def test_paper_values_edit_the_proxies_and_the_ladder():
    config = DispatchConfig(fusion_weight=0.7, macro_window=12, theta_4_8=0.2, theta_fp=0.4)
    assert config.proxies == paper_proxies(0.7, 12, 5)
    assert config.ladder == paper_ladder(0.15, 0.2, 0.4)
    assert config.replace(theta_2_4=0.1).ladder == paper_ladder(0.1, 0.2, 0.4)


def test_a_file_written_before_the_ladder_loads_and_paper_configs_are_written_the_same_way(tmp_path):
    old = {"fusion_weight": 0.3, "theta_fp": 0.5, "theta_2_4": 0.15, "theta_4_8": 0.3, "delay_window": 3,
           "macro_window": 10, "micro_window": 5, "percentile": 95.0, "history": 256, "warmup": 10,
           "hysteresis": "counter", "input": "action", "xyz_slice": [0, 3], "rot_slice": [3, 6]}
    path = tmp_path / "old.json"
    path.write_text(json.dumps(old))
    config = DispatchConfig.load(path)
    assert config == DispatchConfig(proxies=paper_proxies(0.3))
    assert config.to_dict() == old


def test_a_theta_of_none_removes_that_rung_and_survives_json():
    config = DispatchConfig(fusion_weight=0.2, theta_2_4=None, theta_4_8=0.2, theta_fp=0.4)
    assert config.ladder == ((0.2, 4), (0.4, 8)) and config.is_paper_form
    data = json.loads(json.dumps(config.to_dict()))
    assert data["theta_2_4"] is None and DispatchConfig.from_dict(data) == config
    assert DispatchConfig.from_dict({"lambda": 0.2, "theta_2|4": None, "theta_4|8": 0.2, "theta_fp": 0.4}) == config
    assert config.replace(theta_2_4=None) == config  # removing a missing rung changes nothing
    with pytest.raises(ValueError, match="theta_2_4 is the threshold of the 2-bit rung"):
        config.replace(theta_2_4=0.1)


def test_a_single_proxy_and_a_custom_ladder_survive_json():
    config = DispatchConfig(proxies=(ProxyWeight("angular_jerk", 1.0, 5),), ladder=((0.4, 4),))
    assert not config.is_paper_form and config.weight("motion_fineness") == 0.0
    assert math.isnan(config.theta_2_4) and config.theta_4_8 == 0.4 == config.theta_fp
    assert DispatchConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config


BAD_LADDERS_AND_PROXIES = [
    ({"proxies": ()}, TypeError, "proxies must be a non-empty sequence"),
    ({"proxies": (ProxyWeight("motion_fineness", 0.5, 10),)}, ValueError, "proxy weights must be convex"),
    ({"proxies": paper_proxies(0.5)[:1] * 2}, ValueError, "proxies must name each proxy once"),
    ({"proxies": (("wrist_speed", 1.0, 3),)}, ValueError, "proxy name must be one of"),
    ({"proxies": (("motion_fineness", 1.5, 10), ("angular_jerk", -0.5, 5))}, ValueError, "proxy weights must be convex"),
    ({"proxies": (("motion_fineness", 1.0, 0),)}, ValueError, "motion_fineness window must be an int in \\[1, 4096\\]"),
    ({"proxies": (("angular_jerk", 1.0, 5),), "fusion_weight": 0.5}, ValueError, "fusion_weight \\(lambda\\) weighs"),
    ({"proxies": (("angular_jerk", 1.0, 5),), "macro_window": 4}, ValueError, "macro_window is the window of motion"),
    ({"ladder": ()}, TypeError, "ladder must be a non-empty sequence"),
    ({"ladder": ((-0.1, 2),)}, ValueError, "ladder thresholds must be >= 0"),
    ({"ladder": ((0.1, 4), (0.3, 4))}, ValueError, "ladder bits must increase strictly"),
    ({"ladder": ((0.1, 8), (0.3, 4))}, ValueError, "ladder bits must increase strictly"),
    ({"ladder": ((0.1, 16),)}, ValueError, r"ladder\[0\] bits must be a quantized width"),
    ({"ladder": ((0.1, 3),)}, ValueError, r"ladder\[0\] bits must be one of"),
    ({"ladder": ((math.inf, 2),)}, ValueError, r"ladder\[0\] threshold must be finite"),
    ({"ladder": ((0.1, 2, 3),)}, TypeError, r"ladder\[0\] must be a pair"),
    ({"ladder": ((0.1, 8),), "theta_2_4": 0.05}, ValueError, "theta_2_4 is the threshold of the 2-bit rung"),
    ({"smoothing": 3}, TypeError, "unexpected keyword argument 'smoothing'"),
]


@pytest.mark.parametrize("changes, error, message", BAD_LADDERS_AND_PROXIES)
def test_bad_ladders_and_proxies_are_rejected_naming_them(changes, error, message):
    with pytest.raises(error, match=message):
        DispatchConfig(**changes)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"history": 10**9}, r"history must be an int in \[1, 65536\]"),
        ({"warmup": 10**9, "history": 10**9}, "history must be an int in"),
        ({"delay_window": 10**9}, r"delay_window must be an int in \[1, 4096\]"),
        ({"macro_window": 10**9}, r"macro_window must be an int in \[1, 4096\]"),
        ({"xyz_slice": (0, 10**9)}, r"xyz_slice\[1\] must be an int in \[1, 4096\]"),
    ],
)
def test_absurd_sizes_are_rejected_before_anything_is_allocated(kwargs, message):
    with pytest.raises(ValueError, match=message):
        DispatchConfig(**kwargs)
