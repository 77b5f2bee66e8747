"""Many languages, many voices: MBROLA, espeak-ng's own and Festival voices, with exact phone times.

Each :class:`Language` names its espeak-ng code, its family, the voices the multilingual corpus
trains on (``train``), the voices kept out for its test split (``test``), and a few sentences rich
in the sounds that lips show (/p b m/, open vowels, rounded vowels, /f v/). A language with no
``train`` voice is never trained on: it exists to test.

Two engines give the synthesiser's exact phone timings:

* ``mbrola``: the voices of Debian's ``mbrola-*`` packages through espeak-ng; ``train`` and
  ``test`` name MBROLA databases (``de2``), the times come from ``espeak-ng --pho`` (the file
  MBROLA renders). The voices write their phones in their own SAMPA dialects; :func:`sampa_label`
  maps any of them onto the phone labels of the procedural animator (ARPABET, plus ``UY`` and
  ``OE`` for the rounded front vowels /y/ and /ø/ that English lacks), from the IPA features the
  symbols stand for.
* ``espeak-lib``: espeak-ng's own voice ``voice`` (Mandarin from pinyin with tone numbers,
  Cantonese, Korean, ...), whose variants (``m3``, ``f2``: another larynx, formants and pitch)
  make the several voices of a language; ``train`` and ``test`` name variants, and a test variant
  is never a training variant of any language. The times come from the library's phoneme events
  (:mod:`talkmesh.audio.espeak_lib`); :func:`espeak_label` maps espeak-ng's phoneme mnemonics.
  Tones are not visemes: a tone is no phone of its own there.

Festival's voices of other languages (``festival``, ``festival_test``: speakers of
:data:`talkmesh.audio.festival_voices.FESTIVAL_VOICES`) are more voices of a language, with a
third engine; the times come from the utterance's ``Segment`` relation. Finnish, Catalan and
Marathi have only them. They follow every other voice in the corpus (its earlier subjects and
splits stay as they were); a Festival speaker held out in one language is held out in all.

Some voices and languages are reserved for checks made outside the project and are never used
here, for training, tuning or evaluation (:data:`RESERVED_VOICES`, :data:`RESERVED_LANGUAGES`):
:func:`check_not_reserved`, :func:`check_espeak_not_reserved` and
:func:`check_festival_not_reserved` refuse them.
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
# espeak-ng's own voices of them, by language code and by name ("grc" is Ancient Greek)
RESERVED_ESPEAK_LANGUAGES = RESERVED_LANGUAGES | {"grc"}
RESERVED_ESPEAK_NAMES = ("turkish", "hungarian", "romanian", "moldav", "swedish", "greek", "czech")


@dataclass(frozen=True)
class Language:
    code: str  # espeak-ng language
    name: str
    family: str
    train: tuple[str, ...]  # MBROLA databases (us1, de2, ...) or espeak-ng variants (m3, f2)
    test: tuple[str, ...]  # held-out voices of the test split
    sentences: tuple[str, ...]
    engine: str = "mbrola"  # or "espeak-lib": espeak-ng's own voice, times from its library
    voice: str = ""  # espeak-lib: the espeak-ng voice the variants attach to
    # Festival's voices of the language (speakers of talkmesh.audio.festival_voices), after all
    # the others in the corpus: trained on, and held out
    festival: tuple[str, ...] = ()
    festival_test: tuple[str, ...] = ()

    @property
    def trained(self) -> bool:
        return bool(self.train or self.festival)

    def voice_name(self, variant: str) -> str:
        """The synthesiser's voice for one of ``train`` / ``test``: ``mb-de2``, ``yue+m3``."""
        if self.engine == "espeak-lib":
            return f"{self.voice or self.code}+{variant}"
        return f"mb-{variant}"


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
    ), festival=("el",)),
    Language("it", "Italian", "Romance", ("it1",), ("it4",), (
        "Mio padre mangia pane e burro ogni mattina.",
        "La bambina porta un bel mazzo di fiori.",
        "Domani andiamo al mare con la barca.",
        "Per piacere, passami il piatto di pasta.",
        "Il ponte vecchio è molto bello di sera.",
        "Paolo ama la musica e balla sempre.",
    ), festival=("lp", "pc")),
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
    ), festival_test=("nsk",)),  # NSK speaks Telugu and Marathi too: held out in all three
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
    # espeak-ng reads Hebrew script without its vowels ("אמא מבשלת" -> ?m? mvSlt) and cannot read
    # the vowel points, so the sentences are its phoneme input ([[...]]), vowels written out:
    # אבא בא הביתה בבוקר / אמא מבשלת מרק טעים / הבן שלי משחק בפארק / ביום ראשון נלך לים /
    # הפרחים במרפסת יפים מאוד / מה שלומך היום
    Language("he", "Hebrew", "Semitic", (), ("hb1", "hb2"), (
        "[[?'aba b'a hab'ajta bab'okeQ\"]]",
        "[[?'ima mevaS'elet maQ\"'ak ta?'im]]",
        "[[hab'en Sel'i mesaX'ek bap'aQ\"k]]",
        "[[bej'om Q\"iS'on nel'eX laj'am]]",
        "[[hapQ\"aX'im bamiQ\"p'eset jaf'im me?'od]]",
        "[[m'a SlomX'a haj'om]]",
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
    ), festival_test=("nsk",)),
    # espeak-ng's own voices (times from its library's phoneme events); variants are the voices:
    # training ones from m1-m3, f1-f3, held-out ones from m6, m7, f4, f5 (no language trains on them)
    Language("cmn", "Mandarin", "Sinitic", ("m3", "f2", "m1"), ("f4",), (
        "Ba4 ba5 mai3 le5 yi1 ge4 da4 mian4 bao1.",
        "Ma1 ma5 pao3 bu4 pao3 de5 hen3 kuai4.",
        "Fu4 mu3 pei2 wo3 qu4 pa2 shan1.",
        "Wo3 men5 bu2 pa4 bo1 lang4 he2 da4 feng1.",
        "Xiao3 yu2 zai4 lv4 se4 de5 hu2 li3 you2 yong3.",
        "Pang4 pang5 de5 mao1 mi1 zai4 fang2 jian1 li3 shui4 jiao4.",
    ), "espeak-lib", "cmn-latn-pinyin"),  # pinyin: Debian's espeak-ng reads hanzi as English
    Language("ko", "Korean", "Koreanic", ("m1", "f3"), ("m7",), (
        "아빠가 바다에서 물고기를 봤어요.",
        "엄마는 매일 아침 밥을 먹어요.",
        "우리는 버스를 타고 바닷가에 가요.",
        "할머니가 맛있는 빵을 만들었어요.",
        "봄에는 예쁜 꽃이 많이 피어요.",
        "오빠는 파란 모자를 좋아해요.",
    ), "espeak-lib"),
    Language("vi", "Vietnamese", "Austroasiatic", ("m2", "f1"), ("f5",), (
        "Mẹ mua bánh mì ở chợ.",
        "Bố em pha cà phê mỗi buổi sáng.",
        "Bà ngoại nấu phở bò rất ngon.",
        "Chúng tôi đi bơi ở biển vào mùa hè.",
        "Bé Mai mặc áo màu vàng.",
        "Buổi tối ba mẹ đi bộ trong công viên.",
    ), "espeak-lib"),
    Language("sw", "Swahili", "Bantu", ("m3", "f3"), ("m6",), (
        "Mama anapika mboga na wali.",
        "Baba amenunua mkate mpya sokoni.",
        "Watoto wanapenda kucheza mpira.",
        "Mbwa mdogo amelala chini ya meza.",
        "Tafadhali nipe maji baridi.",
        "Bibi anapenda maua mazuri.",
    ), "espeak-lib"),
    Language("ru", "Russian", "Slavic", ("m2", "f2"), ("f4",), (
        "Мама мыла раму утром.",
        "Папа пьёт молоко и ест булку.",
        "Бабушка пошла в магазин за хлебом.",
        "Мы видели большой белый пароход.",
        "Мой брат любит играть в футбол.",
        "Повар приготовил вкусный борщ.",
    ), "espeak-lib", festival=("msu",)),
    # never trained on
    Language("yue", "Cantonese", "Sinitic", (), ("f4", "m7"), (
        "爸爸買咗一個大麵包。",
        "媽媽每朝都去跑步。",
        "婆婆喺菜市場買魚。",
        "我哋一齊去海邊玩。",
        "呢本書好好睇。",
        "阿爸飲咗杯熱咖啡。",
    ), "espeak-lib"),
    Language("uk", "Ukrainian", "Slavic", (), ("m6", "f5"), (
        "Мама купила білий хліб.",
        "Батько варить каву щоранку.",
        "Бабуся пече смачні пиріжки.",
        "Ми підемо до моря влітку.",
        "Мій брат любить футбол.",
        "Пташка співає у парку.",
    ), "espeak-lib"),
    # Festival's voices only
    Language("fi", "Finnish", "Uralic", (), (), (
        "Minun äitini leipoo pullaa aamulla.",
        "Pieni poika pelaa palloa puistossa.",
        "Mummo ostaa maitoa ja banaaneja kaupasta.",
        "Meri on tänään tyyni ja sininen.",
        "Isä maalaa vanhan veneen punaiseksi.",
        "Huomenna menemme bussilla mökille.",
    ), festival=("lj",), festival_test=("mv",)),
    Language("ca", "Catalan", "Romance", (), (), (
        "El meu pare beu una mica d'aigua ben freda.",
        "La mare compra pa i pomes al mercat.",
        "Vam passejar per la platja amb el gos.",
        "El vaixell blau surt del port al matí.",
        "La Maria menja un bon plat de sopa.",
        "Plou molt a la muntanya al novembre.",
    ), festival=("ona",)),
    Language("mr", "Marathi", "Indic", (), (), (  # never trained on
        "माझी आई भाजी बनवते.",
        "बाबा बाजारातून आंबे आणतात.",
        "मुले बागेत खेळत आहेत.",
        "आम्ही बसने मुंबईला जाऊ.",
        "पाऊस पडला की मोर नाचतो.",
        "मला थंड पाणी प्यायचे आहे.",
    ), festival_test=("nsk",)),
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


def check_espeak_not_reserved(voice: str, language: str = "", name: str = "") -> None:
    """Refuses espeak-ng voices of reserved languages (by code, file or name) and MBROLA voices,
    which go through the ``mbrola`` engine where their databases are checked."""
    base = voice.split("+")[0].strip().lower()
    if base.startswith(("mb-", "mb/")) or "/mb-" in base:
        raise TalkmeshError(
            f"'{voice}' is an MBROLA voice: use the mbrola engine (talkmesh.audio.voices.mbrola_voice)"
        )
    for tag in (base.rsplit("/", 1)[-1], language.lower()):
        if tag and tag.split("-")[0] in RESERVED_ESPEAK_LANGUAGES:
            raise TalkmeshError(f"espeak-ng voice '{voice}' is reserved for outside checks")
    if any(n in f"{base} {name.lower()}" for n in RESERVED_ESPEAK_NAMES):
        raise TalkmeshError(f"espeak-ng voice '{voice}' is reserved for outside checks")


def check_festival_not_reserved(voice: str, language: str = "") -> None:
    """Refuses Festival voices of reserved languages (by language code, or by name: Debian's
    Czech voices are ``voice_czech_dita`` ...) and Festival's voices over reserved MBROLA
    databases (``voice_en1_mbrola``). A voice's short name is no language code: Spanish
    ``voice_el_diphone`` is not Greek."""
    import re

    name = voice.strip().lower()
    if language.lower().split("-")[0] in RESERVED_ESPEAK_LANGUAGES:
        raise TalkmeshError(f"Festival voice '{voice}' ({language}) is reserved for outside checks")
    if any(n in name for n in RESERVED_ESPEAK_NAMES):
        raise TalkmeshError(f"Festival voice '{voice}' is reserved for outside checks")
    for db in re.findall(r"([a-z]+\d+)_mbrola", name):
        check_not_reserved(db)


def trained_languages() -> list[Language]:
    return [lang for lang in LANGUAGES if lang.trained]


def never_trained_languages() -> list[Language]:
    return [lang for lang in LANGUAGES if not lang.trained]


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


# --- espeak-ng's phoneme mnemonics -> the procedural animator's phone labels ----------------
# espeak-ng names its phones in its own ASCII scheme (Kirshenbaum-like, the symbols of
# ``espeak-ng -x``): most consonants and plain vowels read as SAMPA (:func:`sampa_label` takes
# them); these differ, or carry espeak-ng's marks (";" palatalised, "." retroflex, "-"
# unreleased or syllabic, "[" dental, "#" a variant). A multi-vowel phone (Mandarin "uai") takes
# its nucleus; the glide before it is a phone of its own where espeak-ng makes one ("X w A").
# fmt: off
_ESPEAK_COMMON = {
    # bilabial, labiodental
    "m-": "M", "p-": "P", "b-": "B", "ph": "P",
    # flaps and trills (the tongue tip, like SAMPA "r")
    "*": "D", "R": "D", "R2": "D", "R3": "D", "R4": "D", "r.": "R",
    # alveolar, dental, retroflex, postalveolar, alveolo-palatal
    "t-": "T", "d-": "D", "t[": "T", "d[": "D", "d_": "D", "n-": "N", "n.": "N", "l.": "L",
    "s-": "S", "ts": "S", "tsh": "S", "dz": "Z", "s.": "SH", "z.": "ZH", "ts.": "CH",
    "ts.h": "CH", "cr": "CH", "tS;": "CH", "tS;h": "CH", "tSh": "CH", "tS;-": "CH",
    "dZ;": "JH", "S;": "SH", "Z;": "ZH", "n^": "N", "l^": "L", "L": "L",
    # palatal, velar, glottal
    "J": "JH", "J^": "JH", ";": "Y", "k-": "K", "q": "K", "q-": "K", "kh": "K", "N-": "NG",
    "X": "HH", "x": "HH",
    # vowels: espeak-ng's unrounded back /ɯ ɤ/, apical /ɿ ʅ/, central /ɵ/, reduced and variants
    "u-": "IH", "o-": "AH", "i.": "IH", "i[": "IH", "8": "OE", "@-": "AH", "@r": "ER",
    "a#": "AH", "V#": "AH", "I#": "IH", "I2": "IH", "I3": "IH", "I^": "IY", "E#": "EH",
    "E2": "EH", "E3": "EH", "E%": "EH", "u#": "UW", 'u"': "UW", "o#": "OW", "O#": "AO",
    "O+": "AO", "O-": "OW", "ju": "UW", "ja": "AA", "ja#": "AH", "a:I": "AY", "a:U": "AW",
    # diphthongs and multi-vowel phones (Mandarin finals), by nucleus
    "Au": "AW", "ai": "AY", "ei": "EY", "ou": "OW", "iA": "AA", "iE": "EH", "iAu": "AW",
    "io": "OW", "iou": "OW", "ong": "UH", "uA": "AA", "ua": "AA", "uai": "AY", "uei": "EY",
    "uo": "OW", "u@": "AH", "yu": "UY", "y&": "UY", "yE": "EH", "y@": "UY", "yi": "UY",
}
# Where a language's phoneme table gives a mnemonic another sound (espeak-ng's phoneme tables)
_ESPEAK_BY_TABLE = {
    "ru": {"y": "IH", "Y": "IH"},  # ы /ɨ/, unrounded
    # च छ /tʃ tʃʰ/ (espeak-ng's palatal stops), झ /dʒʱ/, ह /ɦ/, ग़ /ɣ/
    "hi": {"c": "CH", "c#": "CH", "c:": "CH", "J#": "JH", "H": "HH", "Q": "G"},
    "uk": {"y": "IH", "Y": "IH"},  # Ukrainian reads with the Russian table
    "vi": {"y": "IH", "y@": "IH", "yI": "IH", "u@": "UW", "i@": "IY"},  # ư /ɯ/; ua, ia
    "yue": {  # jyutping-named: z /ts/, c /tsʰ/, a /ɐ/, eo /ɵ/, oe /œ/, yu /y/, finals with -ng
        "z": "S", "c": "S", "a": "AH", "aa": "AA", "aai": "AY", "aau": "AW", "e": "EH",
        "eu": "EH", "iu": "IY", "o": "AO", "oi": "OY", "ui": "UW", "oe": "OE", "eo": "OE",
        "eoi": "OE", "ang": "AH", "aang": "AA", "eng": "EH", "ing": "IH", "ong": "AO",
        "ung": "UH", "oeng": "OE",
    },
}
# fmt: on
ESPEAK_PAUSES = ("_", "||")  # "_", "_:", "_|", "_!" ...: pauses (silent); "||": a clause break


def espeak_label(mnemonic: str, language: str = "") -> str:
    """One espeak-ng phoneme mnemonic (as ``espeak-ng -x`` writes it) -> a procedural-animator
    phone label. ``language``: the voice's espeak-ng language (``cmn-latn-pinyin``, ``yue``, ...),
    whose phoneme table decides the few mnemonics that differ between tables. Stress marks and
    tone digits are not phones; a pause is silence."""
    s = unicodedata.normalize("NFC", mnemonic.strip()).lstrip("',")
    if not s or s.startswith(ESPEAK_PAUSES):
        return SILENCE
    table = _ESPEAK_BY_TABLE.get(language.lower().split("-")[0], {})
    for cand in (s, s.rstrip("0123456789") or s):
        if cand in table:
            return table[cand]
        if cand in _ESPEAK_COMMON:
            return _ESPEAK_COMMON[cand]
    return sampa_label(s)
