"""Dataset subcommands: ``synth``, ``evaluate``, ``baseline``, ``predict``, ``prepare-biwi``,
``prepare-vocaset``."""

from __future__ import annotations

import argparse
from pathlib import Path

from talkmesh.cli.common import Once, Subparsers, add_dataset, add_quiet
from talkmesh.errors import TalkmeshError


def add_synth(sub: Subparsers) -> None:
    sy = sub.add_parser("synth", help="make a multi-speaker synthetic talking-face corpus")
    sy.add_argument("--out", required=True, action=Once, help="output directory (VOCASET layout)")
    sy.add_argument("--subjects", type=int, default=12, help="number of speakers (default 12)")
    sy.add_argument(
        "--sentences",
        type=int,
        default=None,
        help="sentences per speaker (default 40; with --multilingual, utterances per voice, 12)",
    )
    sy.add_argument("--seed", type=int, default=0, help="seed (same seed, same bytes)")
    sy.add_argument("--workers", type=int, help="processes (default: all cores)")
    sy.add_argument("--overwrite", action="store_true", help="write into a non-empty directory")
    sy.add_argument(
        "--multilingual",
        action="store_true",
        help="the multilingual corpus: every voice of talkmesh.audio.languages (MBROLA, "
        "espeak-ng's own and Festival voices, 30 languages; held-out voices and never-trained "
        "languages make the test split), motion "
        "truth from the teacher (lips met through /p b m/, rest in pauses)",
    )
    sy.add_argument(
        "--languages", default="", help="with --multilingual: comma-separated codes (default all)"
    )
    sy.add_argument(
        "--engines",
        default="",
        help="with --multilingual: comma-separated engines among mbrola, espeak-lib, festival "
        "(default all; mbrola,espeak-lib: the corpus before Festival's voices came)",
    )
    add_quiet(sy)
    sy.set_defaults(func=cmd_synth)


def cmd_synth(args: argparse.Namespace) -> int:
    from talkmesh.datasets.synth import make_corpus

    if args.multilingual:
        from talkmesh.datasets.multilingual import make_multilingual_corpus

        languages = [c for c in args.languages.split(",") if c] or None
        info = make_multilingual_corpus(
            Path(args.out),
            utterances_per_voice=args.sentences or 12,
            languages=languages,
            engines=[e for e in args.engines.split(",") if e] or None,
            seed=args.seed,
            workers=args.workers,
            progress=not args.quiet,
            overwrite=args.overwrite,
        )
        if not args.quiet:
            print(f"wrote {info}")
        return 0
    if args.languages or args.engines:
        raise TalkmeshError("--languages and --engines need --multilingual")
    info = make_corpus(
        Path(args.out),
        subjects=args.subjects,
        sentences=40 if args.sentences is None else args.sentences,
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
    add_dataset(ev)
    ev.add_argument(
        "--pred", required=True, help="directory of <SUBJECT>_<SENTENCE>[_condition_<STYLE>].npy"
    )
    ev.add_argument("--protocol", choices=("codetalker", "physical"), default="codetalker")
    ev.add_argument("--regions", help="directory with lve.txt and fdd.txt (default: the dataset's)")
    ev.add_argument("--json", action=Once, help="also write the scores here")
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
    add_dataset(bl)
    bl.add_argument(
        "--method",
        choices=("static", "procedural"),
        required=True,
        help="static: every frame is the subject's neutral template (the floor any model must "
        "beat); procedural: phones recognised from the audio drive talkmesh's procedural lip "
        "sync on the subject's head (needs blendshapes: a synth corpus, whose manifest.json "
        "names a talkmesh identity per subject)",
    )
    bl.add_argument(
        "-o", "--out", required=True, action=Once, help="output directory for the .npy predictions"
    )
    add_quiet(bl)
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
    add_dataset(pr)
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
    pr.add_argument(
        "--pause-gate",
        action="store_true",
        help="close the mouth in the pauses the phone recogniser finds (the pause gate alone)",
    )
    pr.add_argument(
        "--corrections",
        action="store_true",
        help="correct the mouth with the phone recogniser as animate does by default (pause gate, "
        "procedural mix, loudness gain, bilabial closure)",
    )
    pr.add_argument("-o", "--out", required=True, action=Once, help="output directory")
    add_quiet(pr)
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
        pause_gate=args.pause_gate,
        corrections=args.corrections,
        progress=not args.quiet,
    )
    if not args.quiet:
        print(f"wrote {n} predictions to {args.out}")
    return 0


def add_prepare_biwi(sub: Subparsers) -> None:
    pb = sub.add_parser(
        "prepare-biwi", help="CodeTalker's BIWI preprocessing into the VOCASET layout"
    )
    pb.add_argument("raw", help="BIWI's release (faces/, rigid_scans/, videos/) or raw .npy")
    pb.add_argument("out", help="output dataset directory (re-running skips finished files)")
    pb.add_argument(
        "--subset",
        choices=("all", "biwi6"),
        default="all",
        help="all 14 speakers, or biwi6: F2 F3 F4 M3 M4 M5 (train/val/Test-A)",
    )
    pb.add_argument("--regions", help="CodeTalker's BIWI/regions folder (lve.txt, fdd.txt)")
    add_quiet(pb)
    pb.set_defaults(func=cmd_prepare_biwi)


def cmd_prepare_biwi(args: argparse.Namespace) -> int:
    from talkmesh.datasets.biwi import REGIONS_HINT, prepare_biwi, prepare_biwi_release

    raw, out = Path(args.raw), Path(args.out)
    if not (raw / "faces").is_dir():  # the older layout of per-sequence .npy files
        n = prepare_biwi(raw, out, progress=not args.quiet)
        if not args.quiet:
            print(f"wrote {n} sequences to {args.out}")
        return 0
    done = prepare_biwi_release(
        raw, out, subset=args.subset, regions=args.regions, progress=not args.quiet
    )
    if done.written + done.existing == 0:
        raise TalkmeshError(f"{raw / 'faces'}: no sequence could be prepared (see the warnings)")
    if not args.quiet:
        print(f"wrote {done.written} sequences to {out} ({done.existing} already there)")
        if done.skipped:
            print(f"{len(done.skipped)} sequences skipped: {', '.join(done.skipped)}")
        if not (out / "regions" / "lve.txt").is_file():
            print(REGIONS_HINT)
    return 0


def add_prepare_vocaset(sub: Subparsers) -> None:
    pv = sub.add_parser(
        "prepare-vocaset",
        help="VOCASET's release files (data_verts.npy, pickles) into the VOCASET layout",
    )
    pv.add_argument("raw", help="directory with data_verts.npy, raw_audio_fixed.pkl, ...")
    pv.add_argument("out", help="output dataset directory (re-running skips finished files)")
    add_quiet(pv)
    pv.set_defaults(func=cmd_prepare_vocaset)


def cmd_prepare_vocaset(args: argparse.Namespace) -> int:
    from talkmesh.datasets.vocaset import missing_pairs, prepare_vocaset

    written, skipped = prepare_vocaset(Path(args.raw), Path(args.out), progress=not args.quiet)
    if not args.quiet:
        print(f"wrote {written} files to {args.out} ({skipped} already there, skipped)")
        missing = missing_pairs(args.out)
        if missing:
            print(
                f"{len(missing)} sequences of the standard splits have no motion or audio "
                f"(e.g. {missing[0]}); readers skip them"
            )
    return 0
