"""FaceFormer (Fan et al., CVPR 2022): speech-driven 3D facial animation with transformers.

* ``model.py``: the config, :class:`FaceFormer` (training graph and ``generate``) and its
  generation loop;
* ``official.py``: the released ``vocaset.pth`` / ``biwi.pth`` -> a FaceFormer.
"""

from talkmesh.models.faceformer.model import (
    FaceFormer,
    FaceFormerConfig,
    biwi_config,
    small_synth_config,
    vocaset_config,
)

__all__ = ["FaceFormer", "FaceFormerConfig", "biwi_config", "small_synth_config", "vocaset_config"]
