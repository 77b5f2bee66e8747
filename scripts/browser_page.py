"""The in-browser page (web/browser) and every file it loads, in one folder to serve statically:

    python scripts/browser_page.py OUT [--model codetalker-synth]
    python -m http.server -d OUT 8080     # then open http://127.0.0.1:8080/

``page.js`` (web/browser/main.js bundled by esbuild with three.js and onnxruntime-web from
node_modules: `npm ci` first), onnxruntime-web's WebAssembly files (the plain build, and the
asyncify build that its WebGPU bundle loads where WebGPU can run), the model's ONNX graphs
(``ct.onnx``, ``ct.speech.onnx``: ``talkmesh export-onnx``), the bundled head (``head.glb``) and
``model.json`` (frame rate, mel bins, feature width, the mean style vector with the head term
of head.glb's face, the state's shapes, and for a model whose VQ decoder hears the head that
face's ``face`` term).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "web" / "browser"
NODE = ROOT / "node_modules"
WASM = tuple(f"ort-wasm-simd-threaded{v}.{e}" for v in ("", ".asyncify") for e in ("wasm", "mjs"))


def build(out: Path, model: str = "codetalker-synth") -> Path:
    import torch

    from talkmesh.face.assets import load_head
    from talkmesh.models.onnx import OnnxModel, export_onnx
    from talkmesh.models.release import load_model
    from talkmesh.serve.files import neutral_head_glb

    esbuild = NODE / ".bin" / "esbuild"
    if not esbuild.is_file() or not (NODE / "onnxruntime-web").is_dir():
        raise SystemExit(f"{NODE} lacks esbuild or onnxruntime-web: run `npm ci`")
    out.mkdir(parents=True, exist_ok=True)
    subprocess.run(
        [str(esbuild), str(PAGE / "main.js"), "--bundle", "--format=esm", "--target=es2020",
         "--minify", "--log-level=warning", "--external:*.wasm", f"--outfile={out / 'page.js'}"],
        check=True,
    )  # fmt: skip
    shutil.copy(PAGE / "index.html", out)
    for name in WASM:
        shutil.copy(NODE / "onnxruntime-web" / "dist" / name, out)
    with torch.no_grad():
        export_onnx(load_model(model), out / "ct.onnx")
    runtime = OnnxModel(out / "ct.onnx")
    template = load_head().template  # the head the page animates (head.glb)
    info = {
        "fps": runtime.motion_fps,
        "n_mels": runtime.n_mels,
        "speech_dim": int(runtime.step.get_inputs()[0].shape[1]),
        "style": runtime.style(None, template)[0].tolist(),  # with that head's term
        "state": {n: list(s) for n, s in runtime.state.items()},
    }
    face = runtime.face(template)  # the step graph's input "face", for such a model only
    if face is not None:
        info["face"] = face[0].tolist()
    (out / "model.json").write_text(json.dumps(info))
    (out / "head.glb").write_bytes(neutral_head_glb())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--model", default="codetalker-synth")
    args = parser.parse_args()
    print(f"wrote {build(args.out, args.model)}")


if __name__ == "__main__":
    main()
