"""Vertex normals and winding (talkmesh.face.geometry), shared by the renderer and the .glb exporter."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from fixtures import procedural_head

from talkmesh.face.geometry import VertexNormals, vertex_normals, winding_sign


@pytest.fixture(scope="module")
def head() -> tuple[np.ndarray, np.ndarray]:
    return procedural_head()


def reference_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted normals the slow, obvious way: a loop adding each face's cross product."""
    sums = np.zeros((len(vertices), 3))
    v = vertices.astype(np.float64)
    for a, b, c in faces:
        n = np.cross(v[b] - v[a], v[c] - v[a])  # length: twice the area
        for k in (a, b, c):
            sums[k] += n
    return sums / np.linalg.norm(sums, axis=1, keepdims=True)


def test_normals_are_unit_and_outward_on_a_sphere(head):
    vertices, faces = head
    sphere = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    normals = vertex_normals(sphere, faces)
    assert normals.dtype == np.float32
    assert np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-5)
    assert (np.einsum("ij,ij->i", normals, sphere) > 0.99).all()
    np.testing.assert_allclose(vertex_normals(sphere, faces[:, ::-1]), -normals, atol=1e-6)


def test_normals_are_area_weighted():
    # Vertex 0 is shared by a unit right triangle facing +z and one three times larger facing +y:
    # area weighting gives (0, 3, 1) / sqrt(10); angle weighting (trimesh's default) or a plain
    # mean of the face normals would give (0, 1, 1) / sqrt(2).
    vertices = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 3]])
    faces = np.array([[0, 1, 2], [0, 3, 1]])
    normals = vertex_normals(vertices, faces)
    np.testing.assert_allclose(normals[0], np.array([0, 3, 1]) / np.sqrt(10), atol=1e-7)
    np.testing.assert_allclose(normals[2], [0, 0, 1], atol=1e-7)
    np.testing.assert_allclose(normals[3], [0, 1, 0], atol=1e-7)


def test_normals_match_a_direct_loop_on_a_perturbed_head(head):
    vertices, faces = head
    rng = np.random.default_rng(0)
    moved = vertices + rng.normal(0, 0.002, vertices.shape).astype(np.float32)
    expected = reference_normals(moved, faces)
    np.testing.assert_allclose(vertex_normals(moved, faces), expected, atol=1e-6)
    # The renderer's per-frame float32 operator is the same computation at lower precision.
    per_frame = VertexNormals(faces, len(moved))
    np.testing.assert_allclose(per_frame(moved), expected, atol=1e-4)
    np.testing.assert_allclose(per_frame(vertices), reference_normals(vertices, faces), atol=1e-4)


def test_vertices_without_a_normal_get_plus_z():
    # Vertex 3 is in no face; vertices 4-6 only in a face of zero area. glTF needs unit normals.
    vertices = np.float32(
        [[0, 0, 0], [1, 0, 0], [0, 0, 1], [5, 5, 5], [1, 1, 1], [2, 2, 2], [3, 3, 3]]
    )
    faces = np.array([[0, 1, 2], [4, 5, 6]])
    for normals in (vertex_normals(vertices, faces), VertexNormals(faces, len(vertices))(vertices)):
        np.testing.assert_allclose(normals[:3], [[0, -1, 0]] * 3, atol=1e-7)
        np.testing.assert_array_equal(normals[3:], [[0, 0, 1]] * 4)


def test_winding_sign(head):
    vertices, faces = head
    assert winding_sign(vertices, faces) == 1
    assert winding_sign(vertices, faces[:, ::-1]) == -1
    mixed = faces.copy()
    mixed[0] = mixed[0, ::-1]
    assert winding_sign(vertices, mixed) == 0
    # A second part wound inside out (or a flat one) turns culling off too.
    pair = np.concatenate([vertices, vertices + np.float32([0.3, 0, 0])])
    assert winding_sign(pair, np.concatenate([faces, faces + len(vertices)])) == 1
    assert winding_sign(pair, np.concatenate([faces, faces[:, ::-1] + len(vertices)])) == 0
    flat = np.concatenate([vertices, [[0, 0, -0.2], [1, 0, -0.2], [0, 1, -0.2]]])
    assert winding_sign(flat, np.concatenate([faces, len(vertices) + np.arange(3)[None]])) == 0


def test_normals_match_trimesh(head):
    """trimesh's mean of face normals weighted by face area is ours; its default (weighted by the
    corner angles) agrees closely on a smooth surface."""
    vertices, faces = head
    rng = np.random.default_rng(1)
    moved = vertices + rng.normal(0, 0.002, vertices.shape).astype(np.float32)
    mesh = trimesh.Trimesh(moved.astype(np.float64), faces, process=False)
    area_weighted = trimesh.geometry.mean_vertex_normals(
        len(moved), faces, mesh.face_normals * mesh.area_faces[:, None]
    )
    np.testing.assert_allclose(vertex_normals(moved, faces), area_weighted, atol=1e-6)
    unit = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    sphere = trimesh.Trimesh(unit, faces, process=False)
    cosine = np.einsum("ij,ij->i", vertex_normals(sphere.vertices, faces), sphere.vertex_normals)
    assert cosine.min() > 0.999
