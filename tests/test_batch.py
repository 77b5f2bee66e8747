"""``talkmesh animate FOLDER_OR_LIST``: a dialogue library in one command. Workers give the same
frames as one process, a bad file is a failed row and never stops the batch, a rerun skips what is
done (also after a kill -9, which leaves no partial output), and bad inputs are one line each."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from talkmesh.batch import AnimateSettings, animate_batch, find_inputs
from talkmesh.cli import main

LIBRIVOX = Path("/usr/share/pocketsphinx/test/data/librivox")
CLIPS = sorted(LIBRIVOX.glob("sense_and_sensibility_01_austen_64kb-08*.wav"))  # 3 real clips

pytestmark = pytest.mark.skipif(len(CLIPS) < 3, reason="pocketsphinx-testdata not installed")


def one_line_errors(err: str) -> list[str]:
    assert "Traceback" not in err, err
    return [ln for ln in err.splitlines() if ln.startswith("talkmesh: error:")]


@pytest.fixture
def library(tmp_path) -> Path:
    """lib/alice/{a1,a2}.wav, lib/bob/b1.wav (real speech) and lib/bob/broken.wav (not audio)."""
    lib = tmp_path / "lib"
    (lib / "alice").mkdir(parents=True)
    (lib / "bob").mkdir()
    for src, dst in zip(CLIPS, ("alice/a1.wav", "alice/a2.wav", "bob/b1.wav")):
        (lib / dst).write_bytes(src.read_bytes())
    (lib / "bob" / "broken.wav").write_bytes(b"RIFF this is not audio\n" * 10)
    (lib / ".hidden").mkdir()
    (lib / ".hidden" / "x.wav").write_bytes(CLIPS[0].read_bytes())  # hidden folders are skipped
    (lib / "notes.md").write_text("not speech")
    return lib


def read_rows(path: Path) -> dict[str, dict[str, str]]:
    with open(path, newline="") as f:
        return {Path(r["file"]).name: r for r in csv.DictReader(f)}


def test_folder_with_a_bad_file_then_resume(library, tmp_path, capsys):
    out = tmp_path / "out"
    args = ["animate", str(library), "-o", f"{out}/{{stem}}.glb", "-o", f"{out}/{{stem}}.npy"]
    args += ["--model", "procedural", "--workers", "2", "-q"]
    assert main(args) == 1  # one file failed
    err = capsys.readouterr().err
    errors = one_line_errors(err)
    assert len(errors) == 1 and "broken.wav" in errors[0]
    assert "1 of 4 files failed (3 animated, 0 already done)" in err
    frames = {n: np.load(out / n).shape[0] for n in ("alice/a1.npy", "alice/a2.npy", "bob/b1.npy")}
    assert all((out / n).with_suffix(".glb").stat().st_size > 0 for n in frames)
    assert not (out / "bob" / "broken.npy").exists() and not (out / ".hidden").exists()
    rows = read_rows(out / "summary.csv")
    assert list(rows) == ["a1.wav", "a2.wav", "b1.wav", "broken.wav"]  # the library's order
    assert rows["broken.wav"]["status"] == "failed" and "broken.wav" in rows["broken.wav"]["error"]
    for name, n in frames.items():
        row = rows[Path(name).with_suffix(".wav").name]
        assert row["status"] == "ok" and int(row["frames"]) == n and not row["error"]
        assert float(row["duration"]) == pytest.approx(n / 30, abs=1 / 30)

    before = {p: p.stat().st_mtime_ns for p in out.rglob("*.npy")}
    (out / "alice" / "a2.glb").unlink()  # as if the batch had stopped between two formats
    assert main(args) == 1
    assert "1 of 4 files failed (1 animated, 2 already done)" in capsys.readouterr().err
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.npy")} == before  # nothing redone
    assert (out / "alice" / "a2.glb").stat().st_size > 0
    again = read_rows(out / "summary.csv")
    assert again["a1.wav"]["status"] == "skipped"
    assert again["a1.wav"]["frames"] == rows["a1.wav"]["frames"]  # kept from the first run
    assert again["a2.wav"]["status"] == "ok"


def test_workers_give_the_frames_of_one_process(library, tmp_path):
    audio = [i.audio for i in find_inputs([library / "alice"])]
    settings = AnimateSettings(model="procedural", seed=3)
    runs = {}
    for workers in (1, 2):
        outs = [[tmp_path / f"w{workers}" / f"{a.stem}.npy"] for a in audio]
        result = animate_batch(audio, outs, settings, workers=workers)
        assert [r.status for r in result.rows] == ["ok", "ok"]
        runs[workers] = [np.load(o[0]) for o in outs]
    for one, two in zip(runs[1], runs[2]):
        # equal to float32 rounding: a worker's BLAS runs one thread, which sums in another order
        np.testing.assert_allclose(one, two, rtol=0, atol=1e-7)


def test_a_list_of_paths(library, tmp_path, capsys):
    listing = library / "lines.txt"
    listing.write_text("# the lines to animate\nalice/a1.wav\n\n" + f"{library / 'bob/b1.wav'}\n")
    out = tmp_path / "out"
    assert (
        main(["animate", str(listing), "-o", f"{out}/{{stem}}.npy", "--model", "procedural"]) == 0
    )
    assert sorted(p.name for p in out.iterdir()) == ["a1.npy", "b1.npy", "summary.csv"]
    assert "animated 2 files" in capsys.readouterr().out


def test_the_model_is_loaded_once_per_worker(library, tmp_path, monkeypatch):
    import talkmesh.models.release as release
    from talkmesh.face.assets import load_head
    from talkmesh.models.voca.model import VOCA

    path = release.save_model(
        VOCA(VOCA.tiny_config(num_vertices=load_head().num_vertices)), tmp_path / "tiny.safetensors"
    )
    loads = []
    real = release.load_model
    monkeypatch.setattr(release, "load_model", lambda *a, **k: loads.append(a) or real(*a, **k))
    audio = [i.audio for i in find_inputs([library / "alice", library / "bob" / "b1.wav"])]
    outs = [[tmp_path / "out" / f"{a.stem}.npy"] for a in audio]
    result = animate_batch(audio, outs, AnimateSettings(model=str(path), pause_gate=False))
    assert [r.status for r in result.rows] == ["ok"] * 3
    assert len(loads) == 1


def test_forked_workers_share_the_model_loaded_once(library, tmp_path, monkeypatch):
    import multiprocessing

    import talkmesh.models.release as release
    from talkmesh.face.assets import load_head
    from talkmesh.models.voca.model import VOCA

    if "fork" not in multiprocessing.get_all_start_methods():
        pytest.skip("workers are spawned here: each loads the model")
    path = release.save_model(
        VOCA(VOCA.tiny_config(num_vertices=load_head().num_vertices)), tmp_path / "tiny.safetensors"
    )
    pids = tmp_path / "pids.txt"  # a worker's own load would be a line with its pid
    real = release.load_model

    def load(*a, **k):
        with open(pids, "a") as f:
            f.write(f"{os.getpid()}\n")
        return real(*a, **k)

    monkeypatch.setattr(release, "load_model", load)
    audio = [i.audio for i in find_inputs([library / "alice", library / "bob" / "b1.wav"])]
    settings = AnimateSettings(model=str(path), pause_gate=False, procedural_mix=0.0)
    frames = {}
    for workers in (1, 2):
        outs = [[tmp_path / f"w{workers}" / f"{a.stem}.npy"] for a in audio]
        result = animate_batch(audio, outs, settings, workers=workers)
        assert [r.status for r in result.rows] == ["ok"] * 3
        assert [r.file for r in result.rows] == [str(a) for a in audio]  # the input order
        frames[workers] = [np.load(o[0]) for o in outs]
    assert pids.read_text().split() == [str(os.getpid())] * 2  # once per run, in this process
    for one, two in zip(frames[1], frames[2]):
        np.testing.assert_allclose(one, two, rtol=0, atol=1e-6)


def test_longest_files_go_first(library, tmp_path):
    from talkmesh.batch.library import COMPRESSED_BYTES_PER_S, Job, longest_first

    lengths = {c: sf.info(c).duration for c in CLIPS}
    mp3 = tmp_path / "x.mp3"  # not probed: its size stands for its length
    mp3.write_bytes(b"\0" * int(COMPRESSED_BYTES_PER_S * (max(lengths.values()) + 1)))
    broken = library / "bob" / "broken.wav"
    jobs = [Job(p, ()) for p in [broken, *CLIPS, mp3, tmp_path / "gone.wav"]]
    order = [j.audio for j in longest_first(jobs)]
    by_length = sorted(CLIPS, key=lambda c: -lengths[c])
    assert order == [mp3, *by_length, broken, tmp_path / "gone.wav"]  # unreadable: 0 s, in order


def outputs(out: Path) -> list[Path]:
    """The animations in ``out``, not the writers' hidden temporaries."""
    found = out.rglob("*") if out.is_dir() else []
    return [
        p for p in found if p.suffix in (".npy", ".glb") and "/." not in f"/{p.relative_to(out)}"
    ]


def test_killed_batch_leaves_no_partial_output_and_resumes(library, tmp_path):
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "talkmesh", "animate", str(library), "-o", f"{out}/{{stem}}.glb"]
    cmd += ["-o", f"{out}/{{stem}}.npy", "--model", "procedural", "-q"]
    env = dict(os.environ, HF_HUB_OFFLINE="1")
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while proc.poll() is None and not outputs(out) and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    survived = {p: p.stat().st_mtime_ns for p in outputs(out)}
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 1 and "1 of 4 files failed" in res.stderr
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == [
        "alice/a1.glb",
        "alice/a1.npy",
        "alice/a2.glb",
        "alice/a2.npy",
        "bob/b1.glb",
        "bob/b1.npy",
        "summary.csv",
    ]  # no temporaries left behind
    for p, mtime in survived.items():  # what the kill left was whole: kept, not redone
        assert p.stat().st_mtime_ns == mtime
    for p in out.rglob("*.npy"):
        seconds = sf.info(library / p.relative_to(out).with_suffix(".wav")).duration
        assert np.load(p).shape[0] == round(seconds * 30)


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc: no psutil needed)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def _running(pid: int) -> bool:
    """``pid`` exists and is not a zombie (a container's pid 1 may never reap one)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["kill -9", "SIGTERM"])
def test_workers_die_with_their_parent(library, tmp_path, sig):
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "talkmesh", "animate", str(library), "-o", f"{out}/{{stem}}.npz"]
    cmd += ["--model", "procedural", "--workers", "2", "-q"]
    env = dict(os.environ, HF_HUB_OFFLINE="1")
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while len(workers := _children(proc.pid)) < 2:
        assert proc.poll() is None and time.monotonic() < deadline, "no workers started"
        time.sleep(0.05)
    proc.send_signal(sig)
    proc.wait(timeout=60)
    try:
        assert proc.returncode == (-signal.SIGKILL if sig == signal.SIGKILL else 128 + sig)
        deadline = time.monotonic() + 10
        while alive := [w for w in workers if _running(w)]:
            assert time.monotonic() < deadline, f"workers {alive} outlived their parent"
            time.sleep(0.1)
    finally:  # a failed run leaves no orphans behind
        for w in workers:
            if _running(w):
                os.kill(w, signal.SIGKILL)


@pytest.mark.parametrize(
    "make, fragment",
    [
        (lambda t: [str(t / "nowhere")], "no such folder"),
        (lambda t: [str(t / "empty")], "no speech files in this folder"),
        (lambda t: [str(t / "missing.txt")], "no such list"),
        (lambda t: [str(t / "blank.txt")], "names no files"),
    ],
)
def test_bad_sources_are_one_line(tmp_path, capsys, make, fragment):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.md").write_text("no audio here")
    (tmp_path / "blank.txt").write_text("# nothing\n\n")
    assert main(["animate", *make(tmp_path), "-o", str(tmp_path / "out") + "/"]) == 2
    errors = one_line_errors(capsys.readouterr().err)
    assert len(errors) == 1 and fragment in errors[0]
    assert not (tmp_path / "out").exists()


def test_output_folder_that_is_a_file(library, tmp_path, capsys):
    taken = tmp_path / "taken"
    taken.write_text("keep me")
    for o in (f"{taken}/", str(taken), f"{taken}/{{stem}}.npy"):
        assert main(["animate", str(library), "-o", o, "--model", "procedural", "-q"]) == 2
        errors = one_line_errors(capsys.readouterr().err)
        assert len(errors) == 1 and "taken" in errors[0] and "a file" in errors[0], errors
    assert taken.read_text() == "keep me"


def test_zero_workers_is_refused(library, tmp_path, capsys):
    assert main(["animate", str(library), "-o", f"{tmp_path}/o/", "--workers", "0"]) == 2
    assert "--workers 0" in one_line_errors(capsys.readouterr().err)[0]


def test_a_worker_limits_the_blas_threads_too():
    """A forked worker inherits numpy's OpenBLAS pool (one thread per core): the worker's share
    of the cores must bound it, or N workers run N x cores spinning BLAS threads."""
    import subprocess
    import sys

    code = (
        "import numpy, threadpoolctl\n"
        "from talkmesh.batch.library import _set_threads\n"
        "_set_threads(1)\n"
        "print(max(i['num_threads'] for i in threadpoolctl.threadpool_info()))\n"
    )
    env = {**os.environ, "OMP_NUM_THREADS": "2", "OPENBLAS_NUM_THREADS": "2"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "1"


def test_a_warning_in_a_batch_names_its_file(library, tmp_path, capsys):
    """Each file's warnings say which file they are about (a transcript word the dictionary
    lacks warns once per file); a warning naming its file already is not prefixed twice."""
    for f in (library / "bob" / "broken.wav", library / "bob" / "b1.wav"):
        f.unlink()
    out = tmp_path / "out"
    args = ["animate", str(library / "alice"), "-o", f"{out}/{{stem}}.npy", "-q"]
    assert main([*args, "--model", "procedural", "--text", "zzqxvw"]) == 0
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "warning" in ln]
    assert len(lines) == 2, lines
    for line, name in zip(sorted(lines), ("a1.wav", "a2.wav")):
        assert line.startswith("talkmesh: warning: ") and name in line and "zzqxvw" in line, line
    import warnings

    from talkmesh.batch.library import warnings_about

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with warnings_about("x.wav"):
            warnings.warn("x.wav: cut off", stacklevel=1)
            warnings.warn("no transcript", stacklevel=1)
    assert [str(w.message) for w in caught] == ["x.wav: cut off", "x.wav: no transcript"]


def test_a_resume_with_nothing_to_do_loads_no_model(library, tmp_path):
    """A rerun whose outputs are all there decides so before importing torch (or scipy) and
    before loading the model: a no-op takes a moment, not the model's start-up. Run in a fresh
    process, where nothing was imported before."""
    (library / "bob" / "broken.wav").unlink()
    out = tmp_path / "out"
    for name in ("alice/a1", "alice/a2", "bob/b1"):
        done = out / f"{name}.glb"
        done.parent.mkdir(parents=True, exist_ok=True)
        done.write_bytes(b"written by an earlier run")
    pattern = f"{out}/{{stem}}.glb"
    code = (
        "import sys\n"
        "from talkmesh.cli import main\n"
        f"rc = main(['animate', {str(library)!r}, '-o', {pattern!r}, '-q'])\n"
        "print(rc, 'torch' in sys.modules, 'scipy' in sys.modules)\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code], env=dict(os.environ), capture_output=True, text=True
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["0", "False", "False"], res.stdout + res.stderr
    rows = read_rows(out / "summary.csv")
    assert {r["status"] for r in rows.values()} == {"skipped"} and len(rows) == 3
    assert (out / "alice" / "a1.glb").read_bytes() == b"written by an earlier run"
