"""MeshTalk (Richard et al., ICCV 2021): a categorical expression space and an audio-conditioned
prior.

* ``model.py``: the configs, the expression space :class:`MeshTalk` and the release
  :class:`MeshTalkModel` (expression space + prior behind the model interface);
* ``layers.py``: the expression encoder, the fusion quantiser and the template decoder;
* ``prior.py``: the autoregressive prior over expression codes (talkmesh's layout);
* ``context.py``: the same prior in the official ``ContextModel`` layout;
* ``official.py``: the released ``pretrained_models`` files -> a MeshTalkModel.
"""

from talkmesh.models.meshtalk.model import (
    MeshTalk,
    MeshTalkConfig,
    MeshTalkModel,
    MeshTalkModelConfig,
    SamplingConfig,
    meshtalk_config,
)
from talkmesh.models.meshtalk.prior import PriorConfig, prior_config

__all__ = [
    "MeshTalk",
    "MeshTalkConfig",
    "MeshTalkModel",
    "MeshTalkModelConfig",
    "PriorConfig",
    "SamplingConfig",
    "meshtalk_config",
    "prior_config",
]
