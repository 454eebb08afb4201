"""The main job, `dyq demo`, end to end on a short run."""
import json

import pytest

pytest.importorskip("transformers")

from dyq.apps import cli  # noqa: E402


def test_demo_runs_and_reports_every_precision(tmp_path, capsys):
    out = tmp_path / "demo.json"
    assert cli.main(["demo", "--steps", "14", "--prompt-tokens", "16", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    printed = capsys.readouterr().out
    assert "converted 28 linear layers" in printed and "model waited" in printed
    errors = {int(b): f["action_logit_rel_error"] for b, f in result["fidelity"].items()}
    # Fewer activation bits, larger error: the A16 fallback only carries the INT4 weight error.
    assert errors[2] > errors[4] > errors[16]
    assert result["control_loop"]["steps"] == 14
    assert sum(result["control_loop"]["steps_per_bits"].values()) == 14
    assert result["linear_bytes_after"] < 0.2 * result["linear_bytes_before"]
