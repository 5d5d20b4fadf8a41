"""Dask clusters from a spec: a local cluster, SLURM (dask-jobqueue) or Kubernetes (dask operator).

A cluster spec (``infra/slurm.yaml``, ``infra/kubernetes.yaml``) names a CPU pool and an optional
GPU pool. GPU workers are started with ``--resources GPU=1`` so that the fit stage, submitted under
``dask.annotate(resources={"GPU": 1})`` (``dask.gpu_fit``), runs only there. Both pools join one
scheduler: the flow connects to it with ``dask.address``.

- SLURM: dask-jobqueue uses one job template per cluster, so the CPU pool is a ``SLURMCluster`` (it
  owns the scheduler and may adapt) and the GPU pool is a fixed number of ``SLURMJob`` s pointed at
  that scheduler, with ``--gres=gpu:N``.
- Kubernetes: a ``DaskCluster`` resource (default worker group = CPU pool), a ``DaskWorkerGroup``
  for the GPU pool (fixed replicas, ``nvidia.com/gpu``), and a ``DaskAutoscaler``; the operator's
  autoscaler only scales the default group (dask-kubernetes#933), so the GPU group stays fixed.

The ``render_*`` functions are pure: they need neither SLURM nor a Kubernetes API, and tests call
them. ``build_cluster`` starts real resources.

    mobileocc cluster render infra/slurm.yaml        # the job script of each pool
    mobileocc cluster render infra/kubernetes.yaml   # the resources, for kubectl apply -f -
    mobileocc cluster up infra/slurm.yaml --address-file scheduler.txt   # start it and hold it
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Literal

import yaml

from storage.atomic import atomic_write_text

#: Placeholder scheduler address written into rendered SLURM scripts (the real one is filled in
#: by ``build_cluster``).
RENDER_SCHEDULER = "tcp://scheduler:8786"


class ClusterSpecError(ValueError):
    """A cluster spec that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class PoolSpec:
    """One homogeneous pool of Dask workers."""

    #: number of SLURM jobs / Kubernetes pods / local worker processes (the start size)
    jobs: int = 1
    #: cores per job and threads per worker process (cores / processes)
    cores: int = 4
    #: worker processes per job
    processes: int = 1
    #: memory per job, e.g. "16GiB"; split evenly among its processes
    memory: str = "16GiB"
    #: GPUs per job; > 0 makes it a GPU pool (gres / nvidia.com/gpu and the GPU resource)
    gpus: int = 0
    #: adaptive bounds in jobs (CPU pool only; ``None`` = fixed at ``jobs``)
    adapt_minimum: int | None = None
    adapt_maximum: int | None = None
    walltime: str = "04:00:00"
    #: SLURM partition (``None`` = the spec's default)
    queue: str | None = None

    @property
    def threads(self) -> int:
        return max(1, self.cores // self.processes)


@dataclass(frozen=True)
class ClusterSpec:
    kind: Literal["local", "slurm", "kubernetes"]
    name: str = "mobileocc"
    cpu: PoolSpec = PoolSpec()
    gpu: PoolSpec | None = None
    #: container image (Kubernetes) built from infra/Dockerfile
    image: str = "mobileocc:0.1.0"
    #: Kubernetes namespace
    namespace: str = "default"
    #: environment of every worker (e.g. PREFECT_API_URL, so task runs report to the server)
    env: dict[str, str] = field(default_factory=dict)
    #: SLURM: account, default partition, extra #SBATCH lines, commands before the worker starts
    account: str | None = None
    queue: str | None = None
    job_extra_directives: tuple[str, ...] = ()
    job_script_prologue: tuple[str, ...] = ()
    #: the Python on the compute nodes (SLURM); rendered into the job script
    python: str = "python3"
    #: worker scratch space (spilling)
    local_directory: str = "/tmp"


def _pool(data: Any, where: str) -> PoolSpec:
    if not isinstance(data, dict):
        raise ClusterSpecError(f"{where}: expected a mapping, got {type(data).__name__}")
    known = {f.name for f in fields(PoolSpec)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ClusterSpecError(
            f"{where}: unknown field(s) {unknown}; expected some of {sorted(known)}"
        )
    pool = PoolSpec(**data)
    for name in ("jobs", "cores", "processes"):
        if not isinstance(getattr(pool, name), int) or getattr(pool, name) < (
            0 if name == "jobs" else 1
        ):
            raise ClusterSpecError(
                f"{where}.{name}: expected a positive integer, got {getattr(pool, name)!r}"
            )
    if pool.cores % pool.processes:
        raise ClusterSpecError(
            f"{where}: cores ({pool.cores}) must be a multiple of processes ({pool.processes})"
        )
    return pool


def cluster_spec_from_dict(data: dict, where: str = "cluster spec") -> ClusterSpec:
    """Validate a parsed spec; ``where`` names its source in error messages."""
    if not isinstance(data, dict):
        raise ClusterSpecError(f"{where}: expected a mapping at the top level")
    data = dict(data)
    kind = data.get("kind")
    if kind not in ("local", "slurm", "kubernetes"):
        raise ClusterSpecError(f"{where}: kind {kind!r}, expected 'local', 'slurm' or 'kubernetes'")
    known = {f.name for f in fields(ClusterSpec)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ClusterSpecError(
            f"{where}: unknown field(s) {unknown}; expected some of {sorted(known)}"
        )
    data["cpu"] = _pool(data.get("cpu", {}), f"{where}: cpu")
    if data.get("gpu") is not None:
        data["gpu"] = _pool(data["gpu"], f"{where}: gpu")
        if data["gpu"].gpus < 1:
            raise ClusterSpecError(f"{where}: gpu.gpus must be >= 1 for the GPU pool")
        if data["gpu"].adapt_minimum is not None or data["gpu"].adapt_maximum is not None:
            raise ClusterSpecError(
                f"{where}: the GPU pool is fixed; remove gpu.adapt_minimum/maximum"
            )
    for key in ("job_extra_directives", "job_script_prologue"):
        data[key] = tuple(data.get(key) or ())
    data["env"] = {str(k): str(v) for k, v in (data.get("env") or {}).items()}
    return ClusterSpec(**data)


def load_cluster_spec(path: Path | str) -> ClusterSpec:
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ClusterSpecError(f"{path}: not valid YAML ({exc})") from None
    return cluster_spec_from_dict(data, str(path))


# --------------------------------------------------------------------------------------------- SLURM


def _gpu_worker_args(pool: PoolSpec) -> list[str]:
    return ["--resources", f"GPU={pool.gpus // pool.processes or 1}"] if pool.gpus else []


def slurm_job_kwargs(spec: ClusterSpec, pool: str = "cpu") -> dict:
    """Keyword arguments of ``SLURMCluster`` / ``SLURMJob`` for one pool."""
    p = spec.cpu if pool == "cpu" else spec.gpu
    if p is None:
        raise ClusterSpecError(f"cluster spec {spec.name!r} has no {pool!r} pool")
    directives = list(spec.job_extra_directives)
    if p.gpus:
        directives.append(f"--gres=gpu:{p.gpus}")
    return {
        "cores": p.cores,
        "processes": p.processes,
        "memory": p.memory,
        "walltime": p.walltime,
        "queue": p.queue or spec.queue,
        "account": spec.account,
        "job_name": f"{spec.name}-{pool}",
        "job_extra_directives": directives,
        "worker_extra_args": _gpu_worker_args(p),
        "job_script_prologue": [
            *(f"export {k}={_shell_quote(v)}" for k, v in sorted(spec.env.items())),
            *spec.job_script_prologue,
        ],
        "python": spec.python,
        "local_directory": spec.local_directory,
    }


def _shell_quote(value: str) -> str:
    import shlex

    return shlex.quote(value)


def render_slurm_job_script(
    spec: ClusterSpec, pool: str = "cpu", scheduler_address: str = RENDER_SCHEDULER
) -> str:
    """The sbatch script of one pool's jobs; needs no SLURM installation."""
    from dask_jobqueue.slurm import SLURMJob

    job = SLURMJob(
        scheduler=scheduler_address, name=f"{spec.name}-{pool}", **slurm_job_kwargs(spec, pool)
    )
    return job.job_script()


# ----------------------------------------------------------------------------------------- Kubernetes


def _k8s_worker_spec(spec: ClusterSpec, p: PoolSpec) -> dict:
    from dask_kubernetes.operator import make_worker_spec

    limits: dict[str, Any] = {"cpu": str(p.cores), "memory": _k8s_quantity(p.memory)}
    if p.gpus:
        limits["nvidia.com/gpu"] = p.gpus
    command = (
        f"dask worker --nworkers {p.processes} --nthreads {p.threads} "
        f"--memory-limit {_k8s_quantity(p.memory)} --local-directory {spec.local_directory}"
    )
    if p.gpus:
        command += " " + " ".join(_gpu_worker_args(p))
    worker = make_worker_spec(
        image=spec.image,
        n_workers=p.jobs,
        resources={"requests": dict(limits), "limits": dict(limits)},
        env=dict(sorted(spec.env.items())) or None,
        worker_command=command,
    )
    if p.gpus:
        worker["spec"]["tolerations"] = [
            {"key": "nvidia.com/gpu", "operator": "Exists", "effect": "NoSchedule"}
        ]
    return worker


def _k8s_quantity(memory: str) -> str:
    """'16GiB' -> '16Gi' (Kubernetes quantity); '16GB' -> '16G'."""
    m = memory.strip()
    for suffix in ("iB", "B"):
        if m.endswith(suffix):
            return m[: -len(suffix)] + ("i" if suffix == "iB" else "")
    return m


def render_kubernetes_cluster(spec: ClusterSpec) -> list[dict]:
    """The resources to ``kubectl apply``: DaskCluster, the GPU DaskWorkerGroup, DaskAutoscaler.

    Pure: needs no Kubernetes API. The default worker group is the CPU pool; the GPU group has a
    fixed replica count (only the default group is autoscaled by the operator).
    """
    from dask_kubernetes.operator import make_cluster_spec

    cluster = make_cluster_spec(
        name=spec.name,
        image=spec.image,
        n_workers=spec.cpu.jobs,
        env=dict(sorted(spec.env.items())) or None,
    )
    cluster["metadata"]["namespace"] = spec.namespace
    cluster["spec"]["worker"] = _k8s_worker_spec(spec, spec.cpu)
    # distributed >= 2024 ships only the `dask` entry point (no `dask-scheduler` script)
    scheduler = cluster["spec"]["scheduler"]["spec"]["containers"][0]
    scheduler["args"] = ["dask", "scheduler", "--host", "0.0.0.0"]
    if scheduler.get("resources") is None:
        del scheduler["resources"]
    docs = [cluster]
    if spec.gpu is not None:
        docs.append(
            {
                "apiVersion": "kubernetes.dask.org/v1",
                "kind": "DaskWorkerGroup",
                "metadata": {"name": f"{spec.name}-gpu", "namespace": spec.namespace},
                "spec": {"cluster": spec.name, "worker": _k8s_worker_spec(spec, spec.gpu)},
            }
        )
    if spec.cpu.adapt_minimum is not None or spec.cpu.adapt_maximum is not None:
        docs.append(
            {
                "apiVersion": "kubernetes.dask.org/v1",
                "kind": "DaskAutoscaler",
                "metadata": {"name": spec.name, "namespace": spec.namespace},
                "spec": {
                    "cluster": spec.name,
                    "minimum": spec.cpu.adapt_minimum or 0,
                    "maximum": spec.cpu.adapt_maximum or spec.cpu.jobs,
                },
            }
        )
    return docs


def render_kubernetes_yaml(spec: ClusterSpec) -> str:
    return yaml.safe_dump_all(render_kubernetes_cluster(spec), sort_keys=False)


def render(spec: ClusterSpec, scheduler_address: str = RENDER_SCHEDULER) -> str:
    """What ``mobileocc cluster render`` prints: the job script of each SLURM pool, or the
    Kubernetes resources; ClusterSpecError for a local cluster (nothing to render)."""
    if spec.kind == "slurm":
        return "".join(
            f"# ---- {pool} pool ----\n{render_slurm_job_script(spec, pool, scheduler_address)}\n"
            for pool in (("cpu", "gpu") if spec.gpu else ("cpu",))
        )
    if spec.kind == "kubernetes":
        return render_kubernetes_yaml(spec)
    raise ClusterSpecError("a local cluster has nothing to render")


# ------------------------------------------------------------------------------------------ building


class ClusterHandle:
    """A started cluster: ``address`` for ``dask.address``; ``close()`` releases everything."""

    def __init__(self, cluster, extra: list | None = None, closer=None):
        self.cluster = cluster
        self.extra = extra or []
        self._closer = closer

    @property
    def address(self) -> str:
        return self.cluster.scheduler_address

    def close(self) -> None:
        if self._closer is not None:
            self._closer()
        self.cluster.close()

    def __enter__(self) -> ClusterHandle:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def build_cluster(spec: ClusterSpec) -> ClusterHandle:
    """Start the spec's cluster (both pools on one scheduler) and return a handle."""
    if spec.kind == "local":
        return _build_local(spec)
    if spec.kind == "slurm":
        return _build_slurm(spec)
    return _build_kubernetes(spec)


def _build_local(spec: ClusterSpec) -> ClusterHandle:
    from dask.utils import parse_bytes
    from distributed import Nanny, Scheduler, SpecCluster

    workers = {}
    for pool_name, p in (("cpu", spec.cpu), ("gpu", spec.gpu)):
        if p is None:
            continue
        for j in range(p.jobs):
            for k in range(p.processes):
                opts = {
                    "nthreads": p.threads,
                    "memory_limit": parse_bytes(p.memory) // p.processes,
                    "local_directory": spec.local_directory,
                    "env": dict(spec.env),
                }
                if p.gpus:
                    opts["resources"] = {"GPU": p.gpus // p.processes or 1}
                workers[f"{pool_name}-{j}-{k}"] = {"cls": Nanny, "options": opts}
    cluster = SpecCluster(
        workers=workers,
        scheduler={"cls": Scheduler, "options": {"host": "127.0.0.1", "dashboard_address": None}},
        name=spec.name,
    )
    return ClusterHandle(cluster)


def _build_slurm(spec: ClusterSpec) -> ClusterHandle:
    from dask_jobqueue import SLURMCluster
    from dask_jobqueue.slurm import SLURMJob

    cpu = SLURMCluster(**slurm_job_kwargs(spec, "cpu"))
    if spec.cpu.adapt_minimum is not None or spec.cpu.adapt_maximum is not None:
        cpu.adapt(
            minimum_jobs=spec.cpu.adapt_minimum or 0,
            maximum_jobs=spec.cpu.adapt_maximum or spec.cpu.jobs,
        )
    else:
        cpu.scale(jobs=spec.cpu.jobs)
    gpu_jobs = []
    if spec.gpu is not None:
        kwargs = slurm_job_kwargs(spec, "gpu")
        for j in range(spec.gpu.jobs):
            job = SLURMJob(scheduler=cpu.scheduler_address, name=f"{spec.name}-gpu-{j}", **kwargs)
            cpu.sync(job.start)
            gpu_jobs.append(job)

    def close_gpu() -> None:
        for job in gpu_jobs:
            cpu.sync(job.close)

    return ClusterHandle(cpu, gpu_jobs, close_gpu)


def _build_kubernetes(spec: ClusterSpec) -> ClusterHandle:
    from dask_kubernetes.operator import KubeCluster

    docs = render_kubernetes_cluster(spec)
    cluster = KubeCluster(custom_cluster_spec=copy.deepcopy(docs[0]), namespace=spec.namespace)
    for doc in docs[1:]:
        if doc["kind"] == "DaskWorkerGroup":
            cluster.add_worker_group("gpu", custom_spec=doc["spec"]["worker"])
    if spec.cpu.adapt_minimum is not None or spec.cpu.adapt_maximum is not None:
        cluster.adapt(
            minimum=spec.cpu.adapt_minimum or 0, maximum=spec.cpu.adapt_maximum or spec.cpu.jobs
        )
    return ClusterHandle(cluster)


def hold_cluster(spec: ClusterSpec, address_file: Path | None = None, wait=None) -> str:
    """Start the spec's cluster, print its scheduler address (and write it to ``address_file``
    for ``mobileocc rebuild --address $(cat FILE)``), hold it while ``wait(address)`` runs (None:
    until interrupted), then release it and remove the file. Returns the address it had."""
    with build_cluster(spec) as handle:
        address = handle.address
        print(address, flush=True)
        if address_file is not None:
            atomic_write_text(address_file, address + "\n")
        try:
            (wait or _sleep_forever)(address)
        except KeyboardInterrupt:
            pass
        finally:
            if address_file is not None:
                Path(address_file).unlink(missing_ok=True)
    return address


def _sleep_forever(address: str) -> None:  # pragma: no cover - ended by an interrupt
    import time

    while True:
        time.sleep(3600)
