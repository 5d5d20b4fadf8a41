"""Files a config names for the whole run, opened and checked when the config is (issue 41).

``fit.body_model_path`` and ``fit.pose_prior_path`` (read in full with the restricted, bounded
loaders of storage/body_model_files.py), ``fit.cliff_path`` and the ``detect.models`` ONNX files
(a readable regular file of a plausible size), and the bundled BlazePose files (their sha256):
a bad one is not any sequence's failure but the config's, so it is refused before any unit runs
(exit 2, one line naming the key and the file) and nothing published is withdrawn. Per-sequence
files (a CLIFF table under ``fit.init_dir``, ground truth) fail their own sequence as before.
"""

from __future__ import annotations

from pathlib import Path

from configs.schema import Config
from storage.body_model_files import MAX_MODEL_FILE_BYTES, BodyFileError, UnsafePickleError
from storage.files import InputError, open_regular, regular_stat
from storage.network_files import ModelFileError, bundled_model


class ConfigFileError(InputError):
    """A file the config names that cannot be used (exit 2 before any work)."""


def check_model_file(key: str, path: Path) -> None:
    """A network file (ONNX / TFLite): a readable, non-empty regular file of at most
    MAX_MODEL_FILE_BYTES (a device such as /dev/zero, a FIFO, a folder or a huge file refused)."""
    try:
        st = regular_stat(path, what="model file")
        if st.st_size == 0 or st.st_size > MAX_MODEL_FILE_BYTES:
            raise InputError(
                f"{path}: the model file is {st.st_size} bytes (expected 1 to "
                f"{MAX_MODEL_FILE_BYTES})",
                path,
            )
        with open_regular(path, what="model file") as fh:
            fh.read(16)
    except InputError as exc:
        raise ConfigFileError(f"{key}: {exc}", path) from None
    except OSError as exc:
        raise ConfigFileError(f"{key}: {path}: cannot read ({exc.strerror or exc})", path) from None


def check_config_files(config: Config) -> None:
    """Open and check every run-wide file ``config`` names (module docstring); raises
    ConfigFileError naming the key and the file. The body model and prior are loaded through
    the stages' per-process caches, so an inline run does not read them twice."""
    from flows.stages.common import _load_model, _load_prior

    f = config.fit
    for key, path, load in (
        ("fit.body_model_path", f.body_model_path, _load_model),
        ("fit.pose_prior_path", f.pose_prior_path, _load_prior),
    ):
        if path is None:
            continue
        try:
            load(str(path))
        except (BodyFileError, UnsafePickleError) as exc:
            raise ConfigFileError(f"{key}: {exc}", path) from None
    if f.init_provider == "cliff" and f.cliff_path is not None:
        check_model_file("fit.cliff_path", f.cliff_path)
    det = config.detect
    if det.image_provider != "models":
        return
    m = det.models
    for name, part, used in (
        ("detector", m.detector, m.detector.kind != "lidar"),
        ("keypoints", m.keypoints, m.keypoints.kind in ("vitpose", "rtmpose")),
        ("masks", m.masks, m.masks.kind == "mask2former"),
        ("semantic", m.semantic, m.semantic.kind == "onnx"),
    ):
        if used and part.path is not None:
            check_model_file(f"detect.models.{name}.path", part.path)
    if m.keypoints.kind == "blazepose":
        try:
            bundled_model(m.bundled_dir, "pose_landmark_full.tflite")
        except ModelFileError as exc:
            raise ConfigFileError(f"detect.models.bundled_dir: {exc}", m.bundled_dir) from None
