"""`talkmesh rig`: the bundled blendshapes carried onto a head in other units, axes and meshing."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from talkmesh.cli import main
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import load_head
from talkmesh.face.rig import LANDMARK_NAMES, head_landmarks, rig_head
from talkmesh.face.transfer import (
    SAMPLES,
    deformation_gradients,
    fitted_gradients,
    rigid_follow,
    transfer,
)
from talkmesh.output.avatar import animate_avatar, read_glb


@pytest.fixture(scope="module")
def head():
    return load_head()


@pytest.fixture(scope="module")
def z_up_cm(head):
    """The head in centimetres, Z-up, shifted, rigged; and the rotation."""
    r = trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0])[:3, :3]
    return rig_head(100 * head.template @ r.T + [3, -2, 10], head.faces, head), r


def test_units_and_up_axis_are_detected_and_kept(head, z_up_cm):
    """The offsets come back scaled and rotated; the eyes and teeth are found as parts."""
    rig, r = z_up_cm
    assert rig.units == "cm" and rig.up_axis == "-z"
    truth = 100 * head.blendshapes @ r.T
    error_mm = 10 * np.linalg.norm(rig.blendshapes - truth, axis=2).mean(1)
    # rigid parts follow a best rotation, blendshapes rotate linearly: not exact, within 0.3 mm
    assert error_mm.mean() < 0.02 and error_mm.max() < 0.3, dict(
        zip(ARKIT_NAMES, error_mm.round(3))
    )
    assert rig.parts == {"eye": 2, "teeth": 2}
    assert rig.landmarks == head_landmarks(head)  # the same mesh: every landmark on its vertex


def test_vertex_motion_is_carried_through_the_correspondence(head, z_up_cm):
    rig, r = z_up_cm
    offsets = head.blendshapes[[ARKIT_NAMES.index("jawOpen")]]
    carried = rig.carry(offsets)
    assert carried.shape == (1, head.num_vertices, 3)
    np.testing.assert_allclose(carried[0], 100 * offsets[0] @ r.T, atol=1e-3)


def _random_rig(num_vertices=500, num_bundled=100, seed=0):
    """A Rig whose correspondence is random (no registration): what carry needs, cheaply."""
    from talkmesh.face.rig import Rig

    rng = np.random.default_rng(seed)
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    return Rig(
        vertices=rng.normal(size=(num_vertices, 3)).astype(np.float32),
        faces=np.zeros((0, 3), np.int32),
        blendshapes=np.zeros((52, num_vertices, 3), np.float32),
        scale=1000.0,
        rotation=rotation,
        translation=np.zeros(3),
        residual=0.0,
        corners=rng.integers(0, num_bundled, (num_vertices, 3)),
        weights=rng.dirichlet(np.ones(3), num_vertices),
    )


def test_carry_in_blocks_of_vertices_equals_the_whole_gather(monkeypatch):
    """Rig.carry gathers CARRY_VALUES at a time (the (T, V, 3, 3) gather of a million-vertex head
    was 22 GB for one block of frames): the same offsets as the gather of every vertex at once."""
    from talkmesh.face import rig as rig_module

    rig = _random_rig()
    offsets = np.random.default_rng(1).normal(size=(7, 100, 3)) * 1e-3
    whole = np.einsum("vc,tvcx->tvx", rig.weights, offsets[:, rig.corners])
    expected = rig.scale * whole @ rig.rotation.T
    monkeypatch.setattr(rig_module, "CARRY_VALUES", 9 * 7 * 13)  # 13 vertices at a time
    carried = rig.carry(offsets)
    assert carried.dtype == np.float32 and carried.shape == (7, 500, 3)
    np.testing.assert_allclose(carried, expected, rtol=1e-5, atol=1e-6)


def test_carry_blocks_cut_large_blocks_and_keep_every_frame(monkeypatch):
    """Rig.carry_blocks yields blocks of at most BLOCK_VALUES float32 values: the same frames and
    weights, in order, as carrying the whole animation."""
    from talkmesh.animation import Animation, AnimationBlocks
    from talkmesh.face import rig as rig_module

    rig = _random_rig()
    rng = np.random.default_rng(2)
    template = rng.normal(size=(100, 3)).astype(np.float32)
    frames = template + 1e-3 * rng.normal(size=(9, 100, 3)).astype(np.float32)
    weights = rng.random((9, 52)).astype(np.float32)
    blocks = [
        Animation(vertices=frames[a:b], faces=np.zeros((0, 3), np.int32), fps=30.0,
                  weights=weights[a:b], weight_names=list(ARKIT_NAMES))
        for a, b in ((0, 5), (5, 9))
    ]  # fmt: skip
    anim = AnimationBlocks(iter(blocks), 9, np.zeros((0, 3), np.int32), 30.0,
                           weight_names=list(ARKIT_NAMES))  # fmt: skip
    monkeypatch.setattr(rig_module, "BLOCK_VALUES", 3 * 500 * 2)  # two frames a block
    out = list(rig.carry_blocks(anim, template).blocks)
    assert [b.num_frames for b in out] == [2, 2, 1, 2, 2]
    moved = np.concatenate([b.vertices for b in out])
    np.testing.assert_allclose(moved, rig.vertices + rig.carry(frames - template), atol=1e-5)
    np.testing.assert_array_equal(np.concatenate([b.weights for b in out]), weights)


def test_deformation_transfer_is_exact_for_an_affine_map_and_follows_the_gradients():
    """A triangle mesh sheared by A: the gradient of every triangle is A, and transferring it
    (anchored at the true offsets) returns the true offsets; rigid_follow turns a part."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    v, f = mesh.vertices, mesh.faces
    a = np.array([[1.2, 0.3, 0.0], [0.0, 0.9, 0.1], [0.0, 0.0, 1.1]])
    offsets = (v @ a.T - v)[None]
    gradients = deformation_gradients(v, f, offsets)
    edges = v[f[:, 1]] - v[f[:, 0]]  # the gradients map every edge as A does
    np.testing.assert_allclose(np.einsum("fxy,fy->fx", gradients[0], edges), edges @ a.T, atol=1e-9)
    out = transfer(v, f, gradients, offsets)
    np.testing.assert_allclose(out, offsets, atol=1e-9)
    # Anchored at zero, the gradients still give the shape up to a translation.
    free = transfer(v, f, gradients, np.zeros_like(offsets), anchor=1e-6)
    shifted = free[0] - free[0].mean(0) - (offsets[0] - offsets[0].mean(0))
    assert np.abs(shifted).max() < 1e-3
    turn = trimesh.transformations.rotation_matrix(0.3, [0, 1, 0])[:3, :3]
    follow = rigid_follow(v + 5.0, v, (v @ turn.T - v)[None])
    np.testing.assert_allclose(follow[0], (v @ turn.T) - v, atol=1e-9)


def test_fitted_gradients_average_a_field_over_each_triangle():
    """Sampled from an affine field, the fitted gradients map every edge as the field does; from
    a bump inside a triangle (zero at its corners), they fit its mean slope, here zero, so the
    transfer leaves the vertices where the corners' offsets put them."""
    mesh = trimesh.creation.icosphere(subdivisions=1)
    v, f = mesh.vertices, mesh.faces
    a = np.array([[0.2, 0.1, 0.0], [0.0, -0.1, 0.3], [0.1, 0.0, 0.05]])
    points = np.einsum("sc,fcx->fsx", SAMPLES, v[f])  # (F, samples, 3)
    gradients = fitted_gradients(v, f, (points @ a.T)[None])
    edges = v[f[:, 1]] - v[f[:, 0]]
    moved = np.einsum("fxy,fy->fx", gradients[0], edges)
    np.testing.assert_allclose(moved, edges + edges @ a.T, atol=1e-9)
    bump = np.zeros((1, len(f), len(SAMPLES), 3))
    bump[..., 3:, 2] = 1.0  # edge midpoints and centroid raised, corners not
    flat = fitted_gradients(v, f, bump)
    np.testing.assert_allclose(np.einsum("fxy,fy->fx", flat[0], edges), edges, atol=1e-9)


@pytest.mark.slow  # minutes on 2 cores: `make test-slow`
def test_landmarks_can_be_given_and_are_checked(head):
    v = 1000 * head.template.astype(np.float64)
    marks = head_landmarks(head)
    assert set(marks) == set(LANDMARK_NAMES) and len(set(marks.values())) == len(marks)
    rig = rig_head(v, head.faces, head, landmarks=marks, method="closest")
    assert rig.landmarks == marks and rig.units == "mm"
    with pytest.raises(TalkmeshError, match="unknown landmark 'nose'"):
        rig_head(v, head.faces, head, landmarks={"nose": 3})
    with pytest.raises(TalkmeshError, match="vertices 0 to 4765"):
        rig_head(v, head.faces, head, landmarks={"chin": 5000})


def test_a_head_with_sealed_lips_is_one_cli_error(head, tmp_path, capsys):
    """Merging the inner lip vertices of the upper and lower lip closes the mouth opening:
    `talkmesh rig` refuses it in one line and writes nothing."""
    v, f = head.template.astype(np.float64), head.faces.astype(np.int64)
    lips = head.regions.lips
    upper, lower = head.regions.lip_pair
    inner = lips[np.linalg.norm(v[lips] - v[[upper, lower]].mean(0), axis=1) < 0.03]
    # weld: each inner lower-lip vertex within 3 mm of an upper-lip vertex becomes it
    tree = trimesh.proximity.cKDTree(v[inner])
    remap = np.arange(len(v))
    for i in inner:
        d, j = tree.query(v[i], k=2)
        if d[1] < 0.003 and inner[j[1]] < i:
            remap[i] = inner[j[1]]
    sealed = remap[f]
    sealed = sealed[(sealed[:, 0] != sealed[:, 1]) & (sealed[:, 1] != sealed[:, 2])]
    sealed = sealed[sealed[:, 0] != sealed[:, 2]]
    trimesh.Trimesh(v, sealed, process=False).export(tmp_path / "sealed.obj")
    out = tmp_path / "sealed.glb"
    assert main(["rig", str(tmp_path / "sealed.obj"), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no mouth opening" in err and len(err.splitlines()) == 1, err
    assert not out.exists()


def _hand() -> trimesh.Trimesh:
    """A hand-like blob: a flat palm and five finger capsules (the thumb shorter, to the side)."""
    palm = trimesh.creation.icosphere(subdivisions=3)
    palm.apply_scale([0.045, 0.055, 0.015])
    parts = [palm]
    thumb, fingers = [(-0.055, 0.03, 0.04)], [(x, 0.08, 0.06) for x in (-0.03, -0.01, 0.01, 0.03)]
    for x, y, length in thumb + fingers:
        finger = trimesh.creation.capsule(height=length, radius=0.008)
        finger.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
        finger.apply_translation([x, y, 0.0])
        parts.append(finger)
    return trimesh.util.concatenate(parts)


def _not_heads() -> dict[str, trimesh.Trimesh]:
    """Head-sized meshes that are no head (each refused at 10-20% where a head fits under 8%)."""
    box = trimesh.creation.box((0.15, 0.2, 0.18))
    square = trimesh.Trimesh(
        [[0, 0, 0], [0.2, 0, 0], [0.2, 0.25, 0], [0, 0.25, 0]], [[0, 1, 2], [0, 2, 3]]
    )
    return {
        "sphere": trimesh.creation.icosphere(subdivisions=3, radius=0.1),
        "cube": trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(box.vertices, box.faces, 0.02)),
        "plane": trimesh.Trimesh(
            *trimesh.remesh.subdivide_to_size(square.vertices, square.faces, 0.01)
        ),
        "hand": _hand(),
    }


@pytest.mark.parametrize("name", ["sphere", "cube", "plane", "hand"])
def test_a_mesh_that_is_no_head_is_one_cli_error(name, tmp_path, capsys):
    """`talkmesh rig` on a sphere, a cube, a plane, a hand: exit 2, one line naming the file."""
    path, out = tmp_path / f"{name}.obj", tmp_path / f"{name}.glb"
    _not_heads()[name].export(path)
    assert main(["rig", str(path), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "does not look like a head" in err and f"{name}.obj" in err, err
    assert not out.exists()


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
    assert (error / magnitude).mean() < 0.1
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


@pytest.mark.slow  # most of a minute on 2 cores: `make test-slow`
def test_cli_rig_then_animate_as_avatar(tmp_path, capsys, monkeypatch):
    """The rigged .glb drives like any avatar; `animate --head` on the same mesh file reads the
    registration `talkmesh rig` saved instead of registering again."""
    import talkmesh.face.rig_files as rig_module

    head = load_head()
    mesh = trimesh.Trimesh(1000 * head.template, head.faces, process=False)  # millimetres
    mesh.export(tmp_path / "me.obj")
    assert main(["rig", str(tmp_path / "me.obj"), "-o", str(tmp_path / "me.glb")]) == 0
    assert "units mm, up +y" in capsys.readouterr().out
    rig_module._rig_file.cache_clear()
    monkeypatch.setattr(rig_module, "rig_head", None)  # registering again would fail
    saved = rig_module.load_rig(tmp_path / "me.obj")
    rig_module._rig_file.cache_clear()
    jaw = ARKIT_NAMES.index("jawOpen")
    assert saved.units == "mm" and saved.landmarks == head_landmarks(head)
    np.testing.assert_allclose(saved.blendshapes[jaw], 1000 * head.blendshapes[jaw], atol=1e-3)
    gltf, _ = read_glb(tmp_path / "me.glb")
    assert gltf["meshes"][0]["extras"]["targetNames"] == list(ARKIT_NAMES)
    assert "animations" not in gltf  # no still placeholder clip for viewers to play first
    weights = np.zeros((10, 52), np.float32)
    binding = animate_avatar(tmp_path / "me.glb", weights, 30.0, tmp_path / "talk.glb")
    assert not binding.missing and binding.clips == ()
    assert [a["name"] for a in read_glb(tmp_path / "talk.glb")[0]["animations"]] == ["talk"]
    (tmp_path / "bad.obj").write_text("not a mesh\n")
    assert main(["rig", str(tmp_path / "bad.obj"), "-o", str(tmp_path / "b.glb")]) == 2
    assert "bad.obj" in capsys.readouterr().err and not (tmp_path / "b.glb").exists()


@pytest.mark.slow  # minutes on 2 cores: `make test-slow`
def test_cli_rig_of_a_z_up_mesh_stands_up_in_gltf(tmp_path, capsys):
    """glTF is metres and +y up: the .glb of a Z-up millimetre head carries the turn and the unit
    as its root node, and keeps the user's vertices as they were."""
    import pygltflib

    head = load_head()
    r = trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])[:3, :3]  # +y -> +z
    mine = 1000 * head.template @ r.T
    trimesh.Trimesh(mine, head.faces, process=False).export(tmp_path / "z.obj")
    assert main(["rig", str(tmp_path / "z.obj"), "-o", str(tmp_path / "z.glb")]) == 0
    assert "units mm, up +z" in capsys.readouterr().out
    gltf = pygltflib.GLTF2().load(str(tmp_path / "z.glb"))
    (root,) = gltf.scenes[gltf.scene].nodes

    def world(index: int, parent: np.ndarray) -> dict[int, np.ndarray]:
        node = gltf.nodes[index]
        local = np.array(node.matrix or np.eye(4).ravel().tolist(), float).reshape(4, 4).T
        out = {index: parent @ local}
        for child in node.children or []:
            out.update(world(child, out[index]))
        return out

    mesh_node = next(i for i, n in enumerate(gltf.nodes) if n.mesh is not None)
    matrix = world(root, np.eye(4))[mesh_node]
    accessor = gltf.accessors[gltf.meshes[0].primitives[0].attributes.POSITION]
    view = gltf.bufferViews[accessor.bufferView]
    data = gltf.binary_blob()[view.byteOffset + (accessor.byteOffset or 0) :]
    stored = np.frombuffer(data, np.float32, accessor.count * 3).reshape(-1, 3)
    np.testing.assert_allclose(stored, mine, atol=1e-2)  # the user's vertices, recoverable
    up = matrix[:3, :3] @ np.array([0.0, 0.0, 1.0])  # the user's up in the world
    np.testing.assert_allclose(up, [0.0, 0.001, 0.0], atol=1e-9)  # +y, and metres
    placed = stored @ matrix[:3, :3].T + matrix[:3, 3]
    np.testing.assert_allclose(placed, head.template, atol=1e-5)


# --------------------------------------------------------------------------- dense meshes


@pytest.mark.slow  # minutes on 2 cores: `make test-slow`
def test_a_dense_mesh_is_registered_on_a_reduced_copy_and_carried_back(head, monkeypatch):
    """Over REDUCE_ABOVE vertices the registration runs on a decimated copy (its cost no longer
    grows with the mesh) and the shapes come back to every vertex, block by block: the bundled
    head, with the threshold below its own size, gets its own shapes back."""
    from talkmesh.face import rig as rig_module

    monkeypatch.setattr(rig_module, "REDUCE_ABOVE", 3000)
    monkeypatch.setattr(rig_module, "CARRY_BLOCK", 1000)
    registered = []
    inner = rig_module._rig
    monkeypatch.setattr(
        rig_module, "_rig", lambda v, *args: registered.append(len(v)) or inner(v, *args)
    )
    rig = rig_head(head.template, head.faces, head, method="closest")
    assert registered and registered[0] <= 3200  # the copy, not the 4766 vertices
    assert rig.blendshapes.shape == head.blendshapes.shape and np.isfinite(rig.blendshapes).all()
    assert rig.corners.shape == (head.num_vertices, 3) and rig.weights.shape == (
        head.num_vertices,
        3,
    )
    error = np.linalg.norm(rig.blendshapes - head.blendshapes, axis=2).mean(1)
    magnitude = np.linalg.norm(head.blendshapes, axis=2).mean(1)
    assert (error / np.maximum(magnitude, 1e-9)).mean() < 0.2
    jaw = ARKIT_NAMES.index("jawOpen")
    upper, lower = head.regions.lip_pair  # the lower lip takes the lower lip's motion
    assert rig.blendshapes[jaw, lower, 1] < rig.blendshapes[jaw, upper, 1] - 1e-3


def test_a_dense_mesh_that_is_no_head_is_refused_on_a_sample_before_decimating(
    tmp_path, monkeypatch, capsys
):
    """The not-a-head check of a dense mesh fits CHECK_POINTS of its vertices, before the
    decimation (whose time grows with the mesh: a 655k-vertex sphere took 25 s to refuse):
    no rigid fit sees more, nothing is decimated, and the CLI says so in one line."""
    from talkmesh.face import rig as rig_module

    monkeypatch.setattr(rig_module, "REDUCE_ABOVE", 2000)
    monkeypatch.setattr(rig_module, "CHECK_POINTS", 1000)
    fitted = []
    inner = rig_module.rigid_fit
    monkeypatch.setattr(
        rig_module, "rigid_fit", lambda s, t, *a: fitted.append(len(t)) or inner(s, t, *a)
    )

    def no_decimation(*args):
        raise AssertionError("decimated a mesh that is no head")

    monkeypatch.setattr(rig_module, "reduce_mesh", no_decimation)
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.1)  # 10242 vertices
    with pytest.raises(TalkmeshError, match="does not look like a head"):
        rig_head(sphere.vertices, sphere.faces)
    assert fitted == [1000]
    path, out = tmp_path / "sphere.ply", tmp_path / "sphere.glb"
    sphere.export(path)
    assert main(["rig", str(path), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "sphere.ply" in err and "not look like a head" in err
    assert not out.exists()


def test_a_mesh_of_several_parts_is_read_merged(tmp_path):
    """load_mesh takes a one-mesh file as trimesh reads it and merges a scene's meshes."""
    from talkmesh.face.rig_files import load_mesh

    a = trimesh.creation.icosphere(subdivisions=1)
    b = trimesh.creation.box()
    trimesh.Scene([a, b]).export(tmp_path / "two.glb")
    a.export(tmp_path / "one.ply")
    vertices, faces = load_mesh(tmp_path / "two.glb")
    assert vertices.shape == (len(a.vertices) + len(b.vertices), 3)
    assert faces.shape == (len(a.faces) + len(b.faces), 3) and faces.max() < len(vertices)
    vertices, faces = load_mesh(tmp_path / "one.ply")
    np.testing.assert_allclose(vertices, a.vertices)
    np.testing.assert_array_equal(faces, a.faces)


@pytest.mark.slow
def test_a_million_vertices_rig_in_bounded_memory(head, tmp_path):
    """The bundled head subdivided four times (1.2M vertices, in millimetres): `talkmesh rig`
    under 2 GB peak (the shapes alone are 750 MB; 1167 MB measured: docs/results/rigging.md)."""
    import resource
    import subprocess
    import sys

    v, f = head.template.astype(np.float64), head.faces
    for _ in range(4):
        v, f = trimesh.remesh.subdivide(v, f)
    path = tmp_path / "dense.ply"
    trimesh.Trimesh(1000 * v, f, process=False).export(path)
    cmd = [sys.executable, "-m", "talkmesh", "rig", str(path), "-o", str(tmp_path / "d.glb")]
    subprocess.run(cmd, check=True, capture_output=True)
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    assert peak_mb < 2000, peak_mb


def test_the_decimation_runs_in_a_child_that_gives_its_arrays_back():
    """fast-simplification never frees its C++ working arrays (600 MB at 2.4M faces): the
    decimation runs in a forked child (its arrays come back through a pipe); a child that fails
    leaves the work to this process, which raises what it raises."""
    import os

    from talkmesh.face.rig_dense import _in_child

    here = os.getpid()
    ids, ones = _in_child(lambda n: (np.arange(n) + os.getpid() - here, np.ones((2, 3))), 4)
    assert ones.shape == (2, 3) and ids.shape == (4,)
    if hasattr(os, "fork"):
        assert not np.array_equal(ids, np.arange(4))  # another process computed it
    with pytest.raises(ZeroDivisionError):
        _in_child(lambda: (1 / 0,))
