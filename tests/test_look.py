"""The bundled head's colours: irises and pupils, lips, a dark mouth cavity; used by renders."""

from __future__ import annotations

import numpy as np

from talkmesh.face.assets import load_head
from talkmesh.face.look import IRIS, PUPIL, SCLERA, SKIN, head_colors


def luminance(c) -> np.ndarray:
    return np.asarray(c, np.float64) @ [0.2126, 0.7152, 0.0722]


def test_eyes_lips_and_cavity_are_coloured():
    head = load_head()
    colors = head_colors(head)
    assert colors.shape == (head.num_vertices, 3) and colors.dtype == np.float32
    assert colors.min() >= 0 and colors.max() <= 1
    part = head.regions.vertex_part
    for side in (-1, 1):  # each eye has sclera, iris and pupil vertices, pupil in front
        eye = (part == 1) & (np.sign(head.template[:, 0]) == side)
        for c in (SCLERA, IRIS, PUPIL):
            assert np.all(np.isclose(colors[eye], c, atol=1e-6), axis=1).any(), c
        pupil = eye & np.all(np.isclose(colors, PUPIL), axis=1)
        assert head.template[pupil, 2].min() > head.template[eye, 2].mean()
    lips = head.regions.lips
    redness = colors[:, 0] / colors[:, 1]
    assert redness[lips].max() > SKIN[0] / SKIN[1] + 0.25  # lip colour
    skin = part == 0
    dark = skin & (luminance(colors) < 0.5 * luminance(SKIN))
    assert dark.sum() > 20  # the mouth bag
    assert np.all(head.template[dark, 2] < head.template[lips, 2].min())  # behind the lips


def test_renders_use_the_colours():
    from talkmesh.output.render import head_vertex_colors

    head = load_head()
    np.testing.assert_array_equal(head_vertex_colors(head.num_vertices), head_colors(head))
    assert head_vertex_colors(head.num_vertices + 1) is None


def test_the_pupils_follow_the_gaze_shapes():
    """The pupil-coloured vertices move as the eyeLook* shapes turn the eye (the face's own left
    is +x): out and in sideways, up and down, each by millimetres."""
    from talkmesh.face.arkit import ARKIT_NAMES

    head = load_head()
    colors, part = head_colors(head), head.regions.vertex_part
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        eye = (part == 1) & (np.sign(head.template[:, 0]) == sign)
        pupil = eye & np.all(np.isclose(colors, PUPIL), axis=1)
        for shape, axis, direction in (
            ("eyeLookOut", 0, sign),
            ("eyeLookIn", 0, -sign),
            ("eyeLookUp", 1, 1.0),
            ("eyeLookDown", 1, -1.0),
        ):
            moved = head.blendshapes[ARKIT_NAMES.index(shape + side)][pupil].mean(0)
            assert direction * moved[axis] > 0.002, (shape + side, moved)  # over 2 mm
