"""Contact sheet: the seven emotions at full intensity on two phonemes, an open vowel /AA/ and the
closure /M/, and a short video of one line delivered three ways.

    PYTHONPATH=src python scripts/performance_sheet.py [-o docs/images/performance-sheet.png]
        [--video out/three-ways.mp4]

Each cell is the procedural animator holding the phone (0.3 s, between pauses) with the emotion
composed in (the speech in charge of the lips: the /M/ stays closed under every emotion, the /AA/
keeps its opening), the head still, no blinks or gaze, drawn from the front. ``--video`` renders
an espeak-ng sentence neutral, happy and sad side by side (with head motion), for the guide.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image

from talkmesh.audio.phonemes import Phone
from talkmesh.face.assets import load_head
from talkmesh.face.lipsync import SpeakingStyle
from talkmesh.face.performance import EMOTIONS, Performance
from talkmesh.output.labels import TextOverlay
from talkmesh.output.raster import Renderer, head_vertex_colors
from talkmesh.pipeline import animate

CELL = 128
RENDER = 2 * CELL  # drawn at twice the size, the face cropped (CROP: left, top, side) and shrunk
CROP = (62, 95, 176)
GUTTER = 4
PHONES = ("AA", "M")
STILL = SpeakingStyle(blink_rate=0.0, brow_activity=0.0, gaze_activity=0.0)
LINE = "I did not expect to see you here today."


def held(phone: str, emotion: str, head) -> np.ndarray:
    """(V, 3) the face in the middle of ``phone`` held for 0.3 s, under ``emotion`` at 1."""
    phones = [Phone("SIL", 0.0, 0.3), Phone(phone, 0.3, 0.6), Phone("SIL", 0.6, 0.9)]
    anim = animate(
        np.zeros(int(0.9 * 16_000), np.float32),
        head=head,
        phones=phones,
        model="procedural",
        style=STILL,
        performance=Performance({emotion: 1.0}),
        head_motion=0.0,
    )
    return anim.vertices[round(0.45 * anim.fps)]


def sheet(path: Path) -> None:
    head = load_head()
    cols, rows = len(EMOTIONS), len(PHONES)
    step = CELL + GUTTER
    image = np.full((rows * step + GUTTER, cols * step + GUTTER, 3), 255, np.uint8)
    full = np.empty((RENDER, RENDER, 3), np.uint8)
    colors = head_vertex_colors(head.num_vertices)
    left, top, side = CROP
    with Renderer(
        head.faces, RENDER, vertex_colors=colors, reference=head.template, camera="front"
    ) as renderer:
        for c, emotion in enumerate(EMOTIONS):
            for r, phone in enumerate(PHONES):
                renderer.draw(held(phone, emotion, head), full)
                face = Image.fromarray(full[top : top + side, left : left + side])
                cell = np.array(face.resize((CELL, CELL), Image.LANCZOS))
                TextOverlay(f"{emotion} /{phone.lower()}/", CELL, CELL, top=False).draw(cell)
                y, x = GUTTER + r * step, GUTTER + c * step
                image[y : y + CELL, x : x + CELL] = cell
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path, optimize=True)
    print(f"wrote {path} ({path.stat().st_size // 1024} kB)")


def video(path: Path) -> None:
    import tempfile

    from talkmesh.audio.loading import load_audio
    from talkmesh.audio.tts import synthesize_speech
    from talkmesh.output.render import render_side_by_side

    with tempfile.TemporaryDirectory() as tmp:
        phones = synthesize_speech(LINE, Path(tmp) / "line.wav")
        wave = load_audio(Path(tmp) / "line.wav")
    anims = [
        animate(wave, phones=phones, model="procedural", performance=Performance({e: 0.8}), seed=2)
        for e in ("neutral", "happy", "sad")
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    render_side_by_side(anims, ["neutral", "happy 0.8", "sad 0.8"], path, size=256)
    print(f"wrote {path} ({path.stat().st_size // 1024} kB)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "-o", "--output", type=Path, default=Path("docs/images/performance-sheet.png")
    )
    parser.add_argument("--video", type=Path, help="also render the line three ways here (.mp4)")
    args = parser.parse_args()
    sheet(args.output)
    if args.video:
        video(args.video)


if __name__ == "__main__":
    main()
