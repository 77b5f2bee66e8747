"""Region masks on the real topologies: FLAME (VOCASET) and BIWI.

Where they come from (none of these files ship with talkmesh: users have them with the data):

- FLAME: ``FLAME_masks.pkl`` from FLAME's download page (https://flame.is.tue.mpg.de, "FLAME
  Vertex Masks"), a Python-2 pickle of region name -> vertex ids on the 5023-vertex mesh, with
  (among others) ``lips``, ``forehead``, ``eye_region``, ``left_eye_region``, ``right_eye_region``,
  ``nose``, ``left_eyeball``, ``right_eyeball``, ``face``. Put it at ``ROOT/FLAME_masks.pkl`` or
  pass it as ``--regions``. Lips = ``lips``; upper face = ``forehead`` + ``eye_region`` + ``nose``;
  FLAME has no eyelid mask, so the eyelids are the quarter of ``eye_region`` nearest to the
  eyeballs on the neutral template (the skin that closes over them).
- BIWI: CodeTalker's ``BIWI/regions/lve.txt`` (lips) and ``fdd.txt`` (upper face), 0-based,
  comma-separated; an optional ``eyelids.txt`` in the same format adds eyelids.

:func:`region_masks` turns a dataset's regions into MeshTalk's (V,) mouth and upper-face maps
and eyelid ids (binary, as MeshTalk's released masks are).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from talkmesh.datasets.pickles import safe_load_pickle
from talkmesh.errors import TalkmeshError, TalkmeshWarning

LVE_FILE = "lve.txt"
FDD_FILE = "fdd.txt"
EYELIDS_FILE = "eyelids.txt"
FLAME_MASKS_FILE = "FLAME_masks.pkl"  # FLAME's vertex masks, where users of VOCASET keep them
FLAME_VERTICES = 5023
FLAME_UPPER = ("forehead", "eye_region", "nose")
FLAME_EYES = ("eye_region",)
FLAME_EYEBALLS = ("left_eyeball", "right_eyeball")
EYELID_FRACTION = 0.25  # of eye_region, nearest the eyeballs


@dataclass(frozen=True)
class DatasetRegions:
    """Region vertex ids: lve (lips, for lip vertex error), fdd (upper face), eyelids (MeshTalk's
    eyelid loss); None if absent. See :mod:`talkmesh.datasets.regions` for FLAME's and BIWI's."""

    lve: np.ndarray | None = None
    fdd: np.ndarray | None = None
    eyelids: np.ndarray | None = None


def _read_ids(path: Path) -> np.ndarray:
    text = path.read_text().replace("\n", ",").replace(" ", ",")
    try:
        ids = np.array([int(t) for t in text.split(",") if t.strip()], dtype=np.int64)
    except ValueError:
        raise TalkmeshError(f"{path}: expected comma-separated vertex ids") from None
    if len(ids) == 0 or ids.min() < 0:
        raise TalkmeshError(f"{path}: expected non-negative vertex ids")
    return ids


def load_regions(
    directory: str | Path | None, template: np.ndarray | None = None
) -> DatasetRegions:
    """``DIR/lve.txt``, ``DIR/fdd.txt`` and ``DIR/eyelids.txt`` -> :class:`DatasetRegions`
    (missing files give None), or FLAME's ``FLAME_masks.pkl`` (eyelids need the ``template``)."""
    if directory is None:
        return DatasetRegions()
    directory = Path(directory)
    if directory.is_file() and directory.suffix == ".pkl":
        return load_flame_masks(directory, template)
    if not directory.is_dir():
        raise TalkmeshError(f"regions directory not found: {directory}")
    lve, fdd, lids = directory / LVE_FILE, directory / FDD_FILE, directory / EYELIDS_FILE
    return DatasetRegions(
        _read_ids(lve) if lve.is_file() else None,
        _read_ids(fdd) if fdd.is_file() else None,
        _read_ids(lids) if lids.is_file() else None,
    )


def load_flame_masks(path: str | Path, template: np.ndarray | None = None) -> DatasetRegions:
    """``FLAME_masks.pkl`` -> lips (lve), upper face (fdd) and, given the neutral (5023, 3)
    ``template``, eyelids. Read with the safe unpickler: no code in the file can run."""
    path = Path(path)
    obj = safe_load_pickle(path)
    if not isinstance(obj, dict):
        raise TalkmeshError(f"{path}: expected a dict of region name -> vertex ids")
    masks = {
        (k.decode("latin1") if isinstance(k, bytes) else str(k)): np.asarray(v).astype(np.int64)
        for k, v in obj.items()
    }
    needed = ("lips", *FLAME_UPPER, *FLAME_EYEBALLS)
    absent = [k for k in needed if k not in masks]
    if absent:
        raise TalkmeshError(
            f"{path}: no {', '.join(absent)} mask: not FLAME's FLAME_masks.pkl "
            "(download 'FLAME Vertex Masks' from https://flame.is.tue.mpg.de)"
        )
    for name, ids in masks.items():
        if ids.ndim != 1 or (ids.size and (ids.min() < 0 or ids.max() >= FLAME_VERTICES)):
            raise TalkmeshError(f"{path}: mask {name} is not a list of FLAME vertex ids")
    upper = np.unique(np.concatenate([masks[k] for k in FLAME_UPPER]))
    eyelids = None
    if template is not None:
        eyelids = flame_eyelids(masks, np.asarray(template, np.float64))
    return DatasetRegions(lve=np.unique(masks["lips"]), fdd=upper, eyelids=eyelids)


def flame_eyelids(masks: dict[str, np.ndarray], template: np.ndarray) -> np.ndarray:
    """The ``EYELID_FRACTION`` of eye-region vertices nearest to either eyeball."""
    from scipy.spatial import cKDTree

    if template.shape != (FLAME_VERTICES, 3):
        raise TalkmeshError(f"FLAME eyelids need a (5023, 3) template, got {template.shape}")
    eyeballs = np.concatenate([masks[k] for k in FLAME_EYEBALLS])
    region = np.setdiff1d(np.concatenate([masks[k] for k in FLAME_EYES]), eyeballs)
    dist, _ = cKDTree(template[eyeballs]).query(template[region])
    keep = max(1, int(round(EYELID_FRACTION * len(region))))
    return np.sort(region[np.argsort(dist, kind="stable")[:keep]])


class RegionMasks(NamedTuple):
    """MeshTalk's maps: mouth (V,) and upper face (V,) in {0, 1}, eyelid ids (E,)."""

    mouth_weight: np.ndarray | None
    upper_weight: np.ndarray | None
    eyelids: np.ndarray | None


def region_masks(regions: DatasetRegions | None, num_vertices: int) -> RegionMasks:
    """Binary (V,) maps from a dataset's regions; None (uniform) with a warning if it has none."""
    if regions is None or regions.lve is None or regions.fdd is None:
        warnings.warn(
            f"no lip and upper-face regions for this {num_vertices}-vertex topology: MeshTalk's "
            "cross-modality loss weighs every vertex alike (put FLAME_masks.pkl or "
            "regions/lve.txt + fdd.txt in the dataset, or set data.regions)",
            TalkmeshWarning,
            stacklevel=2,
        )
        return RegionMasks(None, None, None)
    maps = []
    for name, ids in (("lip", regions.lve), ("upper-face", regions.fdd)):
        if ids.max() >= num_vertices:
            raise TalkmeshError(
                f"{name} region ids reach {ids.max()}, the mesh has {num_vertices} vertices"
            )
        w = np.zeros(num_vertices, np.float32)
        w[ids] = 1.0
        maps.append(w)
    eyelids = regions.eyelids
    if eyelids is None:
        warnings.warn(
            "no eyelid vertices in the dataset's regions: MeshTalk's eyelid loss is off "
            f"(add regions/{EYELIDS_FILE})",
            TalkmeshWarning,
            stacklevel=2,
        )
    elif eyelids.max() >= num_vertices:
        raise TalkmeshError(f"eyelid ids reach {eyelids.max()}, the mesh has {num_vertices}")
    return RegionMasks(maps[0], maps[1], eyelids)
