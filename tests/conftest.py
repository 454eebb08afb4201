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
