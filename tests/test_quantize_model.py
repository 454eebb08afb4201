"""quantize_model on Hugging Face models built from small configs (no download)."""
import copy

import pytest
import torch

import dyq
from dyq import reference

transformers = pytest.importorskip("transformers")


def tiny_llama():
    config = transformers.LlamaConfig(vocab_size=512, hidden_size=128, intermediate_size=256, num_hidden_layers=2,
                                      num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=64)
    torch.manual_seed(0)
    return transformers.LlamaForCausalLM(config).eval()


def tiny_bert():
    config = transformers.BertConfig(vocab_size=300, hidden_size=128, intermediate_size=256, num_hidden_layers=2,
                                     num_attention_heads=4, max_position_embeddings=64)
    torch.manual_seed(0)
    return transformers.BertModel(config).eval()


def test_llama_is_converted_except_the_lm_head():
    model = tiny_llama()
    report = dyq.quantize_model(model)
    linears = [n for n, m in model.named_modules() if type(m) is torch.nn.Linear]
    assert linears == ["lm_head"]
    assert len(report.converted) == 2 * 7  # q, k, v, o, gate, up, down per layer
    assert "lm_head" in report.skipped
    assert report.linear_bytes_after < 0.2 * report.linear_bytes_before  # fp32 -> INT4 + scales
    assert report.model_bytes_after < report.model_bytes_before
    assert "converted 14 linear layers" in str(report)


@pytest.mark.parametrize("bits", (16, 8, 4, 2))
def test_quantized_llama_matches_the_float_model_with_int4_weights(bits):
    """Against the same model whose Linear weights are replaced by their dequantized INT4 values, only the
    activation quantization differs: nothing at 16 bits, little at 8, more at 4 and 2."""
    model = tiny_llama()
    fake_quantized = copy.deepcopy(model)
    with torch.no_grad():
        for name, module in fake_quantized.named_modules():
            if isinstance(module, torch.nn.Linear) and name != "lm_head":
                codes, scales = reference.quantize_weight(module.weight, 128)
                module.weight.copy_(reference.dequantize_weight(reference.pack_int4(codes), scales, 128))
    ids = torch.randint(0, 512, (2, 12), generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        float_logits = model(ids).logits
        expected = fake_quantized(ids).logits
        dyq.quantize_model(model, flag=dyq.PrecisionFlag(bits))
        logits = model(ids).logits
    rel = ((logits - expected).norm() / expected.norm()).item()
    assert rel < {16: 1e-5, 8: 0.02, 4: 0.3, 2: 1.0}[bits]
    # Random-init weights are Gaussian: round-to-nearest INT4 costs about 20 % of the logits' norm.
    assert ((expected - float_logits).norm() / float_logits.norm()).item() < 0.3


def test_one_flag_write_switches_the_whole_llama():
    model = tiny_llama()
    flag = dyq.PrecisionFlag(16)
    dyq.quantize_model(model, flag=flag)
    ids = torch.randint(0, 512, (1, 10), generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        outputs = {}
        for bits in (16, 8, 2):
            flag.bits = bits
            outputs[bits] = model(ids).logits
        dyq.bind_flag(model, None)
        dyq.set_precision(model, 8)
        assert torch.equal(model(ids).logits, outputs[8])
    assert not torch.equal(outputs[16], outputs[2])


def test_bfloat16_llama_runs_in_bfloat16():
    model = tiny_llama().to(torch.bfloat16)
    dyq.quantize_model(model, act_bits=4)
    with torch.no_grad():
        logits = model(torch.randint(0, 512, (1, 8))).logits
    assert logits.dtype == torch.bfloat16 and torch.isfinite(logits).all()


def test_bert_encoder_with_skip_patterns():
    model = tiny_bert()
    ids = torch.randint(0, 300, (2, 16), generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        expected = model(ids).last_hidden_state
    report = dyq.quantize_model(model, group_size=64, skip=("pooler.*", "*.attention.output.dense"))
    assert all(not n.startswith("pooler") for n in report.converted)
    assert "encoder.layer.0.attention.output.dense" in report.skipped
    assert len(report.converted) == 2 * 5  # q, k, v, intermediate, output per layer
    with torch.no_grad():
        hidden = model(ids).last_hidden_state
    assert ((hidden - expected).norm() / expected.norm()).item() < 0.1


def test_layers_that_do_not_fit_the_group_size_are_skipped_with_a_reason():
    model = torch.nn.Sequential(torch.nn.Linear(128, 96), torch.nn.ReLU(), torch.nn.Linear(96, 10))
    report = dyq.quantize_model(model, group_size=64, skip=())
    assert report.converted == ["0"]
    assert report.skipped == {"2": "in_features = 96 is not a multiple of 64"}


def test_set_precision_needs_dyq_layers():
    with pytest.raises(ValueError, match="contains no DyQLinear"):
        dyq.set_precision(torch.nn.Linear(4, 4), 4)
    with pytest.raises(ValueError, match="bits must be one of"):
        dyq.set_precision(torch.nn.Linear(4, 4), 3)
