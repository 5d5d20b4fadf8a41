"""``mobileocc view``: look at a published dataset in 3D, in the browser.

- served: ``view(dataset, ...)`` starts a viser server on localhost (the next free port when the
  one asked for is taken, said on the console) and its JSON API on the port after it
  (flows/viewer/qa.py), and serves until Ctrl-C;
- ``html=FILE``: one self-contained HTML page of a frame or a short range of frames (viser's
  client and the recorded scene inline: no server, no network), written atomically;
- ``qa=True``: the manual detection QA pass (flows/viewer/qa.py).

Errors a user can cause (a path that is not a dataset, a sequence or frame that does not exist,
a QA table of another version) raise ViewerInputError / QATableError with one message; nothing is
written before they are checked.
"""

from __future__ import annotations

import signal
import sys
import time
from pathlib import Path

from flows.viewer.draw import FrameDrawer, Layers
from storage.atomic import atomic_write_bytes
from storage.manifest import Manifest
from storage.viewer_data import ViewerInputError, ViewerSource

#: at most this many frames in one HTML page (each frame's scene is held in the page)
MAX_HTML_FRAMES = 50


def body_model(out: Path):
    """The body model the dataset was fitted with (``fit.body_model_path`` recorded in the
    manifest), else the procedural one the simulator and the demo use."""
    from storage.body_model_files import load_body_model
    from tasks.body.model import BodyModel
    from tasks.body.procedural import default_body_model

    try:
        config = Manifest.load(out).meta.get("config") or {}
    except (OSError, ValueError):
        config = {}
    path = (config.get("fit") or {}).get("body_model_path")
    if path and Path(path).is_file():
        return BodyModel(load_body_model(Path(path)))
    return default_body_model()


def _start_frame(source: ViewerSource, sequence: str | None, frame: int | None) -> tuple[str, int]:
    sequence = source.check_sequence(sequence) if sequence is not None else source.sequences[0]
    return sequence, source.check_frame(sequence, 0 if frame is None else frame)


def export_html(
    source: ViewerSource,
    sequence: str,
    first: int,
    count: int,
    path: Path,
    layers: Layers,
    fps: float = 5.0,
) -> dict:
    """Write frames ``first .. first + count - 1`` of ``sequence`` (clipped to the sequence) as
    one self-contained HTML page at ``path``; returns {frames, bytes, seconds, layers, notes}."""
    from flows.viewer.app import with_boxes

    if not 1 <= count <= MAX_HTML_FRAMES:
        raise ViewerInputError(f"--frames {count}: expected 1..{MAX_HTML_FRAMES}")
    path = Path(path)
    if path.is_dir():
        raise ViewerInputError(f"--html {path}: is a folder, expected a file name")
    frames = list(range(first, min(source.num_frames(sequence), first + count)))
    datas = (with_boxes(source.frame(sequence, k)) for k in frames)
    res = write_html(datas, path, layers, body_model(source.out), fps)
    return {**res, "frames": frames}


def write_html(datas, path: Path, layers: Layers, model=None, fps: float = 5.0) -> dict:
    """Record the frames ``datas`` (FrameData, in order, 1 / fps s apart) into one self-contained
    HTML page (viser's client with the scene inline) written atomically at ``path``; returns
    {bytes, seconds, layers (of the last frame), notes}."""
    from flows.viewer.app import place_camera, start_viser, stop_viser

    t0 = time.perf_counter()
    server = start_viser("127.0.0.1", 0)  # the recording needs a scene; nothing connects to it
    try:
        serializer, drawer, stats = None, FrameDrawer(server.scene, model), None
        for data in datas:
            if serializer is None:
                place_camera(server.initial_camera, data)
                serializer = server.get_scene_serializer()
            else:
                serializer.insert_sleep(1.0 / fps)
            stats = drawer.draw(data, layers)
        if serializer is None:
            raise ViewerInputError(f"--html {path}: no frame to write")
        page = serializer.as_html().encode()
    finally:
        stop_viser(server)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, page)
    return {
        "bytes": len(page),
        "seconds": time.perf_counter() - t0,
        "layers": stats.layers,
        "notes": stats.notes,
    }


def start(
    dataset: Path,
    sequence: str | None = None,
    frame: int | None = None,
    port: int = 8080,
    host: str = "127.0.0.1",
    layers: Layers | None = None,
    qa: bool = False,
    qa_frames: int | None = None,
    data_root: Path | None = None,
):
    """Start the served viewer (and its API) without blocking; returns (ViewerApp, API server)."""
    from flows.viewer.app import ViewerApp
    from flows.viewer.qa import FRAMES_PER_CONDITION, QASession, serve_api

    source = ViewerSource(dataset, data_root)
    session = None
    if qa:
        session = QASession(source, qa_frames or FRAMES_PER_CONDITION)
        if frame is None and sequence is None:
            nxt = session.progress()["next"]
            if nxt is not None:
                sequence, frame = session.sample[nxt]["sequence"], session.sample[nxt]["frame"]
    sequence, frame = _start_frame(source, sequence, frame)
    app = ViewerApp(
        source,
        sequence,
        frame,
        layers or Layers(),
        host,
        port,
        qa=session,
        body_model=body_model(source.out),
    )
    try:
        api = serve_api(app, host, app.port + 1)
    except OSError:
        app.close()
        raise
    return app, api


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def serving_lines(app, api, port: int) -> list[str]:
    """What `view` says when it serves: the URLs (and that the port asked for was taken)."""
    lines = []
    if app.port != port and port != 0:
        lines.append(f"port {port} is in use: serving on port {app.port} instead")
    lines += [
        f"viewer: {app.url}  (from another machine: ssh -L {app.port}:localhost:{app.port} "
        "<this host>, then open the URL)",
        f"API: http://{app.host}:{api.server_address[1]}/api/state",
    ]
    if app.qa is not None:
        prog = app.qa.progress()
        lines.append(
            f"QA: {prog['checked']} of {prog['total']} sample frames checked; verdicts are saved "
            f"to {app.source.out / 'qa' / 'detection_qa.parquet'}"
        )
    return lines


def view(
    dataset: Path,
    sequence: str | None = None,
    frame: int | None = None,
    port: int = 8080,
    host: str = "127.0.0.1",
    html: Path | None = None,
    frames: int = 1,
    layers: Layers | None = None,
    qa: bool = False,
    qa_frames: int | None = None,
    data_root: Path | None = None,
) -> int:
    """The command: write the HTML page, or serve until interrupted. Returns the exit code."""
    layers = layers or Layers()
    if html is not None:
        source = ViewerSource(dataset, data_root)
        sequence, frame = _start_frame(source, sequence, frame)
        res = export_html(source, sequence, frame, frames, html, layers)
        shown = ", ".join(f"{k} {v['shown']}" for k, v in res["layers"].items())
        print(
            f"{html}: {res['bytes'] / 1e6:.1f} MB, sequence {sequence} frame(s) "
            f"{res['frames'][0]}..{res['frames'][-1]} ({shown}), written in {res['seconds']:.1f} s"
        )
        for note in res["notes"]:
            print(f"  {note}")
        return 0
    app, api = start(dataset, sequence, frame, port, host, layers, qa, qa_frames, data_root)
    for line in serving_lines(app, api, port):
        print(line)
    print("Ctrl-C to stop")
    sys.stdout.flush()
    signal.signal(signal.SIGTERM, _interrupt)  # a service manager's stop: the same clean close
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        api.shutdown()
        app.close()
    return 0
