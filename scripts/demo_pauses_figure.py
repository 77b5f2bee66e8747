"""Before/after strip of the demo recording's pauses: docs/images/demo-pauses.png.

    python scripts/demo_pauses_figure.py [--audio examples/librivox-sense-and-sensibility.flac]

Rows: the bundled model alone (``--no-pause-gate --procedural-mix 0``) and what ``talkmesh
animate`` outputs by default, on the recording as it is and in a reverberant room (RT60 0.5 s,
as the real-speech benchmark makes it). Columns: the middle of every pause of 250 ms or more that
the phone recogniser finds in the recording, and one speech frame; each cell is labelled with its
time and the lip opening above rest.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from talkmesh.audio.loading import SAMPLE_RATE, load_audio
from talkmesh.audio.phonemes import SILENCE, recognize_phones
from talkmesh.evaluation.real_speech import add_reverb
from talkmesh.face.assets import lip_opening, load_head
from talkmesh.face.corrections import Corrections, correct_mouth
from talkmesh.face.pauses import MIN_PAUSE_S
from talkmesh.output.render import _renderer_for
from talkmesh.pipeline import animate

ROOT = Path(__file__).resolve().parents[1]
FPS = 30.0
CELL = 320
CROP = (70, 150, 250, 262)  # the lower face of a CELL-pixel render


def pick_frames(phones) -> list[int]:
    """Middles of the long pauses, with the middle of the longest speech stretch between."""
    pauses = [p for p in phones if p.label == SILENCE and p.end - p.start >= MIN_PAUSE_S]
    times = [0.5 * (p.start + p.end) for p in pauses]
    speech = [p for p in phones if p.label != SILENCE]
    if speech:
        longest = max(speech, key=lambda p: p.end - p.start)
        times.append(0.5 * (longest.start + longest.end))
    return sorted(int(t * FPS) for t in times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--audio", default=ROOT / "examples" / "librivox-sense-and-sensibility.flac")
    ap.add_argument("--out", default=ROOT / "docs" / "images" / "demo-pauses.png")
    args = ap.parse_args()
    from PIL import Image, ImageDraw

    clean = load_audio(args.audio)
    head = load_head()
    frames = pick_frames(recognize_phones(clean, SAMPLE_RATE))
    rows = []
    for room, wave in (("", clean), ("reverb: ", add_reverb(clean))):
        phones = recognize_phones(wave, SAMPLE_RATE)
        bare = animate(
            wave,
            head=head,
            fps=FPS,
            pause_gate=False,
            procedural_mix=0.0,
            loudness_gain=0.0,
            bilabial_closure=False,
        )
        fixed = correct_mouth(bare.vertices.copy(), head, phones, wave, FPS, Corrections())
        rows += [(room + "model alone", bare.vertices), (room + "animate", fixed)]
    rest = float(lip_opening(head.template[None], head.regions)[0])
    w, h = CROP[2] - CROP[0], CROP[3] - CROP[1]
    sheet = Image.new("RGB", (w * len(frames), h * len(rows)), "white")
    image = np.empty((CELL, CELL, 3), np.uint8)
    with _renderer_for(bare, CELL) as renderer:
        for r, (label, vertices) in enumerate(rows):
            opening = (lip_opening(vertices, head.regions) - rest) * 1000
            for c, t in enumerate(frames):
                cell = Image.fromarray(renderer.draw(vertices[t], image).copy()).crop(CROP)
                draw = ImageDraw.Draw(cell)
                draw.text((3, 2), f"{label}\n{t / FPS:.2f} s {opening[t]:+.1f} mm", fill="black")
                sheet.paste(cell, (c * w, r * h))
    sheet.save(args.out)
    print(f"wrote {args.out}: frames at {', '.join(f'{t / FPS:.2f}' for t in frames)} s")


if __name__ == "__main__":
    main()
