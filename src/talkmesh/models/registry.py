"""The learned model families, by the name releases store (``family`` in the metadata).

Adding a family: one file in this package with a :class:`talkmesh.models.base.MotionModel`
subclass, and one line here (docs/adding-a-model.md).
"""

from __future__ import annotations

from talkmesh.models.base import MotionModel
from talkmesh.models.codetalker import CodeTalker
from talkmesh.models.faceformer import FaceFormer
from talkmesh.models.meshtalk import MeshTalkModel
from talkmesh.models.voca import VOCA

FAMILIES: dict[str, type[MotionModel]] = {
    cls.family: cls
    for cls in (
        CodeTalker,
        FaceFormer,
        VOCA,
        MeshTalkModel,
    )
}
