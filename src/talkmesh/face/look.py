"""The bundled head's colours: skin, lips, eyes with iris and pupil, teeth, tongue, mouth cavity.

Per-vertex sRGB colours in [0, 1] for the renderer (vertex colours move with the vertices, so
the irises follow gaze and the lips follow speech). The parts come from ``Regions.vertex_part``;
within them, by geometry of the neutral face (metres, +y up, +z towards the viewer):

* iris and pupil: eye vertices by the angle between +z and their direction from their eyeball's
  centre (the mean of its vertices);
* lips: the part of ``Regions.lips`` within an ellipse around the lips' midline;
* mouth cavity: skin vertices inside the head behind the lips (the mouth bag), darker the deeper
  they are, so an open mouth is dark inside instead of lit like the face;
* teeth and tongue: darker the farther behind the lips they sit (a baked stand-in for the
  occlusion a one-pass renderer cannot compute), so the back teeth do not glow in a 3/4 view.
"""

from __future__ import annotations

import numpy as np

from talkmesh.face.assets import Head

SKIN = (0.86, 0.66, 0.56)
LIPS = (0.74, 0.44, 0.42)
SCLERA = (0.93, 0.91, 0.87)
IRIS = (0.33, 0.42, 0.50)
PUPIL = (0.04, 0.04, 0.05)
TEETH = (0.93, 0.91, 0.85)
TONGUE = (0.70, 0.36, 0.37)
CAVITY = (0.16, 0.06, 0.06)
PART_COLORS = np.array([SKIN, SCLERA, TEETH, TONGUE], np.float32)  # vertex_part 0..3

PUPIL_COS, IRIS_COS = 0.96, 0.885  # cos of the angle from the eye's axis (about 16 and 28 deg)
LIP_BLEND = 0.85
LIP_ELLIPSE = (0.026, 0.012)  # half-width and half-height of the lips (m) around the midline
MOUTH_BOX = ((-0.035, 0.035), (-0.07, -0.01), (-0.075, 0.015))  # x, y, z of the mouth bag (m)
CAVITY_DEPTH = 0.02  # metres behind the box's front over which the cavity darkens fully
INSIDE_SHADE = (0.6, 0.045)  # teeth and tongue: at most this much darker, reached this far (m)
# behind the lips' midline


def head_colors(head: Head) -> np.ndarray:
    """(V, 3) float32 sRGB colours of the bundled head (any of its identities)."""
    part = np.clip(head.regions.vertex_part, 0, len(PART_COLORS) - 1)
    colors = PART_COLORS[part].copy()
    t = head.template.astype(np.float64)

    # Lip colour: an ellipse around the mouth's midline, within the lip region, fading out.
    centre = t[head.regions.lip_pair].mean(0)
    lips = head.regions.lips
    x, y = (t[lips, 0] - centre[0]) / LIP_ELLIPSE[0], (t[lips, 1] - centre[1]) / LIP_ELLIPSE[1]
    weight = LIP_BLEND * np.clip((1.0 - np.hypot(x, y)) / 0.25, 0.0, 1.0)[:, None]
    colors[lips] = weight * np.asarray(LIPS) + (1 - weight) * colors[lips]

    for side in (-1, 1):
        eye = np.flatnonzero((part == 1) & (np.sign(t[:, 0]) == side))
        if not len(eye):
            continue
        d = t[eye] - t[eye].mean(0)
        cos = d[:, 2] / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        colors[eye[cos > IRIS_COS]] = IRIS
        colors[eye[cos > PUPIL_COS]] = PUPIL

    mouth = np.flatnonzero((part == 2) | (part == 3))
    behind = np.clip((centre[2] - t[mouth, 2]) / INSIDE_SHADE[1], 0.0, 1.0)[:, None]
    colors[mouth] *= 1.0 - INSIDE_SHADE[0] * behind

    inside = part == 0
    for axis, (lo, hi) in enumerate(MOUTH_BOX):
        inside &= (t[:, axis] > lo) & (t[:, axis] < hi)
    depth = np.clip((MOUTH_BOX[2][1] - t[inside, 2]) / CAVITY_DEPTH, 0.0, 1.0)[:, None]
    colors[inside] = depth * np.asarray(CAVITY) + (1 - depth) * colors[inside]
    return colors.astype(np.float32)
