"""What a batch animates: speech files named one by one, every speech file under a folder, or the
paths listed in a text file, each with the name its outputs take (``{stem}``)."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

from talkmesh.audio.loading import SOUNDFILE_EXTENSIONS
from talkmesh.errors import TalkmeshError, os_error_message, resolved

# Found in folders: what libsndfile decodes and the usual compressed formats ffmpeg reads.
AUDIO_SUFFIXES = SOUNDFILE_EXTENSIONS | {".mp3", ".m4a", ".aac", ".opus", ".wma", ".mka"}
# A text file of paths, one a line (``#`` starts a comment), relative to the list's folder.
LIST_SUFFIXES = frozenset({".txt", ".lst", ".list"})


class Input(NamedTuple):
    """One speech file and the name its outputs take: the file's stem, or under a folder its
    path relative to that folder without the suffix (``alice/line001``), so that a library's
    subfolders are mirrored in the output folder."""

    audio: Path
    stem: str


def is_batch_source(path: Path) -> bool:
    """Whether ``path`` names many files (a folder or a list) rather than one speech file."""
    return path.is_dir() or path.suffix.lower() in LIST_SUFFIXES


def find_inputs(sources: list[Path]) -> list[Input]:
    """Expand folders and lists into speech files, in order, each file once.

    A path that is neither a folder nor a list is a speech file named by the user: a missing or
    empty one is a one-line :class:`TalkmeshError` here, before any model loads (a file a folder
    or a list holds fails on its own instead, and the rest of the batch goes on). A missing or
    empty folder, and a missing, unreadable or empty list, are one-line errors too.
    """
    found: list[Input] = []
    for src in sources:
        if src.is_dir():
            found += _folder(src)
        elif src.suffix.lower() in LIST_SUFFIXES:
            found += _listed(src)
        elif not src.exists() and not src.suffix:
            raise TalkmeshError(f"{src}: no such folder: give a folder of speech files or a list")
        else:
            check_named(src)
            found.append(Input(src, src.stem))
    seen: set[Path] = set()
    unique = []
    for item in found:
        key = resolved(item.audio)
        if key not in seen:
            seen.add(key)
            unique.append(item)
    return unique


def check_named(path: Path) -> None:
    """Refuse a speech file named on the command line that is missing or empty."""
    if not path.exists():
        raise TalkmeshError(f"audio file not found: {path}: check the path")
    if path.is_file() and path.stat().st_size == 0:
        raise TalkmeshError(f"audio file {path} is empty (0 bytes): re-export or re-record it")


def _folder(folder: Path) -> list[Input]:
    try:
        files = sorted(
            p
            for p in folder.rglob("*")
            if p.suffix.lower() in AUDIO_SUFFIXES
            and not any(part.startswith(".") for part in p.relative_to(folder).parts)
            and p.is_file()
        )
    except OSError as e:
        raise TalkmeshError(os_error_message(e, folder, action="list")) from None
    if not files:
        raise TalkmeshError(
            f"{folder}: no speech files in this folder ({', '.join(sorted(AUDIO_SUFFIXES))}): "
            "check the path"
        )
    return [Input(p, p.relative_to(folder).with_suffix("").as_posix()) for p in files]


def _listed(listing: Path) -> list[Input]:
    if not listing.exists():
        raise TalkmeshError(f"{listing}: no such list: give a text file of speech file paths")
    try:
        text = listing.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise TalkmeshError(
            f"{listing}: not a text file: a list names one speech file per line"
        ) from None
    except OSError as e:
        raise TalkmeshError(os_error_message(e, listing, action="read")) from None
    lines = [ln.strip() for ln in text.splitlines()]
    paths = [ln for ln in lines if ln and not ln.startswith("#")]
    if not paths:
        raise TalkmeshError(f"{listing}: the list names no files: write one speech file per line")
    out = []
    for line in paths:
        p = Path(line).expanduser()
        p = p if p.is_absolute() else listing.parent / p
        out.append(Input(p, p.stem))
    return out
