"""An emotion composed with the speech, the speech in charge of the lips.

An emotion's ARKit weights (:mod:`talkmesh.face.performance`) are added to the speech's. The upper
face (brows, lids, cheeks, nose) takes them as they are. The lower face (jaw and mouth channels)
also shapes the lips, and there the speech must win: /p b m/ close the lips, a pause rests them
and a vowel opens them as far as the speech says, whatever the face feels. The lip opening (the
inner lips' distance at the midline, :func:`talkmesh.face.assets.lip_opening`) is what the speech
owns; the emotion keeps the lips' shape (a smile, pressed or stretched lips) but not their gap:

1. the emotion's lower-face channels are scaled down, frame by frame, as far as needed for the
   opening to grow by no more than ``tolerance`` over the speech's (a surprised jaw drop does not
   open a /m/ or a pause; a smile that would part the pressed lips of a /p/ yields there);
2. where the emotion closes the lips more than ``tolerance`` (a smile or pressed lips over a
   vowel or at rest), lips part (AU25: ``mouthUpperUp`` and ``mouthLowerDown``) as far as the
   speech's opening.

``tolerance`` is the larger of ``GAP_TOLERANCE_M`` and ``GAP_TOLERANCE_SHARE`` of the speech's
opening above the rest face's (so pauses and closures, at or under rest, get 2 micrometres).
Both steps are found by bisection per frame on the clipped weights, exactly for the bundled head
(its vertices are linear in the weights), so frames are independent: a clip composed in blocks
equals one composed at once. An emotion that is zero everywhere returns the speech's weights
themselves, bit for bit.
"""

from __future__ import annotations

import numpy as np

from talkmesh.face.arkit import ARKIT_NAMES

GAP_TOLERANCE_M = 0.002e-3  # the lips' gap may move this far (metres) ...
GAP_TOLERANCE_SHARE = 0.03  # ... or this share of the speech's opening above rest, if larger
BISECTIONS = 14  # steps of each bisection: 1/16384 of the range

# channels that shape the lips: the emotion's share of them yields to the speech
# (the nose wrinkler and cheek raiser lift the upper lip a little too)
LOWER = np.array([n.startswith(("jaw", "mouth", "cheek", "nose", "tongue")) for n in ARKIT_NAMES])
# AU25 (lips part): the upper lip raised and the lower lowered, the channels that open the lips
# without the jaw
PART = np.zeros(len(ARKIT_NAMES), np.float32)
for _name in ("mouthUpperUpLeft", "mouthUpperUpRight", "mouthLowerDownLeft", "mouthLowerDownRight"):
    PART[ARKIT_NAMES.index(_name)] = 1.0


def lip_basis(blendshapes: np.ndarray, lip_pair: np.ndarray) -> np.ndarray:
    """(52, V, 3) blendshapes and the (2,) inner-lip pair -> (52, 3): how each channel moves the
    upper lip's midline vertex relative to the lower one."""
    upper, lower = lip_pair
    return (blendshapes[:, upper] - blendshapes[:, lower]).astype(np.float64)


def compose(
    speech: np.ndarray, emotion: np.ndarray, lips: np.ndarray, basis: np.ndarray, rest: float
) -> np.ndarray:
    """The speech's weights with the emotion added, the lips' gap the speech's.

    Args:
        speech: (T, 52) the speech's ARKit weights in [0, 1].
        emotion: (T, 52) the emotion's weights in [0, 1] (:meth:`Performance.weights`).
        lips: (T, 3) upper minus lower inner-lip vertex (metres) of the speech's face.
        basis: (52, 3) :func:`lip_basis`.
        rest: the rest face's lip gap (metres).

    Returns:
        (T, 52) float32 weights in [0, 1]; ``speech`` itself where ``emotion`` is all zero.
    """
    assert speech.shape == emotion.shape and speech.shape[1] == len(ARKIT_NAMES), emotion.shape
    assert lips.shape == (len(speech), 3), lips.shape
    if not np.any(emotion):
        return speech
    s = speech.astype(np.float64)
    lips = lips.astype(np.float64)
    gap0 = np.linalg.norm(lips, axis=1)
    tol = np.maximum(GAP_TOLERANCE_M, GAP_TOLERANCE_SHARE * (gap0 - rest))
    upper = np.where(LOWER, 0.0, emotion).astype(np.float64)
    lower = np.where(LOWER, emotion, 0.0).astype(np.float64)

    def gap(w: np.ndarray) -> np.ndarray:
        return np.linalg.norm(lips + (w - s) @ basis, axis=1)

    def with_lower(a: np.ndarray) -> np.ndarray:
        return np.clip(s + upper + a[:, None] * lower, 0.0, 1.0)

    # 1. the largest share of the lower-face emotion that opens the lips no further than tol
    alpha = _bisect(lambda a: gap(with_lower(a)) - gap0 <= tol, len(s))
    w = with_lower(alpha)
    # 2. lips parted back to the speech's gap where the emotion closes them
    closed = gap(w) < gap0 - tol
    if closed.any():
        wc, g0 = w[closed], gap0[closed]
        lips_c, s_c = lips[closed], s[closed]

        def parted(b: np.ndarray) -> np.ndarray:
            return np.clip(wc + b[:, None] * PART, 0.0, 1.0)

        def short(b: np.ndarray) -> np.ndarray:
            return np.linalg.norm(lips_c + (parted(b) - s_c) @ basis, axis=1) <= g0

        w[closed] = parted(_bisect(short, len(wc)))
    return w.astype(np.float32)


def _bisect(ok, n: int) -> np.ndarray:
    """(n,) the largest x in [0, 1] with ``ok(x)`` true per row, given ``ok(0)``: 1 where
    ``ok(1)``, else a boundary between an ``ok`` and a failing value found by bisection."""
    hi = np.ones(n)
    good = ok(hi)
    if good.all():
        return hi
    lo = np.zeros(n)
    for _ in range(BISECTIONS):
        mid = (lo + hi) / 2
        fine = ok(mid)
        lo = np.where(fine, mid, lo)
        hi = np.where(fine, hi, mid)
    return np.where(good, 1.0, lo)


def compose_vertices(
    vertices: np.ndarray,
    weights: np.ndarray,
    emotion: np.ndarray,
    blendshapes: np.ndarray,
    lip_pair: np.ndarray,
    rest: float,
) -> np.ndarray:
    """A learned model's (t, V, 3) ``vertices`` and their fitted (t, 52) ``weights`` with the
    (t, 52) ``emotion`` composed in (:func:`compose`, ``rest`` the rest face's lip gap): the change of the weights is added to the
    vertices in place as blendshape offsets (``blendshapes`` (52, V, 3)); returns the weights."""
    upper, lower = lip_pair
    lips = vertices[:, upper] - vertices[:, lower]
    new = compose(weights, emotion, lips, lip_basis(blendshapes, lip_pair), rest)
    if new is not weights:
        delta = (new - weights) @ blendshapes.reshape(len(blendshapes), -1)
        vertices += delta.reshape(vertices.shape).astype(vertices.dtype, copy=False)
    return new


def rest_gap(template: np.ndarray, lip_pair: np.ndarray) -> float:
    """The lip gap (metres) of the (V, 3) rest face."""
    upper, lower = lip_pair
    return float(np.linalg.norm(template[upper].astype(np.float64) - template[lower]))
