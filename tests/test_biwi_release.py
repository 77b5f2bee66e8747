"""``prepare-biwi`` on BIWI's release layout: .vl frames, rigid-scan templates, .flv audio."""

from __future__ import annotations

import io
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from fixtures import write_wav

from talkmesh.datasets.biwi import prepare_biwi_release, read_obj, read_vl
from talkmesh.datasets.reader import load_templates, open_dataset
from talkmesh.errors import TalkmeshError

ROWS, COLS = 95, 246  # 23370 vertices, BIWI's count


def grid_faces() -> np.ndarray:
    idx = np.arange(ROWS * COLS).reshape(ROWS, COLS)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    return np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)]
    )


def grid(rng, scale: float) -> np.ndarray:
    y, x = np.meshgrid(np.arange(ROWS), np.arange(COLS), indexing="ij")
    z = np.sin(x / 9.0) + 0.1 * rng.standard_normal(x.shape)
    return (scale * np.stack([x, y, z], -1).reshape(-1, 3) + [5, 7, 9]).astype(np.float32)


def vl_bytes(v: np.ndarray) -> bytes:
    return np.uint32(len(v)).tobytes() + np.asarray(v, "<f4").tobytes()


def write_obj(path: Path, v: np.ndarray, faces: np.ndarray) -> None:
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in v] + ["vt 0.5 0.5"]
    lines += [f"f {a + 1}/1 {b + 1}/1 {c + 1}/1" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def expected(v: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """CodeTalker's per-frame normalisation, computed independently with trimesh."""
    r = np.asarray(v, np.float64) @ np.diag([1.0, -1.0, -1.0])  # V * rotx(pi), row vectors
    r = r - r.mean(axis=0)
    return r / np.sqrt(trimesh.Trimesh(r, faces, process=False).area)


def make_release(raw: Path) -> dict[str, list[np.ndarray]]:
    """F2: e01 (folder of .vl), e02 (a .tar), e03 (a truncated frame); F1: e37 (audio in .flv)."""
    rng = np.random.default_rng(0)
    faces = grid_faces()
    (raw / "rigid_scans").mkdir(parents=True)
    (raw / "wav").mkdir()
    seqs = {}
    for subject in ("F2", "F1"):
        write_obj(raw / "rigid_scans" / f"{subject}.obj", grid(rng, 2.0), faces)
    for subject, sentence in (("F2", "e01"), ("F2", "e02"), ("F2", "e03"), ("F1", "e37")):
        frames = [grid(rng, 2.0 + 0.1 * k) for k in range(3)]
        seqs[f"{subject}_{sentence}"] = frames
        folder = raw / "faces" / subject / sentence
        if sentence == "e02":
            folder.parent.mkdir(parents=True, exist_ok=True)
            with tarfile.open(folder.parent / "e02.tar", "w") as tar:
                for k, v in reversed(list(enumerate(frames))):  # stored out of order
                    data = vl_bytes(v)
                    info = tarfile.TarInfo(f"e02/frame_{k + 1:03d}.vl")
                    info.size = len(data)
                    tar.addfile(info, io.BytesIO(data))
        else:
            folder.mkdir(parents=True)
            for k, v in enumerate(frames):
                (folder / f"frame_{k + 1:03d}.vl").write_bytes(vl_bytes(v))
        if sentence == "e03":
            (folder / "frame_002.vl").write_bytes(vl_bytes(frames[1])[:-7])
        if subject == "F1":
            from imageio_ffmpeg import get_ffmpeg_exe

            (raw / "videos").mkdir()
            src = "sine=frequency=300:duration=0.2:sample_rate=22050"
            cmd = [get_ffmpeg_exe(), "-loglevel", "error", "-f", "lavfi", "-i", src]
            subprocess.run([*cmd, str(raw / "videos" / "F1_e37.flv")], check=True)
        else:
            write_wav(raw / "wav" / f"{subject}_{sentence}.wav", 0.12, 44100)
    return seqs


def test_vl_round_trip_and_truncation():
    v = np.arange(12, dtype=np.float32).reshape(4, 3)
    np.testing.assert_array_equal(read_vl(vl_bytes(v), "x.vl"), v)
    with pytest.raises(TalkmeshError, match="truncated .vl"):
        read_vl(vl_bytes(v)[:-1], "x.vl")


def test_prepare_biwi_release_follows_codetalker(tmp_path):
    raw, out = tmp_path / "raw", tmp_path / "out"
    seqs = make_release(raw)
    faces = grid_faces()
    with pytest.warns(UserWarning, match="skipped F2_e03: .*truncated"):
        done = prepare_biwi_release(raw, out, progress=False)
    assert (done.written, done.existing, done.skipped) == (3, 0, ["F2_e03"])
    for name in ("F2_e01", "F2_e02", "F1_e37"):
        got = np.load(out / "vertices_npy" / f"{name}.npy")
        assert got.shape == (3, 23370 * 3)
        want = np.stack([expected(v, faces) for v in seqs[name]])
        np.testing.assert_allclose(got.reshape(3, -1, 3), want, atol=1e-9)
    scan, _ = read_obj(raw / "rigid_scans" / "F2.obj")
    templates = load_templates(out / "templates.pkl")
    np.testing.assert_allclose(templates["F2"], expected(scan, faces), atol=1e-6)
    assert sorted(templates) == ["F1", "F2"]
    import soundfile as sf

    assert sf.info(out / "wav" / "F1_e37.wav").samplerate == 44100  # extracted like video2audio
    assert (out / "BIWI.ply").is_file()
    ds = open_dataset("biwi", out, "train")
    assert ds.names == ["F2_e01", "F2_e02"]
    assert ds[1].vertices.shape == (3, 23370, 3)
    with pytest.warns(UserWarning, match="skipped F2_e03"):
        again = prepare_biwi_release(raw, out, progress=False)
    assert (again.written, again.existing) == (0, 3)


def test_prepare_biwi_release_subset_and_missing_parts(tmp_path):
    raw = tmp_path / "raw"
    make_release(raw)
    with pytest.warns(UserWarning):
        done = prepare_biwi_release(raw, tmp_path / "six", subset="biwi6", progress=False)
    assert done.written == 2 and not (tmp_path / "six" / "vertices_npy" / "F1_e37.npy").exists()
    (raw / "rigid_scans" / "F1.obj").unlink()
    with pytest.raises(TalkmeshError, match="F1.obj is missing: the neutral templates"):
        prepare_biwi_release(raw, tmp_path / "out", progress=False)
    with pytest.raises(TalkmeshError, match="faces is missing: request BIWI"):
        prepare_biwi_release(tmp_path / "nothing", tmp_path / "out", progress=False)


def test_prepare_biwi_cli_on_the_release(tmp_path):
    raw, out = tmp_path / "raw", tmp_path / "out"
    make_release(raw)
    regions = tmp_path / "regions"
    regions.mkdir()
    (regions / "lve.txt").write_text("1, 2, 3")
    (regions / "fdd.txt").write_text("4, 5")
    cmd = [sys.executable, "-m", "talkmesh", "prepare-biwi", str(raw)]
    res = subprocess.run([*cmd, str(out)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "talkmesh: warning: skipped F2_e03" in res.stderr
    assert "wrote 3 sequences" in res.stdout and "1 sequences skipped: F2_e03" in res.stdout
    assert "copy CodeTalker's BIWI/regions/" in res.stdout
    res = subprocess.run(
        [*cmd, str(out), "-q", "--regions", str(regions)], capture_output=True, text=True
    )
    assert res.returncode == 0, res.stderr
    assert (out / "regions" / "lve.txt").read_text() == "1, 2, 3"
