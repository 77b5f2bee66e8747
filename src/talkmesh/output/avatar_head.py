"""The head's motion on a user's avatar: its head bone turned as the bundled head turns.

The head bone is the VRM humanoid's ``head`` (VRM 1.0's ``VRMC_vrm`` or VRM 0.x's ``VRM``
extension), else the node named ``head`` (any case, after a ``prefix:``) or one of the common
rigs' head joints (``J_Bip_C_Head``, ``Bip01_Head``). Its rotation turns about its own joint (the
neck), so only rotations are written: a ``rotation`` channel whose keys are the bone's rest
rotation turned by the head pose, the pose's rotation taken in the world frame of the avatar
(+y up, facing +z as glTF says, or -z for VRM 0.x models) and brought into the bone's parent's
frame. An avatar without a recognisable head bone gets no head motion.
"""

from __future__ import annotations

import numpy as np

from talkmesh.face.head_motion import qmul, quaternions

HEAD_JOINTS = frozenset({"head", "j_bip_c_head", "bip01_head", "bip01 head", "def-head"})


def head_node(gltf: dict) -> int | None:
    """The index of the avatar's head bone, or None."""
    nodes = gltf.get("nodes") or []
    ext = gltf.get("extensions") or {}
    human = ((ext.get("VRMC_vrm") or {}).get("humanoid") or {}).get("humanBones") or {}
    index = (human.get("head") or {}).get("node") if isinstance(human, dict) else None
    if index is None:
        bones = ((ext.get("VRM") or {}).get("humanoid") or {}).get("humanBones") or []
        index = next((b.get("node") for b in bones if b.get("bone") == "head"), None)
    if index is None:
        for k, node in enumerate(nodes):
            name = str(node.get("name", "")).lower().rsplit(":", 1)[-1]
            if name in HEAD_JOINTS:
                index = k
                break
    if not isinstance(index, int) or not 0 <= index < len(nodes) or "matrix" in nodes[index]:
        return None  # a bone posed by a matrix cannot take a rotation channel
    return index


def _conjugate(q: np.ndarray) -> np.ndarray:
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def _node_rotation(node: dict) -> np.ndarray:
    """A node's rotation (x, y, z, w): its ``rotation``, or that of its ``matrix``."""
    if "matrix" in node:
        m = np.asarray(node["matrix"], np.float64).reshape(4, 4).T[:3, :3]
        u, _, vt = np.linalg.svd(m)  # the rotation of the matrix, its scale taken out
        r = u @ vt
        w = np.sqrt(max(0.0, 1 + np.trace(r))) / 2
        if w < 1e-6:  # a half turn: any axis form would do, take the largest diagonal
            k = int(np.argmax(np.diag(r)))
            q = np.zeros(4)
            q[k] = np.sqrt(max(0.0, (1 + 2 * r[k, k] - np.trace(r)))) / 2
            return q / np.linalg.norm(q)
        x, y, z = (r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1])
        return np.array([x / (4 * w), y / (4 * w), z / (4 * w), w])
    return np.asarray(node.get("rotation", [0.0, 0.0, 0.0, 1.0]), np.float64)


def _parent_world(gltf: dict, index: int) -> np.ndarray:
    """The world rotation of ``index``'s parent (the product of its ancestors' rotations)."""
    nodes = gltf.get("nodes") or []
    parent = {c: k for k, n in enumerate(nodes) for c in n.get("children") or []}
    world = np.array([0.0, 0.0, 0.0, 1.0])
    k, seen = parent.get(index), set()
    while k is not None and k not in seen:
        seen.add(k)
        world = qmul(_node_rotation(nodes[k]), world)
        k = parent.get(k)
    return world


def head_rotations(gltf: dict, index: int, pose: np.ndarray) -> np.ndarray:
    """(T, 6) head pose -> (T, 4) rotations (x, y, z, w) of node ``index``: its rest rotation
    turned by the pose in the avatar's world frame."""
    turn = quaternions(pose[:, :3])
    if (gltf.get("extensions") or {}).get("VRM") is not None:  # VRM 0.x faces -z: half a turn
        turn = turn * np.array([-1.0, 1.0, -1.0, 1.0])  # about y maps (x, y, z) to (-x, y, -z)
    g = _parent_world(gltf, index)
    local = qmul(qmul(_conjugate(g), turn), g)  # the turn in the parent's frame
    out = qmul(local, _node_rotation(gltf["nodes"][index]))
    return (out / np.linalg.norm(out, axis=-1, keepdims=True)).astype(np.float32)
