"""The QA pass of `mobileocc view --qa`: which frames to check, what a frame's persons are, and
saving verdicts (the viewer's buttons and the HTTP API call the same :class:`QASession`).

The sample: per condition (crowded / uncrowded / night, tasks.view.qa.frame_condition) up to
``per_condition`` frames spread evenly over the dataset's frames of that condition (the paper's
pass: 300 frames over the three conditions, 100 each). Verdicts go to ``OUT/qa/
detection_qa.parquet`` (storage/qa.py) one frame at a time, so a pass stopped halfway resumes at
its first unchecked frame.

HTTP API (JSON; errors are status 400 with ``{"error": message}``; served on localhost by
:func:`serve_api`):

- ``GET  /api/state``: ``{"sequence", "frame", "num_frames", "raw_frame", "viewer_url"}``
- ``POST /api/frame`` ``{"sequence", "frame"}``: show that frame in the viewer
- ``GET  /api/qa``: ``{"sample": [{"sequence", "frame", "raw_frame", "condition", "checked"}],
  "checked", "total", "next"}`` (next: the first unchecked position, null when done)
- ``GET  /api/qa/frame?sequence=S&frame=F``: ``{"persons": [{"track_id", "box2d_xyxy"}],
  "condition", "image_size", "marks"}`` (marks: the saved verdict, [] when none)
- ``POST /api/qa/frame`` ``{"sequence", "frame", "marks": [{"kind", "track_id", "u", "v"}]}``:
  save the frame's verdict (every labelled person marked T or W, misses with a click)
- ``GET  /api/qa/table``: the saved QA table as a list of rows
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlparse

from storage.qa import checked_frames, read_qa, save_frame
from storage.viewer_data import ViewerInputError, ViewerSource
from tasks.view.qa import Mark, QAMarkError, check_marks, frame_condition, sample_frames

#: a frame with at least this many labelled persons is "crowded" when the sequence's metadata
#: says nothing (the simulator's crowded scenes hold 6-12 people, uncrowded ones 1-4)
CROWDED_MIN_PERSONS = 5
#: the paper's pass: 300 frames, 100 per condition
FRAMES_PER_CONDITION = 100


class QASession:
    """The QA pass over the dataset of ``source``; ``clock`` gives the save time (ns)."""

    def __init__(
        self,
        source: ViewerSource,
        per_condition: int = FRAMES_PER_CONDITION,
        crowded_min: int = CROWDED_MIN_PERSONS,
        clock: Callable[[], int] = time.time_ns,
    ):
        self.source, self.clock = source, clock
        self._lock = threading.Lock()
        read_qa(source.out)  # a table of another version is refused before the pass starts
        self.frames: list[dict] = []
        self._persons: dict[str, dict[int, list[dict]]] = {}
        for seq in source.sequences:
            info = source.info(seq)
            crowd = source.metadata(seq).get("crowd")
            persons = self._persons[seq] = source.persons(seq)
            for row in info.frames:
                k = int(row["frame"])
                self.frames.append(
                    {
                        "sequence": seq,
                        "frame": k,
                        "raw_frame": int(row["raw_frame"]),
                        "condition": frame_condition(
                            bool(row.get("is_night")), crowd, len(persons.get(k, [])), crowded_min
                        ),
                    }
                )
        self.sample = [
            self.frames[i]
            for i in sample_frames([f["condition"] for f in self.frames], per_condition)
        ]

    def _frame(self, sequence: str, frame: int) -> dict:
        self.source.check_frame(self.source.check_sequence(sequence), frame)
        return next(f for f in self.frames if f["sequence"] == sequence and f["frame"] == frame)

    def progress(self) -> dict:
        done = checked_frames(read_qa(self.source.out))
        items = [{**f, "checked": (f["sequence"], f["frame"]) in done} for f in self.sample]
        nxt = next((i for i, f in enumerate(items) if not f["checked"]), None)
        return {
            "sample": items,
            "checked": sum(f["checked"] for f in items),
            "total": len(items),
            "next": nxt,
        }

    def persons(self, sequence: str, frame: int) -> list[dict]:
        """The labelled persons of a frame: track id and 2D box (cam0 px)."""
        self._frame(sequence, frame)
        return [
            {"track_id": int(r["track_id"]), "box2d_xyxy": r["box2d_xyxy"]}
            for r in self._persons[sequence].get(int(frame), [])
        ]

    def frame_info(self, sequence: str, frame: int) -> dict:
        f = self._frame(sequence, frame)
        info = self.source.info(sequence)
        table = read_qa(self.source.out)
        rows = [
            r
            for r in table.to_pylist()
            if r["sequence"] == sequence and r["frame"] == frame and r["kind"] is not None
        ]
        return {
            **f,
            "persons": self.persons(sequence, frame),
            "image_size": [info.width, info.height],
            "marks": [{k: r[k] for k in ("kind", "track_id", "u", "v")} for r in rows],
        }

    def save(self, sequence: str, frame: int, marks: list[dict]) -> dict:
        """Check and save a frame's verdict (QAMarkError / ViewerInputError on bad input,
        nothing written)."""
        if not isinstance(marks, list):
            raise QAMarkError(f"sequence {sequence} frame {frame}: marks must be a list")
        f = self._frame(sequence, int(frame))
        parsed = []
        for m in marks:
            if not isinstance(m, dict):
                raise QAMarkError(f"sequence {sequence} frame {frame}: a mark must be an object")
            unknown = set(m) - {"kind", "track_id", "u", "v"}
            if unknown:
                raise QAMarkError(
                    f"sequence {sequence} frame {frame}: unknown mark field(s) {sorted(unknown)}"
                )
            try:
                parsed.append(
                    Mark(
                        str(m.get("kind")),
                        None if m.get("track_id") is None else int(m["track_id"]),
                        None if m.get("u") is None else float(m["u"]),
                        None if m.get("v") is None else float(m["v"]),
                    )
                )
            except (TypeError, ValueError) as exc:
                raise QAMarkError(
                    f"sequence {sequence} frame {frame}: bad mark {m}: {exc}"
                ) from None
        persons = self.persons(sequence, int(frame))
        info = self.source.info(sequence)
        check_marks(
            f"sequence {sequence} frame {frame}",
            [p["track_id"] for p in persons],
            parsed,
            (info.width, info.height),
        )
        with self._lock:
            save_frame(
                self.source.out,
                sequence,
                int(frame),
                f["raw_frame"],
                f["condition"],
                parsed,
                {p["track_id"]: p["box2d_xyxy"] for p in persons if p["box2d_xyxy"] is not None},
                self.source.version(sequence),
                self.clock(),
            )
        prog = self.progress()
        return {"saved": True, "checked": prog["checked"], "total": prog["total"]}


class _Handler(BaseHTTPRequestHandler):
    app = None  # the ViewerApp (set by serve_api)

    def log_message(self, *args) -> None:  # no access log on the console
        pass

    def _send(self, status: int, body) -> None:
        data = json.dumps(body).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Access-Control-Allow-Origin", "*")
        self.end_headers()
        self.wfile.write(data)

    def _body(self) -> dict:
        n = int(self.headers.get("Content-Length") or 0)
        try:
            body = json.loads(self.rfile.read(n) or b"{}")
        except ValueError as exc:
            raise QAMarkError(f"request body is not JSON: {exc}") from None
        if not isinstance(body, dict):
            raise QAMarkError("request body must be a JSON object")
        return body

    def _qa(self) -> QASession:
        if self.app.qa is None:
            raise QAMarkError("the viewer was started without --qa")
        return self.app.qa

    def _route(self, method: str):
        url = urlparse(self.path)
        query = {k: v[-1] for k, v in parse_qs(url.query).items()}
        if method == "GET" and url.path == "/api/state":
            return self.app.state()
        if method == "POST" and url.path == "/api/frame":
            body = self._body()
            return self.app.show(str(body.get("sequence")), int(body.get("frame")))
        if method == "GET" and url.path == "/api/qa":
            return self._qa().progress()
        if method == "GET" and url.path == "/api/qa/frame":
            return self._qa().frame_info(query.get("sequence", ""), int(query.get("frame", -1)))
        if method == "POST" and url.path == "/api/qa/frame":
            body = self._body()
            return self._qa().save(
                str(body.get("sequence")), int(body.get("frame")), body.get("marks")
            )
        if method == "GET" and url.path == "/api/qa/table":
            return read_qa(self.app.source.out).to_pylist()
        return None

    def _handle(self, method: str) -> None:
        try:
            result = self._route(method)
        except (QAMarkError, ViewerInputError, ValueError, TypeError) as exc:
            self._send(400, {"error": str(exc)})
            return
        if result is None:
            self._send(404, {"error": f"no such endpoint: {method} {self.path}"})
        else:
            self._send(200, result)

    def do_GET(self) -> None:
        self._handle("GET")

    def do_POST(self) -> None:
        self._handle("POST")


def serve_api(app, host: str, port: int) -> ThreadingHTTPServer:
    """Start the JSON API of ``app`` on (host, port), the next free port when it is taken; runs in
    a daemon thread; ``.server_address[1]`` is the port."""
    handler = type("Handler", (_Handler,), {"app": app})
    for p in range(port, port + 100):
        try:
            httpd = ThreadingHTTPServer((host, p), handler)
            break
        except OSError:
            continue
    else:
        raise OSError(f"no free port for the API in {port}..{port + 99} on {host}")
    httpd.daemon_threads = True
    threading.Thread(target=httpd.serve_forever, name="mobileocc-view-api", daemon=True).start()
    return httpd


def manual_qa_section(out, current_versions: dict[str, str] | None = None):
    """The manual QA table of the dataset at ``out`` for the evaluation report: ({condition:
    DetectionCounts.as_dict(), ..., "all": ...} or None when no pass was saved, a note or None).
    current_versions: sequence -> its published occupancy version; verdicts on another version
    (the dataset was rebuilt since) are counted and said in the note."""
    from storage.qa import QATableError
    from tasks.view.qa import counts_by_condition

    try:
        table = read_qa(out)
    except QATableError as exc:
        return None, f"manual QA table not read: {exc}"
    if table.num_rows == 0:
        return None, None
    rows = table.to_pylist()
    counts = counts_by_condition([r["condition"] for r in rows], [r["kind"] for r in rows])
    frames = {(r["sequence"], r["frame"]) for r in rows}
    note = f"manual QA: {len(frames)} frame(s) checked, {table.num_rows} row(s) in {out}/qa/"
    stale = sorted(
        {
            r["sequence"]
            for r in rows
            if current_versions is not None
            and r["sequence"] in current_versions
            and r["occupancy_version"] != current_versions[r["sequence"]]
        }
    )
    if stale:
        note += f"; sequence(s) {', '.join(stale)} were rebuilt after their frames were checked"
    return {c: v.as_dict() for c, v in counts.items()}, note
