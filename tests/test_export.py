"""dyq.export: torch.export programs (in memory, saved and loaded, AOTInductor) that read the precision flag
at every call, against the eager model at each width; and the warning of a plain torch.export."""
import warnings

import pytest
import torch

import dyq

transformers = pytest.importorskip("transformers")


def tiny_llama(flag):
    config = transformers.LlamaConfig(hidden_size=128, intermediate_size=256, num_hidden_layers=2,
                                      num_attention_heads=4, num_key_value_heads=2, vocab_size=300)
    torch.manual_seed(0)
    model = transformers.LlamaForCausalLM(config).eval()
    dyq.quantize_model(model, flag=flag)
    return model


class Logits(torch.nn.Module):
    """What a control step exports: input ids to logits, without a cache object among the outputs."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, input_ids):
        return self.model(input_ids=input_ids, use_cache=False).logits


def eager_at_each_width(model, flag, *args):
    outputs = {}
    with torch.no_grad():
        for bits in dyq.VALID_BITS:
            flag.bits = bits
            outputs[bits] = model(*args)
    return outputs


def assert_follows_the_flag(program, flag, expected, *args):
    # Widths in an order that changes at every call, each against the eager model at that width.
    for bits in (16, 2, 8, 4, 16, 4):
        flag.bits = bits
        with torch.no_grad():
            out = program(flag.tensor, *args)
        torch.testing.assert_close(out, expected[bits], rtol=1e-5, atol=1e-5, msg=f"at {bits} bits")


@pytest.fixture
def exported(tmp_path):
    flag = dyq.PrecisionFlag(16)
    model = Logits(tiny_llama(flag))
    ids = torch.randint(0, 300, (1, 12), generator=torch.Generator().manual_seed(1))
    expected = eager_at_each_width(model, flag, ids)
    assert (expected[2] - expected[16]).abs().max() > 1e-3  # the widths differ, so following the flag shows
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # dyq.export itself does not warn
        program = dyq.export(model, (ids,))
    return flag, model, ids, expected, program


def test_the_exported_program_reads_the_flag_at_every_call(exported):
    flag, model, ids, expected, program = exported
    assert_follows_the_flag(program.module(), flag, expected, ids)
    # The eager model still reads its own flag.
    assert all(layer.flag is flag for layer in model.modules() if isinstance(layer, dyq.DyQLinear))
    flag.bits = 2
    with torch.no_grad():
        torch.testing.assert_close(model(ids), expected[2])


def test_a_saved_and_loaded_program_reads_the_flag_passed_to_it(tmp_path):
    # A plain torch model: transformers 4.57's Llama cannot be saved by torch.export.save, quantized or not.
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(256, 512), torch.nn.GELU(), torch.nn.Linear(512, 128)).eval()
    flag = dyq.PrecisionFlag(16)
    dyq.quantize_model(model, skip=(), flag=flag)
    x = torch.randn(3, 256, generator=torch.Generator().manual_seed(1))
    expected = eager_at_each_width(model, flag, x)
    torch.export.save(dyq.export(model, (x,)), tmp_path / "policy.pt2")
    loaded = torch.export.load(tmp_path / "policy.pt2")
    assert_follows_the_flag(loaded.module(), flag, expected, x)
    # A flag of another process (a fresh int32) works the same.
    other = dyq.PrecisionFlag(8)
    with torch.no_grad():
        torch.testing.assert_close(loaded.module()(other.tensor, x), expected[8], rtol=1e-5, atol=1e-5)


def test_an_aot_inductor_package_reads_the_flag_passed_to_it(exported, tmp_path):
    flag, _, ids, expected, program = exported
    package = torch._inductor.aoti_compile_and_package(program, package_path=str(tmp_path / "policy_aoti.pt2"))
    runner = torch._inductor.aoti_load_package(package)
    assert_follows_the_flag(runner, flag, expected, ids)


def test_plain_torch_export_of_a_flag_bound_model_warns_that_the_flag_becomes_a_constant():
    flag = dyq.PrecisionFlag(16)
    model = Logits(tiny_llama(flag))
    ids = torch.randint(0, 300, (1, 12))
    with pytest.warns(UserWarning, match=r"constant.*dyq\.export\(model, args\)"):
        torch.export.export(model, (ids,))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # eager calls and layers without a flag stay quiet
        model(ids)
        dyq.bind_flag(model, None)
        torch.export.export(model, (ids,))


def test_dynamic_shapes_in_the_tuple_form_get_the_flags_entry(exported):
    flag, model, _, _, _ = exported
    length = torch.export.Dim("length", min=2, max=64)
    program = dyq.export(model, (torch.randint(0, 300, (1, 12)),), dynamic_shapes=({1: length},))
    ids = torch.randint(0, 300, (1, 20))
    flag.bits = 4
    with torch.no_grad():
        torch.testing.assert_close(program.module()(flag.tensor, ids), model(ids), rtol=1e-5, atol=1e-5)


def test_models_export_cannot_serve_are_refused_with_the_reason():
    with pytest.raises(ValueError, match="no DyQLinear"):
        dyq.export(torch.nn.Linear(128, 128), (torch.randn(1, 128),))
    unbound = torch.nn.Sequential(torch.nn.Linear(128, 128), torch.nn.Linear(128, 128))
    dyq.quantize_model(unbound, skip=())
    with pytest.raises(ValueError, match="bound to 0 flags"):
        dyq.export(unbound, (torch.randn(1, 128),))
    dyq.bind_flag(unbound[0], dyq.PrecisionFlag(8))
    dyq.bind_flag(unbound[1], dyq.PrecisionFlag(8))
    with pytest.raises(ValueError, match="bound to 2 flags"):
        dyq.export(unbound, (torch.randn(1, 128),))
    dyq.bind_flag(unbound, dyq.PrecisionFlag(8))
    with pytest.raises(TypeError, match="args must be a tuple"):
        dyq.export(unbound, torch.randn(1, 128))
    with pytest.raises(TypeError, match="tuple form"):
        dyq.export(unbound, (torch.randn(1, 128),), dynamic_shapes={"x": None})
