"""The runner contract every adapter takes, and the checks and batching it shares."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

Shape = tuple[int | None, ...]


@runtime_checkable
class ModelRunner(Protocol):
    """A loaded network: named float arrays in, named arrays out.

    source: what to name in errors (the model file). input_shapes / output_shapes: name -> shape
    in the model's declared order, None for a dynamic axis.
    """

    source: str
    input_shapes: dict[str, Shape]
    output_shapes: dict[str, Shape]

    def __call__(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]: ...


class ModelContractError(ValueError):
    """A model's inputs or outputs are not what its adapter expects (names the model and both)."""


def expect(
    runner: ModelRunner,
    family: str,
    inputs: dict[str, Shape] | int,
    outputs: dict[str, Shape] | int,
) -> None:
    """Check a runner's signature: ``inputs`` / ``outputs`` give, in order, a name -> shape
    pattern (a name starting with ``*`` = any name; None in a shape = any size), or only the
    count."""

    def match(kind: str, got: dict[str, Shape], want: dict[str, Shape] | int) -> None:
        count = want if isinstance(want, int) else len(want)
        ok = len(got) == count
        if ok and not isinstance(want, int):
            for (gname, gshape), (wname, wshape) in zip(got.items(), want.items()):
                ok &= wname.startswith("*") or wname == gname
                ok &= len(gshape) == len(wshape) and all(
                    w is None or g is None or g == w for g, w in zip(gshape, wshape)
                )
        if not ok:
            raise ModelContractError(
                f"{runner.source}: not a {family} export: {kind} are {_fmt(got)}, expected "
                f"{count if isinstance(want, int) else _fmt(want)} (None = any size, * = any name)"
            )

    match("inputs", dict(runner.input_shapes), inputs)
    match("outputs", dict(runner.output_shapes), outputs)


def _fmt(shapes: dict[str, Shape]) -> str:
    return ", ".join(
        f"{n} {tuple('?' if s is None else s for s in shape)}" for n, shape in shapes.items()
    )


def input_hw(runner: ModelRunner, name: str, layout: str = "NCHW") -> tuple[int, int]:
    """(height, width) of a static image input; a dynamic size is an error naming the model."""
    shape = runner.input_shapes[name]
    h, w = (shape[2], shape[3]) if layout == "NCHW" else (shape[1], shape[2])
    if h is None or w is None:
        raise ModelContractError(
            f"{runner.source}: input {name} has a dynamic size {shape}; "
            "set the model's input size in the config"
        )
    return int(h), int(w)


def run_batched(
    runner: ModelRunner, feeds: dict[str, np.ndarray], max_batch: int
) -> dict[str, np.ndarray]:
    """Run ``feeds`` (every array batch-first, same length N) in batches the model accepts: one at
    a time for a static batch of 1, else ``max_batch``; outputs concatenated along the batch."""
    n = len(next(iter(feeds.values())))
    first = next(iter(runner.input_shapes.values()))
    step = 1 if first and first[0] == 1 else max(1, max_batch)
    parts = [
        runner({k: np.ascontiguousarray(v[a : a + step]) for k, v in feeds.items()})
        for a in range(0, n, step)
    ]
    if not parts:
        return {}
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
