""".npy ([T, V*3] vertex positions, the VOCASET / FaceFormer layout) and .npz (a whole
:class:`Animation`, no pickle)."""

from __future__ import annotations

import tempfile
import zipfile
from pathlib import Path

import numpy as np

from talkmesh.animation import Animation, AnimationBlocks
from talkmesh.constants import MOTION_FPS, SAMPLE_RATE
from talkmesh.errors import TalkmeshError
from talkmesh.output.files import bundled_head, check_expansion, check_magic, finite

NPY_DEFAULT_FPS = MOTION_FPS  # FaceFormer / CodeTalker write VOCASET predictions at 30 fps
AUDIO_BLOCK = 30 * SAMPLE_RATE  # samples of a streamed waveform written at a time
NPZ_FORMAT_VERSION = 2  # 2: float16 offsets from the template, deflated; 1: float32 vertices


def export_npy(anim: Animation, path: Path) -> None:
    """[T, V*3] float32 vertex positions, the VOCASET / FaceFormer layout."""
    with open(path, "wb") as f:
        np.save(f, anim.vertices.reshape(anim.num_frames, -1), allow_pickle=False)


def import_npy(path: Path, faces: np.ndarray | None, fps: float | None) -> Animation:
    """[T, V*3] (or [T, V, 3]) vertex positions; faces from the caller or the bundled head."""
    check_magic(path, b"\x93NUMPY", ".npy array")
    arr = np.load(path, allow_pickle=False)
    if not isinstance(arr, np.ndarray):
        raise ValueError("not a single .npy array")
    if arr.ndim == 2 and arr.shape[1] % 3 == 0 and arr.shape[1] > 0:
        arr = arr.reshape(len(arr), -1, 3)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"expected [T, V*3] vertex positions, got an array of shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"expected numbers, got {arr.dtype}")
    vertices = finite(arr.astype(np.float32), "vertices")
    if faces is None:
        head = bundled_head()
        if head is None or head.num_vertices != vertices.shape[1]:
            raise TalkmeshError(
                f"{path}: {vertices.shape[1]} vertices do not match the bundled head; "
                "pass the mesh's faces (faces=...)"
            )
        faces = head.faces
    return Animation(vertices, faces, fps or NPY_DEFAULT_FPS)


def export_npz(anim: Animation, path: Path) -> None:
    """Every field of the animation, loadable with ``np.load(path, allow_pickle=False)``: the
    motion as float16 offsets from the template (float32 vertices without one), compressed."""
    _export_npz(NpzWriter(anim, anim.num_frames, path), anim)


def export_npz_weights(anim: Animation, path: Path) -> None:
    """The compact, lossy ``.weights.npz``: as :func:`export_npz` without the per-frame vertices;
    they are ``template + weights @ basis`` (exact for the procedural animator; for learned models
    the weight fit's residual is lost: docs/results/long-audio.md)."""
    _export_npz(NpzWriter(anim, anim.num_frames, path, motion="weights"), anim)


def _export_npz(writer: NpzWriter, anim: Animation) -> None:
    try:
        writer.write(anim)
    finally:
        writer.close()


def check_finite(block: Animation, first: int) -> None:
    """Refuse a block of frames holding NaN or infinite values: never a file of NaN under a
    final name (the writers write to a temporary, removed when this raises)."""
    if not np.isfinite(block.vertices).all() or (
        block.weights is not None and not np.isfinite(block.weights).all()
    ):
        raise TalkmeshError(
            f"frames {first} to {first + block.num_frames} hold NaN or infinite values: nothing "
            "is written (check the template and the model)"
        )


class NpzWriter:
    """Writes an ``.npz`` animation (format 2) a block of frames at a time: the ``offsets``
    member ((T, V, 3) float16 ``vertices - template``, a rounding error of at most 2**-11 of an
    offset: under 0.01 mm for offsets under 2 cm) streams into the deflated archive as blocks
    arrive; the ARKit weights, small, are written at :meth:`close`.

    ``motion="weights"`` writes no per-frame vertices (the lossy ``.weights.npz``).
    ``header`` gives the fields that do not change per frame (an :class:`Animation` or
    :class:`~talkmesh.animation.AnimationBlocks`); without a template the member is ``vertices``
    in float32, as in format 1, which this module still reads.
    """

    def __init__(
        self,
        header: Animation | AnimationBlocks,
        num_frames: int,
        path: Path,
        motion: str = "offsets",
    ) -> None:
        if motion == "weights" and (
            header.template is None or header.basis is None or not header.weight_names
        ):
            raise TalkmeshError(
                f"{path}: a .weights.npz needs ARKit weights with their template and basis; "
                "save a .npz instead"
            )
        self.template = header.template
        self.num_frames, self.done = num_frames, 0
        # the weights (T, 52) wait in a temporary file, not in memory (45 MB an hour)
        self.weights = tempfile.TemporaryFile()
        self.weight_columns: int | None = None
        self.weight_names = list(header.weight_names)
        self.poses: list[np.ndarray] = []  # (t, 6) head poses: 2.6 MB an hour, kept in memory
        self.zip = zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1)
        arrays: dict[str, np.ndarray] = {
            "format_version": np.int64(NPZ_FORMAT_VERSION),
            "faces": header.faces,
            "fps": np.float64(header.fps),
        }
        if header.audio is not None:
            arrays["audio"] = header.audio
            arrays["sample_rate"] = np.int64(header.sample_rate)
        if header.template is not None:
            arrays["template"] = header.template
        if header.basis is not None:
            arrays["basis"] = header.basis
        if header.pose_frame is not None:  # where head_pose's frame lies (a user's head)
            arrays["pose_frame"] = np.asarray(header.pose_frame, "<f8")
        for name, arr in arrays.items():
            if isinstance(arr, np.ndarray) or np.isscalar(arr) or isinstance(arr, np.generic):
                self._put(name, arr)
            else:  # a Waveform (talkmesh.audio.waveform): written as it is read, a block at a time
                self._put_blocks(name, arr)
        self.name = "vertices" if self.template is None else "offsets"
        self.dtype = np.dtype("<f4" if self.template is None else "<f2")
        self.member = None
        if motion != "weights":
            self.member = self.zip.open(f"{self.name}.npy", "w", force_zip64=True)
        self.num_vertices: int | None = None

    def _put(self, name: str, arr: np.ndarray) -> None:
        with self.zip.open(f"{name}.npy", "w", force_zip64=True) as f:
            np.lib.format.write_array(f, np.asarray(arr), allow_pickle=False)

    def _put_blocks(self, name: str, wave) -> None:
        """(S,) float32 ``wave`` read and written ``AUDIO_BLOCK`` samples at a time."""
        with self.zip.open(f"{name}.npy", "w", force_zip64=True) as f:
            header = {"descr": "<f4", "fortran_order": False, "shape": (len(wave),)}
            np.lib.format.write_array_header_1_0(f, header)  # as np.save writes it
            for a in range(0, len(wave), AUDIO_BLOCK):
                f.write(np.ascontiguousarray(wave[a : a + AUDIO_BLOCK], "<f4").tobytes())

    def write(self, block: Animation) -> None:
        """The next frames."""
        if self.member is not None and self.num_vertices is None:
            self.num_vertices = block.num_vertices
            shape = (self.num_frames, block.num_vertices, 3)
            header = {"descr": self.dtype.str, "fortran_order": False, "shape": shape}
            np.lib.format.write_array_header_2_0(self.member, header)
        check_finite(block, self.done)
        if self.member is not None:
            motion = block.vertices if self.template is None else block.vertices - self.template
            self.member.write(np.ascontiguousarray(motion, self.dtype).tobytes())
        if block.weights is not None and self.weight_names:
            self.weight_columns = block.weights.shape[1]
            self.weights.write(np.ascontiguousarray(block.weights, "<f4").tobytes())
        if block.head_pose is not None:
            self.poses.append(block.head_pose)
        self.done += block.num_frames

    def close(self) -> None:
        """Finish the archive (all ``num_frames`` frames must have been written)."""
        try:
            if self.member is not None:
                self.member.close()
            if self.done != self.num_frames:
                raise TalkmeshError(f"{self.done} frames written of {self.num_frames}")
            if self.weight_columns is not None:
                self._put_weights()
                self._put("weight_names", np.array(self.weight_names, dtype=np.str_))
            if self.poses:
                self._put("head_pose", np.concatenate(self.poses).astype("<f4"))
        finally:
            self.weights.close()
            self.zip.close()

    def _put_weights(self) -> None:
        """The (T, 52) float32 weights member, copied from the temporary file a piece at a time."""
        shape = (self.num_frames, self.weight_columns)
        with self.zip.open("weights.npy", "w", force_zip64=True) as f:
            header = {"descr": "<f4", "fortran_order": False, "shape": shape}
            np.lib.format.write_array_header_1_0(f, header)  # as np.save writes it
            self.weights.seek(0)
            while piece := self.weights.read(1 << 20):
                f.write(piece)


class NpyWriter:
    """Writes [T, V*3] float32 vertex positions (the ``.npy`` layout) a block at a time."""

    def __init__(self, header: Animation | AnimationBlocks, num_frames: int, path: Path) -> None:
        self.file = open(path, "wb")
        self.num_frames, self.done = num_frames, 0

    def write(self, block: Animation) -> None:
        check_finite(block, self.done)
        self.done += block.num_frames
        if self.file.tell() == 0:
            shape = (self.num_frames, block.num_vertices * 3)
            header = {"descr": "<f4", "fortran_order": False, "shape": shape}
            np.lib.format.write_array_header_2_0(self.file, header)
        self.file.write(np.ascontiguousarray(block.vertices, "<f4").tobytes())

    def close(self) -> None:
        self.file.close()


def import_npz(path: Path, faces: np.ndarray | None, fps: float | None) -> Animation:
    """An animation saved by :func:`export_npz` (format 2: offsets) or an older talkmesh
    (format 1: float32 vertices)."""
    check_magic(path, b"PK", ".npz archive")
    check_expansion(path)
    with np.load(path, allow_pickle=False) as z:
        motion = next((k for k in ("offsets", "vertices") if k in z.files), "weights")
        needs = {"offsets": ["template"], "weights": ["template", "basis"], "vertices": []}
        missing = [k for k in (motion, "faces", "fps", *needs[motion]) if k not in z.files]
        if missing:
            raise TalkmeshError(f"{path}: not a talkmesh animation (no {', '.join(missing)})")
        d = {k: z[k] for k in z.files if k not in ("offsets", "vertices")}
        if motion == "weights":  # the compact form: the blend of the ARKit basis
            vertices = _blend(d["weights"], d["basis"])
        else:
            vertices = z[motion].astype(np.float32)
    if int(d.get("format_version", 1)) > NPZ_FORMAT_VERSION:
        raise TalkmeshError(f"{path}: written by a newer talkmesh; upgrade talkmesh to read it")
    if motion != "vertices":
        vertices += np.asarray(d["template"], np.float32)
    weights = d.get("weights")
    pose = d.get("head_pose")
    if pose is not None and pose.shape != (len(vertices), 6):
        raise TalkmeshError(f"{path}: head_pose is {pose.shape}, not ({len(vertices)}, 6)")
    frame = d.get("pose_frame")
    if frame is not None and (
        frame.shape != (4, 4)
        or not np.isfinite(frame).all()
        or abs(np.linalg.det(frame[:3, :3].astype(np.float64))) < 1e-12
    ):
        raise TalkmeshError(
            f"{path}: pose_frame must be a finite, invertible (4, 4) matrix; re-export the "
            "animation"
        )
    stored_fps = float(d["fps"])
    if fps is None and not 0 < stored_fps < float("inf"):  # NaN fails too
        raise TalkmeshError(f"{path}: its frame rate is {stored_fps:g}: pass --fps")
    return Animation(
        vertices=finite(vertices, "vertices"),
        faces=d["faces"] if faces is None else faces,
        fps=fps or stored_fps,
        audio=d.get("audio"),
        sample_rate=int(d.get("sample_rate", SAMPLE_RATE)),
        weights=None if weights is None else finite(weights, "weights"),
        weight_names=[str(n) for n in d.get("weight_names", [])],
        template=d.get("template"),
        basis=d.get("basis"),
        head_pose=None if pose is None else finite(pose.astype(np.float32), "head_pose"),
        pose_frame=None if frame is None else frame.astype(np.float64),
    )


def _blend(weights: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """(T, K) weights, (K, V, 3) basis -> (T, V, 3) offsets ``weights @ basis``."""
    w = finite(np.asarray(weights, np.float32), "weights")
    b = np.asarray(basis, np.float32)
    if b.ndim != 3 or w.ndim != 2 or w.shape[1] != b.shape[0]:
        raise TalkmeshError(f"weights {w.shape} do not match the basis {b.shape}")
    return (w @ b.reshape(len(b), -1)).reshape(len(w), -1, 3)
