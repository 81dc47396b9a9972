"""onnxruntime sessions: provider choice, threads, shape checks, dynamic batch, warm-up, timing.

``OnnxModel(spec)`` opens the model file the registry resolves (sha256 checked),
picks the best execution provider present (TensorRT, CUDA, CoreML, else CPU; one
log line says which), checks the graph's input against the description, and —
for graphs exported with a fixed batch of 1 — makes the batch dimension dynamic
once with the ``onnx`` package, caching the edited graph beside the download
cache. If the edited graph cannot run a batch of 2 (a Reshape with a hard-coded
1 inside), the original is kept and batches are run one item at a time.

I/O binding is not used: on the CPU provider inputs are already zero-copy
numpy buffers, so it would not pay; on CUDA the per-frame tensors are small.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from roomcap.core.fileio import atomic_path
from roomcap.keypoints.registry import ModelError, ModelSpec, cache_dir, file_sha256, get_spec, resolve

log = logging.getLogger(__name__)

PROVIDER_ORDER = (
    "TensorrtExecutionProvider",
    "CUDAExecutionProvider",
    "CoreMLExecutionProvider",
    "CPUExecutionProvider",
)


@dataclass(frozen=True)
class RuntimeConfig:
    """Session settings. ``providers`` empty = best available; ``threads`` 0 = onnxruntime's default."""

    providers: tuple[str, ...] = ()
    threads: int = 0
    # make a fixed batch of 1 dynamic; None = only on GPU providers: on the CPU provider the rewritten graph
    # ran a single item 30-50 % slower and a batch of 4 no faster per item than 4 runs of the original
    # (yolox_nano 85 vs 93 ms, blazepose_full 120 vs 116 ms per item, interleaved, 2 loaded cores)
    dynamic_batch: bool | None = None
    warmup_runs: int = 1
    model_dir: str = ""


def choose_providers(wanted: tuple[str, ...] = ()) -> list[str]:
    available = ort.get_available_providers()
    if wanted:
        missing = [p for p in wanted if p not in available]
        if missing:
            raise RuntimeError(
                f"execution provider(s) {missing} are not available; available: {available}. "
                "Install onnxruntime-gpu for CUDA/TensorRT."
            )
        return list(wanted)
    chosen = [p for p in PROVIDER_ORDER if p in available]
    return chosen or ["CPUExecutionProvider"]


def session_options(threads: int = 0) -> ort.SessionOptions:
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    if threads:
        so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    return so


def _dims(shape) -> list:
    return [d if isinstance(d, int) else None for d in shape]


def make_batch_dynamic(src: Path, dst: Path) -> None:
    """Rewrite the first dimension of every graph input and output as the symbol ``N``."""
    import onnx

    model = onnx.load(str(src))
    for vi in list(model.graph.input) + list(model.graph.output):
        dims = vi.type.tensor_type.shape.dim
        if len(dims):
            dims[0].ClearField("dim_value")
            dims[0].dim_param = "N"
    del model.graph.value_info[:]  # stale intermediate shapes would pin the batch again
    # Reshape targets exported as constants with a leading 1 (tf2onnx, torch.onnx with a traced batch):
    # 0 copies the input's first dimension, which is the batch.
    from onnx import numpy_helper

    consts = {t.name: t for t in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type == "Constant":
            for a in node.attribute:
                if a.name == "value":
                    consts[node.output[0]] = a.t
    for node in model.graph.node:
        if node.op_type != "Reshape" or len(node.input) < 2 or node.input[1] not in consts:
            continue
        if any(a.name == "allowzero" and a.i == 1 for a in node.attribute):
            continue
        tensor = consts[node.input[1]]
        shape = numpy_helper.to_array(tensor).copy()
        if shape.ndim == 1 and len(shape) > 1 and shape[0] == 1:
            shape[0] = 0
            tensor.CopyFrom(numpy_helper.from_array(shape, tensor.name))
    with atomic_path(dst) as tmp:
        onnx.save(model, str(tmp))


class OnnxModel:
    """One onnxruntime session for a described model. ``run(x)`` takes (B, ...) and returns the outputs
    the decoder names, each with a leading B; ``run_s`` accumulates the time spent in ``session.run``."""

    def __init__(self, spec: str | ModelSpec, config: RuntimeConfig | None = None):
        self.config = config or RuntimeConfig()
        self.spec = get_spec(spec, self.config.model_dir or None)
        self.path = resolve(self.spec, self.config.model_dir or None)
        self.sha256 = file_sha256(self.path)
        self.providers = choose_providers(self.config.providers)
        self.run_s = 0.0
        self.run_cpu_s = 0.0  # this thread's CPU time in session.run (all of it when intra-op threads = 1)
        self.n_runs = 0
        self.max_batch: int | None = None  # None = any
        self.session = self._open(self.path)
        self._check_signature()
        fixed = self.session.get_inputs()[0].shape[0]
        if fixed == 1:
            self.max_batch = 1
            dyn = self.config.dynamic_batch
            if dyn is None:
                dyn = self.providers[0] != "CPUExecutionProvider"
            if dyn:
                self._try_dynamic()
        log.info(
            "model %s (%s) on %s, batch %s",
            self.spec.name,
            self.path.name,
            self.session.get_providers()[0],
            "dynamic" if self.max_batch is None else self.max_batch,
        )
        for _ in range(self.config.warmup_runs):
            self.run(np.zeros(self.spec.input.tensor_shape(1), dtype=self.spec.input.dtype))
        self.run_s, self.run_cpu_s, self.n_runs = 0.0, 0.0, 0

    def _open(self, path: Path) -> ort.InferenceSession:
        try:
            return ort.InferenceSession(
                str(path), sess_options=session_options(self.config.threads), providers=self.providers
            )
        except Exception as e:  # onnxruntime raises its own exception types
            raise ModelError(
                f"model '{self.spec.name}': onnxruntime cannot load {path}: {e}. " + self.spec.where_to_get()
            ) from e

    def _check_signature(self) -> None:
        inp = {i.name: i for i in self.session.get_inputs()}
        outs = {o.name for o in self.session.get_outputs()}
        spec_in = self.spec.input
        if spec_in.name not in inp:
            raise ModelError(
                f"model '{self.spec.name}' ({self.path}): input '{spec_in.name}' from the description "
                f"{self.spec.source} is not in the graph (inputs: {sorted(inp)}). Fix input.name."
            )
        got = _dims(inp[spec_in.name].shape)
        want = list(spec_in.tensor_shape(None))
        if len(got) != 4 or any(
            g is not None and w is not None and g != w for g, w in zip(got, want, strict=False)
        ):
            raise ModelError(
                f"model '{self.spec.name}' ({self.path}): input shape {inp[spec_in.name].shape} does "
                f"not match the description's {spec_in.layout} {spec_in.size_wh[0]}x"
                f"{spec_in.size_wh[1]} (expected {['B' if w is None else w for w in want]}). "
                f"Fix input.size_wh / input.layout in {self.spec.source}."
            )
        want_type = {"float32": "tensor(float)", "uint8": "tensor(uint8)"}[spec_in.dtype]
        if inp[spec_in.name].type != want_type:
            raise ModelError(
                f"model '{self.spec.name}': input type {inp[spec_in.name].type}, description says "
                f"{spec_in.dtype}. Fix input.dtype in {self.spec.source}."
            )
        missing = [o for o in self.spec.decoder.outputs if o not in outs]
        if missing:
            raise ModelError(
                f"model '{self.spec.name}': outputs {missing} named in {self.spec.source} are not in "
                f"the graph (outputs: {sorted(outs)}). Fix decoder.outputs."
            )

    def _try_dynamic(self) -> None:
        dyn = cache_dir() / "dynamic" / f"{self.sha256[:16]}-{self.path.name}"
        failed = dyn.with_name(dyn.name + ".failed")
        if failed.exists():
            return
        try:
            if not dyn.exists():
                make_batch_dynamic(self.path, dyn)
            so = session_options(self.config.threads)
            so.log_severity_level = 4  # a failure here is expected for some graphs and handled below
            sess = ort.InferenceSession(str(dyn), sess_options=so, providers=self.providers)
            x = np.zeros(self.spec.input.tensor_shape(2), dtype=self.spec.input.dtype)
            outs = sess.run(list(self.spec.decoder.outputs), {self.spec.input.name: x})
            if any(o.shape[0] != 2 for o in outs):
                raise ValueError(f"outputs {[o.shape for o in outs]} lost the batch")
        except Exception as e:  # any failure: keep the fixed-batch graph
            log.info("model %s: batch stays 1 (%s)", self.spec.name, str(e).splitlines()[0][:200])
            try:
                failed.parent.mkdir(parents=True, exist_ok=True)
                failed.write_text(str(e)[:2000])
            except OSError:
                pass
            return
        self.session, self.max_batch = sess, None

    def run(self, x: np.ndarray) -> list[np.ndarray]:
        """x: the input tensor (B, ...) in the description's layout/dtype. Returns the decoder's outputs."""
        names = list(self.spec.decoder.outputs)
        if self.max_batch is None or len(x) <= self.max_batch:
            t, c = time.perf_counter(), time.thread_time()
            out = self.session.run(names, {self.spec.input.name: x})
            self.run_s += time.perf_counter() - t
            self.run_cpu_s += time.thread_time() - c
            self.n_runs += 1
            return out
        parts = [self.run(x[i : i + 1]) for i in range(len(x))]
        return [np.concatenate([p[k] for p in parts]) for k in range(len(names))]

    @property
    def device(self) -> str:
        return self.session.get_providers()[0]
