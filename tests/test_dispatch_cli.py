import json

import numpy as np
import pytest

from dyq.control.dispatch import DispatchConfig, replay_trajectory, synthetic_trajectory
from dyq.apps import cli
from dyq.apps.dispatch_cli import load_trajectory, summarize


def main(argv):
    """`dyq dispatch ...`"""
    return cli.main(["dispatch", *argv])


def test_demo_then_replay_prints_a_summary_and_writes_the_plot_and_trace(tmp_path, capsys):
    trajectory, plot, trace_path = tmp_path / "traj.npz", tmp_path / "plot.png", tmp_path / "trace.json"
    assert main(["demo", str(trajectory), "--steps", "120", "--seed", "2"]) == 0
    assert main(["replay", str(trajectory), "--out", str(plot), "--json", str(trace_path)]) == 0
    printed = capsys.readouterr().out
    assert "switches" in printed and "bits  steps  share" in printed
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    record = json.loads(trace_path.read_text())
    expected = replay_trajectory(synthetic_trajectory(120, seed=2))
    assert record["trace"]["bits"] == expected["bits"].tolist()
    assert record["summary"] == json.loads(json.dumps(summarize(expected)))
    assert record["trace"]["sensitivity"][0] is None  # warm-up: NaN is written as null


def test_replay_uses_the_config_file(tmp_path, capsys):
    trajectory, config_path = tmp_path / "traj.npz", tmp_path / "cfg.json"
    actions = synthetic_trajectory(100, seed=4)
    np.savez(trajectory, actions=actions)
    config = DispatchConfig(hysteresis="window", delay_window=5, ladder=((0.1, 2), (0.2, 4), (0.3, 8)))
    config.save(config_path)
    trace_path = tmp_path / "trace.json"
    assert main(["replay", str(trajectory), "--config", str(config_path), "--json", str(trace_path)]) == 0
    assert "window, K = 5" in capsys.readouterr().out
    assert json.loads(trace_path.read_text())["trace"]["bits"] == replay_trajectory(actions, config)["bits"].tolist()


def test_config_command_writes_the_defaults(tmp_path):
    path = tmp_path / "cfg.json"
    assert main(["config", str(path)]) == 0
    assert DispatchConfig.load(path) == DispatchConfig()


def test_csv_with_and_without_header(tmp_path):
    actions = synthetic_trajectory(50)
    plain, headed = tmp_path / "plain.csv", tmp_path / "headed.csv"
    np.savetxt(plain, actions, delimiter=",")
    np.savetxt(headed, actions, delimiter=",", header="x,y,z,roll,pitch,yaw,gripper", comments="")
    np.testing.assert_allclose(load_trajectory(plain), actions)
    np.testing.assert_allclose(load_trajectory(headed), actions)


def test_npz_array_is_chosen_by_key(tmp_path):
    path = tmp_path / "traj.npz"
    np.savez(path, poses=np.ones((5, 7)), other=np.zeros((5, 7)))
    np.testing.assert_array_equal(load_trajectory(path, "poses"), np.ones((5, 7)))
    with pytest.raises(ValueError, match=r"choose the trajectory with --key, one of \['poses', 'other'\]"):
        load_trajectory(path)


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("traj.txt", "1,2,3", "expected a .npz or .csv trajectory"),
        ("flat.csv", "", "expected a \\(T, D\\) trajectory"),
    ],
)
def test_unreadable_trajectories_are_reported(tmp_path, capsys, name, content, message):
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(ValueError, match=message):
        load_trajectory(path)
    assert main(["replay", str(path)]) == 2
    assert "error:" in capsys.readouterr().err


@pytest.mark.parametrize("rows", ["1,2,3,4,5,6,7\nnan,0,0,0,0,0,0", "1,2,3\n4,5,6", "1,2,3,4,5,6,7\n1,2,3"])
def test_trajectories_the_dispatcher_refuses_are_one_line_errors(tmp_path, capsys, rows):
    """A NaN row, fewer than 6 columns, ragged rows: the user's file, not a bug."""
    path = tmp_path / "bad.csv"
    path.write_text(rows + "\n")
    assert main(["replay", str(path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "bad.csv" in err and "Traceback" not in err, err


@pytest.mark.parametrize("argv, message", [(["--steps", "5"], "--steps 5"), (["--seed", "-1"], "--seed -1")])
def test_demo_arguments_its_trajectory_refuses_are_one_line_errors(tmp_path, capsys, argv, message):
    assert main(["demo", str(tmp_path / "d.npz"), *argv]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and message in err and "Traceback" not in err, err
    assert not (tmp_path / "d.npz").exists()


def test_missing_file_exits_with_an_error(tmp_path, capsys):
    assert main(["replay", str(tmp_path / "missing.npz")]) == 2
    assert "missing.npz" in capsys.readouterr().err


def test_pose_input_can_be_chosen_on_the_command_line(tmp_path, capsys):
    path = tmp_path / "poses.npz"
    poses = np.cumsum(synthetic_trajectory(80), axis=0)
    np.savez(path, poses=poses)
    trace_path = tmp_path / "trace.json"
    assert main(["replay", str(path), "--input", "pose", "--json", str(trace_path)]) == 0
    record = json.loads(trace_path.read_text())
    assert record["config"]["input"] == "pose"
    assert record["trace"]["bits"] == replay_trajectory(poses, DispatchConfig(input="pose"))["bits"].tolist()


def test_python_dash_m_dyq_runs_the_command(tmp_path):
    import subprocess
    import sys

    path = tmp_path / "cfg.json"
    done = subprocess.run([sys.executable, "-m", "dyq", "dispatch", "config", str(path)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert DispatchConfig.load(path) == DispatchConfig()
