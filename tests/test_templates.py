"""``animate --template`` on the topologies of the released datasets, in the layouts they ship
(VOCASET: templates.pkl + FLAME_sample.ply; BIWI: BIWI.ply, .vl frames, rigid-scan .obj), with
synthetic geometry, end to end with the imported official fixture models."""

from __future__ import annotations

import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest

from talkmesh.cli import main
from talkmesh.datasets.biwi import surface_area
from talkmesh.datasets.templates import load_face_template, read_face_template
from talkmesh.errors import TalkmeshError
from talkmesh.output.formats import load_animation

torch = pytest.importorskip("torch")
pytest.importorskip("transformers")
trimesh = pytest.importorskip("trimesh")

FIXTURES = Path(__file__).parent / "fixtures" / "official"
VOCASET_SUBJECTS = ("FaceTalk_170728_03272_TA", "FaceTalk_170809_00138_TA")
BIWI_SUBJECTS = ("F2", "M3")


def grid(rows: int, cols: int, size: float = 0.1, extra: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A curved rows x cols sheet facing +z and ``extra`` loose vertices behind it:
    (rows*cols + extra, 3) vertices, (F, 3) triangles."""
    y, x = np.meshgrid(
        np.linspace(-size, size, rows), np.linspace(-size, size, cols), indexing="ij"
    )
    z = 0.5 * size - (x**2 + y**2) / size
    vertices = np.stack([x, y, z], -1).reshape(-1, 3)
    i = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = i[:-1, :-1], i[:-1, 1:], i[1:, :-1], i[1:, 1:]
    faces = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)]).reshape(-1, 3)
    loose = np.zeros((extra, 3)) - np.array([0.0, 0.0, size])
    return np.concatenate([vertices, loose]), faces


def write_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return path


def write_templates(path: Path, templates: dict[str, np.ndarray]) -> Path:
    with open(path, "wb") as f:  # protocol 2, as the datasets' Python-2 pickles
        pickle.dump({k: np.asarray(v, np.float64) for k, v in templates.items()}, f, protocol=2)
    return path


def write_vl(path: Path, vertices: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    data = np.asarray(vertices, "<f4")
    path.write_bytes(np.uint32(len(data)).tobytes() + data.tobytes())
    return path


def vocaset_layout(root: Path, rows: int, cols: int, extra: int = 0) -> Path:
    """root/templates.pkl (two subjects) + root/FLAME_sample.ply, as VOCASET ships them."""
    root.mkdir(parents=True, exist_ok=True)
    vertices, faces = grid(rows, cols, extra=extra)
    write_mesh(root / "FLAME_sample.ply", vertices, faces)
    rng = np.random.default_rng(0)
    write_templates(
        root / "templates.pkl",
        {s: vertices + rng.normal(0, 0.002, vertices.shape) for s in VOCASET_SUBJECTS},
    )
    return root


def biwi_layout(root: Path, rows: int, cols: int) -> Path:
    """CodeTalker's BIWI folder (templates.pkl, BIWI.ply, normalised) and BIWI's release files
    (faces/F2/e01/frame_001.vl, rigid_scans/F2.obj, in a scanner frame of millimetres)."""
    root.mkdir(parents=True, exist_ok=True)
    vertices, faces = grid(rows, cols)
    unit = vertices / np.sqrt(surface_area(vertices, faces))  # prepared: unit area
    write_mesh(root / "BIWI.ply", unit, faces)
    write_templates(root / "templates.pkl", {s: unit for s in BIWI_SUBJECTS})
    raw = vertices * np.array([1.0, -1.0, -1.0]) * 1000.0 + np.array([5.0, 20.0, 900.0])
    write_vl(root / "faces" / "F2" / "e01" / "frame_001.vl", raw)
    (root / "rigid_scans").mkdir()
    write_mesh(root / "rigid_scans" / "F2.obj", raw, faces)
    return root


def test_vocaset_templates_pkl_with_the_plys_triangles(tmp_path):
    root = vocaset_layout(tmp_path / "vocaset", 81, 62, 1)  # FLAME's 5023 vertices
    faces = trimesh.load(root / "FLAME_sample.ply", process=False).faces
    head = load_face_template(f"{root}/templates.pkl:{VOCASET_SUBJECTS[1]}")
    assert head.num_vertices == 5023 and not head.rigged and head.name == VOCASET_SUBJECTS[1]
    assert np.array_equal(head.faces, faces)
    with open(root / "templates.pkl", "rb") as f:
        want = pickle.load(f)[VOCASET_SUBJECTS[1]]
    np.testing.assert_allclose(head.template, want, atol=1e-6)
    # the subject --style names alone; a .ply as the template itself; its .npy beside the .ply
    assert (
        load_face_template(root / "templates.pkl", VOCASET_SUBJECTS[0]).name == VOCASET_SUBJECTS[0]
    )
    assert load_face_template(root / "FLAME_sample.ply").num_vertices == 5023
    np.save(root / "mine.npy", want.reshape(-1))
    assert np.array_equal(load_face_template(root / "mine.npy").faces, faces)
    # FaceFormer's layout: VOCASET/templates.pkl and VOCASET/templates/FLAME_sample.ply
    ff = tmp_path / "VOCASET"
    (ff / "templates").mkdir(parents=True)
    shutil.copy(root / "templates.pkl", ff)
    shutil.copy(root / "FLAME_sample.ply", ff / "templates")
    assert np.array_equal(
        load_face_template(f"{ff}/templates.pkl:{VOCASET_SUBJECTS[0]}").faces, faces
    )
    with pytest.raises(TalkmeshError, match="holds 2 subjects.*templates.pkl:SUBJECT"):
        load_face_template(root / "templates.pkl")
    with pytest.raises(TalkmeshError, match="no template of F9"):
        load_face_template(f"{root}/templates.pkl:F9")


def test_biwi_release_files_are_normalised_as_prepare_biwi_does(tmp_path):
    root = biwi_layout(tmp_path / "biwi", 123, 190)  # BIWI's 23370 vertices
    prepared = load_face_template(f"{root}/templates.pkl:F2")
    assert prepared.num_vertices == 23370
    assert surface_area(prepared.template, prepared.faces) == pytest.approx(1.0, rel=1e-4)
    vl = root / "faces" / "F2" / "e01" / "frame_001.vl"
    write_mesh(vl.parent / "BIWI.ply", *grid(123, 190))  # the triangles beside the frame
    for spec in (vl, root / "rigid_scans" / "F2.obj"):
        head = load_face_template(spec)
        # rotated by pi about x, centred, unit area: the prepared template up to its centroid
        assert surface_area(head.template, head.faces) == pytest.approx(1.0, rel=1e-4)
        np.testing.assert_allclose(
            head.template, prepared.template - prepared.template.mean(0), atol=1e-5
        )


def test_a_biwi_mesh_is_normalised_only_when_known_raw_or_asked(tmp_path):
    """BIWI's raw files (.vl, rigid_scans/*.obj) are normalised, and said so; another BIWI-
    topology mesh whose area is not 1 (a frame of the user's own) is taken as it is, unless
    asked."""
    vertices, faces = grid(123, 190)
    mine = write_mesh(tmp_path / "mine.ply", vertices * 3.0, faces)
    face, note = read_face_template(mine)
    assert note == ""
    np.testing.assert_allclose(face.template, vertices * 3.0, atol=1e-5)
    face, note = read_face_template(mine, normalize=True)
    assert note.startswith("normalised as prepare-biwi does")
    assert surface_area(face.template, face.faces) == pytest.approx(1.0, rel=1e-4)
    root = biwi_layout(tmp_path / "biwi", 123, 190)
    assert read_face_template(root / "rigid_scans" / "F2.obj").note.startswith("normalised")
    assert read_face_template(f"{root}/templates.pkl:F2").note == ""  # already unit area
    with pytest.raises(TalkmeshError, match="applies to BIWI's 23370-vertex meshes"):
        read_face_template(write_mesh(tmp_path / "small.ply", *grid(6, 4)), normalize=True)


def test_a_vertex_file_without_triangles_beside_it_is_refused(tmp_path):
    write_vl(tmp_path / "frame_001.vl", grid(6, 4)[0])
    with pytest.raises(TalkmeshError, match="no triangles: put the topology's mesh beside it"):
        load_face_template(tmp_path / "frame_001.vl")


def test_vertex_outputs_need_no_triangles(tmp_path, capsys):
    """A vertex file alone (no mesh beside it) animates into .npy; a surface output asks for the
    triangles."""
    vertices = grid(6, 4)[0]
    alone = tmp_path / "alone"
    alone.mkdir()
    np.save(alone / "face.npy", vertices)
    head = load_face_template(alone / "face.npy", triangles=False)
    assert head.num_vertices == 24 and head.faces.shape == (0, 3)
    model = imported(tmp_path, "faceformer", "vocaset")
    argv = ["animate", str(FIXTURES / "speech.wav"), "--model", str(model)]
    argv += ["--template", str(alone / "face.npy"), "--style", f"{VOCASET_SUBJECTS[0]}:1", "-q"]
    assert main([*argv, "-o", str(tmp_path / "out.npy"), "-o", str(tmp_path / "out.npz")]) == 0
    out = np.load(tmp_path / "out.npy")
    assert out.shape[1] == 24 * 3 and np.isfinite(out).all()
    stored = load_animation(tmp_path / "out.npz")
    assert stored.faces.shape == (0, 3)  # float16 offsets: within their rounding
    np.testing.assert_allclose(stored.vertices, out.reshape(-1, 24, 3), atol=1e-3)
    capsys.readouterr()
    assert main([*argv, "-o", str(tmp_path / "out.glb")]) == 2
    assert "no triangles" in capsys.readouterr().err
    assert not (tmp_path / "out.glb").exists()


def imported(tmp_path: Path, family: str, dataset: str) -> Path:
    files = {
        "faceformer": [f"faceformer_{dataset}.pth"],
        "codetalker": [f"codetalker_{dataset}_stage{n}.pth.tar" for n in (1, 2)],
    }[family]
    out = tmp_path / f"{family}_{dataset}.safetensors"
    args = [str(FIXTURES / f) for f in files]
    assert (
        main(
            [
                "import-checkpoint",
                *args,
                "--family",
                family,
                "--dataset",
                dataset,
                "-o",
                str(out),
                "-q",
            ]
        )
        == 0
    )
    return out


def test_animate_an_imported_vocaset_model_on_templates_pkl(tmp_path, capsys):
    """The official fixture models animate 24 vertices: the VOCASET layout at that size."""
    from talkmesh.models.release import load_model

    root = vocaset_layout(tmp_path / "vocaset", 6, 4)
    model = imported(tmp_path, "faceformer", "vocaset")
    subject = VOCASET_SUBJECTS[0]
    outs = [tmp_path / f"talk.{ext}" for ext in ("npz", "glb", "obj", "npy", "mp4")]
    argv = ["animate", str(FIXTURES / "speech.wav"), "--model", str(model)]
    argv += ["--template", str(root / "templates.pkl"), "--style", f"{subject}:1", "-q"]
    assert main(argv + [a for p in outs for a in ("-o", str(p))]) == 0
    anim = load_animation(outs[0])
    assert anim.fps == 30  # the model's own frame rate
    net = load_model(model)
    head = load_face_template(f"{root}/templates.pkl:{subject}")
    with torch.inference_mode():
        want = net.generate(
            torch.from_numpy(np.asarray(anim.audio))[None],
            torch.from_numpy(head.template)[None],
            styles=torch.tensor([net.styles.index(subject)]),
        )[0].numpy()
    faces = trimesh.load(root / "FLAME_sample.ply", process=False).faces
    exact = load_animation(outs[3], faces=faces, fps=30).vertices  # .npy: float32 vertices
    np.testing.assert_allclose(exact, want, atol=1e-5)  # the model's motion as it is
    # .npz: float16 offsets from the template, within float16's rounding of the largest offset
    assert np.abs(anim.vertices - want).max() <= 2**-11 * np.abs(want - head.template).max()
    glb = load_animation(outs[1])
    assert np.array_equal(glb.faces, faces) and glb.num_frames == anim.num_frames
    np.testing.assert_allclose(glb.vertices, exact, atol=2e-4)
    first = trimesh.load(tmp_path / "talk_00000.obj", process=False)
    assert np.array_equal(first.faces, faces)
    np.testing.assert_allclose(first.vertices, exact[0], atol=1e-5)
    assert outs[4].stat().st_size > 1000
    # ARKit weights are solved through the 52 shapes rigged onto the topology (test_solve.py):
    # a sheet of 24 vertices cannot be rigged, which is one line before the model runs
    assert main(argv + ["-o", str(tmp_path / "w.csv")]) == 2
    assert "cannot be rigged onto it" in capsys.readouterr().err
    assert not (tmp_path / "w.csv").exists()


def test_animate_an_imported_biwi_model_at_its_own_rate_unless_fps(tmp_path, capsys):
    root = biwi_layout(tmp_path / "biwi", 6, 4)
    vl = root / "faces" / "F2" / "e01" / "frame_001.vl"
    write_mesh(vl.parent / "BIWI.ply", *grid(6, 4))  # its triangles beside the frame
    model = imported(tmp_path, "codetalker", "biwi")
    argv = ["animate", str(FIXTURES / "speech.wav"), "--model", str(model), "--style", "M3:1"]
    assert main([*argv, "--template", str(vl), "-o", str(tmp_path / "a.npz")]) == 0
    assert "24 vertices, 30 triangles (not the bundled topology" in capsys.readouterr().out
    own = load_animation(tmp_path / "a.npz")
    assert own.fps == 25
    assert (
        main(
            [
                *argv,
                "--template",
                str(root / "BIWI.ply"),
                "--fps",
                "30",
                "-o",
                str(tmp_path / "b.npz"),
                "-q",
            ]
        )
        == 0
    )
    resampled = load_animation(tmp_path / "b.npz")
    assert resampled.fps == 30 and resampled.num_frames == round(len(own.audio) / 16000 * 30)


def test_real_vertex_counts_render_and_export(tmp_path):
    """FLAME's 5023 and BIWI's 23370 vertices through animate, the .glb exporter and the video
    renderer (a tiny talkmesh model of each topology; the imported fixtures have 24)."""
    from talkmesh.models.faceformer.model import FaceFormer
    from talkmesh.models.release import save_model
    from talkmesh.output import write_animation
    from talkmesh.pipeline import animate

    audio = np.random.default_rng(0).normal(0, 0.1, 8000).astype(np.float32)
    vocaset = vocaset_layout(tmp_path / "vocaset", 81, 62, extra=1)  # 5023 vertices
    biwi = biwi_layout(tmp_path / "biwi", 123, 190)  # 23370
    vl = biwi / "faces" / "F2" / "e01" / "frame_001.vl"
    write_mesh(vl.parent / "BIWI.ply", *grid(123, 190))
    for name, spec in (("flame", f"{vocaset}/templates.pkl:{VOCASET_SUBJECTS[0]}"), ("biwi", vl)):
        head = load_face_template(spec)
        torch.manual_seed(0)
        net = FaceFormer(FaceFormer.tiny_config(head.num_vertices))
        torch.nn.init.normal_(net.out.weight, std=0.01)
        save_model(net, tmp_path / f"{name}.safetensors")
        anim = animate(audio, head=head, model=str(tmp_path / f"{name}.safetensors"))
        assert anim.vertices.shape[1] == head.num_vertices and anim.weights is None
        assert np.abs(anim.vertices - head.template).max() > 0
        write_animation(anim, tmp_path / f"{name}.glb", overwrite=False)
        back = load_animation(tmp_path / f"{name}.glb")
        assert np.array_equal(back.faces, head.faces)
        np.testing.assert_allclose(back.vertices, anim.vertices, atol=2e-4)
        write_animation(anim, tmp_path / f"{name}.mp4", overwrite=False, size=64)
        assert (tmp_path / f"{name}.mp4").stat().st_size > 1000
