"""``mobileocc bench viewer``: what a frame costs the 3D viewer, at 0.2 m and at 0.02 m.

Per grid: occupied voxels, surface voxels, what is drawn (voxels or merged blocks), the seconds
to build the scene and write the self-contained page, the page's size, and, in headless Chromium
(when installed), how long the page takes to show the frame (navigation until the class colours
are on screen and the picture stops changing; screenshots every 0.25 s) and the page's JavaScript
heap.

Frames: the benchmark range (x 0.4..10, y -4.8..4.8, z -1..3.8 m) filled as
flows/bench/storage.py's ``synthetic_frames`` does (ground, a car, a wall, a pole, three people:
2.5 M occupied voxels at 0.02 m), and, with ``--dataset OUT``, a frame of a built dataset.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from tasks import conventions as C

#: classes whose colour must be on screen for a frame to count as shown
SHOWN_CLASSES = (C.ROAD, C.TERRAIN, C.PEDESTRIAN)


def class_pixel_counts(image: np.ndarray, classes=SHOWN_CLASSES, tol: float = 0.09) -> dict:
    """{class name: pixels of ``image`` (H, W, 3) uint8 whose colour is that class's colour up to
    shading}: each pixel and colour divided by its largest channel (lighting scales a surface's
    colour), then compared channel by channel within ``tol``; near-black and grey pixels are
    left out (edges, grid lines, the unknown layer)."""
    img = image.reshape(-1, 3).astype(np.float64)
    peak = img.max(1)
    ok = (peak > 60) & (img.max(1) - img.min(1) > 20)
    norm = img[ok] / peak[ok, None]
    out = {}
    for c in classes:
        ref = C.CLASS_COLORS[c].astype(np.float64)
        ref = ref / ref.max()
        out[C.CLASS_NAMES[c]] = int(np.sum(np.all(np.abs(norm - ref) < tol, axis=1)))
    return out


def time_to_show(
    browser, url: str, timeout_s: float = 300.0, min_pixels: int = 50, still: bool = True
) -> dict:
    """Navigate to ``url`` and poll screenshots until every SHOWN_CLASSES colour covers at least
    ``min_pixels`` and (``still``) two screenshots in a row are equal (a page that plays several
    frames never stands still: ``still=False``); {seconds (None: timed out), counts, image}."""
    t0 = time.perf_counter()
    browser.goto(url)
    last = None
    while True:
        img = browser.screenshot()
        counts = class_pixel_counts(img)
        if all(v >= min_pixels for v in counts.values()):
            if not still or (last is not None and np.array_equal(img, last)):
                return {"seconds": time.perf_counter() - t0, "counts": counts, "image": img}
        last = img
        if time.perf_counter() - t0 > timeout_s:
            return {"seconds": None, "counts": counts, "image": img}
        time.sleep(0.25)


FRAME_RATE_JS = (
    "new Promise(done => { let n = 0; const t0 = performance.now();"
    " const tick = () => { n++; if (performance.now() - t0 < 3000) requestAnimationFrame(tick);"
    " else done(n * 1000 / (performance.now() - t0)); }; requestAnimationFrame(tick); })"
)


def page_metrics(browser) -> dict:
    """The page's JavaScript heap (MB), frames drawn per second over 3 s (the page does not
    freeze when this stays above a few per second) and Chromium's CPU time per drawn frame."""
    browser.call("Performance.enable")
    metrics = {m["name"]: m["value"] for m in browser.call("Performance.getMetrics")["metrics"]}
    cpu0, t0 = browser.cpu_seconds(), time.perf_counter()
    fps = float(browser.evaluate(FRAME_RATE_JS))
    cpu = browser.cpu_seconds() - cpu0
    frames = fps * (time.perf_counter() - t0)
    return {
        "js_heap_MB": round(metrics.get("JSHeapUsedSize", 0) / 1e6, 1),
        "frames_per_s": round(fps, 1),
        # what a drawn frame costs Chromium (software WebGL), whatever else the machine runs
        "cpu_ms_per_frame": round(1000 * cpu / frames) if frames > 0 else None,
    }


def synthetic_frame(voxel_size_m: float):
    """One FrameData of the benchmark range at ``voxel_size_m`` (no sensors)."""
    from flows.bench.storage import RANGE_MIN, synthetic_frames
    from storage.viewer_data import FrameData

    g = {k: v[0] for k, v in synthetic_frames(1, voxel_size_m).items()}
    K = np.array([[700.0, 0, 612], [0, 700, 512], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    T[:3, 3] = (0.2, 0.0, 1.0)
    return FrameData(
        sequence="bench",
        frame=0,
        raw_frame=0,
        num_frames=1,
        stamp_ns=0,
        is_night=False,
        range_min=np.asarray(RANGE_MIN, np.float64),
        voxel_size_m=voxel_size_m,
        semantics=g["semantics"],
        instances=g["instances"],
        mask_lidar=g["mask_lidar"],
        mask_camera=g["mask_camera"],
        velocity=g["velocity"],
        persons=[],
        K=K,
        width=1224,
        height=1024,
        T_base_from_cam0=T,
        T_base_from_lidar=np.eye(4),
    )


def measure(data, work: Path, name: str, browser=None, layers=None, model=None) -> dict:
    """Build, write and (with a browser) show one frame (bodies drawn with the body ``model``
    where given); the figures of the module docstring."""
    from flows.commands.view import write_html
    from flows.viewer.draw import Layers

    layers = layers or Layers(lidar=False, camera=False)
    occupied = int(np.count_nonzero(data.semantics < C.FREE))
    page = work / f"{name}.html"
    res = write_html([data], page, layers, model)
    row = {
        "voxel_size_m": data.voxel_size_m,
        "grid": list(data.semantics.shape),
        "occupied_voxels": occupied,
        "labels_layer": res["layers"].get("labels_voxels"),
        "write_seconds": round(res["seconds"], 2),
        "page_MB": round(res["bytes"] / 1e6, 2),
    }
    if browser is not None:
        seen = len(browser.requests)
        shown = time_to_show(browser, page.resolve().as_uri())
        row["show_seconds"] = None if shown["seconds"] is None else round(shown["seconds"], 1)
        row.update(page_metrics(browser))
        row["class_pixels"] = shown["counts"]
        row["requests_not_local"] = [
            u.split(":", 1)[0]
            for u in browser.requests[seen:]
            if not u.startswith(("file:", "data:", "blob:"))
        ]
        if name.startswith("dataset"):
            from PIL import Image

            Image.fromarray(shown["image"]).save(work / f"{name}.png")
    return row


HIDE_NOTICES = (
    "(() => { const s = document.createElement('style');"
    " s.textContent = '.mantine-Notifications-root { display: none !important; }';"
    " document.head.appendChild(s); return true; })()"
)
CLICK_NEXT = (
    "(() => { const b = [...document.querySelectorAll('button')]"
    ".find(e => e.textContent.trim() === 'next frame'); if (b) b.click(); return !!b; })()"
)


def measure_served(dataset: Path, sequence: str, frame: int, browser, screenshot=None) -> dict:
    """The served viewer: seconds until the first frame shows, and from a click on "next frame"
    until the new frame's picture is on screen and still; optionally a screenshot (PNG, 960 px
    wide, notices hidden) of the first frame."""
    from flows.commands.view import start

    app, api = start(dataset, sequence, frame, port=0)
    try:
        first = time_to_show(browser, app.url)
        row = {"show_seconds": None if first["seconds"] is None else round(first["seconds"], 1)}
        row.update(page_metrics(browser))
        if screenshot is not None:
            from PIL import Image

            browser.evaluate(HIDE_NOTICES)
            time.sleep(1.0)
            img = Image.fromarray(browser.screenshot())
            img = img.resize((960, round(img.height * 960 / img.width)), Image.LANCZOS)
            img.save(screenshot, optimize=True)
        before = browser.screenshot()
        t0 = time.perf_counter()
        browser.evaluate(CLICK_NEXT)
        last, step = None, None
        while time.perf_counter() - t0 < 300:
            img = browser.screenshot()
            if not np.array_equal(img, before) and last is not None and np.array_equal(img, last):
                step = time.perf_counter() - t0
                break
            last = img
            time.sleep(0.25)
        row["step_seconds"] = None if step is None else round(step, 1)
        row["frame_after_step"] = app.frame
        row["draw_seconds"] = round(app.stats.seconds, 2)
    finally:
        api.shutdown()
        app.close()
    return row


def bench_viewer(
    dataset: Path | None = None,
    sequence: str | None = None,
    frame: int = 0,
    browser: bool = True,
    synthetic: bool = True,
    keep: Path | None = None,
    screenshot: Path | None = None,
) -> dict:
    """The figures of the module docstring: a frame of ``dataset`` (its page and the served
    viewer) and the synthetic 0.2 m / 0.02 m frames; in Chromium where ``browser`` and one is
    installed. The pages go to ``keep`` (default: a temporary folder, left for a look)."""
    from flows.bench.chromium import Chromium, find_chromium

    work = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="mobileocc-bench-view-"))
    work.mkdir(parents=True, exist_ok=True)
    chromium = Chromium(1280, 800) if browser and find_chromium() is not None else None
    results = {}
    try:
        if dataset is not None:
            from flows.commands.view import body_model
            from flows.viewer.app import with_boxes
            from flows.viewer.draw import Layers
            from storage.viewer_data import ViewerSource

            src = ViewerSource(dataset)
            seq = sequence or src.sequences[0]
            data = with_boxes(src.frame(seq, frame))
            results[f"dataset_{data.voxel_size_m:g}m"] = measure(
                data, work, "dataset", chromium, Layers(), body_model(dataset)
            )
            if chromium is not None:
                results["dataset_served"] = measure_served(
                    dataset, seq, frame, chromium, screenshot
                )
        for vs in (0.2, 0.02) if synthetic else ():
            t0 = time.perf_counter()
            data = synthetic_frame(vs)
            made = time.perf_counter() - t0
            results[f"synthetic_{vs:g}m"] = {
                **measure(data, work, f"synthetic_{vs:g}m", chromium),
                "make_seconds": round(made, 1),
            }
    finally:
        if chromium is not None:
            chromium.close()
    return results
