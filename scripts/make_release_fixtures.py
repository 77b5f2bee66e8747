"""Write tests/fixtures/old_releases/: a tiny release of every family, one imported from the
official FaceFormer fixture, and what each (and the bundled codetalker-synth) generates for one
clip, so that tests/test_old_releases.py can check that releases of an older layout still load
and compute the same. Run it with the code whose releases are to be kept, e.g. the flat layout:

    git archive 397d7e8 src | tar -x -C /tmp/old
    PYTHONPATH=/tmp/old/src python scripts/make_release_fixtures.py \
        tests/fixtures/old_releases tests/fixtures/official

It uses only names both layouts have (registry.FAMILIES, release, official.import_checkpoint).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from talkmesh.models.official import import_checkpoint
from talkmesh.models.registry import FAMILIES
from talkmesh.models.release import load_model, save_model

V, SR = 30, 16_000
EVERY = 97  # the outputs of full-size meshes keep every 97th vertex: a small file


def generate(model, audio: torch.Tensor, template: torch.Tensor) -> np.ndarray:
    K = len(model.styles)
    weights = torch.full((1, K), 1.0 / K) if K else None
    with torch.no_grad():
        return model.generate(audio, template, style_weights=weights, seed=3).numpy()


def main(out: Path, official: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    g = torch.Generator().manual_seed(1234)
    audio = torch.randn(1, SR // 2, generator=g) * 0.1
    template = torch.randn(1, V, 3, generator=g)
    arrays = {"audio": audio.numpy(), "template": template.numpy()}
    for family in sorted(FAMILIES):
        cls = FAMILIES[family]
        torch.manual_seed(0)
        model = cls(cls.tiny_config(num_vertices=V)).eval()
        with torch.no_grad():  # random weights everywhere, so zero-initialised maps move the mesh
            for p in model.parameters():
                p.add_(torch.randn(p.shape) * 0.05)
        path = save_model(model, out / f"{family}.safetensors", dtype=torch.float16)
        arrays[family] = generate(load_model(path), audio, template)
    bundled = load_model("codetalker-synth")
    arrays["bundled_template"] = torch.randn(1, bundled.num_vertices, 3, generator=g) * 0.1
    arrays["codetalker-synth"] = generate(
        bundled, audio, torch.from_numpy(np.asarray(arrays["bundled_template"]))
    )[:, :, ::EVERY]
    imported = import_checkpoint([official / "faceformer_vocaset.pth"], "faceformer", "vocaset")
    path = save_model(imported, out / "faceformer-imported.safetensors", dtype=torch.float16)
    imported = load_model(path)
    arrays["imported_template"] = torch.randn(1, imported.num_vertices, 3, generator=g) * 0.1
    arrays["faceformer-imported"] = generate(
        imported, audio, torch.from_numpy(np.asarray(arrays["imported_template"]))
    )[:, :, ::EVERY]
    np.savez_compressed(out / "outputs.npz", **{k: np.asarray(v) for k, v in arrays.items()})
    for p in sorted(out.iterdir()):
        print(f"{p}: {p.stat().st_size} bytes")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
