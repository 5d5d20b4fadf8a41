"""Config-level files are checked with the config; reads of model files and npz are bounded.

Issue 41, item 3: a malicious or absurd ``fit.body_model_path`` / ``fit.pose_prior_path`` is the
config's error (exit 2, one line, before any unit: nothing published is withdrawn), never a
per-sequence failure; the no-pickle loader refuses a pickle nesting 200,000 deep, a declared
length past the file's end, ``bytearray(n)``, a device such as /dev/zero, before memory is spent;
an ``.npz`` member declaring more than the bound is refused before it is read."""

from __future__ import annotations

import io
import os
import pickle
import zipfile

import numpy as np
import pytest

from flows import cli
from storage.body_model_files import (
    BodyFileError,
    UnsafePickleError,
    load_body_model,
    load_pose_prior,
)
from storage.npzio import check_npz_members, load_npz, save_npz_deterministic


def _s(key: bytes) -> bytes:
    return b"X" + len(key).to_bytes(4, "little") + key


DEEP = 200_000
#: crafted pickles (protocol 2 opcodes written out: pickle.dumps itself crashes on the deep one)
PICKLES = {
    "nested 200,000 deep": (
        b"\x80\x02}" + _s(b"means") + b"]" * DEEP + b"a" * (DEEP - 1) + b"s" + _s(b"covars")
        + b"]s" + _s(b"weights") + b"]s.",
        "nests deeper",
    ),
    "declared length past the end": (b"\x80\x02}X\xff\xff\xff\x7fmeans", "not a readable pickle"),
    "bytearray(2 GB)": (
        b"\x80\x02c__builtin__\nbytearray\nJ\x00\x00\x00\x7f\x85R.",
        "bytearray",
    ),
    "os.system": (b"\x80\x02cos\nsystem\nX\x04\x00\x00\x00true\x85R.", "not allowed"),
    "truncated": (pickle.dumps({"means": [1.0] * 10}, protocol=2)[:-9], "not a readable pickle"),
}  # fmt: skip


@pytest.mark.parametrize("kind", PICKLES)
def test_a_crafted_prior_pickle_is_refused_before_memory_is_spent(kind, tmp_path):
    data, says = PICKLES[kind]
    path = tmp_path / "gmm_08.pkl"
    path.write_bytes(data)
    with pytest.raises((BodyFileError, UnsafePickleError), match=says) as err:
        load_pose_prior(path)
    assert str(path) in str(err.value)


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="needs /dev/zero")
@pytest.mark.parametrize("name", ["gmm_08.pkl", "model.npz"])
def test_a_model_file_that_is_a_device_is_refused(name, tmp_path):
    path = tmp_path / name
    path.symlink_to("/dev/zero")
    load = load_pose_prior if name.endswith(".pkl") else load_body_model
    with pytest.raises(BodyFileError, match="character device"):
        load(path)


def _npz_declaring(path, shape, holds: int = 64):
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f8", "fortran_order": False, "shape": shape}
    )
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("x.npy", header.getvalue() + b"\0" * holds)
    return path


def test_an_npz_member_declaring_more_than_it_holds_is_refused(tmp_path):
    path = _npz_declaring(tmp_path / "gt.npz", (750_000_000,))  # 6 GB declared
    with pytest.raises(ValueError, match="6000000000 bytes"):
        load_npz(path)
    with pytest.raises(BodyFileError, match="6000000000 bytes"):
        load_body_model(path)
    good = save_npz_deterministic(tmp_path / "ok.npz", x=np.arange(6.0).reshape(2, 3))
    assert load_npz(good)["x"].shape == (2, 3)
    with open(good, "rb") as fh, pytest.raises(ValueError, match="more than the 10"):
        check_npz_members(fh, max_member_bytes=10)


@pytest.mark.parametrize(
    "key, content, says",
    [
        ("fit.pose_prior_path", PICKLES["os.system"][0], "not allowed"),
        ("fit.pose_prior_path", PICKLES["nested 200,000 deep"][0], "nests deeper"),
        ("fit.body_model_path", b"PK\x03\x04 garbage", "cannot read body model npz"),
    ],
)
def test_a_bad_config_level_file_is_exit_2_before_any_work(key, content, says, tmp_path, capsys):
    data, out = tmp_path / "data", tmp_path / "out"
    data.mkdir()
    bad = tmp_path / ("model.npz" if key == "fit.body_model_path" else "gmm_08.pkl")
    bad.write_bytes(content)
    code = cli.main(
        ["rebuild", "--data", str(data), "--out", str(out), "--quiet", "--set", f"{key}={bad}"]
    )
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and key in err and says in err and str(bad) in err
    assert "Traceback" not in err
    assert not (out / "manifest.json").exists()  # nothing ran, nothing was withdrawn
