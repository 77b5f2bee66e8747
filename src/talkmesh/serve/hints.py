"""What ``talkmesh serve`` says of a model it cannot stream, and of an ONNX model (``--runtime
onnxruntime``): its jobs (POST /animate) run the exported graphs, its streams are refused (the
exported speech encoder reads whole windows of audio, as the bundled model's does)."""

from __future__ import annotations

from pathlib import Path

from talkmesh.errors import TalkmeshError


def streaming_hint(name: str, source: str, error: TalkmeshError) -> str:
    """The refusal of a model that cannot stream; for a bundled one (one that animates files but
    has no causal decoder: the bundled codetalker-synth streams), which bundled models stream
    and the command that serves them."""
    from talkmesh.models.release import MODELS_DIR

    message = str(error)
    bundled = Path(source).parent == MODELS_DIR.resolve()
    if not bundled or "cannot stream" not in message:
        return message
    reason = message.split("cannot stream", 1)[1].split("(", 1)[0].strip(" :")
    return (
        f"--model {name}: the bundled {name} animates files (`talkmesh animate`) but cannot "
        f"stream ({reason}); the bundled models that stream are codetalker-synth and "
        "procedural: `talkmesh serve --model procedural` (or train a streaming CodeTalker with "
        "configs/codetalker_stream.yaml and pass its model.safetensors to --model)"
    )


def check_onnx(source: str) -> None:
    """Open an .onnx --model once, so that a file of another model or opset stops the server
    before it starts (:class:`talkmesh.models.onnx.OnnxModel` says what is wrong)."""
    from talkmesh.models.onnx import OnnxModel

    OnnxModel(source, threads=1)


def onnx_stream_refusal(name: str) -> str:
    """A session that asks for an ONNX model: what it can do instead."""
    return (
        f"model {name} is an ONNX export: this server animates files with it (POST "
        f"/animate?model={name}) but cannot stream it (its speech encoder reads whole windows "
        "of audio); stream with procedural or a release (.safetensors), or run the "
        "export in the browser page (web/browser), which streams a microphone through it"
    )
