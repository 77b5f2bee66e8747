"""The :class:`Animation` that every animator returns and every renderer/exporter consumes."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import TalkmeshError


@dataclass
class Animation:
    """A talking face.

    Attributes:
        vertices: (T, V, 3) float32 vertex positions in metres (not offsets).
        faces: (F, 3) int32 triangle indices.
        fps: frames per second.
        audio: optional (S,) float32 mono waveform at ``sample_rate``.
        sample_rate: sample rate of ``audio`` in Hz.
        weights: optional (T, 52) float32 ARKit blendshape weights in [0, 1].
        weight_names: names of the columns of ``weights`` (ARKit order).
        template: optional (V, 3) neutral face the motion is relative to.
        basis: optional (52, V, 3) blendshape offsets, so ``vertices ~ template + weights @ basis``
            (lets exporters write morph targets instead of per-frame vertices).
        audio_file: optional speech file ``audio`` was read from: videos mux its sound as it is
            (its own sample rate and channels), not the 16 kHz copy the model hears.
        to_gltf: optional (4, 4) matrix taking the vertices' frame (a user's head in its own
            units and axes, e.g. millimetres, Z-up) to glTF's metres and +y up: a .glb keeps the
            vertices as they are and carries it as its root node, so viewers stand the head up.
        colors: optional (V, 3) sRGB vertex colours in [0, 1] (the bundled head's skin, lips,
            irises: :func:`talkmesh.face.look.head_colors`), written as a .glb's ``COLOR_0``.
        head_pose: optional (T, 6) rigid head motion, pitch, yaw, roll (radians) and a
            translation (the vertices' units): the vertices stay in the head's own frame, as
            ARKit keeps the face apart from the head's transform; a vertex ``v`` is seen at
            ``R @ v + t`` (:mod:`talkmesh.face.head_motion`). Videos, .glb head nodes, Live Link
            head columns and .npz files carry it.
        pose_frame: optional (4, 4) similarity placing ``head_pose``'s frame (the bundled head's
            axes and metres, where the pose was made) in the vertices' frame: a user's head
            (``animate --head``) in its own units and axes is posed as ``F (R F^-1 u + t)``
            (:func:`talkmesh.face.head_motion.pose_vertices`); None: the same frame.
        phones: optional timed phones ``(ARPAbet label, start s, end s)`` the motion was made
            from (the procedural animator's recognised or aligned phones): viseme exports drive
            the tongue visemes from them.
    """

    vertices: np.ndarray
    faces: np.ndarray
    fps: float
    audio: np.ndarray | None = None
    sample_rate: int = SAMPLE_RATE
    weights: np.ndarray | None = None
    weight_names: list[str] = field(default_factory=list)
    template: np.ndarray | None = None
    basis: np.ndarray | None = None
    audio_file: Path | None = None
    to_gltf: np.ndarray | None = None
    colors: np.ndarray | None = None
    head_pose: np.ndarray | None = None
    phones: list[tuple[str, float, float]] | None = None
    pose_frame: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float32)
        self.faces = np.asarray(self.faces, dtype=np.int32)
        if self.vertices.ndim != 3 or self.vertices.shape[2] != 3:
            raise TalkmeshError(f"animation vertices must be (T, V, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise TalkmeshError(f"animation faces must be (F, 3) triangles, got {self.faces.shape}")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= self.num_vertices):
            raise TalkmeshError("animation faces index vertices that do not exist")
        if not 0 < self.fps < float("inf"):  # NaN fails too: it would be written into every file
            raise TalkmeshError(f"fps must be positive and finite, got {self.fps}")
        if self.audio is not None:
            self.audio = np.asarray(self.audio, dtype=np.float32).reshape(-1)
        if self.weights is not None:
            self.weights = np.asarray(self.weights, dtype=np.float32)
            if self.weights.shape[0] != self.num_frames:
                raise TalkmeshError(
                    f"weights have {self.weights.shape[0]} frames but vertices have {self.num_frames}"
                )
            if len(self.weight_names) != self.weights.shape[1]:
                raise TalkmeshError("weight_names must name every column of weights")
        if self.head_pose is not None:
            self.head_pose = np.asarray(self.head_pose, dtype=np.float32)
            if self.head_pose.shape != (self.num_frames, 6):
                raise TalkmeshError(
                    f"head pose must be ({self.num_frames}, 6), got {self.head_pose.shape}"
                )
        if self.template is not None:
            self.template = np.asarray(self.template, dtype=np.float32)
        if self.basis is not None:
            self.basis = np.asarray(self.basis, dtype=np.float32)

    @property
    def num_frames(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[1])

    @property
    def duration(self) -> float:
        """Length in seconds of the motion."""
        return self.num_frames / self.fps


@dataclass
class AnimationBlocks:
    """An :class:`Animation` made a block of frames at a time, so that long audio never holds all
    its (T, V, 3) vertices: what every field means is as in :class:`Animation`; ``blocks`` yields
    the consecutive frames as Animations (vertices and, when ``weight_names`` is set, weights;
    their head pose when there is one), once. File writers stream it
    (:func:`talkmesh.output.streaming.save_blocks`); :meth:`collect` makes the whole Animation."""

    blocks: Iterator[Animation]
    num_frames: int
    faces: np.ndarray
    fps: float
    audio: np.ndarray | None = None
    sample_rate: int = SAMPLE_RATE
    weight_names: list[str] = field(default_factory=list)
    template: np.ndarray | None = None
    basis: np.ndarray | None = None
    audio_file: Path | None = None
    to_gltf: np.ndarray | None = None
    phones: list[tuple[str, float, float]] | None = None
    pose_frame: np.ndarray | None = None

    def collect(self) -> Animation:
        """All frames as one :class:`Animation` (filled in place: one copy of the vertices)."""
        vertices: np.ndarray | None = None
        weights: np.ndarray | None = None
        poses: list[np.ndarray] = []
        t = 0
        for block in self.blocks:
            if vertices is None:
                vertices = np.empty((self.num_frames, block.num_vertices, 3), np.float32)
                if block.weights is not None:
                    weights = np.empty((self.num_frames, block.weights.shape[1]), np.float32)
            n = block.num_frames
            vertices[t : t + n] = block.vertices
            if weights is not None:
                weights[t : t + n] = block.weights
            if block.head_pose is not None:
                poses.append(block.head_pose)
            t += n
        assert vertices is not None and t == self.num_frames, (t, self.num_frames)
        return Animation(
            vertices=vertices,
            faces=self.faces,
            fps=self.fps,
            audio=self.audio,
            sample_rate=self.sample_rate,
            weights=weights,
            weight_names=list(self.weight_names) if weights is not None else [],
            template=self.template,
            basis=self.basis,
            audio_file=self.audio_file,
            to_gltf=self.to_gltf,
            head_pose=np.concatenate(poses) if poses else None,
            phones=self.phones,
            pose_frame=self.pose_frame,
        )
