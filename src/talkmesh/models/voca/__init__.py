"""VOCA (Cudeiro et al., CVPR 2019): a per-frame regressor from a window of speech features to
vertex offsets.

* ``model.py``: the config, the loss and :class:`VOCA`.
"""

from talkmesh.models.voca.model import VOCA, VOCAConfig, paper_vocaset_config, small_config

__all__ = ["VOCA", "VOCAConfig", "paper_vocaset_config", "small_config"]
