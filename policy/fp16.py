"""Float16 weight storage for the policy graphs (obs_encoder.onnx, denoiser.onnx): half the bytes on disk.

    Initializer W (float32)  ->  Cast(W16, to=float32)        W16 float16, stored in the file

Weight-only, like policy.quantize.weight_only_int8: onnxruntime constant-folds the Cast when it creates the
session, so inference still runs in fp32 at fp32 speed; only the stored values change. Export rounds the
torch weights to fp16-representable values first (`round_weights_`), so the Cast is exact and the graph
reproduces that torch model bit for bit; what the rounding itself costs is measured against the unrounded
model and recorded in the manifest. Small tensors (biases, norm scales, folded constants such as the
timestep frequencies) stay float32: they are a negligible share of the bytes.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

MIN_ELEMENTS = 256
SUFFIX = "__fp16"  # the stored float16 copy of initializer W is named W + SUFFIX (policy.bundle_import reads it)


def round_weights_(module) -> None:
    """Round every parameter of a torch module to the nearest float16 value, in place (kept as float32)."""
    for p in module.parameters():
        p.data = p.data.half().float()


def weight_only_fp16(model: onnx.ModelProto, min_elements: int = MIN_ELEMENTS) -> tuple[onnx.ModelProto, dict]:
    """A copy of `model` whose float32 initializers of >= min_elements values are stored as float16, and
    figures: how many were converted and the largest relative change a conversion made (0 when the weights
    were rounded beforehand)."""
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    casts: list[onnx.NodeProto] = []
    worst = 0.0
    for t in list(graph.initializer):
        if t.data_type != TensorProto.FLOAT or int(np.prod(t.dims)) < min_elements:
            continue
        w = numpy_helper.to_array(t)
        h = w.astype(np.float16)
        if not np.all(np.isfinite(h)):  # beyond fp16's range (65504): keep float32 rather than store inf
            continue
        worst = max(worst, float(np.abs(h.astype(np.float32) - w).max() / max(float(np.abs(w).max()), 1e-30)))
        graph.initializer.remove(t)
        graph.initializer.append(numpy_helper.from_array(h, t.name + SUFFIX))
        casts.append(helper.make_node("Cast", [t.name + SUFFIX], [t.name], to=TensorProto.FLOAT,
                                      name=f"{t.name}__cast"))
    # The Cast outputs keep the old names, so no consumer changes; Casts go first (they read only initializers)
    nodes = casts + list(graph.node)
    del graph.node[:]
    graph.node.extend(nodes)
    onnx.checker.check_model(model)
    return model, {"converted": len(casts), "min_elements": min_elements, "max_rel_change": worst}
