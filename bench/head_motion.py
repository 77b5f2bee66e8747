"""Head motion from prosody over a minute of real speech: the range and speed of each angle, and
whether nods fall on stressed syllables more often than chance.

    python bench/head_motion.py [--amount 0.5] [--seeds 0,1,2] [--gap 0.6]

The real recordings with transcripts that Debian packages put on the machine
(:func:`talkmesh.evaluation.real_speech.builtin_clips`, 49 s) are joined with ``--gap`` seconds
of silence between them into one minute of speech, and the head pose
(:func:`talkmesh.face.head_motion.head_pose`) is made from it as ``talkmesh animate`` makes it.

Statistics per angle: the range (max - min) and standard deviation in degrees, and the mean and
95th-percentile absolute angular speed in degrees per second.

Nods: the peaks of the pitch angle, down or up, that stand ``NOD_DEG`` above its course within
0.4 s either side. Stressed syllables: the transcript forced onto each clip, each word's
phones split into syllables as Festival's CMU lexicon (festlex-cmu) syllabifies the word; the
vowel of each syllable with primary stress is its nucleus, and so for the unstressed ones. A nod
is "on" a nucleus when its peak lies within ``WINDOW_S`` of the vowel; chance is the share of
speech time (non-silent phones) within ``WINDOW_S`` of one, the rate at which nods placed at
random in speech would hit. The same is counted for the unstressed vowels; p is a one-sided
binomial test of the first seed's nods against chance (the seeds' nods share their accents, so
they are not pooled for it).
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

from talkmesh.audio.loading import SAMPLE_RATE
from talkmesh.audio.phonemes import SILENCE, Phone, transcript_words, word_phones
from talkmesh.evaluation.real_speech import builtin_clips, read_clip, truth_phones
from talkmesh.face.head_motion import NATURAL, POSE_COLUMNS, head_pose

FPS = 30.0
FESTIVAL_LEXICON = Path("/usr/share/festival/dicts/cmu/cmudict-0.4.out")
NOD_DEG = 1.0  # a nod: a peak of the pitch angle this prominent
WINDOW_S = 0.05  # a nod peak this close to a syllable's vowel is on it
VOWELS = frozenset("AA AE AH AO AW AY EH ER EY IH IY OW OY UH UW".split())


def festival_syllables(words: set[str]) -> dict[str, list[tuple[int, int]]]:
    """word -> [(phones in the syllable, stress 0/1/2), ...] from Festival's CMU lexicon (the
    first entry of each word)."""
    entry = re.compile(r'^\("([^"]+)" \S+ \((.*)\)\)$')
    syllable = re.compile(r"\(\(([^()]*)\) (\d)\)")
    out: dict[str, list[tuple[int, int]]] = {}
    with open(FESTIVAL_LEXICON, encoding="latin-1") as f:
        for line in f:
            m = entry.match(line.strip())
            if m is None or m.group(1) not in words or m.group(1) in out:
                continue
            out[m.group(1)] = [(len(p.split()), int(s)) for p, s in syllable.findall(m.group(2))]
    return out


def nuclei(phones: list[Phone], transcript: str, lexicon) -> dict[int, list[tuple[float, float]]]:
    """stress (0, 1, 2) -> (start, end) in s of the vowel of every syllable with that stress."""
    spans: dict[int, list[tuple[float, float]]] = {0: [], 1: [], 2: []}
    for word, got in zip(transcript_words(transcript), word_phones(phones, transcript)):
        syllables = lexicon.get(word)
        if not got or not syllables:
            continue
        total = sum(n for n, _ in syllables)
        edges = np.cumsum([0] + [n for n, _ in syllables]) * len(got) / total
        for (_, stress), a, b in zip(syllables, edges[:-1], edges[1:]):
            vowels = [p for p in got[int(round(a)) : int(round(b))] if p.label in VOWELS]
            if vowels:
                spans[stress].append((vowels[0].start, vowels[0].end))
    return spans


def one_minute(gap: float):
    """The joined speech (S,), its vowels by stress and its speech spans (s), its clips."""
    clips = builtin_clips()
    if not clips:
        raise SystemExit("no real recordings found: install pocketsphinx-testdata and alsa-utils")
    lexicon = festival_syllables({w for c in clips for w in transcript_words(c.transcript)})
    pieces, speech, t = [], [], 0.0
    vowels: dict[int, list[tuple[float, float]]] = {0: [], 1: [], 2: []}
    for clip in clips:
        wave = read_clip(clip)
        phones = truth_phones(clip, wave)
        for stress, spans in nuclei(phones, clip.transcript, lexicon).items():
            vowels[stress] += [(t + a, t + b) for a, b in spans]
        speech += [(t + p.start, t + p.end) for p in phones if p.label != SILENCE]
        pieces += [wave, np.zeros(int(gap * SAMPLE_RATE), np.float32)]
        t += len(wave) / SAMPLE_RATE + gap
    return np.concatenate(pieces), vowels, speech, clips


def nod_peaks(pitch_deg: np.ndarray) -> np.ndarray:
    """Frames of nod apexes: peaks of the pitch angle, down or up, standing NOD_DEG or more above
    the pitch within 0.4 s either side (their prominence, scipy.signal.find_peaks)."""
    from scipy.signal import find_peaks

    wlen = int(round(0.8 * FPS)) | 1
    down, _ = find_peaks(pitch_deg, prominence=NOD_DEG, wlen=wlen)
    up, _ = find_peaks(-pitch_deg, prominence=NOD_DEG, wlen=wlen)
    return np.sort(np.concatenate([down, up]))


def near(times: np.ndarray, spans: list[tuple[float, float]]) -> np.ndarray:
    """(N,) bool: each time within WINDOW_S of a span."""
    if not spans:
        return np.zeros(len(times), bool)
    a = np.array([s for s, _ in spans]) - WINDOW_S
    b = np.array([e for _, e in spans]) + WINDOW_S
    return ((times[:, None] >= a[None]) & (times[:, None] <= b[None])).any(1)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--amount", type=float, default=NATURAL)
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--gap", type=float, default=0.6, help="silence between clips (s)")
    args = ap.parse_args()
    wave, vowels, speech, clips = one_minute(args.gap)
    frames = int(round(len(wave) / SAMPLE_RATE * FPS))
    times = np.arange(frames) / FPS
    fine = np.arange(0, frames / FPS, 0.001)  # chance on a 1 ms grid of speech time
    in_speech = fine[near(fine, [(a + WINDOW_S, b - WINDOW_S) for a, b in speech])]
    print(
        f"{len(clips)} clips, {len(wave) / SAMPLE_RATE:.1f} s, {len(vowels[1])} vowels with "
        f"primary stress, {len(vowels[0])} unstressed, amount {args.amount:g}, {FPS:g} fps\n"
    )
    print("| seed | angle | range (deg) | std (deg) | mean speed (deg/s) | p95 speed (deg/s) |")
    print("|---|---|---|---|---|---|")
    peaks_all = []
    for seed in (int(s) for s in args.seeds.split(",")):
        pose = head_pose(wave, frames, FPS, amount=args.amount, seed=seed)
        for k, name in enumerate(POSE_COLUMNS[:3]):
            deg = np.degrees(pose[:, k].astype(np.float64))
            speed = np.abs(np.diff(deg)) * FPS
            print(
                f"| {seed} | {name} | {np.ptp(deg):.2f} | {deg.std():.2f} | "
                f"{speed.mean():.2f} | {np.percentile(speed, 95):.2f} |"
            )
        shift = np.ptp(pose[:, 3:], axis=0) * 1000
        print(
            f"| {seed} | translation range (mm) x y z | {' / '.join(f'{v:.1f}' for v in shift)} |"
        )
        peaks_all.append(times[nod_peaks(np.degrees(pose[:, 0].astype(np.float64)))])
    peaks = np.concatenate(peaks_all)
    runs = len(peaks_all)
    print(f"\n{len(peaks)} nods over {runs} seeds ({len(peaks) / runs:.0f} a run)")
    from scipy.stats import binomtest

    print(
        "\n| vowels | nods on one | chance | ratio | p, more than chance (first seed) |"
        "\n|---|---|---|---|---|"
    )
    for stress, name in ((1, "primary stress"), (0, "unstressed")):
        on = float(near(peaks, vowels[stress]).mean()) if len(peaks) else float("nan")
        chance = float(near(in_speech, vowels[stress]).mean())
        hits = int(near(peaks_all[0], vowels[stress]).sum())
        p = binomtest(hits, len(peaks_all[0]), chance, alternative="greater").pvalue
        print(f"| {name} | {on:.0%} | {chance:.0%} | {on / chance:.2f} | {p:.3f} |")


if __name__ == "__main__":
    main()
