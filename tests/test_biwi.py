from __future__ import annotations

import numpy as np
import pytest
import trimesh

from talkmesh.datasets.biwi import normalize_frames, prepare_biwi, surface_area
from talkmesh.datasets.reader import open_dataset
from talkmesh.errors import TalkmeshError


def test_prepare_biwi_gives_unit_area_centred_rotated_frames(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2)
    raw = tmp_path / "raw"
    (raw / "vertices").mkdir(parents=True)
    sphere.export(raw / "BIWI.ply")
    frames = np.stack([sphere.vertices * (3 + k) + [10, 20, 30 + k] for k in range(4)])
    np.save(raw / "vertices" / "F2_e01.npy", frames.reshape(4, -1))
    out = tmp_path / "out"
    assert prepare_biwi(raw, out, progress=False) == 1
    done = np.load(out / "vertices_npy" / "F2_e01.npy").reshape(4, -1, 3)
    np.testing.assert_allclose(surface_area(done, sphere.faces), 1.0, rtol=1e-5)
    np.testing.assert_allclose(done.mean(axis=1), 0.0, atol=1e-6)
    # rotation by pi about x: y and z flip sign (the shapes are the same sphere, scaled)
    top = np.argmax(sphere.vertices[:, 1])
    assert (done[:, top, 1] < 0).all()
    assert (out / "templates.pkl").is_file() and (out / "BIWI.ply").is_file()


def test_normalize_rejects_degenerate_frames():
    with pytest.raises(TalkmeshError, match="zero surface area"):
        normalize_frames(np.zeros((1, 3, 3)), np.array([[0, 1, 2]]))


def test_prepare_biwi_needs_faces(tmp_path):
    (tmp_path / "vertices").mkdir()
    np.save(tmp_path / "vertices" / "F2_e01.npy", np.zeros((1, 9)))
    with pytest.raises(TalkmeshError, match="no .ply or .obj"):
        prepare_biwi(tmp_path, tmp_path / "out", progress=False)
    assert open_dataset  # the output is read by the biwi reader (see test_datasets)
