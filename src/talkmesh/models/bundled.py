"""The models that ship with talkmesh (``talkmesh/data/models/*.safetensors``) and how a
``--model`` value names a release file: without torch, so that commands decide what there is to
do (a batch with every output written, a name that is no model) before paying for its import."""

from __future__ import annotations

from pathlib import Path

from talkmesh.errors import TalkmeshError

MODELS_DIR = Path(__file__).resolve().parents[1] / "data" / "models"


def bundled_models() -> list[str]:
    """The bundled releases' names (``codetalker-synth``), sorted."""
    if not MODELS_DIR.is_dir():
        return []
    return sorted(p.stem for p in MODELS_DIR.glob("*.safetensors"))


def resolve(name_or_path: str | Path) -> Path:
    """The release file of ``name_or_path``: a file, else a bundled model of that name."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    bundled = MODELS_DIR / f"{name_or_path}.safetensors"
    if bundled.is_file():
        return bundled
    names = bundled_models()
    raise TalkmeshError(
        f"model '{name_or_path}' is neither a file nor a bundled model"
        + (f" ({', '.join(names)})" if names else "")
    )
