import numpy as np
import pytest

from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import (
    DATA_DIR,
    list_identities,
    load_head,
    load_template,
    read_mesh_vertices,
)


def test_head_topology_and_blendshapes():
    head = load_head()
    assert 4000 <= head.num_vertices <= 6000
    assert head.faces.shape[1] == 3 and head.faces.max() < head.num_vertices
    assert head.blendshape_names == ARKIT_NAMES
    assert head.blendshapes.shape == (52, head.num_vertices, 3)
    # every ARKit shape moves something, and by a plausible amount (mm to a few cm)
    moved = np.linalg.norm(head.blendshapes, axis=2).max(1)
    assert (moved > 1e-3).all() and (moved < 0.06).all()


def test_identities_differ_in_shape_not_just_scale():
    names = list_identities()
    assert len(names) >= 12
    heads = np.stack([load_head(n).template for n in names])
    centred = heads - heads.mean(1, keepdims=True)
    unit = centred / np.linalg.norm(centred, axis=(1, 2), keepdims=True)
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            # residual after removing scale: > 0 means a different shape
            assert np.abs(unit[i] - unit[j]).max() > 1e-3, (names[i], names[j])


def test_regions_are_sensible():
    head = load_head()
    r = head.regions
    t = head.template
    assert 100 < len(r.lips) < 0.2 * head.num_vertices
    assert len(r.upper_face) > len(r.lips)
    assert not set(r.lips) & set(r.upper_face)
    # lips below the eyelids, upper face above the lips
    assert t[r.lips, 1].mean() < t[r.eyelids, 1].mean()
    assert t[r.upper_face, 1].min() > t[r.lips, 1].max()
    for w in (r.mouth_weight, r.upper_weight):
        assert w.shape == (head.num_vertices,) and w.min() >= 0 and w.max() <= 1
    assert r.mouth_weight[r.lips].mean() > 0.8 and r.mouth_weight[r.upper_face].mean() < 0.1
    assert r.upper_weight[r.upper_face].mean() > 0.5 and r.upper_weight[r.lips].mean() < 0.1


def test_package_data_is_small():
    total = sum(p.stat().st_size for p in DATA_DIR.iterdir() if p.is_file())
    assert total < 15e6


def test_unknown_identity_is_a_one_line_error():
    with pytest.raises(TalkmeshError, match="unknown identity"):
        load_head("nobody")


def test_load_template_converts_units_and_axes_as_the_cli_does(tmp_path):
    """A bundled-topology mesh in millimetres and Z-up comes back in metres and +y up, with a
    warning saying so (the CLI's --template did this, the Python API took it as metres);
    convert=False takes it as it is."""
    from talkmesh.errors import TalkmeshWarning

    head = load_head()
    z_up = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], np.float64)  # +y (head up) -> +z
    path = tmp_path / "mm_z_up.npy"
    np.save(path, 1000 * head.template.astype(np.float64) @ z_up.T)
    with pytest.warns(TalkmeshWarning, match=r"mm_z_up.*millimetres -> metres, up \+z -> \+y"):
        converted = load_template(path)
    np.testing.assert_allclose(converted.template, head.template, atol=1e-6)
    as_given = load_template(path, convert=False)
    np.testing.assert_allclose(as_given.template, 1000 * head.template @ z_up.T, atol=1e-3)


def test_template_roundtrip_and_wrong_vertex_count(tmp_path):
    head = load_head("bo")
    obj = tmp_path / "bo.obj"
    obj.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in head.template))
    assert np.allclose(load_template(obj).template, head.template, atol=1e-6)

    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(TalkmeshError, match=r"bad\.obj.*3 vertices"):
        load_template(bad)
    empty = tmp_path / "empty.obj"
    empty.write_text("")
    with pytest.raises(TalkmeshError, match="empty"):
        read_mesh_vertices(empty)
    with pytest.raises(TalkmeshError, match="no such"):
        read_mesh_vertices(tmp_path / "missing.obj")
