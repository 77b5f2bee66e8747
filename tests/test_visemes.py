"""All 15 Oculus visemes (the tongue visemes from the phones, else from the motion), Azure's 22
viseme ids as timed events, the .visemes.json export, and viseme avatars driven with all 15."""

from __future__ import annotations

import json

import numpy as np
import pytest
from avatars import make_avatar
from test_avatar import clip_values
from test_cli import CLIP

from talkmesh.cli import main
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.arkit_names import VISEMES
from talkmesh.face.visemes import (
    AZURE_FROM_PHONE,
    OCULUS_FROM_PHONE,
    TICKS_PER_S,
    azure_events,
    oculus_visemes,
)
from talkmesh.output.avatar import animate_avatar, bind_avatar, read_glb
from talkmesh.output.formats import save_animation
from talkmesh.pipeline import animate

FPS = 30.0
ALL = [f"viseme_{v}" for v in VISEMES] + ["eyeBlinkLeft"]


def arkit(frames: int, **set_to: float) -> np.ndarray:
    w = np.zeros((frames, 52), np.float32)
    for name, value in set_to.items():
        w[:, ARKIT_NAMES.index(name)] = value
    return w


def column(name: str) -> int:
    return VISEMES.index(name)


def test_phone_tables_cover_the_recogniser_set_and_azure_ids():
    assert set(OCULUS_FROM_PHONE.values()) == set(VISEMES)  # every viseme has phones
    assert set(AZURE_FROM_PHONE.values()) == set(range(22))  # every Azure id has phones


def test_tongue_visemes_follow_the_phones():
    phones = [("SIL", 0.0, 0.2), ("T", 0.2, 0.3), ("S", 0.3, 0.45), ("K", 0.6, 0.7)]
    v = oculus_visemes(arkit(30, jawOpen=0.15), FPS, phones)
    assert v.shape == (30, 15) and v.min() >= 0 and v.max() <= 1
    t = np.arange(30) / FPS
    inside = lambda a, b: (t > a + 0.04) & (t < b - 0.04)  # noqa: E731
    assert (v[inside(0.2, 0.3), column("DD")] > 0.99).all()
    assert (v[inside(0.3, 0.45), column("SS")] > 0.99).all()
    assert (v[t > 0.8, column("kk")] == 0).all() and (v[t < 0.15, column("DD")] == 0).all()
    assert v[:, column("RR")].max() == 0 and v[:, column("CH")].max() == 0  # no R, no SH
    assert v[:, column("aa")].max() == pytest.approx(0.15)  # the jaw still from the motion


def test_tongue_visemes_from_the_motion_without_phones():
    spread = arkit(4, jawOpen=0.15, mouthStretchLeft=0.8, mouthStretchRight=0.8)
    rounded = arkit(4, jawOpen=0.15, mouthFunnel=0.9)
    neutral = arkit(4, jawOpen=0.15)
    wide = arkit(4, jawOpen=0.8)
    shut = arkit(4, jawOpen=0.15, mouthClose=1.0)
    v = {k: oculus_visemes(w, FPS)[0] for k, w in locals().items() if isinstance(w, np.ndarray)}
    assert v["spread"][column("SS")] > 0.3 and v["rounded"][column("CH")] > 0.3
    assert v["neutral"][column("DD")] > 0.3
    assert max(v["wide"][column(n)] for n in ("DD", "SS", "CH")) == 0  # an open vowel
    assert max(v["shut"][column(n)] for n in ("DD", "SS", "CH")) == 0  # lips closed: PP
    for k in ("kk", "nn", "RR"):  # the lips cannot tell these
        assert all(v[c][column(k)] == 0 for c in v)
    rest = oculus_visemes(arkit(2), FPS)
    assert rest[0, column("sil")] == 1 and rest[0].sum() == 1


def test_azure_events_from_phones_and_from_the_motion():
    phones = [
        ("SIL", 0.0, 0.1),
        ("M", 0.1, 0.2),
        ("AA", 0.2, 0.3),
        ("AA", 0.3, 0.4),
        ("T", 0.4, 0.5),
    ]
    events = azure_events(np.zeros((15, 15)), FPS, phones)
    assert events == [
        (0, 0),
        (TICKS_PER_S // 10, 21),
        (2 * TICKS_PER_S // 10, 2),
        (4 * TICKS_PER_S // 10, 19),
    ]
    w = np.zeros((12, 52), np.float32)
    w[3:8, ARKIT_NAMES.index("jawOpen")] = 0.9  # aa over frames 3-7
    w[8, ARKIT_NAMES.index("mouthPucker")] = 0.9  # a one-frame flicker is not an event
    events = azure_events(oculus_visemes(w, FPS), FPS)
    assert [i for _, i in events] == [0, 2, 0]
    assert events[1][0] == round(3 / FPS * TICKS_PER_S)


@pytest.mark.skipif(not CLIP.exists(), reason="pocketsphinx-testdata not installed")
def test_visemes_json_and_a_full_viseme_avatar_from_the_procedural_animator(tmp_path):
    """Real speech: the recognised phones put the tongue visemes into the file and the avatar."""
    anim = animate(CLIP, model="procedural")
    assert anim.phones and all(len(p) == 3 for p in anim.phones)
    (out,) = save_animation(anim, tmp_path / "talk.visemes.json")
    doc = json.loads(out.read_text())
    assert doc["source"] == "phones" and doc["oculus"]["names"] == list(VISEMES)
    frames = np.asarray(doc["oculus"]["frames"])
    assert frames.shape == (anim.num_frames, 15)
    tongue = [column(n) for n in ("DD", "kk", "nn", "SS")]  # "he was not an ill disposed..."
    assert (frames[:, tongue].max(0) > 0.9).all()
    ids = [e["visemeId"] for e in doc["azure"]]
    ticks = [e["audioOffset"] for e in doc["azure"]]
    assert set(ids) <= set(range(22)) and {19, 15} <= set(ids) and ticks == sorted(ticks)
    assert ticks[-1] < anim.duration * TICKS_PER_S

    avatar = make_avatar(tmp_path / "rpm.glb", visemes=True, head_names=ALL)
    binding = animate_avatar(avatar, anim.weights, anim.fps, tmp_path / "o.glb", phones=anim.phones)
    assert binding.visemes == VISEMES and "lacks visemes" not in binding.summary()
    head = clip_values(*read_glb(tmp_path / "o.glb"), 2)
    np.testing.assert_allclose(head[:, :15], frames, atol=1e-4)  # the same curves as the file
    # the CLI gives the avatar the phones too
    assert (
        main(
            [
                "animate",
                str(CLIP),
                "--model",
                "procedural",
                "--avatar",
                str(avatar),
                "-q",
                "-o",
                str(tmp_path / "cli.glb"),
                "-o",
                str(tmp_path / "cli.visemes.json"),
            ]
        )
        == 0
    )
    cli = clip_values(*read_glb(tmp_path / "cli.glb"), 2)
    assert cli[:, tongue].max(0).min() > 0.9
    assert json.loads((tmp_path / "cli.visemes.json").read_text())["source"] == "phones"


def test_viseme_avatar_that_cannot_open_its_mouth_is_one_line(tmp_path):
    avatar = make_avatar(tmp_path / "half.glb", visemes=True, head_names=["viseme_PP", "viseme_DD"])
    gltf = read_glb(avatar)[0]
    for mesh in gltf["meshes"]:  # the teeth's viseme_aa and viseme_O renamed away
        names = (mesh.get("extras") or {}).get("targetNames") or []
        names[:] = [n.replace("viseme_", "custom_") if n[-2:] in ("aa", "_O") else n for n in names]
    with pytest.raises(TalkmeshError, match="none that opens the mouth") as e:
        bind_avatar(gltf, "half.glb")
    assert "\n" not in str(e.value) and "export the full set of 15" in str(e.value)


def test_visemes_json_of_vertices_only_is_refused(tmp_path):
    from talkmesh.animation import Animation

    anim = Animation(np.zeros((3, 4, 3)), np.zeros((0, 3)), FPS)
    with pytest.raises(TalkmeshError, match="no ARKit weights"):
        save_animation(anim, tmp_path / "x.visemes.json")
    assert not (tmp_path / "x.visemes.json").exists()


# --- VRM expressions -------------------------------------------------------------------------

VROID = ["Fcl_MTH_A", "Fcl_MTH_I", "Fcl_MTH_U", "Fcl_MTH_E", "Fcl_MTH_O", "Fcl_EYE_Close"]
HEAD_NODE = 2  # the test avatar's head mesh (0) sits on node 2
REQUIRED_BONES = (
    "spine", "head", "leftUpperLeg", "leftLowerLeg", "leftFoot", "rightUpperLeg", "rightLowerLeg",
    "rightFoot", "leftUpperArm", "leftLowerArm", "leftHand", "rightUpperArm", "rightLowerArm",
    "rightHand",
)  # fmt: skip


def vroid(tmp_path, version: str, groups: bool = True):
    """A VRoid-like avatar: the head's morph targets named as VRoid names them (no ARKit or
    viseme names anywhere), the mouth and blink presets bound to them in VRM ``version``."""
    from talkmesh.output.avatar import glb_bytes

    src = make_avatar(tmp_path / "base.vrm", vrm=True, head_names=VROID)
    gltf, binary = read_glb(src)
    for mesh in gltf["meshes"][1:]:  # teeth and tongue: names no rule knows
        for holder in (
            mesh.get("extras") or {},
            *(p.get("extras") or {} for p in mesh["primitives"]),
        ):
            if "targetNames" in holder:
                holder["targetNames"] = [f"Custom_{k}" for k in range(len(holder["targetNames"]))]
    bones = {"hips": 0, "neck": 1}  # the rest of the bones a VRM requires, as empty nodes
    for bone in REQUIRED_BONES:
        gltf["nodes"].append({"name": bone})
        bones[bone] = len(gltf["nodes"]) - 1
        gltf["nodes"][0].setdefault("children", []).append(bones[bone])
    presets = {"aa": 0, "ih": 1, "ou": 2, "ee": 3, "oh": 4, "blink": 5} if groups else {}
    if version == "0.x":
        gltf["extensions"]["VRM"]["humanoid"]["humanBones"] = [
            {"bone": b, "node": n} for b, n in bones.items()
        ]
        names0 = {"aa": "a", "ih": "i", "ou": "u", "ee": "e", "oh": "o", "blink": "blink"}
        gltf["extensions"]["VRM"]["blendShapeMaster"]["blendShapeGroups"] = [
            {"name": p, "presetName": names0[p], "binds": [{"mesh": 0, "index": i, "weight": 100}]}
            for p, i in presets.items()
        ]
    else:
        gltf["extensions"] = {
            "VRMC_vrm": {
                "specVersion": "1.0",
                "meta": {
                    "name": "Test avatar",
                    "authors": ["talkmesh tests"],
                    "licenseUrl": "https://vrm.dev/licenses/1.0/",
                },
                "humanoid": {"humanBones": {b: {"node": n} for b, n in bones.items()}},
                "expressions": {
                    "preset": {
                        p: {"morphTargetBinds": [{"node": HEAD_NODE, "index": i, "weight": 1.0}]}
                        for p, i in presets.items()
                    }
                },
            }
        }
        gltf["extensionsUsed"] = ["VRMC_vrm"]
    path = tmp_path / f"vroid-{version}.vrm"
    path.write_bytes(glb_bytes(gltf, binary))
    return path


@pytest.mark.parametrize("version", ["0.x", "1.0"])
def test_vrm_expression_presets_are_driven_when_there_are_no_arkit_shapes(tmp_path, version):
    from test_avatar import arkit_weights
    from test_io import validate_glb

    weights = arkit_weights()
    out = tmp_path / "talking.vrm"
    binding = animate_avatar(vroid(tmp_path, version), weights, FPS, out)
    assert binding.vrm == version and binding.expressions == ("aa", "ih", "ou", "ee", "oh", "blink")
    assert f"VRM {version} expressions aa ih ou ee oh blink" in binding.summary()
    head = clip_values(*read_glb(out), HEAD_NODE)
    visemes = oculus_visemes(weights, FPS)
    for k, viseme in enumerate(("aa", "I", "U", "E", "O")):
        np.testing.assert_allclose(head[:, k], visemes[:, column(viseme)], atol=1e-6)
    blink = np.minimum(
        weights[:, ARKIT_NAMES.index("eyeBlinkLeft")],
        weights[:, ARKIT_NAMES.index("eyeBlinkRight")],
    )
    np.testing.assert_allclose(head[:, 5], blink, atol=1e-6)
    assert head[:, 0].max() - head[:, 0].min() > 0.5  # the mouth moves
    assert validate_glb(out)["issues"]["numErrors"] == 0


def test_an_avatar_with_arkit_shapes_and_vrm_presets_uses_arkit(tmp_path):
    from test_avatar import arkit_weights

    avatar = make_avatar(tmp_path / "both.vrm", vrm=True)  # preset "a" bound to jawOpen as well
    binding = animate_avatar(avatar, arkit_weights(), FPS, tmp_path / "o.vrm")
    assert binding.expressions == () and "jawOpen" in binding.channels


@pytest.mark.parametrize("version", ["0.x", "1.0"])
def test_a_vrm_without_mouth_expressions_or_shapes_is_one_line(tmp_path, version):
    avatar = vroid(tmp_path, version, groups=False)
    with pytest.raises(TalkmeshError, match=f"a VRM {version} without mouth expressions") as e:
        bind_avatar(read_glb(avatar)[0], str(avatar))
    assert "\n" not in str(e.value)


def test_azure_events_from_a_partly_open_mouth_are_its_shape_not_silence():
    w = np.zeros((6, 52), np.float32)
    w[2:, ARKIT_NAMES.index("jawOpen")] = 0.3  # sil is 0.7 there, but the mouth is open
    assert [i for _, i in azure_events(oculus_visemes(w, FPS), FPS)] == [0, 2]


def test_a_vrm_whose_presets_bind_a_missing_node_is_one_line(tmp_path):
    gltf = read_glb(vroid(tmp_path, "1.0"))[0]
    gltf["extensions"]["VRMC_vrm"]["expressions"]["preset"]["aa"]["morphTargetBinds"][0]["node"] = (
        999
    )
    with pytest.raises(TalkmeshError, match="does not follow the glTF 2.0 schema") as e:
        bind_avatar(gltf, "broken.vrm")
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("version", ["0.x", "1.0"])
def test_vrm_mouth_presets_bound_to_targets_it_lacks_are_one_line(tmp_path, version):
    """Mouth presets binding a target index past the mesh's last (a broken export) with a valid
    blink: before, the avatar was written blinking with a still mouth; now one line says so."""
    from talkmesh.output.avatar import glb_bytes

    gltf, binary = read_glb(vroid(tmp_path, version))
    if version == "0.x":
        for g in gltf["extensions"]["VRM"]["blendShapeMaster"]["blendShapeGroups"]:
            if g["presetName"] != "blink":
                g["binds"][0]["index"] += 50
    else:
        for name, preset in gltf["extensions"]["VRMC_vrm"]["expressions"]["preset"].items():
            if name != "blink":
                preset["morphTargetBinds"][0]["index"] += 50
    with pytest.raises(TalkmeshError, match="mouth presets .* bind no morph target") as e:
        bind_avatar(gltf, "broken.vrm")
    message = str(e.value)
    assert "\n" not in message and "mesh 0 target 50" in message and "export it again" in message
    avatar = tmp_path / "broken.vrm"
    avatar.write_bytes(glb_bytes(gltf, binary))
    with pytest.raises(TalkmeshError, match="bind no morph target"):
        animate_avatar(avatar, arkit(4), FPS, tmp_path / "o.vrm")
    assert not (tmp_path / "o.vrm").exists()


def test_cli_bad_vrm_and_viseme_avatars_are_one_line_before_the_model(tmp_path, capsys):
    """The avatars the CLI cannot make talk are refused before any model loads (a model that
    does not exist is never looked at), in one line saying what is missing and what to do; a
    viseme avatar with half the set talks, and its line names the visemes it lacks."""
    import soundfile as sf

    from talkmesh.output.avatar import glb_bytes

    speech = tmp_path / "speech.wav"
    sf.write(speech, np.zeros(3200, np.float32), 16_000)
    half = ["viseme_PP", "viseme_DD", "viseme_kk", "viseme_SS"]  # none opens the mouth
    opener = ["viseme_sil", "viseme_PP", "viseme_aa", "viseme_E", "viseme_I", "viseme_O"]
    gltf, binary = read_glb(make_avatar(tmp_path / "half.glb", visemes=True, head_names=half))
    for mesh in gltf["meshes"][1:3]:  # the teeth's viseme_aa and viseme_O, the tongue's TH
        mesh["extras"]["targetNames"] = [f"custom_{k}" for k in mesh["extras"]["targetNames"]]
    (tmp_path / "half.glb").write_bytes(glb_bytes(gltf, binary))
    cases = {
        vroid(tmp_path, "0.x", groups=False): "a VRM 0.x without mouth expressions",
        vroid(tmp_path, "1.0", groups=False): "a VRM 1.0 without mouth expressions",
        tmp_path / "half.glb": "none that opens",
    }
    for avatar, message in cases.items():
        out = tmp_path / f"o{avatar.suffix}"
        args = ["animate", str(speech), "--avatar", str(avatar), "--model", "missing.safetensors"]
        assert main([*args, "-o", str(out)]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1 and not out.exists(), err
        assert "add the mouth presets" in err or "export the full set of 15" in err
    avatar = make_avatar(tmp_path / "six.glb", visemes=True, head_names=opener)
    args = ["animate", str(speech), "--avatar", str(avatar), "--model", "procedural"]
    assert main([*args, "-o", str(tmp_path / "six_talking.glb")]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert "lacks visemes FF, DD, kk, CH, SS, nn, RR, U: export all 15 to drive them" in line
