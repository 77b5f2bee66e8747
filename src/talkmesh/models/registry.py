"""The learned model families, by the name releases store (``family`` in the metadata).

Each family is one folder of this package, ``talkmesh/models/<family>/``, and one line of
:data:`FAMILY_MODELS` naming the folder and its :class:`talkmesh.models.base.MotionModel`
subclass as ``"package:Class"``. A folder is imported only when its family is asked for, so
loading a CodeTalker release does not import MeshTalk. A folder with an ``official.py`` that
defines ``import_official(paths, dataset)`` can also import the paper's released weights
(:func:`talkmesh.models.official.import_checkpoint`). Adding a family: docs/adding-a-model.md.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from talkmesh.models.base import MotionModel

# family name (stored in releases: never rename one) -> "the family's folder:its MotionModel"
FAMILY_MODELS: dict[str, str] = {
    "codetalker": "talkmesh.models.codetalker:CodeTalker",
    "faceformer": "talkmesh.models.faceformer:FaceFormer",
    "voca": "talkmesh.models.voca:VOCA",
    "meshtalk": "talkmesh.models.meshtalk:MeshTalkModel",
}


def family_package(name: str) -> str:
    """The dotted name of family ``name``'s folder, e.g. ``"talkmesh.models.codetalker"``."""
    return FAMILY_MODELS[name].split(":")[0]


def official_families() -> tuple[str, ...]:
    """The families whose folder has an ``official.py`` (``talkmesh import-checkpoint``), read off
    the files without importing the folders (the CLI lists them without importing torch)."""
    found = []
    for name in FAMILY_MODELS:
        spec = importlib.util.find_spec(family_package(name))  # imports talkmesh.models only
        folders = (spec.submodule_search_locations or []) if spec else []
        if any((Path(folder) / "official.py").is_file() for folder in folders):
            found.append(name)
    return tuple(found)


class _Families(Mapping[str, "type[MotionModel]"]):
    """family name -> its MotionModel subclass, importing the family's folder on first use."""

    def __getitem__(self, name: str) -> type[MotionModel]:
        package, attr = FAMILY_MODELS[name].split(":")  # KeyError for an unknown family
        return getattr(importlib.import_module(package), attr)

    def __iter__(self) -> Iterator[str]:
        return iter(FAMILY_MODELS)

    def __len__(self) -> int:
        return len(FAMILY_MODELS)

    def __contains__(self, name: object) -> bool:
        return name in FAMILY_MODELS

    def __repr__(self) -> str:
        return f"FAMILIES({', '.join(FAMILY_MODELS)})"


FAMILIES: Mapping[str, type[MotionModel]] = _Families()
