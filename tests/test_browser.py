"""The browser viewer of `talkmesh serve`, end to end: real Chromium, real speech, real server.

Chromium's fake microphone plays an espeak-ng sentence into the page; the page streams it to
/ws/stream and drives the head's morph targets. Uses Debian's /usr/bin/chromium (``make setup``),
never a browser downloaded by Playwright.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import soundfile as sf
from scipy.signal import resample_poly

CHROMIUM = Path("/usr/bin/chromium")
ROOT = Path(__file__).resolve().parents[1]
STATIC = ROOT / "src" / "talkmesh" / "serve" / "static"
SCREENSHOT = ROOT / "docs" / "images" / "streaming-viewer.png"
SPEECH = "Bob bought a big blue map, and we all peeked at the moon above the bay."
CAPTURE_RATE = 48000  # Chromium's fake capture device plays 16-bit wav; 48 kHz is its native rate
VIEWPORT = {"width": 640, "height": 400}
WAIT_MS = 20_000


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server():
    """The real app under uvicorn in a thread; yields its base URL."""
    yield from run_server()


def run_server(**app_options):
    """Serve ``create_app(models=("procedural",), **app_options)`` in a thread; yields its URL."""
    import uvicorn

    from talkmesh.serve.server import create_app

    static = app_options.get("static_dir", STATIC)
    if static == STATIC and not (static / "viewer.js").is_file():
        pytest.fail(f"{static}/viewer.js is missing: run `make viewer` (or `npm run build:viewer`)")
    port = _free_port()
    app = create_app(models=("procedural",), **app_options)
    config = uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 15
    while True:
        try:
            if httpx.get(f"{url}/health", timeout=1).status_code == 200:
                break
        except httpx.HTTPError:
            pass
        if time.monotonic() > deadline or not thread.is_alive():
            server.should_exit = True
            pytest.fail("talkmesh serve did not answer /health within 15 s")
        time.sleep(0.05)
    yield url
    server.should_exit = True
    thread.join(timeout=10)


@pytest.fixture(scope="module")
def speech_wav(tmp_path_factory) -> Path:
    """About 4 s of espeak-ng speech as 48 kHz mono 16-bit wav, with a short silence after."""
    if shutil.which("espeak-ng") is None:
        pytest.fail("espeak-ng is missing: run `make setup`")
    tmp = tmp_path_factory.mktemp("browser")
    raw = tmp / "speech.wav"
    subprocess.run(["espeak-ng", "-v", "en-us", "-s", "160", "-w", str(raw), SPEECH], check=True)
    audio, rate = sf.read(raw, dtype="float32")
    audio = resample_poly(audio, CAPTURE_RATE, rate).astype(np.float32)
    audio = np.concatenate([audio, np.zeros(CAPTURE_RATE // 2, np.float32)])
    out = tmp / "speech48k.wav"
    sf.write(out, audio, CAPTURE_RATE, subtype="PCM_16")
    return out


JAW_INFLUENCES = """() => {
  const out = [];
  window.talkmesh.head.traverse((o) => {
    const d = o.morphTargetDictionary;
    if (d && d.jawOpen !== undefined) out.push(o.morphTargetInfluences[d.jawOpen]);
  });
  return out;
}"""


def chromium_args(speech_wav: Path) -> list[str]:
    """Headless Chromium with ``speech_wav`` as its microphone and WebGL without a GPU."""
    if not CHROMIUM.is_file():
        pytest.fail(f"{CHROMIUM} is missing: run `make setup` (installs Debian's chromium)")
    return [
        "--use-fake-ui-for-media-stream",
        "--use-fake-device-for-media-stream",
        f"--use-file-for-fake-audio-capture={speech_wav}",
        "--autoplay-policy=no-user-gesture-required",
        "--no-sandbox",
        "--use-angle=swiftshader",  # WebGL without a GPU
        "--enable-unsafe-swiftshader",
    ]


def test_viewer_streams_microphone_speech(server, speech_wav, tmp_path):
    from playwright.sync_api import sync_playwright

    args = chromium_args(speech_wav)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=args)
        try:
            page = browser.new_page(viewport=VIEWPORT)
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(server)
            page.wait_for_function(
                "window.talkmesh && window.talkmesh.head && window.talkmesh.state === 'idle'",
                timeout=WAIT_MS,
            )
            assert page.evaluate(JAW_INFLUENCES), "no mesh of head.glb has a jawOpen morph target"
            assert page.evaluate("document.getElementById('model').value") == "procedural"

            page.click("#mic")
            page.wait_for_function("window.talkmesh.framesReceived >= 30", timeout=WAIT_MS)
            first = page.evaluate("window.talkmesh.framesReceived")
            # The jaw must follow the speech: wait for ~2.5 s of history that opens and closes.
            page.wait_for_function(
                """() => {
                  const h = window.talkmesh.weightHistory.jawOpen;
                  return h.length >= 75 && Math.max(...h) - Math.min(...h) > 0.15;
                }""",
                timeout=WAIT_MS,
            )
            # ... and so must the three.js meshes, not only the numbers.
            seen = set()
            for _ in range(40):
                seen.update(round(v, 4) for v in page.evaluate(JAW_INFLUENCES))
                if len(seen) >= 5 and max(seen) > 0.05:
                    break
                page.wait_for_timeout(50)
            assert len(seen) >= 5 and max(seen) > 0.05, f"jawOpen influences barely moved: {seen}"

            stats = page.evaluate("window.talkmesh")
            assert stats["state"] == "streaming", stats.get("error")
            assert stats["framesReceived"] > first
            assert len(stats["lastWeights"]) == 52
            median, p95 = stats["latencyMs"]["median"], stats["latencyMs"]["p95"]
            assert median is not None and p95 is not None, stats["latencyMs"]
            assert math.isfinite(median) and math.isfinite(p95), stats["latencyMs"]
            assert 0 <= median <= p95, stats["latencyMs"]
            assert stats["fps"] > 0
            assert page.inner_text("#frames") != "0"
            # the frames' head pose turns the head: head.glb moves as a whole
            assert stats["headPose"] is not None and len(stats["headPose"]) == 6
            w = page.evaluate("window.talkmesh.head.quaternion.w")
            assert 1 - abs(w) > 1e-7, "the head never turned"

            # Mid-speech with the mouth open; written to docs/ only once everything passed.
            page.wait_for_function(f"Math.max(...({JAW_INFLUENCES})()) > 0.1", timeout=WAIT_MS)
            shot = page.screenshot()

            # Stop: the page sends {"type": "end"}; the server flushes and counts the frames.
            page.click("#stop")
            page.wait_for_function("window.talkmesh.state === 'done'", timeout=WAIT_MS)
            final = page.evaluate("window.talkmesh")
            assert final["endFrames"] == final["framesReceived"]

            # The same sentence as an audio file: played, streamed to its end, then flushed.
            page.set_input_files("#file", str(speech_wav))
            page.wait_for_function(
                "['connecting', 'streaming'].includes(window.talkmesh.state)", timeout=WAIT_MS
            )
            page.wait_for_function("window.talkmesh.state === 'done'", timeout=WAIT_MS)
            final = page.evaluate("window.talkmesh")
            expected = sf.info(speech_wav).duration * final["streamFps"]
            assert final["endFrames"] == final["framesReceived"]
            assert abs(final["endFrames"] - expected) <= 4, (final["endFrames"], expected)
            jaw = final["weightHistory"]["jawOpen"]
            assert max(jaw) - min(jaw) > 0.15, "the jaw did not follow the audio file"
            assert not errors, errors
        finally:
            browser.close()
    # the docs' copy is refreshed on request (TALKMESH_DOCS=1) or when missing; every run keeps one
    (tmp_path / "viewer.png").write_bytes(shot)
    if os.environ.get("TALKMESH_DOCS") == "1" or not SCREENSHOT.exists():
        SCREENSHOT.write_bytes(shot)


HEAD_LOOK = """() => {
  const out = { colored: 0, meshes: 0 };
  window.talkmesh.head.traverse((o) => {
    if (!o.isMesh) return;
    out.meshes += 1;
    if (o.geometry.attributes.color && o.material.vertexColors) out.colored += 1;
  });
  return out;
}"""


def test_viewer_shows_download_progress_and_the_heads_irises(server, speech_wav):
    """While head.glb downloads the page shows a progress bar (bytes of the total); the head
    comes with the video renderer's vertex colours, irises and pupils included."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=chromium_args(speech_wav)
        )
        try:
            page = browser.new_page(viewport=VIEWPORT)
            seen: list[str] = []
            page.expose_function("noteProgress", lambda text: seen.append(text))
            page.add_init_script(
                """new MutationObserver(() => {
                     const t = document.getElementById('progress-text');
                     if (t) window.noteProgress(t.textContent);
                   }).observe(document, { subtree: true, childList: true, characterData: true });"""
            )
            page.goto(server)
            page.wait_for_function(
                "window.talkmesh && window.talkmesh.head && window.talkmesh.state === 'idle'",
                timeout=WAIT_MS,
            )
            state = page.evaluate("window.talkmesh")
            assert state["loadSteps"] >= 2 and state["loading"] is None, state
            assert page.is_hidden("#loading")
            assert any(re.search(r"loading head\.glb: [\d.]+ of [\d.]+ MB", t) for t in seen), seen
            look = page.evaluate(HEAD_LOOK)
            assert look["meshes"] >= 1 and look["colored"] == look["meshes"], look
        finally:
            browser.close()
