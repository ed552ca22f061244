"""Reading real photos: JPEG or PNG, greyscale or colour, 8- or 16-bit, EXIF orientation applied."""

from __future__ import annotations

from pathlib import Path

import numpy as np


class PhotoError(ValueError):
    """A photo that cannot be read or used."""


PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")


def load_photo(path: str | Path) -> np.ndarray:
    """``(H, W, 3)`` float32 RGB in [0, 1].

    OpenCV's ``IMREAD_COLOR`` applies the EXIF orientation (it is ``IMREAD_UNCHANGED`` that
    ignores it) and turns greyscale into three channels; ``IMREAD_ANYDEPTH`` keeps 16 bits.
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise PhotoError(f"{path}: no such photo")
    if path.suffix.lower() not in PHOTO_SUFFIXES:
        raise PhotoError(f"{path}: unsupported format {path.suffix or '(no extension)'}; expected one of {', '.join(PHOTO_SUFFIXES)}")
    if path.stat().st_size == 0:
        raise PhotoError(f"{path}: empty file")
    from prismonet.files import InputError, read_image

    try:
        img = read_image(path, cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)
    except InputError as e:
        raise PhotoError(str(e)) from None
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(img.dtype)
    if scale is None:
        raise PhotoError(f"{path}: unsupported pixel type {img.dtype} (expected 8- or 16-bit)")
    return (img[..., ::-1].astype(np.float32) / scale).copy()
