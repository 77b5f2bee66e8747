"""Saved registrations (talkmesh.face.rig_cache): `talkmesh animate --head` registers a mesh file
once; a later run on the same bytes reads the correspondence back and gives the same frames; an
edited mesh is registered again; a damaged or mismatched saved file is one warning, never a
traceback, and is replaced."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from talkmesh.cli import main
from talkmesh.cli.common import load_input
from talkmesh.errors import TalkmeshWarning
from talkmesh.face import rig_cache
from talkmesh.face import rig_files as rig_module
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import load_head

CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)


@pytest.fixture
def mesh(tmp_path):
    """The bundled head in millimetres, as a user's OBJ file."""
    head = load_head()
    path = tmp_path / "me.obj"
    trimesh.Trimesh(1000 * head.template, head.faces, process=False).export(path)
    return path


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A cache folder of the test's own; no registration held in the process from before."""
    monkeypatch.setenv(rig_cache.CACHE_ENV, str(tmp_path / "cache"))
    rig_module._rig_file.cache_clear()
    yield tmp_path / "cache"
    rig_module._rig_file.cache_clear()


def _fake_registration(vertices, faces, head=None, **_):
    """The bundled head in mm registered to itself, without the minute of fitting: every vertex
    is its own corresponding point."""
    head = head or load_head()
    n = len(vertices)
    return rig_module._closest_rig(
        vertices,
        faces,
        head,
        scale=1000.0,
        rotation=np.eye(3),
        translation=np.zeros(3),
        residual=0.0,
        corners=np.repeat(np.arange(n)[:, None], 3, axis=1),
        weights=np.tile([1.0, 0.0, 0.0], (n, 1)),
        landmarks={"upper_lip": int(head.regions.lip_pair[0]), "lower_lip": 523},
    )


@pytest.fixture
def registrations(monkeypatch):
    """Counts the (real) registrations run."""
    calls: list[int] = []
    real = rig_module.rig_head
    monkeypatch.setattr(rig_module, "rig_head", lambda *a, **k: calls.append(1) or real(*a, **k))
    return calls


@pytest.fixture
def fake(monkeypatch):
    """Counts the registrations run, each replaced by :func:`_fake_registration`."""
    calls: list[int] = []
    monkeypatch.setattr(
        rig_module, "rig_head", lambda *a, **k: calls.append(1) or _fake_registration(*a, **k)
    )
    return calls


def _load_again(mesh):
    rig_module._rig_file.cache_clear()  # as a new process would
    return rig_module.load_rig(mesh)


@pytest.mark.skipif(not CLIP.exists(), reason="pocketsphinx-testdata not installed")
def test_second_run_reuses_the_registration_and_gives_the_same_frames(
    mesh, cache, registrations, tmp_path
):
    speech = tmp_path / "speech.wav"
    speech.write_bytes(CLIP.read_bytes())
    outs = [tmp_path / "first.npz", tmp_path / "second.npz"]
    for i, out in enumerate(outs):
        rig_module._rig_file.cache_clear()  # as a new process would
        assert main(["animate", str(speech), "--head", str(mesh), "-o", str(out), "-q"]) == 0
        assert len(registrations) == 1, f"run {i + 1} registered again"
    assert [p.name for p in (cache / "rigs").iterdir()] == [f"{rig_cache.file_digest(mesh)}.npz"]
    first, second = (load_input(str(p), None) for p in outs)
    assert np.abs(first.vertices - first.vertices[0]).max() > 1.0  # it moves (mm)
    np.testing.assert_array_equal(first.vertices, second.vertices)


def test_saved_correspondence_is_the_registration(mesh, cache, fake):
    rig = rig_module.load_rig(mesh)
    again = _load_again(mesh)
    assert len(fake) == 1
    for name in ("vertices", "faces", "blendshapes", "rotation", "translation", "corners"):
        np.testing.assert_array_equal(getattr(again, name), getattr(rig, name))
    np.testing.assert_array_equal(again.weights, rig.weights)
    assert (again.scale, again.residual, again.landmarks) == (rig.scale, 0.0, rig.landmarks)
    jaw = load_head().blendshapes[ARKIT_NAMES.index("jawOpen")]
    np.testing.assert_allclose(again.blendshapes[ARKIT_NAMES.index("jawOpen")], 1000 * jaw, 1e-5)


def test_an_edited_mesh_is_registered_again(mesh, cache, fake):
    rig_module.load_rig(mesh)
    moved = trimesh.load(mesh, process=False)
    moved.apply_translation([1.0, 0.0, 0.0])  # one millimetre
    moved.export(mesh)
    _load_again(mesh)
    assert len(fake) == 2 and len(list((cache / "rigs").iterdir())) == 2


def _tamper(path: Path, how: str) -> None:
    """Damage or change a saved registration."""
    if how == "garbage":
        path.write_bytes(b"not a zip file at all")
        return
    if how == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
        return
    with np.load(path, allow_pickle=False) as data:
        saved = {k: data[k] for k in data.files}
    if how == "pickled":  # an object array is stored pickled: refused, never unpickled
        saved["landmark_ids"] = np.array([{"upper_lip": 1}], dtype=object)
    elif how == "format":
        saved["format"] = np.int64(rig_cache.FORMAT + 1)
    elif how == "head":
        saved["head"] = np.str_("0" * 64)
    elif how == "vertices":
        saved["corners"], saved["weights"] = saved["corners"][:-1], saved["weights"][:-1]
    elif how == "corners":
        saved["corners"] = saved["corners"] + 10**6
    elif how == "nan":
        saved["weights"] = np.full_like(saved["weights"], np.nan)
    elif how == "missing":
        del saved["rotation"]
    with zipfile.ZipFile(path, "w") as z:  # written as np.savez does, allow_pickle as given
        for k, v in saved.items():
            with z.open(f"{k}.npy", "w") as f:
                np.lib.format.write_array(f, np.asanyarray(v), allow_pickle=True)


@pytest.mark.parametrize(
    "how",
    ["garbage", "truncated", "pickled", "format", "head", "vertices", "corners", "nan", "missing"],
)
def test_a_damaged_or_mismatched_saved_file_is_one_warning_and_registers_again(
    mesh, cache, fake, how
):
    rig = rig_module.load_rig(mesh)
    saved = rig_cache.saved_path(rig_cache.file_digest(mesh))
    _tamper(saved, how)
    with pytest.warns(TalkmeshWarning, match="ignoring the saved registration") as caught:
        again = _load_again(mesh)
    ours = [w for w in caught if issubclass(w.category, TalkmeshWarning)]
    assert len(ours) == 1 and "\n" not in str(ours[0].message)
    assert len(fake) == 2
    np.testing.assert_array_equal(again.blendshapes, rig.blendshapes)
    _load_again(mesh)  # saved over the damaged file: read back, not registered
    assert len(fake) == 2


@pytest.mark.skipif(not CLIP.exists(), reason="pocketsphinx-testdata not installed")
def test_cli_warns_in_one_line_on_a_damaged_file(mesh, cache, fake, tmp_path, capsys):
    rig_module.load_rig(mesh)
    _tamper(rig_cache.saved_path(rig_cache.file_digest(mesh)), "garbage")
    rig_module._rig_file.cache_clear()
    speech = tmp_path / "speech.wav"
    speech.write_bytes(CLIP.read_bytes())
    out = tmp_path / "talk.npz"
    assert main(["animate", str(speech), "--head", str(mesh), "-o", str(out), "-q"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("talkmesh: warning: ignoring the saved"), err
    assert "cannot read it" in err[0] and len(fake) == 2 and out.exists()


def test_an_unwritable_cache_is_one_warning(mesh, tmp_path, monkeypatch, fake):
    (tmp_path / "file").write_text("")
    monkeypatch.setenv(rig_cache.CACHE_ENV, str(tmp_path / "file"))  # a file, not a folder
    rig_module._rig_file.cache_clear()
    with pytest.warns(TalkmeshWarning, match="cannot save the registration"):
        rig = rig_module.load_rig(mesh)
    rig_module._rig_file.cache_clear()
    assert rig.units == "mm" and len(fake) == 1
