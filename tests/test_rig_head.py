"""`talkmesh animate --head`: a model's motion of the bundled head carried onto a plain head mesh
(here the bundled head remeshed coarser, in millimetres, Z-up), end to end through the CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from talkmesh.cli import main
from talkmesh.cli.common import load_input
from talkmesh.face.assets import load_head
from talkmesh.face.registration import closest_points, vertex_normals
from talkmesh.face.rig_files import load_rig

CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)
pytestmark = pytest.mark.skipif(not CLIP.exists(), reason="pocketsphinx-testdata not installed")
TURN = trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0])[:3, :3]  # a Z-up export
SHIFT = np.array([3.0, -20.0, 100.0])  # millimetres


@pytest.fixture(scope="module")
def user(tmp_path_factory):
    """The bundled head decimated to half its triangles, in mm, Z-up, shifted: (path, vertices
    and faces in metres on the bundled axes, the closest point on the bundled head of each)."""
    fast_simplification = pytest.importorskip("fast_simplification")
    head = load_head()
    v, f = fast_simplification.simplify(
        head.template.astype(np.float32), head.faces.astype(np.int64), target_reduction=0.5
    )
    v = v.astype(np.float64)
    face, bary, _ = closest_points(
        v, head.template.astype(np.float64), head.faces, vertex_normals(v, f)
    )
    path = tmp_path_factory.mktemp("head") / "me.obj"
    trimesh.Trimesh(1000 * v @ TURN.T + SHIFT, f, process=False).export(path)
    return path, v, head.faces[face], bary


def _true(user, source: np.ndarray) -> np.ndarray:
    """(T, V, 3) the source frames (bundled topology, metres) at the user's vertices, in mm Z-up."""
    _, _, corners, bary = user
    return 1000 * np.einsum("vc,tvcx->tvx", bary, source[:, corners]) @ TURN.T + SHIFT


def _lip_gaps(frames: np.ndarray, pair) -> np.ndarray:
    return np.linalg.norm(frames[:, pair[0]] - frames[:, pair[1]], axis=1)


@pytest.mark.slow  # ~2 min: a registration, two animations and a video
def test_procedural_motion_on_a_coarser_head_in_mm(user, tmp_path, capsys):
    """Frames = audio length x fps; the carried motion is the source's at each vertex's closest
    point; the lips open and close where the source's do; the video is written."""
    speech = tmp_path / "speech.wav"
    speech.write_bytes(CLIP.read_bytes())
    src, out, video = tmp_path / "src.npz", tmp_path / "me.npz", tmp_path / "me.mp4"
    assert main(["animate", str(speech), "-o", str(src), "-q"]) == 0
    argv = ["animate", str(speech), "--head", str(user[0]), "-o", str(out), "-o", str(video)]
    assert main(argv) == 0
    assert "units mm, up -z" in capsys.readouterr().out
    source, carried = load_input(str(src), None), load_input(str(out), None)
    assert carried.num_frames == source.num_frames == 90  # 3.0 s at 30 fps
    assert carried.num_vertices == len(user[1]) and video.stat().st_size > 0
    # where the source moves (over 1 mm), the carried motion is the source's at each vertex's
    # closest point: measured 0.10 mm off for 3.2 mm of motion
    head = load_head()
    truth, rest = _true(user, source.vertices), _true(user, head.template[None])[0]
    moving = np.linalg.norm(truth - rest, axis=2) > 1.0
    error = np.linalg.norm(carried.vertices - truth, axis=2)[moving].mean()
    assert error < 0.1 * np.linalg.norm(truth - rest, axis=2)[moving].mean(), error
    # the lips open and close where the source's do: the gap between the user's lip landmarks is
    # the true one there (measured within 0.1 mm), and back at rest where the source's is
    rig = load_rig(user[0])  # the registration the CLI made (cached)
    pair = [rig.landmarks["upper_lip"], rig.landmarks["lower_lip"]]
    ours, true_gap = _lip_gaps(carried.vertices, pair), _lip_gaps(truth, pair)
    theirs = 1000 * _lip_gaps(source.vertices, head.regions.lip_pair)
    assert theirs.min() < 1.0 and theirs.max() > 10.0  # the source closes and opens
    assert np.abs(ours - true_gap).max() < 0.5, np.abs(ours - true_gap).max()
    closed = theirs < theirs[0] + 0.2  # the first frame is silence: lips at rest
    assert (ours[closed] < ours[0] + 0.5).all() and (ours[~closed] > ours[0]).any()


@pytest.mark.slow  # the registration, when run alone
def test_a_vertex_model_moves_the_head_through_the_correspondence(user, tmp_path, tiny_codetalker):
    from talkmesh.models.release import save_model

    head = load_head()
    model = save_model(
        tiny_codetalker(num_vertices=head.num_vertices), tmp_path / "tiny.safetensors"
    )
    speech = tmp_path / "speech.wav"
    speech.write_bytes(CLIP.read_bytes())
    src, out = tmp_path / "src.npz", tmp_path / "me.npz"
    common = ["animate", str(speech), "--model", str(model), "-q"]
    assert main([*common, "-o", str(src)]) == 0
    assert main([*common, "--head", str(user[0]), "-o", str(out)]) == 0
    source, carried = load_input(str(src), None), load_input(str(out), None)
    assert carried.num_frames == source.num_frames == round(3.0 * source.fps)
    # every frame is the user's mesh plus the model's offsets carried through the registration
    rig = load_rig(user[0])
    expected = rig.carry(source.vertices - head.template)
    moved = carried.vertices - rig.vertices
    assert np.abs(expected).max() > 1.0  # it moves (mm)
    # .npz keeps offsets as float16: equal to 1e-3 of the largest
    np.testing.assert_allclose(moved, expected, atol=1e-3 * np.abs(expected).max())


def test_a_mesh_that_is_no_head_is_one_error(tmp_path, capsys):
    box = trimesh.creation.box((0.3, 0.02, 0.4))
    box = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(box.vertices, box.faces, 0.02))
    box.export(tmp_path / "box.obj")
    speech = tmp_path / "speech.wav"
    speech.write_bytes(CLIP.read_bytes())
    rc = main(
        ["animate", str(speech), "--head", str(tmp_path / "box.obj"), "-o", str(tmp_path / "a.npz")]
    )
    err = capsys.readouterr().err
    assert rc == 2 and "does not look like a head" in err and "box.obj" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "a.npz").exists()
