"""``prepare-vocaset``: VOCASET's release files -> what the official preprocessing writes."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fixtures import write_ply
from scipy.io import wavfile

from talkmesh.datasets.reader import VOCASET, open_dataset
from talkmesh.datasets.vocaset import open_verts, prepare_vocaset
from talkmesh.errors import TalkmeshError

SUBJECTS = (VOCASET.train_subjects[0], VOCASET.train_subjects[1])
SENTENCES = ("sentence01", "sentence02")
FRAMES = 5  # at 60 fps on disk
RATE = 22000


def make_release(raw: Path) -> tuple[np.ndarray, dict, dict]:
    """A tiny VOCASET in the release layout: 5023 vertices, shuffled rows, Python-2 pickles."""
    rng = np.random.default_rng(3)
    raw.mkdir(parents=True)
    n = len(SUBJECTS) * len(SENTENCES) * FRAMES
    verts = rng.standard_normal((n, 5023, 3)).astype(np.float32)
    np.save(raw / "data_verts.npy", verts)
    rows = iter(rng.permutation(n).tolist())
    index, audio = {}, {}
    for s in SUBJECTS:
        for t in SENTENCES:
            frames = {f: next(rows) for f in rng.permutation(FRAMES).tolist()}  # unsorted keys too
            index.setdefault(s.encode(), {})[t.encode()] = frames
            samples = (1000 * rng.standard_normal(RATE // 10)).astype(np.int16)
            audio.setdefault(s.encode(), {})[t.encode()] = {
                b"audio": samples,
                b"sample_rate": RATE,
            }
    for name, obj in (("subj_seq_to_idx.pkl", index), ("raw_audio_fixed.pkl", audio)):
        (raw / name).write_bytes(pickle.dumps(obj, protocol=2))
    templates = {s.encode(): rng.standard_normal((5023, 3)) for s in SUBJECTS}
    (raw / "templates.pkl").write_bytes(pickle.dumps(templates, protocol=2))
    write_ply(raw / "FLAME_sample.ply", 5023)
    return verts, index, audio


def test_prepare_vocaset_matches_the_official_layout(tmp_path):
    raw, out = tmp_path / "raw", tmp_path / "out"
    verts, index, audio = make_release(raw)
    written, skipped = prepare_vocaset(raw, out, progress=False)
    assert (written, skipped) == (8, 0)
    for s in SUBJECTS:
        for t in SENTENCES:
            got = np.load(out / "vertices_npy" / f"{s}_{t}.npy")
            rows = list(index[s.encode()][t.encode()].values())  # the pickle's frame order
            assert got.shape == (FRAMES, 15069) and got.dtype == np.float32
            np.testing.assert_array_equal(got, verts[rows].reshape(FRAMES, -1))
            rate, samples = wavfile.read(out / "wav" / f"{s}_{t}.wav")
            entry = audio[s.encode()][t.encode()]
            assert rate == RATE and samples.dtype == np.int16
            np.testing.assert_array_equal(samples, entry[b"audio"])
    assert (out / "templates.pkl").read_bytes() == (raw / "templates.pkl").read_bytes()
    assert (out / "FLAME_sample.ply").read_bytes() == (raw / "FLAME_sample.ply").read_bytes()
    ds = open_dataset("vocaset", out, "train")
    assert sorted(ds.names) == sorted(f"{s}_{t}" for s in SUBJECTS for t in SENTENCES)
    sample = ds[0]
    assert sample.vertices.shape == (3, 5023, 3)  # 60 fps on disk, every second frame read


def test_prepare_vocaset_rerun_skips_finished_files(tmp_path):
    raw, out = tmp_path / "raw", tmp_path / "out"
    make_release(raw)
    prepare_vocaset(raw, out, progress=False)
    done = out / "vertices_npy" / f"{SUBJECTS[0]}_{SENTENCES[0]}.npy"
    stamp = done.stat().st_mtime_ns
    (out / "wav" / f"{SUBJECTS[1]}_{SENTENCES[1]}.wav").unlink()
    assert prepare_vocaset(raw, out, progress=False) == (1, 7)
    assert done.stat().st_mtime_ns == stamp
    assert not [p for p in out.rglob(".*") if p.is_file()]  # no temporary files left


def test_data_verts_is_memory_mapped(tmp_path):
    raw = tmp_path / "raw"
    make_release(raw)
    assert isinstance(open_verts(raw / "data_verts.npy"), np.memmap)


def test_prepare_vocaset_never_runs_code_from_a_pickle(tmp_path):
    raw = tmp_path / "raw"
    make_release(raw)
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    (raw / "subj_seq_to_idx.pkl").write_bytes(pickle.dumps({"s": {"t": Evil()}}, protocol=2))
    with pytest.raises(TalkmeshError, match="unsafe or corrupt pickle"):
        prepare_vocaset(raw, tmp_path / "out", progress=False)
    assert not marker.exists()


def test_prepare_vocaset_names_missing_release_files(tmp_path):
    raw = tmp_path / "raw"
    make_release(raw)
    (raw / "data_verts.npy").unlink()
    with pytest.raises(TalkmeshError, match="data_verts.npy is missing: download VOCASET"):
        prepare_vocaset(raw, tmp_path / "out", progress=False)


def test_prepare_vocaset_rejects_indices_past_the_array(tmp_path):
    raw = tmp_path / "raw"
    make_release(raw)
    index = {b"S": {b"sentence01": {0: 10_000}}}
    (raw / "subj_seq_to_idx.pkl").write_bytes(pickle.dumps(index, protocol=2))
    with pytest.raises(TalkmeshError, match="different releases"):
        prepare_vocaset(raw, tmp_path / "out", progress=False)


def test_prepare_vocaset_cli(tmp_path):
    raw, out = tmp_path / "raw", tmp_path / "out"
    make_release(raw)
    cmd = [sys.executable, "-m", "talkmesh", "prepare-vocaset", str(raw), str(out)]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "wrote 8 files" in res.stdout
    assert "prepare-vocaset" in res.stderr  # the progress bar
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0 and "wrote 0 files" in again.stdout and "8 already" in again.stdout
