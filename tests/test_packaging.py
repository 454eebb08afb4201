"""The build as a new user meets it: plain `pip install .` in a fresh venv (isolated build, no system
packages needed beyond a compiler), `pip install -e .`, the wheel's files, and the CMake branches that
decide about CUDA."""
import json
import subprocess
import sys
import venv
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def copy_of_the_repo(destination: Path) -> Path:
    """The files git would commit (tracked and untracked-not-ignored), without the tree's build outputs."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                            capture_output=True, check=True).stdout.decode().split("\0")
    for name in filter(None, listed):
        source = REPO / name
        if source.is_file():
            target = destination / name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(source.read_bytes())
    return destination


def pip(python: Path, *args: str, cwd: Path) -> None:
    result = subprocess.run([str(python), "-m", "pip", *args], cwd=cwd, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-4000:]


@pytest.mark.slow
def test_plain_pip_install_in_a_fresh_venv_then_editable(tmp_path):
    source = copy_of_the_repo(tmp_path / "src")
    # A data file in a folder without __init__.py, as the trained policies will be.
    data = source / "python/dyq/sim/policies/packaging_test/policy.json"
    data.parent.mkdir(parents=True)
    data.write_text("{}")
    venv.create(tmp_path / "venv", with_pip=True)
    python = tmp_path / "venv/bin/python"
    pip(python, "install", "-q", str(source), cwd=tmp_path)

    check = (
        "import dyq, importlib.metadata as m, pathlib, torch\n"
        "x = torch.randn(3, 256)\n"
        "layer = dyq.DyQLinear.from_linear(torch.nn.Linear(256, 64), group_size=128, act_bits=4)\n"
        "assert layer(x).shape == (3, 64)\n"
        "print(json.dumps({'file': dyq.__file__, 'isa': dyq.cpu_info()['isa'], 'requires': m.requires('dyq'),\n"
        "                  'files': [str(f) for f in m.files('dyq')]}))\n"
    )
    out = subprocess.run([str(python), "-c", "import json\n" + check], cwd=tmp_path, capture_output=True, text=True,
                         check=True).stdout
    report = json.loads(out)
    assert "site-packages" in report["file"] and report["isa"] in ("amx", "avx512_bf16", "avx512", "avx_vnni", "avx2", "portable")
    assert "torch==2.13.*" in report["requires"]
    files = set(report["files"])
    for path in (source / "python/dyq").rglob("*"):
        if path.is_file() and "__pycache__" not in path.parts:
            assert str(path.relative_to(source / "python")) in files, path
    assert any(name.startswith("dyq/_C.") and name.endswith(".so") for name in files)

    pip(python, "install", "-q", "--no-build-isolation", "--no-deps", "-e", str(source), cwd=tmp_path)
    editable = subprocess.run([str(python), "-c", "import dyq; print(dyq.__file__, dyq.cpu_info()['isa'])"],
                              cwd=tmp_path, capture_output=True, text=True, check=True).stdout
    assert editable.startswith(str(source / "python/dyq/__init__.py"))


def configure(tmp_path: Path, *options: str) -> tuple[str, str]:
    """CMake's configure output and the generated build.ninja, for the extension build with `options`."""
    build = tmp_path / "build"
    result = subprocess.run(
        ["cmake", "-S", str(REPO), "-B", str(build), "-G", "Ninja", f"-DPython_EXECUTABLE={sys.executable}",
         "-DDYQ_BUILD_PYTHON=ON", *options], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout, (build / "build.ninja").read_text()


def test_cpu_torch_skips_the_cuda_kernels(tmp_path):
    torch = pytest.importorskip("torch")
    if torch.version.cuda:
        pytest.skip("torch is a CUDA build here")
    out, ninja = configure(tmp_path)
    assert "is a CPU build: CUDA kernels skipped" in out
    assert ".cu" not in ninja and "ops_cuda.cpp" not in ninja


def test_cuda_torch_without_toolkit_builds_the_cpu_ops_and_says_so(tmp_path):
    # A CUDA build of torch is simulated by its CUDA version; DYQ_HIDE_CUDA_TOOLKIT hides nvcc.
    out, ninja = configure(tmp_path, "-DDYQ_TORCH_CUDA_VERSION=13.0", "-DDYQ_HIDE_CUDA_TOOLKIT=ON")
    lines = [line for line in out.splitlines() if "no CUDA toolkit" in line]
    assert len(lines) == 1 and "building the CPU ops only" in lines[0]
    assert "ops_cpu.cpp" in ninja and "ops_cuda.cpp" not in ninja and ".cu" not in ninja
