"""Rendering: golden image, videos with audio, side-by-side, contact sheets, safe outputs.

Regenerate the golden image after an intended change of the look with
``TALKMESH_UPDATE_GOLDEN=1 pytest tests/test_render.py``.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("moderngl")
pytest.importorskip("imageio_ffmpeg")
Image = pytest.importorskip("PIL.Image")

from fixtures import procedural_head  # noqa: E402

from talkmesh.animation import Animation  # noqa: E402
from talkmesh.errors import TalkmeshError  # noqa: E402
from talkmesh.output import VIDEO_SUFFIXES, write_animation  # noqa: E402
from talkmesh.output.render import (  # noqa: E402
    Renderer,
    contact_sheet,
    render_side_by_side,
    render_video,
)
from talkmesh.output.video import ffmpeg_exe  # noqa: E402

GOLDEN = Path(__file__).parent / "golden" / "render_head_128.png"
SIZE = 128
FPS = 25.0
SAMPLE_RATE = 16_000
MAX_MEAN_ABS_DIFF = 2.0  # of 255, over all pixels and channels
STRONG_DIFF = 48  # a pixel differs strongly when a channel is off by more than this ...
MAX_STRONG_FRACTION = 0.01  # ... and at most this fraction of pixels may


def talking(num_frames: int, audio_seconds: float | None = None) -> Animation:
    """The procedural head opening and closing its 'jaw' (the lower half stretches down)."""
    template, faces = procedural_head()
    opening = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(num_frames) / 10)
    lower = np.minimum(template[:, 1], 0)
    vertices = np.repeat(template[None], num_frames, axis=0)
    vertices[:, :, 1] += 0.4 * opening[:, None] * lower[None]
    audio = None
    if audio_seconds is not None:
        t = np.arange(round(audio_seconds * SAMPLE_RATE)) / SAMPLE_RATE
        audio = (0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32)
    return Animation(vertices, faces, FPS, audio=audio, sample_rate=SAMPLE_RATE, template=template)


def probe(path: Path) -> dict[str, float | str]:
    """Streams of a video: codec names, video frame count and size, decoded audio seconds."""
    exe = ffmpeg_exe()
    info = subprocess.run([exe, "-hide_banner", "-i", str(path)], capture_output=True, text=True)
    video = re.search(r"Video: (\w+).*?, (\d+)x(\d+)", info.stderr)
    audio = re.search(r"Audio: (\w+)", info.stderr)
    assert video, info.stderr
    width, height = int(video.group(2)), int(video.group(3))
    gray = [exe, "-v", "error", "-i", str(path), "-map", "0:v:0", "-f", "rawvideo"]
    pixels = subprocess.run([*gray, "-pix_fmt", "gray", "-"], capture_output=True).stdout
    result: dict[str, float | str] = {
        "video_codec": video.group(1),
        "width": width,
        "height": height,
        "frames": len(pixels) / (width * height),
        "audio_codec": audio.group(1) if audio else "",
    }
    if audio:
        pcm = [exe, "-v", "error", "-i", str(path), "-map", "0:a:0", "-f", "f32le", "-ac", "1"]
        samples = subprocess.run([*pcm, "-ar", "48000", "-"], capture_output=True).stdout
        result["audio_seconds"] = len(samples) / 4 / 48_000
    return result


@pytest.fixture(scope="module")
def head() -> tuple[np.ndarray, np.ndarray]:
    return procedural_head()


def eye_colors(vertices: np.ndarray) -> np.ndarray:
    """(V, 3) sRGB: skin, with two dark eyes on the front of the head."""
    colors = np.tile(np.array([0.86, 0.66, 0.56], dtype=np.float32), (len(vertices), 1))
    for x in (-0.03, 0.03):
        eye = (np.hypot(vertices[:, 0] - x, vertices[:, 1] - 0.03) < 0.012) & (vertices[:, 2] > 0)
        colors[eye] = 0.25
    return colors


def test_golden_image(head):
    vertices, faces = head
    with Renderer(faces, SIZE, vertex_colors=eye_colors(vertices)) as renderer:
        image = renderer.render(vertices)
    if os.environ.get("TALKMESH_UPDATE_GOLDEN") == "1":
        GOLDEN.parent.mkdir(exist_ok=True)
        Image.fromarray(image).save(GOLDEN, optimize=True)
        pytest.skip(f"wrote {GOLDEN}")
    assert GOLDEN.exists(), (
        "no golden image: run TALKMESH_UPDATE_GOLDEN=1 pytest tests/test_render.py"
    )
    golden = np.asarray(Image.open(GOLDEN).convert("RGB"))
    assert image.shape == golden.shape
    diff = np.abs(image.astype(np.int16) - golden.astype(np.int16))
    assert diff.mean() < MAX_MEAN_ABS_DIFF, f"mean abs diff {diff.mean():.2f}"
    strong = (diff.max(axis=-1) > STRONG_DIFF).mean()
    assert strong < MAX_STRONG_FRACTION, f"{strong:.2%} of pixels differ strongly"


def test_render_is_shaded_deterministic_and_follows_vertices(head):
    vertices, faces = head
    with Renderer(faces, (160, 96)) as renderer:
        first = renderer.render(vertices)
        again = renderer.render(vertices)
        moved = renderer.render(vertices + np.array([0.02, 0, 0], dtype=np.float32))
    assert first.shape == (96, 160, 3) and first.dtype == np.uint8
    np.testing.assert_array_equal(first, again)
    face = first[30:66, 60:100].reshape(-1, 3).astype(float)
    background = first[:8, :8].reshape(-1, 3).astype(float)
    assert np.abs(face.mean(0) - background.mean(0)).max() > 20  # the face is not the background
    assert face[:, 0].std() > 3  # shaded, not flat
    assert face[:, 0].mean() > face[:, 2].mean() + 20  # skin: more red than blue
    assert np.abs(moved.astype(int) - first).mean() > 1


def test_renderer_without_supersampling_and_shared_use(head):
    vertices, faces = head
    with Renderer(faces, 64, supersample=1) as renderer:
        frames = list(renderer.render_frames(np.stack([vertices, vertices * 1.1])))
    assert len(frames) == 2 and frames[0].shape == (64, 64, 3)
    assert not np.array_equal(frames[0], frames[1])


def test_winding_does_not_change_the_image(head):
    vertices, faces = head
    pair = np.concatenate([vertices, vertices + np.float32([0.2, 0, 0])])
    outward = np.concatenate([faces, faces + len(vertices)])
    images = []
    for faces_variant in (
        outward,
        outward[:, ::-1],
        np.concatenate([faces, faces[:, ::-1] + len(vertices)]),
    ):
        with Renderer(faces_variant, (96, 64)) as renderer:  # culled, culled, two-sided
            images.append(renderer.render(pair).astype(int))
    assert np.abs(images[1] - images[0]).mean() < 0.5
    assert np.abs(images[2] - images[0]).mean() < 2


def test_three_quarter_camera_turns_the_head(head):
    """Seen from 3/4, the eyes leave the image's centre line; an unknown camera is refused."""
    vertices, faces = head
    centres = []
    for camera in ("front", "three-quarter"):
        with Renderer(faces, 96, vertex_colors=eye_colors(vertices), camera=camera) as renderer:
            image = renderer.render(vertices).astype(int)
        dark = np.argwhere(image.sum(-1) < 3 * 90)  # the eyes: (row, column) of dark pixels
        assert len(dark) > 10
        centres.append(dark[:, 1].mean() / 96)
    assert abs(centres[0] - 0.5) < 0.03 and abs(centres[1] - 0.5) > 0.08, centres
    with pytest.raises(TalkmeshError, match="unknown camera 'side'"):
        Renderer(faces, 32, camera="side")


def test_renderer_rejects_bad_input(head):
    vertices, faces = head
    with Renderer(faces, 32) as renderer:
        with pytest.raises(TalkmeshError, match="vertices"):
            renderer.render(vertices[:10])
        with pytest.raises(TalkmeshError, match="NaN"):
            renderer.render(np.full_like(vertices, np.nan))
    with pytest.raises(TalkmeshError, match="closed"):
        renderer.render(vertices)


@pytest.mark.parametrize("audio_seconds", [1.37, 0.3])
def test_video_audio_and_video_durations_agree(tmp_path, audio_seconds):
    anim = talking(20, audio_seconds=audio_seconds)  # 0.8 s of video; longer, shorter audio
    out = render_video(anim, tmp_path / "talk.mp4", SIZE)
    info = probe(out)
    assert info["video_codec"] == "h264" and info["audio_codec"] == "aac"
    assert (info["width"], info["height"]) == (SIZE, SIZE)
    assert info["frames"] == anim.num_frames
    assert abs(info["audio_seconds"] - anim.duration) <= 1 / anim.fps


def test_video_without_audio_is_silent(tmp_path):
    info = probe(render_video(talking(10), tmp_path / "silent.mp4", 64, progress=True))
    assert info["frames"] == 10 and info["audio_codec"] == ""


@pytest.mark.parametrize("suffix", VIDEO_SUFFIXES)
def test_write_animation_renders_every_video_suffix(tmp_path, suffix):
    out = tmp_path / f"talk{suffix}"
    write_animation(talking(6), out, overwrite=False, size=64)
    info = probe(out)
    assert info["video_codec"] == "h264" and info["frames"] == 6


def test_side_by_side_has_a_panel_per_animation(tmp_path):
    anims = [talking(12, audio_seconds=0.2), talking(7)]
    out = render_side_by_side(anims, ["ours", "baseline"], tmp_path / "cmp.mp4", 96)
    info = probe(out)
    assert (info["width"], info["height"]) == (2 * 96, 96)
    assert info["frames"] == 12  # the shorter animation holds its last frame
    assert abs(info["audio_seconds"] - 12 / FPS) <= 1 / FPS
    with pytest.raises(TalkmeshError, match="label"):
        render_side_by_side(anims, ["one"], tmp_path / "bad.mp4", 96)


def test_contact_sheet(tmp_path):
    sheet = contact_sheet(talking(30), tmp_path / "sheet.png", n=6, cols=3, size=64)
    saved = np.asarray(Image.open(tmp_path / "sheet.png"))
    np.testing.assert_array_equal(saved, sheet)
    assert sheet.shape == (2 * 64 + 3 * 4, 3 * 64 + 4 * 4, 3)


def test_refuses_to_overwrite_an_input(tmp_path):
    source = tmp_path / "input.mp4"
    source.write_bytes(b"precious")
    with pytest.raises(TalkmeshError, match="input"):
        render_video(talking(5), source, 64, inputs=[source])
    assert source.read_bytes() == b"precious"
    with pytest.raises(TalkmeshError, match="must end in"):
        render_video(talking(5), tmp_path / "motion.npz", 64)
    with pytest.raises(TalkmeshError, match="even"):
        render_video(talking(5), tmp_path / "odd.mp4", 63)


def test_failed_render_leaves_the_old_file_and_no_partial_file(tmp_path):
    target = tmp_path / "out.mp4"
    target.write_bytes(b"old video")
    broken = talking(10)
    broken.vertices[6] = np.nan  # rendering fails half-way through
    with pytest.raises(TalkmeshError, match="NaN"):
        render_video(broken, target, 64)
    with pytest.raises(TalkmeshError, match="ffmpeg"):  # an encoder error is a one-line message
        render_video(talking(5, audio_seconds=0.2), target, 64, crf=-5)
    assert target.read_bytes() == b"old video"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mp4"]


def dome(rows: int, cols: int, apex: bool) -> tuple[np.ndarray, np.ndarray]:
    """A head-like ellipsoid cap of rows x cols vertices (+ one at its top, fanned to the first
    row): radii 0.08 x 0.11 x 0.09, facing +z, every vertex in a triangle."""
    lat = np.linspace(0.15, 0.85 * np.pi, rows)[:, None]
    lon = np.linspace(-0.6 * np.pi, 0.6 * np.pi, cols)[None, :]
    grid = np.stack(
        [np.sin(lat) * np.sin(lon), np.cos(lat) + 0 * lon, np.sin(lat) * np.cos(lon)], -1
    )
    vertices = (grid.reshape(-1, 3) * [0.08, 0.11, 0.09]).astype(np.float32)
    at = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = at[:-1, :-1], at[:-1, 1:], at[1:, :-1], at[1:, 1:]
    faces = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)]).reshape(-1, 3)
    if apex:
        top = len(vertices)
        vertices = np.concatenate([vertices, np.float32([[0, 0.11, 0]])])
        fan = np.stack([np.full(cols - 1, top), at[0, :-1], at[0, 1:]], -1)
        faces = np.concatenate([faces, fan])
    return vertices, faces


@pytest.mark.parametrize(
    "name, rows, cols, apex, scale, shift",
    [
        ("FLAME", 81, 62, True, 1.0, (0.0, 0.0, 0.0)),  # 5023 vertices, metres
        ("BIWI", 123, 190, False, 1000.0, (20.0, -30.0, 900.0)),  # 23370, millimetres, off-centre
    ],
)
def test_any_topology_renders_framed_and_shaded(name, rows, cols, apex, scale, shift):
    """Meshes of FLAME's and BIWI's vertex counts, in their units and placements, render in plain
    skin colour, framed (the head fills a good part of the image, not all of it), shaded, from
    both cameras."""
    vertices, faces = dome(rows, cols, apex)
    vertices = scale * vertices + np.float32(shift)
    assert len(vertices) == {"FLAME": 5023, "BIWI": 23370}[name]
    for camera in ("front", "three-quarter"):
        with Renderer(faces, 96, reference=vertices, camera=camera) as renderer:
            image = renderer.render(vertices).astype(float)
        background = image[0, 0]
        head = np.abs(image - background).max(-1) > 20
        assert 0.15 < head.mean() < 0.9, (camera, head.mean())
        skin = image[head]
        assert skin[:, 0].mean() > skin[:, 2].mean() + 20 and skin[:, 0].std() > 3, camera
