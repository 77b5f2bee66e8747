"""Frame by frame through the pauses of one real clip: where a mouth that should rest opens.

    python bench/pause_trace.py --clip librivox-0890 --condition reverb \
        [--methods codetalker-synth-raw,runs/x/model.safetensors-raw]

For each pause of the clip's timing truth (``MIN_PAUSE_S`` or longer) prints the loudness (dB,
as ``loudness_r`` reads it) and each method's lip opening above rest (mm) at every frame of the
pause and the frame after it. ``pause_mm`` is the mean over the frames more than
``PAUSE_MARGIN_S`` inside a pause: this shows which frames make it. Methods are those of
``bench/real_speech.py``.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_speech import FPS, _animate_condition  # noqa: E402

from talkmesh.audio.loading import load_audio  # noqa: E402
from talkmesh.audio.phonemes import SILENCE  # noqa: E402
from talkmesh.errors import TalkmeshError  # noqa: E402
from talkmesh.evaluation.real_speech import (  # noqa: E402
    CONDITIONS,
    MIN_PAUSE_S,
    NOISE_FILE,
    builtin_clips,
    degrade,
    log_loudness,
    read_clip,
    truth_phones,
)
from talkmesh.face.assets import lip_opening, load_head  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--clip", required=True, help="a real clip's name (librivox-0890, ...)")
    ap.add_argument("--condition", default="clean", choices=CONDITIONS)
    ap.add_argument("--methods", default="procedural,codetalker-synth-raw")
    args = ap.parse_args()
    clips = {c.name: c for c in builtin_clips()}
    if args.clip not in clips:
        raise SystemExit(f"no real clip {args.clip!r}: use one of {', '.join(clips)}")
    wave = read_clip(clips[args.clip])
    phones = truth_phones(clips[args.clip], wave)
    noise = load_audio(NOISE_FILE) if NOISE_FILE.is_file() else None
    heard = degrade(wave, args.condition, noise, seed=0)
    head = load_head()
    rest = float(lip_opening(head.template[None], head.regions)[0]) * 1000
    methods = [m for m in args.methods.split(",") if m]
    try:
        animated = _animate_condition(heard, methods, head)
    except TalkmeshError as e:
        raise SystemExit(str(e)) from None
    n = min(len(v) for v in animated.values())
    loud = log_loudness(heard, FPS, n)
    opening = {m: lip_opening(v[:n], head.regions) * 1000 - rest for m, v in animated.items()}
    width = max(len(m) for m in ["loudness (dB)", *methods])
    for p in phones:
        if p.label != SILENCE or p.end - p.start < MIN_PAUSE_S:
            continue
        lo, hi = int(p.start * FPS), min(n, int(math.ceil(p.end * FPS)) + 1)
        print(f"\npause {p.start:.2f}-{p.end:.2f} s, frames {lo}-{hi - 1}")
        print(f"{'loudness (dB)':>{width}} " + " ".join(f"{v:5.0f}" for v in loud[lo:hi]))
        for m in methods:
            print(f"{m:>{width}} " + " ".join(f"{v:5.1f}" for v in opening[m][lo:hi]))


if __name__ == "__main__":
    main()
