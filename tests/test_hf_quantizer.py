"""dyq through transformers' quantizer interface: quantize on load, save_pretrained / from_pretrained
round trips, on Llama models built from configs (no download). The interface is transformers 5.x's
(custom quantizers registered with register_quantization_config / register_quantizer)."""
import pytest
import torch

import dyq
from helpers import hf_quantizer_unavailable

transformers = pytest.importorskip("transformers")
pytestmark = pytest.mark.skipif(hf_quantizer_unavailable() is not None, reason=f"{hf_quantizer_unavailable()}")


IDS = torch.randint(0, 256, (2, 7), generator=torch.Generator().manual_seed(0))


def test_from_pretrained_with_a_dyq_config_quantizes_on_load(float_checkpoint):
    model = transformers.LlamaForCausalLM.from_pretrained(
        float_checkpoint, quantization_config=dyq.DyQConfig(group_size=128, act_bits=8))
    layers = [m for m in model.modules() if isinstance(m, dyq.DyQLinear)]
    assert len(layers) == 7 and type(model.lm_head) is torch.nn.Linear  # every Linear but the LM head
    assert dyq.model_flag(model).bits == 8
    reference = transformers.LlamaForCausalLM.from_pretrained(float_checkpoint)
    dyq.quantize_model(reference, group_size=128, act_bits=8, flag=dyq.PrecisionFlag(8))
    with torch.no_grad():
        assert torch.equal(model(IDS).logits, reference(IDS).logits)


def test_save_pretrained_and_from_pretrained_round_trip_a_dyq_model(float_checkpoint, tmp_path):
    model = transformers.LlamaForCausalLM.from_pretrained(
        float_checkpoint, quantization_config=dyq.DyQConfig(group_size=64, act_bits=4))
    model.save_pretrained(tmp_path / "dyq")
    loaded = transformers.LlamaForCausalLM.from_pretrained(tmp_path / "dyq")
    assert isinstance(loaded.config.quantization_config, dyq.DyQConfig)
    assert loaded.model.layers[0].mlp.down_proj.group_size == 64 and dyq.model_flag(loaded).bits == 4
    with torch.no_grad():
        assert torch.equal(loaded(IDS).logits, model(IDS).logits)
    dyq.set_precision(loaded, 16)  # the loaded model's one flag switches it
    with torch.no_grad():
        assert not torch.equal(loaded(IDS).logits, model(IDS).logits)


def test_the_config_has_room_for_later_options_and_checks_them():
    config = dyq.DyQConfig()
    assert config.to_dict()["weight_method"] == "rtn_int4_symmetric" and config.to_dict()["rotation"] is None
    for rotation in ("hadamard", {"kind": "hadamard", "seed": -1, "construction": 2},
                     {"kind": "givens", "seed": 0, "construction": 2}, {"kind": "hadamard", "seed": 0}):
        with pytest.raises(ValueError, match="rotation must be None or a rotated model's description"):
            dyq.DyQConfig(rotation=rotation)
    with pytest.raises(ValueError, match="group_size must be one of"):
        dyq.DyQConfig(group_size=100)


def test_a_gpt2_with_conv1d_layers_quantizes_on_load_and_round_trips(tmp_path):
    config = transformers.GPT2Config(vocab_size=256, n_embd=128, n_layer=1, n_head=4, n_positions=32)
    torch.manual_seed(0)
    transformers.GPT2LMHeadModel(config).save_pretrained(tmp_path / "float")
    model = transformers.GPT2LMHeadModel.from_pretrained(tmp_path / "float",
                                                         quantization_config=dyq.DyQConfig(group_size=64, act_bits=8))
    block = model.transformer.h[0]
    layers = [block.attn.c_attn, block.attn.c_proj, block.mlp.c_fc, block.mlp.c_proj]
    assert all(isinstance(m, dyq.DyQLinear) for m in layers) and type(model.lm_head) is torch.nn.Linear
    reference = transformers.GPT2LMHeadModel.from_pretrained(tmp_path / "float")
    dyq.quantize_model(reference, group_size=64, flag=dyq.PrecisionFlag(8))
    with torch.no_grad():
        assert torch.equal(model(IDS).logits, reference(IDS).logits)
    model.save_pretrained(tmp_path / "dyq")
    loaded = transformers.GPT2LMHeadModel.from_pretrained(tmp_path / "dyq")
    assert isinstance(loaded.transformer.h[0].mlp.c_fc, dyq.DyQLinear)
    with torch.no_grad():
        assert torch.equal(loaded(IDS).logits, model(IDS).logits)


def tied_llama_checkpoint(tmp_path):
    config = transformers.LlamaConfig(vocab_size=256, hidden_size=128, intermediate_size=256, num_hidden_layers=1,
                                      num_attention_heads=4, num_key_value_heads=2, tie_word_embeddings=True)
    torch.manual_seed(1)
    transformers.LlamaForCausalLM(config).save_pretrained(tmp_path / "tied")
    return tmp_path / "tied"


def test_a_tied_lm_head_converted_on_load_saves_untied_and_loads_back(tmp_path):
    model = transformers.LlamaForCausalLM.from_pretrained(
        tied_llama_checkpoint(tmp_path), quantization_config=dyq.DyQConfig(group_size=32, modules_to_not_convert=[]))
    assert isinstance(model.lm_head, dyq.DyQLinear) and not model.config.tie_word_embeddings
    model.save_pretrained(tmp_path / "dyq")
    loaded = transformers.LlamaForCausalLM.from_pretrained(tmp_path / "dyq")
    assert isinstance(loaded.lm_head, dyq.DyQLinear)
    with torch.no_grad():
        assert torch.equal(loaded(IDS).logits, model(IDS).logits)


def test_modules_to_not_convert_that_do_not_match_the_checkpoint_are_refused(float_checkpoint, tmp_path):
    """Edited after saving, the list would leave INT4 shells unfilled (NaN or huge logits) or float layers on
    random weights; a single name is one pattern, not its characters."""
    import json

    assert dyq.DyQConfig(modules_to_not_convert="lm_head").modules_to_not_convert == ["lm_head"]
    with pytest.raises(TypeError, match="modules_to_not_convert must be layer names"):
        dyq.DyQConfig(modules_to_not_convert=[b"lm_head"])
    model = transformers.LlamaForCausalLM.from_pretrained(float_checkpoint, quantization_config=dyq.DyQConfig())
    model.save_pretrained(tmp_path / "dyq")
    config_path = tmp_path / "dyq" / "config.json"
    saved = json.loads(config_path.read_text())
    for edited in ([], ["nothing_here"], ["lm_head", "down_proj"]):
        saved["quantization_config"]["modules_to_not_convert"] = edited
        config_path.write_text(json.dumps(saved))
        with pytest.raises(ValueError, match="does not match the checkpoint"):
            transformers.LlamaForCausalLM.from_pretrained(tmp_path / "dyq")


def test_import_dyq_alone_registers_the_quantizer_for_from_pretrained(float_checkpoint, tmp_path):
    """A program that imports dyq, not dyq.DyQConfig, and then loads a dyq checkpoint gets its INT4 layers
    (unregistered, transformers skips the method and loads float layers of random weights)."""
    import subprocess
    import sys

    model = transformers.LlamaForCausalLM.from_pretrained(float_checkpoint, quantization_config=dyq.DyQConfig())
    model.save_pretrained(tmp_path / "dyq")
    with torch.no_grad():
        torch.save(model(IDS).logits, tmp_path / "logits.pt")
    torch.save(IDS, tmp_path / "ids.pt")
    script = (
        "import sys, torch, dyq, transformers\n"
        f"m = transformers.LlamaForCausalLM.from_pretrained({str(tmp_path / 'dyq')!r})\n"
        "assert type(m.model.layers[0].mlp.down_proj).__name__ == 'DyQLinear', type(m.model.layers[0].mlp.down_proj)\n"
        f"ids = torch.load({str(tmp_path / 'ids.pt')!r})\n"
        "with torch.no_grad():\n"
        f"    assert torch.equal(m(ids).logits, torch.load({str(tmp_path / 'logits.pt')!r}))\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]


def test_save_pretrained_after_quantize_model_loads_back(float_checkpoint, tmp_path):
    """quantize_model sets the config that from_pretrained rebuilds the model from: without it the checkpoint
    loads as float layers of random weights, with only a load report to say so."""
    model = transformers.LlamaForCausalLM.from_pretrained(float_checkpoint)
    dyq.quantize_model(model, group_size=64, flag=dyq.PrecisionFlag(8))
    config = model.config.quantization_config
    assert isinstance(config, dyq.DyQConfig)
    assert (config.group_size, config.act_bits, config.modules_to_not_convert, config.min_act_bits) == \
        (64, 8, ["lm_head"], None)
    model.save_pretrained(tmp_path / "dyq")
    loaded = transformers.LlamaForCausalLM.from_pretrained(tmp_path / "dyq")
    assert sum(isinstance(m, dyq.DyQLinear) for m in loaded.modules()) == 7
    assert type(loaded.lm_head) is torch.nn.Linear and dyq.model_flag(loaded).bits == 8
    with torch.no_grad():
        assert torch.equal(loaded(IDS).logits, model(IDS).logits)


def test_the_saved_config_names_the_layers_where_the_patterns_cannot(float_checkpoint, tmp_path):
    """A compiled regular expression does not fit a JSON config: the float layers' full names stand in
    for it. The floors of min_act_bits load back with the layers."""
    import re

    model = transformers.LlamaForCausalLM.from_pretrained(float_checkpoint)
    dyq.quantize_model(model, group_size=32, flag=dyq.PrecisionFlag(4), skip=(re.compile(r"lm_head|k_proj"),),
                       min_act_bits={"gate_proj": 8, "up_proj": 8})
    config = model.config.quantization_config
    assert sorted(config.modules_to_not_convert) == ["lm_head", "model.layers.0.self_attn.k_proj"]
    assert config.min_act_bits == {"gate_proj": 8, "up_proj": 8}
    model.save_pretrained(tmp_path / "dyq")
    loaded = transformers.LlamaForCausalLM.from_pretrained(tmp_path / "dyq")
    attention, mlp = loaded.model.layers[0].self_attn, loaded.model.layers[0].mlp
    assert type(attention.k_proj) is torch.nn.Linear and isinstance(attention.q_proj, dyq.DyQLinear)
    assert (mlp.gate_proj.min_act_bits, mlp.up_proj.min_act_bits, mlp.down_proj.min_act_bits) == (8, 8, 2)
    for bits in (2, 16):
        dyq.set_precision(model, bits)
        dyq.set_precision(loaded, bits)
        with torch.no_grad():
            assert torch.equal(loaded(IDS).logits, model(IDS).logits)


def test_a_model_one_config_cannot_describe_warns_and_keeps_no_stale_config(float_checkpoint):
    model = transformers.LlamaForCausalLM.from_pretrained(float_checkpoint)
    dyq.quantize_model(model, group_size=128, skip=("lm_head", "down_proj"))
    assert model.config.quantization_config.modules_to_not_convert == ["lm_head", "down_proj"]
    with pytest.warns(UserWarning, match=r"group sizes \[64, 128\].*dyq.save_quantized"):
        dyq.quantize_model(model, group_size=64, skip=("lm_head",))
    assert not isinstance(getattr(model.config, "quantization_config", None), dyq.DyQConfig)


def test_layers_of_several_flags_are_warned_about(float_checkpoint, tmp_path):
    """One config holds one width: the layers that a second call converted without the first call's flag
    load bound to that flag."""
    model = transformers.LlamaForCausalLM.from_pretrained(float_checkpoint)
    dyq.quantize_model(model, group_size=64, flag=dyq.PrecisionFlag(8))
    with pytest.warns(UserWarning, match="read different flags.*one flag at 8 bits"):
        dyq.quantize_model(model, group_size=64, skip=())
    model.save_pretrained(tmp_path / "dyq")
    loaded = transformers.LlamaForCausalLM.from_pretrained(tmp_path / "dyq")
    assert isinstance(loaded.lm_head, dyq.DyQLinear) and dyq.model_flag(loaded).bits == 8
    dyq.bind_flag(model, dyq.PrecisionFlag(8))
    with torch.no_grad():
        assert torch.equal(loaded(IDS).logits, model(IDS).logits)


def test_min_act_bits_in_the_config_is_checked():
    assert dyq.DyQConfig(min_act_bits={"gate_proj": 8}).to_dict()["min_act_bits"] == {"gate_proj": 8}
    with pytest.raises(ValueError, match=r"min_act_bits\['gate_proj'\]"):
        dyq.DyQConfig(min_act_bits={"gate_proj": 5})
    with pytest.raises(TypeError, match="min_act_bits must be a dict"):
        dyq.DyQConfig(min_act_bits=[("gate_proj", 8)])
