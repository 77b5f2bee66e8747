"""Your own character: ARKit names in exporters' spellings, one clip written into a copy of a .glb
or .vrm avatar with everything else byte for byte, the viseme fallback, the CLI and its exports."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import soundfile as sf
from avatars import HEAD_DRIVEN, make_avatar
from test_cli import CLIP
from test_io import validate_glb

from talkmesh.cli import main
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.arkit_names import VISEMES, arkit_channel, viseme_channel, visemes_from_arkit
from talkmesh.face.visemes import oculus_visemes
from talkmesh.output.avatar import animate_avatar, bind_avatar, read_glb

T, FPS = 45, 30.0
APPENDED = ("animations", "accessors", "bufferViews", "buffers")  # the only keys that change


def arkit_weights(frames: int = T, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 1, (frames, 52)).astype(np.float32)


def accessor(gltf: dict, binary: bytes, index: int) -> np.ndarray:
    acc = gltf["accessors"][index]
    view = gltf["bufferViews"][acc["bufferView"]]
    assert acc["componentType"] == 5126 and acc["type"] == "SCALAR"
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return np.frombuffer(binary, "<f4", acc["count"], start)


def clip_values(gltf: dict, binary: bytes, node: int) -> np.ndarray:
    """(T, K) weights the new clip (the first) gives ``node``."""
    clip = gltf["animations"][0]
    (channel,) = [c for c in clip["channels"] if c["target"]["node"] == node]
    sampler = clip["samplers"][channel["sampler"]]
    times = accessor(gltf, binary, sampler["input"])
    return accessor(gltf, binary, sampler["output"]).reshape(len(times), -1)


@pytest.mark.parametrize(
    "name, expected",
    [
        ("jawOpen", "jawOpen"),
        ("JawOpen", "jawOpen"),
        ("jaw_open", "jawOpen"),
        ("Jaw-Open", "jawOpen"),
        ("blendShape1.jawOpen", "jawOpen"),
        ("Head|mouthSmile_L", "mouthSmileLeft"),
        ("mesh:eyeBlink_R", "eyeBlinkRight"),
        ("ARKit_tongueOut", "tongueOut"),
        ("CC_Base_mouthRight", "mouthRight"),
        ("EYE_LOOK_IN_LEFT", "eyeLookInLeft"),
        ("Fcl_MTH_A", None),
        ("viseme_O", None),
        ("smile", None),
    ],
)
def test_arkit_names_in_exporters_spellings(name, expected):
    index = arkit_channel(name)
    assert (ARKIT_NAMES[index] if index >= 0 else None) == expected


def test_viseme_names_and_map():
    assert [viseme_channel(n) for n in ("viseme_sil", "viseme_aa", "viseme_E", "V_PP")] == [
        0,
        10,
        11,
        1,
    ]
    assert viseme_channel("E") == viseme_channel("jawOpen") == -1
    w = np.zeros((3, 52), np.float32)
    w[0, ARKIT_NAMES.index("jawOpen")] = 0.7
    w[1, ARKIT_NAMES.index("mouthPucker")] = 1.0
    w[2, ARKIT_NAMES.index("mouthClose")] = w[2, ARKIT_NAMES.index("mouthPressLeft")] = 1.0
    v = visemes_from_arkit(w)
    assert v.shape == (3, 15) and v.min() >= 0 and v.max() <= 1
    assert v[0, VISEMES.index("aa")] == pytest.approx(0.7) and v[0].sum() == pytest.approx(0.7)
    assert v[1, VISEMES.index("U")] == 1.0
    assert v[2, VISEMES.index("PP")] == 1.0  # 1 + 0.5, clipped


@pytest.mark.parametrize("suffix", [".glb", ".vrm"])
def test_clip_written_into_a_copy_leaves_everything_else_byte_identical(tmp_path, suffix):
    src = make_avatar(tmp_path / f"me{suffix}", vrm=suffix == ".vrm")
    before = src.read_bytes()
    weights = arkit_weights()
    binding = animate_avatar(src, weights, FPS, tmp_path / f"talking{suffix}")
    assert src.read_bytes() == before  # the avatar itself is untouched
    old, old_bin = read_glb(src)
    new, new_bin = read_glb(tmp_path / f"talking{suffix}")

    # Every untouched part of the JSON is the same, and the old arrays are a prefix of the new.
    assert set(new) == set(old)
    for key in set(old) - set(APPENDED):
        assert json.dumps(new[key], sort_keys=True) == json.dumps(old[key], sort_keys=True), key
    for key in ("accessors", "bufferViews"):
        assert new[key][: len(old[key])] == old[key], key
    # The speech is the first clip (the one viewers play); the avatar's own clips follow it.
    assert new["animations"][1:] == old["animations"] and old["animations"][0]["name"] == "Idle"
    # The binary chunk is kept byte for byte (every buffer view: vertices, skin, texture...).
    assert new_bin[: len(old_bin)] == old_bin
    for view in old["bufferViews"]:
        start, end = view["byteOffset"], view["byteOffset"] + view["byteLength"]
        assert new_bin[start:end] == old_bin[start:end]

    # One clip: a channel for each node of the three meshes with ARKit names, none for the hat.
    clip = new["animations"][0]
    assert clip["name"] == "talk"
    assert sorted(c["target"]["node"] for c in clip["channels"]) == [2, 3, 4]
    assert {m.name for m in binding.meshes} == {"Head", "Teeth", "Tongue"}
    assert set(binding.channels) == HEAD_DRIVEN and len(binding.missing) == 52 - len(HEAD_DRIVEN)
    times = accessor(new, new_bin, clip["samplers"][0]["input"])
    assert len(times) == T and times[-1] == pytest.approx((T - 1) / FPS)
    col = {n: weights[:, ARKIT_NAMES.index(n)] for n in ("jawOpen", "mouthFunnel", "tongueOut")}
    head, teeth, tongue = (clip_values(new, new_bin, n) for n in (2, 3, 4))
    np.testing.assert_array_equal(head[:, 0], col["jawOpen"])  # blendShape1.jawOpen
    np.testing.assert_array_equal(teeth[:, 0], col["jawOpen"])  # JawOpen moves with the head
    np.testing.assert_array_equal(teeth[:, 1], col["mouthFunnel"])
    np.testing.assert_array_equal(teeth[:, 2], 0)  # CustomSculpt keeps its rest weight
    np.testing.assert_array_equal(tongue, np.stack([col["jawOpen"], col["tongueOut"]], 1))

    report = validate_glb(tmp_path / f"talking{suffix}")
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]
    # the only remarks: the validator does not know VRM, whose name lacks a vendor prefix
    remarks = [m for m in report["issues"]["messages"] if "/extensions" not in m.get("pointer", "")]
    assert not remarks, remarks
    assert report["info"]["animationCount"] == 2


def test_viseme_fallback_when_no_arkit_mouth_shapes(tmp_path):
    src = make_avatar(tmp_path / "rpm.glb", visemes=True)
    weights = arkit_weights()
    binding = animate_avatar(src, weights, FPS, tmp_path / "out.glb")
    assert binding.visemes == ("sil", "PP", "TH", "aa", "O", "U")
    assert binding.channels == ("eyeBlinkLeft", "eyeBlinkRight")
    assert "6 of 15 Oculus visemes" in binding.summary() and "\n" not in binding.summary()
    assert "lacks visemes FF, DD, kk, CH, SS, nn, RR, E, I: export all 15" in binding.summary()
    gltf, binary = read_glb(tmp_path / "out.glb")
    head = clip_values(gltf, binary, 2)  # sil PP aa O U eyeBlinkLeft eyeBlinkRight
    visemes = visemes_from_arkit(weights)
    others = np.delete(oculus_visemes(weights, FPS), 0, axis=1).max(1)
    np.testing.assert_allclose(head[:, 0], 1 - others, atol=1e-6)  # silence: the mouth at rest
    np.testing.assert_allclose(head[:, 2], visemes[:, VISEMES.index("aa")])
    np.testing.assert_allclose(head[:, 2], weights[:, ARKIT_NAMES.index("jawOpen")])
    np.testing.assert_array_equal(head[:, 5], weights[:, ARKIT_NAMES.index("eyeBlinkLeft")])
    assert validate_glb(tmp_path / "out.glb")["issues"]["numErrors"] == 0


def test_second_run_replaces_the_talk_clip_and_keeps_the_others_after_it(tmp_path):
    """A copy animated again: one speech clip, the new one, first; the avatar's Idle after it."""
    animate_avatar(make_avatar(tmp_path / "a.glb"), arkit_weights(), FPS, tmp_path / "b.glb")
    binding = animate_avatar(tmp_path / "b.glb", arkit_weights(seed=1), FPS, tmp_path / "c.glb")
    assert binding.clips == ("talk", "Idle")
    assert "replaces its clip 'talk'" in binding.summary() and "(Idle)" in binding.summary()
    gltf, binary = read_glb(tmp_path / "c.glb")
    assert [a["name"] for a in gltf["animations"]] == ["talk", "Idle"]
    jaw = arkit_weights(seed=1)[:, ARKIT_NAMES.index("jawOpen")]
    np.testing.assert_array_equal(clip_values(gltf, binary, 2)[:, 0], jaw)  # the second run's
    # read back by a third-party parser too: pygltflib sees the speech clip first
    import pygltflib

    parsed = pygltflib.GLTF2().load(str(tmp_path / "c.glb"))
    assert [a.name for a in parsed.animations] == ["talk", "Idle"]
    assert validate_glb(tmp_path / "c.glb")["issues"]["numErrors"] == 0


def test_bad_avatars_and_outputs_give_one_line_errors(tmp_path):
    src = make_avatar(tmp_path / "a.glb")
    gltf, _ = read_glb(src)
    for mesh in gltf["meshes"]:
        mesh.pop("extras", None)
    with pytest.raises(TalkmeshError, match="no morph targets with ARKit names"):
        bind_avatar(gltf)
    (tmp_path / "x.gltf").write_text('{"asset": {"version": "2.0"}}')
    (tmp_path / "y.glb").write_bytes(b"glTF\x02\0\0\0\x30\0\0\0" + b"\0" * 8)  # says 48 bytes
    cases = [
        (tmp_path / "x.gltf", tmp_path / "o.glb", "not a binary glTF"),
        (tmp_path / "y.glb", tmp_path / "o.glb", "truncated"),
        (tmp_path / "missing.glb", tmp_path / "o.glb", "no such file"),
        (src, src, "refusing to write over the avatar"),
        (src, tmp_path / "o.fbx", "written as .glb or .vrm"),
    ]
    for avatar, out, message in cases:
        with pytest.raises(TalkmeshError, match=message) as e:
            animate_avatar(avatar, arkit_weights(), FPS, out)
        assert "\n" not in str(e.value)
    (tmp_path / "taken.glb").write_bytes(b"keep")
    with pytest.raises(TalkmeshError, match="already exists"):
        animate_avatar(src, arkit_weights(), FPS, tmp_path / "taken.glb")
    assert (tmp_path / "taken.glb").read_bytes() == b"keep"
    assert not list(tmp_path.glob(".talkmesh-*"))


@pytest.mark.skipif(not CLIP.exists(), reason="pocketsphinx-testdata not installed")
@pytest.mark.parametrize("fps", [30.0, 25.0])
def test_cli_avatar_run_exports_glb_vrm_and_live_link(tmp_path, capsys, fps):
    """Frame count = audio length x fps in the avatar's clip and in the Live Link CSV."""
    speech = tmp_path / "speech.wav"
    speech.write_bytes(CLIP.read_bytes())
    avatar = make_avatar(tmp_path / "me.vrm", vrm=True)
    outs = [tmp_path / n for n in ("talking.vrm", "talking.glb", "talking.csv")]
    args = [
        "animate",
        str(speech),
        "--avatar",
        str(avatar),
        "--model",
        "procedural",
        "--fps",
        str(fps),
    ]
    assert main([*args, *(a for p in outs for a in ("-o", str(p)))]) == 0
    out = capsys.readouterr().out
    assert "lacks 45: eyeLookDownLeft" in out and "Head, Teeth, Tongue" in out
    frames = round(sf.info(speech).duration * fps)
    for p in outs[:2]:
        gltf, binary = read_glb(p)
        assert gltf["extensions"]["VRM"]["meta"]["title"] == "Test avatar"
        assert clip_values(gltf, binary, 2).shape == (frames, 6)
    with open(outs[2], newline="") as f:
        assert len(list(csv.reader(f))) == 1 + frames
    jaw = clip_values(*read_glb(outs[0]), 2)[:, 0]
    assert jaw.max() - jaw.min() > 0.1  # the jaw follows the speech


def test_cli_avatar_errors_before_running_the_model(tmp_path, capsys):
    speech = tmp_path / "speech.wav"
    sf.write(speech, np.zeros(1600, np.float32), 16_000)
    gltf_file = tmp_path / "me.gltf"
    gltf_file.write_text("{}")
    assert (
        main(["animate", str(speech), "--avatar", str(gltf_file), "-o", str(tmp_path / "o.glb")])
        == 2
    )
    assert "not a binary glTF" in capsys.readouterr().err
    avatar = make_avatar(tmp_path / "me.glb")
    assert (
        main(["animate", str(speech), "--avatar", str(avatar), "-o", str(avatar), "--overwrite"])
        == 2
    )
    assert "refusing to write over an input" in capsys.readouterr().err


@pytest.mark.parametrize("vrm", [True, False])
def test_head_pose_turns_the_avatar_s_head_bone(tmp_path, vrm):
    from scipy.spatial.transform import Rotation

    from talkmesh.output.avatar import glb_bytes

    src = make_avatar(tmp_path / ("me.vrm" if vrm else "me.glb"), vrm=vrm)
    gltf, binary = read_glb(src)
    if vrm:  # the humanoid's head: the neck joint (node 1) stands in for it
        gltf["extensions"]["VRM"]["humanoid"]["humanBones"].append({"bone": "head", "node": 1})
    else:  # a plain rig's head joint, found by its name
        gltf["nodes"][1]["name"] = "mixamorig:Head"
    gltf["nodes"][0]["rotation"] = [0.0, np.sin(0.2), 0.0, np.cos(0.2)]  # the hips turned
    gltf["nodes"][1]["rotation"] = [np.sin(0.1), 0.0, 0.0, np.cos(0.1)]  # the bone's rest
    src.write_bytes(glb_bytes(gltf, binary))
    rng = np.random.default_rng(2)
    pose = np.concatenate([rng.uniform(-0.2, 0.2, (T, 3)), np.zeros((T, 3))], 1)
    out = tmp_path / ("talking.vrm" if vrm else "talking.glb")
    animate_avatar(src, arkit_weights(), FPS, out, head_pose=pose.astype(np.float32))
    new, new_bin = read_glb(out)
    clip = new["animations"][0]  # the speech clip comes first
    (channel,) = [c for c in clip["channels"] if c["target"]["path"] == "rotation"]
    assert channel["target"]["node"] == 1
    acc = new["accessors"][clip["samplers"][channel["sampler"]]["output"]]
    assert acc["type"] == "VEC4" and acc["count"] == T
    view = new["bufferViews"][acc["bufferView"]]
    got = np.frombuffer(new_bin, "<f4", 4 * T, view["byteOffset"]).reshape(T, 4)
    # the bone's world rotation is the hips' times its own: the pose, turned to face the avatar's
    # front (+z, or -z for VRM 0.x), must be the change of that world rotation
    pitch, yaw, roll = pose[:, :3].T
    turn = Rotation.from_euler("YXZ", np.stack([yaw, pitch, roll], 1))
    if vrm:
        flip = Rotation.from_euler("y", np.pi)
        turn = flip * turn * flip.inv()
    hips = Rotation.from_quat(gltf["nodes"][0]["rotation"])
    rest = hips * Rotation.from_quat(gltf["nodes"][1]["rotation"])  # the bone's world rest
    world = hips * Rotation.from_quat(got)
    np.testing.assert_allclose(world.as_matrix(), (turn * rest).as_matrix(), atol=1e-5)
    report = validate_glb(out)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]
