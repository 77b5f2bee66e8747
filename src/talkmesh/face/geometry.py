"""Mesh geometry shared by the renderer and the exporters: vertex normals and winding.

Vertex normals are the area-weighted mean of the normals of the faces around each vertex (the
cross product of two edges is twice the face's area, so summing unnormalised cross products weights
by area), oriented by the winding: counter-clockwise faces, seen from outside, give outward normals.
A vertex with no well-defined normal (used by no face, or only by faces of zero area) gets +z, so
every normal is unit length, as glTF requires.
"""

from __future__ import annotations

import numpy as np

MIN_NORMAL_LENGTH = 1e-20  # summed cross products shorter than this have no direction: use +z
FALLBACK_NORMAL = (0.0, 0.0, 1.0)  # +z: towards the viewer in the bundled head's frame
NORMAL_FACES = 1 << 18  # faces at a time in vertex_normals (its memory: their corners)
MIN_PART_VOLUME = 1e-5  # of the mesh's bounding cube: flatter parts are not consistently wound


class VertexNormals:
    """Vertex normals of a fixed topology as sparse matrix products (about 1 ms for 9k faces).

    Build it once per mesh and call it per frame (the renderer does); :func:`vertex_normals` is the
    one-shot form.

    Args:
        faces: (F, 3) triangles.
        num_vertices: V.
        dtype: the precision of the arithmetic (float32 for speed, float64 for exports).
    """

    def __init__(self, faces: np.ndarray, num_vertices: int, dtype=np.float32) -> None:
        import scipy.sparse  # here, not above: a .glb export's vertex_normals needs no scipy

        faces = np.asarray(faces, dtype=np.int64)
        self.dtype = np.dtype(dtype)
        num_faces = len(faces)
        rows = np.arange(num_faces).repeat(2)
        signs = np.tile(np.array([1.0, -1.0], dtype=self.dtype), num_faces)
        shape = (num_faces, num_vertices)
        # Edge operators: (F, V) @ (V, 3) -> (F, 3) edges v1 - v0 and v2 - v0.
        self.edge1 = scipy.sparse.csr_matrix((signs, (rows, faces[:, [1, 0]].ravel())), shape=shape)
        self.edge2 = scipy.sparse.csr_matrix((signs, (rows, faces[:, [2, 0]].ravel())), shape=shape)
        # Incidence: (V, F) @ (F, 3) face normals -> (V, 3) sums over each vertex's faces.
        ones = np.ones(3 * num_faces, dtype=self.dtype)
        incidence = (ones, (faces.ravel(), np.arange(num_faces).repeat(3)))
        self.incidence = scipy.sparse.csr_matrix(incidence, shape=(num_vertices, num_faces))
        self._face_normals = np.empty((num_faces, 3), dtype=self.dtype)

    def __call__(self, vertices: np.ndarray) -> np.ndarray:
        """(V, 3) vertices -> (V, 3) unit normals in ``dtype`` (a new array)."""
        vertices = np.asarray(vertices, dtype=self.dtype)
        e1, e2 = self.edge1 @ vertices, self.edge2 @ vertices
        fn = self._face_normals  # e1 x e2: its length is twice the face's area
        np.subtract(e1[:, 1] * e2[:, 2], e1[:, 2] * e2[:, 1], out=fn[:, 0])
        np.subtract(e1[:, 2] * e2[:, 0], e1[:, 0] * e2[:, 2], out=fn[:, 1])
        np.subtract(e1[:, 0] * e2[:, 1], e1[:, 1] * e2[:, 0], out=fn[:, 2])
        normals = self.incidence @ fn
        length = np.sqrt(np.einsum("ij,ij->i", normals, normals))
        normals /= np.maximum(length, MIN_NORMAL_LENGTH)[:, None]
        undefined = length <= MIN_NORMAL_LENGTH
        if undefined.any():
            normals[undefined] = FALLBACK_NORMAL
        return normals


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) vertices, (F, 3) faces -> (V, 3) float32 unit area-weighted normals (+z if none),
    as :class:`VertexNormals` gives them.

    Computed in float64 and rounded once, so exports do not depend on the input's precision;
    ``NORMAL_FACES`` faces at a time (:class:`VertexNormals`' three sparse operators are 360 MB at
    2.4M faces, the peak of rigging a 1.2M-vertex head)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = len(vertices)
    sums = np.zeros((n, 3))
    for a in range(0, len(faces), NORMAL_FACES):
        part = faces[a : a + NORMAL_FACES]
        tri = vertices[part]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        for x in range(3):
            sums[:, x] += sum(np.bincount(part[:, c], fn[:, x], n) for c in range(3))
    length = np.sqrt(np.einsum("ij,ij->i", sums, sums))
    sums /= np.maximum(length, MIN_NORMAL_LENGTH)[:, None]
    sums[length <= MIN_NORMAL_LENGTH] = FALLBACK_NORMAL
    return sums.astype(np.float32)


def winding_sign(vertices: np.ndarray, faces: np.ndarray) -> int:
    """+1 if the (F, 3) faces wind consistently outwards around the (V, 3) vertices, -1 if
    consistently inwards, 0 if not (then back faces are not culled and the shading is two-sided).

    Every connected part must enclose some volume with the same sign: a flat or inside-out part
    (a backdrop plane, a separately modelled eyeball) turns culling off.
    """
    import scipy.sparse.csgraph

    faces = np.asarray(faces, dtype=np.int64)
    num_vertices = len(vertices)
    edges = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    # Consistent winding traverses every shared edge once in each direction.
    if len(np.unique(edges[:, 0] * num_vertices + edges[:, 1])) != len(edges):
        return 0
    links = scipy.sparse.coo_matrix(
        (np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(num_vertices, num_vertices)
    )
    _, part = scipy.sparse.csgraph.connected_components(links, directed=False)
    face_part = part[faces[:, 0]]
    p = np.asarray(vertices, dtype=np.float64)
    volumes = []
    for k in np.unique(face_part):
        tri = p[faces[face_part == k]]  # (Fk, 3, 3)
        tri = tri - tri.reshape(-1, 3).mean(axis=0)
        volumes.append(np.einsum("ij,ij->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6)
    volumes = np.array(volumes)
    extent = np.ptp(p[np.unique(faces)], axis=0).max()
    if (np.abs(volumes) < MIN_PART_VOLUME * extent**3).any():
        return 0
    return int(np.sign(volumes[0])) if len(np.unique(np.sign(volumes))) == 1 else 0
