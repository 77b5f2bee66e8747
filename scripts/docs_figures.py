"""Make the figures in docs/images/: regions on the mesh, lip opening on a real clip, a contact sheet.

python scripts/docs_figures.py regions          # docs/images/regions.png
python scripts/docs_figures.py lipsync [CLIP]   # docs/images/lipsync_<clip>.png and contact_<clip>.png
python scripts/docs_figures.py multilingual NAME --corpus corpus/multilingual --model M   # one clip
python scripts/docs_figures.py avatars          # docs/images/avatar-kinds.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402

from talkmesh.face.assets import lip_opening, load_head  # noqa: E402

DOCS = Path(__file__).resolve().parents[1] / "docs" / "images"
LIBRIVOX = Path("/usr/share/pocketsphinx/test/data/librivox")


def save_small(fig, out: Path) -> None:
    """Save a figure as a palette PNG (docs images stay small)."""
    from talkmesh.evaluation.benchmark import save_png

    save_png(fig, out)
    plt.close(fig)
    print(f"wrote {out} ({out.stat().st_size // 1024} KB)")


def draw_mesh(ax, verts: np.ndarray, faces: np.ndarray, values: np.ndarray, cmap: str) -> None:
    """Front view of a mesh, triangles shaded by a per-vertex value times a Lambert term."""
    tri = verts[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12
    visible = normals[:, 2] > 0
    order = np.argsort(tri[:, :, 2].mean(1))  # painter's algorithm, back to front
    order = order[visible[order]]
    light = np.clip(normals[order] @ np.array([0.3, 0.4, 0.87]), 0.15, 1)
    colours = plt.get_cmap(cmap)(values[faces[order]].mean(1))
    colours[:, :3] *= light[:, None]
    ax.add_collection(PolyCollection(tri[order, :, :2], facecolors=colours, edgecolors="none"))
    ax.set_xlim(verts[:, 0].min(), verts[:, 0].max())
    ax.set_ylim(verts[:, 1].min(), verts[:, 1].max())
    ax.set_aspect("equal")
    ax.axis("off")


def regions_figure(out: Path) -> None:
    head = load_head()
    r, v = head.regions, head.template
    front = v[:, 2] > -0.01
    crop = v.copy()
    crop[~front] = v[front].mean(0)  # keep the back of the head out of the frame

    def mask(idx):
        m = np.zeros(len(v))
        m[idx] = 1
        return m

    panels = [
        ("lips (LVE)", mask(r.lips), "Reds"),
        ("upper face (FDD)", mask(r.upper_face), "Blues"),
        ("eyelids", mask(r.eyelids), "Greens"),
        ("soft mouth map", r.mouth_weight, "magma"),
        ("soft upper-face map", r.upper_weight, "viridis"),
    ]
    fig, axes = plt.subplots(1, len(panels), figsize=(3 * len(panels), 3.6), dpi=80)
    for ax, (title, values, cmap) in zip(axes, panels):
        draw_mesh(ax, crop, head.faces, 0.2 + 0.8 * values, cmap)
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    save_small(fig, out)


def lipsync_figure(
    clip: Path, text: str | None, out_plot: Path, out_sheet: Path, model: str = "procedural"
) -> None:
    from talkmesh.output.render import contact_sheet
    from talkmesh.pipeline import animate

    anim = animate(clip, text=text, model=model)
    head = load_head()
    opening = lip_opening(anim.vertices, head.regions) * 1000
    from talkmesh.audio.loading import load_audio
    from talkmesh.audio.phonemes import recognize_phones

    phones = recognize_phones(load_audio(clip), text=text)
    t = np.arange(anim.num_frames) / anim.fps
    fig, ax = plt.subplots(figsize=(12, 3.2), dpi=80)
    ax.plot(t, opening, color="k", lw=1.2, label="lip opening (mm)")
    for p in phones:
        if p.label in ("P", "B", "M"):
            ax.axvspan(p.start, p.end, color="tab:red", alpha=0.3, lw=0)
        elif p.label in ("AA", "AE", "AH", "AO", "AW", "AY"):
            ax.axvspan(p.start, p.end, color="tab:blue", alpha=0.15, lw=0)
        if p.label != "SIL":
            ax.text(
                (p.start + p.end) / 2,
                opening.max() * 1.02,
                p.label,
                fontsize=6,
                ha="center",
                rotation=90,
            )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("mm")
    ax.set_title(
        f"{clip.name} ({model}): lip opening; red = /p b m/, blue = open vowels "
        f"({'aligned to transcript' if text else 'recognised'} phones)"
    )
    ax.set_xlim(0, t[-1])
    fig.tight_layout()
    save_small(fig, out_plot)
    contact_sheet(anim, out_sheet, n=8, cols=4, size=192)
    print(f"wrote {out_sheet}")


def multilingual_figure(corpus: Path, name: str, model: str, out_plot: Path, out_sheet: Path):
    """One clip of the multilingual corpus: the model's lip opening against the synthesiser's
    exact phones, and a contact sheet."""
    import json

    from talkmesh.audio.loading import load_audio
    from talkmesh.datasets.multilingual import read_phones
    from talkmesh.output.render import contact_sheet
    from talkmesh.pipeline import animate

    manifest = json.loads((corpus / "manifest.json").read_text())
    subject = manifest["subjects"][name.rsplit("_", 1)[0]]
    head = load_head(subject["identity"])
    wave = load_audio(corpus / "wav" / f"{name}.wav")
    anim = animate(wave, head=head, model=model)
    truth = np.load(corpus / "vertices_npy" / f"{name}.npy")[::2]
    phones = read_phones(corpus, name)
    t = np.arange(anim.num_frames) / anim.fps
    fig, ax = plt.subplots(figsize=(12, 3.2), dpi=80)
    ax.plot(t, lip_opening(anim.vertices, head.regions) * 1000, color="k", lw=1.2, label=model)
    tt = np.arange(len(truth)) / 30.0
    tv = lip_opening(truth.reshape(len(truth), -1, 3), head.regions) * 1000
    ax.plot(tt, tv, color="tab:green", lw=0.8, ls="--", label="teacher (truth)")
    for p in phones:
        if p.label in ("P", "B", "M"):
            ax.axvspan(p.start, p.end, color="tab:red", alpha=0.3, lw=0)
        elif p.label == "SIL" and p.end - p.start >= 0.15:
            ax.axvspan(p.start, p.end, color="0.8", alpha=0.5, lw=0)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("lip opening (mm)")
    ax.set_title(
        f"{subject['language']} ({subject['voice']}, a voice no model heard): "
        f"{manifest['sentences'][name]}\nred = /p b m/, grey = pauses (synthesiser timings)",
        fontsize=9,
    )
    ax.legend(fontsize=8, loc="upper right")
    ax.set_xlim(0, t[-1])
    fig.tight_layout()
    save_small(fig, out_plot)
    contact_sheet(anim, out_sheet, n=8, cols=4, size=160)
    print(f"wrote {out_plot} and {out_sheet}")


def motion_figure(corpus: Path, preds: list[str], out: Path) -> None:
    """Per-vertex mean and std of inter-frame motion on the synthetic test split (CodeTalker Fig. 4)."""
    from talkmesh.datasets.reader import open_dataset
    from talkmesh.evaluation.metrics import motion_statistics

    ds = open_dataset("synth", corpus, "test")
    head = load_head()
    rows = [("ground truth", [ds[i].vertices for i in range(len(ds))])]
    for item in preds:
        label, _, directory = item.partition("=")
        seqs = [
            np.load(Path(directory) / f"{n}.npy").reshape(-1, head.num_vertices, 3)
            for n in ds.names
        ]
        rows.append((label, seqs))
    stats = [(label, *motion_statistics(seqs)) for label, seqs in rows]
    top_mean = max(m.max() for _, m, _ in stats) * 1000
    top_std = max(s.max() for _, _, s in stats) * 1000
    v = head.template
    crop = v.copy()
    front = v[:, 2] > -0.01
    crop[~front] = v[front].mean(0)
    fig, axes = plt.subplots(2, len(stats), figsize=(2.6 * len(stats), 5.6), dpi=80, squeeze=False)
    for k, (label, mean, std) in enumerate(stats):
        draw_mesh(axes[0, k], crop, head.faces, mean * 1000 / top_mean, "inferno")
        draw_mesh(axes[1, k], crop, head.faces, std * 1000 / top_std, "inferno")
        axes[0, k].set_title(f"{label}\nmean (max {mean.max() * 1000:.2f} mm/frame)", fontsize=8)
        axes[1, k].set_title(f"std (max {std.max() * 1000:.2f} mm/frame)", fontsize=8)
    fig.suptitle(
        f"inter-frame motion per vertex, synthetic test split ({len(ds)} sequences)", fontsize=9
    )
    fig.tight_layout()
    save_small(fig, out)


def style_figure(model: str, clip: Path, a: str, b: str, out: Path) -> None:
    """Paper Fig. 5: lip distance over time while the style moves from speaker a to speaker b."""
    from talkmesh.pipeline import animate

    head = load_head()
    fig, (ax, ax2) = plt.subplots(
        1, 2, figsize=(12, 3.4), dpi=80, gridspec_kw={"width_ratios": [3, 1]}
    )
    weights = np.linspace(0, 1, 6)
    means = []
    for w in weights:
        anim = animate(
            clip,
            model=model,
            style_mix={a: 1 - w, b: w} if 0 < w < 1 else {(a if w == 0 else b): 1.0},
        )
        opening = lip_opening(anim.vertices, head.regions) * 1000
        means.append(opening.mean())
        t = np.arange(anim.num_frames) / anim.fps
        ax.plot(
            t,
            opening,
            color=plt.get_cmap("coolwarm")(w),
            lw=1.2,
            label=f"{1 - w:.1f} {a} + {w:.1f} {b}",
        )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("lip opening (mm)")
    ax.legend(fontsize=7)
    ax.set_title(f"{clip.name}: style interpolation ({Path(model).stem})", fontsize=9)
    ax2.plot(weights, means, "o-")
    ax2.set_xlabel(f"weight of {b}")
    ax2.set_ylabel("mean lip opening (mm)")
    fig.tight_layout()
    save_small(fig, out)


AVATAR_KINDS = {  # tests/avatars.py's head avatars, a row each
    "arkit": "ARKit glb: 52 shapes",
    "vrm": "VRM 1.0: presets only",
    "visemes": "Oculus visemes only",
}
AVATAR_SENTENCE = "Would you like a cup of tea?"
AVATAR_CELL = 144


def avatars_figure(out: Path) -> None:
    """Three kinds of avatar (the bundled head with ARKit shapes, with only VRM presets, with only
    Oculus visemes) saying one sentence, as their `animate --avatar` videos draw them: rest,
    then where the jaw opening, the rounding, the closure and the spreading peak."""
    import sys
    import tempfile

    from PIL import Image

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from avatars import head_avatar

    from talkmesh.audio.tts import synthesize_speech
    from talkmesh.face.arkit import ARKIT_NAMES
    from talkmesh.output.avatar import talking_scene
    from talkmesh.output.labels import TextOverlay
    from talkmesh.output.render import avatar_renderer
    from talkmesh.pipeline import animate

    with tempfile.TemporaryDirectory() as tmp:
        wav = Path(tmp) / "tea.wav"
        anim = animate(wav, phones=synthesize_speech(AVATAR_SENTENCE, wav), model="procedural")
        w = {name: anim.weights[:, ARKIT_NAMES.index(name)] for name in ARKIT_NAMES}
        mouth = [k for k, name in enumerate(ARKIT_NAMES) if name.startswith(("jaw", "mouth"))]
        picks = [int(np.argmin(anim.weights[:, mouth].sum(1)))]  # rest, then each kind's peak
        for curve in (
            w["jawOpen"],
            w["mouthPucker"] + w["mouthFunnel"],
            w["mouthClose"] + w["mouthPressLeft"] + w["mouthRollLower"],
            w["mouthStretchLeft"] + w["mouthSmileLeft"] - w["jawOpen"],
        ):
            picks.append(int(np.argmax(curve)))
        rows = []
        for kind, label in AVATAR_KINDS.items():
            avatar = head_avatar(Path(tmp) / f"{kind}.{'vrm' if kind == 'vrm' else 'glb'}", kind)
            scene = talking_scene(avatar, anim.weights, anim.fps, phones=anim.phones)
            with avatar_renderer(scene, AVATAR_CELL) as renderer:
                cells = [renderer.render(scene.vertices(t)) for t in picks]
            TextOverlay(label, AVATAR_CELL, AVATAR_CELL, top=True).draw(cells[0])
            for cell, t in zip(cells, picks):
                TextOverlay(f"{t / anim.fps:.2f} s", AVATAR_CELL, AVATAR_CELL, top=False).draw(cell)
            rows.append(np.concatenate(cells, axis=1))
    sheet = Image.fromarray(np.concatenate(rows, axis=0)).quantize(colors=128)  # small PNG
    sheet.save(out, optimize=True)
    print(f"wrote {out} ({out.stat().st_size // 1024} KB)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "figure", choices=["regions", "lipsync", "motion", "style", "multilingual", "avatars"]
    )
    p.add_argument("--model", default="procedural", help="lipsync/style: the animator")
    p.add_argument("--styles", default="", help="style: two training speakers A,B")
    p.add_argument("--pred", action="append", default=[], help="motion: LABEL=PRED_DIR (repeat)")
    p.add_argument("--corpus", default="corpus/synth", help="motion: the synthetic corpus")
    p.add_argument(
        "clip", nargs="?", default=str(LIBRIVOX / "sense_and_sensibility_01_austen_64kb-0880.wav")
    )
    p.add_argument("--text", help="transcript of the clip")
    args = p.parse_args()
    DOCS.mkdir(parents=True, exist_ok=True)
    if args.figure == "regions":
        regions_figure(DOCS / "regions.png")
    elif args.figure == "avatars":
        avatars_figure(DOCS / "avatar-kinds.png")
    elif args.figure == "multilingual":  # clip: a sequence name of the corpus
        tag = Path(args.model).stem
        multilingual_figure(
            Path(args.corpus),
            args.clip,
            args.model,
            DOCS / f"multilingual_{tag}_{args.clip}.png",
            DOCS / f"contact_multilingual_{tag}_{args.clip}.png",
        )
    elif args.figure == "motion":
        motion_figure(Path(args.corpus), args.pred, DOCS / "motion_stats.png")
    else:
        clip = Path(args.clip)
        tag = "" if args.model == "procedural" else f"{Path(args.model).stem}_"
        if args.figure == "style":
            a, b = args.styles.split(",")
            style_figure(args.model, clip, a, b, DOCS / f"style_{tag}{clip.stem}.png")
            return
        lipsync_figure(
            clip,
            args.text,
            DOCS / f"lipsync_{tag}{clip.stem}.png",
            DOCS / f"contact_{tag}{clip.stem}.png",
            args.model,
        )


if __name__ == "__main__":
    main()
