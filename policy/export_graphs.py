"""The policy's ONNX graphs, traced from torch: obs_encoder.onnx, denoiser.onnx and the locators' graphs, with
the I/O contract (names, shapes, dtypes) every graph is declared and checked with (policy/export.py writes the
bundle around them; policy/bundle_manifest.py checks a manifest's graphs against the same contract).
"""

from __future__ import annotations

import copy
import warnings
from pathlib import Path

import torch

from policy.config import TEXT_DIM, PolicyConfig
from policy.goal_locator import LocatorGraph
from policy.graph_frames import with_grasp, with_release
from policy.model import DiffusionPolicy, film_dim, prepare_images

OPSET = 17


def _onnx_export(module, args, path: Path, inputs: list[str], outputs: list[str], dynamic: dict, opset: int):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legacy (TorchScript) exporter's deprecation and tracer notes
        # dynamo=False: the torch.export-based exporter needs onnxscript, which this project does not ship
        torch.onnx.export(module, args, str(path), input_names=inputs, output_names=outputs, dynamic_axes=dynamic,
                          opset_version=opset, dynamo=False, do_constant_folding=True)


def _write_graph(module, args, path: Path, spec: dict, opset: int, fp16: bool) -> dict:
    """Export one policy graph with the contract's I/O; returns its weight-storage figures."""
    import onnx

    from policy.fp16 import weight_only_fp16

    names = {k: [i["name"] for i in spec[k]] for k in ("inputs", "outputs")}
    _onnx_export(module, args, path, names["inputs"], names["outputs"],
                 {n: {0: "B"} for n in names["inputs"] + names["outputs"]}, opset)
    model = _declare_io(onnx.load(str(path)), spec)
    info = {"dtype": "float32"}
    if fp16:
        model, converted = weight_only_fp16(model)
        info = {"dtype": "float16", **converted}
    onnx.save(model, str(path))
    return info


def _declare_io(model, spec: dict):
    """Write the contract's shapes into the graph's declared inputs/outputs (the tracer leaves some output
    dims symbolic, e.g. a Concat's width), so onnxruntime reports exactly what the manifest says."""
    import onnx

    for values, specs in ((model.graph.input, spec["inputs"]), (model.graph.output, spec["outputs"])):
        by_name = {v.name: v for v in values}
        for io in specs:
            dims = by_name[io["name"]].type.tensor_type.shape.dim
            for d, want in zip(dims, io["shape"]):
                if isinstance(want, int):
                    d.dim_value = want
                else:
                    d.dim_param = want
    onnx.checker.check_model(model)
    return model


def _io(name: str, shape: list, dtype: str) -> dict:
    return {"name": name, "shape": shape, "dtype": dtype}


def graph_specs(cfg: PolicyConfig) -> dict:
    """The I/O contract of every graph, as written to the manifest and checked by the loader."""
    To, Tp, Da, Dp, G = cfg.obs_horizon, cfg.pred_horizon, cfg.action_dim, cfg.proprio_input_dim, film_dim(cfg)
    H, W = cfg.image_size
    release = ([_io("release_point", ["B", 4], "float32")] + ([_io("grasp_point", ["B", 4], "float32")]
                                                              if cfg.grasp_input else []),
               [_io("aux_points", ["B", cfg.aux_dim], "float32")]) if cfg.release_input else ([], [])
    return {
        "obs_encoder": {"file": "obs_encoder.onnx",
                        "inputs": [_io(f"image_{c}", ["B", To, H, W, 3], "uint8") for c in cfg.cameras]
                        + [_io("proprio", ["B", To, Dp], "float32"), _io("text_embedding", ["B", cfg.text_input_dim], "float32")]
                        + release[0],
                        "outputs": [_io("cond", ["B", G], "float32")] + release[1]},
        "denoiser": {"file": "denoiser.onnx",
                     "inputs": [_io("noisy_actions", ["B", Tp, Da], "float32"), _io("timestep", ["B"], "int64"),
                                _io("cond", ["B", G], "float32")],
                     "outputs": [_io("noise_pred", ["B", Tp, Da], "float32")]},
        "text_encoder": {"file": "text_encoder.onnx",
                         "inputs": [_io("input_ids", ["B", "L"], "int64"), _io("attention_mask", ["B", "L"], "int64")],
                         "outputs": [_io("embedding", ["B", TEXT_DIM], "float32")]},
    }


class _ObsGraph(torch.nn.Module):
    """obs_encoder.onnx: raw uint8 frames per camera, proprio, text -> cond = the denoiser's FiLM input
    computed from the global cond once per chunk (ConditionalUnet1D.condition). With cfg.release_input also
    release_point in (policy.graph_frames.with_release) and the head's aux_points out."""

    def __init__(self, model: DiffusionPolicy):
        super().__init__()
        self.model, self.cameras, self.crop = model, model.cfg.cameras, model.cfg.crop_size

    def forward(self, *args):
        n = len(self.cameras)
        images = {c: prepare_images(x, self.crop) for c, x in zip(self.cameras, args[:n])}
        proprio, text = args[n], args[n + 1]
        if not self.model.cfg.release_input:
            return self.model.unet.condition(self.model.encode(images, proprio, text))
        features = self.model.obs_encoder(images, proprio, text)
        points = self.model.aux_points(features)
        given = with_release(points, args[n + 2])
        if self.model.cfg.grasp_input:
            given = with_grasp(given, args[n + 3], proprio, self.model.proprio_scale, self.model.proprio_offset)
        cond = self.model.cond_from(features, proprio, given)
        return self.model.unet.condition(cond), points


class _StepGraph(torch.nn.Module):
    """denoiser.onnx: one denoising step from the precomputed FiLM cond (ConditionalUnet1D.denoise)."""

    def __init__(self, model: DiffusionPolicy):
        super().__init__()
        self.unet = model.unet

    def forward(self, noisy, timestep, cond):
        return self.unet.denoise(noisy, timestep, cond)


def write_policy_graphs(model: DiffusionPolicy, out_dir: Path, opset: int = OPSET, fp16: bool = True) -> dict:
    """Trace obs_encoder.onnx and denoiser.onnx of `model` into out_dir; their weight-storage figures by graph.
    The one place the policy graphs are traced: export, and policy.bundle_import's probes, which must get the
    same nodes."""
    cfg = model.cfg
    specs = graph_specs(cfg)
    g = torch.Generator().manual_seed(0)
    H, W = cfg.image_size
    ex_imgs = [torch.randint(0, 256, (1, cfg.obs_horizon, H, W, 3), generator=g, dtype=torch.uint8)
               for _ in cfg.cameras]
    ex_p, ex_t = torch.randn(1, cfg.obs_horizon, cfg.proprio_input_dim), torch.randn(1, cfg.text_input_dim)
    so, sd = specs["obs_encoder"], specs["denoiser"]
    ex = ((*ex_imgs, ex_p, ex_t) + ((torch.tensor([[0.1, 0.4, 0.1, 1.0]]),) if cfg.release_input else ())
          + ((torch.tensor([[0.2, 0.5, 0.05, 1.0]]),) if cfg.grasp_input else ()))
    info = {"obs_encoder": _write_graph(_ObsGraph(model), ex, out_dir / so["file"], so, opset, fp16)}
    with torch.no_grad():
        cond = _ObsGraph(model)(*ex)
        cond = cond[0] if cfg.release_input else cond
    info["denoiser"] = _write_graph(_StepGraph(model), (torch.randn(1, cfg.pred_horizon, cfg.action_dim),
                                                        torch.tensor([5]), cond), out_dir / sd["file"], sd, opset, fp16)
    return info


def _write_locator(locator: DiffusionPolicy, out_dir: Path, spec: dict, opset: int, fp16: bool) -> dict:
    """Trace goal_locator.onnx (policy/goal_locator.py); its weight-storage figures."""
    cfg = locator.cfg
    g = torch.Generator().manual_seed(1)
    H, W = cfg.image_size
    ex = tuple(torch.randint(0, 256, (1, cfg.obs_horizon, H, W, 3), generator=g, dtype=torch.uint8)
               for _ in cfg.cameras) + (torch.randn(1, cfg.text_input_dim),)
    return _write_graph(LocatorGraph(locator), ex, out_dir / spec["file"], spec, opset, fp16)


def _rounded(m: DiffusionPolicy | None) -> DiffusionPolicy | None:
    """A copy of a locator with its weights rounded to float16, as the graphs will hold them (None stays None)."""
    from policy.fp16 import round_weights_

    if m is None:
        return None
    m = copy.deepcopy(m).eval().cpu()
    round_weights_(m)
    return m
