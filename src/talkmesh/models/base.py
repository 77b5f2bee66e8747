"""The one interface every learned model family implements, so that ``animate``, ``predict``,
``evaluate``, ``benchmark``, streaming and the server treat all families alike.

A family is an ``nn.Module`` subclass of :class:`MotionModel` in its own folder of this package
(``talkmesh/models/<family>/``), named by one line of
:data:`talkmesh.models.registry.FAMILY_MODELS`; releases (:mod:`talkmesh.models.release`) rebuild
it from its ``cfg`` alone: ``cls(cfg)``, then ``load_state_dict(strict=True)``.

Axis letters: B batch, S audio samples (16 kHz), T motion frames, V vertices, K training speakers.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor, nn

from talkmesh.constants import CHUNK_FRAMES as CHUNK_FRAMES  # the models' chunks
from talkmesh.constants import frames_for_audio as frames_for_audio
from talkmesh.errors import TalkmeshError
from talkmesh.models.framestream import FrameRequest as FrameRequest
from talkmesh.models.framestream import FrameStream as FrameStream
from talkmesh.models.framestream import next_frames as next_frames


class MotionModel(nn.Module, ABC):
    """A learned speech-driven face model: audio (B, S) + template (B, V, 3) -> vertices (B, T, V, 3).

    Subclasses set the class attributes, take their config as the only ``__init__`` argument and
    implement the abstract members; the optional verbs below raise a one-line TalkmeshError when a
    family does not have them.
    """

    family: ClassVar[str]  # the registry key, stored in releases
    config_class: ClassVar[type]  # the frozen dataclass of ``cfg``
    generation_modes: ClassVar[tuple[str, ...]] = ("fast",)  # generate(mode=...); first: default
    cfg: Any  # the config that rebuilds the model: ``type(model)(model.cfg)``

    @classmethod
    @abstractmethod
    def tiny_config(cls, num_vertices: int = 30, styles: tuple[str, ...] = ("a", "b")) -> Any:
        """The smallest config that runs, for tests and examples (``styles`` is ignored by
        families without speaker conditioning)."""

    @property
    @abstractmethod
    def num_vertices(self) -> int:
        """V: the vertices of the meshes the model animates."""

    @property
    @abstractmethod
    def motion_fps(self) -> float:
        """Motion frames per second of ``generate``'s output."""

    @property
    @abstractmethod
    def styles(self) -> tuple[str, ...]:
        """The training speakers' names, ``()`` when the model has no speaker conditioning."""

    @abstractmethod
    def generate(
        self,
        audio: Tensor,
        template: Tensor,
        *,
        style_weights: Tensor | None = None,
        audio_lengths: Tensor | None = None,
        num_frames: int | None = None,
        seed: int = 0,
        mode: str = "fast",
    ) -> Tensor:
        """audio (B, S) at 16 kHz, template (B, V, 3) -> vertices (B, T, V, 3).

        ``style_weights`` (B, K) over :attr:`styles` (None: a family's default; must be None
        without styles); ``num_frames`` T (default: :meth:`default_frames`);
        ``seed`` matters only to sampling models; ``mode`` one of :attr:`generation_modes`.
        """

    @property
    def resampler(self) -> str:
        """How audio at another rate becomes the 16 kHz that ``generate`` takes
        (:mod:`talkmesh.audio.resamplers`): ``polyphase``, the fastest good one; imported
        official models name their official code's, so that they hear what it heard."""
        return "polyphase"

    def default_frames(self, samples: int) -> int:
        """The frames ``generate`` makes for ``samples`` of 16 kHz audio when not told: the
        duration at :attr:`motion_fps` (imported official models count them as the official code
        does, from the speech encoder's features)."""
        return frames_for_audio(samples, self.motion_fps)

    def generate_chunks(
        self,
        audio: Tensor,
        template: Tensor,
        *,
        style_weights: Tensor | None = None,
        num_frames: int | None = None,
        seed: int = 0,
        mode: str = "fast",
        chunk: int = CHUNK_FRAMES,
    ) -> Iterator[Tensor]:
        """:meth:`generate` for one sample, audio (1, S), template (1, V, 3), handed out as
        vertices (1, t, V, 3) of consecutive frames, ``chunk`` at a time. Families that generate
        incrementally override it so that memory does not grow with the audio; this default
        generates the whole sequence first (a :class:`~talkmesh.audio.waveform.Waveform` is
        read whole)."""
        if not isinstance(audio, Tensor):
            audio = torch.from_numpy(np.asarray(audio, np.float32))[None]
        verts = self.generate(
            audio,
            template,
            style_weights=style_weights,
            num_frames=num_frames,
            seed=seed,
            mode=mode,
        )
        for t in range(0, verts.shape[1], chunk):
            yield verts[:, t : t + chunk]

    # -- optional verbs -----------------------------------------------------------------------

    def check_mode(self, mode: str) -> None:
        """A one-line error unless ``mode`` is one of :attr:`generation_modes`."""
        if mode not in self.generation_modes:
            raise TalkmeshError(
                f"mode {mode} is not a {self.family} generation mode: use "
                f"{', '.join(self.generation_modes)}"
            )

    def mode_note(self, mode: str) -> str | None:
        """A note for the user about what ``mode`` computes on this model (None: nothing to say)."""
        return None

    def int8_copy(self, layers: str) -> MotionModel:
        """A copy whose ``layers`` (one of :data:`talkmesh.constants.INT8_LAYERS`) run in int8 on
        the CPU."""
        raise TalkmeshError(f"--int8 applies to CodeTalker models; this is a {self.family} model")

    def reconstruct(self, vertices: Tensor, template: Tensor) -> Tensor:
        """vertices (B, T, V, 3), template (B, V, 3) -> (B, T, V, 3) through the model's motion
        autoencoder alone (what its codes keep)."""
        raise TalkmeshError(f"{self.family} models have no motion autoencoder to reconstruct with")

    @property
    def codebook_size(self) -> int:
        """The number of codes :meth:`motion_codes` draws from."""
        raise TalkmeshError(f"{self.family} models have no motion codebook")

    def motion_codes(self, vertices: Tensor, template: Tensor) -> Tensor:
        """vertices (B, T, V, 3), template (B, V, 3) -> int codes (B, T', H) of the motion."""
        raise TalkmeshError(f"{self.family} models have no motion codebook")

    def open_frame_stream(
        self,
        style_weights: np.ndarray | None,
        lookahead_ms: float | None,
        template: np.ndarray | None = None,
    ) -> FrameStream:
        """A new :class:`FrameStream`; ``style_weights`` (K,) (None: the mean style);
        ``lookahead_ms`` None: the largest the model was trained for; ``template`` (V, 3) the
        head it drives, for a model whose style reads the head."""
        raise TalkmeshError(f"this {self.family} model cannot stream")

    def onnx_graphs(self) -> tuple[nn.Module, nn.Module]:
        """The speech encoder and one generation step as modules that export to ONNX
        (:mod:`talkmesh.models.onnx`)."""
        raise TalkmeshError(
            f"export-onnx exports CodeTalker models (the bundled codetalker-synth); this is a "
            f"{self.family} model"
        )
