"""The `mobileocc` command line. Heavy imports happen inside the commands."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import NoReturn

import yaml

from tasks.bounds import MAX_SIMULATED_FRAMES


def _add_config_args(p: argparse.ArgumentParser, runtime: bool = True) -> None:
    p.add_argument(
        "--config", type=Path, default=None, help="config YAML (default: configs/default.yaml)"
    )
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config key, e.g. --set fuse.grid.voxel_size_m=0.1 (repeatable)",
    )
    p.add_argument("--data", type=Path, default=None, help="dataset root (dataset.root)")
    p.add_argument("--out", type=Path, default=None, help="output store (output.root)")
    if runtime:
        p.add_argument(
            "--workers",
            type=_at_least(1),
            default=None,
            help="Dask / thread workers (dask.workers)",
        )
        p.add_argument(
            "--runner", choices=["thread", "dask"], default=None, help="task runner (dask.runner)"
        )
        p.add_argument(
            "--address",
            default=None,
            help="existing Dask scheduler, e.g. tcp://host:8786 (dask.address)",
        )


def _config(args: argparse.Namespace, built: bool = False):
    """The config of a command line; ``built``: with no --config, the one the dataset at --out was
    built with (status, reprocess, export: flows/commands/build_config.py)."""
    from configs.schema import load_config

    overrides = {}
    for item in args.overrides:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--set {item!r}: expected KEY=VALUE, e.g. --set fit.iterations=50")
        try:
            overrides[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError as exc:
            problem = str(getattr(exc, "problem", "") or exc).splitlines()[0]
            raise UsageError(
                f"--set {item!r}: the value {value!r} is not YAML ({problem}); quote it for a "
                f"string, e.g. --set '{key.strip()}=\"{value}\"'"
            ) from None
    for attr, key in (
        ("data", "dataset.root"),
        ("out", "output.root"),
        ("workers", "dask.workers"),
        ("runner", "dask.runner"),
        ("address", "dask.address"),
    ):
        value = getattr(args, attr, None)
        if value is not None:
            overrides[key] = str(value) if isinstance(value, Path) else value
    if getattr(args, "address", None):
        overrides["dask.runner"] = "dask"
    if built:
        from flows.commands.build_config import config_for_dataset

        cfg, note = config_for_dataset(args.config, overrides, overrides.get("output.root"))
        if note:
            print(note, file=sys.stderr)
        return cfg
    return load_config(args.config, overrides)


class UsageError(ValueError):
    """A command line that cannot be used (one line, exit 2)."""


def _at_least(low: int):
    """An argparse type: an integer >= ``low`` (argparse prints one usage error otherwise)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be at least {low}, got {value}")
        return value

    return parse


def _in_range(low: int, high: int):
    """An argparse type: a whole number in [low, high] (one usage line otherwise)."""
    at_least = _at_least(low)

    def parse(text: str) -> int:
        value = at_least(text)
        if value > high:
            raise argparse.ArgumentTypeError(f"must be at most {high}, got {value}")
        return value

    return parse


def cmd_config(args: argparse.Namespace) -> int:
    from configs.schema import ConfigError, config_hash, load_config

    if args.action == "validate":
        try:
            cfg = load_config(args.file)
        except ConfigError as exc:
            print(exc, file=sys.stderr)
            return 1
        print(f"{args.file}: valid (hash {config_hash(cfg)})")
        return 0
    cfg = _config(args)
    print(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False), end="")
    print(f"# config hash: {config_hash(cfg)}")
    return 0


#: exit codes of rebuild / reprocess / status (also in `mobileocc --help`)
EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_BUSY = 0, 1, 2, 3
EXIT_CODES = (
    "exit codes: 0 every sequence and frame went through; 1 a sequence failed, was skipped or "
    "lost frames, or a write failed (the summary lists each with its reason); 2 a usage, config, "
    "--data or --out problem; 3 the output store is in use by another run"
)


def _run(args: argparse.Namespace, force: bool) -> int:
    # before prefect is imported: its settings are read once; per-task INFO lines would bury the
    # progress bars and the summary (PREFECT_LOGGING_LEVEL=INFO brings them back)
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    # Prefect's temporary server gets 20 s to start by default: a busy machine (a build beside
    # the run, other agents) misses that and the run fails before its first stage
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
    from flows.commands.perception_sources import run_problem
    from flows.pipeline.plan import PlanCosts, plan_without_hashing
    from flows.pipeline.units import (
        check_run_paths,
        run_units,
        summary_table,
        unclassified_line,
    )
    from storage.manifest import FingerprintCache, Manifest, run_lock

    cfg = _config(args, built=args.command == "reprocess")
    ids, out, verify = check_run_paths(cfg), Path(cfg.output.root), getattr(args, "verify", False)
    if (problem := run_problem(cfg, ids, args.config)) is not None:
        raise UsageError(problem)  # before any work: gt/ the config reads, the bundled models
    prune = getattr(args, "prune", False)
    if cfg.dask.address:
        from flows.pipeline.runtime import check_scheduler

        check_scheduler(cfg.dask.address)
    with run_lock(out):  # a second run is refused here, before any server starts
        costs = PlanCosts()
        plans = plan_without_hashing(
            cfg,
            Manifest.load(out),
            FingerprintCache(out / ".cache" / "sequences", verify),
            force,
            ids,
            costs,
        )
        if plans is not None and all(u.fresh for plan in plans for u in plan.units.values()):
            report = run_units(
                cfg,
                force,
                ids,
                progress=False,
                verify=verify,
                plans=plans,
                lock_held=True,
                prune=prune,
            )
            report.costs = costs  # nothing to run: no task runner, no Prefect server
        else:
            report = _run_flow(cfg, force, not args.quiet, verify, prune=prune)
    print(summary_table(report))
    warning = unclassified_line(report, cfg)
    if warning:
        print(warning)
    return report.exit_code


def _run_flow(cfg, force: bool, progress: bool, verify: bool, prune: bool = False):
    from flows.pipeline.local import run_without_prefect, uses_prefect

    if not uses_prefect(cfg):
        return run_without_prefect(
            cfg, force=force, progress=progress, verify=verify, lock_held=True, prune=prune
        )
    from flows.pipeline.run import rebuild_dataset
    from flows.pipeline.runtime import prefect_api

    with prefect_api():
        report = rebuild_dataset(
            cfg, force=force, progress=progress, verify=verify, lock_held=True, prune=prune
        )
    if isinstance(report, Exception):  # a full disk stopped the run (flows.pipeline.run)
        raise report
    return report


def cmd_rebuild(args: argparse.Namespace) -> int:
    return _run(args, force=args.force)


def cmd_reprocess(args: argparse.Namespace) -> int:
    if args.dry_run:
        return _print_plan(args, dry_run=True)
    return _run(args, force=False)


def _print_plan(args: argparse.Namespace, dry_run: bool) -> int:
    from flows.commands.status import print_plan

    cfg = _config(args, built=True)
    return EXIT_FAILED if print_plan(cfg, dry_run, args.verify) else EXIT_OK


def cmd_status(args: argparse.Namespace) -> int:
    return _print_plan(args, dry_run=False)


def cmd_export(args: argparse.Namespace) -> int:
    from flows.pipeline.inputs import dataset_export_inputs
    from flows.pipeline.run import export_dataset

    if args.gt and args.format != "occ3d":
        print(
            f"--gt exports Occ3D labels; it does not apply to --format {args.format}",
            file=sys.stderr,
        )
        return 2
    from storage.publish import reading

    cfg = _config(args, built=True)
    explicit = args.data is not None or any(
        o.partition("=")[0].strip() == "dataset.root" for o in args.overrides
    )
    with reading(cfg.output.root):  # no run changes the dataset while it is exported
        target = export_dataset(
            dataset_export_inputs(cfg),
            cfg.output.root,
            cfg.dataset.root if explicit else None,  # None: where the dataset was built from
            args.format,
            args.to,
            gt=args.gt,
        )
    print(f"{args.format} export{' of the ground truth' if args.gt else ''} written to {target}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from flows.commands.confusion_report import console_text
    from flows.commands.report import section_table
    from storage.publish import reading

    with reading(args.dataset):  # no run changes the dataset while it is evaluated
        if args.labels == "coda":
            from flows.commands.evaluate_coda import evaluate_coda

            res = evaluate_coda(args.dataset, args.gt, args.report)
        else:
            from flows.commands.evaluate import evaluate

            res = evaluate(args.dataset, args.gt, args.report)
    text = console_text(res)
    if text:
        print(text + "\n")
    if "label_honesty" in res:  # computed with or without ground truth
        print(f"label honesty:\n{section_table('label_honesty', res['label_honesty'])}\n")
    for key, title in (("detection", "automatic"), ("detection_manual_qa", "manual QA")):
        if key in res:  # the paper's Table 4 bottom, computed and checked by hand
            print(f"detection robustness ({title}):\n{section_table(key, res[key])}\n")
    for key, note in sorted((res.get("notes") or {}).items()):
        if "withdrawn" in note["note"]:
            print(f"NOT EVALUATED {key}: {note['note']}")
    print(
        f"report: {args.report / 'report.md'} (figures in {args.report / 'figures'}, "
        f"numbers in {args.report / 'results.json'})"
    )
    return 0


def cmd_check_data(args: argparse.Namespace) -> int:
    from flows.commands.check_data import check_data

    code, text = check_data(_config(args), deep=args.deep, config_path=args.config)
    print(text)
    return code


def _write_json(path: Path | None, value) -> None:
    if path is not None:
        from storage.atomic import atomic_write_text

        atomic_write_text(path, json.dumps(value, indent=1, default=str) + "\n")


def _csv(kind=str, choices: tuple = ()):
    """An argparse type: comma-separated values of ``kind`` (each one of ``choices``, if any)."""

    def parse(text: str) -> tuple:
        values = tuple(kind(v.strip()) for v in text.split(",") if v.strip())
        unknown = sorted(set(values) - set(choices)) if choices else []
        if unknown:
            raise argparse.ArgumentTypeError(f"unknown {unknown}; expected some of {list(choices)}")
        return values

    return parse


def cmd_bench(args: argparse.Namespace) -> int:
    from flows.bench.pipeline import bench

    bench(args.quick, args.json, args.workers)
    return 0


def cmd_bench_scale(args: argparse.Namespace) -> int:
    from flows.bench.scale import bench_scale

    bench_scale(
        args.frames,
        args.sequences,
        args.cluster_workers,
        args.parts,
        args.json,
        sim_long_frames=args.sim_frames,
        sim_workers=args.workers,
        memory_frames=args.memory_frames,
    )
    return 0


def cmd_bench_fit(args: argparse.Namespace) -> int:
    import dataclasses

    from flows.bench import fit as fb
    from tasks.fit.settings import FitSettings, InitLidarSettings

    fit = _config(args).fit
    weights, settings = fit.weights, fit.to(FitSettings)
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    sensor = args.sensors[-1]
    if args.save_pool:
        fb.save_pool(args.save_pool, fb.simulated_pool(args.pool, sensor, args.seed))
        print(f"{args.pool} persons ({sensor}) saved to {args.save_pool}")
        return 0
    pool = fb.load_pool(args.pool_file) if args.pool_file else None
    if args.agreement:
        pool = pool or fb.simulated_pool(args.pool, sensor, args.seed)
        print(json.dumps(fb.device_agreement(pool, args.device, weights)))
        return 0
    if args.throughput:
        rate = fb.bench_throughput(
            args.persons, args.device, weights, settings, args.pool, sensor, args.seed, pool
        )
        print(json.dumps(rate))
        return 0
    results = fb.bench_fit(
        args.persons,
        weights,
        settings,
        args.sensors,
        not args.no_ablations,
        args.device,
        seed=args.seed,
        warm_start=args.warm_start,
        ablation_sensors=args.ablation_sensors,
        start_settings=fit.init_lidar.to(InitLidarSettings)
        if fit.init_provider == "lidar-keypoints"
        else None,
    )
    results["settings"] = {
        "preset": fit.preset,
        "start": "lidar-keypoints" if fit.init_provider == "lidar-keypoints" else "oracle",
        "weights": dataclasses.asdict(weights),
        "fit": dataclasses.asdict(settings),
    }
    _write_json(args.json, {"argv": args.argv, **results})
    return 0


def cmd_bench_fit_tracks(args: argparse.Namespace) -> int:
    import torch

    from flows.bench.fit_tracks import bench_tracks
    from tasks.fit.settings import FitSettings, FlipSettings, InitLidarSettings, RefineSettings

    torch.set_num_threads(args.threads)
    fit = _config(args).fit
    res = bench_tracks(
        args.tracks,
        args.frames,
        fit.weights,
        fit.to(FitSettings),
        fit.init_lidar.to(InitLidarSettings),
        fit.flips.to(FlipSettings),
        fit.refine.to(RefineSettings),
        args.init,
        args.rate_hz,
        args.sensor,
        args.seed,
        args.swap_back_views,
        tuple(args.methods),
    )
    _write_json(args.json, {"argv": args.argv, **res})
    return 0


def cmd_bench_occupancy(args: argparse.Namespace) -> int:
    from flows.bench.occupancy import bench_occupancy, format_table

    out = bench_occupancy(args.quick)
    print(json.dumps(out, indent=2))
    print(format_table(out))
    return 0


def cmd_bench_perception(args: argparse.Namespace) -> int:
    from flows.bench.perception import bench_perception

    result = bench_perception(_config(args), args.boxes)
    print(json.dumps(result, indent=1))
    _write_json(args.json, result)
    return 0


def cmd_bench_geometric_classes(args: argparse.Namespace) -> int:
    from flows.bench.geometric_classes import bench_geometric_classes, format_table

    result = bench_geometric_classes(_config(args), args.every)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def cmd_bench_lidar_people(args: argparse.Namespace) -> int:
    from flows.bench.lidar_people import bench_lidar_people

    result = bench_lidar_people(_config(args), args.multipath, args.ground)
    print(json.dumps(result, indent=1))
    _write_json(args.json, result)
    return 0


def cmd_bench_track_confirm(args: argparse.Namespace) -> int:
    from flows.bench.track_confirm import bench_track_confirm

    result = bench_track_confirm(_config(args), args.log_frames)
    print(json.dumps(result, indent=1))
    _write_json(args.json, result)
    return 0


def cmd_bench_planning(args: argparse.Namespace) -> int:
    import shutil
    import tempfile

    from flows.bench.planning import bench_planning, format_table

    work = args.work or Path(tempfile.mkdtemp(prefix="mobileocc-bench-planning-"))
    try:
        result = bench_planning(args.sizes, work)
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    print(format_table(result))
    _write_json(args.json, result)
    return 0


def cmd_bench_memory(args: argparse.Namespace) -> int:
    from flows.bench.memory import bench_memory, format_table

    result = bench_memory(args.frames, args.work, untiled=args.untiled, stages=tuple(args.stages))
    _write_json(args.json, result)
    print(format_table(result))
    return 0


def cmd_bench_logs(args: argparse.Namespace) -> int:
    from flows.bench.logs import bench_logs, format_table

    result = bench_logs(args.sweeps, args.work, keep=args.keep)
    _write_json(args.json, result)
    print(format_table(result))
    return 0


def cmd_bench_overhead(args: argparse.Namespace) -> int:
    from flows.bench.overhead import bench_overhead

    print(json.dumps(bench_overhead(args.sequences, args.frames), indent=1))
    return 0


def cmd_bench_viewer(args: argparse.Namespace) -> int:
    from flows.bench.viewer import bench_viewer

    result = bench_viewer(
        args.dataset,
        args.sequence,
        args.frame,
        browser=not args.no_browser,
        synthetic=not args.no_synthetic,
        keep=args.keep,
        screenshot=args.screenshot,
    )
    print(json.dumps(result, indent=1))
    _write_json(args.json, result)
    return 0


def _add_bench_parsers(sub) -> None:
    from flows.bench import scale

    p = sub.add_parser(
        "bench",
        help="measure speeds, memory and reference ratios: `mobileocc bench [--quick]` (the "
        "pipeline) or `mobileocc bench fit | fit-tracks | occupancy | perception | "
        "geometric-classes | planning | "
        "memory | scale | overhead | viewer | logs [options]`",
        description="Without BENCHMARK: the pipeline benchmark (flows/bench/pipeline.py) with the "
        "options below; `mobileocc bench BENCHMARK --help` for the others.",
    )
    p.add_argument("--quick", action="store_true", help="20 raw frames instead of 60")
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    p.add_argument("--workers", type=int, default=2, help="fuse fan-out workers")
    p.set_defaults(func=cmd_bench)
    bench = p.add_subparsers(dest="benchmark", metavar="BENCHMARK")

    s = bench.add_parser(
        "scale",
        help="long sequences, many sequences, a loopback cluster, the 116k-frame projection "
        "(flows/bench/scale.py, docs/scale.md)",
    )
    for flag, default, text in (
        ("--frames", scale.DEFAULT_FRAMES, "5 Hz frames of the long-sequence runs"),
        ("--sequences", scale.DEFAULT_SEQUENCES, "sequences of the planning datasets"),
        ("--cluster-workers", scale.DEFAULT_CLUSTER_WORKERS, "worker counts of the Dask cluster"),
        ("--memory-frames", scale.MEMORY_FRAMES, "5 Hz frames of the memory part's sequences"),
    ):
        shown = ",".join(map(str, default))
        s.add_argument(flag, type=_csv(int), default=default, help=f"{text} (default {shown})")
    s.add_argument(
        "--parts",
        type=_csv(str, scale.PARTS),
        default=scale.PARTS,
        help=f"which parts (default {','.join(scale.PARTS)})",
    )
    s.add_argument(
        "--sim-frames", type=int, default=2000, help="raw frames of the simulator's long sequence"
    )
    s.add_argument("--workers", type=int, default=2, help="simulator worker processes")
    s.add_argument("--json", type=Path, default=None)
    s.set_defaults(func=cmd_bench_scale)

    f = bench.add_parser(
        "fit", help="the body fit on simulated persons: accuracy per sensor, ablations, fits/s"
    )
    _add_config_args(f, runtime=False)
    f.add_argument("--persons", type=int, default=32)
    f.add_argument("--sensors", type=_csv(), default=("ouster-32", "ouster-64", "ouster-128"))
    f.add_argument("--no-ablations", action="store_true")
    f.add_argument(
        "--ablation-sensors",
        type=_csv(),
        default=None,
        help="comma-separated sensors that get the ablation rows (default: all)",
    )
    f.add_argument("--device", default="cpu")
    f.add_argument("--warm-start", action="store_true")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument(
        "--json", type=Path, default=None, help="also write the results (means, stds) here"
    )
    f.add_argument(
        "--throughput",
        action="store_true",
        help="only speed: fits/s of one batch of --persons on --device, one JSON line",
    )
    f.add_argument("--pool", type=int, default=64, help="--throughput: distinct simulated persons")
    f.add_argument(
        "--save-pool",
        type=Path,
        default=None,
        help="simulate the --pool persons (and their initial estimates), save them to this .npz, exit",
    )
    f.add_argument(
        "--pool-file",
        type=Path,
        default=None,
        help="--throughput / --agreement: persons saved by --save-pool (no simulator needed)",
    )
    f.add_argument(
        "--agreement",
        action="store_true",
        help="fit the pool on the CPU and on --device (twice); print how they agree, one JSON line",
    )
    f.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch intra-op threads (default: torch's, every core); on a shared CPU 1 per "
        "process avoids OpenMP spin-waiting",
    )
    f.set_defaults(func=cmd_bench_fit)

    t = bench.add_parser(
        "fit-tracks",
        help="the fit along tracks (swaps, one shape, refinement) against frame by frame: "
        "MPJPE, acceleration error, shape spread, CPU s per fit (flows/bench/fit_tracks.py)",
    )
    _add_config_args(t, runtime=False)
    t.add_argument("--tracks", type=int, default=12)
    t.add_argument("--frames", type=int, default=10)
    t.add_argument("--rate-hz", type=float, default=5.0)
    t.add_argument("--sensor", default="ouster-128")
    t.add_argument("--init", default="oracle", choices=("oracle", "lidar-keypoints"))
    t.add_argument(
        "--swap-back-views",
        type=float,
        default=0.0,
        help="probability that a track seen from behind has its keypoints mirrored left / right",
    )
    t.add_argument(
        "--methods", type=_csv(choices=("per-frame", "tracks")), default=("per-frame", "tracks")
    )
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    t.add_argument("--json", type=Path, default=None, help="also write the results here")
    t.set_defaults(func=cmd_bench_fit_tracks)

    o = bench.add_parser(
        "occupancy", help="free-space insertion vs octomap-python; map and fuse frames/s"
    )
    o.add_argument("--quick", action="store_true")
    o.set_defaults(func=cmd_bench_occupancy)

    q = bench.add_parser(
        "perception", help="2D detection, keypoints and masks of the configured providers vs GT"
    )
    _add_config_args(q, runtime=False)
    q.add_argument("--boxes", choices=["provider", "gt"], default="provider")
    q.add_argument("--json", type=Path, default=None)
    q.set_defaults(func=cmd_bench_perception)

    c = bench.add_parser(
        "geometric-classes",
        help="per-point classes from geometry (map.point_classes geometry) vs the simulator's "
        "point labels: precision / recall / IoU per class, confusion (docs/geometric-classes.md)",
    )
    _add_config_args(c, runtime=False)
    c.add_argument("--every", type=_at_least(1), default=1, help="every N-th 5 Hz frame")
    c.add_argument("--json", type=Path, default=None)
    c.set_defaults(func=cmd_bench_geometric_classes)

    lp = bench.add_parser(
        "lidar-people", help="the LiDAR people detector vs the simulator's people (+ multipath)"
    )
    _add_config_args(lp, runtime=False)
    lp.add_argument("--multipath", type=_at_least(0), default=0, help="returns below the road")
    lp.add_argument("--ground", choices=["robust", "linefit"], default="robust")
    lp.add_argument("--json", type=Path, default=None)
    lp.set_defaults(func=cmd_bench_lidar_people)

    tc = bench.add_parser(
        "track-confirm", help="tracks confirmed by evidence vs by hit count, on short logs"
    )
    _add_config_args(tc, runtime=False)
    tc.add_argument(
        "--log-frames", type=_csv(int), default=(1, 2, 0), help="log lengths (0: whole sequence)"
    )
    tc.add_argument("--json", type=Path, default=None)
    tc.set_defaults(func=cmd_bench_track_confirm)

    n = bench.add_parser(
        "planning", help="status / reprocess --dry-run / no-op rebuild vs dataset size"
    )
    n.add_argument("sizes", nargs="*", type=int, default=[10, 100, 1000])
    n.add_argument(
        "--work", type=Path, default=None, help="working folder (default: a temporary one, removed)"
    )
    n.add_argument("--json", type=Path, default=None)
    n.set_defaults(func=cmd_bench_planning)

    m = bench.add_parser("memory", help="peak RSS of map and fuse vs sequence length")
    m.add_argument(
        "--work", type=Path, required=True, help="folder for the sequences and outputs (kept)"
    )
    m.add_argument(
        "--frames", type=int, nargs="+", default=[200, 1000, 2000], help="sequence lengths, 5 Hz"
    )
    m.add_argument("--untiled", action="store_true", help="also the whole-sequence SequenceMapper")
    m.add_argument("--stages", nargs="+", default=["map", "fuse"], choices=["map", "fuse"])
    m.add_argument("--json", type=Path, help="write the results here")
    m.set_defaults(func=cmd_bench_memory)

    g = bench.add_parser(
        "logs", help="robot-log decoding: sweeps/s on one core, peak RSS vs the log's length"
    )
    g.add_argument("--work", type=Path, required=True, help="folder for the logs")
    g.add_argument("--sweeps", type=int, nargs="+", default=[100, 1000], help="log lengths")
    g.add_argument("--keep", action="store_true", help="keep the logs")
    g.add_argument("--json", type=Path, default=None, help="also write the results here")
    g.set_defaults(func=cmd_bench_logs)

    v = bench.add_parser(
        "overhead", help="Prefect overhead per sequence on the thread and Dask runners"
    )
    v.add_argument("--sequences", type=int, default=8)
    v.add_argument("--frames", type=int, default=2, help="raw frames per sequence")
    v.set_defaults(func=cmd_bench_overhead)

    w = bench.add_parser(
        "viewer",
        help="the 3D viewer: page size, time to show and Chromium CPU per frame, 0.2 / 0.02 m "
        "(flows/bench/viewer.py, docs/viewer.md)",
    )
    w.add_argument("--dataset", type=Path, default=None, help="also a frame of this dataset")
    w.add_argument("--sequence", default=None)
    w.add_argument("--frame", type=int, default=0)
    w.add_argument("--no-browser", action="store_true", help="skip the Chromium timings")
    w.add_argument("--no-synthetic", action="store_true", help="only the --dataset frame")
    w.add_argument("--keep", type=Path, default=None, help="keep the pages (and screenshots) here")
    w.add_argument("--json", type=Path, default=None)
    w.add_argument(
        "--screenshot", type=Path, default=None, help="with --dataset: the served viewer, as PNG"
    )
    w.set_defaults(func=cmd_bench_viewer)


def cmd_cluster(args: argparse.Namespace) -> int:
    from flows.deploy.clusters import ClusterSpecError, hold_cluster, load_cluster_spec, render

    try:
        spec = load_cluster_spec(args.spec)
    except ClusterSpecError as exc:  # it names the file and the field
        print(exc, file=sys.stderr)
        return 1
    if args.action == "up":
        hold_cluster(spec, args.address_file)
        return 0
    try:
        print(render(spec, args.scheduler), end="")
    except ClusterSpecError as exc:
        print(f"{args.spec}: {exc}", file=sys.stderr)
        return 1
    return 0


def cmd_deploy(args: argparse.Namespace) -> int:
    from flows.deploy import prefect as deploy

    if args.action == "serve":
        deploy.serve()
    elif args.action == "apply":
        for dep_id in deploy.apply_deployments():
            print(dep_id)
    else:
        from configs.schema import load_config

        cfg = load_config(args.config)
        key = args.key or deploy.default_idempotency_key(cfg, args.force, window=args.window)
        run = deploy.trigger_rebuild(cfg, force=args.force, idempotency_key=key)
        print(f"flow run {run.id} ({run.state.name if run.state else 'unknown'}), key {key}")
    return 0


def _add_deploy_parsers(sub) -> None:
    from flows.deploy.clusters import RENDER_SCHEDULER

    p = sub.add_parser("cluster", help="Dask clusters from a spec (infra/slurm.yaml, ...)")
    cluster = p.add_subparsers(dest="action", required=True)
    r = cluster.add_parser("render", help="print the SLURM job scripts or the Kubernetes resources")
    r.add_argument("spec", type=Path)
    r.add_argument("--scheduler", default=RENDER_SCHEDULER, help="scheduler address (SLURM)")
    u = cluster.add_parser(
        "up",
        help="start the spec's cluster (both pools, one scheduler), print the scheduler "
        "address and hold the cluster until interrupted",
    )
    u.add_argument("spec", type=Path)
    u.add_argument("--address-file", type=Path, default=None, help="also write the address here")
    p.set_defaults(func=cmd_cluster)

    p = sub.add_parser("deploy", help="Prefect deployments of the flows, and their trigger")
    deploy = p.add_subparsers(dest="action", required=True)
    deploy.add_parser("serve", help="serve both flows from this process (needs PREFECT_API_URL)")
    deploy.add_parser("apply", help="register both deployments without serving them")
    t = deploy.add_parser("trigger", help="trigger the rebuild deployment")
    t.add_argument("--config", default=None, help="config YAML (default: configs/default.yaml)")
    t.add_argument("--force", action="store_true")
    t.add_argument(
        "--key", default=None, help="idempotency key (default: from the config and --window)"
    )
    t.add_argument("--window", default="", help="part of the default key, e.g. today's date")
    p.set_defaults(func=cmd_deploy)


def cmd_simulate(args: argparse.Namespace) -> int:
    from flows.commands.simulate import simulate

    ids = simulate(
        args.out,
        sequences=args.sequences,
        frames=args.frames,
        seed=args.seed,
        pedestrians=args.pedestrians,
        crowd=args.crowd,
        night=args.night,
        progress=not args.quiet,
        first_id=args.first_id,
        image_ext=f".{args.image_format}",
        split_style=args.split_style,
        fast=args.fast,
        workers=args.workers,
        fmt=args.format,
        log_poses=args.log_poses,
    )
    print(f"wrote sequence(s) {', '.join(map(str, ids))} to {args.out}")
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    from flows.commands.show import ShowError, show
    from storage.layout import StoreError

    try:
        png = show(args.path, args.png, frame=args.frame, sequence=args.sequence)
    except (ShowError, StoreError, FileNotFoundError) as exc:
        print(f"mobileocc show: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(png)
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from flows.commands.view import view
    from flows.viewer.draw import Layers
    from storage.layout import StoreError

    chosen = {"mask": args.mask, "style": args.style, "max_voxels": args.max_voxels}
    layers = Layers(unknown=args.unknown, **{k: v for k, v in chosen.items() if v is not None})
    try:
        return view(
            args.dataset,
            args.sequence,
            args.frame,
            args.port,
            args.host,
            args.html,
            args.frames,
            layers,
            args.qa,
            args.qa_frames,
            args.data,
        )
    except (StoreError, ValueError, OSError) as exc:
        print(f"mobileocc view: {exc}", file=sys.stderr)
        return EXIT_USAGE


def cmd_models(args: argparse.Namespace) -> int:
    import zipfile

    from storage.network_files import (
        DEFAULT_BUNDLED_CACHE,
        ModelFileError,
        extract_bundled_models,
    )

    try:  # action "unpack-bundled", the only one
        paths = extract_bundled_models(args.wheel, args.cache or DEFAULT_BUNDLED_CACHE)
    except (ModelFileError, OSError, zipfile.BadZipFile) as exc:
        print(f"mobileocc models {args.action}: {exc}", file=sys.stderr)
        return EXIT_FAILED
    for path in paths:
        print(path)
    return EXIT_OK


def cmd_demo(args: argparse.Namespace) -> int:
    from flows.commands.simulate import simulate

    data = args.data or Path("demo-data")
    if not (data / "timestamps").is_dir():
        print(f"generating the synthetic demo dataset in {data} ...")
        simulate(
            data,
            sequences=2,
            frames=args.frames,
            seed=0,
            pedestrians=8,
            crowd="crowded",
            progress=not args.quiet,
        )
    args.data = data
    status = _run(args, force=False)
    from flows.commands.evaluate import evaluate

    out = Path(_config(args).output.root)
    report = out / "report"
    evaluate(out, data, report)
    print(f"\ndemo dataset: {out} (Zarr arrays in {out / 'occupancy'}, tables in {out / 'tables'})")
    print(f"evaluation report: {report / 'report.md'} (pictures in {report / 'figures'})")
    return status


class _Parser(argparse.ArgumentParser):
    """argparse, with a usage error in one line (argparse prints the whole usage first, which
    for a command of many options buries the one line that says what is wrong)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (`{self.prog} --help` lists the options)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="mobileocc",
        description="Human-aware 3D semantic occupancy datasets from raw robot sensor logs.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("config", help="show the resolved config and its hash, or validate a file")
    csub = p.add_subparsers(dest="action", required=True)
    ps = csub.add_parser("show", help="print the resolved config and its hash")
    _add_config_args(ps, runtime=False)
    pv = csub.add_parser("validate", help="validate a config file, listing every error by key path")
    pv.add_argument("file", type=Path)
    p.set_defaults(func=cmd_config)

    for name, func, text in (
        (
            "rebuild",
            cmd_rebuild,
            "run every sequence through the pipeline (cached units are reused)",
        ),
        ("reprocess", cmd_reprocess, "run only what is stale (changed inputs, config or code)"),
        ("status", cmd_status, "per sequence and stage: fresh, stale with reason, or failed"),
    ):
        p = sub.add_parser(name, help=text, epilog=EXIT_CODES)
        _add_config_args(p)
        p.add_argument("--quiet", action="store_true", help="no progress bars")
        p.add_argument(
            "--verify",
            action="store_true",
            help="hash every input file and every output against its record (default: a "
            "sequence whose files kept their size, mtime and inode is taken as unchanged, "
            "without reading it, and outputs are checked by their sizes)",
        )
        if name == "rebuild":
            p.add_argument(
                "--force",
                action="store_true",
                help="compute every unit again (outputs of the same key are replaced)",
            )
        if name in ("rebuild", "reprocess"):
            p.add_argument(
                "--prune",
                action="store_true",
                help="take sequences whose input is no longer under --data out of the dataset "
                "(without it they are reported)",
            )
        if name == "reprocess":
            p.add_argument("--dry-run", action="store_true", help="list what would run and why")
        p.set_defaults(func=func)

    p = sub.add_parser(
        "export", help="export the dataset for occupancy trainers (Occ3D or nuScenes)"
    )
    _add_config_args(p, runtime=False)
    p.add_argument("--format", choices=["occ3d", "nuscenes"], required=True)
    p.add_argument("--to", type=Path, required=True, help="export folder")
    p.add_argument(
        "--gt",
        action="store_true",
        help="occ3d: labels from the synthetic ground truth under the raw data root (--data; "
        "default: the one the dataset was built from)",
    )
    p.set_defaults(func=cmd_export)

    p = sub.add_parser(
        "evaluate", help="label quality against ground truth: Markdown report + JSON"
    )
    p.add_argument("--dataset", type=Path, required=True, help="the output store (OUT)")
    p.add_argument(
        "--gt",
        type=Path,
        default=None,
        help="ground-truth root (default: the dataset root recorded in OUT)",
    )
    p.add_argument("--report", type=Path, required=True, help="report folder")
    p.add_argument(
        "--labels",
        choices=["synthetic", "coda"],
        default="synthetic",
        help="synthetic: the simulator's exact ground truth (gt/); coda: CODa's own "
        "3d_semantic and 3d_bbox labels",
    )
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        "check-data",
        help="check a CODa-layout download or robot logs before a run: a table per sequence "
        "(and a log's topics) and each stage's perception source, exit 1 on blocking problems, "
        "2 when the config reads ground truth (gt/) a sequence lacks",
    )
    _add_config_args(p, runtime=False)
    p.add_argument(
        "--deep", action="store_true", help="read every file (default: sizes and a few samples)"
    )
    p.set_defaults(func=cmd_check_data)

    _add_bench_parsers(sub)
    _add_deploy_parsers(sub)

    p = sub.add_parser(
        "simulate",
        help="generate synthetic campus sequences (CODa layout or robot logs + ground truth)",
    )
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--sequences", type=_at_least(1), default=1)
    p.add_argument(
        "--frames",
        type=_in_range(1, MAX_SIMULATED_FRAMES),
        default=20,
        help=f"raw 10 Hz frames per sequence (at most {MAX_SIMULATED_FRAMES})",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--pedestrians", type=int, default=None)
    p.add_argument("--crowd", choices=["crowded", "uncrowded"], default="uncrowded")
    p.add_argument("--night", action="store_true")
    p.add_argument(
        "--first-id",
        type=int,
        default=0,
        help="id of the first sequence (add sequences of another condition beside others)",
    )
    p.add_argument(
        "--image-format",
        choices=["jpg", "png"],
        default="jpg",
        help="2d_rect images as CODa's downloads (jpg) or the devkit's tools (png) write them",
    )
    p.add_argument(
        "--split-style",
        action="store_true",
        help="files only for blocks of frames, as CODa's split downloads (timestamps, poses: all)",
    )
    p.add_argument(
        "--fast",
        action="store_true",
        help="cameras at half resolution (612x512, same field of view; exact ground truth; "
        "for scale tests)",
    )
    p.add_argument(
        "--workers",
        type=_at_least(1),
        default=1,
        help="frame worker processes (the files are the same bytes for any number)",
    )
    p.add_argument(
        "--format",
        choices=["coda", "mcap", "ros1"],
        default="coda",
        help="the CODa layout, or one robot log per sequence: ROS 2 MCAP (SEQ.mcap) or ROS 1 "
        "bag (SEQ.bag) with real drivers' topics; gt/ beside in every case",
    )
    p.add_argument(
        "--log-poses",
        choices=["tf", "odometry", "none"],
        default=None,
        help="logs only: world poses on /tf (default for mcap), as nav_msgs/Odometry on /odom "
        "(default for ros1), or none (LiDAR odometry makes them)",
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser(
        "show", help="render a bird's-eye view and the camera image of a frame to PNG"
    )
    p.add_argument(
        "path",
        type=Path,
        help="a dataset (rebuild's --out), a robot log, or a ground-truth folder ROOT/gt/SEQ",
    )
    p.add_argument("--frame", type=int, default=None)
    p.add_argument("--sequence", default=None, help="of a dataset or a folder of logs")
    p.add_argument("--png", type=Path, default=Path("frame.png"), help="output PNG (frame.png)")
    p.set_defaults(func=cmd_show)

    p = sub.add_parser(
        "view",
        help="look at a dataset in 3D in the browser (served on localhost, or --html FILE), "
        "and the manual detection QA (--qa)",
    )
    p.add_argument("--dataset", type=Path, required=True, help="the output store (OUT)")
    p.add_argument("--sequence", default=None, help="sequence to open (default: the first)")
    p.add_argument("--frame", type=int, default=None, help="frame index (frames table `frame`)")
    p.add_argument(
        "--port", type=_in_range(0, 65535), default=8080, help="viewer port (next free when taken)"
    )
    p.add_argument("--host", default="127.0.0.1", help="address to serve on")
    p.add_argument("--html", type=Path, default=None, help="write one self-contained HTML page")
    p.add_argument("--frames", type=int, default=1, help="--html: frames in the page (<= 50)")
    p.add_argument("--qa", action="store_true", help="manual detection QA pass (saved in OUT/qa/)")
    p.add_argument("--qa-frames", type=int, default=None, help="QA frames per condition (100)")
    p.add_argument(
        "--mask", choices=["none", "camera", "lidar"], default=None, help="voxels inside it only"
    )
    p.add_argument("--unknown", action="store_true", help="show unknown space in grey")
    p.add_argument(
        "--style", choices=["points", "cubes"], default=None, help="voxels as squares or boxes"
    )
    p.add_argument(
        "--max-voxels", type=int, default=None, help="per layer; beyond, voxels merge into blocks"
    )
    p.add_argument("--data", type=Path, default=None, help="raw data root (default: recorded)")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("models", help="the bundled network files (set-up runs this)")
    msub = p.add_subparsers(dest="action", required=True)
    pu = msub.add_parser(
        "unpack-bundled",
        help="extract the bundled BlazePose .tflite files from a downloaded mediapipe wheel, "
        "checked by sha256",
    )
    pu.add_argument("--wheel", type=Path, required=True, help="mediapipe-0.10.21-*.whl")
    pu.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="where they go (default .cache/models/mediapipe-<version>, the default config's)",
    )
    p.set_defaults(func=cmd_models)

    p = sub.add_parser("demo", help="generate the synthetic demo data (if missing) and process it")
    _add_config_args(p)
    p.add_argument(
        "--frames",
        type=_at_least(1),
        default=30,
        help="raw 10 Hz frames per demo sequence (15 at 5 Hz)",
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = argv
    from configs.schema import ConfigError
    from flows.pipeline.runtime import RunnerUnavailable
    from flows.pipeline.signals import stop_on_signals
    from flows.pipeline.units import DiskFullError, ExportTargetError
    from storage.files import InputError
    from storage.layout import StoreError, shown
    from storage.manifest import OutputError, StoreLockedError

    name = f"mobileocc {args.command}"
    after = (
        "; finished units are kept, the same command resumes"
        if args.command in RUN_COMMANDS
        else ""
    )
    try:
        with stop_on_signals(name, after):
            return args.func(args)
    except ConfigError as exc:
        print(exc, file=sys.stderr)
        return EXIT_USAGE
    except (InputError, OutputError, UsageError, ExportTargetError, RunnerUnavailable) as exc:
        # --data / --out / --set / --to / the runner / a manifest that cannot be read
        print(f"{name}: {shown(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except StoreLockedError as exc:
        print(f"{name}: {shown(exc)}", file=sys.stderr)
        return EXIT_BUSY
    except DiskFullError as exc:  # a run stopped by a full disk (flows.pipeline.units)
        print(f"{name}: {shown(exc)}", file=sys.stderr)
        return EXIT_FAILED
    except StoreError as exc:  # a published store that cannot be read (export, evaluate)
        print(f"{name}: {shown(exc)}", file=sys.stderr)
        return EXIT_FAILED
    except OSError as exc:  # a full disk, a read-only place, a file that went away: one line
        from storage.atomic import os_error_line

        print(f"{name}: {shown(os_error_line(exc))}", file=sys.stderr)
        return EXIT_FAILED


#: commands that run units (a stop leaves finished units in the store)
RUN_COMMANDS = ("rebuild", "reprocess", "demo")


if __name__ == "__main__":
    sys.exit(main())
