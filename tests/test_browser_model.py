"""The in-browser page (web/browser): the bundled model exported to ONNX and run by
onnxruntime-web (WebGPU where present, else WebAssembly: the page says which) in headless
Chromium, no talkmesh server (a static file server only). From a file, the page's motion equals
ONNX Runtime's in Python (the same graphs) to float tolerance and its ARKit weights equal
WeightFitter's; from Chromium's fake microphone (speech then a pause, looped), the mouth moves
with the speech and rests in the pauses; a dropped-in avatar's jaw follows; a non-audio file, a
non-avatar file and a refused microphone are one line each. Timing is printed."""

from __future__ import annotations

import functools
import http.server
import threading
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from scipy.signal import resample_poly
from test_browser import CAPTURE_RATE, CHROMIUM, chromium_args

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


@pytest.fixture(scope="module")
def microphone_wav(tmp_path_factory) -> Path:
    """The speech then 1.5 s of silence as Chromium's fake microphone plays it (48 kHz 16-bit;
    it loops the file)."""
    audio, rate = sf.read(CLIP, dtype="float32")
    audio = resample_poly(audio, CAPTURE_RATE, rate).astype(np.float32)
    path = tmp_path_factory.mktemp("mic") / "speech_pause_48k.wav"
    silence = np.zeros(int(1.5 * CAPTURE_RATE), np.float32)
    sf.write(path, np.concatenate([audio, silence]), CAPTURE_RATE, subtype="PCM_16")
    return path


def open_page(p, url: str, args: list[str]):
    browser = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=args)
    page = browser.new_page(viewport={"width": 480, "height": 360})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_function("window.page.ready || window.page.error", timeout=WAIT_MS)
    return browser, page, errors


DROP = """async ([name, bytes]) => {
  const data = new DataTransfer();
  data.items.add(new File([new Uint8Array(bytes)], name));
  window.dispatchEvent(new DragEvent("drop", { dataTransfer: data, cancelable: true }));
}"""


def run_page(url: str, audio: Path, avatar: Path | None = None, drop: Path | None = None) -> dict:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser, page, errors = open_page(p, url, chromium_args(audio))
        try:
            if drop is not None:  # dragged onto the page
                page.evaluate(DROP, [drop.name, list(drop.read_bytes())])
                page.wait_for_function("window.page.avatar || window.page.error", timeout=WAIT_MS)
                dropped = page.evaluate("window.page.avatar")
            if avatar is not None:
                page.set_input_files("#avatar", str(avatar))
                page.wait_for_function("window.page.avatar || window.page.error", timeout=WAIT_MS)
            page.set_input_files("#file", str(audio))
            page.wait_for_function("window.page.done || window.page.error", timeout=WAIT_MS)
            result = page.evaluate(
                "() => ({error: window.page.error, timing: window.page.timing, "
                "backend: window.page.backend, note: window.page.backendNote, "
                "avatar: window.page.avatar, opening: window.page.opening, "
                "status: document.getElementById('status').textContent, "
                "weights: window.page.weights.map((w) => Array.from(w)), "
                "motion: window.page.motion.map((m) => Array.from(m))})"
            )
        finally:
            browser.close()
    result["errors"] = errors
    if drop is not None:
        result["dropped"] = dropped
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
    template = load_head().template  # the page drives head.glb: its style has that head's term
    want = runtime.generate(wave, torch.from_numpy(template)[None])[0].numpy() - template
    want = want.reshape(len(want), -1)
    scale = np.abs(want).max()
    difference = np.abs(motion - want).max() / scale
    assert difference <= 1e-4, difference
    # the mouth: jawOpen fitted to the page's vertices moves in the speech, rests in the pause
    head = load_head()
    jaw = head.blendshape_names.index("jawOpen")
    fitted = WeightFitter(head.blendshapes)(motion.reshape(len(motion), -1, 3))
    page_weights = np.array(result["weights"], np.float32)  # fitted in the page (fit.js)
    assert page_weights.shape == fitted.shape
    assert np.abs(page_weights - fitted).max() <= 1e-4, np.abs(page_weights - fitted).max()
    weights = fitted[:, jaw]
    speech = weights[: int(2.8 * fps)]
    pause = weights[-int(0.6 * fps) :]
    assert speech.max() - speech.min() > 0.15, speech
    assert pause.max() < 0.5 * speech.max(), (pause.max(), speech.max())
    t = result["timing"]
    rtf = (t["speechMs"] + t["stepsMs"]) / 1000 / t["audioS"]
    assert result["backend"] in ("webgpu", "wasm"), result["backend"]
    print(
        f"\nin-browser (headless Chromium, {result['backend']}: {result['note']}): "
        f"{t['frames']} frames of "
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
    assert result["error"] == result["status"] and "\n" not in result["error"], result
    assert result["error"].startswith("notes.wav: not audio this browser can decode"), result
    assert result["motion"] == []


SILENT_RMS = 0.003  # a frame's audio below this is silence (the pauses are digital zeros)


@pytest.mark.slow
def test_page_streams_the_microphone_and_the_mouth_rests_in_pauses(site, microphone_wav):
    """Two loops of Chromium's fake microphone (3.0 s of speech, 1.5 s of silence) through the
    model as they arrive: every frame in order, the jaw opens and closes in the speech and rests
    in the pauses (frames after 0.3 s of silence); latency and real-time factor printed."""
    from playwright.sync_api import sync_playwright

    from talkmesh.face.arkit import ARKIT_NAMES

    _, url = site
    with sync_playwright() as p:
        browser, page, errors = open_page(p, url, chromium_args(microphone_wav))
        try:
            page.click("#mic")
            page.wait_for_function(
                "window.page.error || (window.page.mic && window.page.mic.frames.length >= 280)",
                timeout=WAIT_MS,
            )
            page.evaluate("document.getElementById('stop').click()")
            mic = page.evaluate("window.page.mic")
            state = page.evaluate(
                "({error: window.page.error, backend: window.page.backend, "
                "note: window.page.backendNote})"
            )
        finally:
            browser.close()
    assert state["error"] is None and not errors, (state, errors)
    assert mic["running"] is False
    frames = mic["frames"]
    assert [f["t"] for f in frames] == list(range(len(frames)))
    jaw = np.array([f["weights"][ARKIT_NAMES.index("jawOpen")] for f in frames])
    silent = np.array([f["rms"] < SILENT_RMS for f in frames])
    speech = ~silent
    rested = np.array([silent[max(0, t - 9) : t + 1].all() for t in range(len(frames))])
    assert speech.sum() > 120 and rested.sum() > 40, (speech.sum(), rested.sum())
    assert jaw[speech].max() - jaw[speech].min() > 0.12, jaw[speech]
    assert jaw[rested].max() < 0.5 * jaw[speech].max(), (jaw[rested].max(), jaw[speech].max())
    assert jaw[rested].mean() < 0.5 * jaw[speech].mean(), (jaw[rested], jaw[speech].mean())
    latency = np.array([f["latency"] for f in frames])
    o = mic["options"]
    print(
        f"\nin-browser microphone (headless Chromium, {state['backend']}: {state['note']}; hop "
        f"{o['hop']} s, context {o['context']} s, look-ahead {o['lookahead']} s): "
        f"{len(frames)} frames of {mic['audioS']:.2f} s of audio in {mic['wallS']:.2f} s; "
        f"computing {mic['busyMs'] / 1000:.2f} s (encoder {mic['encoderMs'] / 1000:.2f} s), "
        f"real-time factor {mic['busyMs'] / 1000 / mic['audioS']:.2f}; latency from a frame's "
        f"audio to its motion: median {np.median(latency):.0f} ms, p95 "
        f"{np.percentile(latency, 95):.0f} ms, max {latency.max():.0f} ms; jaw in speech "
        f"{jaw[speech].mean():.3f} mean / {jaw[speech].max():.3f} max, in pauses "
        f"{jaw[rested].mean():.3f} / {jaw[rested].max():.3f}"
    )


@pytest.mark.slow
def test_page_drives_a_dropped_in_avatar(site, speech_then_pause, tmp_path):
    """A .vrm dragged onto the page (its teeth's target names where UniVRM writes them), then a
    .glb with ARKit targets in three exporters' spellings (tests/avatars.py) chosen in the page:
    the speech file drives every mesh's jaw through the weights fitted in the page."""
    from avatars import make_avatar

    _, url = site
    vrm = make_avatar(tmp_path / "me.vrm", vrm=True)
    avatar = make_avatar(tmp_path / "me.glb")
    result = run_page(url, speech_then_pause, avatar=avatar, drop=vrm)
    assert result["error"] is None and not result["errors"], (result["error"], result["errors"])
    assert result["dropped"]["name"] == "me.vrm", result["dropped"]
    assert set(result["dropped"]["meshes"]) == {"Head", "Teeth", "Tongue"}, result["dropped"]
    assert set(result["avatar"]["meshes"]) == {"Head", "Teeth", "Tongue"}, result["avatar"]
    assert "jawOpen" in result["avatar"]["channels"]
    shown = result["opening"]
    assert len(shown) > 60, len(shown)  # frames shown while the audio played
    for mesh in ("Head", "Teeth", "Tongue"):
        seen = [frame[mesh] for frame in shown]
        assert max(seen) - min(seen) > 0.1, (mesh, seen)


@pytest.mark.slow
def test_page_refuses_a_non_avatar_file_and_a_refused_microphone_in_one_line(
    site, microphone_wav, tmp_path
):
    from playwright.sync_api import sync_playwright

    _, url = site
    args = [a for a in chromium_args(microphone_wav) if a != "--use-fake-ui-for-media-stream"]
    text = tmp_path / "face.glb"
    text.write_text("not a glb\n")
    with sync_playwright() as p:
        browser, page, errors = open_page(p, url, [*args, "--deny-permission-prompts"])
        try:
            lines = []
            page.set_input_files("#avatar", str(text))
            page.wait_for_function("window.page.error", timeout=WAIT_MS)
            lines.append(page.evaluate("[window.page.error, window.page.avatar]"))
            page.evaluate("window.page.error = null")
            page.click("#mic")
            page.wait_for_function("window.page.error", timeout=WAIT_MS)
            lines.append(page.evaluate("[window.page.error, window.page.mic]"))
            status = page.inner_text("#status")
        finally:
            browser.close()
    (avatar_error, avatar), (mic_error, mic) = lines
    assert avatar_error.startswith("face.glb: not a glTF binary") and avatar is None, lines
    assert mic_error.startswith("the microphone was refused") and mic is None, lines
    assert status == mic_error and all("\n" not in e for e, _ in lines) and not errors


@pytest.mark.slow
@pytest.mark.parametrize("version", ["0.x", "1.0"])
def test_page_drives_a_vroid_model_through_its_vrm_presets(
    site, speech_then_pause, tmp_path, version
):
    """A VRoid-like .vrm (no ARKit or viseme target names; tests/test_visemes.py's ``vroid``):
    the page drives its expression presets through the targets its extension binds, as the
    viewer does, and the head's target that the aa preset binds opens and closes with the speech."""
    from test_visemes import vroid

    _, url = site
    result = run_page(url, speech_then_pause, avatar=vroid(tmp_path, version))
    assert result["error"] is None and not result["errors"], (result["error"], result["errors"])
    assert {"aa", "ih", "ou", "ee", "oh"} <= set(result["avatar"]["presets"]), result["avatar"]
    seen = [next(iter(frame.values())) for frame in result["opening"]]
    assert len(seen) > 60 and max(seen) - min(seen) > 0.1, seen
