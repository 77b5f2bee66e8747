"""Videos of the avatar itself: every mesh of a .glb/.vrm posed as its clip moves it (morph
weights, skins, the head bone), in its base colours, from the front and three-quarter cameras;
``animate --avatar -o me.mp4`` and ``render talking.glb``; avatars it cannot draw in one line."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

pytest.importorskip("moderngl")
pytest.importorskip("imageio_ffmpeg")
pytest.importorskip("PIL.Image")

import soundfile as sf  # noqa: E402
from avatars import HEAD_KINDS, head_avatar, make_avatar  # noqa: E402
from test_cli import CLIP  # noqa: E402
from test_render import probe  # noqa: E402

from talkmesh.cli import main  # noqa: E402
from talkmesh.errors import TalkmeshError  # noqa: E402
from talkmesh.face.arkit import ARKIT_NAMES  # noqa: E402
from talkmesh.output.avatar import (  # noqa: E402
    glb_bytes,
    load_avatar_scene,
    read_glb,
    talking_scene,
)
from talkmesh.output.render import avatar_renderer, render_avatar_video  # noqa: E402
from talkmesh.output.scene import load_scene  # noqa: E402
from talkmesh.output.video import ffmpeg_exe  # noqa: E402

FPS, SIZE = 30.0, 128
REST, OPEN, BLINK = slice(0, 4), slice(4, 8), slice(8, 12)
CHANGED = 40  # a pixel changed when its grey level moved by more than this (of 255)


def speech_weights() -> np.ndarray:
    """(12, 52): four frames at rest, four with the mouth open, four with both eyes shut."""
    w = np.zeros((12, 52), np.float32)
    w[OPEN, ARKIT_NAMES.index("jawOpen")] = 0.8
    w[BLINK, ARKIT_NAMES.index("eyeBlinkLeft")] = 1.0
    w[BLINK, ARKIT_NAMES.index("eyeBlinkRight")] = 1.0
    return w


def grey_frames(path, size: int) -> np.ndarray:
    """(T, H, W) uint8 grey frames decoded from a video by ffmpeg."""
    cmd = [ffmpeg_exe(), "-v", "error", "-i", str(path), "-f", "rawvideo", "-pix_fmt", "gray", "-"]
    raw = subprocess.run(cmd, capture_output=True, check=True).stdout
    return np.frombuffer(raw, np.uint8).reshape(-1, size, size)


@pytest.mark.parametrize("kind", HEAD_KINDS)
def test_the_avatar_s_video_has_its_frames_and_its_mouth_opens(tmp_path, kind):
    """ARKit glb, VRM with presets only, visemes only: a frame per clip frame, the audio muxed,
    and the pixels that change when the mouth opens lie below those that change in a blink."""
    avatar = head_avatar(tmp_path / f"me.{'vrm' if kind == 'vrm' else 'glb'}", kind)
    scene = talking_scene(avatar, speech_weights(), FPS)
    assert scene.num_frames == 12 and scene.fps == FPS
    audio = (0.2 * np.sin(np.arange(6400) / 16_000 * 2 * np.pi * 220)).astype(np.float32)
    out = render_avatar_video(scene, tmp_path / "me.mp4", SIZE, audio=audio, sample_rate=16_000)
    info = probe(out)
    assert info["frames"] == 12 and info["audio_codec"] == "aac"
    assert info["audio_seconds"] == pytest.approx(12 / FPS, abs=0.03)
    frames = grey_frames(out, SIZE).astype(int)
    rest = frames[REST].mean(0)
    mouth = np.abs(frames[OPEN].mean(0) - rest) > CHANGED
    eyes = np.abs(frames[BLINK].mean(0) - rest) > CHANGED
    assert mouth.sum() > 20 and eyes.sum() > 5, (mouth.sum(), eyes.sum())
    mouth_rows, eye_rows = np.nonzero(mouth)[0], np.nonzero(eyes)[0]
    assert eye_rows.max() < np.median(mouth_rows)  # the eyes shut above the opening mouth
    assert np.median(mouth_rows) > SIZE / 2 > np.median(eye_rows)


def test_three_quarter_camera_turns_the_avatar(tmp_path):
    scene = talking_scene(head_avatar(tmp_path / "me.glb"), speech_weights(), FPS)
    images = {}
    for camera in ("front", "three-quarter"):
        with avatar_renderer(scene, SIZE, camera=camera) as renderer:
            images[camera] = renderer.render(scene.vertices(0)).astype(int)
    # the silhouette: pixels off the background (the same colour along each row)
    front, turned = (np.abs(im - im[:, :1]).max(2) > 8 for im in images.values())
    asymmetry = [np.mean(m != m[:, ::-1]) for m in (front, turned)]
    assert asymmetry[0] < 0.02 < asymmetry[1], asymmetry  # seen straight on, then turned


def test_skins_node_transforms_textures_and_vrm_facing(tmp_path):
    """The box avatar (a skin of two joints, a textured head, a hat moved by its node): rest
    vertices as trimesh places them, the head bone's turn as scipy's rotation about the joint,
    the checker texture's colours, and a VRM 0.x turned half a turn to face the camera."""
    trimesh = pytest.importorskip("trimesh")
    from scipy.spatial.transform import Rotation

    src = make_avatar(tmp_path / "me.glb")
    gltf, binary = read_glb(src)
    gltf["nodes"][1]["name"] = "Head"  # the neck joint (y = 1.5 m) stands in for a head bone
    src.write_bytes(glb_bytes(gltf, binary))
    still = load_scene(*read_glb(src), "me.glb")  # its Idle clip's first key is the rest pose
    placed = trimesh.load(src, force="scene").to_geometry()
    mine = still.vertices(0)[np.unique(still.faces)]
    theirs = np.asarray(placed.vertices)
    assert len(mine) == len(theirs)
    np.testing.assert_allclose(np.sort(mine, 0), np.sort(theirs, 0), atol=1e-6)

    pose = np.zeros((3, 6), np.float32)
    pose[2, :3] = [0.3, 0.0, 0.0]  # a nod: pitch 0.3 rad
    scene = talking_scene(src, np.zeros((3, 52), np.float32), FPS, head_pose=pose)
    rest, nod = scene.vertices(0), scene.vertices(2)
    head = slice(0, 8)  # the head box, skinned: its upper four corners to the neck joint
    upper = rest[head][:, 1] > 1.6
    turn = Rotation.from_euler("x", 0.3)
    pivot = np.array([0.0, 1.5, 0.0])
    expected = turn.apply(rest[head][upper] - pivot) + pivot
    np.testing.assert_allclose(nod[head][upper], expected, atol=1e-5)
    np.testing.assert_allclose(nod[head][~upper], rest[head][~upper], atol=1e-6)
    assert scene.focus[:8][upper].all() and not scene.focus[:8][~upper].any()

    checker = {(200, 90, 80), (40, 40, 40)}
    assert {tuple(np.round(c * 255).astype(int)) for c in scene.colors[head]} <= checker
    plain = np.array([0.9, 0.9, 0.85])  # the teeth's linear baseColorFactor, in sRGB
    np.testing.assert_allclose(scene.colors[8], 1.055 * plain ** (1 / 2.4) - 0.055, atol=1e-5)

    vrm = load_scene(*read_glb(make_avatar(tmp_path / "me.vrm", vrm=True)), "me.vrm")
    np.testing.assert_allclose(vrm.vertices(0) * [-1, 1, -1], still.vertices(0), atol=1e-6)


@pytest.mark.skipif(not CLIP.exists(), reason="pocketsphinx-testdata not installed")
def test_cli_animate_avatar_to_mp4_and_render_the_talking_vrm(tmp_path, capsys):
    speech = tmp_path / "speech.wav"
    speech.write_bytes(CLIP.read_bytes())
    avatar = make_avatar(tmp_path / "me.vrm", vrm=True)
    args = ["animate", str(speech), "--avatar", str(avatar), "--model", "procedural"]
    outs = ["-o", str(tmp_path / "me.mp4"), "-o", str(tmp_path / "me.vrm.vrm"), "--size", "64"]
    assert main([*args, *outs, "--camera", "three-quarter"]) == 0
    frames = round(sf.info(speech).duration * FPS)
    info = probe(tmp_path / "me.mp4")
    assert info["frames"] == frames and info["width"] == 64
    assert info["audio_seconds"] == pytest.approx(frames / FPS, abs=0.03)
    capsys.readouterr()
    render = ["render", str(tmp_path / "me.vrm.vrm"), "-o", str(tmp_path / "again.mp4")]
    assert main([*render, "--size", "64", "--audio", str(speech), "-q"]) == 0
    again = probe(tmp_path / "again.mp4")
    assert again["frames"] == frames and again["audio_codec"] == "aac"
    # the same clip, posed the same way: the two videos agree frame by frame
    a, b = grey_frames(tmp_path / "me.mp4", 64), grey_frames(tmp_path / "again.mp4", 64)
    assert np.abs(a.astype(int) - b).mean() > 1  # three-quarter against front
    jaw = [np.abs(f.astype(int) - b[0]).mean() for f in b]
    assert max(jaw) > 0.5  # the avatar moves in its video


def without_meshes(tmp_path):
    gltf, binary = read_glb(make_avatar(tmp_path / "a.glb"))
    for node in gltf["nodes"]:
        node.pop("mesh", None)
        node.pop("skin", None)
    path = tmp_path / "empty.vrm"
    path.write_bytes(glb_bytes(gltf, binary))
    return path


def test_avatars_the_renderer_cannot_draw_are_one_line(tmp_path, capsys):
    gltf, binary = read_glb(make_avatar(tmp_path / "a.glb"))
    draco = dict(gltf, extensionsUsed=["KHR_draco_mesh_compression"])
    external = dict(gltf, buffers=[{"byteLength": 10, "uri": "a.bin"}])
    lines = gltf["meshes"]
    flat = dict(gltf, meshes=[{**m, "primitives": [{**p, "mode": 1} for p in m["primitives"]]}
                              for m in lines])  # fmt: skip
    broken = dict(gltf, nodes=[*gltf["nodes"][:3], {"mesh": 99}, *gltf["nodes"][4:]])
    huge = json.loads(json.dumps(gltf))  # a position accessor of 10^12 zeros, without data
    huge["accessors"][huge["meshes"][3]["primitives"][0]["attributes"]["POSITION"]].update(
        {"count": 10**12, "bufferView": None}
    )
    huge["accessors"] = [{k: v for k, v in a.items() if v is not None} for a in huge["accessors"]]
    cases = [
        (draco, "Draco-compressed meshes"),
        (external, "external file"),
        (flat, "no triangle meshes to draw"),
        (broken, "does not follow the glTF 2.0 schema"),
        (huge, "claims 1000000000000 elements without data"),
    ]
    for data, message in cases:
        with pytest.raises(TalkmeshError, match=message) as e:
            load_scene(data, binary, "a.glb")
        assert "\n" not in str(e.value) and "a.glb" in str(e.value)
    with pytest.raises(TalkmeshError, match="no triangle meshes to draw"):
        load_avatar_scene(without_meshes(tmp_path))
    rig = head_avatar(tmp_path / "still.glb")
    gltf2, binary2 = read_glb(rig)
    (tmp_path / "still.vrm").write_bytes(glb_bytes(gltf2, binary2))
    out = str(tmp_path / "o.mp4")
    assert main(["render", str(tmp_path / "still.vrm"), "-o", out]) == 2
    err = capsys.readouterr().err
    assert "no animation clip to play" in err and "--avatar" in err and err.count("\n") == 1
    assert main(["render", str(tmp_path / "a.glb"), str(tmp_path / "a.glb"), "-o", out]) == 2
    assert "one avatar at a time" in capsys.readouterr().err


def test_animate_refuses_an_avatar_it_cannot_draw_before_the_model(tmp_path, capsys):
    speech = tmp_path / "speech.wav"
    sf.write(speech, np.zeros(1600, np.float32), 16_000)
    gltf, binary = read_glb(make_avatar(tmp_path / "a.glb"))
    gltf["extensionsUsed"] = ["KHR_draco_mesh_compression"]
    avatar = tmp_path / "draco.glb"
    avatar.write_bytes(glb_bytes(gltf, binary))
    out = tmp_path / "o.mp4"
    args = ["animate", str(speech), "--avatar", str(avatar), "--model", "no-such-model"]
    assert main([*args, "-o", str(out)]) == 2  # the avatar is refused before the model loads
    err = capsys.readouterr().err
    assert "Draco" in err and err.count("\n") == 1 and not out.exists()
    # the same avatar still gets its .glb copy: only drawing it needs decoded meshes
    assert main([*args[:4], "--model", "procedural", "-o", str(tmp_path / "o.glb"), "-q"]) == 0


def test_three_js_poses_the_talking_avatar_as_the_video_does(tmp_path):
    """three.js (GLTFLoader, AnimationMixer, its skinning and morphing) loads the talking copy
    that animate --avatar writes and places every vertex where the video's frames have it: the
    morph weights, the head bone's turn through the skin, the rigid meshes' node transforms."""
    from test_browser import CHROMIUM, ROOT

    from talkmesh.output.avatar import animate_avatar

    pytest.importorskip("playwright")
    esbuild = ROOT / "node_modules" / ".bin" / "esbuild"
    if not (ROOT / "node_modules" / "three").is_dir() or not esbuild.is_file():
        pytest.fail("three.js or esbuild is missing: run `npm ci` in the repo root")
    if not CHROMIUM.is_file():
        pytest.fail(f"{CHROMIUM} is missing: run `make setup` (installs Debian's chromium)")
    from playwright.sync_api import sync_playwright

    bundle = tmp_path / "player.js"
    subprocess.run(
        [str(esbuild), str(ROOT / "tests" / "pose_player.js"), "--bundle", "--format=iife",
         f"--outfile={bundle}", "--log-level=error"],
        check=True,
        timeout=120,
    )  # fmt: skip
    src = make_avatar(tmp_path / "me.glb")
    gltf, binary = read_glb(src)
    gltf["nodes"][1]["name"] = "Head"  # the neck joint turns as a head bone
    src.write_bytes(glb_bytes(gltf, binary))
    frames = 8
    rng = np.random.default_rng(3)
    weights = rng.uniform(0, 1, (frames, 52)).astype(np.float32)
    pose = np.zeros((frames, 6), np.float32)
    pose[:, :3] = rng.uniform(-0.3, 0.3, (frames, 3))
    out = tmp_path / "talking.glb"
    animate_avatar(src, weights, FPS, out, head_pose=pose)
    scene = load_avatar_scene(out)
    times = [k / FPS for k in range(frames - 1)]  # at the clip's end a looping action wraps
    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=["--no-sandbox"]
        )
        try:
            page = browser.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.set_content("<html><body></body></html>")
            page.add_script_tag(content=bundle.read_text())
            got = page.evaluate(
                "([bytes, times]) => window.poseGlb(bytes, times)",
                [list(out.read_bytes()), times],
            )
            assert not errors, errors
        finally:
            browser.close()
    assert got["clip"] == "talk"
    moved = 0.0
    for t, points in enumerate(got["frames"]):
        theirs = np.asarray(points, np.float64).reshape(-1, 3)  # meshes in the scene's order
        mine = scene.vertices(t).astype(np.float64)
        np.testing.assert_allclose(mine, theirs, atol=1e-5)
        moved = max(moved, np.abs(mine - scene.vertices(0)).max())
    assert moved > 0.01  # the head turned and the shapes moved: a check that can fail


def test_render_tells_avatars_from_talkmesh_s_own_animations(tmp_path):
    from talkmesh.output.scene import is_avatar_file

    assert is_avatar_file(make_avatar(tmp_path / "a.glb"))  # a skin and four meshes
    assert not is_avatar_file(head_avatar(tmp_path / "rig.glb"))  # one morphing mesh
    (tmp_path / "text.glb").write_text("not a glb")
    assert not is_avatar_file(tmp_path / "text.glb") and not is_avatar_file(tmp_path / "none.glb")
