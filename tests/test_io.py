"""Exporters and importers: round trips, the glTF validator, Live Link CSV layout, safety."""

from __future__ import annotations

import json
import re
import shutil
import struct
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from talkmesh.animation import Animation
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES, LIVE_LINK_COLUMNS, LIVE_LINK_NAMES, to_arkit_order
from talkmesh.output import arkit_files, formats, morph, npy
from talkmesh.output import gltf as gltf_module
from talkmesh.output.formats import load_animation, load_arkit_weights, morph_rig, save_animation
from talkmesh.output.gltf import GLB_JSON, glb_bytes

ROOT = Path(__file__).resolve().parents[1]
VALIDATE_SCRIPT = ROOT / "tests" / "gltf_validate.mjs"
T, ROWS, COLS = 20, 20, 10  # 20 frames of a 20 x 10 = 200-vertex grid


def grid_mesh(rows: int = ROWS, cols: int = COLS, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(rows*cols, 3) float32 vertices of a 10 cm bumpy sheet and its (F, 3) triangles."""
    rng = np.random.default_rng(seed)
    y, x = np.meshgrid(np.linspace(0, 0.1, rows), np.linspace(0, 0.05, cols), indexing="ij")
    vertices = np.stack([x, y, rng.normal(0, 0.002, x.shape)], axis=-1).reshape(-1, 3)
    ids = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = ids[:-1, :-1], ids[:-1, 1:], ids[1:, :-1], ids[1:, 1:]
    faces = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)]).reshape(-1, 3)
    return vertices.astype(np.float32), faces.astype(np.int32)


def arkit_animation(frames: int = T, seed: int = 0) -> Animation:
    """Vertices exactly ``template + weights @ basis`` with a random 52-shape basis."""
    rng = np.random.default_rng(seed)
    template, faces = grid_mesh(seed=seed)
    basis = rng.normal(0, 0.003, (52, len(template), 3)).astype(np.float32)
    weights = rng.uniform(0, 1, (frames, 52)).astype(np.float32)
    vertices = template + np.einsum("tk,kvc->tvc", weights, basis)
    audio = rng.normal(0, 0.1, 16_000 * frames // 30).astype(np.float32)
    return Animation(
        vertices,
        faces,
        30.0,
        audio=audio,
        weights=weights,
        weight_names=list(ARKIT_NAMES),
        template=template,
        basis=basis,
    )


def vertex_animation(frames: int = T, rank: int = 6, seed: int = 1) -> Animation:
    """Vertices only: a low-rank motion plus a little nonlinear wobble, at 25 fps."""
    rng = np.random.default_rng(seed)
    template, faces = grid_mesh(seed=seed)
    modes = rng.normal(0, 0.004, (rank, len(template), 3))
    coeffs = np.sin(np.arange(frames)[:, None] * rng.uniform(0.1, 0.9, rank))
    wobble = 0.0005 * np.sin(40 * template[None] + np.arange(frames)[:, None, None] * 0.3)
    vertices = template + np.einsum("tk,kvc->tvc", coeffs, modes) + wobble
    return Animation(vertices.astype(np.float32), faces, 25.0)


def residual_animation() -> Animation:
    """ARKit weights and basis that miss the vertices by a few millimetres."""
    anim = arkit_animation()
    wobble = vertex_animation()
    anim.vertices = anim.vertices + wobble.vertices - wobble.vertices[0]
    return anim


def max_error(a: Animation, b: Animation) -> float:
    assert a.vertices.shape == b.vertices.shape
    return float(np.abs(a.vertices - b.vertices).max())


def glb_json(path: Path) -> dict:
    data = path.read_bytes()
    size, kind = struct.unpack_from("<II", data, 12)
    assert kind == GLB_JSON
    return json.loads(data[20 : 20 + size])


def validate_glb(path: Path) -> dict:
    """The Khronos validator's report for ``path`` (fails the test if node is unavailable)."""
    node = shutil.which("node")
    if node is None:
        pytest.fail("node is not installed: the glTF validator test needs Node.js (make setup)")
    if not (ROOT / "node_modules" / "gltf-validator").is_dir():
        pytest.fail("the gltf-validator npm package is missing: run `npm ci` in the repo root")
    run = subprocess.run(
        [node, str(VALIDATE_SCRIPT), str(path)], capture_output=True, text=True, timeout=120
    )
    assert run.returncode in (0, 1), f"validator did not run: {run.stderr}"
    return json.loads(run.stdout)


# --- .npy / .npz ---------------------------------------------------------------------------


def test_npy_is_vocaset_layout_and_round_trips(tmp_path):
    anim = arkit_animation()
    (out,) = save_animation(anim, tmp_path / "talk.npy")
    raw = np.load(out, allow_pickle=False)
    assert raw.shape == (T, anim.num_vertices * 3) and raw.dtype == np.float32
    back = load_animation(out, faces=anim.faces)
    assert max_error(anim, back) == 0.0
    assert back.fps == npy.NPY_DEFAULT_FPS
    np.testing.assert_array_equal(back.faces, anim.faces)
    assert load_animation(out, faces=anim.faces, fps=60).fps == 60


def test_npy_without_faces_needs_matching_head(tmp_path):
    (out,) = save_animation(arkit_animation(), tmp_path / "talk.npy")
    with pytest.raises(TalkmeshError, match="faces"):
        load_animation(out)


def test_npy_uses_bundled_head_faces(tmp_path):
    from talkmesh.face.assets import load_head

    head = load_head()
    np.save(tmp_path / "pred.npy", np.repeat(head.template.reshape(1, -1), 3, axis=0))
    anim = load_animation(tmp_path / "pred.npy")
    np.testing.assert_array_equal(anim.faces, head.faces)
    assert anim.vertices.shape == (3, head.num_vertices, 3)


def test_npz_round_trip_keeps_everything_without_pickle(tmp_path):
    anim = arkit_animation()
    (out,) = save_animation(anim, tmp_path / "talk.npz")
    with np.load(out, allow_pickle=False) as z:
        assert z["weight_names"].dtype.kind == "U"
        assert {"offsets", "faces", "fps", "audio", "weights", "template", "basis"} <= set(z.files)
    back = load_animation(out)
    # float16 offsets from the template: half a float16 step of the largest offset at most
    assert max_error(anim, back) <= np.abs(anim.vertices - anim.template).max() * 2.0**-11 + 1e-7
    assert back.fps == anim.fps and back.sample_rate == anim.sample_rate
    assert back.weight_names == anim.weight_names
    for name in ("faces", "audio", "weights", "template", "basis"):
        np.testing.assert_array_equal(getattr(back, name), getattr(anim, name))


def test_npz_without_optional_fields(tmp_path):
    anim = vertex_animation()
    (out,) = save_animation(anim, tmp_path / "talk.npz")
    back = load_animation(out)
    assert max_error(anim, back) == 0.0 and back.fps == 25.0
    assert back.weights is None and back.audio is None and back.basis is None


# --- .glb ----------------------------------------------------------------------------------


def test_glb_round_trip_with_arkit_basis(tmp_path):
    anim = arkit_animation()
    (out,) = save_animation(anim, tmp_path / "talk.glb")
    back = load_animation(out)
    assert max_error(anim, back) < 1e-4
    assert back.fps == anim.fps
    assert back.weight_names == list(ARKIT_NAMES)
    np.testing.assert_allclose(back.weights, anim.weights, atol=1e-6)
    np.testing.assert_allclose(back.basis, anim.basis, atol=1e-7)
    np.testing.assert_allclose(back.template, anim.template, atol=1e-6)
    np.testing.assert_array_equal(back.faces, anim.faces)


def test_rig_glb_has_the_targets_and_no_animation(tmp_path):
    """NAME.rig.glb (what `talkmesh rig` writes): the morph targets alone, no still clip for a
    viewer to play first; it reads back as the neutral face with its ARKit basis."""
    anim = arkit_animation()
    one = Animation(
        anim.vertices[:1] * 0 + anim.template,
        anim.faces,
        anim.fps,
        weights=np.zeros((1, 52), np.float32),
        weight_names=list(ARKIT_NAMES),
        template=anim.template,
        basis=anim.basis,
    )
    (out,) = save_animation(one, tmp_path / "head.rig.glb")
    assert "animations" not in glb_json(out)
    back = load_animation(out)
    np.testing.assert_allclose(back.basis, anim.basis, atol=1e-7)
    np.testing.assert_allclose(back.vertices[0], anim.template, atol=1e-6)
    assert validate_glb(out)["issues"]["numErrors"] == 0


def test_glb_round_trip_with_pca_targets(tmp_path):
    anim = vertex_animation()
    (out,) = save_animation(anim, tmp_path / "talk.glb")
    back = load_animation(out)
    assert max_error(anim, back) < 1e-4
    assert back.fps == 25.0 and back.weights is None and back.basis is None
    names = glb_json(out)["meshes"][0]["extras"]["targetNames"]
    assert 1 <= len(names) <= min(T, morph.MAX_PCA_TARGETS)
    assert all(re.fullmatch(r"pca_\d{3}", n) for n in names)


def test_glb_residual_targets_when_basis_misses_vertices(tmp_path):
    anim = residual_animation()
    (out,) = save_animation(anim, tmp_path / "talk.glb")
    names = glb_json(out)["meshes"][0]["extras"]["targetNames"]
    assert names[:52] == list(ARKIT_NAMES) and names[52].startswith("residual_")
    back = load_animation(out)
    assert max_error(anim, back) < 1e-4
    np.testing.assert_allclose(back.weights, anim.weights, atol=1e-6)


def test_pca_weights_stay_in_unit_range_and_rest_is_neutral():
    anim = vertex_animation()
    rig = morph_rig(anim)
    assert rig.weights.min() >= 0 and rig.weights.max() <= 1
    assert rig.rest_weights.min() >= 0 and rig.rest_weights.max() <= 1
    np.testing.assert_allclose(rig.neutral(), anim.vertices[0], atol=1e-6)


def test_pca_caps_targets_on_full_rank_motion():
    rng = np.random.default_rng(3)
    template, faces = grid_mesh()
    noise = rng.normal(0, 0.01, (100, len(template), 3)).astype(np.float32)
    rig = morph_rig(Animation(template + noise, faces, 30.0))
    assert len(rig.names) == morph.MAX_PCA_TARGETS


def test_randomised_pca_on_long_animation():
    anim = vertex_animation(frames=700, rank=8)  # 700 frames x 600 coords > EXACT_SVD_LIMIT
    assert min(anim.num_frames, anim.num_vertices * 3) > morph.EXACT_SVD_LIMIT
    rig = morph_rig(anim)
    assert len(rig.names) < morph.MAX_PCA_TARGETS
    assert np.abs(rig.vertices() - anim.vertices).max() < 1e-4


def test_glb_single_frame_keeps_fps(tmp_path):
    anim = vertex_animation(frames=1)
    (out,) = save_animation(anim, tmp_path / "still.glb")
    back = load_animation(out)
    assert back.num_frames == 1 and back.fps == 25.0 and max_error(anim, back) < 1e-4


Z_UP_MM = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1000]]) / 1000.0


@pytest.mark.parametrize(
    "make",
    [
        arkit_animation,
        vertex_animation,
        residual_animation,
        lambda: vertex_animation(frames=1),
        lambda: replace(arkit_animation(), to_gltf=Z_UP_MM),
        lambda: replace(
            arkit_animation(), colors=np.full((arkit_animation().num_vertices, 3), 0.5)
        ),
        lambda: replace(arkit_animation(), head_pose=head_pose_of(T)),
        lambda: replace(arkit_animation(), head_pose=head_pose_of(T), to_gltf=Z_UP_MM),
    ],
    ids=[
        "arkit",
        "pca",
        "residual",
        "one-frame",
        "root-node",
        "vertex-colours",
        "head-pose",
        "head-pose-root",
    ],
)
def test_glb_passes_khronos_validator(tmp_path, make):
    (out,) = save_animation(make(), tmp_path / "talk.glb")
    report = validate_glb(out)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]
    assert report["issues"]["numWarnings"] == 0, report["issues"]["messages"]
    assert report["info"]["hasMorphTargets"] and report["info"]["animationCount"] == 1


def head_pose_of(frames: int, seed: int = 1) -> np.ndarray:
    """(T, 6) a head pose of a few degrees and millimetres."""
    rng = np.random.default_rng(seed)
    return np.concatenate(
        [rng.uniform(-0.1, 0.1, (frames, 3)), rng.uniform(-0.005, 0.005, (frames, 3))], axis=1
    ).astype(np.float32)


def test_head_pose_is_the_head_node_s_rotation_and_translation(tmp_path):
    from scipy.spatial.transform import Rotation

    anim = replace(arkit_animation(), head_pose=head_pose_of(T))
    (out,) = save_animation(anim, tmp_path / "talk.glb")
    gltf, binary = gltf_module._parse_glb(out.read_bytes())
    head = next(i for i, n in enumerate(gltf["nodes"]) if n.get("name") == "head")
    assert gltf["nodes"][head]["children"] == [0] and gltf["scenes"][0]["nodes"] == [head]
    (animation,) = gltf["animations"]
    got = {}
    for c in animation["channels"]:
        if c["target"]["node"] == head:
            sampler = animation["samplers"][c["sampler"]]
            got[c["target"]["path"]] = gltf_module._read_accessor(gltf, binary, sampler["output"])
    # scipy's intrinsic YXZ Euler angles are R = Ry(yaw) Rx(pitch) Rz(roll)
    pitch, yaw, roll = anim.head_pose[:, :3].T.astype(np.float64)
    want = Rotation.from_euler("YXZ", np.stack([yaw, pitch, roll], 1)).as_matrix()
    np.testing.assert_allclose(Rotation.from_quat(got["rotation"]).as_matrix(), want, atol=1e-6)
    np.testing.assert_allclose(got["translation"], anim.head_pose[:, 3:], atol=1e-7)


def test_head_pose_round_trips_through_npz_and_fills_live_link_head_columns(tmp_path):
    anim = replace(arkit_animation(), head_pose=head_pose_of(T))
    (npz,) = save_animation(anim, tmp_path / "talk.npz")
    (csv,) = save_animation(anim, tmp_path / "take.csv")
    np.testing.assert_array_equal(load_animation(npz).head_pose, anim.head_pose)
    lines = csv.read_text().splitlines()
    header = lines[0].split(",")
    rows = np.array([[float(v) for v in line.split(",")[2:]] for line in lines[1:]])
    cols = [header.index(n) - 2 for n in ("HeadYaw", "HeadPitch", "HeadRoll")]
    # the app's units: radians / pi (Unreal's ARKit face support maps -180..180 deg to -1..1)
    np.testing.assert_allclose(rows[:, cols], anim.head_pose[:, [1, 0, 2]] / np.pi, atol=1e-7)
    assert not rows[:, [header.index("LeftEyeYaw") - 2]].any()


def test_npz_with_a_head_pose_of_the_wrong_length_is_refused(tmp_path):
    anim = replace(arkit_animation(), head_pose=head_pose_of(T))
    (out,) = save_animation(anim, tmp_path / "talk.npz")
    with np.load(out) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["head_pose"] = arrays["head_pose"][:-1]
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    with pytest.raises(TalkmeshError, match="head_pose"):
        load_animation(bad)


def test_glb_layout_for_threejs_and_blender(tmp_path):
    anim = arkit_animation()
    (out,) = save_animation(anim, tmp_path / "talk.glb")
    gltf = glb_json(out)
    mesh = gltf["meshes"][0]
    primitive = mesh["primitives"][0]
    assert mesh["extras"]["targetNames"] == list(ARKIT_NAMES)
    assert len(primitive["targets"]) == len(mesh["weights"]) == 52
    assert {"POSITION", "NORMAL"} <= set(primitive["attributes"])
    accessors = gltf["accessors"]
    assert accessors[primitive["indices"]]["componentType"] == 5123  # UNSIGNED_SHORT
    for ref in [primitive["attributes"]["POSITION"]] + [
        t["POSITION"] for t in primitive["targets"]
    ]:
        assert "min" in accessors[ref] and "max" in accessors[ref]
    (animation,) = gltf["animations"]
    sampler = animation["samplers"][0]
    assert sampler["interpolation"] == "LINEAR"
    assert animation["channels"][0]["target"] == {"node": 0, "path": "weights"}
    assert accessors[sampler["input"]]["count"] == T
    assert accessors[sampler["input"]]["max"] == [pytest.approx((T - 1) / anim.fps)]
    assert accessors[sampler["output"]]["count"] == T * 52


def test_glb_loads_in_trimesh(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    anim = vertex_animation()
    (out,) = save_animation(anim, tmp_path / "talk.glb")
    mesh = trimesh.load(out, force="mesh", process=False)
    assert len(mesh.vertices) == anim.num_vertices and len(mesh.faces) == len(anim.faces)


# --- ARKit weights: Live Link CSV and JSON ---------------------------------------------------


def test_live_link_csv_layout(tmp_path):
    anim = arkit_animation()
    (out,) = save_animation(anim, tmp_path / "take.csv")
    lines = out.read_text().splitlines()
    header = lines[0].split(",")
    assert len(header) == 2 + 61
    assert header[:4] == ["Timecode", "BlendShapeCount", "EyeBlinkLeft", "EyeLookDownLeft"]
    assert header[16:20] == ["JawForward", "JawRight", "JawLeft", "JawOpen"]
    # fmt: skip keeps one line each for the head, the left eye and the right eye.
    assert header[-9:] == [
        "HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
        "RightEyeYaw", "RightEyePitch", "RightEyeRoll",
    ]  # fmt: skip
    assert sorted(header[2:54]) == sorted(LIVE_LINK_NAMES.values())
    rows = [line.split(",") for line in lines[1:]]
    assert len(rows) == anim.num_frames
    assert all(len(r) == 63 and r[1] == "61" for r in rows)
    assert rows[0][0] == "00:00:00:00.000" and rows[-1][0] == "00:00:00:19.000"
    jaw_open = np.array([float(r[header.index("JawOpen")]) for r in rows])
    np.testing.assert_allclose(jaw_open, anim.weights[:, ARKIT_NAMES.index("jawOpen")], atol=1e-7)


def test_live_link_csv_round_trip(tmp_path):
    anim = arkit_animation(frames=100)  # 3.3 s: long enough to infer the fps from timecodes
    (out,) = save_animation(anim, tmp_path / "take.csv")
    back = load_arkit_weights(out)
    assert back.fps == 30.0
    np.testing.assert_allclose(back.weights, anim.weights, atol=1e-7)
    short = tmp_path / "short.csv"
    save_animation(arkit_animation(), short)
    with pytest.raises(TalkmeshError, match="fps"):
        load_arkit_weights(short)
    assert load_arkit_weights(short, fps=30).weights.shape == (T, 52)


def test_timecodes():
    assert arkit_files.timecode(0, 30) == "00:00:00:00.000"
    assert arkit_files.timecode(31, 30) == "00:00:01:01.000"
    assert arkit_files.timecode(30 * 3661 + 29, 30) == "01:01:01:29.000"
    assert arkit_files.timecode(30, 29.97) == "00:00:01:00.030"


def test_json_round_trip(tmp_path):
    anim = arkit_animation()
    (out,) = save_animation(anim, tmp_path / "weights.json")
    doc = json.loads(out.read_text())
    assert set(doc) == {"fps", "names", "frames"}
    assert doc["names"] == list(ARKIT_NAMES) and doc["fps"] == 30.0
    assert np.shape(doc["frames"]) == (T, 52)
    back = load_arkit_weights(out)
    assert back.fps == 30.0
    np.testing.assert_allclose(back.weights, anim.weights, atol=1e-6)


def test_weight_files_use_arkit_order_whatever_the_column_order(tmp_path):
    anim = arkit_animation()
    perm = np.random.default_rng(5).permutation(52)
    shuffled = Animation(
        anim.vertices,
        anim.faces,
        anim.fps,
        weights=anim.weights[:, perm],
        weight_names=[ARKIT_NAMES[i] for i in perm],
    )
    for name in ("w.json", "w.csv"):
        (out,) = save_animation(shuffled, tmp_path / name)
        np.testing.assert_allclose(load_arkit_weights(out, fps=30).weights, anim.weights, atol=1e-6)
    np.testing.assert_array_equal(
        to_arkit_order(shuffled.weights, shuffled.weight_names), anim.weights
    )


@pytest.mark.parametrize("suffix", [".csv", ".json", ".visemes.json"])
def test_weight_formats_need_weights(tmp_path, suffix):
    with pytest.raises(TalkmeshError, match="no ARKit weights") as e:
        save_animation(vertex_animation(), tmp_path / f"talk{suffix}")
    assert str(e.value).startswith(f"talk{suffix}: ")  # not the temporary it was written to
    assert not list(tmp_path.iterdir())


def test_weight_file_plays_on_bundled_head(tmp_path):
    from talkmesh.face.assets import load_head

    (out,) = save_animation(arkit_animation(), tmp_path / "weights.json")
    anim = load_animation(out)
    head = load_head()
    assert anim.vertices.shape == (T, head.num_vertices, 3) and anim.fps == 30.0
    assert anim.weight_names == list(head.blendshape_names)


# --- OBJ sequence ----------------------------------------------------------------------------


def test_obj_sequence(tmp_path):
    anim = vertex_animation()
    written = save_animation(anim, tmp_path / "out" / "talk.obj")
    assert [p.name for p in written] == [f"talk_{t:05d}.obj" for t in range(T)]
    lines = written[7].read_text().splitlines()
    verts = np.array([ln.split()[1:] for ln in lines if ln.startswith("v ")], dtype=np.float32)
    faces = np.array([ln.split()[1:] for ln in lines if ln.startswith("f ")], dtype=np.int32) - 1
    np.testing.assert_allclose(verts, anim.vertices[7], atol=1e-6)
    np.testing.assert_array_equal(faces, anim.faces)


def test_obj_sequence_into_directory(tmp_path):
    written = save_animation(vertex_animation(frames=3), f"{tmp_path}/frames/", format="obj")
    assert [p.name for p in written] == ["frame_00000.obj", "frame_00001.obj", "frame_00002.obj"]
    assert all(p.parent == tmp_path / "frames" for p in written)


# --- safety ----------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".npy", ".npz", ".glb", ".csv", ".json"])
def test_refuses_to_overwrite(tmp_path, suffix):
    path = tmp_path / f"talk{suffix}"
    path.write_bytes(b"precious")
    with pytest.raises(TalkmeshError, match="already exists"):
        save_animation(arkit_animation(), path)
    assert path.read_bytes() == b"precious"
    save_animation(arkit_animation(), path, overwrite=True)
    assert path.read_bytes() != b"precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temp files left


def test_obj_sequence_refuses_to_overwrite_any_frame(tmp_path):
    (tmp_path / "talk_00002.obj").write_text("precious")
    with pytest.raises(TalkmeshError, match="talk_00002.obj already exists"):
        save_animation(vertex_animation(frames=5), tmp_path / "talk.obj")
    assert [p.name for p in tmp_path.iterdir()] == ["talk_00002.obj"]  # nothing half-written


def test_failed_export_leaves_nothing(tmp_path, monkeypatch):
    def broken(anim, path):
        path.write_bytes(b"half a file")
        raise RuntimeError("disk on fire")

    monkeypatch.setitem(formats.EXPORTERS, ".npy", broken)
    with pytest.raises(RuntimeError):
        save_animation(arkit_animation(), tmp_path / "talk.npy")
    assert not list(tmp_path.iterdir())


def test_unknown_extension(tmp_path):
    with pytest.raises(TalkmeshError, match=r"\.fbx.*\.npy, \.npz, \.obj, \.glb"):
        save_animation(arkit_animation(), tmp_path / "talk.fbx")
    (tmp_path / "talk.fbx").write_bytes(b"x")
    with pytest.raises(TalkmeshError, match=r"\.fbx.*\.npy, \.npz, \.glb"):
        load_animation(tmp_path / "talk.fbx")


def _truncated_glb(tmp: Path) -> Path:
    (out,) = save_animation(arkit_animation(), tmp / "full.glb")
    bad = tmp / "bad.glb"
    bad.write_bytes(out.read_bytes()[:1000])
    return bad


def _glb_with_short_bin(tmp: Path) -> Path:
    """Header and chunk lengths consistent, but the accessors point past the binary data."""
    (out,) = save_animation(arkit_animation(), tmp / "full.glb")
    gltf = glb_json(out)
    bad = tmp / "bad.glb"
    bad.write_bytes(glb_bytes(gltf, b"\0" * 64))
    return bad


def _npz(tmp: Path, **arrays) -> Path:
    path = tmp / "bad.npz"
    np.savez(path, **arrays)
    return path


CORRUPT = {
    "missing": lambda tmp: tmp / "nothing.npz",
    "empty glb": lambda tmp: (tmp / "bad.glb", (tmp / "bad.glb").write_bytes(b""))[0],
    "garbage glb": lambda tmp: (tmp / "bad.glb", (tmp / "bad.glb").write_bytes(b"x" * 100))[0],
    "truncated glb": _truncated_glb,
    "glb short bin": _glb_with_short_bin,
    "truncated npz": lambda tmp: (
        tmp / "bad.npz",
        (tmp / "bad.npz").write_bytes(
            save_animation(arkit_animation(), tmp / "ok.npz")[0].read_bytes()[:500]
        ),
    )[0],
    "npz without keys": lambda tmp: _npz(tmp, stuff=np.zeros(3)),
    "npz with pickle": lambda tmp: _npz(
        tmp, vertices=np.zeros((1, 3, 3)), faces=np.array([[0, 1, 2]]), fps=np.array([{}])
    ),
    "npz wrong shape": lambda tmp: _npz(
        tmp, vertices=np.zeros((2, 5)), faces=np.array([[0, 1, 2]]), fps=30.0
    ),
    "npy wrong shape": lambda tmp: (tmp / "bad.npy", np.save(tmp / "bad.npy", np.zeros((4, 7))))[0],
    "npy text": lambda tmp: (tmp / "bad.npy", (tmp / "bad.npy").write_text("hello"))[0],
    "json garbage": lambda tmp: (tmp / "bad.json", (tmp / "bad.json").write_text("{nope"))[0],
    "json wrong": lambda tmp: (
        tmp / "bad.json",
        (tmp / "bad.json").write_text('{"fps": 30, "names": ["jawOpen"], "frames": [[0.5]]}'),
    )[0],
    "csv missing columns": lambda tmp: (
        tmp / "bad.csv",
        (tmp / "bad.csv").write_text("Timecode,BlendShapeCount,JawOpen\n00:00:00:00.000,61,0.5\n"),
    )[0],
}


@pytest.mark.parametrize("make", CORRUPT.values(), ids=CORRUPT.keys())
def test_corrupt_files_give_one_line_errors(tmp_path, make):
    path = make(tmp_path)
    with pytest.raises(TalkmeshError) as info:
        load_animation(path, faces=np.array([[0, 1, 2]]), fps=30)
    message = str(info.value)
    assert path.name in message and "\n" not in message, message


def test_live_link_columns_are_61():
    assert len(LIVE_LINK_COLUMNS) == 61 and LIVE_LINK_COLUMNS[0] == "EyeBlinkLeft"
