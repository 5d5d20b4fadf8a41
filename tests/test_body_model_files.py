"""Body model / pose prior files: npz round-trip, official-layout pkl, restricted unpickler."""

from __future__ import annotations

import pickle
import sys
import types

import numpy as np
import pytest
import scipy.sparse

from storage.body_model_files import (
    BodyFileError,
    UnsafePickleError,
    load_body_model,
    load_pose_prior,
    save_body_model_npz,
    save_pose_prior_pkl,
)
from tasks.conventions import SMPL_PARENTS


def _tiny_params(rng: np.random.Generator, V: int = 30) -> dict[str, np.ndarray]:
    kt = np.zeros((2, 24), dtype=np.int64)
    kt[0] = [2**32 - 1, *SMPL_PARENTS[1:]]  # the official files' root parent
    kt[1] = np.arange(24)
    w = rng.random((V, 24))
    reg = rng.random((24, V)) * (rng.random((24, V)) < 0.2)
    reg[:, 0] += 1e-3
    return {
        "v_template": rng.normal(size=(V, 3)),
        "f": rng.integers(0, V, size=(40, 3)).astype(np.int64),
        "shapedirs": rng.normal(size=(V, 3, 10)),
        "posedirs": rng.normal(size=(V, 3, 207)) * 1e-3,
        "weights": w / w.sum(1, keepdims=True),
        "kintree_table": kt,
        "J_regressor": reg / reg.sum(1, keepdims=True),
    }


def test_npz_round_trip(tmp_path):
    params = _tiny_params(np.random.default_rng(0))
    params["coco_vertex_ids"] = np.array([1, 2, 3, 4, 5], dtype=np.int64)
    path = tmp_path / "model" / "body.npz"
    save_body_model_npz(path, params)
    loaded = load_body_model(path)
    assert sorted(loaded) == sorted(params)
    for k in params:
        np.testing.assert_array_equal(loaded[k], params[k])
        assert loaded[k].dtype == params[k].dtype


def test_npz_missing_key_is_a_clear_error(tmp_path):
    params = _tiny_params(np.random.default_rng(0))
    path = tmp_path / "bad.npz"
    np.savez(path, **{k: v for k, v in params.items() if k != "posedirs"})
    with pytest.raises(BodyFileError, match="posedirs"):
        load_body_model(path)


def _install_fake_chumpy():
    chumpy = types.ModuleType("chumpy")
    ch = types.ModuleType("chumpy.ch")

    class Ch:
        def __init__(self, x):
            self.x = x

        def __getstate__(self):
            return {"x": self.x, "label": "shapedirs", "_dirty_vars": {"x"}}

    Ch.__module__ = "chumpy.ch"
    Ch.__qualname__ = "Ch"
    ch.Ch = Ch
    chumpy.ch = ch
    sys.modules["chumpy"] = chumpy
    sys.modules["chumpy.ch"] = ch
    return Ch


def test_official_layout_pkl(tmp_path):
    params = _tiny_params(np.random.default_rng(1))
    Ch = _install_fake_chumpy()
    try:
        official = dict(params)
        official["J_regressor"] = scipy.sparse.csc_matrix(params["J_regressor"])
        official["shapedirs"] = Ch(params["shapedirs"])
        official["bs_style"] = "lbs"
        official["bs_type"] = "lrotmin"
        path = tmp_path / "SMPL_NEUTRAL.pkl"
        with open(path, "wb") as fh:
            pickle.dump(official, fh, protocol=2)  # what a Python 2 pickle can hold
    finally:
        del sys.modules["chumpy"], sys.modules["chumpy.ch"]
    assert b"chumpy.ch" in path.read_bytes()
    loaded = load_body_model(path)
    for k in params:
        assert isinstance(loaded[k], np.ndarray), k
        np.testing.assert_array_equal(loaded[k], params[k])
    assert "bs_style" not in loaded
    assert "chumpy" not in sys.modules


class _System:
    def __reduce__(self):
        import os

        return (os.system, ("touch PWNED_BY_PICKLE",))


class _Eval:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (eval, (f"open({str(self.marker)!r}, 'w').write('x')",))


@pytest.mark.parametrize("kind", ["system", "eval"])
def test_malicious_pickle_is_refused(tmp_path, monkeypatch, kind):
    monkeypatch.chdir(tmp_path)
    marker = tmp_path / "PWNED_BY_PICKLE"
    payload = _System() if kind == "system" else _Eval(marker)
    for loader, name in ((load_body_model, "model.pkl"), (load_pose_prior, "gmm_08.pkl")):
        path = tmp_path / name
        path.write_bytes(pickle.dumps({"v_template": payload, "means": payload}, protocol=2))
        with pytest.raises(UnsafePickleError, match="not allowed"):
            loader(path)
        assert not marker.exists()


def test_pose_prior_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    A = rng.normal(size=(8, 69, 69))
    prior = {
        "means": rng.normal(size=(8, 69)),
        "covars": A @ A.transpose(0, 2, 1) * 1e-4 + np.eye(69) * 1e-5,
        "weights": np.full(8, 1 / 8),
    }
    path = tmp_path / "gmm_08.pkl"
    save_pose_prior_pkl(path, prior)
    loaded = load_pose_prior(path)
    for k in prior:
        np.testing.assert_array_equal(loaded[k], prior[k])
        assert loaded[k].dtype == np.float64
    with open(path, "rb") as fh:  # plain pickle sees the documented layout
        assert sorted(pickle.load(fh)) == ["covars", "means", "weights"]
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(
        pickle.dumps({"means": prior["means"], "weights": prior["weights"]}, protocol=2)
    )
    with pytest.raises(BodyFileError, match="covars"):
        load_pose_prior(bad)


def test_generated_model_loads_into_body_model(tmp_path):
    import torch

    from tasks.body.model import BodyModel
    from tasks.body.procedural import default_body_params

    params = default_body_params()
    path = tmp_path / "proc.npz"
    save_body_model_npz(path, params)
    model = BodyModel(load_body_model(path))
    z = torch.zeros(1, 3)
    out = model(torch.zeros(1, 10), z, torch.zeros(1, 69), z)
    np.testing.assert_allclose(out.vertices[0].numpy(), params["v_template"], atol=1e-5)


def test_plain_numpy_smpl_pickle_of_the_procedural_model(tmp_path):
    """The procedural stand-in as an SMPL pickle: official keys, plain numpy inside (issue 19)."""
    from storage.body_model_files import save_body_model_pkl
    from storage.plain_pickle import pickle_globals
    from tasks.body.procedural import default_body_params
    from tasks.conventions import SMPL_MODEL_KEYS

    params = default_body_params()
    path = tmp_path / "procedural_smpl.pkl"
    save_body_model_pkl(path, params)
    assert pickle_globals(path.read_bytes()) == {("numpy", "ndarray"), ("builtins", "bytearray")}
    with open(path, "rb") as f:  # how smplx reads it
        raw = pickle.load(f, encoding="latin1")
    assert set(SMPL_MODEL_KEYS) <= set(raw) and raw["v_template"].shape == (6470, 3)
    loaded = load_body_model(path)  # and our restricted reader
    for k in params:
        np.testing.assert_array_equal(loaded[k], params[k])
    save_body_model_pkl(tmp_path / "again.pkl", params)
    assert (tmp_path / "again.pkl").read_bytes() == path.read_bytes()


def test_smplx_poses_our_bodies_like_our_model(tmp_path):
    """Document-as-test: a fitted body's (betas, global_orient, body_pose, transl) posed with
    smplx.SMPL on the procedural pickle gives our model's vertices and joints."""
    smplx = pytest.importorskip("smplx")
    import torch

    from storage.body_model_files import save_body_model_pkl, save_smplx_model, smplx_vertex_ids
    from tasks.body.model import BodyModel
    from tasks.body.procedural import default_body_params

    params = default_body_params()
    path = save_smplx_model(tmp_path / "body_models", params)
    kwargs = dict(
        vertex_ids=smplx_vertex_ids(params),
        use_hands=False,
        use_feet_keypoints=False,
        dtype=torch.float64,
    )
    # smplx.create reads the model type from the file name (issue 32: "procedural_smpl.pkl"
    # gave "Unknown model type procedural"); the file and the folder layout both load
    assert path.name == "SMPL_PROCEDURAL.pkl"
    assert isinstance(smplx.create(str(tmp_path / "body_models"), gender="procedural"), smplx.SMPL)
    model = smplx.create(str(path), **kwargs)
    save_body_model_pkl(tmp_path / "procedural_smpl.pkl", params)
    with pytest.raises(ValueError, match="Unknown model type procedural"):
        smplx.create(str(tmp_path / "procedural_smpl.pkl"))
    rng = np.random.default_rng(0)
    betas, go, pose, transl = (
        torch.as_tensor(rng.normal(0, s, (2, n)))
        for s, n in ((0.8, 10), (0.5, 3), (0.2, 69), (1.0, 3))
    )
    out = model(betas=betas, global_orient=go, body_pose=pose, transl=transl)
    ours = BodyModel(params).double()(betas, go, pose, transl)
    assert out.vertices.shape == (2, 6470, 3)
    np.testing.assert_allclose(out.vertices.detach().numpy(), ours.vertices.numpy(), atol=1e-9)
    np.testing.assert_allclose(out.joints[:, :24].detach().numpy(), ours.joints.numpy(), atol=1e-9)
    np.testing.assert_array_equal(
        out.joints[:, 24:29].detach().numpy(),
        out.vertices[:, params["coco_vertex_ids"][[0, 2, 1, 4, 3]]].detach().numpy(),
    )
