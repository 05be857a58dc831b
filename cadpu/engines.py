"""Inference engines for the learned, deterministic part of the CAD-PU generator on a CPU.

A forward pass is split in two (`cadpu.network.Generator`): `expansion` (curvature, local frames
and the seeded curvature-adaptive draw of every output point's parent) always runs in torch, so
the parents are exactly those of torch eager for a given seed; `decode` (feature extractor with its
feature-space kNN, expansion MLP, regression and the offsets) is deterministic given those and is
what an engine runs. An engine is a callable

    decode(points (B, N, 3), parents (B, M), rank (B, M), frames (B, N, 3, 3), radius (B, N))
        -> (B, M, 3) float32 torch tensor

on CPU tensors. Engines that need an optional package (onnxruntime, openvino) raise
EngineUnavailable when it is missing; `cadpu.inference.Upsampler` then falls back to eager.
docs/inference.md compares them (bench/inference.py).
"""

from __future__ import annotations

import contextlib
import copy
import importlib
import io
import warnings
from collections.abc import Callable

import torch
from torch import nn

from .network import DenseEdgeConv, Generator

Decode = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]

#: Every engine, named <runtime>[-<data type>]; fp32 unless named otherwise.
ENGINES = ("eager", "eager-bf16", "eager-bf16-head", "eager-int8", "compile", "onnxruntime", "onnxruntime-int8",
           "openvino", "openvino-bf16")
#: The packages each engine needs beyond torch (onnx: torch's ONNX exporter writes through it).
REQUIRES = {"onnxruntime": ("onnxruntime", "onnx"), "onnxruntime-int8": ("onnxruntime", "onnx"),
            "openvino": ("openvino", "onnx"), "openvino-bf16": ("openvino", "onnx")}
#: Points per patch of the exported graphs (traced at that size; only the batch axis is dynamic).
EXPORTED_PATCH_POINTS = 256
#: The engines that run an exported graph, and so take patches of EXPORTED_PATCH_POINTS only.
EXPORTED = tuple(name for name in ENGINES if name in REQUIRES)
#: Memory layouts of the EdgeConv edge tensors (see `cadpu.network.DenseEdgeConv`).
LAYOUTS = DenseEdgeConv.LAYOUTS
#: The layout each exported graph is traced with when none is asked for: point-major edges turn
#: the max-pools into contiguous ReduceMax ops, which onnxruntime runs faster.
EXPORT_LAYOUT = "point-major"
#: Largest and mean distance (unit-sphere units of the normalised patch) allowed between an fp32
#: engine's generated points and torch eager's; parents must be identical.
FP32_TOLERANCE = (1e-4, 1e-6)
_INPUTS = ("points", "parents", "rank", "frames", "radius")


class EngineUnavailable(RuntimeError):
    """The engine's package is not installed (or cannot load) in this environment."""


def available(engine: str) -> bool:
    """Whether `engine`'s packages (if any) import here (an engine not in ENGINES is not available)."""
    if engine not in ENGINES:
        return False
    try:
        for package in REQUIRES.get(engine, ()):
            importlib.import_module(package)
    except ImportError:
        return False
    return True


class _Decoder(nn.Module):
    """`Generator.decode` as a module's forward, for export and compilation."""

    def __init__(self, generator: Generator) -> None:
        super().__init__()
        self.generator = generator

    def forward(self, points: torch.Tensor, parents: torch.Tensor, rank: torch.Tensor, frames: torch.Tensor,
                radius: torch.Tensor) -> torch.Tensor:
        return self.generator.decode(points, parents, rank, frames, radius)


def set_layout(generator: Generator, layout: str) -> None:
    """Lay out the edge tensors of every EdgeConv block of `generator` as `layout` (one of LAYOUTS)."""
    if layout not in LAYOUTS:
        raise ValueError(f"EdgeConv layout must be one of {LAYOUTS}, got {layout!r}")
    for block in generator.extractor.blocks:
        block.layout = layout


def onnx_model(generator: Generator, ratio: int, layout: str | None = None) -> bytes:
    """Serialised ONNX graph of `generator.decode`, dynamic in the batch axis, traced on two
    random patches at `ratio` (the kNN runs as TopK in the graph: the same neighbour sets), its
    EdgeConv edges laid out as `layout` (None: EXPORT_LAYOUT); `generator` is left as it was."""
    generator = copy.deepcopy(generator)
    set_layout(generator, layout or EXPORT_LAYOUT)
    n = EXPORTED_PATCH_POINTS
    points = torch.rand(2, n, 3) * 2 - 1
    parents = torch.arange(n).repeat_interleave(ratio).expand(2, -1).contiguous()
    rank = torch.arange(ratio).repeat(n).expand(2, -1).contiguous()
    example = (points, parents, rank, torch.eye(3).expand(2, n, 3, 3).contiguous(), torch.full((2, n), 0.1))
    buffer = io.BytesIO()
    axes = {name: {0: "batch"} for name in (*_INPUTS, "generated")}
    # The TorchScript exporter: well under a second and no extra packages; the torch.export one
    # needs onnxscript and takes many seconds on this small graph.
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(_Decoder(generator).eval(), example, buffer, dynamo=False, input_names=list(_INPUTS),
                          output_names=["generated"], dynamic_axes=axes, opset_version=17)
    return buffer.getvalue()


def _eager(generator: Generator, dtype: torch.dtype = torch.float32) -> Decode:
    if dtype != torch.float32:  # weights and activations in `dtype`; the caller's network stays as it is
        generator = copy.deepcopy(generator).to(dtype)

    def decode(points: torch.Tensor, parents: torch.Tensor, rank: torch.Tensor, frames: torch.Tensor,
               radius: torch.Tensor) -> torch.Tensor:
        with torch.inference_mode():
            return generator.decode(points.to(dtype), parents, rank, frames.to(dtype), radius.to(dtype)).float()
    return decode


class _Bfloat16Linear(nn.Module):
    """A linear layer computed in bfloat16 between float32 activations: on a CPU with AMX, oneDNN
    runs the product on its bf16 tiles."""

    def __init__(self, layer: nn.Linear) -> None:
        super().__init__()
        self.weight = layer.weight.detach().to(torch.bfloat16)
        self.bias = None if layer.bias is None else layer.bias.detach().to(torch.bfloat16)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return nn.functional.linear(x.to(torch.bfloat16), self.weight, self.bias).float()


def _bfloat16_head(generator: Generator) -> Generator:
    """A copy of `generator` whose expansion and regression MLPs (the widest layers, over all r * N
    output points) run in bfloat16; the feature extractor, its kNN and the compiled kernels stay
    float32, so neighbour sets do not change."""
    generator = copy.deepcopy(generator)
    generator.expand_feature = _Bfloat16Linear(generator.expand_feature)
    for mlp in (generator.expand, generator.regress):
        for index, layer in enumerate(mlp):
            if isinstance(layer, nn.Linear):
                mlp[index] = _Bfloat16Linear(layer)
    return generator


def _compiled(generator: Generator) -> Decode:
    compiled = torch.compile(_Decoder(generator).eval(), dynamic=False)

    def decode(*inputs: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return compiled(*inputs)
    return decode


def _onnxruntime(generator: Generator, ratio: int, threads: int, int8: bool, layout: str | None) -> Decode:
    import onnxruntime as ort

    model = onnx_model(generator, ratio, layout)
    if int8:  # dynamic quantisation of every MatMul/Gemm (the 1x1 layers and the kNN products)
        import onnx
        from onnxruntime.quantization import QuantType, quantize_dynamic

        source = onnx.load_from_string(model)
        quantised = io.BytesIO()
        with _scratch_dir() as folder:
            onnx.save(source, f"{folder}/fp32.onnx")
            quantize_dynamic(f"{folder}/fp32.onnx", f"{folder}/int8.onnx", weight_type=QuantType.QInt8)
            with open(f"{folder}/int8.onnx", "rb") as handle:
                quantised.write(handle.read())
        model = quantised.getvalue()
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    # Spinning threads steal the core from the Dask worker beside this one.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    session = ort.InferenceSession(model, options, providers=["CPUExecutionProvider"])

    def decode(*inputs: torch.Tensor) -> torch.Tensor:
        feed = {name: value.numpy() for name, value in zip(_INPUTS, inputs)}
        return torch.from_numpy(session.run(None, feed)[0])
    return decode


def _openvino(generator: Generator, ratio: int, threads: int, precision: str, layout: str | None) -> Decode:
    import openvino as ov

    core = ov.Core()
    with _scratch_dir() as folder:
        with open(f"{folder}/decode.onnx", "wb") as handle:
            handle.write(onnx_model(generator, ratio, layout))
        model = core.read_model(f"{folder}/decode.onnx")
    # OpenVINO runs bf16 by default on CPUs that have it: f32 must be asked for.
    compiled = core.compile_model(model, "CPU", {"INFERENCE_NUM_THREADS": threads,
                                                 "INFERENCE_PRECISION_HINT": precision,
                                                 "PERFORMANCE_HINT": "LATENCY"})
    request = compiled.create_infer_request()
    output = compiled.output(0)

    def decode(*inputs: torch.Tensor) -> torch.Tensor:
        result = request.infer({name: value.numpy() for name, value in zip(_INPUTS, inputs)})
        return torch.from_numpy(result[output].copy())
    return decode


@contextlib.contextmanager
def _scratch_dir():
    import tempfile

    with tempfile.TemporaryDirectory(prefix="cadpu-engine-") as folder:
        yield folder


def build(engine: str, generator: Generator, ratio: int, threads: int | None = None,
          layout: str | None = None) -> Decode:
    """An engine running `generator.decode` on CPU tensors.

    Args:
        engine: one of ENGINES. generator: the loaded network (eval mode, CPU).
        ratio: output points per input point of one pass (the trained ratio, times
            `Upsampler.oversample` when it makes candidates to select from).
        threads: intra-op threads of onnxruntime or openvino (None: torch's current setting).
        layout: EdgeConv layout of an exported graph (None: EXPORT_LAYOUT); torch engines use the
            generator's own (`set_layout`).

    Returns:
        The decode callable (see the module docstring).

    Raises:
        ValueError for an unknown engine; EngineUnavailable when its package is missing.
    """
    if engine not in ENGINES:
        raise ValueError(f"unknown inference engine {engine!r}; choose one of {('auto', *ENGINES)}")
    if not available(engine):
        raise EngineUnavailable(f"inference engine {engine!r} needs the packages {' and '.join(REQUIRES[engine])} "
                                f"(pip install 'kitti-pu[engines]')")
    threads = threads or torch.get_num_threads()
    if engine == "eager":
        return _eager(generator)
    if engine == "eager-bf16":
        return _eager(generator, torch.bfloat16)
    if engine == "eager-bf16-head":
        return _eager(_bfloat16_head(generator))
    if engine == "eager-int8":
        # The 1x1 layers called as modules; DenseEdgeConv's layer2/layer3 weights feed in-place
        # matrix products directly and stay float32.
        layers = {name for name, module in _Decoder(generator).named_modules() if isinstance(module, nn.Linear)
                  and not name.endswith(("layer2", "layer3"))}
        with warnings.catch_warnings():  # torch.ao.quantization is deprecated in favour of torchao
            warnings.simplefilter("ignore")
            quantised = torch.ao.quantization.quantize_dynamic(_Decoder(generator), layers, dtype=torch.qint8)
        return _eager(quantised.generator)
    if engine == "compile":
        return _compiled(generator)
    if engine.startswith("onnxruntime"):
        return _onnxruntime(generator, ratio, threads, engine.endswith("int8"), layout)
    return _openvino(generator, ratio, threads, "bf16" if engine.endswith("bf16") else "f32", layout)
