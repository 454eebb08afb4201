"""The main job, `dyq demo`: the shipped Lift policy in closed loop, DyQ against fp32."""
import pytest

pytest.importorskip("robosuite")
pytest.importorskip("transformers")

from dyq.apps import cli  # noqa: E402
from dyq.sim.evaluate import default_checkpoint  # noqa: E402


def test_demo_runs_closed_loop_episodes_and_draws_the_dispatcher(tmp_path, capsys):
    assert (default_checkpoint("lift") / "model.safetensors").is_file(), "the Lift policy ships with dyq"
    plot = tmp_path / "episode.png"
    assert cli.main(["demo", "--episodes", "1", "--plot", str(plot), "--threads", "1"]) == 0
    printed = capsys.readouterr().out
    assert "converted 28 linear layers" in printed
    for line in ("fp32", "dyq", "DyQ's widths", " 2 bits:", "16 bits:"):
        assert line in printed
    assert plot.stat().st_size > 10_000
