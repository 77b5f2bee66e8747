"""The browser viewer with your own character: `talkmesh serve --avatar`, and drag and drop.

A .vrm whose head, teeth and tongue carry ARKit names in three exporters' spellings (one with the
names where UniVRM writes them) is served with --avatar; a spoken audio file streams and every
mesh's jaw must move. Then an avatar with Oculus visemes only is dropped on the page and its
``viseme_aa`` must follow the speech.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from contextlib import contextmanager
from pathlib import Path

import pytest
from avatars import make_avatar
from test_browser import (  # noqa: F401
    CHROMIUM,
    ROOT,
    VIEWPORT,
    WAIT_MS,
    chromium_args,
    run_server,
    speech_wav,
)

# morph influence of every mesh's first target whose name says "jaw open" or "viseme_aa"
OPENING = """() => {
  const out = {};
  window.talkmesh.head.traverse((o) => {
    const d = o.morphTargetDictionary || {};
    const k = Object.keys(d).find((n) => /jaw.?open|viseme_aa/i.test(n));
    if (k !== undefined) out[o.userData.talkmeshName] = o.morphTargetInfluences[d[k]];
  });
  return out;
}"""


@pytest.fixture(scope="module")
def avatars(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("avatars")
    return make_avatar(tmp / "me.vrm", vrm=True), make_avatar(tmp / "rpm.glb", visemes=True)


@pytest.fixture(scope="module")
def viewer_build(tmp_path_factory) -> Path:
    """web/viewer built with esbuild into a temporary directory, so that this test checks the
    viewer's source whether or not the installed copy (talkmesh/serve/static) was rebuilt."""
    esbuild = ROOT / "node_modules" / ".bin" / "esbuild"
    if not esbuild.is_file():
        pytest.fail("esbuild is missing: run `npm ci` in the repo root")
    out = tmp_path_factory.mktemp("viewer")
    subprocess.run(
        [
            str(esbuild),
            str(ROOT / "web/viewer/main.js"),
            "--bundle",
            "--format=esm",
            "--target=es2020",
            f"--outfile={out / 'viewer.js'}",
            "--log-level=error",
        ],
        check=True,
        timeout=120,
    )
    for name in ("index.html", "style.css"):
        shutil.copy(ROOT / "web/viewer" / name, out / name)
    return out


@pytest.fixture(scope="module")
def avatar_server(avatars, viewer_build):
    yield from run_server(avatar=avatars[0], static_dir=viewer_build)


def stream_file(page, wav) -> dict[str, list[float]]:
    """Play ``wav`` through the page to the end; the opening influences seen on each mesh."""
    page.set_input_files("#file", str(wav))
    seen: dict[str, list[float]] = {}
    for _ in range(400):
        for name, value in page.evaluate(OPENING).items():
            seen.setdefault(name, []).append(value)
        if page.evaluate("window.talkmesh.state") in ("done", "error"):
            break
        page.wait_for_timeout(50)
    page.wait_for_function("window.talkmesh.state === 'done'", timeout=WAIT_MS)
    return seen


@contextmanager
def _viewer(url: str, wav):
    """The viewer at ``url`` in headless Chromium, its bundled avatar shown: (page, the page's
    errors)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=chromium_args(wav)
        )
        try:
            page = browser.new_page(viewport=VIEWPORT)
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url)
            page.wait_for_function(
                "window.talkmesh.avatar && window.talkmesh.state === 'idle'", timeout=WAIT_MS
            )
            yield page, errors
        finally:
            browser.close()


def _drop(page, data: bytes, name: str) -> None:
    """Drop a file called ``name`` holding ``data`` on the page, as a user drags one there."""
    page.evaluate(
        """([data, name]) => {
          const dt = new DataTransfer();
          dt.items.add(new File([new Uint8Array(data)], name));
          window.dispatchEvent(new DragEvent("drop", {dataTransfer: dt, cancelable: true}));
        }""",
        [list(data), name],
    )
    page.wait_for_function(f"window.talkmesh.avatar.name === {name!r}", timeout=WAIT_MS)


def test_viewer_drives_served_and_dropped_avatars(avatar_server, avatars, speech_wav):  # noqa: F811
    with _viewer(avatar_server, speech_wav) as (page, errors):
        info = page.evaluate("window.talkmesh.avatar")
        assert info["name"] == "me.vrm"
        assert sorted(info["meshes"]) == ["Head", "Teeth", "Tongue"]
        assert len(info["channels"]) == 7 and "eyeLookUpLeft" in info["missing"]
        assert info["visemes"] == []
        assert "7 of 52" in page.inner_text("#avatar")

        seen = stream_file(page, speech_wav)
        # Teeth carry their names on the glTF primitive (UniVRM's place): they move too.
        for mesh in ("Head", "Teeth", "Tongue"):
            values = seen.get(mesh, [])
            assert values and max(values) - min(values) > 0.1, (mesh, values[:20])

        # Drop an avatar with visemes only on the page: viseme_aa follows the speech.
        _drop(page, avatars[1].read_bytes(), "rpm.glb")
        info = page.evaluate("window.talkmesh.avatar")
        assert info["visemes"] == ["PP", "TH", "aa", "O", "U"]
        assert info["channels"] == ["eyeBlinkLeft", "eyeBlinkRight"]
        seen = stream_file(page, speech_wav)
        head = seen.get("Head", [])
        assert head and max(head) - min(head) > 0.1, head[:20]
        assert not errors, errors


def test_viewer_reads_names_like_python():
    """web/client/arkit_names.js and talkmesh.face.arkit_names agree on every spelling."""
    from talkmesh.face.arkit import ARKIT_NAMES
    from talkmesh.face.arkit_names import VISEME_FROM_ARKIT, VISEMES, arkit_channel, viseme_channel

    names = [
        *ARKIT_NAMES,
        "blendShape1.jawOpen",
        "JawOpen",
        "jaw_open",
        "Head|mouthSmile_L",
        "mesh:eyeBlink_R",
        "ARKit_tongueOut",
        "CC_Base_mouthRight",
        "EYE_LOOK_IN_LEFT",
        "A25_Jaw_Open",
        "Fcl_MTH_A",
        "viseme_aa",
        "viseme_O",
        "V_PP",
        "E",
        "smile",
        "",
    ]
    script = (
        f"import * as n from {json.dumps(str(ROOT / 'web/client/arkit_names.js'))};"
        "const names = JSON.parse(process.argv[1]);"
        "console.log(JSON.stringify({arkit: names.map(n.arkitChannel), visemes: names.map("
        "n.visemeChannel), order: [n.ARKIT_NAMES, n.VISEMES], map: n.VISEME_FROM_ARKIT}));"
    )
    node = shutil.which("node")
    assert node, "node is not installed (make setup)"
    run = subprocess.run(
        [node, "--input-type=module", "-e", script, json.dumps(names)],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    js = json.loads(run.stdout)
    assert js["arkit"] == [arkit_channel(n) for n in names]
    assert js["visemes"] == [viseme_channel(n) for n in names]
    assert js["order"] == [list(ARKIT_NAMES), list(VISEMES)]
    assert js["map"] == VISEME_FROM_ARKIT


def test_server_serves_the_avatar_as_it_is(avatars, tmp_path):
    from starlette.testclient import TestClient

    from talkmesh.errors import TalkmeshError
    from talkmesh.serve.server import create_app

    with TestClient(create_app(avatar=avatars[0])) as client:
        assert client.get("/health").json()["avatar"] == "me.vrm"
        response = client.get("/avatar.glb")
        assert response.status_code == 200 and response.content == avatars[0].read_bytes()
    with TestClient(create_app()) as client:
        response = client.get("/avatar.glb")
        assert response.status_code == 404 and "--avatar" in response.json()["message"]
    (tmp_path / "plain.glb").write_bytes(b"not a glb at all, just text")
    with pytest.raises(TalkmeshError, match="not a binary glTF"):
        create_app(avatar=tmp_path / "plain.glb")


PRESETS_JS = """
import * as n from %s;
import { readFileSync } from "node:fs";
const [path, frames] = JSON.parse(process.argv[1]);
const data = readFileSync(path);
const json = JSON.parse(data.subarray(20, 20 + data.readUInt32LE(12)).toString());
const meshes = json.meshes.map((m, i) => ({
  mesh: i,
  targets: (m.extras || {}).targetNames || (m.primitives[0].extras || {}).targetNames || [],
}));
const b = n.bindAvatar(meshes, n.ARKIT_NAMES, n.readVrmExpressions(json));
const values = new Float32Array(b.presetTerms.length);
const out = frames.map((w) => {
  n.presetValues(w, b.presetTerms, values);
  return b.meshes.map((m, i) => {
    const inf = new Array(meshes[i].targets.length).fill(0);
    for (const [k, p, x] of m.presets) inf[k] += values[p] * x;
    return inf.map((x) => Math.min(1, Math.max(0, x)));
  });
});
console.log(JSON.stringify({ expressions: b.expressions, vrm: b.vrm, out,
  presets: b.meshes.map((m) => m.presets.length) }));
"""


@pytest.mark.parametrize("version", ["0.x", "1.0", "1.0 one-eye", "arkit"])
def test_viewer_drives_vrm_presets_as_the_files_do(tmp_path, version):
    """web/client/arkit_names.js binds a VRM's presets and drives them from a stream's ARKit
    weights to the influences `animate --avatar` writes into the file's clip (VRM 0.x and 1.0,
    one blink or one per eye); an avatar with ARKit mouth shapes keeps them (no presets)."""
    import numpy as np
    from test_avatar import arkit_weights, clip_values
    from test_visemes import HEAD_NODE, vroid

    from talkmesh.output.avatar import animate_avatar, glb_bytes, read_glb

    if version == "arkit":
        avatar = make_avatar(tmp_path / "both.vrm", vrm=True)  # preset "a" and ARKit names
    else:
        avatar = vroid(tmp_path, version.split()[0])
    if version == "1.0 one-eye":  # Fcl_EYE_Close bound to blinkLeft and blinkRight at 0.5 and 1
        gltf, binary = read_glb(avatar)
        preset = gltf["extensions"]["VRMC_vrm"]["expressions"]["preset"]
        bind = preset.pop("blink")["morphTargetBinds"][0]
        preset["blinkLeft"] = {"morphTargetBinds": [{**bind, "weight": 0.5}]}
        preset["blinkRight"] = {"morphTargetBinds": [bind]}
        avatar.write_bytes(glb_bytes(gltf, binary))
    weights = arkit_weights()
    weights[5:9, :14] = 1.0  # blinks and eye looks at full
    weights[7:9, 7] = 0.3  # one eye half open
    out = tmp_path / "talking.vrm"
    binding = animate_avatar(avatar, weights, 30.0, out)
    node = shutil.which("node")
    assert node, "node is not installed (make setup)"
    script = PRESETS_JS % json.dumps(str(ROOT / "web/client/arkit_names.js"))
    run = subprocess.run(
        [node, "--input-type=module", "-e", script, json.dumps([str(avatar), weights.tolist()])],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    js = json.loads(run.stdout)
    assert js["expressions"] == list(binding.expressions) and js["vrm"] == binding.vrm
    if version == "arkit":
        assert js["expressions"] == [] and js["presets"] == [0, 0, 0, 0]
        return
    head = np.array([frame[0] for frame in js["out"]])  # mesh 0, the head, on node HEAD_NODE
    np.testing.assert_allclose(head, clip_values(*read_glb(out), HEAD_NODE), atol=1e-5)
    assert head[:, 0].max() - head[:, 0].min() > 0.3 and head[:, 5].max() > 0.9


MOUTH_A = """() => {
  let out = null;
  window.talkmesh.head.traverse((o) => {
    const d = o.morphTargetDictionary || {};
    if (d.Fcl_MTH_A !== undefined) out = o.morphTargetInfluences[d.Fcl_MTH_A];
  });
  return out;
}"""


def test_viewer_drives_a_dropped_vrm_s_presets(avatar_server, tmp_path, speech_wav):  # noqa: F811
    """A VRoid-like VRM 1.0 (presets only, no ARKit or viseme names) dropped on the page: the
    panel names its presets and the target its `aa` preset binds opens with the speech."""
    from test_visemes import vroid

    avatar = vroid(tmp_path, "1.0")
    with _viewer(avatar_server, speech_wav) as (page, errors):
        _drop(page, avatar.read_bytes(), "vroid.vrm")
        info = page.evaluate("window.talkmesh.avatar")
        assert info["expressions"] == ["aa", "ih", "ou", "ee", "oh", "blink"]
        assert info["vrm"] == "1.0" and info["meshes"] == ["Head"]
        assert "VRM 1.0 presets aa ih ou ee oh blink" in page.inner_text("#avatar")
        page.set_input_files("#file", str(speech_wav))
        seen = []
        for _ in range(400):
            seen.append(page.evaluate(MOUTH_A))
            if page.evaluate("window.talkmesh.state") in ("done", "error"):
                break
            page.wait_for_timeout(50)
        page.wait_for_function("window.talkmesh.state === 'done'", timeout=WAIT_MS)
        assert max(seen) - min(seen) > 0.1, seen[:20]
        assert not errors, errors
