"""The OpenGL face renderer: one headless context per :class:`Renderer`, reused for every frame.

Each frame recomputes the vertex normals, rewrites the same vertex buffer, draws the face at twice
the resolution and averages 2x2 pixels while compositing it over the background (supersampling:
llvmpipe's 4x MSAA is slower for the same quality). Lighting is evaluated per vertex (two lights,
wrapped Lambert and a soft specular), which is smooth at the bundled head's density and keeps a
software rasteriser above 60 frames/s at 512x512.

Coordinates follow the bundled head: metres, +y up, +z towards the viewer. The camera looks down
-z at the bounding box of a reference mesh so the face fills the image.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING

import numpy as np

from talkmesh.errors import MissingDependencyError, TalkmeshError
from talkmesh.face.geometry import VertexNormals, winding_sign
from talkmesh.output.media import VIDEO_SIZE, size_pair

if TYPE_CHECKING:
    import moderngl

# Camera and image.
SUPERSAMPLE = 2  # render at 2x and average 2x2 pixels: 4 samples per pixel
FOV_DEG = 18.0  # a portrait lens: little perspective distortion of the nose
FRAME_MARGIN = 1.08  # the reference bounding box fills 1 / FRAME_MARGIN of the image height
# Camera positions: how far the head is turned about its vertical (+y) axis, in degrees; the
# three-quarter view shows the face's right side (the viewer's left), the mouth's depth with it.
CAMERAS = {"front": 0.0, "three-quarter": 35.0}

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


def head_vertex_colors(num_vertices: int) -> np.ndarray | None:
    """(V, 3) sRGB colours of the bundled head (``talkmesh.face.look``: lips, irises and pupils,
    teeth, tongue, a dark mouth cavity), or None if the mesh is not that head."""
    try:
        from talkmesh.face.assets import load_head
        from talkmesh.face.look import head_colors

        head = load_head()
    except Exception:  # no bundled head (or a broken one): the caller renders plain skin
        return None
    if head.num_vertices != num_vertices:
        return None
    return head_colors(head)


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
        camera: a name in ``CAMERAS``: "front" or "three-quarter" (the head turned 35 degrees).
        focus: optional (V,) bool, the vertices the camera aims at (an avatar's head); default
            all of them.
        ctx: an OpenGL context to share (see :func:`create_context`); by default the renderer
            creates its own and releases it in :meth:`close`.

    Use it as a context manager, or call :meth:`close`, to free the context.
    """

    def __init__(
        self,
        faces: np.ndarray,
        size: int | tuple[int, int] = (VIDEO_SIZE, VIDEO_SIZE),
        *,
        vertex_colors: np.ndarray | None = None,
        reference: np.ndarray | None = None,
        fov_deg: float = FOV_DEG,
        supersample: int = SUPERSAMPLE,
        ctx: moderngl.Context | None = None,
        camera: str = "front",
        focus: np.ndarray | None = None,
    ) -> None:
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise TalkmeshError(
                f"no triangles to draw (faces {faces.shape}): the animation holds vertices "
                "only; animate with a template whose mesh has triangles to render it"
            )
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
        self.width, self.height = size_pair(size)
        if supersample not in (1, 2):
            raise TalkmeshError(f"supersample must be 1 or 2, got {supersample}")
        self.fov_y = math.radians(fov_deg)
        if camera not in CAMERAS:
            raise TalkmeshError(f"unknown camera '{camera}': choose {' or '.join(CAMERAS)}")
        turn = math.radians(CAMERAS[camera])
        self._turn = None
        if turn:
            c, s = math.cos(turn), math.sin(turn)
            self._turn = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], np.float32).T
        self._normals = VertexNormals(self.faces.astype(np.int64), self.num_vertices)
        self._focus = None
        if focus is not None:
            self._focus = np.asarray(focus, bool)
            if self._focus.shape != (self.num_vertices,) or not self._focus.any():
                raise TalkmeshError(f"focus must be (V,) bool with one True, got {focus.shape}")
        self._framed = False
        self._flags = 0
        self._front_face = "ccw"

        moderngl = _import_moderngl()
        self._owns_ctx = ctx is None
        self.ctx = create_context() if ctx is None else ctx
        self._depth_test, self._cull_face = moderngl.DEPTH_TEST, moderngl.CULL_FACE
        self._create_targets(moderngl, supersample)
        self._create_programs(vertex_colors)
        if reference is not None:
            self.frame(reference)

    def _create_targets(self, moderngl, supersample: int) -> None:
        """The supersampled face texture and depth buffer, and the output image."""
        c = self.ctx
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

    def _create_programs(self, vertex_colors: np.ndarray | None) -> None:
        """The shaded-mesh and compositing programs and their vertex buffers."""
        c = self.ctx
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

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height

    def frame(self, vertices: np.ndarray) -> None:
        """Aims the camera at (V, 3) vertices (those of ``focus``) so that their bounding box
        fills the image, and decides from their winding whether back faces can be culled."""
        vertices = self._check_vertices(vertices)
        aimed = vertices if self._focus is None else vertices[self._focus]
        lo, hi = aimed.min(axis=0), aimed.max(axis=0)
        center = (lo + hi) / 2
        aspect = self.width / self.height
        half = max((hi[1] - lo[1]) / 2, (hi[0] - lo[0]) / 2 / aspect, 1e-6) * FRAME_MARGIN
        distance = half / math.tan(self.fov_y / 2)  # the front of the box fills the view
        depth = max(float(hi[2] - vertices[:, 2].min()), 1e-6)  # all of it behind the front
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
        return self.draw(vertices, image)

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
        vertices = vertices[: self.num_vertices]
        return vertices if self._turn is None else vertices @ self._turn

    def draw(self, vertices: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
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
