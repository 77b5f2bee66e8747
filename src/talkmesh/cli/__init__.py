"""``talkmesh`` command line: a thin layer of subcommands over the Python API.

Each subcommand is a pair: ``add_<name>(subparsers)`` declares its arguments and
``cmd_<name>(args)`` calls the library with them; the pairs live in modules by topic
(:mod:`.animate`, :mod:`.data`, :mod:`.models`, :mod:`.serve`). :data:`COMMANDS` lists them in the
order ``talkmesh --help`` shows them: adding a subcommand is one new pair plus one line there.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Callable

from talkmesh.cli.animate import add_animate, add_export_head, add_rig
from talkmesh.cli.common import Subparsers
from talkmesh.cli.data import (
    add_baseline,
    add_evaluate,
    add_predict,
    add_prepare_biwi,
    add_prepare_vocaset,
    add_synth,
)
from talkmesh.cli.models import (
    add_benchmark,
    add_convert_whisper,
    add_dub,
    add_export_onnx,
    add_import_checkpoint,
    add_retarget,
    add_train,
)
from talkmesh.cli.render import add_export, add_render
from talkmesh.cli.serve import add_info, add_livelink, add_serve
from talkmesh.errors import TalkmeshError, os_error_message, show_warnings, warning_line
from talkmesh.version import __version__

COMMANDS: tuple[Callable[[Subparsers], None], ...] = (
    add_animate,
    add_render,
    add_export,
    add_synth,
    add_evaluate,
    add_baseline,
    add_predict,
    add_prepare_biwi,
    add_prepare_vocaset,
    add_convert_whisper,
    add_import_checkpoint,
    add_export_onnx,
    add_train,
    add_benchmark,
    add_retarget,
    add_dub,
    add_rig,
    add_export_head,
    add_serve,
    add_livelink,
    add_info,
)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="talkmesh", description="Speech-driven 3D facial animation.")
    p.add_argument("--version", action="version", version=f"talkmesh {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks for errors")
    sub = p.add_subparsers(dest="command", required=True)
    for add in COMMANDS:
        add(sub)
    return p


_plain_format_warning = warnings.formatwarning


def _format_warning(message, category, filename, lineno, line=None) -> str:
    return warning_line(message, category) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # one line per warning (--debug: Python's own, with the file and line that raised it)
    warnings.formatwarning = _plain_format_warning if args.debug else _format_warning
    show_warnings(every=not args.debug)
    try:
        return int(args.func(args) or 0)
    except TalkmeshError as e:
        if args.debug:
            raise
        print(f"talkmesh: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # the machine's answer (disk full, permission denied): not a bug
        if args.debug:
            raise
        print(f"talkmesh: error: {os_error_message(e, action='use')}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("talkmesh: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # a bug, not bad input: still one line, with a way to see more
        if args.debug:
            raise
        print(
            f"talkmesh: internal error: {type(e).__name__}: {e} (rerun with --debug for the "
            "traceback and please report it)",
            file=sys.stderr,
        )
        return 3
