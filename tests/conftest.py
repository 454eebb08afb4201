import pytest
import torch


@pytest.fixture
def rng():
    """A fresh generator per test: inputs are new random draws every run (the seed is printed on failure)."""
    seed = torch.randint(0, 2**31 - 1, ()).item()
    print(f"seed = {seed}")
    return torch.Generator().manual_seed(seed)


def pytest_collection_modifyitems(config, items):
    skip_cuda = pytest.mark.skip(reason="needs a CUDA device")
    if not torch.cuda.is_available():
        for item in items:
            if "cuda" in item.keywords:
                item.add_marker(skip_cuda)


@pytest.fixture
def float_checkpoint(tmp_path):
    """A float Llama saved with save_pretrained (built from a config, nothing downloaded). Hidden 576 (SmolLM2's)
    and intermediate 960 (SmolVLA's backbone): remainder groups at G = 128."""
    transformers = pytest.importorskip("transformers")
    config = transformers.LlamaConfig(vocab_size=256, hidden_size=576, intermediate_size=960, num_hidden_layers=1,
                                      num_attention_heads=4, num_key_value_heads=2)
    torch.manual_seed(0)
    transformers.LlamaForCausalLM(config).save_pretrained(tmp_path / "float")
    return tmp_path / "float"
