"""quantize_model on the backbones of today's vision-language-action policies, each built from a small config
(no download): OpenVLA's (DINOv2 and SigLIP features, an MLP projector, Llama), PaliGemma (pi0), Idefics3 and
SmolVLM (SmolVLA), Qwen2-VL and Qwen2.5-VL, LLaVA, and the language models of their families. In each running
model every converted layer is checked against the float64 reference at every width, the model's output against
the float model with the same INT4 weights, and a saved model against its reloaded copy."""
import copy
import inspect

import pytest
import torch
from helpers import assert_gemm_close

import dyq
from dyq import reference

transformers = pytest.importorskip("transformers")

VOCAB, IMAGE_TOKEN = 512, 500  # image placeholder tokens sit above the text ids (0..399) drawn below


def _generator(seed):
    return torch.Generator().manual_seed(seed)


def _text_ids(batch=2, length=8):
    return torch.randint(0, 400, (batch, length), generator=_generator(1))


def _text_config(config_class, **overrides):
    fields = dict(vocab_size=VOCAB, hidden_size=128, intermediate_size=256, num_hidden_layers=2,
                  num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=256)
    return config_class(**{**fields, **overrides})


def _vision_layers(config_class, **overrides):
    """A 32 x 32 image in 8 x 8 patches: 16 patches."""
    fields = dict(hidden_size=64, intermediate_size=128, num_hidden_layers=2, num_attention_heads=4, image_size=32,
                  patch_size=8)
    return config_class(**{**fields, **overrides})


def _with_image_tokens(image_tokens, **extra):
    ids = torch.cat([torch.full((2, image_tokens), IMAGE_TOKEN), _text_ids()], 1)
    return {"input_ids": ids, "attention_mask": torch.ones_like(ids), **extra}


def _causal_lm(model_class, config_class, **overrides):
    def build():
        model = getattr(transformers, model_class)(_text_config(getattr(transformers, config_class), **overrides))
        return model, {"input_ids": _text_ids()}
    return build


def _paligemma():
    config = transformers.PaliGemmaConfig(
        vision_config=_vision_layers(transformers.SiglipVisionConfig, projection_dim=128).to_dict(),
        text_config=_text_config(transformers.GemmaConfig, head_dim=32).to_dict(),
        image_token_index=IMAGE_TOKEN, vocab_size=VOCAB, projection_dim=128)
    pixels = torch.randn(2, 3, 32, 32, generator=_generator(2))
    return transformers.PaliGemmaForConditionalGeneration(config), _with_image_tokens(16, pixel_values=pixels)


def _llava():
    config = transformers.LlavaConfig(
        vision_config=_vision_layers(transformers.CLIPVisionConfig, projection_dim=64).to_dict(),
        text_config=_text_config(transformers.LlamaConfig).to_dict(), image_token_index=IMAGE_TOKEN,
        vision_feature_layer=-1)
    pixels = torch.randn(2, 3, 32, 32, generator=_generator(2))
    model = transformers.LlavaForConditionalGeneration(config)
    # The default feature selection drops the class token: 16 image tokens, which releases before 4.47 expand
    # from one placeholder themselves.
    legacy = hasattr(model, "_merge_input_ids_with_image_features")
    return model, _with_image_tokens(1 if legacy else 16, pixel_values=pixels)


def _idefics3(model_class="Idefics3ForConditionalGeneration", config_class="Idefics3Config",
              vision_class="Idefics3VisionConfig"):
    def build():
        config = getattr(transformers, config_class)(
            vision_config=_vision_layers(getattr(transformers, vision_class)).to_dict(),
            text_config=_text_config(transformers.LlamaConfig).to_dict(), image_token_id=IMAGE_TOKEN, scale_factor=2)
        pixels = torch.randn(2, 1, 3, 32, 32, generator=_generator(2))  # one image per sample
        # 16 patches, shuffled by 2 x 2 into 4 image tokens.
        return getattr(transformers, model_class)(config), _with_image_tokens(4, pixel_values=pixels)
    return build


def _qwen_vl(model_class, config_class, vision):
    def build():
        text = _text_config(transformers.Qwen2Config, rope_scaling={"type": "mrope", "mrope_section": [4, 6, 6]})
        config = getattr(transformers, config_class)(
            vision_config=vision, text_config=text.to_dict(), image_token_id=IMAGE_TOKEN, video_token_id=501,
            vision_start_token_id=502, vision_end_token_id=503)
        model = getattr(transformers, model_class)(config)
        # One 32 x 32 image a sample: 4 x 4 patches of 8 (each 2 frames deep), merged 2 x 2 into 4 tokens.
        ids = torch.cat([torch.full((2, 1), 502), torch.full((2, 4), IMAGE_TOKEN), torch.full((2, 1), 503),
                         _text_ids()], 1)
        inputs = {"input_ids": ids, "attention_mask": torch.ones_like(ids),
                  "pixel_values": torch.randn(2 * 16, 3 * 2 * 8 * 8, generator=_generator(2)),
                  "image_grid_thw": torch.tensor([[1, 4, 4], [1, 4, 4]])}
        if "mm_token_type_ids" in inspect.signature(model.forward).parameters:
            inputs["mm_token_type_ids"] = (ids == IMAGE_TOKEN).long()
        return model, inputs
    return build


class OpenVLAShaped(torch.nn.Module):
    """OpenVLA's layout: DINOv2 and SigLIP patch features side by side, a three-layer MLP projector into the
    language model's width, the projected patches before the prompt's embeddings, then Llama."""

    def __init__(self):
        super().__init__()
        self.dino = transformers.Dinov2Model(_vision_layers(transformers.Dinov2Config, layerscale_value=0.1))
        self.siglip = transformers.SiglipVisionModel(_vision_layers(transformers.SiglipVisionConfig))
        self.projector = torch.nn.Sequential(torch.nn.Linear(128, 256), torch.nn.GELU(), torch.nn.Linear(256, 128),
                                             torch.nn.GELU(), torch.nn.Linear(128, 128))
        self.llm = transformers.LlamaForCausalLM(_text_config(transformers.LlamaConfig))

    def forward(self, input_ids, pixel_values):
        dino = self.dino(pixel_values=pixel_values).last_hidden_state[:, 1:]  # the patches, not the class token
        siglip = self.siglip(pixel_values=pixel_values).last_hidden_state
        patches = self.projector(torch.cat([dino, siglip], -1))
        embeds = torch.cat([patches, self.llm.get_input_embeddings()(input_ids)], 1)
        return self.llm(inputs_embeds=embeds)


def _openvla():
    return OpenVLAShaped(), {"input_ids": _text_ids(), "pixel_values": torch.randn(2, 3, 32, 32, generator=_generator(2))}


BACKBONES = {
    "openvla": ("Dinov2Model", _openvla),
    "paligemma": ("PaliGemmaForConditionalGeneration", _paligemma),
    "llava": ("LlavaForConditionalGeneration", _llava),
    "idefics3": ("Idefics3ForConditionalGeneration", _idefics3()),
    "smolvlm": ("SmolVLMForConditionalGeneration",
                _idefics3("SmolVLMForConditionalGeneration", "SmolVLMConfig", "SmolVLMVisionConfig")),
    "qwen2_vl": ("Qwen2VLForConditionalGeneration", _qwen_vl(
        "Qwen2VLForConditionalGeneration", "Qwen2VLConfig",
        dict(depth=2, embed_dim=64, hidden_size=128, num_heads=4, patch_size=8, spatial_merge_size=2,
             temporal_patch_size=2, in_chans=3, mlp_ratio=2))),
    "qwen2_5_vl": ("Qwen2_5_VLForConditionalGeneration", _qwen_vl(
        "Qwen2_5_VLForConditionalGeneration", "Qwen2_5_VLConfig",
        dict(depth=2, hidden_size=64, intermediate_size=128, out_hidden_size=128, num_heads=4, patch_size=8,
             spatial_merge_size=2, temporal_patch_size=2, in_chans=3, window_size=32, fullatt_block_indexes=[1]))),
    "gemma": ("GemmaForCausalLM", _causal_lm("GemmaForCausalLM", "GemmaConfig", head_dim=32)),
    "gemma2": ("Gemma2ForCausalLM", _causal_lm("Gemma2ForCausalLM", "Gemma2Config", head_dim=32)),
    "qwen2": ("Qwen2ForCausalLM", _causal_lm("Qwen2ForCausalLM", "Qwen2Config")),
    "mistral": ("MistralForCausalLM", _causal_lm("MistralForCausalLM", "MistralConfig")),
    "phi3": ("Phi3ForCausalLM", _causal_lm("Phi3ForCausalLM", "Phi3Config", pad_token_id=0)),
}


def build(name):
    """The model in eval mode and its inputs, or a skip where this transformers lacks the architecture."""
    model_class, builder = BACKBONES[name]
    if not hasattr(transformers, model_class):
        pytest.skip(f"transformers {transformers.__version__} has no {model_class}")
    torch.manual_seed(0)
    model, inputs = builder()
    return model.eval(), inputs


def output_of(model, inputs):
    with torch.no_grad():
        return model(**inputs).logits


def relative_error(actual, expected):
    return ((actual - expected).norm() / expected.norm()).item()


@pytest.mark.parametrize("name", BACKBONES)
def test_every_layer_of_the_running_model_matches_the_reference_at_every_width(name):
    model, inputs = build(name)
    flag = dyq.PrecisionFlag(16)
    report = dyq.quantize_model(model, flag=flag)
    left = {n for n, m in model.named_modules() if type(m) is torch.nn.Linear}
    assert left == {n for n in report.skipped if not n.endswith("attention.out_proj")}
    assert any(n.endswith("lm_head") for n in report.skipped)
    calls = []
    hooks = [m.register_forward_hook(lambda m, args, out: calls.append((m, args[0], out)))
             for m in model.modules() if isinstance(m, dyq.DyQLinear)]
    try:
        for bits in (16, 8, 4, 2):
            flag.bits = bits
            calls.clear()
            output_of(model, inputs)
            # Every converted layer ran (the vision tower and the projector too), each as the reference says.
            assert {id(m) for m, _, _ in calls} == {id(m) for m in model.modules() if isinstance(m, dyq.DyQLinear)}
            for layer, x, out in calls:
                assert_gemm_close(out, x, layer.qweight, layer.scales, layer.group_size, bits, layer.bias)
    finally:
        for hook in hooks:
            hook.remove()


@pytest.mark.parametrize("name", BACKBONES)
def test_the_output_at_16_bits_is_the_float_models_with_int4_weights_and_a_reload_is_bit_for_bit(name, tmp_path):
    model, inputs = build(name)
    float_output = output_of(model, inputs)
    int4_weights = copy.deepcopy(model)
    report = dyq.quantize_model(model, flag=dyq.PrecisionFlag(16))
    with torch.no_grad():
        layers = dict(int4_weights.named_modules())
        for layer_name in report.converted:
            layer = layers[layer_name]
            codes, scales = reference.quantize_weight(layer.weight, 128)
            layer.weight.copy_(reference.dequantize_weight(reference.pack_int4(codes), scales, 128))
    expected = output_of(int4_weights, inputs)
    # The W4A16 GEMMs of the CPU round their activations to bf16 (docs/numerics.md): about 2^-9 a layer.
    assert relative_error(output_of(model, inputs), expected) < 2e-2
    assert relative_error(expected, float_output) < 0.4  # round-to-nearest INT4 of random Gaussian weights
    by_width = {}
    for bits in (8, 2):
        dyq.set_precision(model, bits)
        by_width[bits] = output_of(model, inputs)
    assert relative_error(by_width[8], expected) < relative_error(by_width[2], expected)

    dyq.save_quantized(model, tmp_path)
    torch.manual_seed(1)  # the fresh model's own weights differ: the file must replace them all
    fresh, _ = build(name)
    loaded = dyq.load_quantized(fresh, tmp_path)
    assert torch.equal(output_of(loaded, inputs), by_width[2])  # saved while the flag said 2 bits


@pytest.mark.parametrize("name", ["paligemma", "qwen2_5_vl", "smolvlm", "gemma2"])
def test_generation_with_the_kv_cache_follows_the_flag(name):
    """generate() over the cache, switched between widths as the dispatcher would between control steps, equals
    the greedy tokens of full forwards at the same width."""
    model, inputs = build(name)
    flag = dyq.PrecisionFlag(8)
    dyq.quantize_model(model, flag=flag)
    for bits in (8, 4, 8):
        flag.bits = bits
        with torch.no_grad():
            generated = model.generate(**inputs, max_new_tokens=3, do_sample=False)
        prompt = inputs["input_ids"].shape[1]
        ids = inputs["input_ids"]
        for step in range(3):
            extended = {**inputs, "input_ids": ids, "attention_mask": torch.ones_like(ids)}
            if "mm_token_type_ids" in inputs:
                extended["mm_token_type_ids"] = torch.nn.functional.pad(inputs["mm_token_type_ids"], (0, step))
            next_token = output_of(model, extended)[:, -1].argmax(-1, keepdim=True)
            ids = torch.cat([ids, next_token], 1)
        assert torch.equal(generated[:, prompt:], ids[:, prompt:]), bits
