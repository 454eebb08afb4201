"""The kernel API: the ops (``torch.ops.dyq``), the precision registry, the reference numerics,
``DyQLinear`` and whole-model quantization."""
