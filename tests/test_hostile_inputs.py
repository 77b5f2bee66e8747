"""Hostile and careless inputs on every entry point (docs/security.md): each is one line
``talkmesh: error:`` naming what is wrong, never ``internal error``, and leaves no output.

The cases are those an outside battery found answered with "internal error", a hang, a raw
warning or a misleading message: symbolic link loops, glb files whose JSON has the wrong types
or nests 100000 deep, a mesh with every vertex at the origin, templates.pkl holding text, object
arrays or shared lists nested 60 times, checkpoints with a text step or a list for weights,
animation files nested deep or holding NaN, out-of-range options.
"""

from __future__ import annotations

import copy
import errno
import io
import os
import pickle
import struct
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from avatars import make_avatar

from talkmesh import cli
from talkmesh.errors import TalkmeshError

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "tests" / "recipes" / "meshtalk_expression.yaml"


def run(capsys, *argv: str) -> tuple[int, str]:
    code = cli.main([str(a) for a in argv])
    return code, capsys.readouterr().err


def assert_refused(code: int, err: str, *words: str) -> str:
    """One ``talkmesh: error:`` line (a batch adds its summary line), exit 1 or 2, no bug."""
    assert code in (1, 2), err
    assert "internal error" not in err and "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert lines and lines[0].startswith("talkmesh: error:"), err
    assert all(line.startswith("talkmesh:") for line in lines), err
    assert len(lines) == 1 or (len(lines) == 2 and "files failed" in lines[1]), err
    for w in words:
        assert w in lines[0], err
    return lines[0]


@pytest.fixture
def wav(tmp_path) -> Path:
    t = np.arange(16000) / 16000
    path = tmp_path / "s.wav"
    sf.write(path, (0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32), 16000)
    return path


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def loop(tmp: Path, name: str) -> Path:
    """``name`` -> ``name.2`` -> ``name``: a symbolic link loop."""
    a, b = tmp / name, tmp / (name + ".2")
    a.symlink_to(b.name)
    b.symlink_to(a.name)
    return a


# --------------------------------------------------------------------------- 6: symlink loops


@pytest.mark.parametrize(
    "argv",
    [
        ["animate", "{loop.wav}", "--model", "procedural", "-o", "o.npz"],
        ["animate", "{wav}", "--model", "procedural", "-o", "{loop.npz}"],
        ["export", "{loop.npz}", "-o", "e.glb"],
        ["animate", "{wav}", "--model", "procedural", "--avatar", "{loop.glb}", "-o", "a.glb"],
        ["rig", "{loop.obj}", "-o", "r.glb"],
    ],
)
def test_symlink_loops_are_one_line(capsys, tmp_path, wav, argv):
    args = [
        str(loop(tmp_path, a[1:-1])) if a.startswith("{loop") else str(wav) if a == "{wav}" else a
        for a in argv
    ]
    assert_refused(*run(capsys, *args))
    assert not [p for p in tmp_path.iterdir() if p.suffix in (".npz", ".glb") and p.is_file()]


# --------------------------------------------------------------------------- 6: glb JSON


def _glb_json(text: bytes) -> bytes:
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text
    return struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body


BAD_GLTF = {
    "meshes is a number": lambda g: g.update(meshes=5),
    "a mesh is a number": lambda g: g.update(meshes=[1, 2]),
    "nodes is text": lambda g: g.update(nodes="x"),
    "extras is a list": lambda g: g["meshes"][0].update(extras=[1]),
    "primitives is an object": lambda g: g["meshes"][0].update(primitives={"a": 1}),
    "a primitive is a number": lambda g: g["meshes"][0].update(primitives=[3]),
    "targets is text": lambda g: g["meshes"][0]["primitives"][0].update(targets="abc"),
    "weights is text": lambda g: g["meshes"][0].update(weights="abc"),
    "weights of another length": lambda g: g["meshes"][0].update(weights=[1, 2]),
    "buffers is a number": lambda g: g.update(buffers=3),
    "a buffer is text": lambda g: g.update(buffers=["x"]),
    "animations is an object": lambda g: g.update(animations={"a": 1}),
    "an animation is a list": lambda g: g.update(animations=[[1]]),
}


@pytest.fixture(scope="module")
def avatar_json(tmp_path_factory) -> tuple[dict, bytes]:
    from talkmesh.output.avatar import read_glb

    return read_glb(make_avatar(tmp_path_factory.mktemp("avatar") / "av.glb"))


@pytest.mark.parametrize("case", list(BAD_GLTF))
def test_avatar_with_json_of_the_wrong_types_is_one_line(capsys, tmp_path, wav, avatar_json, case):
    from talkmesh.output.avatar import glb_bytes

    gltf = copy.deepcopy(avatar_json[0])
    BAD_GLTF[case](gltf)
    bad = tmp_path / "bad.glb"
    bad.write_bytes(glb_bytes(gltf, avatar_json[1]))
    args = ["animate", wav, "--model", "procedural", "--avatar", bad, "-o", "out.glb"]
    assert_refused(*run(capsys, *args), "bad.glb")
    assert not (tmp_path / "out.glb").exists()
    code, err = run(capsys, "export", bad, "-o", "e.npz")  # the glb read as an animation
    assert code == 0 or assert_refused(code, err, "bad.glb")


def test_glb_nested_100000_deep_is_one_line_everywhere(capsys, tmp_path, wav):
    from talkmesh.serve.server import create_app

    deep = tmp_path / "deep.glb"
    deep.write_bytes(
        _glb_json(b'{"asset":{"version":"2.0"},"x":' + b"[" * 100_000 + b"]" * 100_000 + b"}")
    )
    args = ["animate", wav, "--model", "procedural", "--avatar", deep, "-o", "out.glb"]
    assert_refused(*run(capsys, *args), "deep.glb", "nested")
    assert_refused(*run(capsys, "export", deep, "-o", "e.npz"), "deep.glb")
    with pytest.raises(TalkmeshError, match="deep.glb: its JSON chunk is nested too deeply"):
        create_app(avatar=deep, static_dir=None)  # serve --avatar: before it listens


# --------------------------------------------------------------------------- 6: meshes, pickles


def _obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    lines = [f"v {x} {y} {z}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_mesh_with_every_vertex_at_the_origin_is_one_line(capsys, tmp_path, wav):
    rng = np.random.default_rng(0)
    mesh = _obj(tmp_path / "origin.obj", np.zeros((500, 3)), rng.integers(0, 500, (900, 3)))
    assert_refused(*run(capsys, "rig", mesh, "-o", "r.glb"), "origin.obj", "not a head")
    args = ["animate", wav, "--model", "procedural", "--head", mesh, "-o", "h.npz"]
    assert_refused(*run(capsys, *args), "origin.obj")
    assert not (tmp_path / "r.glb").exists() and not (tmp_path / "h.npz").exists()


@pytest.mark.parametrize(
    "content, words",
    [
        ({"alice": "a string"}, "str"),
        ({"alice": np.array([[1, 2, 3]], dtype=object)}, "object"),
        ({"alice": [["x", 1, 2]]}, "not an array of numbers"),
        ("just text", "expected a dict"),
    ],
)
def test_templates_pickle_of_text_or_objects_is_one_line(capsys, tmp_path, wav, content, words):
    pkl = tmp_path / "templates.pkl"
    pkl.write_bytes(pickle.dumps(content, protocol=2))
    args = ["animate", wav, "--model", "procedural", "--template", pkl, "-o", "t.npz"]
    assert_refused(*run(capsys, *args), "templates.pkl", words)


def test_animation_json_nested_deep_is_one_line(capsys, tmp_path):
    deep = tmp_path / "deep.json"
    deep.write_text('{"fps": 30, "names": ' + "[" * 100_000 + "]" * 100_000 + ', "frames": []}')
    assert_refused(*run(capsys, "export", deep, "-o", "e.npz"), "deep.json")
    assert_refused(*run(capsys, "render", deep, "-o", "e.mp4"), "deep.json")


# --------------------------------------------------------------------------- 6: options


@pytest.mark.parametrize(
    "argv, words",
    [
        (["animate", "{wav}", "--seed", "-1", "-o", "o.npz"], ["--seed -1", "0 to"]),
        (["animate", "{wav}", "--fps", "0.001", "-o", "o.npz"], ["--fps 0.001", "1 to 240"]),
        (["animate", "{wav}", "--fps", "nan", "-o", "o.npz"], ["--fps nan"]),
        (["animate", "{wav}", "--style", "A:nan", "-o", "o.npz"], ["A:nan", "0 to"]),
        (["animate", "{wav}", "--style", "A:-1", "-o", "o.npz"], ["A:-1"]),
        (["serve", "--port", "70000"], ["--port 70000", "65535"]),
    ],
)
def test_out_of_range_options_are_one_line(capsys, tmp_path, wav, argv, words):
    args = [str(wav) if a == "{wav}" else a for a in argv]
    assert_refused(*run(capsys, *args), *words)
    assert not (tmp_path / "o.npz").exists()


# --------------------------------------------------------------------------- 6: checkpoints


@pytest.mark.parametrize(
    "content, words",
    [
        ({"global_step": "abc", "epoch": 1}, "global_step is str"),
        ({"global_step": [1], "epoch": 1}, "global_step is list"),
        ({"global_step": 1, "epoch": 1, "state_dict": [1, 2]}, "state_dict is a list"),
    ],
)
def test_checkpoints_with_wrong_types_are_one_line(capsys, tmp_path, content, words):
    torch = pytest.importorskip("torch")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    torch.save(content, run_dir / "last.ckpt")
    code, err = run(capsys, "train", RECIPE, f"train.out_dir={run_dir}", "--resume", "-q")
    assert_refused(code, err, "last.ckpt", words)
    assert sorted(p.name for p in run_dir.iterdir()) == ["last.ckpt"]


# --------------------------------------------------------------------------- 8: messages


class Planted:
    """Unpickling this would create ``marker``."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.parametrize("kind", ["plain pickle", "zip", "legacy torch"])
def test_checkpoint_refusals_say_what_the_file_is_and_that_nothing_ran(tmp_path, kind):
    torch = pytest.importorskip("torch")
    from talkmesh.models.checkpoint_io import load_checkpoint
    from talkmesh.training.checkpoints import read_checkpoint

    marker, path = tmp_path / "marker", tmp_path / "last.ckpt"
    content = {"epoch": 1, "global_step": 2, "payload": Planted(marker)}
    if kind == "plain pickle":
        path.write_bytes(pickle.dumps(content, protocol=4))
    else:
        torch.save(content, path, _use_new_zipfile_serialization=kind == "zip")
    for read in (read_checkpoint, load_checkpoint):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with pytest.raises(TalkmeshError) as e:
                read(path)
        message = str(e.value)
        assert not caught, [str(w.message) for w in caught]  # torch's pickle-protocol warning
        assert message.startswith(f"{path}: refused: ") and "\n" not in message, message
        assert "nothing from it ran: delete it" in message, message
        assert "truncated" not in message and "weights_only" not in message, message
        if kind == "plain pickle":
            assert "a plain Python pickle" in message, message
        else:
            assert "tries to load io.open" in message, message
    assert not marker.exists()


def test_library_warnings_are_one_line(capsys, tmp_path, wav):
    code, _ = run(capsys, "animate", wav, "--model", "procedural", "-o", "o.npz", "-q")
    assert code == 0
    warnings.warn("something numpy said", RuntimeWarning, stacklevel=1)
    err = capsys.readouterr().err
    assert err == "talkmesh: warning: something numpy said (RuntimeWarning)\n", err


@pytest.mark.parametrize("kind", ["fifo", "device"])
def test_fifo_and_devices_are_not_called_empty(capsys, tmp_path, kind):
    if kind == "fifo":
        source = tmp_path / "pipe.wav"
        os.mkfifo(source)
    else:
        source = Path("/dev/zero")
    line = assert_refused(*run(capsys, "animate", source, "--model", "procedural", "-o", "o.npz"))
    assert ("named pipe" if kind == "fifo" else "a device") in line and "empty" not in line


@pytest.mark.parametrize("overwrite", [[], ["--overwrite"]])
def test_an_output_that_is_a_folder_says_so(capsys, tmp_path, wav, overwrite):
    (tmp_path / "out.npz").mkdir()
    args = ["animate", wav, "--model", "procedural", "-o", "out.npz", *overwrite]
    line = assert_refused(*run(capsys, *args), "out.npz is a folder")
    assert "--overwrite" not in line


def test_disk_full_on_npz_names_the_output(capsys, tmp_path, wav, monkeypatch):
    from talkmesh.output import npy

    def full(*_args, **_kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(npy.NpzWriter, "_put_blocks", full)
    monkeypatch.setattr(npy.NpzWriter, "_put", full)
    line = assert_refused(*run(capsys, "animate", wav, "--model", "procedural", "-o", "o.npz"))
    assert "o.npz: cannot write it (No space left on device)" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.wav"]


def test_summary_into_an_unwritable_folder_is_refused_before_any_file(capsys, tmp_path, wav):
    folder = tmp_path / "in"
    folder.mkdir()
    for stem in "ab":
        (folder / f"{stem}.wav").write_bytes(wav.read_bytes())
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the summary's folder would be")
    args = ["animate", folder, "--model", "procedural", "-o", "out/", "--summary"]
    code, err = run(capsys, *args, blocked / "summary.csv")
    assert_refused(code, err, "--summary")
    assert not (tmp_path / "out").exists()


def test_avatar_with_an_external_buffer_is_refused_before_the_model_runs(tmp_path, avatar_json):
    from talkmesh.output.avatar import bind_avatar

    gltf = copy.deepcopy(avatar_json[0])
    gltf["buffers"][0]["uri"] = "data.bin"
    with pytest.raises(TalkmeshError, match="av.glb: the avatar keeps its binary data in an ext"):
        bind_avatar(gltf, "av.glb")  # what `animate --avatar` checks before loading a model


def test_avatar_summary_counts_meshes_of_one_name(avatar_json):
    from talkmesh.output.avatar import bind_avatar

    gltf = copy.deepcopy(avatar_json[0])
    head = next(m for m in gltf["meshes"] if m["name"] == "Head")
    gltf["meshes"] = [head] * 3000
    gltf["nodes"] = [{"mesh": k} for k in range(3000)]
    summary = bind_avatar(gltf).summary()
    assert "3000 meshes: Head x 3000;" in summary and summary.count("Head") == 1, summary


# --------------------------------------------------------------------------- 4: finiteness


@pytest.mark.parametrize("bad", [np.nan, np.inf])
@pytest.mark.parametrize("suffix", [".obj", ".npy", ".pkl"])
def test_template_with_non_finite_vertices_is_refused_up_front(capsys, tmp_path, wav, bad, suffix):
    from talkmesh.datasets.reader import write_templates
    from talkmesh.face.assets import load_head

    head = load_head()
    vertices = head.template.astype(np.float64)
    vertices[7, 1] = bad
    path = tmp_path / f"face{suffix}"
    if suffix == ".obj":
        _obj(path, vertices, head.faces)
    elif suffix == ".npy":
        np.save(path, vertices)
    else:
        write_templates(path, {"alice": vertices})
    args = ["animate", wav, "--model", "procedural", "--template", path, "-o", "t.npz"]
    assert_refused(*run(capsys, *args), "face", "NaN or infinite")
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name, "s.wav"]


def test_avatar_whose_header_understates_its_length_is_refused(capsys, tmp_path, wav):
    avatar = make_avatar(tmp_path / "av.glb")
    data = avatar.read_bytes()
    avatar.write_bytes(data[:8] + struct.pack("<I", len(data) // 3) + data[12:])
    args = ["animate", wav, "--model", "procedural", "--avatar", avatar, "-o", "out.glb"]
    assert_refused(*run(capsys, *args), "av.glb", f"the header says {len(data) // 3} bytes")
    assert not (tmp_path / "out.glb").exists()


@pytest.mark.parametrize("fps", [np.nan, np.inf, 0.0, -30.0])
def test_export_of_an_npz_with_a_bad_frame_rate_is_refused(capsys, tmp_path, fps):
    import talkmesh
    from talkmesh.output.formats import save_animation

    anim = talkmesh.animate(np.zeros(8000, np.float32), model="procedural")
    good = tmp_path / "good.npz"
    save_animation(anim, good)
    with np.load(good) as z:
        members = {k: z[k] for k in z.files}
    members["fps"] = np.float64(fps)
    bad = tmp_path / "bad.npz"
    np.savez(bad, **members)
    for out in ("e.glb", "e.json", "e.npz"):
        assert_refused(*run(capsys, "export", bad, "-o", out), "bad.npz", "frame rate")
        assert not (tmp_path / out).exists()


def test_frames_of_nan_never_reach_a_final_name(tmp_path):
    from talkmesh.output.streaming import save_blocks
    from talkmesh.pipeline import animate_blocks

    anim = animate_blocks(np.zeros(16000, np.float32), model="procedural", block=10)

    def poisoned(blocks):
        for k, block in enumerate(blocks):
            if k == 1:
                block.vertices[3] = np.nan
            yield block

    anim.blocks = poisoned(anim.blocks)
    paths = [tmp_path / "a.npz", tmp_path / "a.npy"]
    with pytest.raises(TalkmeshError, match="frames 10 to 20 hold NaN"):
        save_blocks(anim, paths, overwrite=False)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- 5: FLAC


def unknown_length(flac: bytes) -> bytes:
    """``flac`` with STREAMINFO's total samples 0, as ffmpeg writes FLAC to a pipe
    (``ffmpeg -i x.wav -f flac - > y.flac``): the length is known only by decoding."""
    assert flac[:4] == b"fLaC"
    data = bytearray(flac)
    fields = int.from_bytes(data[18:26], "big")  # rate, channels, bits, then 36 bits of samples
    data[18:26] = (fields & ~((1 << 36) - 1)).to_bytes(8, "big")
    return bytes(data)


def tone_flac(seconds: float) -> bytes:
    t = np.arange(int(16000 * seconds)) / 16000
    buf = io.BytesIO()
    sf.write(buf, (0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32), 16000, format="FLAC")
    return buf.getvalue()


def test_flac_without_a_stated_length_is_read(tmp_path):
    from talkmesh.audio.loading import audio_duration, load_audio
    from talkmesh.audio.waveform import open_audio

    path = tmp_path / "pipe.flac"
    path.write_bytes(unknown_length(tone_flac(2.0)))
    assert sf.info(str(path)).frames > 2**62  # what libsndfile makes of "total samples 0"
    assert len(load_audio(path)) == 32000 and len(open_audio(path)) == 32000
    assert 1.5 < audio_duration(path) <= 2.0  # counted by decoding (the last block is lost)
    assert 1.0 < audio_duration(path, limit=1.0) < 1.3  # and only until past the limit


def test_flac_without_a_stated_length_animates(capsys, tmp_path):
    path = tmp_path / "pipe.flac"
    path.write_bytes(unknown_length(tone_flac(2.0)))
    code, err = run(capsys, "animate", path, "--model", "procedural", "-o", "o.npz")
    assert code == 0, err
    with np.load(tmp_path / "o.npz") as z:
        assert len(z["offsets"]) == 60


def test_truncated_and_corrupt_flac_animate_through_ffmpeg_in_a_batch(capsys, tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    whole = tone_flac(3.0)
    (folder / "cut.flac").write_bytes(whole[: len(whole) // 2])
    broken = bytearray(whole)
    broken[len(whole) // 2 : len(whole) // 2 + 300] = b"\x55" * 300
    (folder / "broken.flac").write_bytes(bytes(broken))
    code, err = run(capsys, "animate", folder, "--model", "procedural", "-o", "out/", "-q")
    assert "internal error" not in err and "LibsndfileError" not in err, err
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "broken.mp4",
        "cut.mp4",
        "summary.csv",
    ]


# --------------------------------------------------------------------------- 3: expansion


def shared_lists(levels: int) -> list:
    """A list nesting the same list twice, ``levels`` deep: a few hundred bytes pickled,
    2**levels items to whoever walks it."""
    nested: list = []
    for _ in range(levels):
        nested = [nested, nested]
    return nested


def deep_list_pickle(depth: int) -> bytes:
    """A protocol-2 pickle of {'alice': [[[...]]]} nested ``depth`` deep (built by opcodes:
    pickle.dumps itself would overflow the stack)."""
    return b"\x80\x02}X\x05\x00\x00\x00alice" + b"]" * depth + b"a" * (depth - 1) + b"s."


@pytest.mark.parametrize(
    "content, words",
    [
        (pickle.dumps({"alice": shared_lists(60)}, protocol=2), "nested over"),
        (pickle.dumps({"alice": shared_lists(30)}, protocol=2), "expands to over"),
        (deep_list_pickle(100_000), "nested over"),
    ],
    ids=["shared 60 deep", "shared 30 deep", "100000 deep"],
)
def test_templates_pickle_that_expands_without_bound_is_one_line(
    capsys, tmp_path, wav, content, words
):
    from talkmesh.datasets.reader import load_templates

    pkl = tmp_path / "templates.pkl"
    pkl.write_bytes(content)
    assert len(content) < 300_000
    with pytest.raises(TalkmeshError, match=words):  # prepare-vocaset and datasets read it so
        load_templates(pkl)
    args = ["animate", wav, "--model", "procedural", "--template", pkl, "-o", "t.npz"]
    assert_refused(*run(capsys, *args), "templates.pkl", "refused")


def test_checkpoint_whose_recipe_expands_without_bound_is_refused(capsys, tmp_path):
    torch = pytest.importorskip("torch")
    from talkmesh.training.checkpoints import read_checkpoint

    shared: dict = {}
    for _ in range(34):
        shared = {"a": shared, "b": shared}
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    path = run_dir / "last.ckpt"
    torch.save({"global_step": 1, "epoch": 0, "talkmesh_recipe": shared}, path)
    assert path.stat().st_size < 100_000
    with pytest.raises(TalkmeshError, match="last.ckpt: refused: containers nested over"):
        read_checkpoint(path)
    code, err = run(capsys, "train", RECIPE, f"train.out_dir={run_dir}", "--resume", "-q")
    assert_refused(code, err, "last.ckpt", "refused")


def test_npz_whose_members_expand_a_hundredfold_is_refused_before_reading(
    capsys, tmp_path, monkeypatch
):
    from talkmesh.output import files

    monkeypatch.setattr(files, "EXPANSION_FREE", 1 << 20)  # the same rule, at a test's size
    bomb = tmp_path / "bomb.npz"
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as z:
        for name, arr in (("faces", np.zeros((1, 3), np.int32)), ("fps", np.float64(30))):
            with z.open(f"{name}.npy", "w") as f:
                np.lib.format.write_array(f, np.asarray(arr))
        with z.open("vertices.npy", "w", force_zip64=True) as f:
            shape = (2000, 1000, 3)  # 24 MB of zeros in 24 kB
            np.lib.format.write_array_header_1_0(
                f, {"descr": "<f4", "fortran_order": False, "shape": shape}
            )
            zeros = bytes(1 << 20)
            for _ in range(2000 * 1000 * 3 * 4 >> 20):
                f.write(zeros)
    line = assert_refused(*run(capsys, "export", bomb, "-o", "e.glb"), "bomb.npz", "expand")
    assert "times" in line and not (tmp_path / "e.glb").exists()


def test_release_whose_config_is_nested_deep_is_one_line(tmp_path):
    pytest.importorskip("safetensors")
    import torch
    from safetensors.torch import save_file

    from talkmesh.models.release import load_model

    path = tmp_path / "deep.safetensors"
    meta = {
        "format": "talkmesh-model",
        "format_version": "1",
        "family": "codetalker",
        "config": "[" * 100_000 + "]" * 100_000,
    }
    save_file({"w": torch.zeros(1)}, str(path), metadata=meta)
    with pytest.raises(TalkmeshError, match="deep.safetensors: a malformed talkmesh model"):
        load_model(path)
    save_file({"w": torch.zeros(1)}, str(path), metadata={**meta, "format_version": "x"})
    with pytest.raises(TalkmeshError, match="deep.safetensors: a malformed talkmesh model"):
        load_model(path)


def test_save_animation_refuses_nan_frames(tmp_path):
    from talkmesh.animation import Animation
    from talkmesh.output.formats import save_animation

    vertices = np.zeros((2, 3, 3), np.float32)
    vertices[1, 0, 0] = np.nan
    anim = Animation(vertices=vertices, faces=np.array([[0, 1, 2]]), fps=30.0)
    for name in ("a.glb", "a.obj", "a.npz"):
        with pytest.raises(TalkmeshError, match="NaN or infinite"):
            save_animation(anim, tmp_path / name)
    assert list(tmp_path.iterdir()) == []
