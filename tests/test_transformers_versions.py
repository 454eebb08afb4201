"""dyq across transformers versions: the names that changed between 4.40 and 5.x, on fake signatures (CI
installs one version), and the error of the Hugging Face quantizer where transformers lacks its hooks."""
import importlib
import sys

import pytest
import torch

transformers = pytest.importorskip("transformers")
import dyq  # noqa: E402
import dyq.sim.policy as policy  # noqa: E402


class RecordingModel:
    """Returns what a causal LM returns, under the cache's name, and records each call's keywords."""

    def __init__(self, cache_name):
        self.cache_name, self.calls = cache_name, []

    def __call__(self, input_ids, **keywords):
        self.calls.append(keywords)
        return {"logits": torch.zeros(1, input_ids.shape[1], 4), self.cache_name: ("cache", len(self.calls))}


@pytest.mark.parametrize("parameters, logits_keyword", [
    ({"cache", "logits_to_keep"}, "logits_to_keep"),                     # transformers 5
    ({"past_key_values", "logits_to_keep"}, "logits_to_keep"),           # 4.50 to 4.57
    ({"past_key_values", "num_logits_to_keep"}, "num_logits_to_keep"),   # 4.45 to 4.49
    ({"past_key_values"}, None),                                         # 4.40 to 4.44: every position's logits
])
def test_cached_forward_speaks_each_versions_names_and_passes_on_the_returned_cache(monkeypatch, parameters,
                                                                                    logits_keyword):
    monkeypatch.setattr(policy, "_forward_keywords",
                        lambda: policy.forward_keywords(parameters | {"input_ids", "use_cache"}))
    cache_name = "cache" if "cache" in parameters else "past_key_values"
    model = RecordingModel(cache_name)
    _, first = policy.cached_forward(model, torch.zeros(1, 5, dtype=torch.long))
    _, second = policy.cached_forward(model, torch.zeros(1, 1, dtype=torch.long), first,
                                      position_ids=torch.tensor([[5]]))
    # The first call makes its cache; each later one gets the cache the call before it returned (4.4x returns
    # new tuples every call).
    assert first == ("cache", 1) and second == ("cache", 2)
    assert cache_name not in model.calls[0] and model.calls[1][cache_name] == first
    for keywords in model.calls:
        assert keywords["use_cache"] is True
        assert {k for k in keywords if k.endswith("logits_to_keep")} == ({logits_keyword} if logits_keyword else set())
        if logits_keyword:
            assert keywords[logits_keyword] == 1
    assert model.calls[1]["position_ids"].tolist() == [[5]]


def test_the_installed_transformers_decodes_the_same_with_and_without_the_cache():
    config = transformers.LlamaConfig(hidden_size=64, intermediate_size=128, num_hidden_layers=2,
                                      num_attention_heads=4, num_key_value_heads=4, vocab_size=50)
    torch.manual_seed(0)
    model = transformers.LlamaForCausalLM(config).eval()
    ids = torch.randint(0, 50, (1, 9), generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        full = model(input_ids=ids).logits[0, -1]
        _, cache = policy.cached_forward(model, ids[:, :-1])
        out, _ = policy.cached_forward(model, ids[:, -1:], cache, position_ids=torch.tensor([[8]]))
    torch.testing.assert_close(out["logits"][0, -1], full, rtol=1e-5, atol=1e-5)


@pytest.fixture
def transformers_without_quantizer_hooks(monkeypatch):
    """transformers as before 4.49, and dyq's quantizer not imported yet."""
    import dyq.core
    import transformers.quantizers.auto

    monkeypatch.delattr(transformers.quantizers.auto, "register_quantization_config", raising=False)
    monkeypatch.delitem(sys.modules, "dyq.core.hf_quantizer", raising=False)
    monkeypatch.delattr(dyq.core, "hf_quantizer", raising=False)


def test_the_hf_quantizer_without_transformers_hooks_says_what_to_use_instead(transformers_without_quantizer_hooks):
    with pytest.raises(ImportError, match=r"transformers >= 4\.49.*dyq\.quantize_model\(model\)"):
        importlib.import_module("dyq.core.hf_quantizer")
    with pytest.raises(ImportError, match=r"transformers >= 4\.49"):
        dyq.DyQConfig  # noqa: B018


def test_dyq_quantize_without_the_hooks_refuses_before_loading_the_model(transformers_without_quantizer_hooks,
                                                                          float_checkpoint, tmp_path, capsys):
    from dyq.apps import cli

    assert cli.main(["quantize", str(float_checkpoint), str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert error.startswith("dyq quantize: error: OUT is a checkpoint that from_pretrained loads through "
                            "dyq.DyQConfig") and "transformers >= 4.49" in error and error.count("\n") == 1
    assert not (tmp_path / "out").exists()
