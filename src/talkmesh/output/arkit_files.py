"""ARKit blendshape weight files: Live Link Face takes (.csv) and talkmesh's ARKit JSON."""

from __future__ import annotations

import csv
import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from talkmesh.animation import Animation
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import (
    ARKIT_NAMES,
    LIVE_LINK_BLENDSHAPES,
    LIVE_LINK_COLUMNS,
    arkit_index,
    live_link_head,
    to_arkit_order,
)
from talkmesh.output.files import bundled_head, check_readable, finite, reading


class ArkitWeights(NamedTuple):
    """ARKit blendshape weights read from a ``.csv`` or ``.json`` file.

    Attributes:
        weights: (T, 52) float32 weights in ``ARKIT_NAMES`` order.
        fps: frames per second.
    """

    weights: np.ndarray
    fps: float


def load_arkit_weights(path: str | Path, *, fps: float | None = None) -> ArkitWeights:
    """(T, 52) ARKit weights from a Live Link Face ``.csv`` or a talkmesh ``.json`` file.

    ``fps`` replaces the stored frame rate (a Live Link CSV stores none: it is inferred from the
    timecodes, which needs at least 2 s of frames).
    """
    path = Path(path)
    reader = WEIGHT_IMPORTERS.get(path.suffix.lower())
    if reader is None:
        raise TalkmeshError(
            f"{path}: cannot read ARKit weights from '{path.suffix or path.name}' files; "
            f"use one of {', '.join(WEIGHT_IMPORTERS)}"
        )
    check_readable(path)
    with reading(path):
        weights, stored_fps = reader(path)
        fps = fps or stored_fps
        if fps is None:
            raise TalkmeshError("cannot tell the frame rate from under 2 s of timecodes; pass fps=")
        if not fps > 0:
            raise TalkmeshError(f"fps must be positive, got {fps}")
        return ArkitWeights(finite(weights, "weights").astype(np.float32), float(fps))


def arkit_weights_of(anim: Animation, path: Path) -> np.ndarray:
    """(T, 52) weights of ``anim`` in ARKit order, or a TalkmeshError saying it has none."""
    if anim.weights is None:
        raise TalkmeshError(
            f"{path.name}: the animation has no ARKit weights (only vertices); "
            "save it as .glb, .npz, .npy or .obj instead"
        )
    return to_arkit_order(anim.weights, anim.weight_names)


def export_live_link_csv(anim: Animation, path: Path) -> None:
    """A Live Link Face take: ``Timecode,BlendShapeCount,EyeBlinkLeft,...,RightEyeRoll``.

    Timecodes are ``HH:MM:SS:FF.mmm`` with FF counted at the animation's fps; the head's
    rotations are its ``head_pose`` as the app writes them, radians / pi (HeadYaw, HeadPitch,
    HeadRoll, :func:`talkmesh.face.arkit.live_link_head`; zero without one,
    :mod:`talkmesh.face.head_motion` gives the signs), the eyes' rotations are zero (the eyes move
    by the eyeLook blendshapes).
    """
    weights = arkit_weights_of(anim, path)
    columns = [arkit_index(n) for n in LIVE_LINK_BLENDSHAPES]
    values = np.zeros((anim.num_frames, len(LIVE_LINK_COLUMNS)), dtype=np.float64)
    values[:, : len(columns)] = weights[:, columns]
    if anim.head_pose is not None:
        head = len(columns) + np.arange(3)  # HeadYaw, HeadPitch, HeadRoll
        values[:, head] = live_link_head(anim.head_pose)
    row_format = "%s," + str(len(LIVE_LINK_COLUMNS)) + ",%.8f" * len(LIVE_LINK_COLUMNS) + "\n"
    lines = ["Timecode,BlendShapeCount," + ",".join(LIVE_LINK_COLUMNS) + "\n"]
    lines += [row_format % (timecode(t, anim.fps), *row) for t, row in enumerate(values.tolist())]
    path.write_text("".join(lines))


def timecode(frame: int, fps: float) -> str:
    """``HH:MM:SS:FF.mmm`` of frame ``frame`` at ``fps`` (FF is the frame within the second)."""
    seconds = int(np.floor(frame / fps + 1e-9))
    within = max(frame - seconds * fps, 0.0)
    ff = int(within + 1e-9)
    millis = min(max(round((within - ff) * 1000), 0), 999)
    minutes, s = divmod(seconds, 60)
    h, m = divmod(minutes, 60)
    return f"{h:02d}:{m:02d}:{s:02d}:{ff:02d}.{millis:03d}"


_TIMECODE = re.compile(r"^\s*(\d+):(\d+):(\d+)[:;](\d+)(?:\.(\d+))?\s*$")


def read_live_link_csv(path: Path) -> tuple[np.ndarray, float | None]:
    """(T, 52) weights in ARKit order and the fps inferred from the timecodes (None if < 2 s)."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header = [h.strip() for h in rows[0]]
    body = [r for r in rows[1:] if any(c.strip() for c in r)]
    if not body:
        raise ValueError("no frames after the header")
    names = [n for n in header if arkit_index(n) >= 0]
    cols = [header.index(n) for n in names]
    table = np.array([[float(r[c]) for c in cols] for r in body], dtype=np.float64)
    weights = to_arkit_order(table, names)
    fps = None
    if header and header[0].lower() == "timecode":
        seconds = []
        for r in body:
            match = _TIMECODE.match(r[0])
            if match is None:
                raise ValueError(f"bad timecode '{r[0]}' (expected HH:MM:SS:FF.mmm)")
            h, m, s = (int(match.group(i)) for i in (1, 2, 3))
            seconds.append(h * 3600 + m * 60 + s)
        # Rows per whole second: the first and last seconds may be partial.
        _, counts = np.unique(seconds, return_counts=True)
        if len(counts) >= 3:
            fps = float(np.median(counts[1:-1]))
    return weights, fps


def export_arkit_json(anim: Animation, path: Path) -> None:
    """``{"fps": 30.0, "names": [52 ARKit names], "frames": [[52 weights], ...]}``."""
    weights = arkit_weights_of(anim, path)
    doc = {
        "fps": float(anim.fps),
        "names": list(ARKIT_NAMES),
        "frames": np.round(weights.astype(np.float64), 6).tolist(),
    }
    path.write_text(json.dumps(doc, separators=(",", ":")) + "\n")


def read_arkit_json(path: Path) -> tuple[np.ndarray, float | None]:
    """(T, 52) weights in ARKit order and the stored fps, from :func:`export_arkit_json`."""
    doc = json.loads(path.read_text())
    if not isinstance(doc, dict) or "frames" not in doc or "names" not in doc:
        raise ValueError('expected {"fps": ..., "names": [...], "frames": [[...], ...]}')
    names = [str(n) for n in doc["names"]]
    frames = np.array(doc["frames"], dtype=np.float64).reshape(-1, len(names))
    fps = doc.get("fps")
    return to_arkit_order(frames, names), None if fps is None else float(fps)


def import_weights_on_head(path: Path, faces: np.ndarray | None, fps: float | None) -> Animation:
    """ARKit weights played on the bundled head (``faces`` is not used)."""
    weights, stored_fps = load_arkit_weights(path, fps=fps)
    head = bundled_head()
    if head is None:
        raise TalkmeshError(
            f"{path}: playing ARKit weights needs the bundled head (talkmesh.face.assets)"
        )
    order = [arkit_index(n) for n in head.blendshape_names]
    head_weights = weights[:, order]
    return Animation(
        vertices=head.vertices_from_weights(head_weights),
        faces=head.faces,
        fps=stored_fps,
        weights=head_weights,
        weight_names=list(head.blendshape_names),
        template=head.template,
        basis=head.blendshapes,
    )


WEIGHT_IMPORTERS: dict[str, Callable[[Path], tuple[np.ndarray, float | None]]] = {
    ".csv": read_live_link_csv,
    ".json": read_arkit_json,
}
