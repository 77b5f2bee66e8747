"""A talking .vrm played by three.js with @pixiv/three-vrm (the VRM loader web apps use), in
Chromium: the VRM 0.x and 1.0 avatars whose expression presets talkmesh drives load as VRMs with
their presets, the speech is their first clip, and the morph targets the presets bind follow it."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
from test_browser import CHROMIUM, ROOT, WAIT_MS  # noqa: F401
from test_visemes import column, vroid

from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.visemes import oculus_visemes
from talkmesh.output.avatar import animate_avatar

FPS = 30.0


@pytest.fixture(scope="module")
def player(tmp_path_factory) -> str:
    """tests/vrm_player.js bundled with three.js and three-vrm."""
    esbuild = ROOT / "node_modules" / ".bin" / "esbuild"
    if not (ROOT / "node_modules" / "@pixiv" / "three-vrm").is_dir() or not esbuild.is_file():
        pytest.fail("@pixiv/three-vrm or esbuild is missing: run `npm ci` in the repo root")
    out = tmp_path_factory.mktemp("vrm") / "player.js"
    subprocess.run(
        [str(esbuild), str(ROOT / "tests" / "vrm_player.js"), "--bundle", "--format=iife",
         f"--outfile={out}", "--log-level=error"],
        check=True,
        timeout=120,
    )  # fmt: skip
    return out.read_text()


@pytest.mark.parametrize("version", ["0.x", "1.0"])
def test_three_vrm_plays_the_driven_expressions(tmp_path, player, version):
    from playwright.sync_api import sync_playwright

    frames = 20
    weights = np.zeros((frames, 52), np.float32)
    weights[:, ARKIT_NAMES.index("jawOpen")] = np.linspace(0, 0.9, frames)  # aa opens
    weights[:, ARKIT_NAMES.index("mouthPucker")] = np.linspace(0.8, 0, frames)  # ou closes
    weights[10:14, ARKIT_NAMES.index("eyeBlinkLeft")] = 1.0  # a blink
    weights[10:14, ARKIT_NAMES.index("eyeBlinkRight")] = 1.0
    out = tmp_path / "talking.vrm"
    animate_avatar(vroid(tmp_path, version), weights, FPS, out)
    shown = frames - 1  # at the clip's end a looping action wraps to its start
    times = [k / FPS for k in range(shown)]
    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=["--no-sandbox"]
        )
        try:
            page = browser.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.set_content("<html><body></body></html>")
            page.add_script_tag(content=player)
            got = page.evaluate(
                "([bytes, times]) => window.playVrm(bytes, times)",
                [list(out.read_bytes()), times],
            )
            assert not errors, errors
        finally:
            browser.close()
    assert got["version"] == ("0" if version == "0.x" else "1")
    assert {"aa", "ih", "ou", "ee", "oh", "blink"} <= set(got["presets"])
    assert got["clips"] == ["talk", "Idle"]  # the speech first, the avatar's own clip after it
    index = next(k for k, name in enumerate(got["meshes"]) if name.startswith("Head"))
    head = np.array([f[index] for f in got["frames"]])  # (T, 6 targets): three.js's influences
    visemes = oculus_visemes(weights, FPS)[:shown]
    np.testing.assert_allclose(head[:, 0], visemes[:, column("aa")], atol=1e-5)
    np.testing.assert_allclose(head[:, 2], visemes[:, column("U")], atol=1e-5)
    np.testing.assert_allclose(
        head[:, 5], [1.0 if 10 <= k < 14 else 0.0 for k in range(shown)], atol=1e-5
    )
