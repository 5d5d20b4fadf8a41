"""The served viewer: a viser server on localhost with a frame slider, play, layer toggles and,
with ``--qa``, the QA panel; its JSON API (flows/viewer/qa.py) on the next port.

One scene for every browser that connects (viser's shared state): stepping a frame in one
browser steps it in all. Drawing a frame happens under a lock; requests that arrive meanwhile
collapse to the latest.
"""

from __future__ import annotations

import threading
import time
from contextlib import redirect_stdout
from io import StringIO

import numpy as np

from flows.viewer.draw import FrameDrawer, Layers, view_center
from storage.viewer_data import ViewerSource
from tasks.view import scene as S
from tasks.view.qa import QAMarkError
from tasks.viz import instance_colors

LAYER_TOGGLES = (
    ("voxels", "occupied voxels"),
    ("pedestrian_voxels", "pedestrian voxels"),
    ("unknown", "unknown (grey)"),
    ("bodies", "bodies"),
    ("boxes", "boxes"),
    ("velocity", "velocity arrows"),
    ("lidar", "LiDAR sweep"),
    ("camera", "camera + image"),
    ("ground_truth", "ground truth (beside)"),
    ("difference", "difference (right)"),
)


def start_viser(host: str, port: int):
    """A viser server on (host, port), the next free port when taken (viser tries upwards);
    its banner is kept off the console (the command prints its own line)."""
    import viser

    with redirect_stdout(StringIO()):
        server = viser.ViserServer(host=host, port=port, label="mobileocc", verbose=False)
    server.scene.set_up_direction("+z")
    # no image-based lighting: it pales the bodies' colours and costs seconds of software
    # rendering on machines without a GPU; the default lights shade the bodies
    server.scene.configure_environment_map(hdri=None)
    server.scene.configure_default_lights(enabled=True, cast_shadow=False)
    return server


def stop_viser(server) -> None:
    with redirect_stdout(StringIO()):  # viser's "Server stopped" line
        server.stop()


def place_camera(target, data) -> None:
    """Initial view: behind and above the robot, looking at the labels' grid (target: a
    server's ``initial_camera`` or a client's ``camera``)."""
    center = view_center(data)
    extent = float(np.max(np.asarray(data.semantics.shape[:2]) * data.voxel_size_m))
    target.look_at = tuple(center)
    target.position = tuple(center + [-0.55 * extent, 0.25 * extent, 0.6 * extent])


class ViewerApp:
    """The viewer of ``source`` (storage.viewer_data.ViewerSource). ``qa``: a QASession or None."""

    def __init__(
        self,
        source: ViewerSource,
        sequence: str,
        frame: int,
        layers: Layers,
        host: str = "127.0.0.1",
        port: int = 8080,
        qa=None,
        body_model=None,
        fps: float = 5.0,
    ):
        self.source, self.layers, self.qa, self.fps = source, layers, qa, fps
        self.server = start_viser(host, port)
        self.host, self.port = host, int(self.server.get_port())
        self.drawer = FrameDrawer(self.server.scene, body_model)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self.sequence, self.frame, self.data, self.stats = sequence, int(frame), None, None
        self._qa_widgets: list = []
        self._verdicts: dict[int, str] = {}
        self._misses: list[dict] = []
        try:
            self._build_gui()
            self.show(sequence, frame)
        except BaseException:
            stop_viser(self.server)
            raise
        place_camera(self.server.initial_camera, self.data)
        if qa is not None:
            self._enable_image_clicks()
        self._player = threading.Thread(target=self._play_loop, daemon=True, name="view-play")
        self._player.start()

    # ---- state ---------------------------------------------------------------------------------

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    def state(self) -> dict:
        d = self.data
        return {
            "sequence": self.sequence,
            "frame": self.frame,
            "num_frames": self.source.num_frames(self.sequence),
            "raw_frame": None if d is None else d.raw_frame,
            "viewer_url": self.url,
            "drawn": None if self.stats is None else self.stats.layers,
        }

    def show(self, sequence: str, frame: int) -> dict:
        """Draw ``frame`` of ``sequence`` (ViewerInputError when there is no such frame)."""
        frame = self.source.check_frame(self.source.check_sequence(sequence), int(frame))
        with self._lock:
            data = with_boxes(self.source.frame(sequence, frame))
            self.stats = self.drawer.draw(data, self.layers)
            self.sequence, self.frame, self.data = sequence, frame, data
            self._sync_gui()
            if self.qa is not None:
                self._attach_click()
        return self.state()

    # ---- GUI -----------------------------------------------------------------------------------

    def _build_gui(self) -> None:
        gui = self.server.gui
        n = self.source.num_frames(self.sequence)
        with gui.add_folder("Frame"):
            self.g_seq = gui.add_dropdown(
                "sequence", tuple(self.source.sequences), initial_value=self.sequence
            )
            self.g_frame = gui.add_slider("frame", 0, max(n - 1, 1), 1, self.frame)
            self.g_prev = gui.add_button("previous frame")
            self.g_next = gui.add_button("next frame")
            self.g_play = gui.add_checkbox("play", False)
            self.g_info = gui.add_markdown("")
        with gui.add_folder("Layers"):
            self.g_layers = {
                key: gui.add_checkbox(label, bool(getattr(self.layers, key)))
                for key, label in LAYER_TOGGLES
            }
            self.g_mask = gui.add_dropdown(
                "mask", ("none", "camera", "lidar"), initial_value=self.layers.mask
            )
            self.g_style = gui.add_dropdown(
                "voxel style", ("points", "cubes"), initial_value=self.layers.style
            )
            self.g_look = gui.add_button("look through the camera")

        @self.g_seq.on_update
        def _(_) -> None:  # also fired when show() sets the value: then it is the sequence shown
            if self.g_seq.value != self.sequence:
                self._request(self.g_seq.value, 0)

        @self.g_frame.on_update
        def _(_) -> None:
            if int(self.g_frame.value) != self.frame:
                self._request(self.sequence, int(self.g_frame.value))

        @self.g_prev.on_click
        def _(_) -> None:
            self._request(self.sequence, max(0, self.frame - 1))

        @self.g_next.on_click
        def _(_) -> None:
            n = self.source.num_frames(self.sequence)
            self._request(self.sequence, min(n - 1, self.frame + 1))

        for key, box in self.g_layers.items():
            box.on_update(lambda _, key=key, box=box: self._set_layers(**{key: bool(box.value)}))
        self.g_mask.on_update(lambda _: self._set_layers(mask=self.g_mask.value))
        self.g_style.on_update(lambda _: self._set_layers(style=self.g_style.value))

        @self.g_look.on_click
        def _(event) -> None:
            cam = self.drawer.camera
            if cam is None or event.client is None:
                return
            R = _rotation(cam.wxyz)
            event.client.camera.position = tuple(cam.position)
            event.client.camera.look_at = tuple(cam.position + R[:, 2] * 5.0)
            event.client.camera.up_direction = tuple(-R[:, 1])

        if self.qa is not None:
            self._build_qa_gui()

    def _request(self, sequence: str, frame: int) -> None:
        try:
            self.show(sequence, frame)
        except Exception as exc:  # shown in the panel, the viewer goes on
            self.g_info.content = f"**cannot show {sequence} frame {frame}:** {exc}"

    def _set_layers(self, **kw) -> None:
        self.layers = self.layers.with_(**kw)
        self._request(self.sequence, self.frame)

    def _sync_gui(self) -> None:
        d, st = self.data, self.stats
        n = self.source.num_frames(self.sequence)
        if self.g_seq.value != self.sequence:
            self.g_seq.value = self.sequence
        self.g_frame.max = max(n - 1, 1)
        if int(self.g_frame.value) != self.frame:
            self.g_frame.value = self.frame
        lines = [
            f"**sequence {d.sequence}, frame {d.frame} / {n - 1}** (raw {d.raw_frame}"
            f"{', night' if d.is_night else ''}), {len(d.persons)} person(s), "
            f"{d.voxel_size_m:g} m voxels {d.grid_shape}",
        ]
        for key, v in st.layers.items():
            block = f", merged {v['block']}x{v['block']}x{v['block']}" if v["block"] > 1 else ""
            lines.append(
                f"- {key}: {v['shown']} {v.get('style', '')} of {v['selected']} voxels "
                f"({v['surface']} on the surface{block})"
            )
        lines.append(f"- drawn in {st.seconds:.2f} s")
        lines += [f"- *{note}*" for note in st.notes]
        self.g_info.content = "\n".join(lines)
        if self.qa is not None:
            self._refresh_qa_gui()

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            if self.g_play.value:
                n = self.source.num_frames(self.sequence)
                self._request(self.sequence, (self.frame + 1) % n)
            self._stop.wait(max(0.0, 1.0 / self.fps - (time.monotonic() - t0)))

    # ---- QA ------------------------------------------------------------------------------------

    def _build_qa_gui(self) -> None:
        gui = self.server.gui
        with gui.add_folder("QA"):
            self.g_qa_info = gui.add_markdown("")
            self.g_qa_goto = gui.add_button("go to the next unchecked frame")
            self.g_qa_miss = gui.add_dropdown(
                "a click on the image marks", ("nothing", "M_vis", "M_occ"), initial_value="M_vis"
            )
            self.g_qa_clear = gui.add_button("clear the clicked misses")
            self.g_qa_save = gui.add_button("save this frame and go on")
            self.g_qa_persons = gui.add_folder("labelled persons: T or W")

        @self.g_qa_goto.on_click
        def _(_) -> None:
            nxt = self.qa.progress()["next"]
            if nxt is not None:
                f = self.qa.sample[nxt]
                self._request(f["sequence"], f["frame"])

        self.g_qa_clear.on_click(lambda _: self.clear_misses())

        self.g_qa_save.on_click(lambda _: self.save_verdict())

    def save_verdict(self) -> str | None:
        """The panel's "save this frame and go on": save the marks made on this frame, then show
        the next unchecked one; returns None, or why nothing was saved (also in the panel)."""
        marks = [{"kind": k, "track_id": t} for t, k in self._verdicts.items()] + self._misses
        try:
            self.qa.save(self.sequence, self.frame, marks)
        except (QAMarkError, ValueError) as exc:
            self.g_qa_info.content = f"**not saved:** {exc}"
            return str(exc)
        nxt = self.qa.progress()["next"]
        if nxt is not None:
            f = self.qa.sample[nxt]
            self._request(f["sequence"], f["frame"])
        else:
            self._refresh_qa_gui()
        return None

    def _refresh_qa_gui(self) -> None:
        for w in self._qa_widgets:
            w.remove()
        self._qa_widgets = []
        saved = self.qa.frame_info(self.sequence, self.frame)
        self._verdicts = {
            int(m["track_id"]): m["kind"] for m in saved["marks"] if m["track_id"] is not None
        }
        self._misses = [m for m in saved["marks"] if m["track_id"] is None]
        with self.g_qa_persons:
            for p in saved["persons"]:
                tid = p["track_id"]
                group = self.server.gui.add_button_group(f"#{tid}", ("T", "W"))
                group.on_click(lambda e, tid=tid: self.mark(tid, e.target.value))
                self._qa_widgets.append(group)
        self._draw_misses()
        self._refresh_qa_text()

    def clear_misses(self) -> None:
        """The panel's "clear the clicked misses"."""
        self._misses = []
        self._draw_misses()
        self._refresh_qa_text()

    def mark(self, track_id: int, kind: str) -> None:
        """A labelled person's button: T or W."""
        self._verdicts[int(track_id)] = kind
        self._refresh_qa_text()

    def _refresh_qa_text(self) -> None:
        prog = self.qa.progress()
        here = next(
            (
                f
                for f in prog["sample"]
                if (f["sequence"], f["frame"]) == (self.sequence, self.frame)
            ),
            None,
        )
        persons = self.qa.persons(self.sequence, self.frame)
        lines = [
            f"**{prog['checked']} / {prog['total']} frames checked**; this frame: "
            + ("not in the sample" if here is None else here["condition"])
            + (" (saved)" if here is not None and here["checked"] else ""),
            "marks: "
            + (
                ", ".join(
                    f"#{p['track_id']} {self._verdicts.get(p['track_id'], '?')}" for p in persons
                )
                or "no labelled person"
            ),
            f"misses clicked: {', '.join(m['kind'] for m in self._misses) or 'none'}",
        ]
        self.g_qa_info.content = "\n\n".join(lines)

    def _enable_image_clicks(self) -> None:
        self._image_click = lambda event: self.click_image(event.ray_origin, event.ray_direction)
        self._attach_click()

    def click_image(self, ray_origin, ray_direction) -> tuple[float, float] | None:
        """A click on the camera image (QA): a missed person (of the kind the panel's menu says)
        at the pixel the click ray hits; returns that pixel, or None (no image hit, or the menu
        says nothing)."""
        kind = self.g_qa_miss.value
        d, cam = self.data, self.drawer.camera
        if kind == "nothing" or d is None or cam is None:
            return None
        uv = S.pixel_from_ray(ray_origin, ray_direction, d.K, d.T_base_from_cam0, cam.depth_m)
        if uv is None or not (0 <= uv[0] < d.width and 0 <= uv[1] < d.height):
            return None
        self._misses.append({"kind": kind, "track_id": None, "u": uv[0], "v": uv[1]})
        self._draw_misses()
        self._refresh_qa_text()
        return uv

    def _attach_click(self) -> None:
        handle = self.drawer.handles.get("/sensors/image")
        if handle is not None and getattr(self, "_image_click", None) is not None:
            handle.on_click(self._image_click)

    def _draw_misses(self) -> None:
        d, cam = self.data, self.drawer.camera
        for name in [n for n in self.drawer.handles if n.startswith("/qa/")]:
            self.drawer.handles.pop(name).remove()
        if d is None or cam is None:
            return
        T = d.T_base_from_cam0
        for i, m in enumerate(self._misses):
            p_cam = np.array(
                [
                    (m["u"] - d.K[0, 2]) / d.K[0, 0] * cam.depth_m,
                    (m["v"] - d.K[1, 2]) / d.K[1, 1] * cam.depth_m,
                    cam.depth_m * 0.99,
                ]
            )
            p = T[:3, :3] @ p_cam + T[:3, 3]
            color = (31, 90, 220) if m["kind"] == "M_vis" else (120, 120, 120)
            self.drawer.handles[f"/qa/miss_{i}"] = self.server.scene.add_icosphere(
                f"/qa/miss_{i}", radius=0.03, color=color, position=tuple(p)
            )
        self._attach_click()

    def close(self) -> None:
        self._stop.set()
        stop_viser(self.server)


def _rotation(wxyz) -> np.ndarray:
    w, x, y, z = (float(v) for v in wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def with_boxes(data):
    """The frame with its labelled persons' 2D boxes drawn on the camera image."""
    from dataclasses import replace

    if data.image is None:
        return data
    rows = [r for r in data.persons if r.get("box2d_xyxy") is not None]
    boxes = np.asarray([r["box2d_xyxy"] for r in rows], np.float64).reshape(-1, 4)
    colors = instance_colors([int(r["track_id"]) for r in rows])
    return replace(data, image=S.draw_boxes_2d(data.image, boxes, colors))
