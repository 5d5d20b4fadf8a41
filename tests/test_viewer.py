"""`mobileocc view` end to end on a small simulated dataset: the self-contained page in headless
Chromium (class colours on screen, no request leaves the machine), the served viewer stepping
frames in the browser, a QA pass through the HTTP API into `evaluate`'s report, and bad input.

The Chromium tests skip, saying why, where no Chromium is installed (`make test` installs
Debian's `chromium` where it can: root or passwordless sudo).
"""

from __future__ import annotations

import json
import socket
import urllib.error
import urllib.request

import numpy as np
import pytest

from flows.bench.chromium import Chromium, find_chromium
from flows.bench.viewer import class_pixel_counts, time_to_show
from flows.commands.view import export_html, serving_lines, start
from flows.viewer.draw import Layers
from storage.qa import QATableError, qa_path
from storage.viewer_data import ViewerInputError, ViewerSource

# one worker builds the module's dataset once; end to end with a browser: slow
pytestmark = [pytest.mark.xdist_group("viewer"), pytest.mark.slow]

needs_chromium = pytest.mark.skipif(
    find_chromium() is None,
    reason="no working chromium on PATH: the viewer's browser tests need headless Chromium "
    "(`make test` apt-installs Debian's `chromium` where it can)",
)
#: generous: software WebGL on a loaded 2-core machine
SHOW_TIMEOUT_S = 300


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """Two sequences of 5 frames each (10 Hz, no striding): 0 crowded by day, 1 at night; every
    stage of the default config (fitted bodies: meshes and boxes in the instances table)."""
    from flows.bench.common import make_config, run_stages
    from flows.commands.simulate import simulate
    from flows.pipeline.dag import STAGES

    root = tmp_path_factory.mktemp("viewer")
    data, out = root / "data", root / "out"
    simulate(data, sequences=1, frames=5, seed=5, pedestrians=4, crowd="crowded", progress=False,
             fast=True)  # fmt: skip
    simulate(data, sequences=1, frames=5, seed=6, pedestrians=3, crowd="uncrowded", night=True,
             progress=False, first_id=1, fast=True)  # fmt: skip
    run_stages(make_config(data, out, {"dataset.rate_hz": 10.0}), tuple(STAGES))
    return data, out


def _get(url: str, body: dict | None = None):
    req = urllib.request.Request(
        url,
        data=None if body is None else json.dumps(body).encode(),
        headers={"Content-Type": "application/json"},
        method="GET" if body is None else "POST",
    )
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def _shown(counts: dict, min_pixels: int = 50) -> bool:
    return all(counts[c] >= min_pixels for c in ("road", "terrain", "pedestrian"))


def test_frame_data_and_bad_input(built, tmp_path):
    data, out = built
    src = ViewerSource(out)
    assert src.sequences == ("0", "1") and src.num_frames("0") == 5
    f = src.frame("0", 2)
    assert f.gt is not None and f.image is not None and f.points_lidar is not None
    assert f.persons and all(p["betas"] is not None for p in f.persons), "bodies to draw"
    assert (f.semantics == 5).any() and (f.semantics == 4).any()  # terrain and road labelled
    with pytest.raises(ViewerInputError, match="not a mobileocc dataset"):
        ViewerSource(data)  # the raw data root, not the output
    with pytest.raises(ViewerInputError, match="no such dataset folder"):
        ViewerSource(tmp_path / "nothing")
    with pytest.raises(ViewerInputError, match=r"no sequence '7'; it has \['0', '1'\]"):
        src.frame("7", 0)
    with pytest.raises(ViewerInputError, match=r"no frame 5; its frames are 0..4"):
        src.frame("1", 5)
    # the CLI: one line, exit 2, no page written
    from flows.cli import main

    page = tmp_path / "p.html"
    assert main(["view", "--dataset", str(out), "--sequence", "1", "--frame", "9",
                 "--html", str(page)]) == 2  # fmt: skip
    assert not page.exists()


@needs_chromium
def test_html_page_shows_the_classes_and_fetches_nothing(built, tmp_path):
    _, out = built
    page = tmp_path / "frame.html"
    res = export_html(ViewerSource(out), "0", 1, 3, page, Layers())
    assert res["frames"] == [1, 2, 3] and page.stat().st_size == res["bytes"] > 500_000
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp")]
    with Chromium(1280, 800) as browser:
        # the page plays its 3 frames in a loop: it never stands still
        shown = time_to_show(browser, page.as_uri(), SHOW_TIMEOUT_S, still=False)
        counts = shown["counts"]
        assert _shown(counts), f"class colours on screen: {counts}"
        # its timeline spans the 3 frames, 0.2 s apart (5 Hz)
        assert browser.evaluate(
            "[...document.querySelectorAll('[role=slider]')].map(e => e.getAttribute('aria-valuemax'))"
        ) == ["0.4"]
        # every request the page made stayed inside the file (the page itself, data: / blob:
        # URLs of its inline assets); the resolver maps every other host to nothing anyway
        schemes = {u.split(":", 1)[0] for u in browser.requests}
        assert schemes <= {"file", "data", "blob"}, schemes
    # and the screenshot is not a lucky palette: a blank page has none of these colours
    assert not _shown(class_pixel_counts(np.full((100, 100, 3), 255, np.uint8)), 1)


@needs_chromium
def test_served_viewer_answers_and_steps_frames_in_the_browser(built):
    _, out = built
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    port = taken.getsockname()[1]
    app, api = start(out, "0", 1, port=port)
    try:
        assert app.port != port  # the port was in use: the next free one, and said
        assert serving_lines(app, api, port)[0] == (
            f"port {port} is in use: serving on port {app.port} instead"
        )
        with urllib.request.urlopen(app.url, timeout=60) as r:
            assert r.status == 200 and b"Viser" in r.read()
        base = f"http://127.0.0.1:{api.server_address[1]}"
        assert _get(base + "/api/state")[1]["frame"] == 1
        with Chromium(1280, 800) as browser:
            shown = time_to_show(browser, app.url, SHOW_TIMEOUT_S)
            assert _shown(shown["counts"]), shown["counts"]
            before = shown["image"]
            for want in (2, 3):  # two steps, by the "next frame" button of the page
                clicked = browser.evaluate(
                    "(() => { const b = [...document.querySelectorAll('button')]"
                    ".find(e => e.textContent.trim() === 'next frame');"
                    " if (!b) return false; b.click(); return true; })()"
                )
                assert clicked, "the page has a 'next frame' button"
                browser.wait_for(lambda w=want: _get(base + "/api/state")[1]["frame"] == w, 120)
            after = browser.wait_for(
                lambda: (lambda img: img if not np.array_equal(img, before) else None)(
                    browser.screenshot()
                ),
                SHOW_TIMEOUT_S,
            )
            assert _shown(class_pixel_counts(after))
        # the API moves the viewer too, and refuses a frame that does not exist
        assert _get(base + "/api/frame", {"sequence": "1", "frame": 4})[1]["raw_frame"] == 4
        status, body = _get(base + "/api/frame", {"sequence": "1", "frame": 5})
        assert status == 400 and "no frame 5" in body["error"]
    finally:
        api.shutdown()
        app.close()
        taken.close()


def test_qa_pass_through_the_api_appears_in_evaluate(built, tmp_path, capsys):
    from flows.cli import main

    data, out = built
    app, api = start(out, qa=True, qa_frames=5, port=0)
    base = f"http://127.0.0.1:{api.server_address[1]}"
    posted = []
    try:
        status, prog = _get(base + "/api/qa")
        assert status == 200 and prog["total"] == 10 and prog["next"] == 0
        assert {f["condition"] for f in prog["sample"]} == {"crowded", "night"}
        # an incomplete verdict is refused and nothing is written
        first = prog["sample"][0]
        info = _get(base + f"/api/qa/frame?sequence={first['sequence']}&frame={first['frame']}")[1]
        assert info["persons"], "the crowded frame has labelled persons"
        status, body = _get(base + "/api/qa/frame", {**first, "marks": []})
        assert status == 400 and "not marked T or W" in body["error"]
        assert not qa_path(out).exists()
        for i, f in enumerate(prog["sample"]):
            q = f"?sequence={f['sequence']}&frame={f['frame']}"
            persons = _get(base + "/api/qa/frame" + q)[1]["persons"]
            marks = [
                {"kind": "W" if (i + k) % 4 == 3 else "T", "track_id": p["track_id"]}
                for k, p in enumerate(persons)
            ]
            if i % 3 == 0:
                marks.append({"kind": "M_vis" if i % 2 else "M_occ", "u": 100.0 + i, "v": 200.0})
            status, body = _get(
                base + "/api/qa/frame",
                {"sequence": f["sequence"], "frame": f["frame"], "marks": marks},
            )
            assert status == 200 and body["checked"] == i + 1, body
            posted += [(f["condition"], m["kind"]) for m in marks]
            if i == 3:  # a pass stopped here resumes at the fifth frame
                from flows.viewer.qa import QASession

                assert QASession(ViewerSource(out), 5).progress()["next"] == 4
        assert _get(base + "/api/qa")[1]["next"] is None
        table = _get(base + "/api/qa/table")[1]
        assert sorted((r["condition"], r["kind"]) for r in table if r["kind"]) == sorted(posted)
    finally:
        api.shutdown()
        app.close()
    assert main(["evaluate", "--dataset", str(out), "--gt", str(data), "--report",
                 str(tmp_path / "report")]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "detection robustness (automatic)" in printed
    assert "detection robustness (manual QA)" in printed
    res = json.loads((tmp_path / "report" / "results.json").read_text())
    manual = res["detection_manual_qa"]
    for cond in ("crowded", "night"):
        for kind in ("T", "W", "M_vis", "M_occ"):
            assert manual[cond][kind] == posted.count((cond, kind)), (cond, kind)
    md = (tmp_path / "report" / "report.md").read_text()
    auto_at, manual_at = md.index("## Detection robustness\n"), md.index("(manual QA)")
    assert auto_at < manual_at  # beside the automatic table, right after it
    assert f"| all | {manual['all']['T']} |" in md[manual_at:]

    # the panel's way: the T / W buttons and a click on the camera image, for the first frame
    from storage.qa import read_qa

    app, api = start(out, qa=True, qa_frames=5, port=0)
    try:
        f = app.qa.sample[0]
        app.show(f["sequence"], f["frame"])  # shows its saved verdict, which the reviewer redoes
        app.clear_misses()
        for p in app.qa.persons(f["sequence"], f["frame"]):
            app.mark(p["track_id"], "T")
        d, cam = app.data, app.drawer.camera
        u, v = 300.0, 200.0
        p_cam = np.array([(u - d.K[0, 2]) / d.K[0, 0], (v - d.K[1, 2]) / d.K[1, 1], 1.0])
        p = d.T_base_from_cam0[:3, :3] @ (p_cam * cam.depth_m) + d.T_base_from_cam0[:3, 3]
        eye = p + np.array([-2.0, 1.0, 1.5])  # the reviewer's view, behind and above
        assert app.click_image(eye, p - eye) == pytest.approx((u, v), abs=1e-6)
        assert app.save_verdict() is None
    finally:
        api.shutdown()
        app.close()
    rows = [r for r in read_qa(out).to_pylist() if (r["sequence"], r["frame"]) == (
        f["sequence"], f["frame"])]  # fmt: skip
    assert sorted(r["kind"] for r in rows) == sorted(["T"] * len(info["persons"]) + ["M_vis"])
    miss = next(r for r in rows if r["kind"] == "M_vis")
    assert (miss["u"], miss["v"]) == pytest.approx((u, v), abs=1e-3)


def test_qa_table_of_an_older_version_stops_the_viewer_before_anything_is_written(built, tmp_path):
    import shutil

    import pyarrow as pa
    import pyarrow.parquet as pq

    _, out = built
    copy = tmp_path / "out"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("qa"))
    path = qa_path(copy)
    path.parent.mkdir()
    pq.write_table(
        pa.table({"frame": [0]}).replace_schema_metadata(
            {"mobileocc.schema": "detection_qa", "mobileocc.schema_version": "0"}
        ),
        path,
    )
    before = path.read_bytes()
    with pytest.raises(QATableError, match="schema version 0, written by an older mobileocc"):
        start(copy, qa=True, port=0)
    assert path.read_bytes() == before
