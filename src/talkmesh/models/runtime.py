"""What runs a learned model: PyTorch, or ONNX Runtime on the model's exported graphs.

The bundled CodeTalker runs on ONNX Runtime by default (``runtime="auto"``), from graphs that
:func:`talkmesh.models.onnx.export_onnx` writes once into the cache folder
(:func:`talkmesh.cache.cache_dir`, ``onnx/``): a run then never imports torch, whose import alone
took 2.7 s of a 6.4 s ``talkmesh animate`` on an idle 2-core machine (docs/results/latency.md).
The graphs generate the motion torch does (within 1e-6 of its scale, ``tests/test_onnx.py``).

The cached graphs are named by the release file's SHA-256 and a digest of the code that
exports them (this package's ``models/`` sources and the talkmesh version), so another release
or another talkmesh exports again. A cached file that ONNX Runtime cannot open is exported again.
Where the export cannot happen (no ``onnx``/``onnxruntime`` installed, a cache folder that cannot
be written), ``auto`` runs the model on PyTorch as before.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from functools import lru_cache
from importlib.util import find_spec
from pathlib import Path
from typing import Any

from talkmesh.cache import cache_dir, file_digest
from talkmesh.errors import TalkmeshError
from talkmesh.models.bundled import bundled_models, resolve
from talkmesh.version import __version__

RUNTIMES = ("auto", "torch", "onnxruntime")
MODELS_SOURCE = Path(__file__).resolve().parent  # the code the exported graphs come from


def is_onnx_file(model: Any) -> bool:
    return isinstance(model, (str, Path)) and str(model).lower().endswith(".onnx")


def check_runtime(runtime: str, model: Any, int8: str | None = None) -> None:
    """One-line errors for a ``runtime`` that cannot run ``model`` (with ``int8``): an unknown
    one, torch for an .onnx file, ONNX Runtime for the procedural animator or with int8 layers."""
    if runtime not in RUNTIMES:
        raise TalkmeshError(f"--runtime {runtime}: use one of {', '.join(RUNTIMES)}")
    if is_onnx_file(model):
        if runtime == "torch":
            raise TalkmeshError(f"--runtime torch runs releases, not {model}: drop --runtime")
        if int8 is not None:
            raise TalkmeshError("--int8 applies to PyTorch models, not to an .onnx file")
    elif runtime == "onnxruntime" and model == "procedural":
        raise TalkmeshError(
            "--runtime onnxruntime runs learned models, and procedural is not one: drop --runtime"
        )
    elif runtime == "onnxruntime" and int8 is not None:
        raise TalkmeshError("--int8 runs on PyTorch: drop --runtime onnxruntime")


def open_model(
    model: str | Path | Any, runtime: str = "auto", *, int8: str | None = None, threads=None
) -> Any:
    """``model`` (a bundled name, a release or ``.onnx`` file, or a loaded model) ready to
    generate, on ``runtime``: ``torch``, ``onnxruntime`` (a release is exported to the cache
    first) or ``auto`` (ONNX Runtime for a bundled model when it is installed and ``int8`` is not
    asked for, else torch), with ``int8`` layers if asked. ``threads``: ONNX Runtime's threads
    (torch's are the caller's)."""
    check_runtime(runtime, model, int8)
    if not isinstance(model, (str, Path)):
        return model.int8_copy(int8) if int8 is not None else model
    if is_onnx_file(model):
        return _onnx_model(Path(model), threads)
    if runtime == "onnxruntime" or (runtime == "auto" and _auto_onnx(model, int8)):
        graphs = cached_graphs(model, required=runtime == "onnxruntime")
        if graphs is not None:
            try:
                return _onnx_model(graphs, threads)
            except TalkmeshError:  # a damaged cache entry: export again, once
                shutil.rmtree(graphs.parent, ignore_errors=True)
                return _onnx_model(cached_graphs(model, required=True), threads)
    if find_spec("torch") is None:
        raise TalkmeshError("learned models need torch: run `make setup`")
    from talkmesh.models.release import load_model

    net = load_model(model)
    return net.int8_copy(int8) if int8 is not None else net


def _onnx_model(path: Path, threads):
    """The :class:`OnnxModel` of ``path``, opened once per process for its bytes (a script that
    calls ``animate`` in a loop opens the graphs once: 0.4 s each on 2 cores)."""
    stat = path.stat() if path.is_file() else None
    key = (str(path.resolve()), stat and (stat.st_mtime_ns, stat.st_size), threads)
    return _opened(*key)


@lru_cache(maxsize=4)
def _opened(path: str, version, threads):
    from talkmesh.models.onnx import OnnxModel

    return OnnxModel(path, threads=threads)


def _auto_onnx(model: str | Path, int8: str | None) -> bool:
    """``auto`` runs ``model`` on ONNX Runtime: a bundled model, no int8, ONNX installed."""
    return (
        int8 is None
        and str(model) in bundled_models()
        and find_spec("onnxruntime") is not None
        and find_spec("onnx") is not None
    )


@lru_cache(maxsize=1)
def _code_digest() -> str:
    """A digest of the code that builds the exported graphs, and of talkmesh's version."""
    digest = hashlib.sha256(__version__.encode())
    for path in sorted(MODELS_SOURCE.rglob("*.py")):
        digest.update(path.relative_to(MODELS_SOURCE).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


@lru_cache(maxsize=8)
def _release_digest(path: str, mtime_ns: int, size: int) -> str:
    """SHA-256 of a release file, read once per process for the same file (47 MB)."""
    return file_digest(path)


def graphs_folder(model: str | Path) -> Path:
    """The cache folder of ``model``'s exported graphs."""
    release = resolve(model)
    stat = release.stat()
    digest = _release_digest(str(release.resolve()), stat.st_mtime_ns, stat.st_size)
    key = hashlib.sha256((digest + _code_digest()).encode()).hexdigest()[:20]
    return cache_dir() / "onnx" / f"{release.stem}-{key}"


def cached_graphs(model: str | Path, *, required: bool = False) -> Path | None:
    """``model.onnx`` of ``model``'s cached graphs, exported now if missing; None (or, when
    ``required``, a one-line error) when they cannot be exported or saved."""
    folder = graphs_folder(model)
    path = folder / "model.onnx"
    if path.is_file() and (folder / "model.speech.onnx").is_file():
        return path
    try:
        _export_into(model, folder)
    except (OSError, TalkmeshError) as e:
        if required:
            raise TalkmeshError(
                f"cannot run {model} on ONNX Runtime: {e} (set TALKMESH_CACHE to a writable "
                "folder, or pass --runtime torch)"
            ) from None
        return None
    return path


def _export_into(model: str | Path, folder: Path) -> None:
    """Export ``model`` into ``folder`` whole: written in a temporary folder beside it, then
    renamed into place (a process that finds the folder there finds both graphs)."""
    from talkmesh.models.onnx import export_onnx
    from talkmesh.models.release import load_model

    folder.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{folder.name}-", dir=folder.parent))
    try:
        export_onnx(load_model(model), work / "model.onnx")
        try:
            os.replace(work, folder)
        except OSError:
            if not (folder / "model.onnx").is_file():  # not another process's export
                raise
    finally:
        shutil.rmtree(work, ignore_errors=True)
