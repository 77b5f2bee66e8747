"""Text labels drawn onto rendered frames (Pillow's built-in font)."""

from __future__ import annotations

import numpy as np

from talkmesh.errors import MissingDependencyError

LABEL_TEXT_HEIGHT = 0.06  # label text height as a fraction of the panel height
LABEL_MIN_PX = 9  # smallest legible label text
LABEL_BOX_ALPHA = 0.55


def import_pil():
    try:
        from PIL import Image, ImageDraw, ImageFont
    except ImportError as e:
        raise MissingDependencyError("pillow", "render", "Drawing labels and writing PNGs") from e
    return Image, ImageDraw, ImageFont


class TextOverlay:
    """A white label on a translucent dark box, drawn with Pillow's built-in font.

    Args:
        text: the label.
        width, height: size of the image it goes on.
        top: centred at the top if True, else at the bottom left.
    """

    def __init__(self, text: str, width: int, height: int, *, top: bool) -> None:
        Image, ImageDraw, _ = import_pil()
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
    _, _, ImageFont = import_pil()
    try:
        return ImageFont.load_default(size=px)
    except TypeError:
        return ImageFont.load_default()
