"""The benchmark's figures (paper Figs. 4, 5/8 and 7) and its side-by-side video."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from talkmesh.errors import MissingDependencyError
from talkmesh.evaluation.benchmark.config import BASELINES, SYMBOLS, AblationSpec, fmt_value

MAX_PNG_BYTES = 200_000
MAX_VIDEO_BYTES = 2_000_000


def _matplotlib():
    try:
        from matplotlib.collections import PolyCollection
        from matplotlib.figure import Figure
    except ImportError:
        raise MissingDependencyError("matplotlib", "benchmark", "benchmark figures") from None
    return Figure, PolyCollection


def save_png(fig, path: Path) -> Path:
    """A figure as a palette PNG (docs images stay small)."""
    from io import BytesIO

    from PIL import Image

    buf = BytesIO()
    fig.savefig(buf, format="png")
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.open(buf).convert("RGB").quantize(colors=128).save(path, optimize=True)
    return path


def _load_pred(pred_dir: Path, name: str, num_vertices: int) -> np.ndarray:
    return np.load(pred_dir / f"{name}.npy").reshape(-1, num_vertices, 3)


def sample_indices(n: int, k: int) -> list[int]:
    """``k`` sequence indices spread over a split of ``n`` (the first is always 0)."""
    if k <= 0 or n == 0:
        return []
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(k, n))})


def lip_figure(dataset, indices: list[int], preds: dict[str, Path], path: Path) -> Path | None:
    """Paper Figs. 5/8: upper-lower lip distance over time, every method vs ground truth."""
    from talkmesh.evaluation.evaluate import bundled_lip_pairs
    from talkmesh.evaluation.metrics import lip_opening_pairs

    Figure, _ = _matplotlib()
    first = dataset[indices[0]]
    pairs = bundled_lip_pairs(len(first.template))
    if pairs is None:
        return None
    fps = dataset.spec.motion_fps
    fig = Figure(figsize=(10, 2.1 * len(indices) + 0.4), dpi=80)
    axes = fig.subplots(len(indices), 1, squeeze=False)[:, 0]
    for ax, index in zip(axes, indices):
        s = dataset[index]
        t = np.arange(len(s.vertices)) / fps
        ax.plot(
            t, lip_opening_pairs(s.vertices, pairs) * 1e3, color="k", lw=2.0, label="ground truth"
        )
        for k, (label, d) in enumerate(preds.items()):
            v = _load_pred(d, s.name, len(s.template))
            style = "--" if label in BASELINES else "-"
            ax.plot(
                np.arange(len(v)) / fps,
                lip_opening_pairs(v, pairs) * 1e3,
                style,
                lw=1.1,
                color=f"C{k}",
                label=label,
            )
        ax.set_title(s.name, fontsize=9)
        ax.set_ylabel("lip distance (mm)", fontsize=8)
        ax.set_xlim(0, t[-1] if len(t) > 1 else 1)
        ax.tick_params(labelsize=7)
    axes[-1].set_xlabel("time (s)", fontsize=8)
    axes[0].legend(fontsize=7, ncol=min(4, len(preds) + 1), loc="upper right")
    fig.tight_layout()
    return save_png(fig, path)


def draw_on_mesh(
    ax, verts: np.ndarray, faces: np.ndarray | None, values: np.ndarray, vmax: float, poly=None
) -> Any:
    """Front orthographic view (x right, y up, +z to the viewer), faces coloured by the mean of
    their vertices' values on one scale 0..vmax; back-facing triangles culled, the rest drawn back
    to front. ``poly``: matplotlib's PolyCollection (imported here when None)."""
    if poly is None:
        poly = _matplotlib()[1]
    if faces is None:
        order = np.argsort(verts[:, 2])
        art = ax.scatter(
            verts[order, 0],
            verts[order, 1],
            c=values[order],
            s=1,
            cmap="inferno",
            vmin=0,
            vmax=vmax,
            linewidths=0,
        )
        shown = verts
    else:
        tri = verts[faces]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        order = np.argsort(tri[:, :, 2].mean(1))
        order = order[normals[order, 2] > 0]
        # edges in the face colour: no hairline gaps between the triangles
        colour = values[faces[order]].mean(1)
        art = poly(tri[order, :, :2], array=colour, cmap="inferno", edgecolors="face", lw=0.3)
        art.set_clim(0, vmax)
        ax.add_collection(art)
        shown = tri[order].reshape(-1, 3)
    ax.set_xlim(shown[:, 0].min(), shown[:, 0].max())
    ax.set_ylim(shown[:, 1].min(), shown[:, 1].max())
    ax.set_aspect("equal")
    ax.axis("off")
    return art


def motion_figure(dataset, preds: dict[str, Path], path: Path) -> Path:
    """Paper Fig. 4: per-vertex mean and std over time of the inter-frame motion, on the mesh."""
    from talkmesh.evaluation.metrics import motion_statistics

    Figure, poly = _matplotlib()
    samples = [dataset[i] for i in range(len(dataset))]
    V = len(samples[0].template)
    rows = [("ground truth", motion_statistics([s.vertices for s in samples]))]
    for label, d in preds.items():
        rows.append((label, motion_statistics([_load_pred(d, s.name, V) for s in samples])))
    top = [max(float(st[k].max()) for _, st in rows) * 1e3 or 1.0 for k in (0, 1)]
    fig = Figure(figsize=(2.3 * len(rows) + 0.8, 5.2), dpi=72)
    axes = fig.subplots(2, len(rows), squeeze=False)
    arts: list[Any] = [None, None]
    for k, (label, (mean, std)) in enumerate(rows):
        for r, (values, name) in enumerate(((mean, "mean"), (std, "std"))):
            arts[r] = draw_on_mesh(
                axes[r, k], samples[0].template, dataset.faces, values * 1e3, top[r], poly
            )
            title = f"{label}\n{name}" if r == 0 else name
            axes[r, k].set_title(f"{title} (max {values.max() * 1e3:.2f})", fontsize=8)
    for r in (0, 1):
        fig.colorbar(arts[r], ax=axes[r, :].tolist(), shrink=0.8, label="mm / frame")
    fig.suptitle(
        f"inter-frame motion per vertex, {dataset.split} split "
        f"({len(samples)} sequences; seed-0 models)",
        fontsize=9,
    )
    return save_png(fig, path)


def ablation_figure(ab: AblationSpec, cells: list[dict[str, Any]], path: Path) -> Path:
    """Heatmaps of reconstruction LVE (mm) and codebook usage (%) over the grid."""
    Figure, _ = _matplotlib()
    keys = list(ab.grid)
    if len(keys) == 2:
        rows, cols = [list(ab.grid[keys[0]]), list(ab.grid[keys[1]])]
    else:
        rows, cols = [None], [c["label"] for c in cells]
    shape = (len(rows), len(cols))
    lve = np.array([c["physical"]["lve"] * 1e3 for c in cells]).reshape(shape)
    usage = np.array([c["usage"]["usage"] * 100 for c in cells]).reshape(shape)
    fig = Figure(figsize=(1.2 * len(cols) * 2 + 2.4, 0.7 * len(rows) + 1.4), dpi=80)
    axes = fig.subplots(1, 2)
    for ax, values, title, cmap in (
        (axes[0], lve, "reconstruction LVE (mm)", "viridis_r"),
        (axes[1], usage, "codebook usage (%)", "viridis"),
    ):
        im = ax.imshow(values, cmap=cmap, aspect="auto")
        for (i, j), v in np.ndenumerate(values):
            r, g, b, _ = im.cmap(im.norm(v))
            dark = 0.299 * r + 0.587 * g + 0.114 * b < 0.5  # white text on dark cells
            text = f"{v:.2f}" if values is lve else f"{v:.0f}"
            ax.text(j, i, text, ha="center", va="center", fontsize=8, color="w" if dark else "k")
        ax.set_xticks(range(len(cols)))
        ax.set_yticks(range(len(rows)))
        if len(keys) == 2:
            short = [SYMBOLS.get(k.split(".")[-1], k.split(".")[-1]) for k in keys]
            ax.set_xticklabels([f"{short[1]}={fmt_value(c)}" for c in cols], fontsize=8)
            ax.set_yticklabels([f"{short[0]}={fmt_value(r)}" for r in rows], fontsize=8)
        else:
            ax.set_xticklabels([str(c) for c in cols], fontsize=7, rotation=30)
            ax.set_yticklabels([""])
        ax.set_title(title, fontsize=9)
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.tight_layout()
    return save_png(fig, path)


def side_by_side_video(
    dataset, index: int, preds: dict[str, Path], path: Path, size: int, progress: bool
) -> Path | None:
    """Ground truth and every method (seed 0) on one test sentence, with its audio."""
    from talkmesh.animation import Animation
    from talkmesh.audio.loading import SAMPLE_RATE
    from talkmesh.output.render import render_side_by_side

    faces = dataset.faces
    if faces is None:
        return None
    s = dataset[index]
    fps = dataset.spec.motion_fps
    anims = [Animation(s.vertices, faces, fps, audio=s.audio, sample_rate=SAMPLE_RATE)]
    for d in preds.values():
        anims.append(Animation(_load_pred(d, s.name, len(s.template)), faces, fps))
    path.parent.mkdir(parents=True, exist_ok=True)
    labels = ["ground truth", *preds]
    render_side_by_side(anims, labels, path, size=size, progress=progress)
    if path.stat().st_size > MAX_VIDEO_BYTES:  # docs stay small: trade quality for size
        render_side_by_side(anims, labels, path, size=size, crf=30, progress=progress)
    return path
