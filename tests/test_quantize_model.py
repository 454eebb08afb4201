"""quantize_model on Hugging Face models built from small configs (no download)."""
import copy

import pytest
import torch
from helpers import assert_gemm_close, bf16_fallback

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
    # At 16 bits only the float sums differ, unless the CPU's W4A16 runs on bf16 dot products, which round
    # the activations to bf16 (2^-9 relative each: docs/numerics.md).
    exact = 8e-3 if bf16_fallback(ids.numel(), model.config.hidden_size, 128) else 1e-5
    assert rel < {16: exact, 8: 0.02, 4: 0.3, 2: 1.0}[bits]
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
        hidden = model.model(torch.randint(0, 512, (1, 8))).last_hidden_state
    # The decoder's output (transformers 4.x casts the logits to fp32 after the LM head, 5.x does not).
    assert hidden.dtype == torch.bfloat16 and torch.isfinite(hidden).all()


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


def test_layers_of_any_width_are_converted():
    """in_features need not be a multiple of the group size (the last group holds the remainder), nor even."""
    model = torch.nn.Sequential(torch.nn.Linear(128, 96), torch.nn.ReLU(), torch.nn.Linear(96, 7),
                                torch.nn.Linear(7, 5))
    x = torch.randn(3, 128)
    report = dyq.quantize_model(model, group_size=64, skip=(), act_bits=8)
    assert report.converted == ["0", "2", "3"] and report.skipped == {}
    out = model(x)
    assert out.shape == (3, 5) and torch.isfinite(out).all()
    assert model[3].qweight.shape == (5, 4)  # the odd in_features padded with a zero column


def test_a_bare_linear_is_converted_in_place():
    torch.manual_seed(11)
    linear = torch.nn.Linear(96, 8)
    x = torch.randn(2, 96)
    expected = linear(x).detach()
    report = dyq.quantize_model(linear, group_size=32, skip=())
    assert isinstance(linear, dyq.DyQLinear) and report.converted == [""]
    out = linear(x).detach()
    # The layer computes x W^T + b with its INT4 weights (x rounded to bf16 at most, 2^-8 of each term) ...
    dequantized = linear.dequantized_weight()
    exact = x.double() @ dequantized.double().t() + linear.bias.double()
    assert ((out.double() - exact).abs() <= 2.0 ** -8 * (x.abs() @ dequantized.abs().t()).double() + 1e-5).all()
    # ... which stay close to the float ones: INT4 in groups of 32 moves these outputs by about 7 % (median
    # over seeds; 6.8 % with this one, up to 15 % with others).
    assert (out - expected).norm() < 0.1 * expected.norm()



def test_a_shared_linear_becomes_one_dyq_layer_everywhere_and_the_report_says_so():
    shared = torch.nn.Linear(64, 64)
    model = torch.nn.Module()
    model.first, model.second = torch.nn.Sequential(shared), torch.nn.Sequential(torch.nn.ReLU(), shared)
    report = dyq.quantize_model(model, group_size=64, skip=())
    assert model.first[0] is model.second[1] and isinstance(model.first[0], dyq.DyQLinear)
    assert report.converted == ["first.0"] and report.shared == {"first.0": ["second.1"]}
    assert "shared first.0: also held as second.1" in str(report)


def test_a_shared_linear_is_skipped_if_any_of_its_names_matches():
    shared = torch.nn.Linear(64, 64)
    model = torch.nn.Module()
    model.body, model.lm_head = shared, shared
    report = dyq.quantize_model(model, group_size=64)
    assert type(model.body) is torch.nn.Linear and "body" in report.skipped


def test_a_second_call_says_the_model_is_already_quantized():
    model = tiny_llama()
    dyq.quantize_model(model)
    again = dyq.quantize_model(model)
    assert again.converted == [] and len(again.already_quantized) == 14
    assert "already quantized (14 DyQLinear layers)" in str(again)


def test_copies_and_reloads_keep_one_working_flag_each(tmp_path):
    import io

    model = tiny_llama()
    flag = dyq.PrecisionFlag(16)
    dyq.quantize_model(model, flag=flag)
    buffer = io.BytesIO()
    torch.save(model, buffer)
    buffer.seek(0)
    for copy_ in (copy.deepcopy(model), torch.load(buffer, weights_only=False)):
        copy_flag = dyq.model_flag(copy_)
        assert copy_flag is not flag
        dyq.set_precision(copy_, 2)
        assert copy_flag.bits == 2 and flag.bits == 16
        assert all(layer.precision == 2 for layer in copy_.modules() if isinstance(layer, dyq.DyQLinear))
    assert dyq.model_flag(model) is flag


@pytest.mark.parametrize("group_size", (64, 128))
def test_save_and_load_quantized_round_trip_through_safetensors(tmp_path, group_size):
    model = tiny_llama()
    flag = dyq.PrecisionFlag(4)
    dyq.quantize_model(model, group_size=group_size, flag=flag)
    dyq.save_quantized(model, tmp_path)
    assert (tmp_path / "model.safetensors").exists() and (tmp_path / "dyq_config.json").exists()
    loaded = dyq.load_quantized(tiny_llama(), tmp_path)
    assert dyq.model_flag(loaded).bits == 4
    ids = torch.randint(0, 512, (2, 9), generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        assert torch.equal(loaded(ids).logits, model(ids).logits)
    from_config = dyq.load_quantized(model.config, tmp_path)
    assert isinstance(from_config.model.layers[0].self_attn.q_proj, dyq.DyQLinear)
    assert from_config.model.layers[0].self_attn.q_proj.group_size == group_size


def test_load_quantized_reports_what_does_not_fit(tmp_path):
    model = tiny_llama()
    dyq.quantize_model(model)
    dyq.save_quantized(model, tmp_path)
    narrower = transformers.LlamaForCausalLM(transformers.LlamaConfig(
        vocab_size=512, hidden_size=64, intermediate_size=256, num_hidden_layers=2, num_attention_heads=4,
        num_key_value_heads=2))
    with pytest.raises(ValueError, match="saved as Linear"):
        dyq.load_quantized(narrower, tmp_path)
    with pytest.raises(FileNotFoundError, match="no dyq_config.json"):
        dyq.load_quantized(tiny_llama(), tmp_path / "missing")


def test_load_quantized_into_a_quantized_model_takes_the_saved_precision(tmp_path):
    """A model quantized before the load (other act_bits, no flag) ends as a fresh load does: the saved
    flag and floors, and the same outputs."""
    model = tiny_llama()
    dyq.quantize_model(model, group_size=64, flag=dyq.PrecisionFlag(8), min_act_bits={"gate_proj": 16})
    dyq.save_quantized(model, tmp_path)
    before = tiny_llama()
    dyq.quantize_model(before, group_size=64, act_bits=2)
    loaded = dyq.load_quantized(before, tmp_path)
    fresh = dyq.load_quantized(tiny_llama(), tmp_path)
    assert dyq.model_flag(loaded).bits == 8
    for name, layer in fresh.named_modules():
        if isinstance(layer, dyq.DyQLinear):
            other = loaded.get_submodule(name)
            assert (other.precision, other.min_act_bits, other.flag is dyq.model_flag(loaded)) == (
                layer.precision, layer.min_act_bits, True), name
    ids = torch.randint(0, 512, (2, 9), generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        assert torch.equal(loaded(ids).logits, fresh(ids).logits)
    other_groups = tiny_llama()
    dyq.quantize_model(other_groups, group_size=128)
    with pytest.raises(ValueError, match="is a DyQLinear of .* here but was saved as"):
        dyq.load_quantized(other_groups, tmp_path)


def test_a_non_finite_weight_is_named_before_any_layer_is_converted():
    model = torch.nn.Sequential(torch.nn.Linear(64, 64), torch.nn.ReLU(), torch.nn.Linear(64, 8))
    model[2].weight.data[0, 0] = float("inf")
    with pytest.raises(ValueError, match=r"layers \['2'\] have NaN or Inf weights"):
        dyq.quantize_model(model, group_size=64, skip=())
    assert type(model[0]) is torch.nn.Linear and type(model[2]) is torch.nn.Linear
    report = dyq.quantize_model(model, group_size=64, skip=("2",))
    assert report.converted == ["0"] and "2" in report.skipped
    with pytest.raises(TypeError, match=r"pass skip=\(\) to convert every layer, got None"):
        dyq.quantize_model(tiny_llama(), skip=None)


def test_set_precision_needs_dyq_layers():
    with pytest.raises(ValueError, match="contains no DyQLinear"):
        dyq.set_precision(torch.nn.Linear(4, 4), 4)
    with pytest.raises(ValueError, match="bits must be one of"):
        dyq.set_precision(torch.nn.Linear(4, 4), 3)


def test_min_act_bits_keeps_the_named_layers_at_or_above_their_floor():
    """gate/up with a floor of 8: at flag 4 they compute exactly what they compute at flag 8, the other layers
    follow the flag; at 16 the floor changes nothing."""
    model, flag = tiny_llama(), dyq.PrecisionFlag(4)
    report = dyq.quantize_model(model, group_size=32, flag=flag, min_act_bits={"gate_proj": 8, "up_proj": 8})
    assert set(report.min_act_bits) == {f"model.layers.{i}.mlp.{n}" for i in range(2) for n in ("gate_proj", "up_proj")}
    assert "4 layers never run below A8" in str(report)
    mlp, attn = model.model.layers[0].mlp, model.model.layers[0].self_attn
    x = torch.randn(3, 128)
    for bits in (2, 4, 8, 16):
        flag.bits = bits
        assert mlp.up_proj.precision == max(bits, 8) and attn.q_proj.precision == bits
        # At flag 16 the layer runs the W4A16 fallback, whose bf16 dot products (where the CPU has them)
        # round x to bf16: that is assert_gemm_close's documented tolerance, not 1e-4.
        assert_gemm_close(mlp.up_proj(x), x, mlp.up_proj.qweight, mlp.up_proj.scales, 32, max(bits, 8))
        q_expected = reference.gemm(x, attn.q_proj.qweight, attn.q_proj.scales, 32, bits).float()
        if bits != 16:  # the W4A16 fallback may round x to bf16 (docs/numerics.md)
            torch.testing.assert_close(attn.q_proj(x), q_expected, rtol=1e-4, atol=1e-4)
    assert "min_act_bits=8" in repr(mlp.up_proj)


def test_a_compiled_layer_keeps_its_floor_under_every_flag_value():
    """The floor travels with the flag into the op (min_act_bits), so a graph traced once follows later
    flag writes on both sides of the floor, with no host-side branch on the flag's value."""
    model, flag = tiny_llama(), dyq.PrecisionFlag(16)
    dyq.quantize_model(model, group_size=32, flag=flag, min_act_bits={"up_proj": 8})
    up = model.model.layers[0].mlp.up_proj
    compiled = torch.compile(up, backend="eager", fullgraph=True)
    x = torch.randn(3, 128)
    for bits in (16, 2, 8, 4):
        flag.bits = bits
        assert torch.equal(compiled(x), dyq.ops.gemm(x, up.qweight, up.scales, 32, max(bits, 8)))


def test_min_act_bits_is_saved_and_loaded(tmp_path):
    model, flag = tiny_llama(), dyq.PrecisionFlag(2)
    dyq.quantize_model(model, group_size=32, flag=flag, min_act_bits={"down_proj": 8})
    dyq.save_quantized(model, tmp_path)
    loaded = dyq.load_quantized(transformers.LlamaForCausalLM(model.config), tmp_path)
    floors = {n: m.min_act_bits for n, m in loaded.named_modules() if isinstance(m, dyq.DyQLinear)}
    assert {n for n, b in floors.items() if b == 8} == {"model.layers.0.mlp.down_proj", "model.layers.1.mlp.down_proj"}
    assert all(b == 2 for n, b in floors.items() if "down_proj" not in n)
    ids = torch.randint(0, 512, (1, 9))
    with torch.no_grad():
        torch.testing.assert_close(loaded(ids).logits, model(ids).logits)


def test_min_act_bits_refuses_a_pattern_that_reaches_no_converted_layer():
    """A misspelt name, or one that only skipped layers carry, would leave every layer without its floor."""
    model = tiny_llama()
    before = {n: p.clone() for n, p in model.state_dict().items()}
    with pytest.raises(ValueError, match=r"min_act_bits: \['gate_prj'\] match no layer"):
        dyq.quantize_model(model, min_act_bits={"gate_proj": 8, "gate_prj": 8})
    with pytest.raises(ValueError, match=r"\['lm_head'\] match no layer"):
        dyq.quantize_model(model, min_act_bits={"lm_head": 8})  # skipped by default
    assert not any(isinstance(m, dyq.DyQLinear) for m in model.modules())  # refused before converting
    assert all(torch.equal(before[n], p) for n, p in model.state_dict().items())


def test_min_act_bits_refuses_a_width_that_does_not_exist():
    with pytest.raises(ValueError, match=r"min_act_bits\['gate_proj'\]"):
        dyq.quantize_model(tiny_llama(), min_act_bits={"gate_proj": 6})


def test_min_act_bits_must_be_a_mapping_of_patterns():
    with pytest.raises(TypeError, match=r"min_act_bits must be a dict \{pattern: bits\}.*got int 8"):
        dyq.quantize_model(tiny_llama(), min_act_bits=8)
    with pytest.raises(TypeError, match=r"min_act_bits patterns must be glob strings.*got int 0"):
        dyq.quantize_model(tiny_llama(), min_act_bits={0: 8})


def test_a_skip_pattern_that_matches_no_layer_is_warned_about():
    """A misspelt skip name converts the layer it meant to keep: the conversion goes on, with a warning."""
    model = tiny_llama()
    with pytest.warns(UserWarning, match=r"skip patterns \['lm-head'\] match no linear layer"):
        report = dyq.quantize_model(model, skip=("lm-head", "*.q_proj"))
    assert "lm_head" in report.converted
    assert {n for n in report.skipped} == {"model.layers.0.self_attn.q_proj", "model.layers.1.self_attn.q_proj"}
    with pytest.raises(TypeError, match=r"skip patterns must be glob strings.*got int 1"):
        dyq.quantize_model(tiny_llama(), skip=(1,))


def test_the_default_skip_is_quiet_on_a_model_without_an_lm_head(recwarn):
    report = dyq.quantize_model(tiny_bert())
    assert report.converted and not report.skipped
    assert not [w for w in recwarn if "dyq" in str(w.message)]


def test_a_model_without_linear_layers_is_warned_about():
    with pytest.warns(UserWarning, match=r"Sequential holds no nn.Linear; nothing to convert"):
        report = dyq.quantize_model(torch.nn.Sequential(torch.nn.ReLU()))
    assert not report.converted


def tiny_gpt2():
    config = transformers.GPT2Config(vocab_size=300, n_embd=128, n_layer=2, n_head=4, n_positions=64)
    torch.manual_seed(0)
    return transformers.GPT2LMHeadModel(config).eval()


def conv1d_type():
    from transformers.pytorch_utils import Conv1D
    return Conv1D


@pytest.mark.parametrize("bits", (16, 8))
def test_gpt2s_conv1d_layers_are_converted_like_linear_ones(bits):
    """GPT-2 keeps its linear layers as transformers' Conv1D (weight [in, out]); each becomes a DyQLinear
    of the transposed weight, checked against the float model with those weights dequantized."""
    model = tiny_gpt2()
    fake_quantized = copy.deepcopy(model)
    with torch.no_grad():
        for module in fake_quantized.modules():
            if isinstance(module, conv1d_type()):
                codes, scales = reference.quantize_weight(module.weight.t(), 128)
                module.weight.copy_(reference.dequantize_weight(reference.pack_int4(codes), scales, 128).t())
    report = dyq.quantize_model(model, flag=dyq.PrecisionFlag(bits))
    assert len(report.converted) == 2 * 4 and list(report.skipped) == ["lm_head"]  # c_attn, c_proj, c_fc, c_proj
    assert not any(isinstance(m, conv1d_type()) for m in model.modules())
    attention = model.transformer.h[0].attn.c_attn
    assert isinstance(attention, dyq.DyQLinear) and (attention.in_features, attention.out_features) == (128, 384)
    ids = torch.randint(0, 300, (2, 12), generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        expected, logits = fake_quantized(ids).logits, model(ids).logits
    rel = ((logits - expected).norm() / expected.norm()).item()
    exact = 8e-3 if bf16_fallback(ids.numel(), 128, 128) else 1e-5
    assert rel < {16: exact, 8: 0.02}[bits], rel


def test_a_skipped_conv1d_stays_one_and_a_saved_gpt2_loads_into_a_fresh_one(tmp_path):
    model = tiny_gpt2()
    report = dyq.quantize_model(model, skip=("lm_head", "c_fc"), flag=dyq.PrecisionFlag(4))
    assert sorted(report.skipped) == ["lm_head", "transformer.h.0.mlp.c_fc", "transformer.h.1.mlp.c_fc"]
    assert isinstance(model.transformer.h[1].mlp.c_fc, conv1d_type())
    dyq.save_quantized(model, tmp_path)
    loaded = dyq.load_quantized(tiny_gpt2(), tmp_path)
    assert isinstance(loaded.transformer.h[0].attn.c_attn, dyq.DyQLinear)
    assert isinstance(loaded.transformer.h[0].mlp.c_fc, conv1d_type())
    ids = torch.randint(0, 300, (1, 9), generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        assert torch.equal(loaded(ids).logits, model(ids).logits)
    # From the config alone: a model of other random weights, all replaced, and in eval mode (no dropout).
    torch.manual_seed(5)
    from_config = dyq.load_quantized(model.config, tmp_path)
    assert not from_config.training
    with torch.no_grad():
        assert torch.equal(from_config(ids).logits, model(ids).logits)


def tiny_encoder():
    torch.manual_seed(0)
    layer = torch.nn.TransformerEncoderLayer(128, 4, 256, batch_first=True)
    return torch.nn.TransformerEncoder(layer, 2, enable_nested_tensor=False).eval()


@pytest.mark.parametrize("bits", (16, 8))
def test_torch_transformer_encoders_get_their_feed_forward_layers_converted(bits, tmp_path):
    """nn.MultiheadAttention reads out_proj's weight without calling it: that layer is left alone, with the
    reason. nn.TransformerEncoderLayer's fused inference path reads linear1's and linear2's weights: they are
    converted and the layer routed through its module path, checked against the float encoder with those
    two layers' weights dequantized, at inference (where torch would take the fused path)."""
    model = tiny_encoder()
    fake_quantized = copy.deepcopy(model)
    with torch.no_grad():
        for layer in fake_quantized.layers:
            for linear in (layer.linear1, layer.linear2):
                codes, scales = reference.quantize_weight(linear.weight, 128)
                linear.weight.copy_(reference.dequantize_weight(reference.pack_int4(codes), scales, 128))
    report = dyq.quantize_model(model, flag=dyq.PrecisionFlag(bits))
    assert report.converted == [f"layers.{i}.linear{j}" for i in (0, 1) for j in (1, 2)]
    assert report.skipped == {f"layers.{i}.self_attn.out_proj": "its parent MultiheadAttention reads its weight "
                              "without calling it" for i in (0, 1)}
    x = torch.randn(2, 10, 128, generator=torch.Generator().manual_seed(1))
    with torch.inference_mode():
        expected, out = fake_quantized(x), model(x)
    rel = ((out - expected).norm() / expected.norm()).item()
    exact = 8e-3 if bf16_fallback(20, 128, 128) else 1e-5
    assert rel < {16: exact, 8: 0.02}[bits], rel
    dyq.save_quantized(model, tmp_path)
    torch.manual_seed(7)
    fresh = torch.nn.TransformerEncoder(torch.nn.TransformerEncoderLayer(128, 4, 256, batch_first=True), 2,
                                        enable_nested_tensor=False).eval()
    loaded = dyq.load_quantized(fresh, tmp_path)
    with torch.inference_mode():
        assert torch.equal(loaded(x), out)


def test_a_transformer_decoder_layer_and_a_bare_multihead_attention():
    torch.manual_seed(0)
    decoder = torch.nn.TransformerDecoderLayer(64, 4, 128, batch_first=True).eval()
    attention = torch.nn.MultiheadAttention(64, 4, batch_first=True).eval()
    model = torch.nn.ModuleDict({"decoder": decoder, "attention": attention})
    report = dyq.quantize_model(model)
    assert report.converted == ["decoder.linear1", "decoder.linear2"]
    assert set(report.skipped) == {"decoder.self_attn.out_proj", "decoder.multihead_attn.out_proj",
                                   "attention.out_proj"}
    x, memory = torch.randn(1, 5, 64), torch.randn(1, 7, 64)
    with torch.inference_mode():
        assert decoder(x, memory).shape == (1, 5, 64)
        assert attention(x, memory, memory)[0].shape == (1, 5, 64)


def test_a_siglip_vision_tower_with_its_attention_pooling_head_converts_and_runs():
    """SigLIP (the vision encoder of OpenVLA and PaliGemma) pools with an nn.MultiheadAttention head."""
    config = transformers.SiglipVisionConfig(hidden_size=64, intermediate_size=128, num_hidden_layers=2,
                                             num_attention_heads=4, image_size=32, patch_size=8)
    torch.manual_seed(0)
    model = transformers.SiglipVisionModel(config).eval()
    pixels = torch.randn(2, 3, 32, 32, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        float_pooled = model(pixel_values=pixels).pooler_output
    report = dyq.quantize_model(model, flag=dyq.PrecisionFlag(8))
    # The tower sits at the top (transformers 5) or under vision_model (4.x).
    pooling = [name for name, module in model.named_modules() if isinstance(module, torch.nn.MultiheadAttention)]
    assert len(pooling) == 1 and pooling[0].endswith("head.attention")
    assert list(report.skipped) == [f"{pooling[0]}.out_proj"]
    assert len(report.converted) == 2 * 6 + 2  # q, k, v, out, fc1, fc2 per layer; the head's MLP
    with torch.no_grad():
        pooled = model(pixel_values=pixels).pooler_output
    assert pooled.shape == float_pooled.shape
    assert ((pooled - float_pooled).norm() / float_pooled.norm()).item() < 0.3  # INT4 weights, A8
