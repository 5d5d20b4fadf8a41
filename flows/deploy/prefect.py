"""Prefect deployments of the two flows, and an idempotent trigger.

Two ways to deploy (see infra/README.md):

- ``mobileocc deploy serve``: ``prefect.serve`` of both flows in this process (one machine;
  the flow runs execute here). Needs ``PREFECT_API_URL`` of a running server.
- ``prefect deploy --all`` with ``infra/prefect.yaml``: deployments on a work pool, executed by a
  worker (process, Docker or Kubernetes).

``trigger_rebuild`` starts the rebuild deployment with an idempotency key: a second trigger with the
same key returns the flow run of the first instead of starting another (the server deduplicates on
(deployment, key)). A new key starts a new run.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

from configs.schema import Config, config_hash

#: deployment names, as ``run_deployment`` takes them ("<flow name>/<deployment name>")
REBUILD_DEPLOYMENT = "rebuild-dataset/rebuild"


def deployments(tags: tuple[str, ...] = ("mobileocc",)) -> list:
    """RunnerDeployments of ``rebuild_dataset`` ("rebuild") and ``process_sequence`` ("sequence")."""
    from prefect.deployments.runner import EntrypointType

    from flows.pipeline.run import process_sequence, rebuild_dataset

    module = (
        EntrypointType.MODULE_PATH
    )  # "flows.pipeline.run:rebuild_dataset", as in infra/prefect.yaml
    return [
        rebuild_dataset.to_deployment(
            name="rebuild",
            tags=list(tags),
            entrypoint_type=module,
            parameters={"progress": False},
            description="Every selected sequence through the six stages",
        ),
        process_sequence.to_deployment(
            name="sequence",
            tags=list(tags),
            entrypoint_type=module,
            description="One sequence through the six stages",
        ),
    ]


def apply_deployments(tags: tuple[str, ...] = ("mobileocc",)) -> list:
    """Register both deployments with the API (no work pool: runs wait for ``serve`` or a runner)."""
    return [d.apply() for d in deployments(tags)]


def serve(limit: int | None = None) -> None:
    """Serve both deployments from this process until interrupted."""
    from prefect import serve as prefect_serve

    prefect_serve(*deployments(), limit=limit)


def default_idempotency_key(
    config: Config, force: bool = False, sequences: list[str] | None = None, window: str = ""
) -> str:
    """A key for "this config, these sequences, this window" (e.g. a date or a data version).

    Two triggers of the same request within one window start one run; pass a new ``window`` (or
    your own key) to run the same request again later.
    """
    payload = {
        "config": config_hash(config),
        "force": force,
        "sequences": sorted(sequences) if sequences is not None else None,
        "window": window,
    }
    digest = hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:24]
    return f"rebuild-{digest}"


def trigger_rebuild(
    config: Config,
    force: bool = False,
    sequences: list[str] | None = None,
    idempotency_key: str | None = None,
    deployment: str = REBUILD_DEPLOYMENT,
    timeout: float | None = 0,
    **kwargs: Any,
):
    """Start (or find) a rebuild run of the deployment; returns the FlowRun.

    ``timeout=0`` returns at once (the run is scheduled); ``None`` waits for it to finish. With
    ``idempotency_key`` a duplicate trigger returns the first trigger's flow run.
    """
    from prefect.deployments import run_deployment

    parameters = {
        "config": config.model_dump(mode="json"),
        "force": force,
        "sequences": sequences,
        "progress": False,
    }
    return run_deployment(
        deployment,
        parameters=parameters,
        timeout=timeout,
        idempotency_key=idempotency_key,
        **kwargs,
    )
