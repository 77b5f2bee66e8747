"""VRM expressions: the presets a VRoid / VRM avatar binds to its morph targets, driven from ARKit
weights when the avatar has no ARKit mouth shapes of its own.

VRM 1.0 (``extensions.VRMC_vrm.expressions.preset``) names ``aa ih ou ee oh`` (the mouth),
``blink blinkLeft blinkRight``, ``lookUp lookDown lookLeft lookRight`` and the emotions; each
preset's ``morphTargetBinds`` are ``{node, index, weight 0-1}``. VRM 0.x
(``extensions.VRM.blendShapeMaster.blendShapeGroups``) calls them ``a i u e o``, ``blink
blink_l blink_r``, ``lookup lookdown lookleft lookright``, with ``binds`` of ``{mesh, index,
weight 0-100}``. Both are read into one :class:`Expressions`: for every preset driven here, the
(mesh, morph target, weight) it binds. The emotion presets are left alone (speech does not say
how the speaker feels); the ``material`` and ``texture`` binds are not animated by glTF clips.

Preset weights per frame (:func:`preset_weights`): the mouth presets are the Oculus vowels of
:mod:`talkmesh.face.visemes` (``aa`` = ``aa``, ``ih`` = ``I``, ``ou`` = ``U``, ``ee`` = ``E``,
``oh`` = ``O``); ``blinkLeft`` / ``blinkRight`` are ``eyeBlinkLeft`` / ``eyeBlinkRight``, and
``blink`` is their smaller one (both eyes shut) when the avatar has no one-eye presets, else the
one-eye presets carry it; ``lookUp`` is the mean of both eyes' ``eyeLookUp``; ``lookLeft`` (the
avatar's own left) the mean of ``eyeLookOutLeft`` and ``eyeLookInRight``. A morph target bound by
several presets takes the sum of weight x bind, clipped to [0, 1], as VRM players blend them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.arkit_names import VISEMES
from talkmesh.face.visemes import oculus_visemes

PRESETS = (
    "aa", "ih", "ou", "ee", "oh",
    "blink", "blinkLeft", "blinkRight",
    "lookUp", "lookDown", "lookLeft", "lookRight",
)  # fmt: skip
MOUTH = PRESETS[:5]
VRM0_PRESETS = dict(
    zip(
        ("a", "i", "u", "e", "o", "blink", "blink_l", "blink_r", "lookup", "lookdown",
         "lookleft", "lookright"),
        PRESETS,
        strict=True,
    )
)  # fmt: skip
_OCULUS = {"aa": "aa", "ih": "I", "ou": "U", "ee": "E", "oh": "O"}


@dataclass(frozen=True)
class Expressions:
    """The VRM presets an avatar binds: preset -> ((mesh, morph target, weight 0-1), ...), and
    the VRM version they were read from ("0.x" or "1.0")."""

    binds: dict[str, tuple[tuple[int, int, float], ...]]
    version: str

    @property
    def mouth(self) -> tuple[str, ...]:
        return tuple(p for p in MOUTH if self.binds.get(p))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p for p in PRESETS if self.binds.get(p))


def read_expressions(gltf: dict) -> Expressions | None:
    """The presets of a VRM 1.0 or 0.x ``gltf`` with morph-target binds; None when it is no VRM.

    Raises:
        ValueError: binds of the wrong types (the caller makes it a one-line error).
    """
    ext = gltf.get("extensions") or {}
    if not isinstance(ext, dict):
        raise ValueError("'extensions' should be an object")
    nodes = gltf.get("nodes") or []
    if isinstance(ext.get("VRMC_vrm"), dict):
        preset = ((ext["VRMC_vrm"].get("expressions") or {}).get("preset")) or {}
        binds = {}
        for name in PRESETS:
            found = []
            for b in (preset.get(name) or {}).get("morphTargetBinds") or []:
                mesh = nodes[int(b["node"])].get("mesh")
                if isinstance(mesh, int):
                    found.append((mesh, int(b["index"]), float(b.get("weight", 1.0))))
            binds[name] = tuple(found)
        return Expressions(binds, "1.0")
    if isinstance(ext.get("VRM"), dict):
        groups = (ext["VRM"].get("blendShapeMaster") or {}).get("blendShapeGroups") or []
        binds = {name: () for name in PRESETS}
        for g in groups:
            name = VRM0_PRESETS.get(str(g.get("presetName", "")).lower())
            if name is None:
                continue
            binds[name] += tuple(
                (int(b["mesh"]), int(b["index"]), float(b.get("weight", 100.0)) / 100.0)
                for b in g.get("binds") or []
            )
        return Expressions(binds, "0.x")
    return None


def preset_weights(arkit: np.ndarray, fps: float, presets: tuple[str, ...]) -> np.ndarray:
    """(T, 52) ARKit weights -> (T, len(PRESETS)) weights in [0, 1] of the avatar's ``presets``
    (see the module doc)."""
    a = {n: arkit[:, i] for i, n in enumerate(ARKIT_NAMES)}
    visemes = oculus_visemes(arkit, fps)
    out = np.zeros((len(arkit), len(PRESETS)), np.float32)
    for preset, viseme in _OCULUS.items():
        out[:, PRESETS.index(preset)] = visemes[:, VISEMES.index(viseme)]
    one_eye = "blinkLeft" in presets and "blinkRight" in presets
    if one_eye:
        out[:, PRESETS.index("blinkLeft")] = a["eyeBlinkLeft"]
        out[:, PRESETS.index("blinkRight")] = a["eyeBlinkRight"]
    else:
        out[:, PRESETS.index("blink")] = np.minimum(a["eyeBlinkLeft"], a["eyeBlinkRight"])
    out[:, PRESETS.index("lookUp")] = 0.5 * (a["eyeLookUpLeft"] + a["eyeLookUpRight"])
    out[:, PRESETS.index("lookDown")] = 0.5 * (a["eyeLookDownLeft"] + a["eyeLookDownRight"])
    out[:, PRESETS.index("lookLeft")] = 0.5 * (a["eyeLookOutLeft"] + a["eyeLookInRight"])
    out[:, PRESETS.index("lookRight")] = 0.5 * (a["eyeLookInLeft"] + a["eyeLookOutRight"])
    return np.clip(out, 0.0, 1.0)


def target_matrix(expressions: Expressions, mesh: int, num_targets: int) -> np.ndarray:
    """(len(PRESETS), K) bind weights of ``mesh``'s K morph targets (zero where unbound)."""
    m = np.zeros((len(PRESETS), num_targets), np.float32)
    for p, preset in enumerate(PRESETS):
        for bound_mesh, index, weight in expressions.binds.get(preset, ()):
            if bound_mesh == mesh and 0 <= index < num_targets:
                m[p, index] += weight
    return m
