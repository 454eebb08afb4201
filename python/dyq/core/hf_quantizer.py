"""dyq as a Hugging Face quantization method: ``from_pretrained(..., quantization_config=DyQConfig(...))``.

Registered through transformers' custom-quantizer hooks (``register_quantization_config`` /
``register_quantizer``, transformers 5.x). Loading a float checkpoint with a :class:`DyQConfig`
quantizes it after its weights are loaded (:func:`dyq.quantize_model`); ``save_pretrained`` writes the
INT4 state dict with the config in ``config.json``, and ``from_pretrained`` of that directory rebuilds
the DyQLinear layers before loading it. Either way every converted layer is bound to one new
:class:`~dyq.PrecisionFlag` (``dyq.model_flag(model)``) holding ``act_bits``.
"""
from __future__ import annotations

from typing import Any

import torch
import transformers
from torch import nn

try:
    from transformers.quantizers.auto import register_quantization_config, register_quantizer
except ImportError as missing:  # the hooks came with transformers 4.49
    raise ImportError(
        f"dyq.DyQConfig plugs into transformers' custom quantizers (transformers >= 4.49; tested with 5.x), which "
        f"transformers {transformers.__version__} lacks. Without them: build or load the float model, then "
        f"dyq.quantize_model(model); dyq.save_quantized(model, dir) and dyq.load_quantized(model, dir) save "
        f"and load it.") from missing
from transformers.quantizers.base import HfQuantizer
from transformers.utils.quantization_config import QuantizationConfigMixin

from ..control.flag import PrecisionFlag
from .linear import DyQLinear, is_transposed_linear, route_encoder_layers_through_modules, weight_readers
from .precision import check_bits, check_group_size
from .norm import fuse_rms_norms
from .quantize import _floor_of, _matches, quantize_model
from .serialization import WEIGHT_METHOD_NAMES, WEIGHT_METHODS
from .weight_methods import CALIBRATED_METHODS


@register_quantization_config("dyq")
class DyQConfig(QuantizationConfigMixin):
    """dyq's quantization config: INT4 weights in groups of ``group_size``, activations at ``act_bits``
    (the flag's initial value), the layers of ``modules_to_not_convert`` kept in full precision.
    ``weight_method`` is the saved name of a :func:`dyq.quantize_model` method; quantizing on load runs
    the calibration-free ones (round-to-nearest, the clipping search), while a calibrated model (AWQ, GPTQ) is
    quantized with ``dyq.quantize_model(..., calibration=...)`` and then saved. ``min_act_bits``
    (``{layer-name pattern: bits}``, as :func:`dyq.quantize_model` takes it) is the floor on the width of the
    layers it matches. ``rotation`` is a rotated model's description (``model.dyq_rotation``, from
    :func:`dyq.rotation.rotate_llama`): its weights hold the rotation, and loading attaches the run-time
    rotation of each down_proj's input again. A float checkpoint is not rotated on load (rotate the float
    model, then :func:`dyq.quantize_model` it).

    :func:`dyq.quantize_model` sets one on a transformers model it converts (``model.config.quantization_config``),
    so that ``save_pretrained`` after it writes a checkpoint that ``from_pretrained`` loads back."""

    def __init__(self, group_size: int = 128, act_bits: int = 16, modules_to_not_convert=("lm_head",),
                 weight_method: str = WEIGHT_METHODS[0], rotation: dict | None = None,
                 min_act_bits: dict[str, int] | None = None, **kwargs: Any):
        self.quant_method = "dyq"
        self.group_size = check_group_size(group_size)
        self.act_bits = check_bits(act_bits, "act_bits")
        if isinstance(modules_to_not_convert, str):  # one name, not its characters
            modules_to_not_convert = [modules_to_not_convert]
        self.modules_to_not_convert = list(modules_to_not_convert or ())
        if not all(isinstance(name, str) for name in self.modules_to_not_convert):
            raise TypeError(f"modules_to_not_convert must be layer names (strings), got {modules_to_not_convert!r}")
        if weight_method not in WEIGHT_METHODS:
            raise ValueError(f"weight_method must be one of {WEIGHT_METHODS}, got {weight_method!r}")
        self.weight_method, self.rotation = weight_method, _checked_rotation(rotation)
        if min_act_bits is not None and not isinstance(min_act_bits, dict):
            raise TypeError(f"min_act_bits must be a dict {{layer-name pattern: bits}}, got {min_act_bits!r}")
        for pattern, bits in (min_act_bits or {}).items():
            if not isinstance(pattern, str):
                raise TypeError(f"min_act_bits: patterns must be layer names or globs (strings), got {pattern!r}")
            check_bits(bits, f"min_act_bits[{pattern!r}]")
        self.min_act_bits = dict(min_act_bits) if min_act_bits else None


def _checked_rotation(rotation) -> dict | None:
    """None, or ``{"kind": "hadamard", "seed": int >= 0, "construction": one of HADAMARD_CONSTRUCTIONS}``."""
    if rotation is None:
        return None
    from ..rotation import HADAMARD_CONSTRUCTIONS

    described = isinstance(rotation, dict) and set(rotation) == {"kind", "seed", "construction"}
    seed = rotation["seed"] if described else None
    if (not described or rotation["kind"] != "hadamard" or isinstance(seed, bool) or not isinstance(seed, int)
            or seed < 0 or rotation["construction"] not in HADAMARD_CONSTRUCTIONS):
        raise ValueError("rotation must be None or a rotated model's description, {'kind': 'hadamard', 'seed': "
                         f"int >= 0, 'construction': one of {HADAMARD_CONSTRUCTIONS}}} (model.dyq_rotation), got "
                         f"{rotation!r}")
    return dict(rotation)


@register_quantizer("dyq")
class DyQHfQuantizer(HfQuantizer):
    """Quantizes on load (a float checkpoint) or rebuilds DyQLinear layers (a dyq checkpoint)."""

    requires_calibration = False

    def _targets(self, model: nn.Module):
        skip = tuple(self.quantization_config.modules_to_not_convert)
        readers = weight_readers(model)  # layers quantize_model leaves alone too
        return [(name, module) for name, module in model.named_modules()
                if (type(module) is nn.Linear or is_transposed_linear(module)) and not _matches(name, skip)
                and id(module) not in readers]

    def _check_stored_layers(self, model, targets, checkpoint_files) -> None:
        """The layers the checkpoint stores in INT4 must be those modules_to_not_convert leaves to convert:
        a shell the checkpoint does not fill would run on uninitialized codes, and a float layer whose weight
        it does not hold on random ones. Checked where the loader names safetensors files (transformers 5)."""
        files = [str(f) for f in checkpoint_files or () if str(f).endswith(".safetensors")]
        if not files:
            return
        from safetensors import safe_open

        stored = set()
        for file in files:
            with safe_open(file, framework="pt") as f:
                stored.update(key[: -len(".qweight")] for key in f.keys() if key.endswith(".qweight"))
        if not stored:
            return

        def same_layer(a: str, b: str) -> bool:  # a checkpoint of the base model lacks the head's prefix, or has more
            return a == b or a.endswith("." + b) or b.endswith("." + a)

        names = [name for name, _ in targets]
        unfilled = [name for name in names if not any(same_layer(name, s) for s in stored)]
        in_float = sorted(s for s in stored if not any(same_layer(name, s) for name in names))
        if unfilled or in_float:
            self._refuse_mismatch(unfilled, in_float)

    def _refuse_mismatch(self, unfilled, in_float) -> None:
        raise ValueError(
            f"quantization_config.modules_to_not_convert={self.quantization_config.modules_to_not_convert} does "
            f"not match the checkpoint: it would convert {unfilled[:5]}, whose INT4 tensors the checkpoint "
            f"lacks, and keep in float {in_float[:5]}, which it stores in INT4; restore the list it was "
            "saved with")

    # transformers 4.x names the keys its load found and did not find (5.x passes the checkpoint's files to
    # _process_model_before_weight_loading instead, where _check_stored_layers reads them).
    def update_missing_keys(self, model, missing_keys, prefix):
        if self.pre_quantized:
            unfilled = sorted({key.rsplit(".", 1)[0] for key in missing_keys if key.endswith((".qweight", ".scales"))})
            if unfilled:
                self._refuse_mismatch(unfilled, [])
        return missing_keys

    def update_unexpected_keys(self, model, unexpected_keys):
        if self.pre_quantized:
            in_float = sorted({key.rsplit(".", 1)[0] for key in unexpected_keys
                               if key.endswith((".qweight", ".scales"))})
            if in_float:
                self._refuse_mismatch([], in_float)
        return unexpected_keys

    def _process_model_before_weight_loading(self, model, **kwargs):
        config = self.quantization_config
        if not self.pre_quantized:
            if config.rotation is not None:
                raise ValueError("rotation is a rotated checkpoint's description; a float checkpoint is not rotated "
                                 "on load: rotate the float model with dyq.rotation.rotate_llama, then "
                                 "dyq.quantize_model it")
            return
        method = next(m for m, saved in WEIGHT_METHOD_NAMES.items() if saved == config.weight_method)
        targets = self._targets(model)
        self._check_stored_layers(model, targets, kwargs.get("checkpoint_files"))
        head = model.get_output_embeddings() if hasattr(model, "get_output_embeddings") else None
        if (head is not None and any(linear is head for _, linear in targets)
                and getattr(model.config, "tie_word_embeddings", False)):
            raise ValueError(
                "this checkpoint's LM head is INT4 but its config ties it to the input embeddings, which "
                "transformers then reads as a float weight: load it with dyq.load_quantized(model, directory), "
                "or quantize again keeping lm_head in float (the default modules_to_not_convert)")
        for _, linear in targets:  # shells of the saved shape; the load fills them
            DyQLinear.convert_in_place(linear, group_size=config.group_size, act_bits=config.act_bits,
                                       quantize=False)
            linear.weight_method = method
        route_encoder_layers_through_modules(model)
        # Some architectures' weight initialization, which transformers runs after loading, reaches from a
        # parent into its children's weights (GPT-2 rescales c_proj.weight from its attention and MLP blocks),
        # and a DyQLinear has no weight. A parent that holds no tensor of its own is marked initialized: the
        # checkpoint holds its DyQLinear children's tensors, and its other children are initialized apart.
        for parent in model.modules():
            if (any(isinstance(child, DyQLinear) for child in parent.children())
                    and next(parent.parameters(recurse=False), None) is None
                    and next(parent.buffers(recurse=False), None) is None):
                parent._is_hf_initialized = True

    def _process_model_after_weight_loading(self, model, **kwargs):
        config = self.quantization_config
        flag = PrecisionFlag(config.act_bits)
        if self.pre_quantized:
            layers = [(name, module) for name, module in model.named_modules() if isinstance(module, DyQLinear)]
            # transformers 4.x casts every floating tensor of a quantized checkpoint to the model's dtype, the fp32
            # group scales included (5.x keeps them): the numerics would change without a word.
            rounded = [(name, layer.scales.dtype) for name, layer in layers if layer.scales.dtype != torch.float32]
            if rounded:
                raise ValueError(
                    f"transformers {transformers.__version__} loaded the fp32 group scales of {len(rounded)} DyQLinear "
                    f"layers ({rounded[0][0]}, ...) as {rounded[0][1]}, which would change "
                    "their numerics: load with dtype=torch.float32 (torch_dtype before transformers 4.56; "
                    "model.to(torch.bfloat16) afterwards keeps the scales in fp32), or with transformers 5")
            if config.rotation is not None:
                # The weights hold the rotation; down_proj's run-time input rotation is rebuilt from its seed
                # (non-persistent buffers, so after loading, on the device the weights landed on).
                from ..rotation import attach_online_rotations

                attach_online_rotations(model, config.rotation["seed"], config.rotation["construction"])
                model.dyq_rotation = dict(config.rotation)
            floors = config.min_act_bits or {}
            for name, module in layers:
                module.bind_flag(flag)
                module.place_packed_weights()  # the loader may have put tensors of its own in place
                floor = _floor_of((name,), floors)
                if floor is not None:
                    module.set_min_act_bits(floor)
            fuse_rms_norms(model)  # as quantize_model does on the other branch
        else:
            method = next(m for m, saved in WEIGHT_METHOD_NAMES.items() if saved == config.weight_method)
            if method in CALIBRATED_METHODS:
                raise ValueError(f"weight_method={config.weight_method!r} needs calibration data, which loading "
                                 "cannot pass: quantize with dyq.quantize_model(model, method=..., calibration=...)")
            quantize_model(model, group_size=config.group_size, skip=config.modules_to_not_convert,
                           act_bits=config.act_bits, flag=flag, method=method, min_act_bits=config.min_act_bits)
            model.config.quantization_config = config  # the one it was loaded with (quantize_model sets its own)
        return model

    def param_needs_quantization(self, model, param_name: str, **kwargs) -> bool:
        return False  # weights load as they are; conversion happens after loading

    def is_serializable(self, safe_serialization=None) -> bool:
        return True

    @property
    def is_trainable(self) -> bool:
        return True  # adapters train beside the frozen INT4 weights
