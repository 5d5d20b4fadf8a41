"""infra/: the SLURM job scripts and Kubernetes resources render from the specs, prefect.yaml names
importable flows, and a duplicate trigger with the same idempotency key starts no second run."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from configs.schema import load_config
from flows.deploy.clusters import (
    ClusterSpecError,
    cluster_spec_from_dict,
    load_cluster_spec,
    render_kubernetes_cluster,
    render_kubernetes_yaml,
    render_slurm_job_script,
)

INFRA = Path(__file__).resolve().parents[1] / "infra"

pytestmark = [pytest.mark.usefixtures("prefect_harness"), pytest.mark.xdist_group("prefect")]


def _sbatch(script: str) -> list[str]:
    return [line[len("#SBATCH ") :] for line in script.splitlines() if line.startswith("#SBATCH ")]


def _worker_line(script: str) -> str:
    (line,) = [ln for ln in script.splitlines() if "distributed.cli.dask_worker" in ln]
    return line


def test_slurm_job_scripts_render_gpu_pool_apart():
    spec = load_cluster_spec(INFRA / "slurm.yaml")
    cpu = render_slurm_job_script(spec, "cpu", "tcp://10.0.0.1:8786")
    gpu = render_slurm_job_script(spec, "gpu", "tcp://10.0.0.1:8786")

    assert "--gres=gpu:1" in _sbatch(gpu)
    assert not any("gres" in d for d in _sbatch(cpu))
    assert _worker_line(gpu).split()[-2:] == ["--resources", "GPU=1"]
    assert "--resources" not in _worker_line(cpu)
    # the pools' sizes and partitions come from the spec
    assert "--cpus-per-task=8" in _sbatch(cpu) and "--mem=32G" in _sbatch(cpu)
    assert "-p cpu" in _sbatch(cpu) and "-p gpu" in _sbatch(gpu)
    assert "--mem=64G" in _sbatch(gpu) and "-t 08:00:00" in _sbatch(gpu)
    cpu_worker = _worker_line(cpu).split()
    assert cpu_worker[cpu_worker.index("--nworkers") + 1] == "2"
    assert cpu_worker[cpu_worker.index("--nthreads") + 1] == "4"
    # both pools join the same scheduler and report to the same Prefect API
    for script in (cpu, gpu):
        assert "tcp://10.0.0.1:8786" in _worker_line(script)
        assert (
            "export PREFECT_API_URL=http://prefect.example.internal:4200/api" in script.splitlines()
        )
        assert _worker_line(script).startswith("/opt/mobileocc/.venv/bin/python ")


def test_kubernetes_resources_render_fixed_gpu_group():
    spec = load_cluster_spec(INFRA / "kubernetes.yaml")
    docs = render_kubernetes_cluster(spec)
    assert [d["kind"] for d in docs] == ["DaskCluster", "DaskWorkerGroup", "DaskAutoscaler"]
    cluster, gpu_group, autoscaler = docs
    assert all(d["apiVersion"] == "kubernetes.dask.org/v1" for d in docs)
    assert all(d["metadata"]["namespace"] == "mobileocc" for d in docs)

    cpu_worker = cluster["spec"]["worker"]
    (cpu_container,) = cpu_worker["spec"]["containers"]
    assert cpu_worker["replicas"] == 2
    assert "nvidia.com/gpu" not in cpu_container["resources"]["limits"]
    assert "--resources" not in cpu_container["args"]
    assert cpu_container["image"] == "registry.example.internal/mobileocc:0.1.0"
    (scheduler,) = cluster["spec"]["scheduler"]["spec"]["containers"]
    assert scheduler["args"][:2] == ["dask", "scheduler"]

    assert gpu_group["spec"]["cluster"] == "mobileocc"
    assert gpu_group["metadata"]["name"] == "mobileocc-gpu"
    assert gpu_group["spec"]["worker"]["replicas"] == 2
    (gpu_container,) = gpu_group["spec"]["worker"]["spec"]["containers"]
    assert gpu_container["resources"]["limits"]["nvidia.com/gpu"] == 1
    args = gpu_container["args"]
    assert args[args.index("--resources") + 1] == "GPU=1"
    assert {
        "name": "PREFECT_API_URL",
        "value": "http://prefect-server.prefect.svc:4200/api",
    } in gpu_container["env"]

    # only the default (CPU) group autoscales: the autoscaler names the cluster, the GPU group is fixed
    assert autoscaler["spec"] == {"cluster": "mobileocc", "minimum": 1, "maximum": 20}
    # the multi-document YAML for kubectl apply parses back to the same resources
    assert list(yaml.safe_load_all(render_kubernetes_yaml(spec))) == docs


def test_cluster_spec_errors_name_the_field():
    with pytest.raises(ClusterSpecError, match="gpu: unknown field.*'gpu_count'"):
        cluster_spec_from_dict({"kind": "slurm", "gpu": {"gpu_count": 1}})
    with pytest.raises(ClusterSpecError, match="the GPU pool is fixed"):
        cluster_spec_from_dict({"kind": "kubernetes", "gpu": {"gpus": 1, "adapt_maximum": 4}})
    with pytest.raises(ClusterSpecError, match="kind 'pbs'"):
        cluster_spec_from_dict({"kind": "pbs"})
    with pytest.raises(
        ClusterSpecError, match="cores \\(6\\) must be a multiple of processes \\(4\\)"
    ):
        cluster_spec_from_dict({"kind": "slurm", "cpu": {"cores": 6, "processes": 4}})


def test_cluster_render_is_a_subcommand_of_the_one_cli(capsys, tmp_path):
    from flows import cli

    spec = load_cluster_spec(INFRA / "slurm.yaml")
    assert (
        cli.main(["cluster", "render", str(INFRA / "slurm.yaml"), "--scheduler", "tcp://s:1"]) == 0
    )
    printed = capsys.readouterr().out
    assert printed == (
        f"# ---- cpu pool ----\n{render_slurm_job_script(spec, 'cpu', 'tcp://s:1')}\n"
        f"# ---- gpu pool ----\n{render_slurm_job_script(spec, 'gpu', 'tcp://s:1')}\n"
    )
    local = tmp_path / "local.yaml"
    local.write_text("kind: local\n")
    assert cli.main(["cluster", "render", str(local)]) == 1
    assert capsys.readouterr().err == f"{local}: a local cluster has nothing to render\n"


def test_prefect_yaml_entrypoints_import():
    from prefect.flows import load_flow_from_entrypoint

    data = yaml.safe_load((INFRA / "prefect.yaml").read_text())
    entry = {d["name"]: d["entrypoint"] for d in data["deployments"]}
    assert entry == {
        "rebuild": "flows.pipeline.run:rebuild_dataset",
        "sequence": "flows.pipeline.run:process_sequence",
    }
    assert load_flow_from_entrypoint(entry["rebuild"]).name == "rebuild-dataset"
    assert load_flow_from_entrypoint(entry["sequence"]).name == "process-sequence"
    # the file also validates against the schema `prefect deploy` uses (a private module: optional)
    try:
        from prefect.cli.deploy._models import PrefectYamlModel
    except ImportError:  # pragma: no cover - moved in another Prefect release
        return
    model = PrefectYamlModel.model_validate(data)
    assert [(d.name, d.work_pool.name) for d in model.deployments] == [
        ("rebuild", "mobileocc"),
        ("sequence", "mobileocc"),
    ]


def test_duplicate_trigger_returns_the_same_flow_run(tmp_path):
    from prefect.client.orchestration import get_client

    from flows.deploy.prefect import (
        REBUILD_DEPLOYMENT,
        apply_deployments,
        default_idempotency_key,
        trigger_rebuild,
    )

    ids = apply_deployments(tags=("mobileocc", "test"))
    assert len(set(ids)) == 2
    cfg = load_config(
        overrides={"dataset.root": str(tmp_path / "data"), "output.root": str(tmp_path / "out")}
    )
    key = default_idempotency_key(cfg, window=str(tmp_path))
    first = trigger_rebuild(cfg, idempotency_key=key)
    again = trigger_rebuild(cfg, idempotency_key=key)
    other = trigger_rebuild(cfg, idempotency_key=key + "-2")
    assert again.id == first.id
    assert other.id != first.id
    assert first.parameters["config"]["output"]["root"] == str(tmp_path / "out")

    with get_client(sync_client=True) as client:
        dep = client.read_deployment_by_name(REBUILD_DEPLOYMENT)
        assert dep.entrypoint == "flows.pipeline.run.rebuild_dataset"  # Prefect's module-path form
        from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterId
        from prefect.client.schemas.sorting import FlowRunSort

        runs = client.read_flow_runs(
            deployment_filter=DeploymentFilter(id=DeploymentFilterId(any_=[dep.id])),
            sort=FlowRunSort.ID_DESC,
            limit=100,
        )
        assert len(runs) == 2  # three triggers, two keys
        assert sum(r.idempotency_key == key for r in runs) == 1


def test_local_cluster_from_spec_has_a_gpu_pool():
    from distributed import Client

    from flows.deploy.clusters import build_cluster

    spec = cluster_spec_from_dict(
        {
            "kind": "local",
            "cpu": {"jobs": 1, "cores": 1, "memory": "1GiB"},
            "gpu": {"jobs": 1, "cores": 1, "gpus": 1, "memory": "1GiB"},
        }
    )
    with build_cluster(spec) as handle, Client(handle.address) as client:
        client.wait_for_workers(2, timeout=120)
        workers = client.scheduler_info(n_workers=-1)["workers"].values()
        assert sorted((w["name"], w["resources"]) for w in workers) == [
            ("cpu-0-0", {}),
            ("gpu-0-0", {"GPU": 1}),
        ]
        on = client.submit(_worker_name, resources={"GPU": 1}, pure=False).result()
        assert on == "gpu-0-0"


def test_cluster_up_writes_the_address_and_releases_it(tmp_path):
    # `mobileocc cluster up SPEC --address-file F`: the runbook's way to start a cluster and hand
    # its address to `mobileocc rebuild --address`
    from distributed import Client

    from flows.deploy.clusters import hold_cluster

    spec = cluster_spec_from_dict(
        {"kind": "local", "cpu": {"jobs": 1, "cores": 2, "processes": 2, "memory": "2GiB"}}
    )
    seen = {}

    def probe(address: str) -> None:  # runs while the cluster is held
        seen["file"] = (tmp_path / "address").read_text().strip()
        with Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=120)
            seen["threads"] = sorted(
                w["nthreads"] for w in client.scheduler_info(n_workers=-1)["workers"].values()
            )

    address = hold_cluster(spec, tmp_path / "address", wait=probe)
    assert address.startswith("tcp://") and seen == {"file": address, "threads": [1, 1]}
    assert not (tmp_path / "address").exists()


def _worker_name() -> str:
    from distributed import get_worker

    return str(get_worker().name)


FAKE_SBATCH = """#!/bin/bash
# test stand-in for sbatch: run the job script in its own session, print a SLURM-like reply
# (dask-jobqueue deletes the script file when sbatch returns: run a copy)
job="$(dirname "$0")/job-$RANDOM$RANDOM.sh"
cp "$1" "$job"
setsid bash "$job" > "$job.log" 2>&1 < /dev/null &
echo "Submitted batch job $!"
"""
FAKE_SCANCEL = """#!/bin/bash
for id in "$@"; do kill -TERM -- "-$id" 2>/dev/null; done
exit 0
"""


def test_slurm_cluster_from_spec_with_a_stand_in_sbatch(tmp_path, monkeypatch):
    """build_cluster on SLURM with sbatch/scancel stand-ins that run the rendered job scripts here:
    the CPU pool and the separately submitted GPU job join one scheduler, GPU=1 only on the latter."""
    import os
    import sys

    from distributed import Client

    from flows.deploy.clusters import build_cluster

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name, text in (
        ("sbatch", FAKE_SBATCH),
        ("scancel", FAKE_SCANCEL),
        ("squeue", "#!/bin/bash\n"),
    ):
        (bin_dir / name).write_text(text)
        (bin_dir / name).chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    spec = cluster_spec_from_dict(
        {
            "kind": "slurm",
            "python": sys.executable,
            "local_directory": str(tmp_path),
            "job_script_prologue": [f"cd {Path(__file__).resolve().parents[1]}"],
            "cpu": {"jobs": 1, "cores": 1, "memory": "1GiB"},
            "gpu": {"jobs": 1, "cores": 1, "memory": "1GiB", "gpus": 1},
        }
    )
    with build_cluster(spec) as handle, Client(handle.address) as client:
        client.wait_for_workers(2, timeout=120)
        workers = client.scheduler_info(n_workers=-1)["workers"].values()
        assert sorted((w["resources"] for w in workers), key=len) == [{}, {"GPU": 1}]
        assert (
            client.submit(_worker_name, resources={"GPU": 1}, pure=False)
            .result()
            .startswith("mobileocc-gpu")
        )
