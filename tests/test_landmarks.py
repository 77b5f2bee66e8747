"""Landmarks found from a head mesh's own geometry (talkmesh.face.landmarks), without a
registration: the rigid frame is known here, as the rigid fit would give it."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from talkmesh.face.assets import load_head
from talkmesh.face.landmarks import IDENTITY, Frame, boundary_loops, find_landmarks
from talkmesh.face.registration import vertex_normals
from talkmesh.face.rig import AUTOMATIC, EYE, LANDMARK_NAMES, SKIN, head_landmarks

TURN = trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0])[:3, :3]  # a Z-up export


@pytest.fixture(scope="module")
def head():
    return load_head()


def _find(vertices, faces, frame, head, shift=(0.0, 0.0, 0.0)):
    marks = head_landmarks(head)
    t = head.template.astype(np.float64)
    predicted = {
        k: frame.scale * (t[i] + shift) @ frame.rotation.T + frame.shift for k, i in marks.items()
    }
    return find_landmarks(vertices, faces, vertex_normals(vertices, faces), frame, predicted)


def test_the_bundled_head_in_mm_z_up_gives_its_own_landmarks(head):
    """Every automatic landmark is found, on the bundled head's own vertex, whatever the units
    and axes; all are distinct skin vertices, left on the left."""
    marks = head_landmarks(head)
    assert set(marks) == set(LANDMARK_NAMES) and len(set(marks.values())) == len(marks)
    assert all(head.regions.vertex_part[i] == SKIN for i in marks.values())
    t = head.template.astype(np.float64)
    assert t[marks["mouth_left"], 0] > 0.01 and t[marks["eye_outer_right"], 0] < -0.03
    assert t[marks["eye_inner_left"], 0] < t[marks["eye_outer_left"], 0]
    frame = Frame(1000.0, TURN, np.array([3.0, -20.0, 100.0]))
    found = _find(1000 * t @ TURN.T + frame.shift, head.faces.astype(np.int64), frame, head)
    names = ["nose_tip", "chin", "upper_lip", "lower_lip", "mouth_left", "mouth_right"]
    names += [k for k in LANDMARK_NAMES if k.startswith("eye_")]
    assert set(AUTOMATIC) <= set(names)
    assert found == {k: marks[k] for k in names}


def test_a_prediction_far_off_finds_nothing_and_raises_nothing(head):
    """Each landmark is checked against where the rigid fit puts it: 3 cm aside, none is kept."""
    t, f = head.template.astype(np.float64), head.faces.astype(np.int64)
    assert _find(t, f, IDENTITY, head, shift=np.array([0.03, 0.0, 0.0])) == {}


def test_eye_corners_from_eye_openings_without_eyeballs(head):
    """Eyeballs removed and the skin behind the eyelids cut away: the eye openings are boundary
    loops now, and their ends are found within a few millimetres of the bundled eye corners."""
    t, f = head.template.astype(np.float64), head.faces.astype(np.int64)
    part = head.regions.vertex_part
    marks = head_landmarks(head)
    socket = np.zeros(len(t), bool)
    for sign in (1, -1):
        eye = (part == EYE) & (sign * t[:, 0] > 0)
        centre = t[eye].mean(0)
        # the skin inside the eyeball's sphere and behind the lids' rim
        socket |= (part == SKIN) & (np.linalg.norm(t - centre, axis=1) < 0.0165)
    keep = (part[f] == SKIN).all(1) & ~socket[f].any(1)
    loops = boundary_loops(f[keep], len(t))
    assert len(loops) >= 3  # the neck and two eye openings
    found = _find(t, f[keep], IDENTITY, head)
    names = [k for k in LANDMARK_NAMES if k.startswith("eye_")]
    assert set(names) <= set(found)
    error_mm = [1000 * np.linalg.norm(t[found[k]] - t[marks[k]]) for k in names]
    assert max(error_mm) < 4.0, dict(zip(names, np.round(error_mm, 1)))
