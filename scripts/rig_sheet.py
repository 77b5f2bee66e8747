"""Contact sheet: three heads, rigged by `talkmesh rig`, saying the same sentence.

    PYTHONPATH=src python scripts/rig_sheet.py [-o docs/images/rig-sheet.png] [--mesh HEAD.obj ...]

The heads are bundled identities turned into "user" meshes of other meshing, units and axes (the
bench's kinds): kemi quadric-decimated to 50% of the triangles in centimetres and Z-up, otto
subdivided once in millimetres, hana decimated to 25% and turned 20 degrees. Each is rigged with
``rig_head`` (deformation transfer) from its mesh alone, then driven by the same ARKit weights from
the procedural animator on an espeak-ng sentence. Columns: rest, then the frames where the jaw
opening, the rounding (pucker + funnel), the closure (close + press + roll) and the spreading
peak. The frames are drawn in plain skin colour, brought back to +y up by the rig's fitted pose.
``--mesh`` adds a row for each head mesh file given (any units, axes and topology).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from rig_transfer import decimate, rotation  # noqa: E402

from talkmesh.audio.tts import synthesize_speech  # noqa: E402
from talkmesh.face.arkit import ARKIT_NAMES  # noqa: E402
from talkmesh.face.assets import load_head  # noqa: E402
from talkmesh.face.rig import rig_head  # noqa: E402
from talkmesh.face.rig_files import load_mesh  # noqa: E402
from talkmesh.output.labels import TextOverlay  # noqa: E402
from talkmesh.output.raster import Renderer  # noqa: E402
from talkmesh.pipeline import animate  # noqa: E402

SENTENCE = "Would you like a cup of tea?"
CELL = 150


def heads(bundled, meshes=()):
    s = bundled.blendshapes.astype(np.float64)
    v, f = load_head("kemi").template.astype(np.float64), bundled.faces
    cv, cf, _ = decimate(v, f, s, 0.5)
    yield "kemi: 50% tris, cm, Z-up", 100 * cv @ rotation([1, 0, 0], -90).T, cf
    v = load_head("otto").template.astype(np.float64)
    sv, sf = trimesh.remesh.subdivide(v, f)
    yield "otto: subdivided, mm", 1000 * sv, sf
    v = load_head("hana").template.astype(np.float64)
    cv, cf, _ = decimate(v, f, s, 0.25)
    yield "hana: 25% tris, turned", cv @ rotation([0.2, 1, 0], 20).T, cf
    for path in meshes:
        yield (Path(path).stem, *load_mesh(path))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default="docs/images/rig-sheet.png")
    parser.add_argument("--mesh", nargs="*", default=[], help="more head meshes, a row each")
    args = parser.parse_args()
    bundled = load_head()
    with tempfile.TemporaryDirectory() as tmp:
        wav = Path(tmp) / "tea.wav"
        phones = synthesize_speech(SENTENCE, wav)
        anim = animate(wav, phones=phones, model="procedural")
    w = {name: anim.weights[:, ARKIT_NAMES.index(name)] for name in ARKIT_NAMES}
    mouth = [k for k, name in enumerate(ARKIT_NAMES) if name.startswith(("jaw", "mouth"))]
    picks = [int(np.argmin(anim.weights[:, mouth].sum(1)))]  # rest, then where each kind peaks
    for curve in (
        w["jawOpen"],
        w["mouthPucker"] + w["mouthFunnel"],
        w["mouthClose"] + w["mouthPressLeft"] + w["mouthRollLower"],
        w["mouthStretchLeft"] + w["mouthSmileLeft"] - w["jawOpen"],
    ):
        picks.append(int(np.argmax(curve)))
    rows = []
    for label, v, f in heads(bundled, args.mesh):
        rig = rig_head(v, f, bundled)
        frames = rig.vertices[None] + np.einsum("tk,kvx->tvx", anim.weights[picks], rig.blendshapes)
        upright = (frames - rig.translation) @ rig.rotation / rig.scale  # back to +y up, metres
        rest = upright[0]
        centre = rest.mean(0)
        face = rest[(rest[:, 2] > centre[2]) & (np.abs(rest[:, 1] - centre[1] + 0.01) < 0.075)]
        aim = np.clip(rest, face.min(0), face.max(0))  # the face's box fills the cell
        with Renderer(rig.faces, CELL, reference=aim) as renderer:
            cells = [renderer.render(u) for u in upright]
        TextOverlay(label, CELL, CELL, top=True).draw(cells[0])
        for cell, t in zip(cells, picks):
            TextOverlay(f"{t / anim.fps:.2f} s", CELL, CELL, top=False).draw(cell)
        rows.append(np.concatenate(cells, axis=1))
        print(f"{label}: {len(v)} vertices, units {rig.units}, up {rig.up_axis}", flush=True)
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    sheet = Image.fromarray(np.concatenate(rows, axis=0)).quantize(colors=128)  # small PNG
    sheet.save(args.output, optimize=True)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
