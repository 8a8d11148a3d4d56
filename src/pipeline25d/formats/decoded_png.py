"""Images the renderer cannot take as they are (a glTF's WEBP, an I3S package's DDS), decoded by
Pillow and stored as PNG, as the chunks and the render job take them."""

from __future__ import annotations


def image_as_png(data: bytes) -> tuple[bytes | None, str | None]:
    """An image Pillow decodes (a glTF's WEBP, an I3S package's DDS) as PNG bytes, RGB or RGBA,
    which the chunks and the render job take (level 1: fast); (None, Pillow's problem) when it
    cannot be decoded."""
    import io

    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as image:
            out = io.BytesIO()
            image.convert("RGBA" if "A" in image.mode else "RGB").save(out, format="PNG", compress_level=1)
    except Exception as exc:        # Pillow raises several types for an unknown format or a cut file
        return None, str(exc)
    return out.getvalue(), None
