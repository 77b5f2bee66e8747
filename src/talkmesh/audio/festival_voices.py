"""Festival's voices of languages other than English, for the multilingual corpus.

Debian packages Festival voices for Spanish, Italian, Russian, Finnish, Catalan, Hindi, Marathi
and Telugu. Like the English ones (:func:`talkmesh.audio.voices.synthesize_festival`), each gives
the times of the phones it rendered: the utterance's ``Segment`` relation holds each phone's end.

Each voice writes its phones in its own phone set; the tables below map every phone of every
set (as ``(PhoneSet.description)`` lists it for the installed voice) onto the procedural
animator's labels (ARPABET, plus ``UY`` and ``OE`` for the rounded front vowels /y/ and /ø/),
from what the symbol stands for in that voice. A phone missing from its table is an error, never
a guess. Symbols that read like English ones often are not: ``th`` is Spanish /θ/ but the Indic
voices' dental stop /t̪/ (त), ``x`` is Spanish /x/ but a phone no Indic lexicon produces, ``r``
is a tap or trill (the tongue tip: ``D``, as :func:`talkmesh.audio.languages.sampa_label` reads
SAMPA ``r``), ``y`` is Russian ы /ɨ/ (unrounded) but Finnish /y/ (rounded).

The diphone voices of Spanish, Italian, Finnish and Catalan read ISO-8859-1 text
(:data:`ENCODINGS`); the others read UTF-8.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from talkmesh.audio.phonemes import SILENCE
from talkmesh.errors import TalkmeshError

FESTIVAL_VOICES_DIR = Path("/usr/share/festival/voices")


@dataclass(frozen=True)
class FestivalVoice:
    language: str  # a code of talkmesh.audio.languages.LANGUAGES
    speaker: (
        str  # the corpus's voice "fest-SPEAKER": one id per person (NSK speaks three languages)
    )
    function: str  # Festival's voice function
    folder: str  # where Debian installs it, under FESTIVAL_VOICES_DIR
    package: str  # the Debian package
    phoneset: str  # a key of PHONE_TABLES
    description: str
    stretches: bool = True  # honours Duration_Stretch (unit selection and HTS voices do not)


# fmt: off
FESTIVAL_VOICES: tuple[FestivalVoice, ...] = (
    FestivalVoice("es", "el", "voice_el_diphone", "spanish/el_diphone", "festvox-ellpc11k",
                  "spanish", "Castilian Spanish male (Festival el diphone)"),
    FestivalVoice("it", "lp", "voice_lp_diphone", "italian/lp_diphone", "festvox-italp16k",
                  "italian", "Italian female (Festival lp diphone)"),
    FestivalVoice("it", "pc", "voice_pc_diphone", "italian/pc_diphone", "festvox-itapc16k",
                  "italian", "Italian male (Festival pc diphone)"),
    FestivalVoice("ru", "msu", "voice_msu_ru_nsh_clunits", "russian/msu_ru_nsh_clunits",
                  "festvox-ru", "msu_ru", "Russian male (Festival msu unit selection)", False),
    FestivalVoice("fi", "lj", "voice_suo_fi_lj_diphone", "finnish/suo_fi_lj_diphone",
                  "festvox-suopuhe-lj", "finnish", "Finnish female (Festival Suopuhe lj diphone)"),
    FestivalVoice("fi", "mv", "voice_hy_fi_mv_diphone", "finnish/hy_fi_mv_diphone",
                  "festvox-suopuhe-mv", "finnish", "Finnish male (Festival Suopuhe mv diphone)"),
    FestivalVoice("ca", "ona", "voice_upc_ca_ona_hts", "catalan/upc_ca_ona_hts",
                  "festvox-ca-ona-hts", "catalan", "Catalan female (Festival ona HTS)", False),
    FestivalVoice("hi", "nsk", "voice_hindi_NSK_diphone", "hindi/hindi_NSK_diphone",
                  "festvox-hi-nsk", "indic", "Hindi male (Festival NSK diphone)"),
    FestivalVoice("mr", "nsk", "voice_marathi_NSK_diphone", "marathi/marathi_NSK_diphone",
                  "festvox-mr-nsk", "indic", "Marathi male (Festival NSK diphone)"),
    FestivalVoice("te", "nsk", "voice_telugu_NSK_diphone", "telugu/telugu_NSK_diphone",
                  "festvox-te-nsk", "indic", "Telugu male (Festival NSK diphone)"),
)

# The phone sets (each voice's (PhoneSet.description)) -> the animator's labels.
_SPANISH = {  # el_diphone; digits: stress, i0 u0: the glides of diphthongs
    "#": SILENCE, "a": "AA", "a1": "AA", "e": "EH", "e1": "EH", "i": "IY", "i1": "IY",
    "o": "OW", "o1": "OW", "u": "UW", "u1": "UW", "i0": "Y", "u0": "W",
    "p": "P", "b": "B", "m": "M", "f": "F", "t": "T", "d": "D", "th": "TH", "s": "S", "n": "N",
    "l": "L", "r": "D", "rr": "D", "ch": "CH", "ny": "N", "ll": "L", "k": "K", "g": "G", "x": "HH",
}
_ITALIAN = {  # lp and pc diphone; E O: open mid vowels, J ɲ, L ʎ, nf ɱ (lip to teeth), ng ŋ
    "#": SILENCE, "a": "AA", "a1": "AA", "e": "EH", "e1": "EH", "E": "EH", "E1": "EH",
    "i": "IY", "i1": "IY", "o": "OW", "o1": "OW", "O": "AO", "O1": "AO", "u": "UW", "u1": "UW",
    "j": "Y", "w": "W", "p": "P", "b": "B", "m": "M", "f": "F", "v": "V", "nf": "V",
    "t": "T", "d": "D", "s": "S", "z": "Z", "ts": "S", "dz": "Z", "n": "N", "l": "L", "r": "D",
    "S": "SH", "Z": "ZH", "tS": "CH", "dZ": "JH", "J": "N", "L": "L", "k": "K", "g": "G",
    "ng": "NG",
}
_RUSSIAN = {  # msu_ru: doubled consonants are palatalised; doubled vowels stressed;
    # ae ay: reduced unrounded, ur: reduced rounded; y yy: ы /ɨ/ (unrounded); c ц, sch щ
    "pau": SILENCE, "a": "AA", "aa": "AA", "e": "EH", "ee": "EH", "i": "IH", "ii": "IY",
    "y": "IH", "yy": "IH", "oo": "OW", "u": "UW", "uu": "UW", "ae": "AH", "ay": "AH",
    "ur": "UH", "p": "P", "pp": "P", "b": "B", "bb": "B", "m": "M", "mm": "M", "f": "F",
    "ff": "F", "v": "V", "vv": "V", "t": "T", "tt": "T", "d": "D", "dd": "D", "s": "S",
    "ss": "S", "z": "Z", "zz": "Z", "c": "S", "n": "N", "nn": "N", "l": "L", "ll": "L",
    "r": "D", "rr": "D", "sh": "SH", "zh": "ZH", "ch": "CH", "sch": "SH", "j": "Y", "k": "K",
    "kk": "K", "g": "G", "gg": "G", "h": "HH", "hh": "HH",
}
_FINNISH = {  # Suopuhe (":" long, a phone of its own); @ ä /æ/, 7 ö /ø/, y /y/, & /ə/ (loans)
    "#": SILENCE, "##": SILENCE, "a": "AA", "e": "EH", "i": "IY", "o": "OW", "u": "UW",
    "y": "UY", "@": "AE", "7": "OE", "&": "AH", "a:": "AA", "e:": "EH", "i:": "IY", "o:": "OW",
    "u:": "UW", "y:": "UY", "@:": "AE", "7:": "OE", "p": "P", "p:": "P", "b": "B", "b:": "B",
    "m": "M", "m:": "M", "f": "F", "f:": "F", "v": "V", "v:": "V", "w": "W", "w:": "W",
    "T": "TH", "T:": "TH", "D:": "DH", "t": "T", "t:": "T", "d": "D", "d:": "D", "s": "S",
    "s:": "S", "z:": "Z", "n": "N", "n:": "N", "l": "L", "l:": "L", "L": "L", "L:": "L",
    "r": "D", "r:": "D", "S": "SH", "S:": "SH", "Z:": "ZH", "j": "Y", "j:": "Y", "k": "K",
    "k:": "K", "g": "G", "g:": "G", "N": "NG", "N:": "NG", "h": "HH", "h:": "HH",
}
_CATALAN = {  # upc ona (central Catalan); ax: the reduced /ə/, E O open mid, J ɲ, L ʎ
    "pau": SILENCE, "_": SILENCE, "#": SILENCE, "ax": "AH", "a": "AA", "a1": "AA", "e": "EH",
    "e1": "EH", "E": "EH", "E1": "EH", "i": "IY", "i1": "IY", "o": "OW", "o1": "OW", "O": "AO",
    "O1": "AO", "u": "UW", "u1": "UW", "j": "Y", "w": "W", "p": "P", "b": "B", "m": "M",
    "f": "F", "t": "T", "d": "D", "s": "S", "z": "Z", "n": "N", "l": "L", "r": "D", "rr": "D",
    "S": "SH", "Z": "ZH", "J": "N", "L": "L", "k": "K", "g": "G",
}
_INDIC = {  # the NSK voices (Hindi, Marathi, Telugu share the set and IIIT's lexicons):
    # a: the inherent vowel /ə/; eh ए, ay ऐ, oh ओ, aw औ; ee oo: ऍ ऑ in Hindi and Marathi (rare),
    # Telugu's long ఏ ఓ (common): EH, OW. th dh: the dental stops त द (not /θ ð/), tth ddh:
    # their aspirates; T D N L: retroflex; R: the flap ड़; j: ज /dʒ/; y: य; ksh क्ष, sri श्री:
    # clusters, by their first sound; @ and x are in the set but no lexicon produces them
    # (@: a long open vowel; x: no features at all, so weak and neighbour-led). The lexicons
    # speak the anusvara as m: the audio says m there, and the truth closes the lips with it.
    "pau": SILENCE, "a": "AH", "aa": "AA", "@": "AA", "ih": "IH", "iy": "IY", "uh": "UH",
    "uw": "UW", "eh": "EH", "ee": "EH", "ay": "EH", "oh": "OW", "oo": "OW", "aw": "AO",
    "w": "W", "p": "P", "b": "B", "bh": "B", "m": "M", "f": "F", "v": "V", "th": "T",
    "tth": "T", "dh": "D", "ddh": "D", "T": "T", "td": "T", "D": "D", "n": "N", "N": "N",
    "s": "S", "l": "L", "L": "L", "r": "D", "R": "D", "sh": "SH", "sri": "SH", "zh": "ZH",
    "ch": "CH", "j": "JH", "y": "Y", "k": "K", "kh": "K", "ksh": "K", "g": "G", "gh": "G",
    "h": "HH", "x": "HH",
}
# fmt: on
PHONE_TABLES = {
    "spanish": _SPANISH,
    "italian": _ITALIAN,
    "msu_ru": _RUSSIAN,
    "finnish": _FINNISH,
    "catalan": _CATALAN,
    "indic": _INDIC,
}
ENCODINGS = {"spanish": "latin-1", "italian": "latin-1", "finnish": "latin-1", "catalan": "latin-1"}


def festival_label(symbol: str, phoneset: str) -> str:
    """One phone of a Festival voice's phone set -> the animator's label; an unknown one is an
    error (a new voice's set gets its table first)."""
    table = PHONE_TABLES.get(phoneset)
    if table is None or symbol not in table:
        raise TalkmeshError(f"Festival phone '{symbol}' of phone set '{phoneset}' has no mapping")
    return table[symbol]


def get_festival_voice(language: str, speaker: str) -> FestivalVoice:
    for v in FESTIVAL_VOICES:
        if (v.language, v.speaker) == (language, speaker):
            return v
    known = ", ".join(f"{v.language}/{v.speaker}" for v in FESTIVAL_VOICES)
    raise TalkmeshError(
        f"no Festival voice '{speaker}' of language '{language}': use one of {known}"
    )


def festival_installed(v: FestivalVoice) -> bool:
    """Whether Festival and the voice's Debian package are installed here."""
    import shutil

    return bool(shutil.which("festival")) and (FESTIVAL_VOICES_DIR / v.folder).is_dir()
