"""The in-browser page (web/browser): the bundled model exported to ONNX and run by
onnxruntime-web (WebAssembly) in headless Chromium, no talkmesh server (a static file server
only). The mouth moves with the speech and rests in the pause after it; the page's motion equals
ONNX Runtime's in Python (the same graphs) to float tolerance; its timing is printed."""

from __future__ import annotations

import functools
import http.server
import threading
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from test_browser import CHROMIUM, chromium_args

ROOT = Path(__file__).resolve().parents[1]
CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)  # 3.0 s of speech
PAUSE_S = 1.0  # of silence after the speech
WAIT_MS = 300_000


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The page's folder (scripts/browser_page.py) served by Python's static file server."""
    import sys

    sys.path.insert(0, str(ROOT / "scripts"))
    from browser_page import build

    out = build(tmp_path_factory.mktemp("page"))
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(out))
    handler.log_message = lambda *a: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield out, f"http://127.0.0.1:{server.server_address[1]}/"
    server.shutdown()
    thread.join(timeout=10)


@pytest.fixture(scope="module")
def speech_then_pause(tmp_path_factory) -> Path:
    audio, rate = sf.read(CLIP, dtype="float32")
    path = tmp_path_factory.mktemp("audio") / "speech_pause.wav"
    sf.write(path, np.concatenate([audio, np.zeros(int(PAUSE_S * rate), np.float32)]), rate)
    return path


def run_page(url: str, audio: Path) -> dict:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=chromium_args(audio)
        )
        try:
            page = browser.new_page(viewport={"width": 480, "height": 360})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url)
            page.wait_for_function("window.page.ready || window.page.error", timeout=WAIT_MS)
            page.set_input_files("#file", str(audio))
            page.wait_for_function("window.page.done || window.page.error", timeout=WAIT_MS)
            result = page.evaluate(
                "() => ({error: window.page.error, timing: window.page.timing, "
                "motion: window.page.motion.map((m) => Array.from(m))})"
            )
        finally:
            browser.close()
    result["errors"] = errors
    return result


@pytest.mark.slow
def test_page_runs_the_model_and_the_mouth_follows_the_speech(site, speech_then_pause):
    import torch

    from talkmesh.face.arkit import WeightFitter
    from talkmesh.face.assets import load_head
    from talkmesh.models.onnx import OnnxModel

    folder, url = site
    result = run_page(url, speech_then_pause)
    assert result["error"] is None and not result["errors"], (result["error"], result["errors"])
    motion = np.array(result["motion"], np.float32)  # (T, V * 3)
    audio, rate = sf.read(speech_then_pause, dtype="float32")
    fps = 30.0
    assert len(motion) == round(len(audio) / rate * fps)
    # the same graphs in Python: the page's log-mel, interpolation and loop are right
    runtime = OnnxModel(folder / "ct.onnx")
    from talkmesh.audio.loading import load_audio

    wave = torch.from_numpy(load_audio(speech_then_pause))[None]
    want = runtime.generate(wave, torch.zeros(1, runtime.num_vertices, 3))[0].numpy()
    want = want.reshape(len(want), -1)
    scale = np.abs(want).max()
    difference = np.abs(motion - want).max() / scale
    assert difference <= 1e-4, difference
    # the mouth: jawOpen fitted to the page's vertices moves in the speech, rests in the pause
    head = load_head()
    jaw = head.blendshape_names.index("jawOpen")
    weights = WeightFitter(head.blendshapes)(motion.reshape(len(motion), -1, 3))[:, jaw]
    speech = weights[: int(2.8 * fps)]
    pause = weights[-int(0.6 * fps) :]
    assert speech.max() - speech.min() > 0.15, speech
    assert pause.max() < 0.5 * speech.max(), (pause.max(), speech.max())
    t = result["timing"]
    rtf = (t["speechMs"] + t["stepsMs"]) / 1000 / t["audioS"]
    print(
        f"\nin-browser (headless Chromium, WebAssembly, 1 thread): {t['frames']} frames of "
        f"{t['audioS']:.2f} s: speech encoder {t['speechMs']:.0f} ms, steps {t['stepsMs']:.0f} ms "
        f"({t['stepsMs'] / t['frames']:.1f} ms/frame), real-time factor {rtf:.2f}; largest "
        f"difference from Python's ONNX Runtime {difference:.1e} of the motion's scale"
    )


@pytest.mark.slow
def test_page_given_a_non_audio_file_says_so(site, tmp_path):
    _, url = site
    bad = tmp_path / "notes.wav"
    bad.write_text("not audio at all\n" * 10)
    result = run_page(url, bad)
    assert result["error"] and "\n" not in result["error"], result
    assert result["motion"] == []
