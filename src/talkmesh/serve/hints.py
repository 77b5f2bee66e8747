"""What ``talkmesh serve`` says of a model it cannot stream."""

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
