"""The learned models: one folder per family, the pieces they share beside them.

* ``<family>/`` (``codetalker``, ``faceformer``, ``voca``, ``meshtalk``): the family's model
  (``model.py``) and what only it uses: a quantiser or prior, its generation loop, batching,
  the mapping of the paper's released weights (``official.py``). Its ``__init__`` names the
  family's public classes.
* Shared: :mod:`~talkmesh.models.base` (the :class:`MotionModel` interface every family
  implements), :mod:`~talkmesh.models.registry` (family name -> folder, one line per family),
  :mod:`~talkmesh.models.release` (save/load a release), :mod:`~talkmesh.models.layers` and
  :mod:`~talkmesh.models.postnorm` (transformer layers), the speech encoders
  (:mod:`~talkmesh.models.speech`, :mod:`~talkmesh.models.whisper`, :mod:`~talkmesh.models.mel`,
  :mod:`~talkmesh.models.speech_chunks`, :mod:`~talkmesh.models.frames`),
  :mod:`~talkmesh.models.int8`, and the official-checkpoint reading
  (:mod:`~talkmesh.models.checkpoint_io`, :mod:`~talkmesh.models.official`).

A family folder imports the shared modules and its own files, never another family; the shared
modules reach a family only through the registry's names (docs/architecture.md).
"""
