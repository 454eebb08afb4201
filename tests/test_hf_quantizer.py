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
    with pytest.raises(ValueError, match="rotation must be None"):
        dyq.DyQConfig(rotation="hadamard")
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
