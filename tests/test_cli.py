"""The command line with good and bad inputs: one-line errors, never a traceback, never a lost file."""

from __future__ import annotations

import hashlib
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from talkmesh.cli import main
from talkmesh.face.assets import load_head
from talkmesh.pipeline import available_models

LIBRIVOX = Path("/usr/share/pocketsphinx/test/data/librivox")
CLIP = (
    LIBRIVOX / "sense_and_sensibility_01_austen_64kb-0880.wav"
)  # 3.0 s, "he was not an ill disposed young man"

pytestmark = pytest.mark.skipif(not CLIP.exists(), reason="pocketsphinx-testdata not installed")


def run_cli(
    *args: str, cwd: Path | None = None, timeout: float = 300
) -> subprocess.CompletedProcess:
    """Run the installed console script the way a user does."""
    env = dict(os.environ, HF_HUB_OFFLINE="1")
    return subprocess.run(
        [sys.executable, "-m", "talkmesh", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=timeout,
    )


def assert_one_line_error(stderr: str, *fragments: str) -> None:
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("talkmesh: error:")]
    assert errors, stderr
    assert "Traceback" not in stderr, stderr
    for frag in fragments:
        assert any(frag in ln for ln in errors), (frag, stderr)


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def speech(tmp_path) -> Path:
    """A short real recording, copied so the test may put files next to it."""
    dst = tmp_path / "speech.wav"
    dst.write_bytes(CLIP.read_bytes())
    return dst


def test_animate_real_clip_end_to_end(speech, tmp_path):
    out_npy, out_csv = tmp_path / "a.npy", tmp_path / "a.csv"
    rc = main(["animate", str(speech), "-o", str(out_npy), "-o", str(out_csv), "-q"])
    assert rc == 0
    verts = np.load(out_npy)
    head = load_head()
    assert verts.shape == (90, head.num_vertices * 3)  # 3.0 s at 30 fps, VOCASET layout
    rows = out_csv.read_text().splitlines()
    assert len(rows) == 1 + 90
    motion = np.abs(verts.reshape(90, -1, 3) - head.template).max()
    assert 1e-3 < motion < 0.05  # the face moves, by millimetres to centimetres


def test_int8_animation_stays_close_to_float32(speech, tmp_path, capsys):
    exact, out = tmp_path / "a.npy", {}
    assert main(["animate", str(speech), "-o", str(exact), "-q", "--no-blinks"]) == 0
    head = load_head()
    ref = np.load(exact).reshape(90, -1, 3)
    motion = np.abs(ref - head.template).max()
    for mode in ("speech", "all"):
        path = tmp_path / f"{mode}.npy"
        args = ["animate", str(speech), "-o", str(path), "-q", "--no-blinks", "--int8", mode]
        assert main(args) == 0
        out[mode] = np.load(path).reshape(90, -1, 3)
        diff = np.abs(out[mode] - ref).max(-1).mean()  # mean per-vertex distance
        assert 0 < diff < 0.1 * motion, (mode, diff, motion)  # int8 ran, and is close
    assert not np.array_equal(out["speech"], out["all"])
    rc = main(
        [
            "animate",
            str(speech),
            "--model",
            "procedural",
            "--int8",
            "all",
            "-o",
            str(tmp_path / "p.npy"),
        ]
    )
    assert rc == 1 and not (tmp_path / "p.npy").exists()
    assert_one_line_error(capsys.readouterr().err, "--int8", "procedural")


def test_python_module_entry_point_prints_version():
    res = run_cli("--version")
    assert res.returncode == 0
    assert res.stdout.startswith("talkmesh ")


@pytest.mark.parametrize(
    "name, content, fragment",
    [
        ("missing.wav", None, "not found"),
        ("empty.wav", b"", "empty"),
        ("notes.wav", b"this is not audio at all\n" * 20, "notes.wav"),
        ("noise.mp3", bytes(range(256)) * 64, "noise.mp3"),
    ],
)
def test_bad_audio_gives_one_line_error_and_writes_nothing(tmp_path, name, content, fragment):
    """Refused before any model loads, as argument errors are: exit 2, one line."""
    src = tmp_path / name
    if content is not None:
        src.write_bytes(content)
    out = tmp_path / "out.npy"
    res = run_cli("animate", str(src), "-o", str(out))
    assert res.returncode == 2
    assert_one_line_error(res.stderr, fragment)
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert not out.exists()
    if content is not None:
        assert src.read_bytes() == content  # the input is untouched


REFUSE_AND_SAY_WHAT_LOADED = """
import sys
from talkmesh.cli import main
code = main(sys.argv[1:])
heavy = sorted(m for m in ("torch", "transformers", "scipy.signal") if m in sys.modules)
print("loaded:", " ".join(heavy) or "none")
sys.exit(code)
"""


@pytest.mark.parametrize(
    "case", ["missing", "empty", "not audio", "output under a file", "bad format"]
)
def test_refusals_that_need_no_model_load_no_model(speech, tmp_path, case):
    """Bad input and output paths are refused before torch (or any model) is imported: one line,
    exit 2, as argument errors."""
    (tmp_path / "empty.wav").write_bytes(b"")
    (tmp_path / "notes.wav").write_text("this is not audio at all\n" * 20)
    (tmp_path / "file").write_text("not a folder")
    audio, out = {
        "missing": (tmp_path / "missing.wav", tmp_path / "a.npy"),
        "empty": (tmp_path / "empty.wav", tmp_path / "a.npy"),
        "not audio": (tmp_path / "notes.wav", tmp_path / "a.npy"),
        "output under a file": (speech, tmp_path / "file" / "a.npy"),
        "bad format": (speech, tmp_path / "a.xyz"),
    }[case]
    res = subprocess.run(
        [sys.executable, "-c", REFUSE_AND_SAY_WHAT_LOADED, "animate", str(audio), "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert_one_line_error(res.stderr)
    assert res.stdout.strip() == "loaded: none"


def test_folder_without_speech_as_audio(tmp_path, capsys):
    rc = main(["animate", str(tmp_path), "-o", str(tmp_path / "x.npy")])
    assert rc == 2  # a folder is a library (tests/test_batch.py); this one has no speech
    assert_one_line_error(capsys.readouterr().err, str(tmp_path), "no speech files")


def test_one_bad_file_among_good_ones_is_reported_at_the_end(speech, tmp_path, capsys):
    bad = tmp_path / "bad.wav"
    bad.write_bytes(b"RIFF garbage")
    rc = main(["animate", str(bad), str(speech), "-o", str(tmp_path / "out" / "{stem}.npy"), "-q"])
    err = capsys.readouterr().err
    assert rc == 1
    assert_one_line_error(err, "bad.wav")
    assert "1 of 2 files failed" in err
    assert np.load(tmp_path / "out" / "speech.npy").shape[0] == 90  # the good file is still done
    assert not (tmp_path / "out" / "bad.npy").exists()


def test_tenth_of_a_second_clip_gives_a_short_animation(tmp_path):
    clip, sr = sf.read(CLIP, dtype="float32")
    short = tmp_path / "short.wav"
    sf.write(short, clip[sr : sr + sr // 10], sr)
    out = tmp_path / "short.npy"
    assert main(["animate", str(short), "-o", str(out), "-q"]) == 0
    verts = np.load(out)
    assert verts.shape[0] == 3  # 0.1 s at 30 fps
    assert np.isfinite(verts).all()


def test_template_with_wrong_vertex_count(speech, tmp_path):
    head = load_head()
    bad = tmp_path / "face.obj"
    bad.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in head.template[:100]) + "f 1 2 3\n")
    out = tmp_path / "a.npy"
    res = run_cli("animate", str(speech), "--template", str(bad), "-o", str(out))
    assert res.returncode == 2
    assert_one_line_error(res.stderr, "face.obj", "100", str(head.num_vertices))
    assert not out.exists()


def test_own_template_with_the_bundled_topology_is_animated(speech, tmp_path):
    head = load_head()
    shifted = head.template + np.float32([0.0, 0.01, 0.0])
    npy = tmp_path / "mine.npy"
    np.save(npy, shifted)
    out = tmp_path / "a.npy"
    assert main(["animate", str(speech), "--template", str(npy), "-o", str(out), "-q"]) == 0
    first = np.load(out)[0].reshape(-1, 3)
    assert (
        np.abs(first - shifted).max() < 0.02
    )  # animated around the user's face, not the bundled one


@pytest.mark.parametrize(
    "units, turn, said",
    [
        (1000.0, "z-up", "converted: millimetres -> metres, up +z -> +y"),
        (100.0, None, "converted: centimetres -> metres"),
        (1.0, "z-up", "converted: up +z -> +y"),
    ],
)
def test_template_in_other_units_or_axes_is_converted_and_said(
    speech, tmp_path, capsys, units, turn, said
):
    """A bundled-topology mesh in millimetres or Z-up (a Blender export) moves as the bundled
    head does, in metres and +y up, and the terminal says what was converted."""
    from talkmesh.output.formats import load_animation

    head = load_head()
    z_up = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], np.float32)  # +y -> +z
    mine = (head.template @ (z_up.T if turn else np.eye(3, dtype=np.float32))) * units
    npy = tmp_path / "mine.npy"
    np.save(npy, mine)
    out = tmp_path / "a.npz"
    argv = ["animate", str(speech), "--template", str(npy), "--model", "procedural"]
    assert main([*argv, "-o", str(out)]) == 0
    assert f"template {npy}: {said}" in capsys.readouterr().out
    anim = load_animation(out)
    np.testing.assert_allclose(anim.template, head.template, atol=1e-5)
    moved = np.abs(anim.vertices - anim.template).max()
    assert 1e-3 < moved < 0.05  # metre-sized motion on a metre-sized face


def test_template_at_one_point_is_one_line(speech, tmp_path, capsys):
    npy = tmp_path / "dot.npy"
    np.save(npy, np.zeros_like(load_head().template))
    assert (
        main(["animate", str(speech), "--template", str(npy), "-o", str(tmp_path / "a.npz")]) == 2
    )
    assert_one_line_error(capsys.readouterr().err, "dot.npy", "one point")


def test_template_in_metres_and_y_up_is_taken_as_it_is(speech, tmp_path, capsys):
    head = load_head()
    tilt = np.radians(8.0)  # a head turned a little is the user's pose, not another axis
    turn = np.array(
        [[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]], np.float32
    )
    npy = tmp_path / "mine.npy"
    np.save(npy, head.template @ turn.T + np.float32([0.0, 1.6, 0.0]))
    from talkmesh.datasets.templates import read_face_template

    face, note = read_face_template(npy)
    assert note == ""
    np.testing.assert_allclose(face.template, np.load(npy), atol=1e-6)


def test_existing_output_is_never_overwritten(speech, tmp_path):
    out = tmp_path / "keep.npy"
    out.write_bytes(b"precious")
    res = run_cli("animate", str(speech), "-o", str(out))
    assert res.returncode == 2
    assert_one_line_error(res.stderr, "keep.npy", "--overwrite")
    assert out.read_bytes() == b"precious"


def test_refuses_to_write_over_the_input(speech, tmp_path):
    before = digest(speech)
    res = run_cli("animate", str(speech), "-o", str(speech))
    assert res.returncode == 2
    assert_one_line_error(res.stderr, "speech.wav")
    assert digest(speech) == before
    anim = tmp_path / "anim.npy"
    np.save(anim, np.repeat(load_head().template.reshape(1, -1), 3, axis=0))
    before = digest(anim)
    res = run_cli("export", str(anim), "-o", str(anim), "--overwrite")
    assert res.returncode == 2
    assert_one_line_error(res.stderr, "input")
    assert digest(anim) == before


def test_unknown_output_format(speech, tmp_path):
    res = run_cli("animate", str(speech), "-o", str(tmp_path / "a.xyz"))
    assert res.returncode == 2
    assert_one_line_error(res.stderr, ".xyz")


def test_unknown_identity_and_model(speech, tmp_path, capsys):
    assert (
        main(["animate", str(speech), "--identity", "nobody", "-o", str(tmp_path / "a.npy")]) == 2
    )
    assert_one_line_error(capsys.readouterr().err, "nobody")
    rc = main(["animate", str(speech), "--model", "nothing", "-o", str(tmp_path / "b.npy"), "-q"])
    assert rc == 2  # refused before any file is animated
    assert_one_line_error(capsys.readouterr().err, "nothing")
    assert not (tmp_path / "b.npy").exists()


def test_export_and_render_bad_animation_files(tmp_path, capsys):
    bad = tmp_path / "anim.npy"
    bad.write_bytes(b"\x93NUMPY garbage")
    assert main(["export", str(bad), "-o", str(tmp_path / "x.glb")]) == 2
    assert_one_line_error(capsys.readouterr().err, "anim.npy")
    wrong = tmp_path / "wrong.npy"
    np.save(wrong, np.zeros((5, 30), np.float32))  # 10 vertices: not the bundled head
    assert main(["export", str(wrong), "-o", str(tmp_path / "y.glb")]) == 2
    assert_one_line_error(capsys.readouterr().err, "wrong.npy")
    assert not (tmp_path / "x.glb").exists() and not (tmp_path / "y.glb").exists()


def test_export_head_writes_a_mesh_to_try_template_and_rig_on(tmp_path, capsys):
    from talkmesh.face.assets import list_identities, read_mesh_vertices
    from talkmesh.face.rig_files import load_mesh

    out = tmp_path / "head.obj"
    identity = list_identities()[-1]
    assert main(["export-head", "-o", str(out), "--identity", identity]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    head = load_head(identity)
    np.testing.assert_allclose(read_mesh_vertices(out), head.template, atol=1e-6)
    vertices, faces = load_mesh(out)
    np.testing.assert_array_equal(faces, head.faces)
    assert main(["export-head", "-o", str(out)]) == 2  # never over an existing file
    assert_one_line_error(capsys.readouterr().err, "head.obj", "--overwrite")
    assert main(["export-head", "-o", str(tmp_path / "head.stl")]) == 2
    assert_one_line_error(capsys.readouterr().err, "head.stl", ".obj")


def test_obj_sequence_export_names_files_that_exist(tmp_path, capsys):
    anim = tmp_path / "anim.npy"
    np.save(anim, np.repeat(load_head().template.reshape(1, -1), 3, axis=0))
    out = tmp_path / "talk.obj"
    assert main(["export", str(anim), "-o", str(out)]) == 0
    said = capsys.readouterr().out.split()
    named = [Path(w) for w in said if w.endswith(".obj")]
    assert named[0] == tmp_path / "talk_00000.obj" and named[-1].name == "talk_00002.obj"
    assert all((tmp_path / p.name).is_file() for p in named)
    assert main(["export", str(anim), "-o", str(out)]) == 2  # the frames are there now
    err = capsys.readouterr().err
    assert_one_line_error(err, "talk_00000.obj", "--overwrite")
    assert "overwrite=True" not in err


def test_output_without_an_extension_is_a_folder_for_one_input_and_several(speech, tmp_path):
    result = tmp_path / "result"
    args = ["--model", "procedural", "--size", "64", "-q"]
    assert main(["animate", str(speech), "-o", str(result), *args]) == 0
    assert sorted(p.name for p in result.iterdir()) == ["speech.mp4"]  # the default format
    other = tmp_path / "other.wav"
    other.write_bytes(speech.read_bytes())
    out = tmp_path / "out"
    assert main(["animate", str(speech), str(other), "-o", str(out), *args]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["other.mp4", "speech.mp4"]


def test_an_existing_file_without_an_extension_is_no_folder(speech, tmp_path, capsys):
    notes = tmp_path / "notes"
    notes.write_text("precious")
    assert main(["animate", str(speech), "-o", str(notes), "-q"]) == 2
    assert_one_line_error(capsys.readouterr().err, "notes", "unknown output format")
    assert notes.read_text() == "precious"


def test_the_video_keeps_the_original_sound(speech, tmp_path):
    """The mp4 muxes the user's file (44.1 kHz, stereo), not the 16 kHz copy the model hears:
    a 12 kHz tone survives."""
    from imageio_ffmpeg import get_ffmpeg_exe

    clip, sr = sf.read(speech, dtype="float32")
    rate = 44100
    t = np.arange(round(len(clip) / sr * rate)) / rate
    tone = 0.1 * np.sin(2 * np.pi * 12000 * t)
    wav = tmp_path / "wide.wav"
    sf.write(wav, np.stack([tone, tone], 1).astype(np.float32), rate)
    out = tmp_path / "wide.mp4"
    assert main(["animate", str(wav), "-o", str(out), "--model", "procedural", "--size", "64"]) == 0
    probe = subprocess.run([get_ffmpeg_exe(), "-hide_banner", "-i", str(out)], capture_output=True)
    audio_line = next(ln for ln in probe.stderr.decode().splitlines() if "Audio:" in ln)
    assert "44100 Hz" in audio_line and "stereo" in audio_line, audio_line
    raw = subprocess.run(
        [get_ffmpeg_exe(), "-v", "error", "-i", str(out), "-f", "f32le", "-ac", "1", "-"],
        capture_output=True,
        check=True,
    ).stdout
    decoded = np.frombuffer(raw, np.float32)
    spectrum = np.abs(np.fft.rfft(decoded))
    freqs = np.fft.rfftfreq(len(decoded), 1 / rate)
    assert spectrum[freqs > 8000].max() > 0.5 * spectrum.max()  # the tone is there


def test_a_transcript_that_does_not_fit_is_one_warning_line(speech, tmp_path):
    out = tmp_path / "a.npz"
    too_long = " ".join(["and mister john dashwood had then leisure to consider how much"] * 4)
    res = run_cli("animate", str(speech), "--text", too_long, "-o", str(out))
    assert res.returncode == 0, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    warned = [ln for ln in lines if "could not be aligned" in ln]
    assert len(warned) == 1 and warned[0].startswith("talkmesh: warning: "), res.stderr
    assert "UserWarning" not in res.stderr and "recognize_phones(" not in res.stderr
    assert out.is_file()


def test_export_and_render_write_every_output(tmp_path, capsys):
    anim = tmp_path / "anim.npy"
    head = load_head()
    np.save(anim, np.repeat(head.template.reshape(1, -1), 3, axis=0))
    e1, e2 = tmp_path / "e1.glb", tmp_path / "e2.npz"
    assert main(["export", str(anim), "-o", str(e1), "-o", str(e2), "-q"]) == 0
    assert e1.stat().st_size > 0 and e2.stat().st_size > 0
    r1, r2 = tmp_path / "r1.mp4", tmp_path / "r2.mp4"
    assert main(["render", str(e2), "-o", str(r1), "-o", str(r2), "--size", "64", "-q"]) == 0
    assert r1.stat().st_size > 0 and r1.read_bytes() == r2.read_bytes()
    assert main(["render", str(e2), "-o", str(tmp_path / "r.glb"), "-q"]) == 2
    assert_one_line_error(capsys.readouterr().err, "r.glb", "export")


def test_commands_writing_one_file_refuse_a_second_output(tmp_path, capsys):
    a, b = tmp_path / "a.glb", tmp_path / "b.glb"
    with pytest.raises(SystemExit) as exit_:
        main(["rig", str(tmp_path / "head.obj"), "-o", str(a), "-o", str(b)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "given twice" in err and str(b) in err
    assert not a.exists() and not b.exists()


def test_every_output_option_takes_several_or_refuses_a_second():
    """No command keeps only the last of two outputs: each takes them all or refuses."""
    import argparse

    from talkmesh.cli import build_parser
    from talkmesh.cli.common import Once

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    writes = {"output", "out", "json", "summary"}
    for name, parser in sub.choices.items():
        for action in parser._actions:
            if action.option_strings and action.dest in writes:
                several = isinstance(action, argparse._AppendAction)
                assert several or isinstance(action, Once), (name, action.option_strings)


def test_docs_agree_on_the_demo_glb_target_count():
    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    exports = (root / "docs" / "guide" / "exports.md").read_text()
    total, residual = map(
        int, re.search(r"demo\.glb`: (\d+) = 52 ARKit \+ (\d+) residual", readme).groups()
    )
    assert total == 52 + residual
    said = re.search(
        r"demo\.glb` \(the bundled CodeTalker\) has (\d+) targets:\s+52 ARKit \+ (\d+)", exports
    )
    assert said and (int(said[1]), int(said[2])) == (total, residual)


def test_info_lists_assets_and_models(capsys):
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert "identities (16" in out
    assert "procedural" in out


@pytest.mark.slow
@pytest.mark.parametrize(
    "model, bound_mb",
    [
        ("procedural", 2500),
        # the learned path also holds torch, the model and, for the .glb, a float32 copy of the
        # residual motion that the fitted ARKit weights miss (1 GB at 10 minutes)
        ("codetalker-synth", 3500),
    ],
)
def test_ten_minute_clip_in_bounded_memory(tmp_path, model, bound_mb):
    """10 min of speech -> ARKit weights (.json) and a .glb: finishes, and peak memory stays bounded."""
    if model not in available_models():
        pytest.fail(f"{model} is not bundled")
    clip, sr = sf.read(CLIP, dtype="float32")
    n = 600 * sr
    long = tmp_path / "long.wav"
    sf.write(long, np.tile(clip, n // len(clip) + 1)[:n], sr)
    out, glb = tmp_path / "long.json", tmp_path / "long.glb"
    code = (
        "import resource, sys; from talkmesh.cli import main; rc = main(sys.argv[1:]); "
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss); sys.exit(rc)"
    )
    res = subprocess.run(
        [
            sys.executable,
            "-c",
            code,
            "animate",
            str(long),
            "--model",
            model,
            "-o",
            str(out),
            "-o",
            str(glb),
            "-q",
        ],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert res.returncode == 0, res.stderr
    peak_mb = int(res.stdout.split()[-1]) / 1024
    assert peak_mb < bound_mb, peak_mb  # 18000 frames x 4766 vertices are 1 GB of float32 alone
    assert out.stat().st_size > 0 and glb.stat().st_size > 0


# Every subcommand with its positional arguments and long options: none may disappear.
COMMANDS = {
    "animate": (
        ["audio"],
        "--avatar --bilabial-closure --camera --cluster --emotion --fps --head --head-motion "
        "--identity --int8 "
        "--lip-closure --loudness-gain --model --no-bilabial-closure --no-blinks --no-lip-closure "
        "--no-pause-gate "
        "--normalize-template --output --overwrite --pause-source "
        "--performance --procedural-mix --quiet --runtime --seed --size --style --summary "
        "--template --text --workers",
    ),
    "render": (["anim"], "--audio --camera --fps --labels --output --overwrite --quiet --size"),
    "export": (["anim"], "--camera --fps --output --overwrite --quiet --size"),
    "synth": (
        [],
        "--engines --languages --multilingual --out --overwrite --quiet --seed --sentences "
        "--subjects --workers",
    ),
    "evaluate": ([], "--data --dataset --json --overwrite --pred --protocol --regions --split"),
    "baseline": ([], "--data --dataset --method --out --quiet --split"),
    "predict": (
        [],
        "--blinks --conditions --corrections --data --dataset --mode --model --out --pause-gate "
        "--quiet --split",
    ),
    "prepare-biwi": (["raw", "out"], "--quiet --regions --subset"),
    "prepare-vocaset": (["raw", "out"], "--quiet"),
    "convert-whisper": (["source"], "--out --overwrite --quiet"),
    "import-checkpoint": (["files"], "--dataset --family --out --overwrite --quiet"),
    "export-onnx": (["model"], "--output --overwrite --quiet"),
    "train": (["recipe", "overrides"], "--devices --num-nodes --quiet --resume --stage"),
    "benchmark": (
        ["config"],
        "--cluster --cpus-per-task --dry-run --only --quiet --skip-ablation --skip-video",
    ),
    "retarget": (
        [],
        "--anim --audio --model --output --overwrite --quiet --source-template --template",
    ),
    "dub": ([], "--anim --audio --model --output --overwrite --quiet --source-template"),
    "rig": (["mesh"], "--landmark --landmarks --output --overwrite --quiet"),
    "export-head": ([], "--identity --output --overwrite --quiet"),
    "serve": (
        [],
        "--avatar --batch-wait-ms --first-message-timeout --host --idle-timeout --jobs "
        "--livelink --max-message-bytes --max-queue --max-seconds --max-sessions --max-upload-mb "
        "--model --port --quiet --request-timeout --runtime --torch-threads --workers",
    ),
    "livelink": (["audio"], "--head-motion --model --no-audio --quiet --seed --subject --to"),
    "info": ([], ""),
}


def test_every_command_and_flag_is_there():
    import argparse

    from talkmesh.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    found = {}
    for name, parser in sub.choices.items():
        options = [o for a in parser._actions for o in a.option_strings if o.startswith("--")]
        positional = [a.dest for a in parser._actions if not a.option_strings]
        found[name] = (positional, " ".join(sorted(set(options) - {"--help"})))
    assert found == COMMANDS


def test_baseline_help_explains_its_choices(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["baseline", "--help"])
    assert exit_.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for name in ("vocaset", "biwi", "synth", "folder"):  # --dataset
        assert name in text
    assert "static: every frame is the subject's neutral template" in text  # --method
    assert "procedural: phones recognised from the audio" in text
    for split in ("train", "val", "test", "test-a", "test-b"):  # --split
        assert split in text
