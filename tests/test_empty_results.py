"""Empty results are errors: an empty split, or a run that writes nothing, exits non-zero."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fixtures import make_dataset


def talkmesh(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "talkmesh", *args], capture_output=True, text=True, timeout=300
    )


def test_two_subjects_leave_an_empty_test_split_and_baseline_says_so(tmp_path):
    corpus = tmp_path / "corpus"
    res = talkmesh("synth", "--subjects", "2", "--sentences", "2", "--out", str(corpus), "-q")
    if res.returncode != 0 and "no synthetic voices" in res.stderr:
        pytest.fail("synth needs the voices of `make setup`")
    assert res.returncode == 0, res.stderr
    assert "talkmesh: warning: with 2 subject(s) the test split is empty" in res.stderr
    proc = tmp_path / "proc"
    res = talkmesh(
        "baseline",
        "--dataset",
        "synth",
        "--data",
        str(corpus),
        "--method",
        "static",
        "-o",
        str(proc),
    )
    assert res.returncode != 0
    assert "wrote 0" not in res.stdout
    assert "the test split has no sequences" in res.stderr and "--split train" in res.stderr
    assert "--subjects 3" in res.stderr
    res = talkmesh(
        "evaluate",
        "--dataset",
        "synth",
        "--data",
        str(corpus),
        "--pred",
        str(proc),
        "--split",
        "val",
    )
    assert res.returncode != 0 and "the val split has no sequences" in res.stderr
    res = talkmesh(
        "baseline",
        "--dataset",
        "synth",
        "--data",
        str(corpus),
        "--method",
        "static",
        "--split",
        "train",
        "-o",
        str(proc),
    )
    assert res.returncode == 0, res.stderr
    assert "wrote 4 predictions" in res.stdout


def folder(root: Path) -> Path:
    class Spec:
        num_vertices, faces_file = 10, "faces.ply"

    make_dataset(root, Spec, ["alice_s01", "alice_s02"], 6, disk_fps=30, sr=16000)
    (root / "splits.json").write_text(
        json.dumps(
            {
                "train_subjects": ["alice"],
                "fps": 30,
                "splits": {"train": {"alice": ["s01", "s02"]}, "test": {"alice": ["s01", "s02"]}},
            }
        )
    )
    return root


def test_a_run_whose_every_sequence_fails_writes_nothing_and_fails(tmp_path):
    root = folder(tmp_path / "data")
    for name in ("alice_s01", "alice_s02"):
        np.save(root / "vertices_npy" / f"{name}.npy", np.full((6, 30), np.nan, np.float32))
    out = tmp_path / "pred"
    res = talkmesh(
        "baseline", "--dataset", "folder", "--data", str(root), "--method", "static", "-o", str(out)
    )
    assert res.returncode != 0
    assert "talkmesh: warning: skipped alice_s01" in res.stderr
    assert "2 sequences skipped by baseline" in res.stderr
    assert "baseline wrote no predictions" in res.stderr


def test_one_bad_sequence_is_skipped_counted_and_the_run_goes_on(tmp_path):
    root = folder(tmp_path / "data")
    (root / "vertices_npy" / "alice_s02.npy").write_bytes(b"\x93NUMPY broken")
    out = tmp_path / "pred"
    res = talkmesh(
        "baseline", "--dataset", "folder", "--data", str(root), "--method", "static", "-o", str(out)
    )
    assert res.returncode == 0, res.stderr
    assert "skipped alice_s02: alice_s02.npy: truncated" in res.stderr
    assert "1 sequences skipped by baseline" in res.stderr
    assert "wrote 1 predictions" in res.stdout
    assert sorted(p.name for p in out.iterdir()) == ["alice_s01.npy"]


def test_evaluation_skips_a_bad_ground_truth_file_and_counts_it(tmp_path):
    root = folder(tmp_path / "data")
    (root / "regions").mkdir()
    (root / "regions" / "lve.txt").write_text("0,1,2")
    (root / "regions" / "fdd.txt").write_text("3,4,5")
    out = tmp_path / "pred"
    res = talkmesh(
        "baseline",
        "--dataset",
        "folder",
        "--data",
        str(root),
        "--method",
        "static",
        "-o",
        str(out),
        "-q",
    )
    assert res.returncode == 0, res.stderr
    np.save(root / "vertices_npy" / "alice_s02.npy", np.full((6, 30), np.inf, np.float32))
    res = talkmesh(
        "evaluate",
        "--dataset",
        "folder",
        "--data",
        str(root),
        "--pred",
        str(out),
        "--protocol",
        "physical",
    )
    assert res.returncode == 0, res.stderr
    assert "skipped alice_s02" in res.stderr and "1 sequences skipped by evaluation" in res.stderr
    assert "| 1 |" in res.stdout  # one sequence scored
