"""Viseme curves as a file: ``NAME.visemes.json`` holds the 15 Oculus visemes per frame and
Azure's viseme events with their times (:mod:`talkmesh.face.visemes`).

.. code-block:: json

    {"fps": 30.0,
     "source": "phones",
     "oculus": {"names": ["sil", "PP", ...], "frames": [[15 weights], ...]},
     "azure": [{"audioOffset": 0, "visemeId": 0}, {"audioOffset": 1500000, "visemeId": 21}, ...]}

``azure`` is what the Speech SDK's ``VisemeReceived`` events carry (``audioOffset`` in 100 ns
ticks, ``visemeId`` 0-21), so a player written for Azure's viseme stream plays the file as it is;
``source`` says whether the tongue visemes and the ids came from the phones or from the motion.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from talkmesh.animation import Animation
from talkmesh.face.arkit_names import VISEMES
from talkmesh.face.visemes import azure_events, oculus_visemes
from talkmesh.output.arkit_files import arkit_weights_of


def export_visemes_json(anim: Animation, path: Path) -> None:
    """``anim``'s ARKit weights (and phones, if it has them) as Oculus and Azure visemes."""
    weights = arkit_weights_of(anim, path)
    visemes = oculus_visemes(weights, anim.fps, anim.phones)
    doc = {
        "fps": float(anim.fps),
        "source": "phones" if anim.phones else "motion",
        "oculus": {"names": list(VISEMES), "frames": np.round(visemes, 4).tolist()},
        "azure": [
            {"audioOffset": ticks, "visemeId": viseme_id}
            for ticks, viseme_id in azure_events(visemes, anim.fps, anim.phones)
        ],
    }
    path.write_text(json.dumps(doc, separators=(",", ":")) + "\n")
