"""``talkmesh render`` and ``export``: animations to videos (an avatar's own meshes for a .vrm or
an avatar .glb) and to other files."""

from __future__ import annotations

import argparse
from pathlib import Path

from talkmesh.cli.common import Subparsers, add_output_options, check_outputs, load_input
from talkmesh.errors import TalkmeshError
from talkmesh.output import VIDEO_SUFFIXES, output_name, write_animation


def add_render(sub: Subparsers) -> None:
    r = sub.add_parser("render", help="render animations to an mp4 (several: side by side)")
    r.add_argument(
        "anim",
        nargs="+",
        help="animation files (.npz .glb .npy), or one avatar (.vrm, a .glb with a skin or "
        "several meshes: `animate --avatar` output) drawn whole playing its first clip",
    )
    r.add_argument(
        "-o",
        "--output",
        required=True,
        action="append",
        help="output .mp4 (.m4v .mov); repeat for several copies of the one video",
    )
    r.add_argument("--audio", help="speech to mux into the video")
    r.add_argument("--labels", help="comma-separated panel labels for side-by-side")
    r.add_argument("--fps", type=float, help="frame rate of .npy inputs (default 30)")
    add_output_options(r)
    r.set_defaults(func=cmd_render)


def cmd_render(args: argparse.Namespace) -> int:
    from talkmesh.audio.loading import SAMPLE_RATE, load_audio
    from talkmesh.output.atomic import remove_stale_temps, writing
    from talkmesh.output.render import render_side_by_side, render_video

    outs = [Path(o) for o in args.output]
    inputs = [Path(a) for a in args.anim] + ([Path(args.audio)] if args.audio else [])
    check_outputs([outs], inputs, args.overwrite)
    for out in outs:
        if out.suffix.lower() not in VIDEO_SUFFIXES:
            raise TalkmeshError(
                f"{out}: render writes videos ({' '.join(VIDEO_SUFFIXES)}); "
                "`talkmesh export` writes the other formats"
            )
    scene = avatar_input(args.anim)
    anims = [load_input(a, args.fps) for a in args.anim] if scene is None else []
    audio = load_audio(args.audio) if args.audio else None
    if args.audio and anims:
        anims[0].audio, anims[0].sample_rate = audio, SAMPLE_RATE
        anims[0].audio_file = Path(args.audio)  # the video keeps its own rate and channels
    for out in outs:
        with writing(out):
            out.parent.mkdir(parents=True, exist_ok=True)
            remove_stale_temps(out.parent)
    if scene is not None:
        render_avatar(scene, outs, audio, args)
        return 0
    out = outs[0]
    if len(anims) == 1:
        render_video(anims[0], out, size=args.size, progress=not args.quiet, camera=args.camera)
    else:
        labels = args.labels.split(",") if args.labels else [Path(a).stem for a in args.anim]
        if len(labels) != len(anims):
            raise TalkmeshError(
                f"--labels names {len(labels)} panels but {len(anims)} animations were given"
            )
        render_side_by_side(
            anims, labels, out, size=args.size, progress=not args.quiet, camera=args.camera
        )
    for copy in outs[1:]:  # one encode; the other outputs are byte copies of it
        copy_file(out, copy)
    if not args.quiet:
        print(f"wrote {', '.join(map(str, outs))}")
    return 0


def avatar_input(anims: list[str]):
    """The avatar (a .vrm, or a .glb with a skin or several meshes) to render as a whole, or
    None for the animations talkmesh writes; an avatar is rendered alone."""
    from talkmesh.output.avatar import load_avatar_scene
    from talkmesh.output.scene import is_avatar_file

    found = [
        a
        for a in anims
        if Path(a).suffix.lower() == ".vrm"
        or (Path(a).suffix.lower() == ".glb" and is_avatar_file(a))
    ]
    if found and len(anims) > 1:
        raise TalkmeshError(
            f"{found[0]} is an avatar: render draws one avatar at a time, not side by side"
        )
    return load_avatar_scene(found[0]) if found else None


def render_avatar(scene, outs: list[Path], audio, args: argparse.Namespace) -> None:
    """``render AVATAR.glb``: the avatar's own meshes playing its first clip."""
    from talkmesh.output.render import render_avatar_video

    out = outs[0]
    render_avatar_video(
        scene,
        out,
        args.size,
        audio=audio,
        audio_file=args.audio,
        inputs=[*args.anim, *([args.audio] if args.audio else [])],
        progress=not args.quiet,
        camera=args.camera,
    )
    for copy in outs[1:]:
        copy_file(out, copy)
    if not args.quiet:
        print(f"wrote {', '.join(map(str, outs))} ({scene.num_frames} frames of '{scene.clip}')")


def copy_file(src: Path, dst: Path) -> None:
    """``src``'s bytes to ``dst``, written beside it and renamed into place."""
    import shutil

    from talkmesh.output.atomic import writing
    from talkmesh.output.video import atomic_output

    with writing(dst), atomic_output(dst, (dst.suffix.lower(),)) as tmp:
        shutil.copyfile(src, tmp)


def add_export(sub: Subparsers) -> None:
    e = sub.add_parser("export", help="convert an animation to other formats")
    e.add_argument("anim", help="animation file (.npz .glb .npy)")
    e.add_argument(
        "-o",
        "--output",
        required=True,
        action="append",
        help="output file; the extension picks the format; repeat for several",
    )
    e.add_argument("--fps", type=float, help="frame rate of .npy inputs (default 30)")
    add_output_options(e)
    e.set_defaults(func=cmd_export)


def cmd_export(args: argparse.Namespace) -> int:
    src, outs = Path(args.anim), [Path(o) for o in args.output]
    check_outputs([outs], [src], args.overwrite)
    anim = load_input(args.anim, args.fps)
    for out in outs:
        write_animation(anim, out, overwrite=args.overwrite, size=args.size, camera=args.camera)
        if not args.quiet:
            print(f"wrote {output_name(out, anim.num_frames)}")
    return 0
