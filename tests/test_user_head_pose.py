"""The head pose on a user's own head (``animate --head``): the same rigid motion in every output
that carries vertices or a head node, whatever the mesh's units and axes."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import trimesh

from talkmesh.animation import Animation, AnimationBlocks
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import load_head
from talkmesh.face.head_motion import quaternions
from talkmesh.face.rig import Rig
from talkmesh.output.formats import load_animation, save_animation
from talkmesh.output.render import posed

TURN = trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0])[:3, :3]  # a Z-up export
SHIFT = np.array([3.0, -20.0, 100.0])  # millimetres
T = 6


@pytest.fixture(scope="module")
def head():
    return load_head()


def identity_rig(head) -> Rig:
    """The bundled head itself as a user's mesh in mm, Z-up, shifted: each user vertex is the
    bundled vertex it came from (so carrying is exact)."""
    v = len(head.template)
    return Rig(
        vertices=(1000 * head.template.astype(np.float64) @ TURN.T + SHIFT).astype(np.float32),
        faces=head.faces,
        blendshapes=np.zeros((len(ARKIT_NAMES), v, 3), np.float32),
        scale=1000.0,
        rotation=TURN,
        translation=SHIFT,
        residual=0.0,
        corners=np.repeat(np.arange(v)[:, None], 3, axis=1),
        weights=np.tile([1.0, 0.0, 0.0], (v, 1)),
    )


def talking(head) -> tuple[Animation, AnimationBlocks]:
    rng = np.random.default_rng(0)
    weights = rng.random((T, len(ARKIT_NAMES))).astype(np.float32) * 0.3
    pose = np.zeros((T, 6), np.float32)
    pose[:, :3] = np.radians(rng.uniform(-8, 8, (T, 3)))
    pose[:, 3:] = rng.uniform(-0.01, 0.01, (T, 3))
    anim = Animation(
        vertices=head.vertices_from_weights(weights),
        faces=head.faces,
        fps=30.0,
        weights=weights,
        weight_names=list(ARKIT_NAMES),
        head_pose=pose,
    )
    blocks = AnimationBlocks(
        blocks=iter([anim]), num_frames=T, faces=head.faces, fps=30.0,
        weight_names=list(ARKIT_NAMES), template=head.template,
    )  # fmt: skip
    return anim, blocks


def in_user_frame(points: np.ndarray) -> np.ndarray:
    return 1000 * points.astype(np.float64) @ TURN.T + SHIFT


def test_the_pose_moves_a_users_head_as_it_moves_the_bundled_one(head):
    source, blocks = talking(head)
    mine = identity_rig(head).carry_blocks(blocks, head.template).collect()
    np.testing.assert_array_equal(mine.head_pose, source.head_pose)  # the angles are the head's
    assert mine.pose_frame is not None
    for t in range(T):
        want = in_user_frame(posed(source, t))
        np.testing.assert_allclose(posed(mine, t), want, atol=2e-3)  # mm, float32
    # a posed frame is rigid: the pose moves every vertex, by a turn and not a distortion
    moved = np.linalg.norm(posed(mine, 0) - mine.vertices[0], axis=1)
    assert moved.max() > 5.0  # mm
    # the video draws the head turned to the bundled head's front: the same motion there
    facing = identity_rig(head).facing(mine)
    assert facing.pose_frame is None
    np.testing.assert_allclose(posed(facing, 3), posed(source, 3), atol=2e-6)


def test_the_npz_keeps_the_pose_and_its_frame(head, tmp_path):
    _, blocks = talking(head)
    mine = identity_rig(head).carry_blocks(blocks, head.template).collect()
    (path,) = save_animation(mine, tmp_path / "me.npz")
    back = load_animation(path)
    np.testing.assert_array_equal(back.head_pose, mine.head_pose)
    np.testing.assert_array_equal(back.pose_frame, mine.pose_frame)
    np.testing.assert_allclose(posed(back, 2), posed(mine, 2), atol=0.05)  # float16 offsets


def test_a_broken_pose_frame_in_an_npz_is_one_line(head, tmp_path):
    _, blocks = talking(head)
    mine = identity_rig(head).carry_blocks(blocks, head.template).collect()
    mine.pose_frame = np.zeros((4, 4))
    (path,) = save_animation(mine, tmp_path / "bad.npz")
    with pytest.raises(TalkmeshError, match="pose_frame") as e:
        load_animation(path)
    assert "\n" not in str(e.value)


def _glb(path):
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    gltf = json.loads(data[20 : 20 + length])
    binary = data[20 + length + 8 :]
    return gltf, binary


def _accessor(gltf, binary, k) -> np.ndarray:
    acc = gltf["accessors"][k]
    view = gltf["bufferViews"][acc["bufferView"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return np.frombuffer(binary, "<f4", acc["count"] * width, start).reshape(acc["count"], width)


def _node_matrix(node, quat=None, move=None) -> np.ndarray:
    if "matrix" in node:
        return np.array(node["matrix"], np.float64).reshape(4, 4).T
    m = np.eye(4)
    if quat is not None:
        x, y, z, w = quat
        m[:3, :3] = trimesh.transformations.quaternion_matrix([w, x, y, z])[:3, :3]
    if move is not None:
        m[:3, 3] = move
    return m


def test_the_glb_head_node_turns_the_users_head_as_the_pose_does(head, tmp_path):
    """The face's world transform at a key (root x user frame x head key x pose frame), applied
    to the frame's unposed vertices, is the posed head in glTF's frame."""
    from test_io import validate_glb

    _, blocks = talking(head)
    mine = identity_rig(head).carry_blocks(blocks, head.template).collect()
    (path,) = save_animation(mine, tmp_path / "me.glb")
    assert not validate_glb(path)["issues"]["numErrors"]
    gltf, binary = _glb(path)
    nodes = gltf["nodes"]
    head_node = next(i for i, n in enumerate(nodes) if n.get("name") == "head")
    channels = gltf["animations"][0]["channels"]
    samplers = gltf["animations"][0]["samplers"]
    keyed = {
        c["target"]["path"]: _accessor(gltf, binary, samplers[c["sampler"]]["output"])
        for c in channels
        if c["target"]["node"] == head_node
    }
    parents = {c: i for i, n in enumerate(nodes) for c in n.get("children", [])}
    for t in (0, 4):
        world, k = np.eye(4), 0
        while True:  # from the face mesh (node 0) up to the scene's root
            quat = keyed["rotation"][t] if k == head_node else None
            move = keyed["translation"][t] if k == head_node else None
            world = _node_matrix(nodes[k], quat, move) @ world
            if k not in parents:
                break
            k = parents[k]
        got = mine.vertices[t] @ world[:3, :3].T + world[:3, 3]
        want = posed(mine, t) @ mine.to_gltf[:3, :3].T + mine.to_gltf[:3, 3]
        np.testing.assert_allclose(got, want, atol=1e-4)
    np.testing.assert_allclose(keyed["rotation"], quaternions(mine.head_pose[:, :3]), atol=1e-6)
