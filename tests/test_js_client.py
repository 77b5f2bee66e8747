"""web/client (talkmesh-client) in headless Chromium against a running ``talkmesh serve``: its
example page plays a speech file on the server's head and the mouth follows the speech, each
frame shown once the audio has reached its time."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from test_browser import CHROMIUM, chromium_args, run_server, speech_wav  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]
CLIENT = ROOT / "web" / "client"
ESBUILD = ROOT / "node_modules" / ".bin" / "esbuild"
CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)  # 3.0 s of speech
WAIT_MS = 30_000


@pytest.fixture(scope="module")
def example(tmp_path_factory) -> Path:
    """The example page bundled by esbuild (three.js from node_modules) into a static folder."""
    if not ESBUILD.is_file():
        pytest.fail(f"{ESBUILD} is missing: run `make setup` (npm ci)")
    out = tmp_path_factory.mktemp("client")
    subprocess.run(
        [str(ESBUILD), str(CLIENT / "example" / "main.js"), "--bundle", "--format=esm",
         "--target=es2020", f"--outfile={out / 'example.js'}", "--log-level=warning"],
        check=True,
    )  # fmt: skip
    shutil.copy(CLIENT / "example" / "index.html", out)
    return out


def test_client_plays_speech_on_the_head_in_step_with_the_audio(example):
    from playwright.sync_api import sync_playwright

    server = run_server(static_dir=example)
    url = next(server)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(
                executable_path=str(CHROMIUM), headless=True, args=chromium_args(CLIP)
            )
            try:
                page = browser.new_page(viewport={"width": 480, "height": 360})
                errors: list[str] = []
                page.on("pageerror", lambda e: errors.append(str(e)))
                page.goto(url)
                page.wait_for_function("window.example && window.example.ready", timeout=WAIT_MS)
                page.set_input_files("#file", str(CLIP))
                page.wait_for_function(
                    "window.example.error || (window.example.client.state === 'done' && "
                    "window.example.client.frames.length === 0)",
                    timeout=WAIT_MS,
                )
                result = page.evaluate(
                    """() => ({error: window.example.error, jaw: window.example.jaw,
                      received: window.example.client.received,
                      shown: window.example.client.shown, fps: window.example.client.fps})"""
                )
            finally:
                browser.close()
    finally:
        next(server, None)
    assert result["error"] is None and not errors, (result["error"], errors)
    expected = sf.info(CLIP).duration * result["fps"]
    assert abs(result["received"] - expected) <= 2, (result["received"], expected)
    shown = result["shown"]
    times = [t for t, _ in shown]  # the display's rate: frames between two are skipped
    assert times[-1] == pytest.approx((result["received"] - 1) / result["fps"])  # to the end
    assert times == sorted(set(times))  # in order, each once
    assert all(t <= audio for t, audio in shown)  # never ahead of the audio
    jaw = result["jaw"]
    assert max(jaw) - min(jaw) > 0.15, "the head's jaw did not follow the speech"


def open_example(p, args):
    browser = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=args)
    page = browser.new_page(viewport={"width": 480, "height": 360})
    return browser, page


def test_client_streams_the_microphone_live(example, speech_wav):  # noqa: F811
    """Chromium's fake microphone (an espeak-ng sentence, looped) streamed by
    streamMicrophone(): frames come back while it speaks, the jaw follows, and stopping sends
    the end message so the server counts every frame it sent."""
    from playwright.sync_api import sync_playwright

    server = run_server(static_dir=example)
    url = next(server)
    try:
        with sync_playwright() as p:
            browser, page = open_example(p, chromium_args(speech_wav))
            try:
                errors: list[str] = []
                page.on("pageerror", lambda e: errors.append(str(e)))
                page.goto(url)
                page.wait_for_function("window.example && window.example.ready", timeout=WAIT_MS)
                page.click("#mic")
                page.wait_for_function(
                    "window.example.error || (window.example.client.received >= 120 && "
                    "window.example.jaw.length >= 60)",
                    timeout=WAIT_MS,
                )
                page.evaluate("window.example.client.stopMicrophone()")
                page.wait_for_function(
                    "window.example.error || window.example.client.state === 'done'",
                    timeout=WAIT_MS,
                )
                result = page.evaluate(
                    """() => ({error: window.example.error, jaw: window.example.jaw,
                      received: window.example.client.received,
                      latencies: window.example.client.latencies,
                      status: document.getElementById('status').textContent})"""
                )
            finally:
                browser.close()
    finally:
        next(server, None)
    assert result["error"] is None and not errors, (result["error"], errors)
    assert result["status"] == f"{result['received']} frames"  # the server's count at the end
    jaw = result["jaw"]
    assert max(jaw) - min(jaw) > 0.15, "the head's jaw did not follow the microphone"
    latencies = np.array(result["latencies"])
    assert len(latencies) >= 100 and (latencies >= 0).all(), latencies
    print(
        f"\nclient microphone (procedural, headless Chromium): {result['received']} frames, "
        f"latency median {np.median(latencies):.0f} ms, p95 {np.percentile(latencies, 95):.0f} ms"
    )


def test_client_with_the_microphone_refused_says_so_in_one_line(example, speech_wav):  # noqa: F811
    from playwright.sync_api import sync_playwright

    server = run_server(static_dir=example)
    url = next(server)
    args = [a for a in chromium_args(speech_wav) if a != "--use-fake-ui-for-media-stream"]
    try:
        with sync_playwright() as p:
            browser, page = open_example(p, [*args, "--deny-permission-prompts"])
            try:
                page.goto(url)
                page.wait_for_function("window.example && window.example.ready", timeout=WAIT_MS)
                page.click("#mic")
                page.wait_for_function("window.example.error", timeout=WAIT_MS)
                error = page.evaluate("window.example.error")
                shown = page.inner_text("#status")
            finally:
                browser.close()
    finally:
        next(server, None)
    assert error == shown and "\n" not in error, error
    assert error.startswith("the microphone was refused"), error
