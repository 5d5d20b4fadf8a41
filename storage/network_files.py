"""Model files -> runners: the only place that opens network weights.

``open_onnx(path, device)`` loads an ONNX file into an onnxruntime session (CPU, or CUDA where the
``onnxruntime-gpu`` build and a GPU are present); ``open_tflite(path)`` loads a TFLite file into
an ai-edge-litert interpreter. Both return a runner (the contract of
:class:`tasks.perception.models.runner.ModelRunner`): ``source``, ``input_shapes``,
``output_shapes``, ``__call__(feeds) -> outputs``. The adapters in tasks/perception/models/
check the signature against what their model family exports and name the file when it differs.

The bundled BlazePose models: ``bundled_model(cache, name)`` is a ``.tflite`` file that set-up
(``make setup``: ``mobileocc models unpack-bundled``, :func:`extract_bundled_models`) extracted
once from the ``mediapipe`` wheel; nothing is fetched at run time.
"""

from __future__ import annotations

import hashlib
import os
import threading
import zipfile
from pathlib import Path

import numpy as np

from storage.atomic import atomic_write_bytes
from tasks.perception.models.settings import DEFAULT_BUNDLED_CACHE as DEFAULT_BUNDLED_CACHE
from tasks.perception.models.settings import MEDIAPIPE_VERSION

#: file name -> (path inside the wheel, sha256 of the file)
BUNDLED_MODELS = {
    "pose_detection.tflite": (
        "mediapipe/modules/pose_detection/pose_detection.tflite",
        "9ba9dd3d42efaaba86b4ff0122b06f29c4122e756b329d89dca1e297fd8f866c",
    ),
    "pose_landmark_full.tflite": (
        "mediapipe/modules/pose_landmark/pose_landmark_full.tflite",
        "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f",
    ),
}
#: the checkout (or installed tree) this module lives in
_CHECKOUT = Path(__file__).resolve().parents[1]


class ModelFileError(ValueError):
    """A model file is missing, unreadable, or not what its adapter expects."""


def _shape(dims) -> tuple[int | None, ...]:
    return tuple(d if isinstance(d, int) and d > 0 else None for d in dims)


class OnnxRunner:
    """An onnxruntime session as a runner (sessions are safe to call from several threads)."""

    def __init__(self, path: str | os.PathLike, device: str = "cpu", threads: int = 0):
        import onnxruntime as ort

        path = Path(path)
        if not path.is_file():
            raise ModelFileError(f"{path}: model file not found")
        available = ort.get_available_providers()
        if device == "auto":
            device = "cuda" if "CUDAExecutionProvider" in available else "cpu"
        if device == "cuda" and "CUDAExecutionProvider" not in available:
            raise ModelFileError(
                f"{path}: device 'cuda' asked for, but this onnxruntime offers only {available} "
                "(install onnxruntime-gpu on GPU workers)"
            )
        providers = (["CUDAExecutionProvider"] if device == "cuda" else []) + [
            "CPUExecutionProvider"
        ]
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        if threads:
            opts.intra_op_num_threads = threads
        try:
            self.session = ort.InferenceSession(str(path), sess_options=opts, providers=providers)
        except Exception as error:  # onnxruntime raises its own exception types
            raise ModelFileError(f"{path}: not a loadable ONNX model ({error})") from error
        self.source = str(path)
        self.device = device
        self.input_shapes = {i.name: _shape(i.shape) for i in self.session.get_inputs()}
        self.output_shapes = {o.name: _shape(o.shape) for o in self.session.get_outputs()}

    def __call__(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        names = list(self.output_shapes)
        return dict(zip(names, self.session.run(names, feeds)))


class TfliteRunner:
    """An ai-edge-litert interpreter as a runner (one call at a time: interpreters are not
    thread-safe, so calls take a lock)."""

    def __init__(self, path: str | os.PathLike, threads: int = 1):
        from ai_edge_litert.interpreter import Interpreter

        path = Path(path)
        if not path.is_file():
            raise ModelFileError(f"{path}: model file not found")
        try:
            self.interpreter = Interpreter(model_path=str(path), num_threads=threads)
            self.interpreter.allocate_tensors()
        except (ValueError, RuntimeError) as error:
            raise ModelFileError(f"{path}: not a loadable TFLite model ({error})") from error
        self.source = str(path)
        self._inputs = {d["name"]: d["index"] for d in self.interpreter.get_input_details()}
        self._outputs = {d["name"]: d["index"] for d in self.interpreter.get_output_details()}
        self.input_shapes = {
            d["name"]: tuple(int(x) for x in d["shape"])
            for d in self.interpreter.get_input_details()
        }
        self.output_shapes = {
            d["name"]: tuple(int(x) for x in d["shape"])
            for d in self.interpreter.get_output_details()
        }
        self._lock = threading.Lock()

    def __call__(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        with self._lock:
            for name, value in feeds.items():
                self.interpreter.set_tensor(
                    self._inputs[name], np.ascontiguousarray(value, np.float32)
                )
            self.interpreter.invoke()
            return {
                name: self.interpreter.get_tensor(i).copy() for name, i in self._outputs.items()
            }


def open_onnx(path: str | os.PathLike, device: str = "cpu") -> OnnxRunner:
    """An ONNX file as a runner; device 'cpu', 'cuda' or 'auto' (CUDA where offered)."""
    return OnnxRunner(path, device)


def open_tflite(path: str | os.PathLike) -> TfliteRunner:
    """A TFLite file as a runner."""
    return TfliteRunner(path)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def bundled_model(cache: str | os.PathLike, name: str) -> Path:
    """The extracted bundled model ``name`` under ``cache``; a clear error when set-up has not
    extracted it (nothing is downloaded here). A relative ``cache`` is looked up in the working
    directory, then in the checkout `make setup` ran in, so a run from a data folder finds it."""
    if name not in BUNDLED_MODELS:
        raise ModelFileError(f"{name}: not a bundled model; bundled: {sorted(BUNDLED_MODELS)}")
    cache = Path(cache)
    tried = [cache / name]
    if not cache.is_absolute():
        tried.append(_CHECKOUT / cache / name)
    for path in tried:
        if path.is_file():
            # an unpacked file is a cache product: verified before use (its sha256, cheap next
            # to loading the network); a damaged one is unpacked again by `make setup`
            digest = _sha256(path)
            if digest != BUNDLED_MODELS[name][1]:
                raise ModelFileError(
                    f"{path}: damaged (sha256 {digest[:12]}..., expected "
                    f"{BUNDLED_MODELS[name][1][:12]}...); run `make setup` (or `mobileocc models "
                    f"unpack-bundled --wheel mediapipe-{MEDIAPIPE_VERSION}-*.whl --cache {cache}`)"
                )
            return path
    raise ModelFileError(
        f"{' or '.join(map(str, tried))}: bundled model missing; run `make setup` (or `mobileocc "
        f"models unpack-bundled --wheel mediapipe-{MEDIAPIPE_VERSION}-*.whl --cache {cache}`)"
    )


def extract_bundled_models(wheel: str | os.PathLike, cache: str | os.PathLike) -> list[Path]:
    """Copy the bundled .tflite files out of a downloaded mediapipe wheel into ``cache`` (checked
    against their sha256; files already there and intact are kept). Returns their paths."""
    wheel, cache = Path(wheel), Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    out = []
    with zipfile.ZipFile(wheel) as zf:
        for name, (member, digest) in BUNDLED_MODELS.items():
            target = cache / name
            if not (target.is_file() and _sha256(target) == digest):
                try:
                    data = zf.read(member)
                except KeyError:
                    raise ModelFileError(
                        f"{wheel}: has no {member} (mediapipe {MEDIAPIPE_VERSION} ships it)"
                    ) from None
                if hashlib.sha256(data).hexdigest() != digest:
                    raise ModelFileError(
                        f"{wheel}: {member} has sha256 {hashlib.sha256(data).hexdigest()}, "
                        f"expected {digest}"
                    )
                atomic_write_bytes(target, data)
            out.append(target)
    return out
