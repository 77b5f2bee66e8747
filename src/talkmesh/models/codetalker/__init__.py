"""CodeTalker (Xing et al., CVPR 2023): a discrete motion prior and a speech-driven code query.

* ``model.py``: the configs, stage 2 and :class:`CodeTalker` (training graph and ``generate``);
* ``vq.py``: stage 1, the motion VQ-VAE and its quantiser;
* ``generate.py``: the cached generation engine (offline and frame by frame);
* ``batch.py``: the streaming steps of many streams at once;
* ``official.py``: the released ``*_stage1.pth.tar`` + ``*_stage2.pth.tar`` -> a CodeTalker.
"""

from talkmesh.models.codetalker.model import (
    CodeTalker,
    CodeTalkerConfig,
    Stage2Config,
    paper_biwi_config,
    paper_vocaset_config,
    small_synth_config,
)
from talkmesh.models.codetalker.vq import VQConfig

__all__ = [
    "CodeTalker",
    "CodeTalkerConfig",
    "Stage2Config",
    "VQConfig",
    "paper_biwi_config",
    "paper_vocaset_config",
    "small_synth_config",
]
