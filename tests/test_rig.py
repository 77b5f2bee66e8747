"""`talkmesh rig`: the bundled blendshapes carried onto a head in other units, axes and meshing."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from talkmesh.cli import main
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import load_head
from talkmesh.face.rig import rig_head
from talkmesh.output.avatar import animate_avatar, read_glb


@pytest.fixture(scope="module")
def head():
    return load_head()


def test_units_and_up_axis_are_detected_and_kept(head):
    """The head in centimetres, Z-up, shifted: the offsets come back scaled and rotated."""
    r = trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0])[:3, :3]
    rig = rig_head(100 * head.template @ r.T + [3, -2, 10], head.faces, head)
    assert rig.units == "cm" and rig.up_axis == "-z"
    truth = 100 * head.blendshapes @ r.T
    error_mm = 10 * np.linalg.norm(rig.blendshapes - truth, axis=2).mean(1)
    assert error_mm.max() < 0.05, dict(zip(ARKIT_NAMES, error_mm.round(3)))


@pytest.mark.slow
def test_denser_mesh_keeps_the_shapes_and_the_lips_apart(head):
    """One midpoint subdivision: the true shapes are the subdivided ones; closed lips touch, and
    the lower lip must still open with the jaw."""
    v, f = trimesh.remesh.subdivide(head.template, head.faces)
    truth = np.stack(
        [trimesh.remesh.subdivide(head.template + s, head.faces)[0] - v for s in head.blendshapes]
    )
    rig = rig_head(v, f, head)
    error = np.linalg.norm(rig.blendshapes - truth, axis=2).mean(1)
    magnitude = np.linalg.norm(truth, axis=2).mean(1)
    assert (error / magnitude).mean() < 0.05
    jaw = ARKIT_NAMES.index("jawOpen")
    upper, lower = head.regions.lip_pair  # original vertices keep their index
    gap = np.linalg.norm((v + rig.blendshapes[jaw])[upper] - (v + rig.blendshapes[jaw])[lower])
    true_gap = np.linalg.norm((v + truth[jaw])[upper] - (v + truth[jaw])[lower])
    assert gap == pytest.approx(true_gap, rel=0.05)


def test_not_a_head(head):
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    box = trimesh.creation.box((0.3, 0.02, 0.4))
    box = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, 0.02)
    with pytest.raises(TalkmeshError, match="does not look like a head"):
        rig_head(*box, head)
    with pytest.raises(TalkmeshError, match="at least 100 vertices"):
        rig_head(sphere.vertices[:50], sphere.faces[:10], head)


def test_cli_rig_then_animate_as_avatar(tmp_path, capsys):
    head = load_head()
    mesh = trimesh.Trimesh(1000 * head.template, head.faces, process=False)  # millimetres
    mesh.export(tmp_path / "me.obj")
    assert main(["rig", str(tmp_path / "me.obj"), "-o", str(tmp_path / "me.glb")]) == 0
    assert "units mm, up +y" in capsys.readouterr().out
    gltf, _ = read_glb(tmp_path / "me.glb")
    assert gltf["meshes"][0]["extras"]["targetNames"] == list(ARKIT_NAMES)
    weights = np.zeros((10, 52), np.float32)
    binding = animate_avatar(tmp_path / "me.glb", weights, 30.0, tmp_path / "talk.glb")
    assert not binding.missing
    (tmp_path / "bad.obj").write_text("not a mesh\n")
    assert main(["rig", str(tmp_path / "bad.obj"), "-o", str(tmp_path / "b.glb")]) == 2
    assert "bad.obj" in capsys.readouterr().err and not (tmp_path / "b.glb").exists()
