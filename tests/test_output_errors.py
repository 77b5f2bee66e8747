"""Careless outputs and inputs on the command line: one-line errors, batches that go on, no leftovers."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from talkmesh import cli
from talkmesh.errors import TalkmeshError
from talkmesh.output import write_animation
from talkmesh.output.atomic import remove_stale_temps

CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)
DEAD_PID = 999_999_999  # above any pid Linux hands out (pid_max <= 2**22)


def talkmesh(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, HF_HUB_OFFLINE="1", PYTHONWARNINGS="ignore")
    return subprocess.run(
        [sys.executable, "-m", "talkmesh", *args], capture_output=True, text=True, env=env, cwd=cwd
    )


def error_lines(stderr: str) -> list[str]:
    assert "Traceback" not in stderr and "internal error" not in stderr, stderr
    return [line for line in stderr.splitlines() if line.startswith("talkmesh: error:")]


@pytest.fixture(scope="module")
def anim_file(tmp_path_factory) -> Path:
    import talkmesh
    from talkmesh.output.formats import save_animation

    path = tmp_path_factory.mktemp("anim") / "talk.npz"
    save_animation(talkmesh.animate(CLIP, model="procedural"), path)
    return path


def test_batch_goes_on_past_an_output_whose_parent_is_a_file(tmp_path):
    for stem in "abc":
        shutil.copy(CLIP, tmp_path / f"{stem}.wav")
    (tmp_path / "out_b").write_text("a file where a folder is needed")
    args = ["animate", "a.wav", "b.wav", "c.wav", "--model", "procedural", "-q"]
    proc = talkmesh(*args, "-o", "out_{stem}/talk.npz", cwd=tmp_path)
    assert proc.returncode == 1, proc.stderr
    (line,) = error_lines(proc.stderr)
    assert "out_b/talk.npz" in line and "not a folder" in line, line
    assert "1 of 3 files failed" in proc.stderr
    assert (tmp_path / "out_a" / "talk.npz").is_file() and (
        tmp_path / "out_c" / "talk.npz"
    ).is_file()


def test_export_into_a_file_is_one_line_naming_the_path(tmp_path, anim_file):
    (tmp_path / "blocker").write_text("x")
    proc = talkmesh("export", str(anim_file), "-o", "blocker/talk.glb", cwd=tmp_path)
    assert proc.returncode == 2
    (line,) = error_lines(proc.stderr)
    assert "blocker/talk.glb" in line


def test_render_into_a_file_is_one_line_naming_the_path(tmp_path, anim_file):
    (tmp_path / "blocker").write_text("x")
    proc = talkmesh("render", str(anim_file), "-o", "blocker/talk.mp4", cwd=tmp_path)
    assert proc.returncode == 2
    (line,) = error_lines(proc.stderr)
    assert "blocker/talk.mp4" in line


@pytest.mark.parametrize(
    "code, hint",
    [(errno.ENOSPC, "free some space"), (errno.EACCES, "permissions"), (errno.EROFS, "read-only")],
)
def test_every_oserror_on_output_is_a_user_error(
    tmp_path, anim_file, monkeypatch, capsys, code, hint
):
    import talkmesh.output as output

    def fail(*args, **kwargs):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(output, "_write", fail)
    target = tmp_path / "out.glb"
    with pytest.raises(TalkmeshError, match=hint) as e:
        write_animation(None, target, overwrite=False)
    assert str(target) in str(e.value) and "\n" not in str(e.value)
    assert cli.main(["export", str(anim_file), "-o", str(target)]) == 2
    (line,) = error_lines(capsys.readouterr().err)
    assert str(target) in line and os.strerror(code) in line


def test_stale_temporaries_of_killed_writers_go_on_the_next_write(tmp_path, anim_file):
    dead = tmp_path / f".talkmesh-{DEAD_PID}-x1y2"
    dead.mkdir()
    (dead / "talk.glb").write_bytes(b"half a file")
    dead_video = tmp_path / f".talkmesh-{DEAD_PID}-talk.abc.part.mp4"
    dead_video.write_bytes(b"half a video")
    live = tmp_path / f".talkmesh-{os.getpid()}-busy"  # a writer still at work: kept
    live.mkdir()
    old, new = tmp_path / ".talkmesh-old", tmp_path / ".talkmesh-new"  # no pid: by age
    old.mkdir(), new.mkdir()
    hours_ago = time.time() - 2 * 3600
    os.utime(old, (hours_ago, hours_ago))
    proc = talkmesh("export", str(anim_file), "-o", "talk.glb", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([live.name, new.name, "talk.glb"])
    assert remove_stale_temps(tmp_path) == []


def test_nan_audio_fails_its_file_and_a_cut_short_one_warns(tmp_path):
    wave = (0.3 * np.sin(np.arange(16_000) / 8)).astype(np.float32)
    broken = wave.copy()
    broken[100] = np.nan
    sf.write(tmp_path / "nan.wav", broken, 16_000, subtype="FLOAT")
    sf.write(tmp_path / "cut.wav", np.tile(wave, 3), 16_000, subtype="PCM_16")
    data = (tmp_path / "cut.wav").read_bytes()
    (tmp_path / "cut.wav").write_bytes(data[: 44 + 2 * 16_000])  # header: 3.00 s, data: 1.00 s
    args = ["animate", "nan.wav", "cut.wav", "--model", "procedural", "-q", "-o", "{stem}.npz"]
    proc = talkmesh(*args, cwd=tmp_path)
    assert proc.returncode == 1
    (line,) = error_lines(proc.stderr)
    assert "nan.wav" in line and "NaN or infinite" in line
    assert not (tmp_path / "nan.npz").exists() and (tmp_path / "cut.npz").is_file()
    warning = [w for w in proc.stderr.splitlines() if w.startswith("talkmesh: warning:")]
    assert len(warning) == 1 and "3.00 s" in warning[0] and "1.00 s" in warning[0], proc.stderr
