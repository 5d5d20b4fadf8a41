"""Which perception source each stage of a run will use, and which settings read the simulator's
ground truth (``gt/<SEQ>/`` beside the data, storage/GT_FORMAT.md).

The default config reads no ground truth (configs/default.yaml); configs/oracle.yaml and the
files that extend it do. A run whose config needs ``gt/`` where a sequence has none is refused
before any work (``rebuild`` / ``reprocess`` / ``demo``: exit 2), and ``check-data`` prints the
sources per sequence and refuses the same way, so a setting that reads the truth is never silent.

The places that read ``gt/`` in a run (a new one is added to :func:`truth_settings`):

- detect: ``detect.image_provider: oracle`` and ``detect.lidar_provider: oracle``
  (flows/stages/providers.py OracleImage / OracleLidar); ``detect.models.semantic.kind: oracle``
  with ``image_provider: models`` (the oracle's semantics and ground-truth identities);
- fit: ``fit.init_provider: oracle`` (OracleInit: the ground-truth bodies perturbed);
- fuse: ``fuse.body_source: ground-truth`` (flows/stages/fuse.py: the simulator's bodies).

``evaluate``, ``export --gt`` and ``show``'s ground-truth view read it too, on request only.
"""

from __future__ import annotations

from pathlib import Path

from configs.schema import Config
from storage.gt import gt_dir

#: setting -> (the value that reads gt/, the value of the default path)
TRUTH_SETTINGS: dict[str, tuple[str, str]] = {
    "detect.image_provider": ("oracle", "models"),
    "detect.models.semantic.kind": ("oracle", "none"),
    "detect.lidar_provider": ("oracle", "lidar-clusters"),
    "fit.init_provider": ("oracle", "lidar-keypoints"),
    "fuse.body_source": ("ground-truth", "fit"),
}


def truth_settings(config: Config) -> list[str]:
    """The settings of ``config`` that make a run read the simulator's ground truth (keys of
    :data:`TRUTH_SETTINGS`), in stage order."""
    d = config.detect
    values = {
        "detect.image_provider": d.image_provider,
        # the semantic model runs only under image_provider 'models'
        "detect.models.semantic.kind": d.models.semantic.kind
        if d.image_provider == "models"
        else None,
        "detect.lidar_provider": d.lidar_provider,
        "fit.init_provider": config.fit.init_provider,
        "fuse.body_source": config.fuse.body_source,
    }
    return [key for key, (truth, _) in TRUTH_SETTINGS.items() if values[key] == truth]


def stage_sources(config: Config) -> dict[str, str]:
    """What each stage will use, in words: detect image / lidar, semantics, fit start, fuse
    bodies; a source that reads the ground truth says so ("(gt/)")."""
    d, m = config.detect, config.detect.models
    gt = " (gt/)"
    if d.image_provider == "models":
        boxes = (
            "LiDAR boxes" if m.detector.kind == "lidar" else f"{m.detector.kind} {m.detector.path}"
        )
        image = f"models: boxes {boxes}, keypoints {m.keypoints.kind}, masks {m.masks.kind}"
        semantics = {"oracle": "oracle" + gt, "none": "none (no image semantics)"}.get(
            m.semantic.kind, f"{m.semantic.kind} {m.semantic.path}"
        )
    elif d.image_provider == "oracle":
        image, semantics = "oracle" + gt, "oracle" + gt
    else:
        image = semantics = f"precomputed {d.precomputed_dir}"
    lidar = {"oracle": "oracle" + gt, "precomputed": f"precomputed {d.precomputed_dir}"}.get(
        d.lidar_provider, d.lidar_provider
    )
    f = config.fit
    start = {
        "oracle": "oracle" + gt,
        "precomputed": f"precomputed CLIFF {f.init_dir}",
        "cliff": f"CLIFF {f.cliff_path}",
    }.get(f.init_provider, f.init_provider)
    bodies = "ground-truth" + gt if config.fuse.body_source == "ground-truth" else "fitted bodies"
    return {
        "detect image": image,
        "detect lidar": lidar,
        "semantics": semantics,
        "fit start": start,
        "fuse bodies": bodies,
    }


def truth_folder(config: Config, sequence: str) -> Path:
    """Where the ground truth of ``sequence`` would be: ``ROOT/gt/SEQ`` for the CODa layout,
    ``gt/SEQ`` beside the log for robot logs (as `mobileocc simulate --format mcap` writes it)."""
    from flows.pipeline.inputs import source
    from storage.sources.log.bag import find_logs

    root = Path(config.dataset.root)
    if source(config).kind == "log":
        log = find_logs(root).get(sequence)
        base = log.parent if log is not None else (root if root.is_dir() else root.parent)
        return gt_dir(base, sequence)
    return gt_dir(root, sequence)


def has_truth(config: Config, sequence: str) -> bool:
    return (truth_folder(config, sequence) / "sequence.npz").is_file()


def source_lines(config: Config, sequences: list[str]) -> list[str]:
    """One line per sequence: the source of each stage and whether the run can have them."""
    sources = "; ".join(f"{k} {v}" for k, v in stage_sources(config).items())
    needs = truth_settings(config)
    lines = []
    for seq in sequences:
        if not needs:
            verdict = "reads no gt/"
        elif has_truth(config, seq):
            verdict = "reads gt/ (present)"
        else:
            verdict = f"NEEDS gt/: {truth_folder(config, seq)} missing"
        lines.append(f"  {seq}: {sources}; {verdict}")
    return lines


def truth_problem(config: Config, sequences: list[str], config_path: Path | None) -> str | None:
    """None when the run can have what its config reads; else one message naming the sequences
    without ground truth, the settings to change and the config to use."""
    needs = truth_settings(config)
    if not needs:
        return None
    lacking = [s for s in sequences if not has_truth(config, s)]
    if not lacking:
        return None
    shown = ", ".join(lacking[:5]) + (f" and {len(lacking) - 5} more" if len(lacking) > 5 else "")
    change = ", ".join(f"{k}: {TRUTH_SETTINGS[k][1]} (not {TRUTH_SETTINGS[k][0]})" for k in needs)
    given = f"config {config_path}" if config_path is not None else "the config"
    return (
        f"{given} reads the simulator's ground truth (gt/), which sequence(s) {shown} lack "
        f"(no {truth_folder(config, lacking[0]) / 'sequence.npz'}): set {change}, or run "
        "with the default config (no --config: it reads no gt/); configs/oracle.yaml is for "
        "simulated data with gt/ only"
    )


def model_problem(config: Config) -> str | None:
    """None when the bundled models the config runs are in place; else the error that says to
    run `make setup` (checked before a run, not in the detect stage of every sequence)."""
    from storage.network_files import ModelFileError, bundled_model

    d, m = config.detect, config.detect.models
    if d.image_provider != "models" or "blazepose" not in (m.keypoints.kind, m.masks.kind):
        return None
    try:
        bundled_model(m.bundled_dir, "pose_landmark_full.tflite")
    except ModelFileError as exc:
        return f"detect.models (the bundled BlazePose): {exc}"
    return None


def run_problem(config: Config, sequences: list[str], config_path: Path | None) -> str | None:
    """What keeps a run of ``sequences`` from starting (gt/ the config reads but a sequence lacks,
    bundled models not extracted), in one message; None when nothing does."""
    return truth_problem(config, sequences, config_path) or model_problem(config)
