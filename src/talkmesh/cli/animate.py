"""``talkmesh animate``, ``rig`` and ``export-head``: speech to animations, a plain head mesh to a
rigged .glb, the bundled head as a mesh (``render`` and ``export``: :mod:`talkmesh.cli.render`)."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from talkmesh.cli.common import (
    DEFAULT_OUTPUT,
    Once,
    Subparsers,
    add_output_options,
    add_quiet,
    check_outputs,
    check_writable,
    parse_outputs,
)
from talkmesh.constants import INT8_LAYERS
from talkmesh.errors import TalkmeshError
from talkmesh.face.corrections import (
    BILABIAL,
    GAIN,
    LIP_CLOSURE,
    MIX,
    PAUSE_SOURCE,
    PAUSE_SOURCES,
)
from talkmesh.face.head_motion import NATURAL, check_amount
from talkmesh.models.runtime import RUNTIMES, check_runtime
from talkmesh.output import VIDEO_SUFFIXES, output_name

RUNTIME_HELP = (
    "what runs a learned model: auto (default: ONNX Runtime for an .onnx file and for the "
    "bundled model, whose graphs are exported once into the cache folder; torch otherwise), "
    "torch, or onnxruntime (an .onnx file, or a CodeTalker release exported once)"
)


def add_animate(sub: Subparsers) -> None:
    a = sub.add_parser("animate", help="animate a face from speech files, folders or lists")
    a.add_argument(
        "audio",
        nargs="+",
        help="speech files (wav, flac, ogg, mp3, ...), folders of them (searched recursively) "
        "or text files listing them (.txt .lst, one path a line)",
    )
    a.add_argument(
        "-o",
        "--output",
        action="append",
        help="output file; the extension picks the format (.mp4 .glb .npy .npz .obj .csv .json, "
        ".visemes.json: Oculus and Azure visemes); "
        "repeat for several; {stem} is the input name (default {stem}.mp4); a folder (out/, or "
        "a name without an extension: out) takes {stem}.mp4 for each input, mirroring the "
        "subfolders of an input folder",
    )
    who = a.add_mutually_exclusive_group()
    who.add_argument("--identity", help="a bundled identity (see `talkmesh info`)")
    who.add_argument(
        "--template",
        help="your own neutral face (.obj .ply .npy): the bundled topology, or a learned model's "
        "own with its triangles (VOCASET: templates.pkl[:SUBJECT] beside FLAME_sample.ply; "
        "BIWI: BIWI.ply, a .vl frame or a rigid scan .obj)",
    )
    who.add_argument(
        "--head",
        help="your own head mesh without a rig (.obj .ply .stl .off .glb .gltf, any units and "
        "up-axis): registered to the bundled head and moved as the model moves it, outputs in "
        "the mesh's own units and axes (as `talkmesh rig` finds them)",
    )
    a.add_argument(
        "--normalize-template",
        action="store_true",
        help="rotate, centre and rescale a BIWI-topology --template as prepare-biwi does (done "
        "without asking only for BIWI's raw files: a .vl frame, rigid_scans/SUBJECT.obj)",
    )
    a.add_argument(
        "--avatar",
        help="your rigged character (.glb .vrm with ARKit-named morph targets, VRM presets or "
        "Oculus visemes): .glb/.vrm outputs are copies of it with the speech as one animation "
        "clip, videos show it playing that clip",
    )
    a.add_argument(
        "--text",
        help="transcript of the speech (forced alignment instead of recognition); [happy] or "
        "[sad:0.5] tags before a word set the emotion from there on",
    )
    _add_performance(a)
    a.add_argument("--seed", type=int, default=0, help="seed of blinks and other free motion")
    a.add_argument("--fps", type=float, help="frames per second (default: the model's own)")
    a.add_argument(
        "--model",
        default=None,
        help="a bundled model (default codetalker-synth), procedural, a .safetensors release, or "
        "an .onnx file of export-onnx (run by ONNX Runtime)",
    )
    a.add_argument("--runtime", choices=RUNTIMES, default="auto", help=RUNTIME_HELP)
    a.add_argument(
        "--style", help="learned models: speaker mix, e.g. A:0.7,B:0.3 (default: all alike)"
    )
    a.add_argument(
        "--no-blinks",
        action="store_true",
        help="learned models: keep the model's own eye motion instead of procedural blinks and "
        "gaze (speech cannot predict them)",
    )
    _add_corrections(a)
    a.add_argument(
        "--int8",
        choices=INT8_LAYERS,
        help="CodeTalker models: run the speech encoder, the decoders or both in int8 "
        "(faster on CPUs, not exact: see docs/results/codetalker.md)",
    )
    add_batch_options(a)
    add_output_options(a)
    a.set_defaults(func=cmd_animate)


def _add_performance(a) -> None:
    """The options of the emotion (talkmesh.face.performance)."""
    a.add_argument(
        "--emotion",
        metavar="MIX",
        help="the emotion of the whole clip: neutral happy sad angry surprised fearful disgusted, "
        "with intensities 0 to 1 and mixes, e.g. happy:0.6,surprised:0.2 (default neutral)",
    )
    a.add_argument(
        "--head-motion",
        type=float,
        default=NATURAL,
        metavar="AMOUNT",
        help="how much the head nods, turns and tilts with the speech's prosody, 0 (still) to 1 "
        f"(lively); default {NATURAL:g}, a natural amount (the bundled head's topology)",
    )
    a.add_argument(
        "--performance",
        metavar="JSON",
        help="an emotion timeline: a JSON list of spans {start, end, emotion, intensity, onset, "
        "offset} (seconds; docs/guide/performance.md)",
    )


def performance_from(args: argparse.Namespace):
    """``--emotion`` and ``--performance`` as a :class:`Performance` (None: neutral)."""
    from talkmesh.face.performance import Performance, parse_emotion, read_performance

    base = parse_emotion(args.emotion) if args.emotion else {}
    if args.performance:
        return read_performance(args.performance, base)
    return Performance(base) if base else None


def _add_corrections(a) -> None:
    """The options of the mouth corrections of learned models (talkmesh.face.corrections)."""
    a.add_argument(
        "--no-pause-gate",
        action="store_true",
        help="learned models: keep the model's mouth in pauses instead of closing it where "
        "nobody speaks",
    )
    a.add_argument(
        "--pause-source",
        choices=PAUSE_SOURCES,
        default=PAUSE_SOURCE,
        help="learned models: where the pause gate finds pauses: vad (voice activity, any "
        "language; default) or recognizer (the English phone recogniser's silences)",
    )
    a.add_argument(
        "--lip-closure",
        action=argparse.BooleanOptionalAction,
        default=LIP_CLOSURE,
        help="learned models: shut the lips (met) where the model's lips dip nearly closed in "
        "speech (default on; any language)",
    )
    a.add_argument(
        "--procedural-mix",
        type=float,
        default=MIX,
        metavar="SHARE",
        help="learned models: share of the procedural animator's mouth mixed into the model's "
        f"outside its lip closures, 0 to 1 (default {MIX:g}; 0 turns it off)",
    )
    a.add_argument(
        "--bilabial-closure",
        action=argparse.BooleanOptionalAction,
        default=BILABIAL,
        help="learned models: shut the lips where the model nearly closes them by a /p b m/ "
        "the English phone recogniser finds (default off: --lip-closure does it in any language)",
    )
    a.add_argument(
        "--loudness-gain",
        type=float,
        default=GAIN,
        metavar="GAIN",
        help="learned models: how much further the loudest speech opens the model's mouth, 0 to "
        f"2 (default {GAIN:g}; 0 turns it off)",
    )


def add_batch_options(a: argparse.ArgumentParser) -> None:
    a.add_argument(
        "--workers",
        type=int,
        default=None,
        help="processes animating files at once, each loading the model once (default 1; with "
        "--cluster, one per CPU of the cluster)",
    )
    a.add_argument(
        "--cluster",
        metavar="ADDRESS",
        help="run the files on a Ray cluster: HOST:PORT of its head (`ray start --head`), "
        "ray://HOST:PORT, auto, or local for one on this machine (docs/guide/scale.md)",
    )
    a.add_argument(
        "--summary",
        metavar="CSV",
        action=Once,
        help="write a row per file (file, duration, frames, seconds, status, error); default "
        "summary.csv in the output folder when an input is a folder or a list",
    )


def cmd_animate(args: argparse.Namespace) -> int:
    """Folders and lists are a library: files whose outputs exist are skipped (the run resumes)
    and a summary CSV is written; files named one by one refuse existing outputs as before."""
    from talkmesh.batch import animate_batch, find_inputs, is_batch_source, write_summary
    from talkmesh.batch.summary import read_summary, with_earlier
    from talkmesh.heap import fix_mmap_threshold

    fix_mmap_threshold()  # flat memory on long audio (talkmesh.heap)
    from talkmesh.pipeline import check_fps_seed, parse_style

    check_fps_seed(args.fps, args.seed)  # refused before any file is looked at
    if args.text:
        from talkmesh.face.performance import split_tags

        split_tags(args.text)  # a bad tag is refused before any file is looked at
    performance_from(args)
    check_amount(args.head_motion)
    check_runtime(args.runtime, args.model, args.int8)
    style_mix = parse_style(args.style)
    sources = [Path(a) for a in args.audio]
    library = any(is_batch_source(p) for p in sources)
    found = find_inputs(sources)
    inputs = [f.audio for f in found]
    if len(inputs) == 1 and not library:  # one file: unreadable audio is refused before the model
        from talkmesh.audio.loading import audio_duration

        audio_duration(inputs[0])  # its header only (a batch reports such files row by row)
    avatar = Path(args.avatar) if args.avatar else None
    default = DEFAULT_OUTPUT if avatar is None else "{stem}" + avatar.suffix.lower()
    outputs = parse_outputs(args.output or [default], inputs, [f.stem for f in found], default)
    resume = library and not args.overwrite  # existing outputs are done files, not conflicts
    check_outputs(
        outputs, inputs + ([avatar] if avatar else []), args.overwrite or resume, bool(avatar)
    )
    if args.workers is not None and args.workers < 1:
        raise TalkmeshError(f"--workers {args.workers}: give 1 or more")
    summary = Path(args.summary) if args.summary else (summary_path(outputs) if library else None)
    if summary is not None:
        check_writable(summary, "--summary")  # before any file is animated
    if args.cluster:
        from talkmesh.batch.cluster import check_reachable

        check_reachable(args.cluster)
    if avatar is not None:
        check_avatar(avatar, outputs, args.quiet)
    _face(args, style_mix, outputs, avatar)  # what cannot work fails before any run
    bar, say = progress(len(inputs), args.quiet)
    written = {str(a): paths for a, paths in zip(inputs, outputs)}

    def on_row(row) -> None:
        if bar is not None:
            bar.update()
        if row.status == "ok" and not args.quiet:
            names = ", ".join(output_name(p, row.frames) for p in written[row.file])
            note = f"; {row.note}" if row.note else ""
            say(f"wrote {names} ({row.frames} frames, {row.duration:.2f} s{note})")

    try:
        with exit_on_sigterm():  # `timeout`, systemd, `docker stop`: the workers stop too
            result = animate_batch(
                inputs,
                outputs,
                animate_settings(args, triangles=needs_triangles(outputs)),
                workers=args.workers or (None if args.cluster else 1),
                cluster=args.cluster,
                on_row=on_row,
            )
    finally:
        if bar is not None:
            bar.close()
    if summary is not None:
        write_summary(summary, with_earlier(result.rows, read_summary(summary)))
    return report_batch(result, summary, args.quiet)


def check_avatar(avatar: Path, outputs: list[list[Path]], quiet: bool) -> None:
    """What the avatar cannot do fails before the model runs: no shapes to drive, or (for a
    video) meshes the renderer cannot draw; else one line says what it drives."""
    from talkmesh.output.avatar import bind_avatar, read_glb
    from talkmesh.output.scene import load_scene

    gltf, binary = read_glb(avatar)
    binding = bind_avatar(gltf, str(avatar))
    if any(p.suffix.lower() in VIDEO_SUFFIXES for paths in outputs for p in paths):
        load_scene(gltf, binary, str(avatar))
    if not quiet:
        print(f"avatar {avatar}: {binding.summary()}")


def progress(files: int, quiet: bool):
    """A progress bar over ``files`` (None for one file or ``quiet``) and how to print a line
    beside it; tqdm is imported only when there is a bar to show."""
    if quiet or files < 2:
        return None, print
    from tqdm import tqdm

    return tqdm(total=files, unit="file"), tqdm.write


@contextmanager
def exit_on_sigterm() -> Iterator[None]:
    """SIGTERM as SystemExit(143) in the main thread, so that ``finally`` blocks run (a batch
    stops its worker processes, temporaries are removed) instead of the process vanishing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _face(args: argparse.Namespace, style_mix, outputs: list[list[Path]], avatar: Path | None):
    """The face to animate: ``--template`` on any topology (a templates.pkl without :SUBJECT
    takes the subject --style names alone) or a bundled identity; a template of another topology
    than the bundled head's is refused with the bundled models and for ARKit outputs."""
    from talkmesh.datasets.templates import read_face_template
    from talkmesh.face.assets import load_head
    from talkmesh.pipeline import available_models

    if args.head:
        if avatar is not None:
            raise TalkmeshError("--head and --avatar: give one (a plain mesh or a rigged avatar)")
        from talkmesh.face.rig_files import load_rig

        rig = load_rig(args.head)  # registered once: forked workers share it
        if not args.quiet:
            print(
                f"head {args.head}: {len(rig.vertices)} vertices, units {rig.units}, up "
                f"{rig.up_axis}, registered within {rig.residual:.3g} (median, its units)"
            )
        return load_head()
    if not args.template:
        return load_head(args.identity)
    alone = next(iter(style_mix)) if style_mix and len(style_mix) == 1 else None
    if args.normalize_template and not args.template:
        raise TalkmeshError("--normalize-template applies to a --template")
    head, note = read_face_template(
        args.template,
        subject=alone,
        triangles=needs_triangles(outputs),
        normalize=args.normalize_template,
    )
    if note and not args.quiet:
        print(f"template {args.template}: {note}")
    if head.rigged:
        return head
    if args.model is None or args.model in available_models():
        raise TalkmeshError(
            f"{args.template}: {head.num_vertices} vertices, not the bundled head's "
            f"{load_head().num_vertices}: the procedural animator and the bundled models "
            "animate the bundled topology; pass --model FILE.safetensors of this topology"
        )
    if needs_arkit(outputs, avatar):  # rigged now (once per mesh, then saved): fails here
        import time

        from talkmesh.face.solve import solver_for_mesh

        start = time.perf_counter()
        solver_for_mesh(head.template, head.faces, f"{args.template} ({head.name})")
        if not args.quiet:
            print(
                f"template {head.name}: {head.num_vertices} vertices, not the bundled topology: "
                "ARKit weights solved from the model's motion through the 52 shapes rigged "
                f"onto it ({time.perf_counter() - start:.1f} s; the registration is saved)"
            )
    elif not args.quiet:
        print(
            f"template {head.name}: {head.num_vertices} vertices, {len(head.faces)} triangles "
            "(not the bundled topology: the model's motion as it is, no ARKit weights)"
        )
    return head


def needs_arkit(outputs: list[list[Path]], avatar: Path | None) -> bool:
    """Whether any output needs ARKit weights (.csv, .json, an avatar's copy)."""
    from talkmesh.output.avatar import AVATAR_SUFFIXES
    from talkmesh.output.streaming import WEIGHT_SUFFIXES

    suffixes = WEIGHT_SUFFIXES + (AVATAR_SUFFIXES if avatar is not None else ())
    return any(p.suffix.lower() in suffixes for paths in outputs for p in paths)


VERTEX_ONLY = (".npy", ".npz")  # outputs that need no triangles (they store them when known)


def needs_triangles(outputs: list[list[Path]]) -> bool:
    """Whether any output draws or exports a surface (a video, .glb, .obj)."""
    return any(p.suffix.lower() not in VERTEX_ONLY for paths in outputs for p in paths)


def animate_settings(args: argparse.Namespace, *, triangles: bool = True):
    """The options of ``talkmesh animate`` as :class:`talkmesh.batch.AnimateSettings`."""
    from talkmesh.batch import AnimateSettings
    from talkmesh.pipeline import default_model, parse_style

    model = args.model or ("procedural" if args.text is not None else default_model())
    return AnimateSettings(
        model=model,
        identity=args.identity,
        template=args.template,
        avatar=args.avatar,
        head=args.head,
        text=args.text,
        fps=args.fps,
        seed=args.seed,
        style_mix=parse_style(args.style),
        blinks=not args.no_blinks,
        pause_gate=not args.no_pause_gate,
        lip_closure=args.lip_closure,
        procedural_mix=args.procedural_mix,
        loudness_gain=args.loudness_gain,
        bilabial_closure=args.bilabial_closure,
        pause_source=args.pause_source,
        performance=performance_from(args),
        head_motion=args.head_motion,
        int8=args.int8,
        runtime=args.runtime,
        size=args.size,
        camera=args.camera,
        overwrite=args.overwrite,
        triangles=triangles,
        normalize_template=args.normalize_template,
    )


def summary_path(outputs: list[list[Path]]) -> Path:
    """``summary.csv`` in the folder that holds every output."""
    folders = [str(p.parent.absolute()) for paths in outputs for p in paths]
    return Path(os.path.commonpath(folders)) / "summary.csv"


def report_batch(result, summary: Path | None, quiet: bool) -> int:
    """Each failure on a line of its own, then a summary line; 1 when any file failed."""
    failed = result.failed
    for r in failed:
        print(f"talkmesh: error: {r.error}", file=sys.stderr)
    skipped = sum(r.status == "skipped" for r in result.rows)
    done = len(result.rows) - skipped - len(failed)
    where = f"; summary {summary}" if summary is not None else ""
    if failed:
        print(
            f"talkmesh: {len(failed)} of {len(result.rows)} files failed ({done} animated, "
            f"{skipped} already done){where}",
            file=sys.stderr,
        )
    elif not quiet and (len(result.rows) > 1 or summary is not None):
        print(f"animated {done} files in {result.seconds:.1f} s ({skipped} already done){where}")
    return 1 if failed else 0


def add_rig(sub: Subparsers) -> None:
    rg = sub.add_parser("rig", help="give a plain head mesh the 52 ARKit blendshapes (.glb out)")
    rg.add_argument(
        "mesh", help="a head mesh (.obj .ply .stl .off .glb .gltf), any units and up-axis"
    )
    rg.add_argument(
        "-o", "--output", required=True, action=Once, help="output .glb (use it with --avatar)"
    )
    rg.add_argument(
        "--landmarks",
        metavar="FILE",
        help='landmark vertex ids of your mesh as JSON {"nose_tip": 1234, ...}, overriding the '
        "automatic ones (names: nose_tip chin upper_lip lower_lip mouth_left mouth_right "
        "eyelid_left eyelid_right brow_left brow_right eye_inner_left eye_outer_left "
        "eye_inner_right eye_outer_right)",
    )
    rg.add_argument(
        "--landmark",
        action="append",
        default=[],
        metavar="NAME=VERTEX_ID",
        help="one landmark vertex id (repeatable; wins over --landmarks)",
    )
    rg.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_quiet(rg)
    rg.set_defaults(func=cmd_rig)


def cmd_rig(args: argparse.Namespace) -> int:
    from talkmesh.face.rig import read_landmarks, rig_head
    from talkmesh.face.rig_files import load_mesh, save_registration
    from talkmesh.heap import fix_mmap_threshold
    from talkmesh.output.formats import save_animation

    fix_mmap_threshold()  # a dense mesh's blockwise carry frees what it took (talkmesh.heap)

    out = Path(args.output)
    if out.suffix.lower() != ".glb":
        raise TalkmeshError(f"{out}: the rigged head is written as .glb")
    if out.exists() and not args.overwrite:
        raise TalkmeshError(f"{out} already exists: choose another -o or pass --overwrite")
    landmarks = read_landmarks(args.landmarks) if args.landmarks else {}
    for item in args.landmark:
        name, _, index = item.partition("=")
        if not index.strip().isdigit():
            raise TalkmeshError(f"--landmark {item}: give NAME=VERTEX_ID, e.g. nose_tip=1234")
        landmarks[name.strip()] = int(index)
    try:
        rig = rig_head(*load_mesh(args.mesh), landmarks=landmarks)
    except TalkmeshError as e:
        message = str(e)
        raise TalkmeshError(
            message if args.mesh in message else f"{args.mesh}: {message}"
        ) from None
    # no clip: a one-key still clip would be the first one viewers play
    save_animation(rig.neutral_animation(), out, format="rig.glb", overwrite=args.overwrite)
    save_registration(args.mesh, rig)  # `animate --head` on the same file reads it back
    if not args.quiet:
        parts = ", ".join(f"{n} {k}" for k, n in rig.parts.items()) or "none"
        print(
            f"wrote {out}: 52 ARKit morph targets on {len(rig.vertices)} vertices (units "
            f"{rig.units}, up {rig.up_axis}, fit within {rig.residual:.3g} {rig.units} median; "
            f"separate parts following rigidly: {parts})"
        )
    return 0


def add_export_head(sub: Subparsers) -> None:
    eh = sub.add_parser(
        "export-head",
        help="write the bundled head's neutral mesh (.obj): a mesh to try `rig` and --template on",
    )
    eh.add_argument(
        "-o", "--output", required=True, action=Once, help="output .obj (or .npy: vertices only)"
    )
    eh.add_argument(
        "--identity", help="a bundled identity (see `talkmesh info`; default: the default one)"
    )
    eh.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_quiet(eh)
    eh.set_defaults(func=cmd_export_head)


def cmd_export_head(args: argparse.Namespace) -> int:
    from talkmesh.face.assets import load_head
    from talkmesh.output.head_mesh import write_head_mesh

    head = load_head(args.identity)
    out = write_head_mesh(head, args.output, overwrite=args.overwrite)
    if not args.quiet:
        print(
            f"wrote {out}: identity {head.name}, {head.num_vertices} vertices, "
            f"{len(head.faces)} triangles (metres, +y up)"
        )
    return 0
