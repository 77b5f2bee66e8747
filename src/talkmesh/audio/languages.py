"""Many languages, many voices: the MBROLA voices of Debian's ``mbrola-*`` packages through espeak-ng.

Each :class:`Language` names its espeak-ng code, its family, the MBROLA voices the multilingual
corpus trains on (``train``), the voices kept out for its test split (``test``), and a few
sentences rich in the sounds that lips show (/p b m/, open vowels, rounded vowels, /f v/). A
language with no ``train`` voice is never trained on: it exists to test.

The synthesiser's exact phone timings come from ``espeak-ng --pho`` (the file MBROLA renders). The
voices write their phones in their own SAMPA dialects; :func:`sampa_label` maps any of them onto
the phone labels of the procedural animator (ARPABET, plus ``UY`` and ``OE`` for the rounded front
vowels /y/ and /ø/ that English lacks), from the IPA features the symbols stand for.

Some voices and languages are reserved for checks made outside the project and are never used
here, for training, tuning or evaluation (:data:`RESERVED_VOICES`, :data:`RESERVED_LANGUAGES`):
:func:`check_not_reserved` refuses them.
"""

from __future__ import annotations

import unicodedata
from dataclasses import dataclass

from talkmesh.audio.phonemes import SILENCE
from talkmesh.errors import TalkmeshError

# Never train, tune or evaluate on these (kept for an outside check).
RESERVED_VOICES = frozenset({"de1", "fr1", "es1", "it3", "pl1", "nl2", "br1", "en1"})
RESERVED_LANGUAGES = frozenset({"tr", "hu", "ro", "sv", "el", "cs"})  # any voice of them
RESERVED_DBS_PREFIXES = ("tr", "hu", "ro", "sw", "gr", "cz")  # their MBROLA databases


@dataclass(frozen=True)
class Language:
    code: str  # espeak-ng language
    name: str
    family: str
    train: tuple[str, ...]  # MBROLA databases (us1, de2, ...) the corpus trains on
    test: tuple[str, ...]  # held-out voices of the test split
    sentences: tuple[str, ...]


# fmt: off
LANGUAGES: tuple[Language, ...] = (
    Language("en-us", "English", "Germanic", ("us1", "us2"), ("us3",), (
        "Bob bought a big map of the park before breakfast.",
        "My mother made warm bread when the bus was late.",
        "Please pass the paper, then wait by the open window.",
        "We walked along the harbour as the boats came home.",
        "A small dog barked at the moon all night.",
        "Put the black box on the top shelf, but be careful.",
    )),
    Language("de", "German", "Germanic", ("de2", "de4", "de6"), ("de3",), (
        "Mein Bruder baut ein Boot am Meer.",
        "Bitte bring mir das Papier und die Bücher.",
        "Am Morgen möchte Paul immer frisches Brot.",
        "Über der Brücke blühen schöne Blumen.",
        "Die Mutter malt ein Bild von dem alten Baum.",
        "Wir fahren morgen mit dem Bus nach Bremen.",
    )),
    Language("nl", "Dutch", "Germanic", ("nl1",), ("nl3",), (
        "Mijn moeder bakt brood in de morgen.",
        "De boot vaart langs de brug naar de haven.",
        "Papa koopt bloemen op de markt.",
        "We wandelen met de hond in het bos.",
        "Het meisje pakt een boek van de plank.",
        "Bij mooi weer spelen de kinderen buiten.",
    )),
    Language("af", "Afrikaans", "Germanic", ("af1",), (), (
        "My pa bak brood in die oggend.",
        "Die boot vaar oor die blou water.",
        "Ons speel met die bal in die park.",
        "Ma maak 'n lekker bord pampoen.",
        "Die blomme blom mooi in die lente.",
        "Bring asseblief die boek vir my.",
    )),
    Language("is", "Icelandic", "Germanic", ("ic1",), (), (
        "Pabbi minn borðar brauð á morgnana.",
        "Mamma bakar pönnukökur í dag.",
        "Báturinn siglir út á bláan sjóinn.",
        "Við förum í bíó með bróður mínum.",
        "Hundurinn sefur undir borðinu.",
        "Blómin í garðinum eru falleg.",
    )),
    Language("fr-fr", "French", "Romance", ("fr2", "fr4"), ("fr6",), (
        "Mon père a bu un bon café au bord de la mer.",
        "Le petit bateau part pour la plage à midi.",
        "Marie mange une pomme sous le grand arbre.",
        "Nous voulons du beurre et du pain pour le matin.",
        "Il pleut beaucoup sur la montagne en novembre.",
        "Pierre a mis ses bottes bleues dans la boîte.",
    )),
    Language("es", "Spanish", "Romance", ("es2", "mx1"), ("es3",), (
        "Mi madre compra pan en el mercado por la mañana.",
        "El barco blanco parte para Barcelona.",
        "Pablo bebe un poco de agua muy fría.",
        "Buenos días, me gusta mucho tu sombrero.",
        "Vamos a la playa con mi primo Manuel.",
        "El perro pequeño duerme bajo la mesa.",
    )),
    Language("it", "Italian", "Romance", ("it1",), ("it4",), (
        "Mio padre mangia pane e burro ogni mattina.",
        "La bambina porta un bel mazzo di fiori.",
        "Domani andiamo al mare con la barca.",
        "Per piacere, passami il piatto di pasta.",
        "Il ponte vecchio è molto bello di sera.",
        "Paolo ama la musica e balla sempre.",
    )),
    Language("pt", "Portuguese", "Romance", ("br3", "pt1"), ("br4",), (
        "Meu pai bebe um bom café pela manhã.",
        "O barco branco parte para o mar.",
        "A menina comprou maçãs no mercado.",
        "Por favor, me passe o pão e a manteiga.",
        "Amanhã vamos ver a bela montanha.",
        "O pombo pousou em cima da ponte.",
    )),
    Language("hr", "Croatian", "Slavic", ("cr1",), (), (
        "Moj brat pije mlijeko svako jutro.",
        "Mama peče kruh u malom domu.",
        "Brod plovi po mirnom moru.",
        "Pas spava ispod bijelog stola.",
        "Molim te, daj mi plavu olovku.",
        "Baka pjeva lijepu pjesmu.",
    )),
    Language("ja", "Japanese", "Japonic", ("jp1", "jp2"), ("jp3",), (
        "わたしは まいにち パンを たべます。",
        "ぼくの ともだちは びょういんに います。",
        "あめが ふって いるので かさを もって いきます。",
        "はなが とても きれいです。",
        "みんなで うみへ いきましょう。",
        "おかあさんは ごはんを つくって います。",
    )),
    Language("hi", "Hindi", "Indic", ("in1",), ("in2",), (
        "मेरा भाई बाज़ार में आम खरीदता है।",
        "माँ सुबह पानी पीती है।",
        "बच्चे बाग में खेल रहे हैं।",
        "हम बस से मुंबई जाएंगे।",
        "पापा ने मुझे एक किताब दी।",
        "बारिश में मोर नाचता है।",
    )),
    Language("ar", "Arabic", "Semitic", ("ar1",), ("ar2",), (
        "ذهب الولد إلى المدرسة في الصباح",
        "أمي تحب الموز والبرتقال",
        "الباب مفتوح والبيت كبير",
        "شربت الماء البارد بعد المباراة",
        "أبي يقرأ الكتاب في المساء",
        "البحر جميل في الربيع",
    )),
    Language("fa", "Persian", "Iranian", ("ir1",), (), (
        "پدرم هر روز نان می خرد",
        "مادر بزرگ در باغ گل می کارد",
        "ما با اتوبوس به بازار رفتیم",
        "باران بهاری بسیار زیباست",
        "برادرم کتاب می خواند",
        "امروز هوا خیلی خوب است",
    )),
    Language("id", "Indonesian", "Austronesian", ("id1",), (), (
        "Bapak membeli buah mangga di pasar.",
        "Ibu memasak nasi untuk makan malam.",
        "Kami pergi ke pantai pada hari Minggu.",
        "Buku baru itu ada di atas meja.",
        "Anak itu bermain bola bersama temannya.",
        "Tolong buka pintu belakang.",
    )),
    Language("ms", "Malay", "Austronesian", ("ma1",), (), (
        "Bapa membeli buah pisang di pasar.",
        "Emak memasak makanan yang sedap.",
        "Mereka bermain bola di padang.",
        "Saya mahu minum air sejuk.",
        "Bulan purnama bersinar malam ini.",
        "Kami pergi ke pantai pada pagi Ahad.",
    )),
    # never trained on: test-only languages
    Language("he", "Hebrew", "Semitic", (), ("hb1", "hb2"), (
        "אבא בא הביתה בבוקר",
        "אמא מבשלת מרק טעים",
        "הבן שלי משחק בפארק",
        "ביום ראשון נלך לים",
        "הפרחים במרפסת יפים מאוד",
        "מה שלומך היום",
    )),
    Language("lt", "Lithuanian", "Baltic", (), ("lt1", "lt2"), (
        "Mano brolis perka duoną mieste.",
        "Mama verda sriubą pietums.",
        "Laivas plaukia per mėlyną jūrą.",
        "Berniukas bėga į parką su šunimi.",
        "Prašau paduoti man popierių.",
        "Bobutė mezga baltas pirštines.",
    )),
    Language("et", "Estonian", "Uralic", (), ("ee1",), (
        "Minu ema paneb piima lauale.",
        "Poiss mängib pargis palliga.",
        "Paat sõidab üle mere.",
        "Me läheme homme bussiga poodi.",
        "Palun anna mulle see punane pliiats.",
        "Vanaema peab meeles palju lugusid.",
    )),
    Language("te", "Telugu", "Dravidian", (), ("tl1",), (
        "మా అమ్మ పాలు తాగుతుంది",
        "బాబు బడికి వెళ్ళాడు",
        "మేము బస్సులో పట్నం వెళ్తాము",
        "పాప బొమ్మతో ఆడుకుంటుంది",
        "ఈ పుస్తకం చాలా బాగుంది",
        "వర్షం పడుతోంది",
    )),
)
# fmt: on
BY_CODE = {lang.code: lang for lang in LANGUAGES}


def get_language(code: str) -> Language:
    if code in BY_CODE:
        return BY_CODE[code]
    raise TalkmeshError(f"unknown language '{code}': use one of {', '.join(BY_CODE)}")


def check_not_reserved(db: str, language: str = "") -> None:
    """Refuses a voice or language reserved for outside checks (never trained or tuned on here)."""
    if db in RESERVED_VOICES or db.startswith(RESERVED_DBS_PREFIXES):
        raise TalkmeshError(f"MBROLA voice '{db}' is reserved for outside checks: choose another")
    if language.split("-")[0] in RESERVED_LANGUAGES:
        raise TalkmeshError(f"language '{language}' is reserved for outside checks")


def trained_languages() -> list[Language]:
    return [lang for lang in LANGUAGES if lang.train]


def never_trained_languages() -> list[Language]:
    return [lang for lang in LANGUAGES if not lang.train]


# --- SAMPA (any MBROLA voice's dialect) -> the procedural animator's phone labels -------------
# Consonants by place and manner, vowels by height, backness and rounding. Keys are bare symbols
# (length, nasality, aspiration and stress marks are stripped first, see :func:`sampa_label`).
# fmt: off
_CONSONANTS = {
    # bilabial: the lips close
    "p": "P", "b": "B", "m": "M", "B": "V", "p\\": "F", "bh": "B", "ph": "P", "mb": "M",
    # labiodental: the lower lip tucks under the upper teeth
    "f": "F", "v": "V", "F": "V", "P": "V", "v\\": "V", "pf": "F",
    # dental / alveolar
    "T": "TH", "D": "DH", "t": "T", "d": "D", "n": "N", "l": "L", "s": "S", "z": "Z",
    "ts": "S", "dz": "Z", "r": "D", "rr": "D", "4": "T", "r\\": "R", "l\\": "L", "5": "L",
    "th": "T", "dh": "D", "t`": "T", "d`": "D", "n`": "N", "s`": "SH", "z`": "ZH", "r`": "R",
    "l`": "L", "rh": "R", "tt": "T", "dd": "D", "ll": "L", "nn": "N", "ss": "S",
    # postalveolar / palatal
    "S": "SH", "Z": "ZH", "tS": "CH", "dZ": "JH", "c": "K", "J\\": "G", "C": "SH", "j\\": "Y",
    "J": "N", "L": "L", "j": "Y", "jj": "Y", "tsh": "CH", "ts`": "CH", "dz`": "JH", "ts\\": "CH",
    "dz\\": "JH", "s\\": "SH", "z\\": "ZH", "x\\": "SH", "tS'": "CH", "tSh": "CH", "dZh": "JH",
    # velar / uvular / glottal / pharyngeal
    "k": "K", "g": "G", "N": "NG", "x": "HH", "G": "G", "R": "G", "X": "HH", "q": "K",
    "h": "HH", "?": "HH", "h\\": "HH", "X\\": "HH", "?\\": "HH", "kh": "K", "gh": "G", "K": "HH",
    "ng": "NG", "kk": "K", "gg": "G",
    # approximants with lip rounding
    "w": "W", "H": "W", "W": "W", "v`": "W",
}
_VOWELS = {
    # open (jaw wide)
    "a": "AA", "A": "AA", "6": "AH", "&": "AE", "{": "AE", "Q": "AA", "V": "AH", "aa": "AA",
    # mid
    "e": "EH", "E": "EH", "@": "AH", "3": "ER", "8": "AH", "7": "AH", "@\\": "AH", "e@": "EH",
    # close front unrounded
    "i": "IY", "I": "IH", "1": "IH", "ii": "IY", "ee": "EY",
    # rounded
    "u": "UW", "U": "UH", "o": "OW", "O": "AO", "uu": "UW", "oo": "OW", "M": "UH", "}": "UW",
    # rounded front: /y Y/ close, /2 9/ mid (German ü, ö; French u, eu)
    "y": "UY", "Y": "UY", "2": "OE", "9": "OE", "&\\": "OE",
    # diphthongs (the animator glides between the two targets)
    "aI": "AY", "ai": "AY", "aU": "AW", "au": "AW", "OY": "OY", "OI": "OY", "oI": "OY",
    "eI": "EY", "ei": "EY", "EI": "EY", "@U": "OW", "oU": "OW", "ou": "OW", "9Y": "OE",
    "Ei": "EY", "Ai": "AY", "ui": "UW", "uo": "OW", "ia": "AA", "ie": "IY", "Au": "AW",
    "aj": "AY", "aw": "AW", "ej": "EY", "oj": "OY", "uj": "UW", "eu": "EH",
}
# fmt: on
SILENT_SYMBOLS = frozenset({"_", "#", "sil", "pau", "%"})
_STRIP = ":~=\"'`_0123456789;,.!^"


def sampa_label(symbol: str) -> str:
    """One MBROLA phone symbol (any voice's SAMPA) -> a procedural-animator phone label.

    Tries the symbol as written, then without its marks (length ``:``, nasal ``~``, syllabic
    ``=``, stress and tone digits, ``_h`` aspiration), then its first one or two characters.
    Unknown symbols map to ``HH`` (a weak, neighbour-led mouth), never to silence.
    """
    s = unicodedata.normalize("NFC", symbol.strip())
    if not s or s in SILENT_SYMBOLS:
        return SILENCE
    for table in (_CONSONANTS, _VOWELS):
        if s in table:
            return table[s]
    bare = s.split("_")[0] if "_" in s[1:] else s
    stripped = bare.strip(_STRIP) or bare
    for cand in (bare, stripped, stripped.lower(), stripped[:2], stripped[:1]):
        for table in (_CONSONANTS, _VOWELS):
            if cand in table:
                return table[cand]
    return "HH"
