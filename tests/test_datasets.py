from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
from fixtures import make_biwi, make_dataset, make_vocaset, write_wav

from talkmesh.datasets.reader import (
    BIWI,
    VOCASET,
    VOCASET_TEST,
    VOCASET_TRAIN,
    collate,
    load_regions,
    open_dataset,
    report_skipped,
    safe_load_pickle,
)
from talkmesh.errors import TalkmeshError, TalkmeshWarning


@pytest.fixture(scope="module")
def vocaset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("vocaset")
    make_vocaset(root)
    return root


@pytest.fixture(scope="module")
def biwi(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("biwi")
    make_biwi(root)
    return root


def test_vocaset_official_splits_skip_missing_pairs(vocaset):
    train = open_dataset("vocaset", vocaset, "train")
    expected = [f"{s}_sentence{k:02d}" for s in VOCASET_TRAIN for k in range(1, 41)]
    present = {p.stem for p in (vocaset / "vertices_npy").glob("*.npy")}
    assert train.names == [n for n in expected if n in present]
    assert len(train.skipped) == len(expected) - len(train.names) > 0
    test = open_dataset("vocaset", vocaset, "test")
    assert {n.rpartition("_")[0] for n in test.names} == set(VOCASET_TEST)
    assert {n.rpartition("_")[2] for n in test.names} == {f"sentence{k}" for k in range(21, 41)}
    assert len(open_dataset("vocaset", vocaset, "val")) == 40


def test_vocaset_sample_is_30fps_float32_with_style(vocaset):
    train = open_dataset("vocaset", vocaset, "train")
    sample = train[0]
    raw = np.load(vocaset / "vertices_npy" / f"{sample.name}.npy")
    assert raw.shape == (4, 5023 * 3)
    assert sample.vertices.shape == (2, 5023, 3)  # 60 fps on disk, every second frame
    np.testing.assert_array_equal(sample.vertices[1], raw[2].reshape(-1, 3))
    assert sample.vertices.dtype == np.float32 and sample.template.dtype == np.float32
    assert sample.audio.dtype == np.float32 and len(sample.audio) == round(2 * 16000 / 30)
    assert sample.style == VOCASET_TRAIN.index(sample.subject)
    assert open_dataset("vocaset", vocaset, "test")[0].style == -1
    assert train.regions.lve is None  # VOCASET ships no region files
    assert train.faces.shape[1] == 3


def test_biwi_official_splits_and_regions(biwi):
    for split in ("train", "val", "test", "test-a", "test-b"):
        ds = open_dataset("biwi", biwi, split)
        official = {f"{s}_{n}" for s, sents in BIWI.splits[split].items() for n in sents}
        assert set(ds.names) <= official and len(ds.names) == 2 * len(BIWI.splits[split])
    assert open_dataset("biwi", biwi, "test-a").names == open_dataset("biwi", biwi, "test").names
    assert {n[:2] for n in open_dataset("biwi", biwi, "test-b").names} == {
        "F1",
        "F5",
        "F6",
        "F7",
        "F8",
        "M1",
        "M2",
        "M6",
    }
    ds = open_dataset("biwi", biwi, "train")
    sample = ds[0]
    assert (
        sample.vertices.shape == (2, 23370, 3) and sample.vertices.dtype == np.float32
    )  # float64 on disk
    assert len(sample.audio) == round(2 / 25 * 16000)  # 44.1 kHz resampled to 16 kHz
    assert ds.regions.lve.shape == (4996,) and ds.regions.fdd.shape == (7784,)


def test_collate_pads_and_masks(vocaset):
    ds = open_dataset("vocaset", vocaset, "train")
    a, b = ds[0], ds[1]
    b = b._replace(vertices=np.concatenate([b.vertices] * 3), audio=np.concatenate([b.audio] * 3))
    batch = collate([a, b])
    assert batch.vertices.shape == (2, 6, 5023, 3)
    assert batch.motion_mask.tolist() == [[True] * 2 + [False] * 4, [True] * 6]
    assert batch.audio_lengths.tolist() == [len(a.audio), len(b.audio)]
    assert (batch.audio[0, len(a.audio) :] == 0).all()
    np.testing.assert_array_equal(batch.vertices[0, 2], a.template)  # padding rests at the template


def test_unknown_kind_and_split(vocaset):
    with pytest.raises(TalkmeshError, match="unknown dataset kind 'voca'"):
        open_dataset("voca", vocaset)
    with pytest.raises(TalkmeshError, match="no split 'test-b'.*train, val, test"):
        open_dataset("vocaset", vocaset, "test-b")
    with pytest.raises(TalkmeshError, match="not found"):
        open_dataset("vocaset", vocaset / "nope")


class Exploit:
    def __init__(self, target: Path):
        self.target = str(target)

    def __reduce__(self):
        return (Path.touch, (Path(self.target),))


def test_malicious_pickle_is_refused_and_never_runs(tmp_path):
    target = tmp_path / "pwned"
    path = tmp_path / "templates.pkl"
    path.write_bytes(pickle.dumps({"subject": Exploit(target)}))
    with pytest.raises(TalkmeshError, match="templates.pkl.*unsafe"):
        safe_load_pickle(path)
    assert not target.exists()


def test_safe_pickle_reads_python2_style_arrays(tmp_path):
    path = tmp_path / "t.pkl"
    data = {b"A": np.arange(6.0).reshape(2, 3)}
    path.write_bytes(pickle.dumps(data, protocol=2))
    out = safe_load_pickle(path)
    np.testing.assert_array_equal(out[b"A"], data[b"A"])


def small_folder(root: Path, frames: int = 6) -> Path:
    import json

    class Spec:
        num_vertices, faces_file = 10, "faces.ply"

    make_dataset(root, Spec, ["alice_s01", "alice_s02", "bob_s01"], frames, disk_fps=30, sr=16000)
    (root / "splits.json").write_text(
        json.dumps(
            {
                "train_subjects": ["alice"],
                "fps": 30,
                "motion_fps": 30,
                "splits": {"train": {"alice": ["s01", "s02"]}, "test": {"bob": ["s01"]}},
            }
        )
    )
    return root


def test_folder_dataset(tmp_path):
    root = small_folder(tmp_path)
    ds = open_dataset("folder", root, "train")
    assert ds.names == ["alice_s01", "alice_s02"]
    assert ds[0].vertices.shape == (6, 10, 3)
    assert open_dataset("folder", root, "test")[0].style == -1


@pytest.mark.parametrize(
    "damage, fragment",
    [
        ("truncate", "alice_s01.npy: truncated"),
        ("width", "alice_s01.npy: shape"),
        ("short_wav", "alice_s01.wav"),
        ("bad_wav", "alice_s01.wav: not readable audio"),
        ("one_frame", "too short"),
    ],
)
def test_bad_sequence_is_skipped_with_a_warning_naming_it(tmp_path, damage, fragment):
    root = small_folder(tmp_path)
    npy, wav = root / "vertices_npy" / "alice_s01.npy", root / "wav" / "alice_s01.wav"
    if damage == "truncate":
        npy.write_bytes(npy.read_bytes()[:-40])
    elif damage == "width":
        np.save(npy, np.zeros((6, 33), np.float32))
    elif damage == "short_wav":
        write_wav(wav, 2 / 30, 16000)  # 2 frames of audio for 6 of motion
    elif damage == "bad_wav":
        wav.write_bytes(b"RIFF\x00\x00")
    elif damage == "one_frame":
        np.save(npy, np.zeros((1, 30), np.float32))
    with pytest.warns(TalkmeshWarning, match=f"skipped alice_s01: .*{fragment}"):
        ds = open_dataset("folder", root, "train")
    assert ds.names == ["alice_s02"] and ds.bad == ["alice_s01"]
    assert ds[0].name == "alice_s02"


def test_a_file_failing_at_load_time_is_skipped_and_counted(tmp_path):
    root = small_folder(tmp_path)
    bad = np.zeros((6, 30), np.float32)
    bad[2, 4] = np.nan  # only the full read sees it
    np.save(root / "vertices_npy" / "alice_s01.npy", bad)
    ds = open_dataset("folder", root, "train")
    assert ds.names == ["alice_s01", "alice_s02"]
    with pytest.warns(TalkmeshWarning, match="skipped alice_s01: .*NaN"):
        sample = ds.sample_or_next(0)
    assert sample.name == "alice_s02" and ds.bad == ["alice_s01"]
    with pytest.warns(TalkmeshWarning, match="1 sequences skipped by training"):
        assert report_skipped(ds, "training") == 1


def test_an_empty_split_is_an_error_naming_the_splits_with_data(tmp_path):
    root = small_folder(tmp_path)
    (root / "vertices_npy" / "bob_s01.npy").unlink()
    with pytest.raises(TalkmeshError, match="test split has no sequences .*--split train"):
        open_dataset("folder", root, "test")
    assert len(open_dataset("folder", root, "test", allow_empty=True)) == 0


def test_a_corrupt_template_file_is_an_error(tmp_path):
    root = small_folder(tmp_path)
    (root / "templates.pkl").write_bytes(b"\x80\x02}q\x00(X")  # cut short
    with pytest.raises(TalkmeshError, match="templates.pkl"):
        open_dataset("folder", root, "train")


def test_template_vertex_count_mismatch(tmp_path, vocaset):
    import shutil

    root = tmp_path / "v"
    shutil.copytree(vocaset, root)
    templates = pickle.loads((root / "templates.pkl").read_bytes(), encoding="latin1")
    templates[VOCASET_TRAIN[0].encode()] = np.zeros((100, 3))
    (root / "templates.pkl").write_bytes(pickle.dumps(templates, protocol=2))
    with pytest.raises(TalkmeshError, match="templates.pkl: template of .* has 100 vertices"):
        open_dataset("vocaset", root, "train")


def test_regions_files(tmp_path):
    (tmp_path / "lve.txt").write_text("1, 2,3\n4")
    (tmp_path / "fdd.txt").write_text("x,y")
    with pytest.raises(TalkmeshError, match="fdd.txt"):
        load_regions(tmp_path)
    (tmp_path / "fdd.txt").write_text("7")
    r = load_regions(tmp_path)
    assert r.lve.tolist() == [1, 2, 3, 4] and r.fdd.tolist() == [7]
    assert VOCASET.num_vertices == 5023
