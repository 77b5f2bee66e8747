"""espeak-ng's own voices with the synthesiser's exact phone times, from its C library.

``espeak-ng --pho`` gives exact durations only for MBROLA voices. espeak-ng's own voices (about a
hundred languages, Mandarin and Cantonese among them) report their phones through the library:
initialised with ``espeakINITIALIZE_PHONEME_EVENTS``, every phone it renders comes to the synth
callback as an ``espeakEVENT_PHONEME`` event carrying the phone's mnemonic (the symbols of
``espeak-ng -x``) and ``sample``, the index of the output sample where the phone begins (the
wave generator emits the event when it reaches the phone in its command queue, so the index is
where the audio of the phone starts). A phone lasts from its event to the next one; the last to
the end of the audio. Pauses are phones too (``_``, ``_:``, ``_|``): they are silent.

The library is called through :mod:`ctypes` (no build step, no new dependency); the structures
follow ``espeak-ng/speak_lib.h`` (API revision 12, espeak-ng 1.51). The library keeps global
state: one process renders one text at a time (a lock); each text is synthesised in a forked
child (``AUDIO_OUTPUT_SYNCHRONOUS``, see :func:`render`), so that a text always gives the same
samples and events. POSIX only (``os.fork``), as the rest of the synthetic corpus.
"""

from __future__ import annotations

import ctypes
import threading
from dataclasses import dataclass

import numpy as np

from talkmesh.audio.languages import check_espeak_not_reserved
from talkmesh.errors import TalkmeshError
from talkmesh.forked import in_child

LIBRARY = "libespeak-ng.so.1"
# speak_lib.h constants
_AUDIO_OUTPUT_SYNCHRONOUS = 2
_INITIALIZE_PHONEME_EVENTS = 0x0001
_INITIALIZE_DONT_EXIT = 0x8000  # return an error instead of exit() when its data is missing
_EVENT_LIST_TERMINATED = 0
_EVENT_PHONEME = 7
_CHARS_UTF8 = 1
_POS_CHARACTER = 1
_RATE, _PITCH = 1, 3  # espeak_PARAMETER
_EE_OK = 0
_BUFFER_MS = 200  # callback buffers; the event list of each holds 200 * 200 / 1000 + 20 events


class _EventId(ctypes.Union):
    _fields_ = [("number", ctypes.c_int), ("name", ctypes.c_char_p), ("string", ctypes.c_char * 8)]


class _Event(ctypes.Structure):
    """``espeak_EVENT``."""

    _fields_ = [
        ("type", ctypes.c_int),
        ("unique_identifier", ctypes.c_uint),
        ("text_position", ctypes.c_int),
        ("length", ctypes.c_int),
        ("audio_position", ctypes.c_int),  # ms, rounded down
        ("sample", ctypes.c_int),  # the output sample the event belongs to
        ("user_data", ctypes.c_void_p),
        ("id", _EventId),
    ]


class _VoiceInfo(ctypes.Structure):
    """``espeak_VOICE``."""

    _fields_ = [
        ("name", ctypes.c_char_p),
        ("languages", ctypes.c_char_p),  # a priority byte, then the language
        ("identifier", ctypes.c_char_p),  # its file under espeak-ng-data/voices, with +variant
        ("gender", ctypes.c_ubyte),
        ("age", ctypes.c_ubyte),
        ("variant", ctypes.c_ubyte),
        ("xx1", ctypes.c_ubyte),
        ("score", ctypes.c_int),
        ("spare", ctypes.c_void_p),
    ]


_CALLBACK = ctypes.CFUNCTYPE(
    ctypes.c_int, ctypes.POINTER(ctypes.c_short), ctypes.c_int, ctypes.POINTER(_Event)
)


@dataclass(frozen=True)
class Rendering:
    """One text spoken: ``audio`` (S,) int16 at ``sample_rate``; ``events`` (mnemonic, first
    sample) of every phone in order, pauses included."""

    audio: np.ndarray
    sample_rate: int
    events: list[tuple[str, int]]
    language: str  # the voice's language as espeak-ng names it ("cmn-latn-pinyin", "yue", ...)
    identifier: str  # the voice file, with its variant ("sit/cmn-Latn-pinyin+f2")


class _Library:
    """The loaded, initialised library and the buffers its callback fills."""

    def __init__(self, path: str):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            raise TalkmeshError(
                f"espeak-ng's library ({path}) is not installed: "
                "`sudo apt-get install libespeak-ng1` (or `make setup`)"
            ) from None
        lib.espeak_Initialize.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_char_p, ctypes.c_int]
        lib.espeak_SetVoiceByName.argtypes = [ctypes.c_char_p]
        lib.espeak_SetParameter.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int]
        lib.espeak_GetCurrentVoice.restype = ctypes.POINTER(_VoiceInfo)
        lib.espeak_Synth.argtypes = [
            ctypes.c_char_p,
            ctypes.c_size_t,
            ctypes.c_uint,
            ctypes.c_int,
            ctypes.c_uint,
            ctypes.c_uint,
            ctypes.c_void_p,
            ctypes.c_void_p,
        ]
        options = _INITIALIZE_PHONEME_EVENTS | _INITIALIZE_DONT_EXIT
        rate = lib.espeak_Initialize(_AUDIO_OUTPUT_SYNCHRONOUS, _BUFFER_MS, None, options)
        if rate <= 0:
            raise TalkmeshError(
                f"espeak-ng's library could not start (its data is missing?): {rate}"
            )
        self.lib, self.sample_rate = lib, int(rate)
        self.chunks: list[np.ndarray] = []
        self.events: list[tuple[str, int]] = []
        self.voices: dict[str, tuple[str, str, str]] = {}  # voice -> its details, looked up once
        self.callback = _CALLBACK(self._on_audio)  # kept alive as long as the library
        lib.espeak_SetSynthCallback(self.callback)
        self.lock = threading.Lock()

    def _on_audio(self, wav, count, events) -> int:
        if wav and count > 0:
            self.chunks.append(np.ctypeslib.as_array(wav, (count,)).copy())
        k = 0
        while events[k].type != _EVENT_LIST_TERMINATED:
            e = events[k]
            if e.type == _EVENT_PHONEME:
                # 8 bytes, zero-terminated unless the name fills them
                name = bytes(e.id.string).split(b"\0")[0].decode("utf-8", "replace")
                self.events.append((name, int(e.sample)))
            k += 1
        return 0


_LOADED: dict[str, _Library] = {}


def _library() -> _Library:
    if LIBRARY not in _LOADED:
        _LOADED[LIBRARY] = _Library(LIBRARY)
    return _LOADED[LIBRARY]


def voice_details(voice: str) -> tuple[str, str, str]:
    """(name, language, identifier) of an espeak-ng voice (``cmn-latn-pinyin+m3``), as the
    library resolves it; an unknown voice is an error."""
    lib = _library()
    with lib.lock:
        return _details(lib, voice)


def _details(lib: _Library, voice: str) -> tuple[str, str, str]:
    """The voice looked up in a forked child, never in this process: each voice selection leaves
    commands in the library's wave command queue that only synthesis drains, and a process that
    selected about 50 voices without speaking would hand its children a queue so full that they
    drop the phoneme events of their first buffer (their first phones silently lost). Each voice
    is looked up once per process."""
    if voice in lib.voices:
        return lib.voices[voice]

    def look():
        if lib.lib.espeak_SetVoiceByName(voice.encode()) != _EE_OK:
            return np.array([0]), np.array(["", "", ""])
        info = lib.lib.espeak_GetCurrentVoice().contents
        fields = (info.name or b"", (info.languages or b"\0")[1:], info.identifier or b"")
        return np.array([1]), np.array([f.decode(errors="replace") for f in fields])

    out = in_child(look)
    if out is None:
        raise TalkmeshError(f"espeak-ng stopped while looking up voice '{voice}'")
    found, fields = out
    if not found[0]:
        raise TalkmeshError(
            f"espeak-ng has no voice '{voice}': `espeak-ng --voices` lists them "
            "(a variant follows a '+': cmn-latn-pinyin+f2)"
        )
    lib.voices[voice] = (str(fields[0]), str(fields[1]), str(fields[2]))
    return lib.voices[voice]


def render(voice: str, text: str, pitch: int = 50, speed: int = 160) -> Rendering:
    """Speak ``text`` with espeak-ng's voice ``voice`` (a variant after '+'), pitch 0-99 and
    ``speed`` in words per minute; returns the audio and every phone's event.

    The same arguments give the same samples and events: the synthesis runs in a child forked
    from a process that has never synthesised, because the wave generator keeps state from one
    text to the next (its pitch flutter's position, the noise generator), which moves where the
    phones fall by a few milliseconds.
    """
    lib = _library()
    with lib.lock:
        name, language, identifier = _details(lib, voice)
        check_espeak_not_reserved(identifier, language, name)
        status, audio, events = _render_in_child(lib, voice, text, pitch, speed)
    if status != _EE_OK:
        raise TalkmeshError(f"espeak-ng could not speak with voice '{voice}' (error {status})")
    return Rendering(audio, lib.sample_rate, events, language, identifier)


def _render_in_child(lib: _Library, voice: str, text: str, pitch: int, speed: int):
    """(status, audio (S,) int16, events) from a forked child that synthesises and exits."""

    def speak():
        status = _synthesise(lib, voice, text, pitch, speed)
        audio = np.concatenate(lib.chunks) if lib.chunks else np.zeros(0, np.int16)
        names = np.array([m for m, _ in lib.events], dtype="<U16")
        samples = np.array([s for _, s in lib.events], dtype=np.int64)
        return np.array([status]), audio.astype(np.int16), names, samples

    out = in_child(speak)
    if out is None:
        raise TalkmeshError(f"espeak-ng stopped while speaking with voice '{voice}'")
    status, audio, names, samples = out
    return int(status[0]), audio, [(str(m), int(s)) for m, s in zip(names, samples)]


def _synthesise(lib: _Library, voice: str, text: str, pitch: int, speed: int) -> int:
    """In the child: one synthesis into ``lib.chunks`` and ``lib.events``; espeak's status."""
    ctypes.CDLL(None).srand(1)  # the noise generator (libc's rand) from its default seed
    lib.lib.espeak_SetVoiceByName(voice.encode())
    lib.lib.espeak_SetParameter(_RATE, int(speed), 0)
    lib.lib.espeak_SetParameter(_PITCH, int(pitch), 0)
    lib.chunks, lib.events = [], []
    data = text.encode("utf-8")
    return lib.lib.espeak_Synth(data, len(data) + 1, 0, _POS_CHARACTER, 0, _CHARS_UTF8, None, None)
