"""What several subcommands share: common options, dataset arguments and output paths."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from talkmesh.errors import TalkmeshError, resolved
from talkmesh.output import VIDEO_SIZE, VIDEO_SUFFIXES

Subparsers = argparse._SubParsersAction  # what ``add_subparsers()`` returns
DEFAULT_OUTPUT = "{stem}.mp4"


class Once(argparse.Action):
    """An option that may be given once: a second value is refused (exit 2), never a silent
    last-wins (``rig -o a.glb -o b.glb`` would otherwise write only ``b.glb``)."""

    def __call__(self, parser, namespace, values, option_string=None):
        seen = namespace.__dict__.setdefault("_given_once", set())
        if self.dest in seen:
            parser.error(
                f"{'/'.join(self.option_strings)} given twice ({getattr(namespace, self.dest)} and "
                f"{values}): this command writes one; run it again for another"
            )
        seen.add(self.dest)
        setattr(namespace, self.dest, values)


def add_quiet(sp: argparse.ArgumentParser, text: str = "print nothing but errors") -> None:
    sp.add_argument("-q", "--quiet", action="store_true", help=text)


def add_output_options(sp: argparse.ArgumentParser) -> None:
    """--overwrite, --size and --quiet of the commands that write animations."""
    sp.add_argument("--overwrite", action="store_true", help="replace existing output files")
    sp.add_argument(
        "--size",
        type=int,
        default=VIDEO_SIZE,
        help=f"video size in pixels (default {VIDEO_SIZE})",
    )
    sp.add_argument(
        "--camera",
        choices=("front", "three-quarter"),
        default="front",
        help="video view: front (default) or three-quarter (the head turned 35 degrees)",
    )
    add_quiet(sp)


DATASET_HELP = (
    "dataset kind: vocaset (VOCASET, FLAME meshes at 30 fps), biwi (BIWI after `talkmesh "
    "prepare-biwi`, 25 fps), synth (a `talkmesh synth` corpus) or folder (your own, described "
    "by DATA/splits.json)"
)
SPLIT_HELP = (
    "which sentences: train, val or test (default test); biwi also has test-a (the training "
    "speakers' test sentences, the same as test) and test-b (unseen speakers); synth and folder "
    "datasets name their own splits in manifest.json or splits.json"
)


def add_dataset(sp: argparse.ArgumentParser) -> None:
    """--dataset, --data and --split of the commands that read a dataset split."""
    sp.add_argument("--dataset", required=True, help=DATASET_HELP)
    sp.add_argument("--data", required=True, help="dataset root directory")
    sp.add_argument("--split", default="test", help=SPLIT_HELP)


# ---------------------------------------------------------------------------------------------
# Output paths


def parse_outputs(
    patterns: list[str],
    inputs: list[Path],
    stems: list[str] | None = None,
    default: str = DEFAULT_OUTPUT,
) -> list[list[Path]]:
    """Expand ``-o`` values into output paths per input.

    Each value is a file path (its extension picks the format), a pattern with ``{stem}`` (the
    input's file name without extension, or ``stems[k]`` when given, e.g. ``alice/line001`` for
    a file in a subfolder of an input folder) or a folder: one ending in ``/``, an existing one,
    or a path without an extension that is no file (``-o result``); a folder takes
    ``DIR/{default}`` (``{stem}.mp4``) for each input, and is made when the first file is written.
    """
    stems = stems if stems is not None else [a.stem for a in inputs]
    out: list[list[Path]] = [[] for _ in inputs]
    for pattern in patterns:
        if is_folder(pattern):
            pattern = os.path.join(pattern, default)
        if len(inputs) > 1 and "{stem}" not in pattern:
            if Path(pattern).is_file():
                raise TalkmeshError(
                    f"-o {pattern}: that is a file, not a folder: give a folder for the outputs "
                    "of several inputs (-o out/)"
                )
            raise TalkmeshError(
                f"-o {pattern}: several inputs need a directory (-o out/) or a pattern "
                "with {stem} (-o out/{stem}.glb)"
            )
        for k in range(len(inputs)):
            out[k].append(Path(pattern.replace("{stem}", stems[k])))
    return out


def is_folder(pattern: str) -> bool:
    """Whether an ``-o`` value names a folder: it ends in ``/``, is an existing folder without an
    extension, or has no extension and is neither an existing file nor a ``{stem}`` pattern. An
    existing folder named like a file (``out.npz/``) is refused later as a folder, not filled."""
    path = Path(pattern)
    if pattern.endswith(("/", os.sep)) or (path.is_dir() and not path.suffix):
        return True
    return not path.suffix and "{stem}" not in pattern and not path.exists() and bool(path.name)


def check_folders(outputs: list[list[Path]]) -> None:
    """Refuse outputs whose folder is (or lies under) an existing file, before any work. With
    several inputs this is left to each file's write, so one bad output fails only its file."""
    if len(outputs) > 1:
        return
    checked: set[Path] = set()
    for paths in outputs:
        for p in paths:
            for folder in p.parents:
                if folder in checked:
                    break
                checked.add(folder)
                if folder.exists():
                    if not folder.is_dir():
                        raise TalkmeshError(
                            f"{p}: {folder} is a file, not a folder: choose another -o"
                        )
                    break


def check_outputs(
    outputs: list[list[Path]], inputs: list[Path], overwrite: bool, avatar: bool = False
) -> None:
    """Refuse unknown formats, writing over an input, two writes to one file, and (without
    ``overwrite``) existing files, before any work starts. With ``avatar``, .glb/.vrm outputs
    are copies of the avatar (and videos show the avatar)."""
    from talkmesh.output.avatar import AVATAR_SUFFIXES
    from talkmesh.output.formats import EXPORTERS

    known = set(EXPORTERS) | set(VIDEO_SUFFIXES)
    if avatar:
        known |= set(AVATAR_SUFFIXES)
    check_folders(outputs)
    resolved_inputs = {resolved(p) for p in inputs}
    seen: set[Path] = set()
    for paths in outputs:
        for p in paths:
            suffix = p.suffix.lower()
            if suffix not in known:
                raise TalkmeshError(
                    f"{p}: unknown output format '{suffix or '(none)'}': "
                    f"use one of {', '.join(sorted(known))}"
                )
            r = resolved(p)
            if r in resolved_inputs:
                raise TalkmeshError(f"{p}: refusing to write over an input file")
            if r in seen:
                raise TalkmeshError(f"{p}: two inputs would write the same output file")
            seen.add(r)
            if p.is_dir():
                raise TalkmeshError(
                    f"{p} is a folder: give a file name (-o {p / ('talk' + suffix)}) or another -o"
                )
            if p.exists() and not overwrite:
                raise TalkmeshError(f"{p} already exists: choose another -o or pass --overwrite")


def load_input(path: str, fps: float | None):
    from talkmesh.output.formats import load_animation

    return load_animation(Path(path), fps=fps)


def check_writable(path: Path, what: str) -> None:
    """Refuse ``path`` (``what``: the option that names it) when no file can be written there:
    its folder is made if missing and a probe file is written and removed (and the folders made
    for it), so a read-only or full folder is found before any work rather than after it."""
    import tempfile

    from talkmesh.errors import os_error_message

    if path.is_dir():
        raise TalkmeshError(f"{what} {path} is a folder: give a file name")
    missing = [p for p in [path.parent, *path.parent.parents] if not p.exists()]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=".talkmesh-probe-"):
            pass
    except OSError as e:
        raise TalkmeshError(
            f"{what} {os_error_message(e, path.parent, action='write in')}"
        ) from None
    finally:  # folders made for the probe go again: a later refusal leaves nothing behind
        for folder in missing:
            try:
                folder.rmdir()
            except OSError:
                pass
