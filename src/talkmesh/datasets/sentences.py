"""English sentences for the synthetic corpus, generated from a small grammar written for talkmesh.

The word lists cover every ARPABET phone, with many bilabials (/p b m/), rounded vowels and open
vowels, so lip closure, rounding and jaw opening all occur often. Sentences take roughly 2-5 s
to say. ``generate_sentences(n, seed)`` returns ``n`` distinct sentences, the same for a seed.
"""

from __future__ import annotations

import numpy as np

from talkmesh.errors import TalkmeshError

NAMES = (
    "Bob",
    "Maggie",
    "Paul",
    "Ruth",
    "George",
    "Yvonne",
    "Thomas",
    "Zoe",
    "Father Joseph",
    "Uncle Woody",
    "the baker",
    "my brother",
    "the young pilot",
    "our neighbour",
    "the old shepherd",
    "a busy mother",
    "the boy",
    "the judge",
    "the choir",
    "Aunt Beth",
)
VERBS = (
    "bought",
    "polished",
    "measured",
    "borrowed",
    "pushed",
    "painted",
    "chose",
    "found",
    "moved",
    "watched",
    "thought about",
    "mopped",
    "bumped into",
    "wrapped",
    "showed us",
    "shared",
    "carried",
    "opened",
    "fixed",
    "judged",
)
ADJECTIVES = (
    "big",
    "blue",
    "bumpy",
    "smooth",
    "rusty",
    "purple",
    "huge",
    "tiny",
    "broken",
    "golden",
    "pleasant",
    "yellow",
    "awkward",
    "chubby",
    "foolish",
    "moody",
    "bright",
    "plump",
    "thin",
    "odd",
)
NOUNS = (
    "map",
    "boat",
    "umbrella",
    "pumpkin",
    "mirror",
    "bottle",
    "bubble",
    "ship",
    "window",
    "voucher",
    "jigsaw",
    "vision board",
    "mop",
    "book",
    "oven",
    "puppet",
    "fishing rod",
    "moon rock",
    "bench",
    "pillow",
)
PLACES = (
    "by the pool",
    "at the museum",
    "in the bathroom",
    "near the harbour",
    "on the balcony",
    "behind the barn",
    "at the zoo",
    "in the garage",
    "under the bridge",
    "beyond the hills",
    "at the pub",
    "in the playroom",
    "by the church",
    "at the beach",
    "on the bumpy road",
)
TIMES = (
    "yesterday",
    "every morning",
    "at noon",
    "this autumn",
    "on Thursday",
    "before supper",
    "after the show",
    "in June",
    "twice a month",
    "when the moon rose",
)
FEELINGS = (
    "happy",
    "puzzled",
    "amused",
    "bored",
    "pleased",
    "jealous",
    "thrilled",
    "worried",
    "calm",
    "embarrassed",
)
QUESTIONS = (
    "Why would",
    "How could",
    "Where did",
    "When will",
    "Who made",
)

TEMPLATES = (
    "{name} {verb} a {adj} {noun} {place}.",
    "{name} {verb} the {adj} {noun} {time}.",
    "{time_cap}, {name} {verb} a {noun} {place}.",
    "{question} {name} keep the {adj} {noun} {place}?",
    "{name_cap} was {feeling} because the {noun} looked so {adj}.",
    "Please bring me the {adj} {noun} from {place_short}, {name}.",
    "Maybe {name} {verb} my {noun}, but the {adj} one is still {place}.",
    "{name_cap} and {name2} {verb} a {adj} {noun} {time}.",
)
PLACE_SHORT = (
    "the pool",
    "the museum",
    "the bathroom",
    "the harbour",
    "the balcony",
    "the barn",
    "the zoo",
    "the garage",
    "the bridge",
    "the pub",
    "the beach",
    "the market",
)


def _cap(text: str) -> str:
    return text[0].upper() + text[1:]


def generate_sentences(n: int, seed: int = 0) -> list[str]:
    """``n`` distinct sentences, deterministic for ``seed``."""
    if n < 0:
        raise TalkmeshError("the number of sentences must be >= 0")
    rng = np.random.default_rng(seed)
    out: list[str] = []
    seen: set[str] = set()
    attempts = 0
    while len(out) < n:
        attempts += 1
        if attempts > 100 * n + 1000:
            raise TalkmeshError(f"the grammar cannot make {n} distinct sentences")
        pick = lambda words: words[int(rng.integers(len(words)))]  # noqa: E731
        name, name2 = pick(NAMES), pick(NAMES)
        if name2 == name:
            continue
        template = pick(TEMPLATES)
        text = template.format(
            name=name,
            name_cap=_cap(name),
            name2=name2,
            verb=pick(VERBS),
            adj=pick(ADJECTIVES),
            noun=pick(NOUNS),
            place=pick(PLACES),
            place_short=pick(PLACE_SHORT),
            time=pick(TIMES),
            time_cap=_cap(pick(TIMES)),
            feeling=pick(FEELINGS),
            question=pick(QUESTIONS),
        )
        text = text.replace(" a a", " an a").replace(" a u", " an u").replace(" a o", " an o")
        text = _cap(text)
        if text not in seen:
            seen.add(text)
            out.append(text)
    return out
