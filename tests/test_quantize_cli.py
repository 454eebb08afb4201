"""``dyq quantize``: a local Hugging Face checkpoint in, one that from_pretrained loads as dyq's INT4 model out,
the same model quantize_model makes in memory."""
import numpy as np
import pytest
import torch
from packaging.version import Version

import dyq
from dyq.apps import cli
from dyq.core.serialization import from_pretrained_dtype
from helpers import hf_quantizer_unavailable

transformers = pytest.importorskip("transformers")
pytestmark = pytest.mark.skipif(hf_quantizer_unavailable() is not None, reason=f"{hf_quantizer_unavailable()}")

IDS = torch.randint(0, 256, (2, 7), generator=torch.Generator().manual_seed(0))


@pytest.fixture
def checkpoint(float_checkpoint):
    """conftest's float Llama, with a tokenizer file beside it."""
    (float_checkpoint / "tokenizer_config.json").write_text("{}")
    return float_checkpoint


def in_memory(checkpoint, **kwargs):
    model = transformers.LlamaForCausalLM.from_pretrained(checkpoint).eval()
    dyq.quantize_model(model, **kwargs)
    return model


@pytest.mark.parametrize("method", ["rtn", "gptq"])
def test_the_written_checkpoint_loads_as_the_model_quantize_model_makes(checkpoint, tmp_path, method, capsys):
    argv = ["quantize", str(checkpoint), str(tmp_path / "dyq"), "--group-size", "64", "--act-bits", "8",
            "--method", method]
    calibration = None
    if method == "gptq":
        ids = np.random.default_rng(1).integers(0, 256, size=(4, 16))
        np.save(tmp_path / "ids.npy", ids)
        argv += ["--calibration", str(tmp_path / "ids.npy")]
        calibration = torch.from_numpy(ids).long()
    assert cli.main(argv) == 0
    assert "converted 7 linear layers" in capsys.readouterr().out
    files = sorted(p.name for p in (tmp_path / "dyq").iterdir())
    assert "tokenizer_config.json" in files and "model.safetensors" in files
    loaded = transformers.LlamaForCausalLM.from_pretrained(tmp_path / "dyq")
    assert isinstance(loaded.model.layers[0].mlp.down_proj, dyq.DyQLinear)
    assert loaded.model.layers[0].mlp.down_proj.weight_method == method
    assert type(loaded.lm_head) is torch.nn.Linear and dyq.model_flag(loaded).bits == 8
    expected = in_memory(checkpoint, group_size=64, flag=dyq.PrecisionFlag(8), method=method,
                         calibration=calibration)
    with torch.no_grad():
        assert torch.equal(loaded(IDS).logits, expected(IDS).logits)


def test_dtype_bfloat16_keeps_what_stays_in_float_in_bf16(checkpoint, tmp_path):
    assert cli.main(["quantize", str(checkpoint), str(tmp_path / "dyq"), "--dtype", "bfloat16"]) == 0
    expected = transformers.LlamaForCausalLM.from_pretrained(
        checkpoint, **from_pretrained_dtype(torch.bfloat16)).eval()
    dyq.quantize_model(expected, flag=dyq.PrecisionFlag(16))
    if Version(transformers.__version__).major == 4:
        # transformers 4.x would load the fp32 group scales as bf16: refused, with the way out, which loads
        # exactly the saved INT4 layers.
        with pytest.raises(ValueError, match=r"group scales of 7 DyQLinear layers .* as torch\.bfloat16.*"
                                             r"dtype=torch\.float32"):
            transformers.LlamaForCausalLM.from_pretrained(tmp_path / "dyq", **from_pretrained_dtype("auto"))
        loaded = transformers.LlamaForCausalLM.from_pretrained(tmp_path / "dyq", **from_pretrained_dtype(torch.float32))
        for name, layer in expected.named_modules():
            if isinstance(layer, dyq.DyQLinear):
                saved = loaded.get_submodule(name)
                assert torch.equal(saved.qweight, layer.qweight) and torch.equal(saved.scales, layer.scales), name
        return
    loaded = transformers.LlamaForCausalLM.from_pretrained(tmp_path / "dyq", **from_pretrained_dtype("auto"))
    assert loaded.model.embed_tokens.weight.dtype == torch.bfloat16 and loaded.lm_head.weight.dtype == torch.bfloat16
    assert loaded.model.layers[0].self_attn.q_proj.scales.dtype == torch.float32
    with torch.no_grad():
        logits = loaded(IDS).logits
        assert logits.dtype == torch.bfloat16 and torch.equal(logits, expected(IDS).logits)


def test_mistakes_are_one_line_usage_errors(checkpoint, tmp_path, capsys):
    def error(*argv):
        assert cli.main(["quantize", *map(str, argv)]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        return err

    out = tmp_path / "out"
    assert "--method awq needs --calibration" in error(checkpoint, out, "--method", "awq")
    np.save(tmp_path / "floats.npy", np.zeros((2, 3), dtype=np.float32))
    assert "expected integer token ids of shape [batch, seq]" in error(checkpoint, out, "--method", "gptq",
                                                                       "--calibration", tmp_path / "floats.npy")
    assert "only used by --method awq and gptq" in error(checkpoint, out, "--calibration",
                                                         tmp_path / "floats.npy")
    assert "OUT must differ from SRC" in error(checkpoint, checkpoint)
    assert "has no config.json" in error(tmp_path, out)
    # A config no architecture matches, and a config without weights: SRC's faults, not bugs.
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "config.json").write_text("{}")
    assert "not a Hugging Face checkpoint transformers can load" in error(tmp_path / "empty", out)
    (tmp_path / "no_weights").mkdir()
    (tmp_path / "no_weights" / "config.json").write_text((checkpoint / "config.json").read_text())
    assert "not a Hugging Face checkpoint transformers can load" in error(tmp_path / "no_weights", out)
    assert not out.exists()
