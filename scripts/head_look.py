"""Before/after frames of the bundled head's look for docs/guide/avatars.md.

    PYTHONPATH=src python scripts/head_look.py [-o docs/images/head-look.png]

Left: the plain part colours; middle: ``talkmesh.face.look`` (irises and pupils, lip colour, dark
mouth cavity, teeth and tongue shaded by depth); right: the same from the three-quarter camera
(``--camera three-quarter``). Mouth half open (jawOpen 0.5), eyes looking left (eyeLookOutLeft /
eyeLookInRight 0.6).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image

from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import load_head
from talkmesh.face.look import head_colors
from talkmesh.output.raster import PART_SRGB, Renderer

SIZE = 384
POSE = {"jawOpen": 0.5, "eyeLookOutLeft": 0.6, "eyeLookInRight": 0.6}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default="docs/images/head-look.png")
    args = parser.parse_args()
    head = load_head()
    weights = np.zeros(len(ARKIT_NAMES), np.float32)
    for name, w in POSE.items():
        weights[ARKIT_NAMES.index(name)] = w
    vertices = head.vertices_from_weights(weights[None])[0]
    plain = PART_SRGB[np.clip(head.regions.vertex_part, 0, len(PART_SRGB) - 1)]
    panels = []
    for colors, camera in (
        (plain, "front"),
        (head_colors(head), "front"),
        (head_colors(head), "three-quarter"),
    ):
        with Renderer(
            head.faces, SIZE, vertex_colors=colors, reference=vertices, camera=camera
        ) as renderer:
            panels.append(renderer.render(vertices))
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(panels, axis=1)).save(args.output, optimize=True)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
