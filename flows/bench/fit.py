"""Synthetic-LiDAR benchmark of the human fitting stage (paper appendix C, Tables 1 and 5).

``bench_fit(persons)`` simulates persons (varied poses, shapes, 3-12 m, random heading) seen by a
camera and a co-located Ouster-style LiDAR, perturbs them into monocular-like initial estimates,
fits them, and prints a paper-style table: full method, without L_3D, without L_theta,occ,
without the visibility filter, and the initial estimate; plus person-fits per second (full
method, wall clock of ``fit_persons`` including ICP). No prefect: a plain function / CLI.

    nice .venv/bin/mobileocc bench fit --persons 64 --sensors ouster-128 [--set fit.iterations=60]

The fit settings and loss weights are the pipeline's (the config loader: the default config,
``--config``, ``--set``), so the table measures what the pipeline runs.

``--throughput`` measures only speed: person-fits/s of one large batch on ``--device`` (e.g.
``mobileocc bench fit --device cuda --throughput --persons 1024``) after a warm-up, printed as one
JSON line.
"""

from __future__ import annotations

import dataclasses
import time

from storage.npzio import save_npz_deterministic


def _variants(weights, ablations: bool):
    out = [("Ours", weights, {})]
    if ablations:
        out += [
            ("w/o L_3D", weights.with_(lambda_3d=0.0), {}),
            ("w/o L_theta,occ", weights.with_(lambda_occ=0.0), {}),
            ("w/o visibility", weights, {"use_visibility": False}),
        ]
    return out


def bench_fit(
    persons: int,
    weights,
    settings,
    sensors=("ouster-32", "ouster-64", "ouster-128"),
    ablations: bool = True,
    device: str = "cpu",
    seed: int = 0,
    warm_start: bool = False,
    ablation_sensors=None,
    start_settings=None,
) -> dict:
    """Run the benchmark; returns {sensor: {variant: {metric: mean}}} plus 'person_fits_per_s'.

    start_settings: None: the fits start from the oracle's estimates (truth with monocular-like
    errors); tasks.fit.settings.InitLidarSettings: from the weight-free start computed from each
    person's points and keypoints (``fit.init_provider: lidar-keypoints``; the oracle's estimates
    are drawn all the same, so the persons and the noise are the same in both).

    weights (tasks.fit.weights.FitWeights) and settings (tasks.fit.settings.FitSettings: iterations,
    learning rate, nn_every, the L_3D cap, converge_rtol, batch_persons as the chunk): the
    pipeline's, from the config loader (``mobileocc bench fit``: the default config, ``--config``,
    ``--set``).

    Metrics (mean over persons): pve, mpjpe (sensor frame, no alignment, mm), pve_root /
    mpjpe_root (pelvis-aligned, mm), pa_mpjpe (mm), mpere; per sensor also 'occluded_subset'
    (the same metrics on persons with a simulated occluded limb). With warm_start, a second frame
    per person (the body moved a little) is fitted from the first frame's fit and from a fresh
    oracle estimate, and both are reported. ablation_sensors: the sensors that get the ablation
    rows (None = every sensor).
    """
    import numpy as np
    import torch

    from tasks.body.poses import sample_plausible_poses
    from tasks.body.prior import GMMPosePrior, generate_pose_prior
    from tasks.body.procedural import default_body_model
    from tasks.fit.init_oracle import oracle_initial_estimate
    from tasks.fit.lidar_sim import SENSORS, synthesize_persons
    from tasks.fit.metrics import fit_metrics
    from tasks.fit.optimize import fit_persons, ragged_points

    model = default_body_model()
    g = generate_pose_prior()
    prior = GMMPosePrior(g["means"], g["covars"], g["weights"]).to(device)
    iterations, chunk = settings.iterations, settings.batch_persons
    results: dict = {}
    fit_time, fit_count = 0.0, 0

    def run_fits(sp, init, w, extra):
        nonlocal fit_time, fit_count
        extra = dict(extra)
        count = extra.pop("count", True)
        its = extra.pop("iterations", iterations)
        outs = []
        for s in range(0, persons, chunk):
            idx = slice(s, min(persons, s + chunk))
            t0 = time.perf_counter()
            r = fit_persons(
                model,
                prior,
                init.take(idx),
                sp.keypoints[idx],
                sp.K,
                sp.T_cam_from_lidar,
                *ragged_points(sp.points_lidar[idx], sp.point_mask[idx]),
                w,
                dataclasses.replace(settings, iterations=its, device=device, seed=seed),
                **extra,
            )
            if count:
                fit_time += time.perf_counter() - t0
                fit_count += idx.stop - idx.start
            outs.append(r)
        return (
            np.concatenate([r.vertices for r in outs]),
            np.concatenate([r.joints for r in outs]),
            outs,
        )

    for si, sensor in enumerate(sensors):
        rng = np.random.default_rng(seed + 1000 * si)
        poses = sample_plausible_poses(persons, rng)
        sp = synthesize_persons(model, poses, SENSORS[sensor], rng)
        truth = sp.truth
        init = oracle_initial_estimate(model, truth, rng)
        if start_settings is not None:
            from tasks.fit.init_lidar import lidar_keypoint_init

            pts, counts = ragged_points(sp.points_lidar, sp.point_mask)
            T = np.asarray(sp.T_cam_from_lidar, np.float64)
            init = lidar_keypoint_init(
                model,
                sp.keypoints,
                sp.K,
                pts.astype(np.float64) @ T[:3, :3].T + T[:3, 3],
                counts,
                T[:3, :3] @ np.array([0.0, 0.0, 1.0]),  # the LiDAR's z is up
                start_settings,
            )
        occ = sp.occluded_limb >= 0
        table: dict = {}

        def record(name, verts, joints):
            m = fit_metrics(verts, joints, sp.truth_vertices, sp.truth_joints, model.faces)
            table[name] = {k: float(np.mean(v)) for k, v in m.items()}
            table[name]["std"] = {k: float(np.std(v)) for k, v in m.items()}
            if occ.any():
                table[name]["occluded_subset"] = {k: float(np.mean(v[occ])) for k, v in m.items()}

        with_ablations = ablations and (ablation_sensors is None or sensor in ablation_sensors)
        for name, w, extra in _variants(weights, with_ablations):
            v, j, _ = run_fits(sp, init, w, extra)
            record(name, v, j)
        with torch.no_grad():
            o = model(
                *(
                    torch.as_tensor(a)
                    for a in (init.betas, init.global_orient, init.body_pose, init.transl)
                )
            )
        record("Initial estimate", o.vertices.numpy(), o.joints.numpy())
        if warm_start:
            table.update(
                _warm_start_rows(
                    model,
                    prior,
                    sp,
                    truth,
                    init,
                    weights,
                    rng,
                    run_fits,
                    fit_metrics,
                    sensor,
                    sorted({30, 60, iterations}),
                )
            )
        results[sensor] = table
        _print_table(sensor, table, persons, int(occ.sum()))
    results["person_fits_per_s"] = fit_count / max(fit_time, 1e-9)
    print(
        f"person-fits/s (full pipeline incl. ICP, {device}, {iterations} it, chunk {chunk}): "
        f"{results['person_fits_per_s']:.2f}"
    )
    return results


def _warm_start_rows(
    model, prior, sp, truth, init, weights, rng, run_fits, fit_metrics, sensor, counts
):
    """Second frame 0.2 s later: the person walked ~0.25 m and the pose drifted a little; fit it
    from the first frame's fit (warm) and from a fresh oracle estimate (cold), each with every
    iteration count in ``counts`` (iterations to converge)."""
    import numpy as np
    import torch

    from tasks.body.params import BodyParams
    from tasks.fit.init_oracle import oracle_initial_estimate
    from tasks.fit.lidar_sim import SENSORS, synthesize_persons

    B = len(truth)
    _, _, first = run_fits(sp, init, weights, {"count": False})
    prev = BodyParams.concat(first)
    # frame 2 ground truth: same person, moved and re-posed slightly; new sweep and keypoints
    pose2 = truth.body_pose + rng.normal(0.0, 0.05, truth.body_pose.shape).astype(np.float32)
    sp2 = synthesize_persons(model, pose2, SENSORS[sensor], rng)
    # keep the identity: same shape and heading as frame 1, shifted by a step
    step = rng.normal(0.0, 0.15, (B, 3)) * np.array([1.0, 0.0, 1.0])
    truth2 = BodyParams(
        truth.betas, truth.global_orient, pose2, (truth.transl + step).astype(np.float32)
    )
    with torch.no_grad():
        o = model(
            *(
                torch.as_tensor(a)
                for a in (truth2.betas, truth2.global_orient, truth2.body_pose, truth2.transl)
            )
        )
    sp2 = _resimulate(model, sp2, o.vertices.numpy(), o.joints.numpy(), sensor, rng)
    rows = {}
    for name, start in (("warm", prev), ("cold", oracle_initial_estimate(model, truth2, rng))):
        with torch.no_grad():
            s = model(
                *(
                    torch.as_tensor(a)
                    for a in (start.betas, start.global_orient, start.body_pose, start.transl)
                )
            )
        m = fit_metrics(
            s.vertices.numpy(), s.joints.numpy(), o.vertices.numpy(), o.joints.numpy(), model.faces
        )
        rows[f"frame 2, {name} start, 0 it"] = {k: float(np.mean(x)) for k, x in m.items()}
        for its in counts:
            v, j, _ = run_fits(sp2, start, weights, {"count": False, "iterations": its})
            m = fit_metrics(v, j, o.vertices.numpy(), o.joints.numpy(), model.faces)
            rows[f"frame 2, {name} start, {its} it"] = {k: float(np.mean(x)) for k, x in m.items()}
    return rows


def _resimulate(model, sp, verts, joints, sensor, rng):
    """Keypoints and a sweep for given true meshes (B, V, 3) / joints, cam frame."""

    import numpy as np
    import torch

    from tasks.fit.lidar_sim import (
        R_CAM_FROM_LIDAR,
        SENSORS,
        frustum_ray_directions,
        simulate_sweep,
    )
    from tasks.fit.optimize import model_keypoints

    B, P = sp.point_mask.shape
    kp3 = model_keypoints(
        torch.as_tensor(joints), torch.as_tensor(verts), model.keypoint_vertex_ids
    ).numpy()
    uvw = kp3 @ sp.K.T
    kp = sp.keypoints.copy()
    kp[..., :2] = uvw[..., :2] / uvw[..., 2:3] + rng.normal(0.0, 3.0, (B, 17, 2))
    dirs = frustum_ray_directions(SENSORS[sensor], sp.K, (1920, 1080))
    pts = np.zeros_like(sp.points_lidar)
    mask = np.zeros_like(sp.point_mask)
    for b in range(B):
        p, _ = simulate_sweep(verts[b], np.asarray(model.faces), dirs, SENSORS[sensor], rng)
        if len(p) > P:
            p = p[rng.choice(len(p), P, replace=False)]
        pts[b, : len(p)] = p @ R_CAM_FROM_LIDAR
        mask[b, : len(p)] = True
    return dataclasses.replace(
        sp,
        keypoints=kp,
        points_lidar=pts,
        point_mask=mask,
        truth_vertices=verts,
        truth_joints=joints,
    )


#: the arrays of a simulated person pool (tasks.fit.lidar_sim.SyntheticPersons and the oracle's
#: initial estimates) that the throughput and agreement runs need
POOL_FIELDS = (
    "keypoints",
    "K",
    "points_lidar",
    "point_mask",
    "T_cam_from_lidar",
    "truth_joints",
    "init_betas",
    "init_global_orient",
    "init_body_pose",
    "init_transl",
)


def save_pool(path, arrays: dict) -> None:
    """Persons of :func:`simulated_pool` to an .npz (``mobileocc bench fit --save-pool``)."""
    save_npz_deterministic(path, **arrays)


def load_pool(path) -> dict:
    """Persons saved by :func:`save_pool` (``--pool-file``)."""
    import numpy as np

    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in POOL_FIELDS}


def simulated_pool(pool: int, sensor: str, seed: int, **synthesize) -> dict:
    """``pool`` simulated persons (the LiDAR simulation, CPU, needs open3d) and their oracle
    initial estimates, as plain arrays (:data:`POOL_FIELDS`): saved with ``--save-pool`` they run
    on a machine without the simulator's dependencies (``--pool-file``)."""
    import numpy as np

    from tasks.body.params import BodyParams
    from tasks.body.poses import sample_plausible_poses
    from tasks.body.procedural import default_body_model
    from tasks.fit.init_oracle import oracle_initial_estimate
    from tasks.fit.lidar_sim import SENSORS, synthesize_persons

    model, rng = default_body_model(), np.random.default_rng(seed)
    sp = synthesize_persons(
        model, sample_plausible_poses(pool, rng), SENSORS[sensor], rng, **synthesize
    )
    init = oracle_initial_estimate(model, sp.truth, rng)
    arrays = {k: getattr(sp, k) for k in POOL_FIELDS if not k.startswith("init_")}
    arrays.update({f"init_{k}": getattr(init, k) for k in BodyParams.FIELDS})
    return arrays


def bench_throughput(
    persons: int,
    device: str,
    weights,
    settings,
    pool: int = 64,
    sensor: str = "ouster-128",
    seed: int = 0,
    pool_arrays: dict | None = None,
) -> dict:
    """Person-fits/s of ``fit_persons`` on one batch of ``persons`` on ``device``.

    ``pool`` distinct persons are simulated (or given as ``pool_arrays``, :func:`simulated_pool`)
    and repeated to fill the batch: fits do not interact, so repeats cost the same as new persons.
    A warm-up fit of a few persons first (device start-up, kernels, numba compilation); the timed
    fit returns numpy arrays, so the device has finished when the clock stops (and it is
    synchronised explicitly as well). Also timed alone: the batched ICP of the same batch. Returns
    the JSON record (fits_per_s, wall_s, icp_s, mpjpe_mm of the fits, peak device memory)."""
    import numpy as np
    import torch

    from tasks.body.params import BodyParams
    from tasks.body.prior import GMMPosePrior, generate_pose_prior
    from tasks.body.procedural import default_body_model
    from tasks.fit.icp import icp_align
    from tasks.fit.metrics import mean_error_mm
    from tasks.fit.optimize import LIDAR_MIN_POINTS, fit_persons, ragged_points
    from tasks.fit.visibility import vertex_parts, visibility_masks

    iterations = settings.iterations

    def sync():
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    model = default_body_model()
    g = generate_pose_prior()
    prior = GMMPosePrior(g["means"], g["covars"], g["weights"]).to(device)
    a = pool_arrays if pool_arrays is not None else simulated_pool(min(pool, persons), sensor, seed)
    n = len(a["keypoints"])
    init0 = BodyParams(*(a[f"init_{k}"] for k in BodyParams.FIELDS))
    rep = np.arange(persons) % n
    init = init0.take(rep)
    pts, counts = ragged_points(a["points_lidar"][rep], a["point_mask"][rep])
    fit_settings = dataclasses.replace(settings, device=device)
    w = min(4, persons)
    warm_pts, warm_counts = ragged_points(a["points_lidar"][rep[:w]], a["point_mask"][rep[:w]])
    fit_persons(
        model,
        prior,
        init.take(slice(0, w)),
        a["keypoints"][rep[:w]],
        a["K"],
        a["T_cam_from_lidar"],
        warm_pts,
        warm_counts,
        weights,
        dataclasses.replace(fit_settings, iterations=min(iterations, 6)),
    )
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    sync()
    cpu0, t0 = time.process_time(), time.perf_counter()
    r = fit_persons(
        model,
        prior,
        init,
        a["keypoints"][rep],
        a["K"],
        a["T_cam_from_lidar"],
        pts,
        counts,
        weights,
        fit_settings,
    )
    sync()
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    # the ICP alone, as the fit runs it: the initial meshes' visible vertices of the same batch
    dev_model = model.to(device) if device != "cpu" else model
    kp = torch.as_tensor(a["keypoints"][rep], device=device)
    with torch.no_grad():
        o = dev_model(
            *(torch.as_tensor(getattr(init, k), device=device) for k in BodyParams.FIELDS)
        )
        vis = visibility_masks(
            o.vertices,
            dev_model.faces_tensor,
            torch.as_tensor(vertex_parts(model.lbs_weights), device=device),
            kp[..., 2],
            w=weights.w,
            j_conf=weights.j_conf,
        )
    T = torch.as_tensor(a["T_cam_from_lidar"], dtype=torch.float64, device=device)
    p_cam = (
        torch.as_tensor(pts, dtype=torch.float64, device=device) @ T[:3, :3].T + T[:3, 3]
    ).float()
    person = torch.repeat_interleave(
        torch.arange(persons, device=device), torch.as_tensor(counts, device=device)
    )
    sync()
    t1 = time.perf_counter()
    icp_align(o.vertices, vis.vertex_mask, p_cam, person, min_person_points=LIDAR_MIN_POINTS)
    sync()
    icp_s = time.perf_counter() - t1
    out = {
        "device": device,
        "device_name": torch.cuda.get_device_name() if device.startswith("cuda") else "cpu",
        "torch_threads": torch.get_num_threads(),
        "persons": persons,
        "distinct_persons": n,
        "iterations": iterations,
        "nn_every": settings.nn_every,
        "wall_s": round(wall, 3),
        "fits_per_s": round(persons / wall, 2),
        # the process CPU time (all its threads): less sensitive to a busy machine than wall_s
        "cpu_s": round(cpu, 3),
        "fits_per_cpu_s": round(persons / cpu, 2),
        "icp_s": round(icp_s, 3),
        "mpjpe_mm": round(float(mean_error_mm(r.joints, a["truth_joints"][rep]).mean()), 2),
        "mean_steps": float(r.residuals["steps"].mean()),
    }
    if device.startswith("cuda"):
        out["peak_memory_gb"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
    return out


def device_agreement(pool_arrays: dict, device: str, weights, iterations: int = 30) -> dict:
    """The same persons fitted on the CPU and on ``device`` (twice): the largest vertex
    difference CPU vs device (m), whether the steps taken agree, the largest ICP-fitness
    difference, and whether two device runs are bit-identical (tests/test_fit.py asserts the same
    on a 2-person scene where CUDA is present)."""
    import copy

    import numpy as np

    from tasks.body.params import BodyParams
    from tasks.body.prior import GMMPosePrior, generate_pose_prior
    from tasks.body.procedural import default_body_model
    from tasks.fit.optimize import fit_persons, ragged_points
    from tasks.fit.settings import FitSettings

    a, model = pool_arrays, default_body_model()
    g = generate_pose_prior()
    prior = GMMPosePrior(g["means"], g["covars"], g["weights"])
    init = BodyParams(*(a[f"init_{k}"] for k in BodyParams.FIELDS))
    pts, counts = ragged_points(a["points_lidar"], a["point_mask"])
    settings = dataclasses.replace(FitSettings(), iterations=iterations)

    def fit(dev):
        p = prior if dev == "cpu" else copy.deepcopy(prior).to(dev)
        return fit_persons(
            model,
            p,
            init,
            a["keypoints"],
            a["K"],
            a["T_cam_from_lidar"],
            pts,
            counts,
            weights,
            dataclasses.replace(settings, device=dev),
        )

    c, d1, d2 = fit("cpu"), fit(device), fit(device)
    return {
        "persons": len(counts),
        "iterations": iterations,
        "max_vertex_diff_m": float(np.abs(c.vertices - d1.vertices).max()),
        "steps_equal": bool(np.array_equal(c.residuals["steps"], d1.residuals["steps"])),
        "max_icp_fitness_diff": float(
            np.abs(c.residuals["icp_fitness"] - d1.residuals["icp_fitness"]).max()
        ),
        "device_runs_identical": bool(np.array_equal(d1.vertices, d2.vertices)),
    }


def _print_table(sensor: str, table: dict, persons: int, occluded: int) -> None:
    cols = ("pve", "mpjpe", "pa_mpjpe", "pve_root", "mpjpe_root", "mpere")
    print(f"\n{sensor}: {persons} persons ({occluded} with an occluded limb); mm, MPERE unitless")
    print(f"{'method':24s}" + "".join(f"{c:>11s}" for c in cols))
    for name, m in table.items():
        print(
            f"{name:24s}"
            + "".join(f"{m[c]:11.1f}" if c != "mpere" else f"{m[c]:11.3f}" for c in cols)
        )
    print("std over persons:")
    for name, m in table.items():
        if "std" in m:
            o = m["std"]
            print(
                f"  {name:22s}"
                + "".join(f"{o[c]:11.1f}" if c != "mpere" else f"{o[c]:11.3f}" for c in cols)
            )
    for name, m in table.items():
        if "occluded_subset" in m:
            o = m["occluded_subset"]
            print(
                f"  occluded subset, {name:18s}"
                + "".join(f"{o[c]:11.1f}" if c != "mpere" else f"{o[c]:11.3f}" for c in cols)
            )
