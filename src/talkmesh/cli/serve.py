"""``talkmesh serve`` (the streaming server) and ``talkmesh info`` (what is installed)."""

from __future__ import annotations

import argparse
import sys

from talkmesh.cli.common import Subparsers, add_quiet
from talkmesh.version import __version__

LIVELINK_HELP = (
    "also send every session's frames as Live Link Face UDP packets to Unreal there (port 11111 "
    "by default; a session names its subject with ?livelink=NAME, or opts out with ?livelink=0)"
)

RUNTIME_HELP = (
    "what runs the learned models: torch (releases) or onnxruntime (.onnx files of export-onnx, "
    "their jobs and streams without torch); default: by the file"
)


def add_serve(sub: Subparsers) -> None:
    sv = sub.add_parser(
        "serve", help="stream face animation over WebSocket and serve the browser viewer"
    )
    sv.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    sv.add_argument("--port", type=int, default=8000, help="port (default 8000; 0: any free port)")
    sv.add_argument(
        "--model",
        action="append",
        help="procedural, a bundled model (codetalker-synth) or a streaming CodeTalker "
        ".safetensors; repeat to offer several, clients pick one by name (default procedural)",
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
    sv.add_argument(
        "--avatar",
        help="a .glb/.vrm with ARKit-named morph targets for the viewer to show instead of the "
        "bundled head",
    )
    limits = (
        ("--max-seconds", float, 300.0, "longest audio POST /animate accepts, from its header"),
        ("--jobs", int, 2, "POST /animate jobs computing at once"),
        ("--max-queue", int, 8, "jobs waiting for a slot; more get 503 + Retry-After"),
        ("--request-timeout", float, 30.0, "seconds to send a request head, then its body"),
        (
            "--first-message-timeout",
            float,
            2.0,
            "seconds from a stream's hello to its first message",
        ),
    )  # docs/security.md
    for flag, kind, default, what in limits:
        sv.add_argument(flag, type=kind, default=default, help=f"{what} (default {default:g})")
    sv.add_argument(
        "--batch-wait-ms",
        type=float,
        default=15.0,  # talkmesh.serve.batching.DEFAULT_BATCH_WAIT_MS (anyio: not imported here)
        help="wait this long after a stream's audio arrives to compute it together with other "
        "streams' (default 15: most sessions' next 20 ms chunk joins the tick; 0: every tick "
        "takes what has arrived)",
    )
    sv.add_argument(
        "--torch-threads",
        type=int,
        help="threads of the batched model steps (default: the server's share of the cores beside "
        "its --workers, at least 1)",
    )
    sv.add_argument(
        "--workers",
        type=int,
        help="processes that compute the procedural sessions (default: one per core; 0: the "
        "server process itself)",
    )
    sv.add_argument("--livelink", metavar="HOST:PORT", help=LIVELINK_HELP)
    sv.add_argument("--runtime", choices=("torch", "onnxruntime"), help=RUNTIME_HELP)
    add_quiet(sv, "log only warnings and errors")
    sv.set_defaults(func=cmd_serve)


def check_serve_runtime(runtime: str | None, models: list[str]) -> None:
    """``--runtime`` must agree with every ``--model``: ONNX Runtime runs .onnx files only,
    torch runs releases (and the procedural animator, which is neither)."""
    from talkmesh.errors import TalkmeshError

    for model in models:
        onnx = model.lower().endswith(".onnx")
        if runtime == "onnxruntime" and not onnx:
            raise TalkmeshError(
                f"--runtime onnxruntime serves .onnx files: export {model} with `talkmesh "
                f"export-onnx {model} -o model.onnx` and pass --model model.onnx"
                if model != "procedural"
                else "--runtime onnxruntime serves .onnx files of export-onnx, and procedural is "
                "not one: pass --model model.onnx (talkmesh export-onnx codetalker-synth -o "
                "model.onnx), or drop --runtime"
            )
        if runtime == "torch" and onnx:
            raise TalkmeshError(
                f"--runtime torch runs releases, not {model}: pass --runtime onnxruntime"
            )


def cmd_serve(args: argparse.Namespace) -> int:
    check_serve_runtime(args.runtime, args.model or ["procedural"])
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
        avatar=args.avatar,
        max_seconds=args.max_seconds,
        jobs=args.jobs,
        max_queue=args.max_queue,
        request_timeout=args.request_timeout,
        first_message_timeout=args.first_message_timeout,
        batch_wait_ms=args.batch_wait_ms,
        torch_threads=args.torch_threads,
        workers=args.workers,
        livelink=args.livelink,
    )
    return 0


def add_livelink(sub: Subparsers) -> None:
    ll = sub.add_parser(
        "livelink",
        help="animate a speech file and send it live to Unreal as Live Link Face packets, with "
        "its audio",
    )
    ll.add_argument("audio", help="speech file")
    ll.add_argument(
        "--to",
        required=True,
        metavar="HOST:PORT",
        help="where Unreal's Live Link Face source listens (port 11111 by default)",
    )
    ll.add_argument(
        "--subject", default="talkmesh", help="the subject name Unreal lists (default talkmesh)"
    )
    ll.add_argument(
        "--model",
        help="a bundled model (default codetalker-synth), procedural, or a .safetensors release",
    )
    ll.add_argument(
        "--no-audio", action="store_true", help="send the frames in real time without playing"
    )
    ll.add_argument("--seed", type=int, default=0, help="seed of blinks and gaze (default 0)")
    ll.add_argument(
        "--head-motion",
        type=float,
        default=0.5,
        metavar="AMOUNT",
        help="how much the head moves with the prosody, 0 to 1 (default 0.5)",
    )
    add_quiet(ll)
    ll.set_defaults(func=cmd_livelink)


def cmd_livelink(args: argparse.Namespace) -> int:
    """Everything that can fail is checked before the first frame: the target, the audio, the
    model; then the frames go out in real time with the audio."""
    import time

    from talkmesh.audio.loading import audio_duration
    from talkmesh.output import livelink as ll
    from talkmesh.pipeline import animate

    target = ll.parse_target(args.to)
    audio_duration(args.audio)  # unreadable audio is refused before the model runs
    with ll.LiveLinkSender(target, args.subject) as sender:
        sender.check()
        anim = animate(args.audio, model=args.model, seed=args.seed, head_motion=args.head_motion)
        lag = 0.0
        if not args.no_audio:
            assert anim.audio is not None
            lag = ll.start_audio(anim.audio, anim.sample_rate)
        if not args.quiet:
            print(
                f"sending {anim.num_frames} frames ({anim.duration:.2f} s at {anim.fps:g} fps) "
                f"to {target} as subject {args.subject}",
                flush=True,
            )
        try:
            played = ll.play_live_link(anim, sender, start=time.perf_counter() + lag)
        finally:
            if not args.no_audio:
                ll.stop_audio()
    if played.refused:
        print(
            f"talkmesh: warning: {played.refused} of {anim.num_frames} frames were refused by "
            f"{target} (nothing listened there then)",
            file=sys.stderr,
        )
    if not args.quiet:
        late = played.late * 1000
        print(
            f"sent {played.sent} frames; sent late by {late.mean():.2f} ms on average, "
            f"{late.max():.2f} ms at most"
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
