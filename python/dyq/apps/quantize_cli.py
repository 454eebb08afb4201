"""``dyq quantize``: convert a local Hugging Face checkpoint to dyq's INT4 weights, once, for deployment.

    dyq quantize path/to/float path/to/dyq                        # round-to-nearest, group 128
    dyq quantize float dyq --method mse --group-size 64 --act-bits 8
    dyq quantize float dyq --method gptq --calibration ids.npy    # token ids [batch, seq], not evaluation data
    dyq quantize float dyq --dtype bfloat16                       # what stays in float (embeddings, norms,
                                                                  # LM head) in bf16: faster on CPUs with bf16
                                                                  # dot products (README, Benchmarks)

The model is read from ``SRC`` (its ``config.json`` names the transformers class; nothing is downloaded),
converted by :func:`dyq.quantize_model` and written to ``OUT`` with ``save_pretrained``, its config carrying a
:class:`dyq.DyQConfig`, beside the other files of ``SRC`` (tokenizer, processor). Any transformers program
that has imported dyq then loads it with ``from_pretrained(OUT)``: the INT4 layers, the skipped ones in
float, and one PrecisionFlag at ``--act-bits``.
"""
from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from ..core.precision import GROUP_SIZES, VALID_BITS
from ..core.quantize import DEFAULT_SKIP
from ..core.weight_methods import CALIBRATED_METHODS, METHODS
from .usage import UsageError, input_dir, input_file, output_dir, require

WEIGHT_SUFFIXES = (".safetensors", ".bin", ".pt", ".pth", ".ckpt", ".h5", ".msgpack")
WRITTEN_BY_SAVE = ("config.json", "generation_config.json")
DTYPES = ("auto", "float32", "bfloat16", "float16")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", type=input_dir, help="a Hugging Face checkpoint folder (config.json and weights)")
    parser.add_argument("out", type=output_dir, help="the folder to write the quantized checkpoint to")
    parser.add_argument("--group-size", type=int, choices=GROUP_SIZES, default=128)
    parser.add_argument("--method", choices=METHODS, default="rtn",
                        help="how the INT4 codes are chosen (awq and gptq need --calibration)")
    parser.add_argument("--act-bits", type=int, choices=VALID_BITS, default=16,
                        help="the activation width the loaded model starts at (its flag's value)")
    parser.add_argument("--skip", action="append", metavar="PATTERN",
                        help=f"a layer name pattern to keep in float (repeatable; default: {', '.join(DEFAULT_SKIP)})")
    parser.add_argument("--dtype", choices=DTYPES, default="auto",
                        help="the dtype of what stays in float (default: the checkpoint's own)")
    parser.add_argument("--calibration", type=input_file(".npy", ".pt"),
                        help="token ids [batch, seq] (.npy, or a tensor saved with torch.save) for awq and gptq")


def _calibration_ids(path: Path):
    import numpy as np
    import torch

    try:
        ids = torch.from_numpy(np.load(path)) if path.suffix == ".npy" else torch.load(path, weights_only=True)
    except Exception as error:  # noqa: BLE001 (a file that does not parse is the user's to fix)
        raise UsageError(f"--calibration {path}: cannot read it: {error}") from None
    if not isinstance(ids, torch.Tensor) or ids.dim() != 2 or ids.dtype.is_floating_point or ids.numel() == 0:
        raise UsageError(f"--calibration {path}: expected integer token ids of shape [batch, seq], got "
                         f"{getattr(ids, 'dtype', type(ids).__name__)} {tuple(getattr(ids, 'shape', ()))}")
    return ids.long()


def main(args: argparse.Namespace) -> int:
    transformers = require("transformers", "dyq quantize")
    import dyq

    from ..core.serialization import from_pretrained_dtype, transformers_model_class

    try:  # OUT is read back through the quantizer: refuse before loading a model that could not be written
        dyq.DyQConfig
    except ImportError as missing:
        raise UsageError(f"OUT is a checkpoint that from_pretrained loads through dyq.DyQConfig. {missing}") from None

    if not (args.src / "config.json").is_file():
        raise UsageError(f"{args.src} has no config.json: expected a Hugging Face checkpoint folder")
    if args.src.resolve() == args.out.resolve():
        raise UsageError("OUT must differ from SRC: the float checkpoint would be overwritten")
    if args.method in CALIBRATED_METHODS and args.calibration is None:
        raise UsageError(f"--method {args.method} needs --calibration (token ids [batch, seq])")
    if args.method not in CALIBRATED_METHODS and args.calibration is not None:
        raise UsageError(f"--calibration is only used by --method {' and '.join(CALIBRATED_METHODS)}, "
                         f"not {args.method}")
    calibration = _calibration_ids(args.calibration) if args.calibration is not None else None
    skip = tuple(args.skip) if args.skip else DEFAULT_SKIP

    import torch

    dtype = "auto" if args.dtype == "auto" else getattr(torch, args.dtype)
    # SRC's own faults (a config no architecture matches, no weight file) are the user's to fix, not a bug.
    try:
        config = transformers.AutoConfig.from_pretrained(args.src, local_files_only=True)
        model_class = transformers_model_class(config, "AutoModelForCausalLM")
        model = model_class.from_pretrained(args.src, local_files_only=True, **from_pretrained_dtype(dtype)).eval()
    except (ValueError, OSError) as error:
        raise UsageError(f"{args.src}: not a Hugging Face checkpoint transformers can load ({error})") from None
    try:
        report = dyq.quantize_model(model, group_size=args.group_size, skip=skip, act_bits=args.act_bits,
                                    flag=dyq.PrecisionFlag(args.act_bits), method=args.method,
                                    calibration=calibration)
    except ValueError as error:  # calibration ids that do not fit the model, non-finite weights
        raise UsageError(f"{args.src}: {error}") from None
    print(report)
    if not report.converted:
        raise UsageError(f"{args.src}: no linear layer was converted; nothing to write")
    # quantize_model set model.config.quantization_config, which save_pretrained writes for from_pretrained.
    args.out.mkdir(parents=True, exist_ok=True)
    model.save_pretrained(args.out)
    copied = []
    for path in sorted(args.src.iterdir()):  # tokenizer, processor and the like, not the float weights
        if path.is_file() and path.suffix not in WEIGHT_SUFFIXES and not path.name.endswith(".index.json") \
                and path.name not in WRITTEN_BY_SAVE:
            shutil.copy2(path, args.out / path.name)
            copied.append(path.name)
    print(f"wrote {args.out}" + (f" (with {', '.join(copied)} from {args.src})" if copied else "")
          + "; load it with from_pretrained after `import dyq`")
    return 0
