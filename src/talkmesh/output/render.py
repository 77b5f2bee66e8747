"""Headless rendering of talking faces to images, mp4 videos and contact sheets.

One OpenGL context (EGL; Mesa's llvmpipe is enough) per :class:`Renderer`, created once and reused
for every frame: each frame recomputes the vertex normals, rewrites the same vertex buffer, draws
the face at twice the resolution and averages 2x2 pixels while compositing it over the background
(supersampling: llvmpipe's 4x MSAA is slower for the same quality). Lighting is evaluated per
vertex (two lights, wrapped Lambert and a soft specular), which is smooth at the bundled head's
density and keeps a software rasteriser above 60 frames/s at 512x512.

Videos are encoded by one ffmpeg process (the static binary of ``imageio-ffmpeg``) that reads raw
RGBA frames on stdin and muxes the audio from a temporary wav in the same pass. Every file is
written to a temporary name next to the target and renamed at the end, so a failed render never
leaves a partial file or destroys an existing one.

Coordinates follow the bundled head: metres, +y up, +z towards the viewer. The camera looks down
-z at the bounding box of a reference mesh (the template or the first frame) so the face fills
the image.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from fractions import Fraction
from pathlib import Path
from typing import IO, TYPE_CHECKING

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import soundfile
from tqdm import tqdm

from talkmesh.animation import Animation
from talkmesh.errors import MissingDependencyError, TalkmeshError

if TYPE_CHECKING:
    import moderngl

# Camera and image.
SUPERSAMPLE = 2  # render at 2x and average 2x2 pixels: 4 samples per pixel
FOV_DEG = 18.0  # a portrait lens: little perspective distortion of the nose
FRAME_MARGIN = 1.08  # the reference bounding box fills 1 / FRAME_MARGIN of the image height
MIN_SIZE, MAX_SIZE = 16, 4096
MIN_PART_VOLUME = 1e-5  # of the mesh's bounding cube: flatter parts are shaded two-sided

# Materials and lights. Colours are sRGB in [0, 1]; light directions point towards the lights in
# view space (x right, y up, z towards the viewer).
SKIN_SRGB = (0.86, 0.66, 0.56)
# Colours of the bundled head's parts (``Regions.vertex_part``): skin, eye, teeth, tongue.
PART_SRGB = np.array(
    [SKIN_SRGB, (0.28, 0.22, 0.20), (0.93, 0.91, 0.85), (0.75, 0.40, 0.40)], dtype=np.float32
)
BACKGROUND_TOP_SRGB = (0.95, 0.95, 0.96)
BACKGROUND_BOTTOM_SRGB = (0.72, 0.73, 0.76)
LIGHT_DIRS = ((-0.45, 0.55, 0.75), (0.75, 0.05, 0.45))  # key: upper left front; fill: right
LIGHT_LINEAR = ((1.00, 0.96, 0.92), (0.28, 0.31, 0.36))  # warm key, weaker cool fill
AMBIENT_LINEAR = (0.13, 0.13, 0.15)
RIM_STRENGTH = 0.12  # a faint rim light separates the silhouette from the background
WRAP = 0.3  # wrapped Lambert: light bleeds past the terminator, as through skin
SPEC_STRENGTH = 0.10
SHININESS = 20.0

# Encoding.
VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov")
VIDEO_CRF = 18  # visually lossless H.264
VIDEO_PRESET = "veryfast"
AUDIO_BITRATE = "128k"
AUDIO_RATE = 48_000  # AAC frames are 1024 samples: 21 ms at 48 kHz, so ends align within a frame
FFMPEG_FINISH_TIMEOUT_S = 120  # time ffmpeg gets to finish after its last frame
LABEL_TEXT_HEIGHT = 0.06  # label text height as a fraction of the panel height
LABEL_MIN_PX = 9  # smallest legible label text
LABEL_BOX_ALPHA = 0.55
SHEET_GUTTER = 4  # pixels between contact sheet cells

_MESH_VERTEX_SHADER = """
#version 330
uniform mat4 proj;
uniform vec3 eye;
uniform vec3 light_dir[2];
uniform vec3 light_col[2];
uniform vec3 ambient;
uniform float rim_strength;
uniform float wrap;
uniform float spec_strength;
uniform float shininess;
uniform float normal_sign;  // +1 or -1 for consistently wound meshes; 0: turn towards the viewer
in vec3 in_pos;
in vec3 in_normal;
in vec3 in_color;
out vec3 v_color;
void main() {
    vec3 p = in_pos - eye;  // the camera does not rotate: view space is world space shifted
    vec3 v = normalize(-p);
    vec3 n = in_normal;
    n *= normal_sign != 0.0 ? normal_sign : (dot(n, v) < 0.0 ? -1.0 : 1.0);
    vec3 albedo = in_color * in_color;  // sRGB -> linear with gamma 2
    float facing = max(dot(n, v), 0.0);
    vec3 col = albedo * ambient + rim_strength * (1.0 - facing) * (1.0 - facing) * ambient;
    for (int i = 0; i < 2; i++) {
        float diffuse = max((dot(n, light_dir[i]) + wrap) / (1.0 + wrap), 0.0);
        float spec = pow(max(dot(n, normalize(light_dir[i] + v)), 0.0), shininess);
        col += light_col[i] * (albedo * diffuse + spec_strength * spec);
    }
    v_color = sqrt(clamp(col, 0.0, 1.0));  // linear -> sRGB with gamma 2
    gl_Position = proj * vec4(p, 1.0);
}
"""

_COLOR_FRAGMENT_SHADER = """
#version 330
in vec3 v_color;
out vec4 f_color;
void main() {
    f_color = vec4(v_color, 1.0);
}
"""

# One triangle covering the screen samples the supersampled face at the centre of each 2x2 block
# (bilinear filtering averages the four) and composites it over a vertical gradient. The mesh
# projection flips y so that rows read out top first: texture row 0 is the top of the image.
_COMPOSITE_VERTEX_SHADER = """
#version 330
uniform vec3 top;
uniform vec3 bottom;
out vec2 v_uv;
out vec3 v_background;
void main() {
    vec2 p = vec2(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0);
    v_uv = 0.5 * p + 0.5;
    v_background = mix(top, bottom, v_uv.y);
    gl_Position = vec4(p, 0.0, 1.0);
}
"""

_COMPOSITE_FRAGMENT_SHADER = """
#version 330
uniform sampler2D face;
in vec2 v_uv;
in vec3 v_background;
out vec4 f_color;
void main() {
    vec4 c = texture(face, v_uv);  // premultiplied: alpha is the face's coverage of the pixel
    f_color = vec4(c.rgb + (1.0 - c.a) * v_background, 1.0);
}
"""


def _import_moderngl():
    try:
        import moderngl
    except ImportError as e:
        raise MissingDependencyError("moderngl", "render", "Rendering") from e
    return moderngl


def _import_pil():
    try:
        from PIL import Image, ImageDraw, ImageFont
    except ImportError as e:
        raise MissingDependencyError("pillow", "render", "Drawing labels and writing PNGs") from e
    return Image, ImageDraw, ImageFont


def _ffmpeg_exe() -> str:
    try:
        import imageio_ffmpeg
    except ImportError as e:
        raise MissingDependencyError("imageio-ffmpeg", "render", "Writing videos") from e
    return imageio_ffmpeg.get_ffmpeg_exe()


def _size_pair(size: int | tuple[int, int]) -> tuple[int, int]:
    width, height = (size, size) if isinstance(size, int) else (int(size[0]), int(size[1]))
    if not (MIN_SIZE <= width <= MAX_SIZE and MIN_SIZE <= height <= MAX_SIZE):
        raise TalkmeshError(
            f"image size must be {MIN_SIZE} to {MAX_SIZE} pixels a side, got {width}x{height}"
        )
    return width, height


def _video_size(size: int | tuple[int, int]) -> tuple[int, int]:
    width, height = _size_pair(size)
    if width % 2 or height % 2:
        raise TalkmeshError(f"video width and height must be even for H.264, got {width}x{height}")
    return width, height


def create_context() -> moderngl.Context:
    """A headless OpenGL 3.3 context, to share between several :class:`Renderer`.

    EGL first (Linux without a display); the platform's default (macOS, Windows) if that fails.
    """
    moderngl = _import_moderngl()
    try:
        return moderngl.create_standalone_context(backend="egl", require=330)
    except Exception as e:  # any EGL or driver failure is an environment problem to fix
        egl_error = (str(e).strip().splitlines() or [type(e).__name__])[0]
    try:
        return moderngl.create_standalone_context(require=330)
    except Exception:
        raise TalkmeshError(
            f"could not create a headless OpenGL context ({egl_error}): install Mesa's EGL "
            "(Debian: `apt-get install libegl1 libgl1-mesa-dri`)"
        ) from None


class _NormalOperator:
    """Vertex normals of a fixed topology as sparse matrix products (about 1 ms for 9k faces).

    Args:
        faces: (F, 3) triangles.
        num_vertices: V.
    """

    def __init__(self, faces: np.ndarray, num_vertices: int) -> None:
        num_faces = len(faces)
        rows = np.arange(num_faces).repeat(2)
        signs = np.tile(np.array([1.0, -1.0], dtype=np.float32), num_faces)
        shape = (num_faces, num_vertices)
        # Edge operators: (F, V) @ (V, 3) -> (F, 3) edges v1 - v0 and v2 - v0.
        self.edge1 = scipy.sparse.csr_matrix((signs, (rows, faces[:, [1, 0]].ravel())), shape=shape)
        self.edge2 = scipy.sparse.csr_matrix((signs, (rows, faces[:, [2, 0]].ravel())), shape=shape)
        # Incidence: (V, F) @ (F, 3) face normals -> (V, 3) sums over each vertex's faces.
        ones = np.ones(3 * num_faces, dtype=np.float32)
        incidence = (ones, (faces.ravel(), np.arange(num_faces).repeat(3)))
        self.incidence = scipy.sparse.csr_matrix(incidence, shape=(num_vertices, num_faces))
        self._face_normals = np.empty((num_faces, 3), dtype=np.float32)

    def __call__(self, vertices: np.ndarray) -> np.ndarray:
        """(V, 3) vertices -> (V, 3) unit normals, the area-weighted mean of the face normals."""
        e1, e2 = self.edge1 @ vertices, self.edge2 @ vertices
        fn = self._face_normals  # the cross product's length is twice the area: area weighting
        np.subtract(e1[:, 1] * e2[:, 2], e1[:, 2] * e2[:, 1], out=fn[:, 0])
        np.subtract(e1[:, 2] * e2[:, 0], e1[:, 0] * e2[:, 2], out=fn[:, 1])
        np.subtract(e1[:, 0] * e2[:, 1], e1[:, 1] * e2[:, 0], out=fn[:, 2])
        normals = self.incidence @ fn
        normals /= np.maximum(np.sqrt(np.einsum("ij,ij->i", normals, normals)), 1e-20)[:, None]
        return normals


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) vertices, (F, 3) faces -> (V, 3) float32 unit area-weighted vertex normals."""
    vertices = np.asarray(vertices, dtype=np.float32)
    return _NormalOperator(np.asarray(faces, dtype=np.int64), len(vertices))(vertices)


def winding_sign(vertices: np.ndarray, faces: np.ndarray) -> int:
    """+1 if the (F, 3) faces wind consistently outwards around the (V, 3) vertices, -1 if
    consistently inwards, 0 if not (then back faces are not culled and the shading is two-sided).

    Every connected part must enclose some volume with the same sign: a flat or inside-out part
    (a backdrop plane, a separately modelled eyeball) turns culling off.
    """
    faces = np.asarray(faces, dtype=np.int64)
    num_vertices = len(vertices)
    edges = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    # Consistent winding traverses every shared edge once in each direction.
    if len(np.unique(edges[:, 0] * num_vertices + edges[:, 1])) != len(edges):
        return 0
    links = scipy.sparse.coo_matrix(
        (np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(num_vertices, num_vertices)
    )
    _, part = scipy.sparse.csgraph.connected_components(links, directed=False)
    face_part = part[faces[:, 0]]
    p = np.asarray(vertices, dtype=np.float64)
    volumes = []
    for k in np.unique(face_part):
        tri = p[faces[face_part == k]]  # (Fk, 3, 3)
        tri = tri - tri.reshape(-1, 3).mean(axis=0)
        volumes.append(np.einsum("ij,ij->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6)
    volumes = np.array(volumes)
    extent = np.ptp(p[np.unique(faces)], axis=0).max()
    if (np.abs(volumes) < MIN_PART_VOLUME * extent**3).any():
        return 0
    return int(np.sign(volumes[0])) if len(np.unique(np.sign(volumes))) == 1 else 0


def head_vertex_colors(num_vertices: int) -> np.ndarray | None:
    """(V, 3) sRGB colours of the bundled head's parts, or None if the mesh is not that head."""
    try:
        from talkmesh.face.assets import load_head

        head = load_head()
    except Exception:  # no bundled head (or a broken one): the caller renders plain skin
        return None
    if head.num_vertices != num_vertices:
        return None
    return PART_SRGB[np.clip(head.regions.vertex_part, 0, len(PART_SRGB) - 1)]


def _perspective(fov_y: float, aspect: float, near: float, far: float) -> np.ndarray:
    """(4, 4) OpenGL projection, with y flipped so that the framebuffer reads out top row first."""
    f = 1.0 / math.tan(fov_y / 2)
    return np.array(
        [
            [f / aspect, 0, 0, 0],
            [0, -f, 0, 0],
            [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)],
            [0, 0, -1, 0],
        ],
        dtype=np.float32,
    )


class Renderer:
    """Renders frames of one mesh topology with a single OpenGL context.

    Args:
        faces: (F, 3) int triangles.
        size: image size in pixels: an int for a square, or (width, height).
        vertex_colors: optional (V, 3) sRGB colours in [0, 1]; default skin colour everywhere.
        reference: optional (V, 3) vertices to aim the camera at; default the first rendered frame.
        fov_deg: vertical field of view of the camera.
        supersample: render at this multiple of ``size`` and average (1 turns anti-aliasing off).
        ctx: an OpenGL context to share (see :func:`create_context`); by default the renderer
            creates its own and releases it in :meth:`close`.

    Use it as a context manager, or call :meth:`close`, to free the context.
    """

    def __init__(
        self,
        faces: np.ndarray,
        size: int | tuple[int, int] = (512, 512),
        *,
        vertex_colors: np.ndarray | None = None,
        reference: np.ndarray | None = None,
        fov_deg: float = FOV_DEG,
        supersample: int = SUPERSAMPLE,
        ctx: moderngl.Context | None = None,
    ) -> None:
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise TalkmeshError(f"faces must be a non-empty (F, 3) array, got {faces.shape}")
        if faces.min() < 0:
            raise TalkmeshError("faces must not have negative vertex indices")
        self.faces = faces.astype(np.int32)
        self.num_vertices = int(faces.max()) + 1
        if vertex_colors is not None:
            vertex_colors = np.asarray(vertex_colors, dtype=np.float32)
            if vertex_colors.ndim != 2 or vertex_colors.shape[1] != 3:
                raise TalkmeshError(f"vertex colours must be (V, 3), got {vertex_colors.shape}")
            if len(vertex_colors) < self.num_vertices:
                raise TalkmeshError(
                    f"{len(vertex_colors)} vertex colours for {self.num_vertices} vertices"
                )
            self.num_vertices = len(vertex_colors)
        self.width, self.height = _size_pair(size)
        if supersample not in (1, 2):
            raise TalkmeshError(f"supersample must be 1 or 2, got {supersample}")
        self.fov_y = math.radians(fov_deg)
        self._normals = _NormalOperator(self.faces.astype(np.int64), self.num_vertices)
        self._framed = False
        self._flags = 0
        self._front_face = "ccw"

        moderngl = _import_moderngl()
        self._owns_ctx = ctx is None
        self.ctx = create_context() if ctx is None else ctx
        c = self.ctx
        self._depth_test, self._cull_face = moderngl.DEPTH_TEST, moderngl.CULL_FACE
        # The face is drawn into a supersampled texture, then composited into the output image.
        big = (self.width * supersample, self.height * supersample)
        self._face_texture = c.texture(big, 4)
        self._face_texture.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self._face_texture.repeat_x = self._face_texture.repeat_y = False
        self._depth = c.depth_renderbuffer(big)
        self._face_fbo = c.framebuffer(self._face_texture, self._depth)
        self._image = c.renderbuffer((self.width, self.height), 4)
        self._image_fbo = c.framebuffer(self._image)
        self._rgba = np.empty((self.height, self.width, 4), dtype=np.uint8)

        self._program = c.program(
            vertex_shader=_MESH_VERTEX_SHADER, fragment_shader=_COLOR_FRAGMENT_SHADER
        )
        uniforms = {
            "light_dir": [tuple(np.array(d) / np.linalg.norm(d)) for d in LIGHT_DIRS],
            "light_col": LIGHT_LINEAR,
            "ambient": AMBIENT_LINEAR,
            "rim_strength": RIM_STRENGTH,
            "wrap": WRAP,
            "spec_strength": SPEC_STRENGTH,
            "shininess": SHININESS,
        }
        for name, value in uniforms.items():
            self._program[name].value = value
        # Positions and normals interleaved in one buffer, rewritten in place every frame.
        self._attributes = np.zeros((self.num_vertices, 6), dtype=np.float32)
        self._vbo = c.buffer(reserve=self._attributes.nbytes, dynamic=True)
        colors = np.empty((self.num_vertices, 3), dtype=np.float32)
        colors[:] = SKIN_SRGB if vertex_colors is None else np.clip(vertex_colors, 0, 1)
        self._color_vbo = c.buffer(colors.tobytes())
        self._ibo = c.buffer(self.faces.tobytes())
        self._vao = c.vertex_array(
            self._program,
            [(self._vbo, "3f 3f", "in_pos", "in_normal"), (self._color_vbo, "3f", "in_color")],
            index_buffer=self._ibo,
            index_element_size=4,
        )
        self._composite = c.program(
            vertex_shader=_COMPOSITE_VERTEX_SHADER, fragment_shader=_COMPOSITE_FRAGMENT_SHADER
        )
        self._composite["top"].value = BACKGROUND_TOP_SRGB
        self._composite["bottom"].value = BACKGROUND_BOTTOM_SRGB
        self._composite["face"].value = 0
        self._composite_vao = c.vertex_array(self._composite, [])
        if reference is not None:
            self.frame(reference)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height

    def frame(self, vertices: np.ndarray) -> None:
        """Aims the camera at (V, 3) vertices so that their bounding box fills the image, and
        decides from their winding whether back faces can be culled."""
        vertices = self._check_vertices(vertices)
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        center = (lo + hi) / 2
        aspect = self.width / self.height
        half = max((hi[1] - lo[1]) / 2, (hi[0] - lo[0]) / 2 / aspect, 1e-6) * FRAME_MARGIN
        distance = half / math.tan(self.fov_y / 2)  # the front of the box fills the view
        depth = max(float(hi[2] - lo[2]), 1e-6)
        near, far = distance / 2, distance + 2 * depth
        self._program["eye"].value = (float(center[0]), float(center[1]), float(hi[2] + distance))
        self._program["proj"].write(_perspective(self.fov_y, aspect, near, far).T.tobytes())
        sign = winding_sign(vertices, self.faces)
        self._program["normal_sign"].value = float(sign)
        self._flags = self._depth_test | self._cull_face if sign else self._depth_test
        # The projection flips y, which turns counter-clockwise outward faces clockwise.
        self._front_face = "cw" if sign > 0 else "ccw"
        self._framed = True

    def render(self, vertices: np.ndarray) -> np.ndarray:
        """(V, 3) vertices in metres -> (H, W, 3) uint8 RGB image (a new array)."""
        image = np.empty((self.height, self.width, 3), dtype=np.uint8)
        return self._draw(vertices, image)

    def render_frames(self, frames: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
        """Renders (V, 3) vertex frames (e.g. a (T, V, 3) array) lazily -> (H, W, 3) uint8."""
        for vertices in frames:
            yield self.render(vertices)

    def _check_vertices(self, vertices: np.ndarray) -> np.ndarray:
        vertices = np.asarray(vertices, dtype=np.float32)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise TalkmeshError(f"vertices must be (V, 3), got {vertices.shape}")
        if len(vertices) < self.num_vertices:
            raise TalkmeshError(
                f"the faces need {self.num_vertices} vertices but the frame has {len(vertices)}"
            )
        if not np.isfinite(vertices).all():
            raise TalkmeshError("cannot render vertices that are NaN or infinite")
        return vertices[: self.num_vertices]

    def _draw(self, vertices: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Renders into ``out``, a contiguous (H, W, 3) RGB or (H, W, 4) RGBA uint8 array, by
        default the internal RGBA buffer, which the next frame overwrites."""
        if self.ctx is None:
            raise TalkmeshError("this renderer has been closed")
        vertices = self._check_vertices(vertices)
        if not self._framed:
            self.frame(vertices)
        self._attributes[:, :3] = vertices
        self._attributes[:, 3:] = self._normals(vertices)
        self._vbo.write(self._attributes)

        c = self.ctx
        self._face_fbo.use()
        self._face_fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        c.enable_only(self._flags)  # the context may be shared: set all the state used
        c.front_face = self._front_face
        self._vao.render()
        self._image_fbo.use()
        c.enable_only(c.NOTHING)
        self._face_texture.use(0)
        self._composite_vao.render(vertices=3)
        out = self._rgba if out is None else out
        self._image_fbo.read_into(out, components=out.shape[2], alignment=1)
        return out

    def close(self) -> None:
        """Releases the OpenGL objects, and the context if the renderer created it."""
        if self.ctx is None:
            return
        objects = [self._vao, self._composite_vao, self._vbo, self._color_vbo, self._ibo]
        objects += [self._program, self._composite, self._face_fbo, self._image_fbo]
        objects += [self._face_texture, self._depth, self._image]
        for obj in objects:
            obj.release()
        if self._owns_ctx:
            self.ctx.release()
        self.ctx = None

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _renderer_for(
    anim: Animation,
    size: int | tuple[int, int],
    vertex_colors: np.ndarray | None = None,
    ctx: moderngl.Context | None = None,
) -> Renderer:
    """A renderer aimed at the animation's template (or first frame), in the head's colours."""
    template = anim.template
    reference = (
        template if template is not None and template.shape == anim.vertices.shape[1:] else None
    )
    if vertex_colors is None:
        vertex_colors = head_vertex_colors(anim.num_vertices)
    return Renderer(
        anim.faces,
        size,
        vertex_colors=vertex_colors,
        reference=anim.vertices[0] if reference is None else reference,
        ctx=ctx,
    )


def render_video(
    anim: Animation,
    path: str | os.PathLike,
    size: int | tuple[int, int] = 512,
    *,
    vertex_colors: np.ndarray | None = None,
    inputs: Iterable[str | os.PathLike] = (),
    crf: int = VIDEO_CRF,
    progress: bool = False,
) -> Path:
    """Renders an animation to an mp4 (H.264 yuv420p, with AAC audio if it has audio).

    Args:
        anim: the animation; its audio is padded or trimmed to the duration of its frames.
        path: output .mp4 (or .m4v/.mov); replaced only once the video is complete.
        size: frame size in pixels (even): an int for a square, or (width, height).
        vertex_colors: optional (V, 3) sRGB colours; default the bundled head's part colours
            when the mesh is that head, else skin.
        inputs: files the caller read from; writing over one of them is refused.
        crf: H.264 quality (lower is better; 18 is visually lossless).
        progress: show a progress bar on stderr.

    Returns:
        The path written.
    """
    size, inputs = _video_size(size), list(inputs)
    _check_output(path, VIDEO_SUFFIXES, inputs)
    with _renderer_for(anim, size, vertex_colors) as renderer:
        frames = (renderer._draw(v) for v in anim.vertices)
        return _write_video(
            frames,
            anim.num_frames,
            size,
            anim.fps,
            path,
            audio=anim.audio,
            sample_rate=anim.sample_rate,
            inputs=inputs,
            crf=crf,
            progress=progress,
        )


def render_side_by_side(
    anims: Sequence[Animation],
    labels: Sequence[str],
    path: str | os.PathLike,
    size: int | tuple[int, int] = 512,
    *,
    inputs: Iterable[str | os.PathLike] = (),
    crf: int = VIDEO_CRF,
    progress: bool = False,
) -> Path:
    """Renders animations next to each other, each labelled, into one mp4.

    Every panel is ``size`` and is sampled at the first animation's frame rate; shorter animations
    hold their last frame until the longest ends. The audio is that of the first animation that
    has audio, padded or trimmed to the video.

    Args:
        anims: the N animations, left to right (their meshes may differ).
        labels: N labels drawn at the top of the panels.
        path: output .mp4 (or .m4v/.mov); replaced only once the video is complete.
        size: panel size in pixels (even): an int for a square, or (width, height).
        inputs: files the caller read from; writing over one of them is refused.
        crf: H.264 quality.
        progress: show a progress bar on stderr.

    Returns:
        The path written; the video is (N * width) x height.
    """
    if not anims or len(anims) != len(labels):
        raise TalkmeshError(f"need one label per animation, got {len(anims)} and {len(labels)}")
    (width, height), inputs = _video_size(size), list(inputs)
    _check_output(path, VIDEO_SUFFIXES, inputs)
    fps = anims[0].fps
    num_frames = max(max(1, round(a.duration * fps)) for a in anims)
    overlays = [_TextOverlay(label, width, height, top=True) for label in labels]
    sound = next((a for a in anims if a.audio is not None), None)
    ctx = create_context()
    renderers: list[Renderer] = []
    try:
        renderers = [_renderer_for(a, (width, height), ctx=ctx) for a in anims]
        canvas = np.empty((height, width * len(anims), 4), dtype=np.uint8)

        def frames() -> Iterator[np.ndarray]:
            for i in range(num_frames):
                for j, (anim, renderer) in enumerate(zip(anims, renderers, strict=True)):
                    t = min(round(i * anim.fps / fps), anim.num_frames - 1)
                    panel = canvas[:, j * width : (j + 1) * width]
                    panel[:] = renderer._draw(anim.vertices[t])
                    overlays[j].draw(panel)
                yield canvas

        return _write_video(
            frames(),
            num_frames,
            (canvas.shape[1], height),
            fps,
            path,
            audio=None if sound is None else sound.audio,
            sample_rate=16_000 if sound is None else sound.sample_rate,
            inputs=inputs,
            crf=crf,
            progress=progress,
        )
    finally:
        for renderer in renderers:
            renderer.close()
        ctx.release()


def contact_sheet(
    anim: Animation,
    path: str | os.PathLike,
    n: int = 8,
    cols: int = 4,
    size: int = 256,
    *,
    inputs: Iterable[str | os.PathLike] = (),
) -> np.ndarray:
    """Saves a PNG grid of ``n`` evenly spaced frames, each labelled with its time.

    Returns:
        (H, W, 3) uint8 sheet: ceil(n / cols) rows of ``size`` pixel cells, with thin gutters.
    """
    if n < 1 or cols < 1:
        raise TalkmeshError(f"a contact sheet needs n >= 1 and cols >= 1, got n={n}, cols={cols}")
    inputs = list(inputs)
    _check_output(path, (".png",), inputs)
    Image, _, _ = _import_pil()
    picks = np.linspace(0, anim.num_frames - 1, min(n, anim.num_frames)).round().astype(int)
    cols = min(cols, len(picks))
    rows = -(-len(picks) // cols)
    step = size + SHEET_GUTTER
    sheet = np.full((rows * step + SHEET_GUTTER, cols * step + SHEET_GUTTER, 3), 255, np.uint8)
    image = np.empty((size, size, 3), dtype=np.uint8)
    with _renderer_for(anim, size) as renderer:
        for k, t in enumerate(picks):
            y, x = SHEET_GUTTER + (k // cols) * step, SHEET_GUTTER + (k % cols) * step
            cell = sheet[y : y + size, x : x + size]
            cell[:] = renderer._draw(anim.vertices[t], image)
            _TextOverlay(f"{t / anim.fps:.2f} s", size, size, top=False).draw(cell)
    with _atomic_output(path, (".png",), inputs) as tmp:
        Image.fromarray(sheet).save(tmp, format="PNG")
    return sheet


# ---------------------------------------------------------------------------------------------
# Output files, ffmpeg and labels.


def _check_output(
    path: str | os.PathLike, suffixes: Sequence[str], inputs: Iterable[str | os.PathLike]
) -> Path:
    """Refuses an output path with another suffix, in a missing folder, or that is an input."""
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise TalkmeshError(f"{path}: the output must end in {' or '.join(suffixes)}")
    if not path.parent.is_dir():
        raise TalkmeshError(f"{path}: the folder {path.parent} does not exist")
    if path.is_dir():
        raise TalkmeshError(f"{path}: is a folder, not a file")
    if path.exists():
        for other in inputs:
            if Path(other).exists() and os.path.samefile(path, other):
                raise TalkmeshError(
                    f"{path}: refusing to overwrite an input; choose another output"
                )
    return path


@contextmanager
def _atomic_output(
    path: str | os.PathLike, suffixes: Sequence[str], inputs: Iterable[str | os.PathLike] = ()
) -> Iterator[Path]:
    """Yields a temporary file next to ``path`` that replaces it only if the block succeeds."""
    path = _check_output(path, suffixes, inputs)
    mode = path.stat().st_mode & 0o777 if path.exists() else 0o644
    fd, name = tempfile.mkstemp(
        prefix=f".{path.stem}.", suffix=f".part{path.suffix}", dir=path.parent
    )
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _fps_arg(fps: float) -> str:
    """Frame rate as the exact fraction ffmpeg expects (29.97 -> 2997/100)."""
    frac = Fraction(fps).limit_denominator(100_000)
    return f"{frac.numerator}/{frac.denominator}"


def _fit_audio(audio: np.ndarray, sample_rate: int, duration: float) -> np.ndarray:
    """(S,) audio zero-padded or trimmed to ``duration`` seconds -> (round(duration * rate),)."""
    num = round(duration * sample_rate)
    fitted = np.zeros(num, dtype=np.float32)
    fitted[: min(num, len(audio))] = audio[:num]
    return fitted


def _write_video(
    frames: Iterable[np.ndarray],
    num_frames: int,
    size: tuple[int, int],
    fps: float,
    path: str | os.PathLike,
    *,
    audio: np.ndarray | None,
    sample_rate: int,
    inputs: Iterable[str | os.PathLike],
    crf: int,
    progress: bool,
) -> Path:
    """Encodes ``num_frames`` (H, W, 4) uint8 RGBA frames and optional (S,) audio into an mp4.

    One ffmpeg process reads the frames on stdin and the audio, padded or trimmed to the video's
    duration so that both streams end together, from a temporary wav.
    """
    width, height = _video_size(size)
    path = Path(path)
    cmd = [_ffmpeg_exe(), "-hide_banner", "-nostdin", "-loglevel", "error", "-y"]
    cmd += ["-f", "rawvideo", "-pix_fmt", "rgba", "-s", f"{width}x{height}"]
    cmd += ["-framerate", _fps_arg(fps), "-i", "pipe:0"]
    with tempfile.TemporaryDirectory(prefix="talkmesh-") as tmpdir:
        if audio is not None:
            wav = Path(tmpdir) / "audio.wav"
            soundfile.write(wav, _fit_audio(audio, sample_rate, num_frames / fps), sample_rate)
            cmd += ["-i", str(wav), "-map", "0:v:0", "-map", "1:a:0"]
            cmd += ["-c:a", "aac", "-b:a", AUDIO_BITRATE, "-ar", str(AUDIO_RATE)]
        cmd += ["-c:v", "libx264", "-preset", VIDEO_PRESET, "-crf", str(crf), "-pix_fmt", "yuv420p"]
        with (
            _atomic_output(path, VIDEO_SUFFIXES, inputs) as tmp,
            open(Path(tmpdir) / "ffmpeg.log", "w+b") as log,
        ):
            cmd += ["-movflags", "+faststart", "-f", "mp4", str(tmp)]
            proc = subprocess.Popen(
                cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=log
            )
            try:
                _pipe_frames(proc, frames, num_frames, (height, width, 4), progress)
                returncode = proc.wait(timeout=FFMPEG_FINISH_TIMEOUT_S)
            except BrokenPipeError:  # ffmpeg stopped reading: its log says why
                returncode = proc.wait(timeout=FFMPEG_FINISH_TIMEOUT_S) or 1
            except BaseException:
                proc.kill()
                proc.wait()
                raise
            finally:
                try:
                    proc.stdin.close()
                except OSError:  # a broken pipe: ffmpeg has gone already
                    pass
            if returncode != 0:
                raise TalkmeshError(
                    f"{path}: ffmpeg could not write the video ({_first_error(log)})"
                )
    return path


def _first_error(log: IO[bytes]) -> str:
    """The first line of an ffmpeg log (the cause; later lines are consequences), unprefixed."""
    log.seek(0)
    for line in log.read().decode(errors="replace").splitlines():
        line = re.sub(r"^\[[^\]]*\]\s*", "", line.strip())  # "[libx264 @ 0x55...] Value ..."
        if line:
            return line
    return "no message"


def _pipe_frames(
    proc: subprocess.Popen,
    frames: Iterable[np.ndarray],
    num_frames: int,
    shape: tuple[int, int, int],
    progress: bool,
) -> None:
    """Writes exactly ``num_frames`` frames of ``shape`` to ffmpeg's stdin, then closes it."""
    written = 0
    with tqdm(total=num_frames, unit="frame", disable=not progress) as bar:
        for frame in frames:
            if written == num_frames:
                break
            assert frame.shape == shape and frame.dtype == np.uint8, (frame.shape, frame.dtype)
            proc.stdin.write(np.ascontiguousarray(frame).data)
            written += 1
            bar.update()
    assert written == num_frames, (written, num_frames)
    proc.stdin.close()


class _TextOverlay:
    """A white label on a translucent dark box, drawn with Pillow's built-in font.

    Args:
        text: the label.
        width, height: size of the image it goes on.
        top: centred at the top if True, else at the bottom left.
    """

    def __init__(self, text: str, width: int, height: int, *, top: bool) -> None:
        Image, ImageDraw, _ = _import_pil()
        measure = ImageDraw.Draw(Image.new("L", (1, 1)))
        px = max(LABEL_MIN_PX, round(height * LABEL_TEXT_HEIGHT))
        pad = max(2, px // 3)
        font = _font(px)
        left, upper, right, lower = measure.textbbox((0, 0), text, font=font)
        if right - left + 4 * pad > width:  # a long label: shrink it to fit the panel
            px = max(LABEL_MIN_PX, px * (width - 4 * pad) // (right - left))
            font = _font(px)
            left, upper, right, lower = measure.textbbox((0, 0), text, font=font)
        box_w = min(right - left + 2 * pad, width)
        box_h = min(lower - upper + 2 * pad, height)
        strip = Image.new("RGBA", (box_w, box_h), (0, 0, 0, round(255 * LABEL_BOX_ALPHA)))
        ImageDraw.Draw(strip).text((pad - left, pad - upper), text, font=font, fill=(255,) * 4)
        rgba = np.asarray(strip, dtype=np.float32) / 255
        self.keep = 1 - rgba[..., 3:]
        self.premultiplied = rgba[..., :3] * rgba[..., 3:] * 255 + 0.5  # + 0.5: round
        self.x = (width - box_w) // 2 if top else min(pad, width - box_w)
        self.y = min(pad, height - box_h) if top else max(0, height - box_h - pad)

    def draw(self, image: np.ndarray) -> None:
        """Blends the label into an (H, W, 3 or 4) uint8 image in place."""
        h, w = self.keep.shape[:2]
        region = image[self.y : self.y + h, self.x : self.x + w, :3]
        region[:] = (region * self.keep + self.premultiplied).astype(np.uint8)


def _font(px: int):
    """Pillow's built-in font at ``px`` pixels (a fixed-size bitmap font on Pillow < 10.1)."""
    _, _, ImageFont = _import_pil()
    try:
        return ImageFont.load_default(size=px)
    except TypeError:
        return ImageFont.load_default()
