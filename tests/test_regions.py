"""Region masks on FLAME (FLAME_masks.pkl) and BIWI (CodeTalker's region files), and MeshTalk
training on a VOCASET-layout dataset with them."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fixtures import make_dataset

from talkmesh.datasets.reader import BIWI, VOCASET, DatasetRegions, open_dataset
from talkmesh.datasets.regions import load_flame_masks, region_masks
from talkmesh.errors import TalkmeshError, TalkmeshWarning

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "tests" / "recipes" / "meshtalk_expression.yaml"


def flame_masks() -> dict[str, np.ndarray]:
    """The structure of FLAME's FLAME_masks.pkl (region -> vertex ids), made-up ids."""
    ids = np.random.default_rng(0).permutation(5023)
    parts = {
        "lips": 250,
        "forehead": 300,
        "left_eye_region": 200,
        "right_eye_region": 200,
        "nose": 150,
        "left_eyeball": 50,
        "right_eyeball": 50,
        "neck": 400,
        "scalp": 600,
        "left_ear": 100,
        "right_ear": 100,
        "boundary": 80,
    }
    out, start = {}, 0
    for name, n in parts.items():
        out[name] = np.sort(ids[start : start + n])
        start += n
    out["eye_region"] = np.concatenate([out["left_eye_region"], out["right_eye_region"]])
    out["face"] = np.concatenate([out[k] for k in ("lips", "forehead", "eye_region", "nose")])
    return out


def write_masks(path: Path, masks: dict[str, np.ndarray]) -> None:
    path.write_bytes(pickle.dumps(masks, protocol=2))


def template_around_eyes(masks) -> np.ndarray:
    """Eye-region vertices at known distances from the eyeballs."""
    t = np.random.default_rng(1).uniform(-1, 1, (5023, 3)) + [0, 0, 5]
    t[masks["left_eyeball"]] = [0, 0, 0]
    t[masks["right_eyeball"]] = [0, 0, 0]
    region = masks["eye_region"]
    t[region] = np.linspace(0.01, 2.0, len(region))[:, None] * [1, 0, 0]
    return t


def test_flame_masks_give_lips_upper_face_and_eyelids(tmp_path):
    masks = flame_masks()
    write_masks(tmp_path / "FLAME_masks.pkl", masks)
    t = template_around_eyes(masks)
    r = load_flame_masks(tmp_path / "FLAME_masks.pkl", t)
    assert r.lve.tolist() == sorted(masks["lips"].tolist())
    upper = np.concatenate([masks["forehead"], masks["eye_region"], masks["nose"]])
    assert r.fdd.tolist() == sorted(upper.tolist())
    assert len(r.eyelids) == 100  # a quarter of the 400 eye-region vertices, the nearest ones
    assert r.eyelids.tolist() == sorted(masks["eye_region"][:100].tolist())


def test_flame_masks_are_read_safely_and_checked(tmp_path):
    masks = flame_masks()
    del masks["lips"]
    write_masks(tmp_path / "m.pkl", masks)
    with pytest.raises(TalkmeshError, match="no lips mask: not FLAME's"):
        load_flame_masks(tmp_path / "m.pkl")
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    (tmp_path / "e.pkl").write_bytes(pickle.dumps({"lips": Evil()}, protocol=2))
    with pytest.raises(TalkmeshError, match="unsafe"):
        load_flame_masks(tmp_path / "e.pkl")
    assert not marker.exists()


def vocaset_root(root: Path, masks: bool = True) -> Path:
    names = [f"{VOCASET.train_subjects[0]}_sentence0{k}" for k in (1, 2, 3)]
    make_dataset(root, VOCASET, names, frames=16, disk_fps=60, sr=22050, python2_pickle=True)
    if masks:
        write_masks(root / "FLAME_masks.pkl", flame_masks())
    return root


def test_vocaset_finds_flame_masks_in_its_root(tmp_path):
    ds = open_dataset("vocaset", vocaset_root(tmp_path / "v"), "train")
    assert ds.regions.lve is not None and ds.regions.fdd is not None
    assert ds.regions.eyelids is not None and len(ds.regions.eyelids) == 100


def test_biwi_region_files_with_and_without_eyelids(tmp_path):
    regions = tmp_path / "regions"
    regions.mkdir()
    (regions / "lve.txt").write_text("1, 2, 3")
    (regions / "fdd.txt").write_text("10, 11")
    make_dataset(tmp_path / "b", BIWI, ["F2_e01"], frames=2, disk_fps=25, sr=16000)
    ds = open_dataset("biwi", tmp_path / "b", "train", regions=regions)
    with pytest.warns(TalkmeshWarning, match="no eyelid vertices"):
        m = region_masks(ds.regions, 23370)
    assert m.mouth_weight[[1, 2, 3]].tolist() == [1, 1, 1] and m.mouth_weight.sum() == 3
    assert m.upper_weight.sum() == 2 and m.eyelids is None
    (regions / "eyelids.txt").write_text("20,21")
    ds = open_dataset("biwi", tmp_path / "b", "train", regions=regions)
    assert region_masks(ds.regions, 23370).eyelids.tolist() == [20, 21]


def test_no_regions_means_uniform_maps_with_a_warning():
    with pytest.warns(TalkmeshWarning, match="weighs every vertex alike"):
        assert region_masks(DatasetRegions(), 100) == (None, None, None)
    with pytest.raises(TalkmeshError, match="reach 500"):
        region_masks(DatasetRegions(np.array([500]), np.array([1])), 100)


def test_meshtalk_trains_on_vocaset_with_flame_masks_and_skips_a_bad_file(tmp_path):
    root = vocaset_root(tmp_path / "v")
    bad = np.load(root / "vertices_npy" / f"{VOCASET.train_subjects[0]}_sentence03.npy")
    bad[4, 7] = np.nan  # an even row: VOCASET readers take every second frame
    np.save(root / "vertices_npy" / f"{VOCASET.train_subjects[0]}_sentence03.npy", bad)
    out = tmp_path / "run"
    args = [
        f"data.root={root}",
        "data.kind=vocaset",
        f"train.out_dir={out}",
        "train.epochs=1",
        "data.batch_size=1",
        "data.max_seconds=0",
        "train.accelerator=cpu",
        "model.expression_widths=[16,16]",
        "model.decoder_widths=[16,16]",
        "model.fusion_width=16",
        "train.lr_step_size=1",
        "train.lr_step_unit=step",
        "train.lr_gamma=0.5",
    ]
    res = subprocess.run(
        [sys.executable, "-m", "talkmesh", "train", str(RECIPE), *args, "-q"],
        capture_output=True,
        text=True,
        timeout=600,
        env=dict(os.environ, HF_HUB_OFFLINE="1"),
    )
    assert res.returncode == 0, res.stderr
    assert "skipped FaceTalk_170728_03272_TA_sentence03" in res.stderr
    assert "1 sequences skipped by training" in res.stderr
    from safetensors import safe_open

    with safe_open(str(out / "model.safetensors"), "pt") as f:
        keys = {k: f.get_tensor(k) for k in f.keys() if k.endswith(("mouth_weight", "eyelid_mask"))}
    mouth = next(v for k, v in keys.items() if k.endswith("mouth_weight"))
    lids = next(v for k, v in keys.items() if k.endswith("eyelid_mask"))
    assert sorted(np.flatnonzero(mouth.numpy()).tolist()) == sorted(flame_masks()["lips"].tolist())
    assert int(lids.sum()) == 100
