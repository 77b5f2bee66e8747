"""Draw docs/images/architecture.png: talkmesh's packages by level, and the data that flows through.

    python scripts/architecture_figure.py [-o docs/images/architecture.png]

A package may import only packages on the rows above it (tests/test_architecture.py checks it).
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "docs" / "images" / "architecture.png"

# One row per level, top to bottom: (package, what it holds). A row imports only rows above it.
ROWS: list[list[tuple[str, str]]] = [
    [("core", "constants, errors, config, animation")],
    [("audio", "load + resample, phones, voices")],
    [("face", "head, ARKit rig, procedural lip sync")],
    [("models", "one interface, a folder per family"), ("datasets", "readers, synthetic corpus")],
    [("output", "formats registry, renderer")],
    [("pipeline", "animate()"), ("retarget", "retarget, dub")],
    [("training", "recipes, Lightning system"), ("batch", "libraries, Ray cluster")],
    [("evaluation", "metrics, evaluate, benchmark")],
    [("serve", "open_stream, server, viewer")],
    [("cli", "talkmesh COMMAND")],
]
# What moves down the flow, level by level (right-hand column).
DATA = {
    1: "speech file -> (S,) float32, 16 kHz",
    2: "timed phones -> ARKit weights",
    3: "features (B, T, D) -> vertices (B, T, V, 3)",
    4: ".mp4 .glb .npz .npy .obj .csv .json",
    5: "Animation: vertices + ARKit weights",
    8: "chunks in, frames out (WebSocket)",
}
BOX_W, BOX_H, ROW_H, GAP = 3.3, 0.62, 0.85, 0.2


def draw(out: Path) -> None:
    fig, ax = plt.subplots(figsize=(8.4, 7.6), dpi=80)
    ax.set_xlim(0, 11.0)
    ax.set_ylim(-len(ROWS) * ROW_H, 0.55)
    ax.axis("off")
    ax.text(0.1, 0.25, "package (imports only rows above)", fontsize=10, weight="bold")
    ax.text(7.2, 0.25, "data flowing down", fontsize=10, weight="bold", color="#555555")
    for level, row in enumerate(ROWS):
        y = -(level + 1) * ROW_H + (ROW_H - BOX_H) / 2
        width = (2 * BOX_W + GAP - GAP * (len(row) - 1)) / len(row)
        for k, (name, what) in enumerate(row):
            x = 0.1 + k * (width + GAP)
            ax.add_patch(
                FancyBboxPatch(
                    (x, y),
                    width,
                    BOX_H,
                    boxstyle="round,pad=0.02,rounding_size=0.08",
                    facecolor="#dbe8f6" if name != "core" else "#eeeeee",
                    edgecolor="#3b6ea5",
                )
            )
            ax.text(x + 0.12, y + BOX_H * 0.62, name, fontsize=10, weight="bold", va="center")
            ax.text(x + 0.12, y + BOX_H * 0.25, what, fontsize=7.5, va="center", color="#333333")
        if level + 1 < len(ROWS):
            ax.add_patch(
                FancyArrowPatch(
                    (0.1 + BOX_W + GAP / 2, y),
                    (0.1 + BOX_W + GAP / 2, y - (ROW_H - BOX_H)),
                    arrowstyle="-|>",
                    mutation_scale=9,
                    color="#3b6ea5",
                )
            )
        if level in DATA:
            ax.text(7.2, y + BOX_H / 2, DATA[level], fontsize=8, va="center", color="#555555")
    out.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight", pad_inches=0.05)
    plt.close(fig)
    from PIL import Image

    buf.seek(0)  # a palette PNG: a few colours, a few tens of KB
    Image.open(buf).convert("RGB").quantize(colors=32).save(out, optimize=True)
    print(f"wrote {out} ({out.stat().st_size // 1024} KB)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--out", type=Path, default=OUT)
    draw(parser.parse_args().out)


if __name__ == "__main__":
    main()
