"""ARKit weights solved from another topology's vertex motion (talkmesh.face.solve): the bounded
least-squares solve on small known cases, and ``animate --template`` of another topology with
.csv, .json and --avatar outputs instead of a refusal."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import trimesh
from avatars import make_avatar
from test_templates import FIXTURES, VOCASET_SUBJECTS, imported, vocaset_layout

from talkmesh.cli import main
from talkmesh.errors import TalkmeshError
from talkmesh.face import rig_files
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import load_head
from talkmesh.face.rig import Rig
from talkmesh.face.solve import ArkitSolver, Residual, solver_for_mesh
from talkmesh.output.avatar import read_glb

UPPER, LOWER = 474, 523  # the bundled head's midline lip pair
JAW, CLOSE = ARKIT_NAMES.index("jawOpen"), ARKIT_NAMES.index("mouthClose")


def bundled(frames: int = 60, seed: int = 0, **options) -> tuple[ArkitSolver, np.ndarray]:
    """A solver with the bundled shapes on a third of the bundled head's vertices (the lip pair
    among them), and smooth true weights in [0, 1] (T, 52)."""
    head = load_head()
    keep = np.unique(np.r_[np.arange(0, head.num_vertices, 3), UPPER, LOWER])
    pair = (int(np.searchsorted(keep, UPPER)), int(np.searchsorted(keep, LOWER)))
    solver = ArkitSolver(head.template[keep], head.blendshapes[:, keep], pair, **options)
    t = np.arange(frames)[:, None] / 30.0
    phase = np.random.default_rng(seed).uniform(0, 2 * np.pi, 52)
    truth = 0.5 + 0.5 * np.sin(2 * np.pi * 1.5 * t + phase)
    truth[:, np.random.default_rng(seed + 1).random(52) < 0.3] = 0.0  # unused channels
    return solver, truth.astype(np.float32)


def test_weights_of_motion_the_shapes_make_are_solved_back():
    solver, truth = bundled()
    offsets = np.einsum("tk,kvx->tvx", truth, solver.blendshapes)
    solved = solver.solve(offsets)
    assert solved.weights.shape == truth.shape and solved.weights.dtype == np.float32
    assert solved.weights.min() >= 0 and solved.weights.max() <= 1
    assert np.abs(solved.weights - truth).mean() < 0.01
    assert np.abs(solved.weights - truth).mean(0).max() < 0.05  # every channel
    assert solved.residual < 1e-3


def test_bounds_hold_and_the_residual_is_the_share_the_shapes_miss():
    # without the lip term: the motion outside the shapes moves the lip pair too, which that
    # term would follow on purpose (test_lip_closure_is_kept...)
    solver, truth = bundled(frames=20, lips=0.0)
    shapes = solver.blendshapes.astype(np.float64)
    inside = np.einsum("tk,kvx->tvx", 3.0 * truth, shapes)  # weights up to 3: clipped to 1
    solved = solver.solve(inside)
    assert solved.weights.max() <= 1 and solved.weights.min() >= 0
    # motion orthogonal to every shape: the solve cannot express it, the residual says how much
    basis = shapes.reshape(52, -1)
    noise = np.random.default_rng(2).normal(size=(len(truth), basis.shape[1]))
    q, _ = np.linalg.qr(basis.T)
    outside = (noise - (noise @ q) @ q.T).reshape(len(truth), -1, 3)
    outside *= 0.5 * np.linalg.norm(inside) / np.linalg.norm(outside)  # a fifth of the motion
    mixed = np.einsum("tk,kvx->tvx", truth, shapes)
    mixed_outside = mixed + outside * np.linalg.norm(mixed) / np.linalg.norm(inside)
    solved = solver.solve(mixed_outside)
    share = np.sum(outside**2) * (np.linalg.norm(mixed) / np.linalg.norm(inside)) ** 2
    share /= np.sum(mixed_outside**2)
    assert solved.residual == pytest.approx(share, rel=0.05)
    assert np.abs(solved.weights - truth).mean() < 0.02


def test_lip_closure_is_kept_where_the_motion_closes_the_lips():
    """Shut lips (jaw open, lips closed by mouthClose) with a disturbance: the lip term keeps
    the pair's gap, which a plain fit spreads away."""
    rng = np.random.default_rng(3)
    solver, truth = bundled(frames=30)
    plain = ArkitSolver(solver.template, solver.blendshapes, solver.lip_pair, lips=0.0)
    truth[:, JAW] = truth[:, CLOSE] = 0.4
    shapes = solver.blendshapes.astype(np.float64)
    offsets = np.einsum("tk,kvx->tvx", truth, shapes)
    offsets += rng.normal(0, 0.3 * np.abs(offsets).mean(), offsets.shape)
    upper, lower = solver.lip_pair

    def gap_error(weights):
        moved = solver.template + np.einsum("tk,kvx->tvx", weights.astype(np.float64), shapes)
        real = solver.template + offsets
        solved = np.linalg.norm(moved[:, upper] - moved[:, lower], axis=1)
        return np.abs(solved - np.linalg.norm(real[:, upper] - real[:, lower], axis=1)).max()

    assert gap_error(solver.solve(offsets).weights) < 0.5 * gap_error(plain.solve(offsets).weights)


def test_smoothness_and_blocks_continue_one_another():
    """Jittered motion comes out smoother with the smoothness term; a clip solved in blocks
    (each continuing the last) is close to the clip solved whole."""
    solver, truth = bundled(frames=60)
    rough = ArkitSolver(solver.template, solver.blendshapes, solver.lip_pair, smooth=0.0)
    offsets = np.einsum("tk,kvx->tvx", truth, solver.blendshapes.astype(np.float64))
    offsets += np.random.default_rng(4).normal(0, 2e-4, offsets.shape)

    def jitter(w):
        return np.abs(np.diff(w, 2, axis=0)).mean()

    whole = solver.solve(offsets).weights
    assert jitter(whole) < jitter(rough.solve(offsets).weights)
    first = solver.solve(offsets[:30])
    second = solver.solve(offsets[30:], first.weights[-1])
    pieces = np.concatenate([first.weights, second.weights])
    assert np.abs(pieces - whole).max() < 0.05


def test_blocks_get_weights_and_the_residual_adds_up():
    from talkmesh.animation import Animation, AnimationBlocks

    solver, truth = bundled(frames=40)
    verts = solver.template + np.einsum("tk,kvx->tvx", truth, solver.blendshapes)
    faces = np.zeros((0, 3), np.int32)
    pose = np.random.default_rng(0).uniform(-0.1, 0.1, (40, 6)).astype(np.float32)
    anim = AnimationBlocks(
        blocks=(
            Animation(verts[a : a + 16], faces, 30.0, head_pose=pose[a : a + 16])
            for a in range(0, 40, 16)
        ),
        num_frames=40,
        faces=faces,
        fps=30.0,
        template=solver.template,
        phones=[("M", 0.0, 0.1)],
    )
    residual = Residual()
    solved = solver.solve_blocks(anim, residual)
    assert solved.phones == anim.phones and solved.template is anim.template
    blocks = list(solved.blocks)
    weights = np.concatenate([b.weights for b in blocks])
    assert weights.shape == (40, 52) and blocks[0].weight_names == list(ARKIT_NAMES)
    # the rest of each block as the model made it: its vertices and its head's motion
    np.testing.assert_array_equal(np.concatenate([b.head_pose for b in blocks]), pose)
    np.testing.assert_array_equal(np.concatenate([b.vertices for b in blocks]), verts)
    assert np.abs(weights - truth).mean() < 0.01
    assert 0 <= residual.share < 1e-3 and residual.total > 0


def test_a_topology_that_cannot_be_rigged_is_one_line():
    v, f = trimesh.creation.icosphere(2).vertices, trimesh.creation.icosphere(2).faces
    with pytest.raises(TalkmeshError, match="cannot be rigged onto it") as e:
        solver_for_mesh(v, f, "ball.obj")
    assert "\n" not in str(e.value) and "ball.obj" in str(e.value)
    with pytest.raises(TalkmeshError, match="need its triangles"):
        solver_for_mesh(v, np.zeros((0, 3), np.int64), "points.npy")


def fake_rig(vertices, faces, size: float = 0.002) -> Rig:
    """A rig of the small meshes the fixture models move: every shape a smooth field of about
    ``size`` (the registration itself is tested in test_rig.py; here the wiring)."""
    v = np.asarray(vertices, np.float32)
    rng = np.random.default_rng(0)
    shapes = rng.normal(0, size, (52, 1, 3)) * (1 + v[None, :, :1]) + rng.normal(
        0, size / 2, (52, len(v), 3)
    )
    return Rig(
        v,
        np.asarray(faces, np.int32),
        shapes.astype(np.float32),
        1.0,
        np.eye(3),
        np.zeros(3),
        0.0,
        landmarks={"upper_lip": 13, "lower_lip": 9},
    )


def test_cli_template_of_another_topology_writes_csv_json_and_the_avatar(
    tmp_path, capsys, monkeypatch
):
    """Was refused ("ARKit weights need the bundled head's topology"): now the weights are
    solved from the model's motion of its own 24-vertex face."""
    monkeypatch.setattr(rig_files, "rig_mesh", fake_rig)
    root = vocaset_layout(tmp_path / "vocaset", 6, 4)
    model = imported(tmp_path, "faceformer", "vocaset")
    avatar = make_avatar(tmp_path / "me.glb")
    outs = [tmp_path / n for n in ("talk.csv", "talk.json", "talk.glb", "talk.npz")]
    argv = ["animate", str(FIXTURES / "speech.wav"), "--model", str(model), "--avatar", str(avatar)]
    argv += ["--template", str(root / "templates.pkl"), "--style", f"{VOCASET_SUBJECTS[0]}:1"]
    assert main(argv + [a for p in outs for a in ("-o", str(p))]) == 0
    out = capsys.readouterr().out
    assert "ARKit weights solved from the model's motion" in out
    assert "% of the motion)" in out and "ARKit weights miss" in out  # the residual share
    with open(outs[0], newline="") as f:
        rows = list(csv.reader(f))
    frames = json.loads(outs[1].read_text())["frames"]
    assert len(rows) == 1 + len(frames) and len(frames) > 10
    weights = np.asarray(frames, np.float32)
    assert weights.shape[1] == 52 and weights.min() >= 0 and weights.max() <= 1
    assert weights.std(0).max() > 0  # the motion moves them
    gltf, _ = read_glb(outs[2])
    assert gltf["animations"][0]["name"] == "talk"  # a copy of the avatar, the speech first


@pytest.mark.slow  # a registration (~30 s) and a tiny model on 2398 vertices
def test_cli_tiny_model_on_a_remeshed_head_drives_an_avatar(tmp_path, capsys, monkeypatch):
    import fast_simplification
    import torch

    from talkmesh.models.faceformer.model import FaceFormer
    from talkmesh.models.release import save_model

    monkeypatch.setenv("TALKMESH_CACHE", str(tmp_path / "cache"))
    head = load_head()
    v, f = fast_simplification.simplify(head.template, head.faces.astype(np.int64), 0.5)
    trimesh.Trimesh(1000 * v, f, process=False).export(tmp_path / "mine.obj")  # millimetres
    torch.manual_seed(0)
    net = FaceFormer(FaceFormer.tiny_config(len(v)))
    torch.nn.init.normal_(net.out.weight, std=0.01)
    save_model(net, tmp_path / "mine.safetensors")
    avatar = make_avatar(tmp_path / "me.vrm", vrm=True)
    argv = ["animate", str(FIXTURES / "speech.wav"), "--model", str(tmp_path / "mine.safetensors")]
    argv += ["--template", str(tmp_path / "mine.obj"), "--avatar", str(avatar)]
    argv += ["-o", str(tmp_path / "talk.vrm"), "-o", str(tmp_path / "talk.csv")]
    assert main(argv) == 0
    assert "ARKit weights solved" in capsys.readouterr().out
    assert list((tmp_path / "cache" / "rigs").glob("*.npz"))  # the registration is saved
    gltf, _ = read_glb(tmp_path / "talk.vrm")
    assert [a["name"] for a in gltf["animations"]][0] == "talk"


def test_a_model_stream_of_another_topology_gets_solved_arkit_weights(
    monkeypatch, tiny_stream_model
):
    """The stream's ARKit channel on a model's own topology (was refused: "the face's blendshapes
    are not the 52 ARKit shapes"): chunk by chunk, the weights of the solve on the whole clip."""
    from talkmesh.face.assets import plain_head
    from talkmesh.serve.stream import open_stream, push_together

    # the untrained tiny model moves its face by about 0.5: shapes of that size
    monkeypatch.setattr(rig_files, "rig_mesh", lambda v, f: fake_rig(v, f, size=0.3))
    rng = np.random.default_rng(0)
    v = rng.normal(0, 0.05, (20, 3))
    head = plain_head(v, np.array([[0, 1, 2], [2, 3, 4]]), "mine")
    path = tiny_stream_model()
    audio = rng.normal(0, 0.1, 24_000).astype(np.float32)
    stream = open_stream(path, head=head, offsets=True)
    frames = [f for i in range(0, len(audio), 1600) for f in stream.push(audio[i : i + 1600])]
    frames += stream.flush()
    weights = np.stack([f.weights for f in frames])
    offsets = np.stack([f.offsets for f in frames])
    assert weights.shape == (len(frames), 52) and weights.min() >= 0 and weights.max() <= 1
    assert weights.std(0).max() > 0
    whole = solver_for_mesh(v, head.faces).solve(offsets).weights
    assert np.abs(weights - whole).max() < 0.05  # chunks continue one another
    together = push_together([(open_stream(path, head=head), [audio], True)])[0]
    np.testing.assert_allclose(np.stack([f.weights for f in together]), whole, atol=0.05)
    with pytest.raises(TalkmeshError, match="procedural animator streams the bundled head"):
        open_stream("procedural", head=head)
