"""talkmesh: speech-driven 3D facial animation.

import talkmesh
anim = talkmesh.animate("speech.wav")           # the bundled CodeTalker on the bundled head
talkmesh.save_animation(anim, "speech.glb")      # glTF morph-target animation
talkmesh.render_video(anim, "speech.mp4")        # shaded head, with the audio
model = talkmesh.load_model("codetalker-synth")  # a release by name or path, offline
"""

from __future__ import annotations

from talkmesh.animation import Animation
from talkmesh.errors import TalkmeshError
from talkmesh.face.assets import Head, list_identities, load_head, load_template
from talkmesh.version import __version__

__all__ = [
    "Animation",
    "Head",
    "TalkmeshError",
    "__version__",
    "animate",
    "list_identities",
    "load_animation",
    "load_audio",
    "load_head",
    "load_model",
    "load_template",
    "open_stream",
    "render_video",
    "save_animation",
]


def __getattr__(name: str):
    # Heavier modules load on first use so `import talkmesh` stays fast.
    if name == "animate":
        from talkmesh.pipeline import animate

        return animate
    if name in ("save_animation", "load_animation"):
        from talkmesh.output import formats as io

        return getattr(io, name)
    if name == "load_audio":
        from talkmesh.audio.loading import load_audio

        return load_audio
    if name == "load_model":
        from talkmesh.models.release import load_model

        return load_model
    if name == "open_stream":
        from talkmesh.serve.stream import open_stream

        return open_stream
    if name == "render_video":
        from talkmesh.output.render import render_video

        return render_video
    raise AttributeError(f"module 'talkmesh' has no attribute {name!r}")
