"""How the in-browser page's microphone windows (web/browser/model.js, ``Streamer``) move the
mouth, simulated with ONNX Runtime in Python on the exported bundled model:

    python bench/browser_stream_windows.py [--loops 2] [--onnx ct.onnx]

The speech encoder attends both ways, so the page encodes the last context + hop + look-ahead
seconds of log-mel every hop and steps the frames up to look-ahead before the newest audio. This
runs that schedule (and the whole audio at once, as a file is animated) on the test clip followed
by 1.5 s of silence, looped, and prints the jawOpen weight (fitted as ``WeightFitter`` fits it) in
speech and in pauses (frames after 0.3 s of silence). The page's log-mel is frame by frame with
the running peak; here it is the whole recording's, equal once the loudest frame has passed.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)
RATE, FPS, FEATURE_HOP, MEL_HOP = 16000, 30, 320, 160
CONFIGS = (
    (1.0, 1.5, 0.3),
    (1.0, 2.0, 0.3),
    (1.0, 3.0, 0.3),
    (1.5, 3.0, 0.3),
)  # hop, context, look-ahead


def streamed_features(model, mel: np.ndarray, n: int, frames: int, hop, context, lookahead):
    """(frames, D) features as the page computes them, one encoder window per hop."""
    feats = np.zeros((frames, int(model.step.get_inputs()[0].shape[1])), np.float32)
    done, heard = 0, 0
    while done < frames:
        heard = min(n, heard + int(hop * RATE))
        mel_end = (heard // FEATURE_HOP * FEATURE_HOP // MEL_HOP) & ~1
        mel_start = max(0, mel_end - int(np.ceil((context + hop + lookahead) * 50)) * 2)
        f = model.speech.run(None, {"mel": mel[..., mel_start:mel_end]})[0][0]
        last = int((mel_end * MEL_HOP / RATE - (lookahead if heard < n else 0)) * FPS)
        for t in range(done, min(last, frames)):
            x = np.clip(t / FPS * 50 - mel_start / 2, 0, len(f) - 1)
            i, w = int(x), x - int(x)
            feats[t] = f[i] * (1 - w) + f[min(i + 1, len(f) - 1)] * w
        done = max(done, min(last, frames))
    return feats


def jaw_of(model, feats: np.ndarray, fitter, jaw: int) -> np.ndarray:
    style = model.style(None)
    state = model.start(style)
    motion = []
    for t in range(len(feats)):
        m, state = model.step_frames(feats[t : t + 1], np.array([t]), style, state)
        motion.append(m[0])
    return fitter(np.array(motion).reshape(len(feats), -1, 3))[:, jaw]


def main() -> None:
    from talkmesh.audio.loading import load_audio
    from talkmesh.face.arkit import WeightFitter
    from talkmesh.face.assets import load_head
    from talkmesh.models.onnx import OnnxModel, export_onnx
    from talkmesh.models.release import load_model
    from talkmesh.models.whisper import log_mel

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--loops", type=int, default=2)
    parser.add_argument("--onnx", type=Path, help="an export of the bundled model (default: made)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = args.onnx
        if path is None:
            path = Path(tmp) / "ct.onnx"
            with torch.no_grad():
                export_onnx(load_model("codetalker-synth"), path)
        model = OnnxModel(path)
        head = load_head()
        fitter, jaw = WeightFitter(head.blendshapes), head.blendshape_names.index("jawOpen")
        one = load_audio(CLIP)
        audio = np.tile(np.concatenate([one, np.zeros(int(1.5 * RATE), np.float32)]), args.loops)
        n, frames = len(audio), int(len(audio) / RATE * FPS)
        mel = log_mel(torch.from_numpy(audio)[None], model.n_mels).numpy()
        step = RATE // FPS
        loud = np.array(
            [np.sqrt(np.mean(audio[t * step : (t + 1) * step] ** 2)) for t in range(frames)]
        )
        speech = loud > 0.003
        rested = np.array([not speech[max(0, t - 9) : t + 1].any() for t in range(frames)])
        rows = [("whole audio at once", jaw_of(model, model.features(audio, frames), fitter, jaw))]
        for hop, context, lookahead in CONFIGS:
            feats = streamed_features(model, mel, n, frames, hop, context, lookahead)
            rows.append((f"hop {hop:g} s, context {context:g} s, look-ahead {lookahead:g} s",
                         jaw_of(model, feats, fitter, jaw)))  # fmt: skip
    print("| features | jaw in speech: max | mean | jaw in pauses: max | mean |")
    print("|---|---:|---:|---:|---:|")
    for name, w in rows:
        print(
            f"| {name} | {w[speech].max():.2f} | {w[speech].mean():.2f} | "
            f"{w[rested].max():.2f} | {w[rested].mean():.2f} |"
        )


if __name__ == "__main__":
    main()
