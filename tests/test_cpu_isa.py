"""The CPU paths (csrc/cpu/cpu_isa.h): the ops' tests pass on every path this CPU can execute, and
DYQ_CPU_ISA chooses the path that runs."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

import dyq

HERE = Path(__file__).resolve().parent
RUNNABLE = dyq.cpu_info()["runnable"]


def run_with(isa: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=HERE, env={**os.environ, "DYQ_CPU_ISA": isa},
                          capture_output=True, text=True)


def test_the_best_runnable_path_is_chosen_by_default():
    info = dyq.cpu_info()
    assert info["runnable"][-1] == "portable" and set(info["runnable"]) <= set(info["compiled"])
    if info["forced"] is None:
        assert info["isa"] == info["runnable"][0]


@pytest.mark.parametrize("isa", RUNNABLE)
def test_ops_match_the_reference_on_every_runnable_path(isa):
    chosen = run_with(isa, "-c", "import dyq; print(dyq.cpu_info()['isa'])")
    assert chosen.stdout.strip() == isa, chosen.stderr
    tests = run_with(isa, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_ops.py", "-k",
                     "gemm or quantize_activations")
    assert tests.returncode == 0, tests.stdout[-3000:]


def test_an_unknown_or_unrunnable_path_is_an_error():
    result = run_with("no-such-path", "-c", "import dyq; dyq.cpu_info()")
    assert result.returncode != 0 and "is not one of this build's paths" in result.stderr


def test_the_kernels_run_on_torchs_threads_where_torch_ships_its_openmp_runtime():
    # Two thread pools on the same cores slow each other down (csrc/parallel/parallel.h): the build puts
    # dyq's kernels on torch's intra-op threads wherever torch ships libgomp, and on its own pool elsewhere.
    import torch

    ships_libgomp = (Path(torch.__file__).parent / "lib" / "libgomp.so.1").exists()
    assert dyq.cpu_info()["threads"] == ("torch" if ships_libgomp else "dyq")
