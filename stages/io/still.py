"""Still images through OpenImageIO: TIFF (multi-page too), PNG, JPEG and whatever else OpenImageIO reads."""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

import numpy as np
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError
from fluorocal.stages.io.atomic import atomic_write
from fluorocal.stages.io.pixels import to_source_dtype

NAME = "still image (OpenImageIO)"
#: the suffixes named in messages; any extension OpenImageIO has a reader for is accepted
COMMON_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".bmp", ".exr", "...")
#: file signatures: TIFF (both byte orders, and BigTIFF), PNG, JPEG, BMP, OpenEXR, JPEG 2000, PNM/PGM
_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+", b"\x89PNG", b"\xff\xd8\xff", b"BM", b"v/1\x01")
_MAGIC_JP2 = b"\x00\x00\x00\x0cjP  "
_OIIO_DTYPE = {np.dtype(np.uint8): "uint8", np.dtype(np.uint16): "uint16", np.dtype(np.float32): "float"}


def sniff_content(head: bytes) -> bool:
    """A still image by its signature."""
    if head.startswith(_MAGIC) or head.startswith(_MAGIC_JP2):
        return True
    return len(head) > 2 and head[:1] == b"P" and head[1:2] in b"256" and head[2:3].isspace()


def accepts_suffix(suffix: str) -> bool:
    """Whether OpenImageIO has a reader for files ending in ``suffix`` (lower case, with the dot)."""
    return suffix in _oiio_suffixes()


@lru_cache(maxsize=1)
def _oiio_suffixes() -> frozenset[str]:
    import OpenImageIO as oiio

    listed = oiio.get_string_attribute("extension_list")  # "tiff:tif,tiff;png:png;..."
    return frozenset("." + ext.lower() for entry in listed.split(";") for ext in entry.partition(":")[2].split(","))


def _open(path: Path):
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read as an image ({oiio.geterror()})")
    return inp


def probe(path: Path) -> tuple[int, tuple[int, int]]:
    """Number of subimages and the first one's ``(width, height)`` px, from the header."""
    inp = _open(path)
    size = (inp.spec().width, inp.spec().height)
    n = 0
    while inp.seek_subimage(n, 0):
        n += 1
    inp.close()
    return n, size


def read(path: Path) -> list[Radiograph]:
    """Every subimage as a monochrome frame (RGB through Rec. 601 luma), in its stored bit depth."""
    inp = _open(path)
    try:
        frames = []
        subimage = 0
        while inp.seek_subimage(subimage, 0):
            spec = inp.spec()
            pixels = inp.read_image(spec.format)
            if pixels is None:
                raise InputError(f"{path}: cannot decode subimage {subimage} ({inp.geterror()})")
            frames.append(_to_radiograph(path, subimage, spec, pixels, inp.format_name()))
            subimage += 1
    finally:
        inp.close()
    return frames


def _to_radiograph(path: Path, index: int, spec, pixels: np.ndarray, format_name: str) -> Radiograph:
    pixels = np.asarray(pixels)
    if pixels.ndim == 3:
        if spec.nchannels not in (1, 2, 3, 4):
            raise InputError(f"{path}: unsupported channel count {spec.nchannels}")
        # grey + alpha, or RGB(A) converted with Rec. 601 luma
        pixels = pixels[..., 0] if spec.nchannels <= 2 else pixels[..., :3] @ np.array([0.299, 0.587, 0.114])
    native_bits = pixels.dtype.itemsize * 8 if np.issubdtype(pixels.dtype, np.integer) else 32
    bits = spec.get_int_attribute("oiio:BitsPerSample", native_bits) or native_bits
    image = pixels.astype(np.float32)
    if np.issubdtype(pixels.dtype, np.integer) and bits < native_bits:
        # OIIO rescales fewer stored bits to the container's full range; undo it
        image = np.round(image * ((2**bits - 1) / (2**native_bits - 1))).astype(np.float32)
    meta = {"format": format_name or path.suffix.lstrip(".").lower()}  # OpenImageIO's name: "tiff", "png", ...
    return Radiograph(image, int(bits), str(path), index, meta)


def write_still(
    path: str | os.PathLike, image: np.ndarray, *, attributes: dict | None = None, file_format: str = ""
) -> None:
    """Write a monochrome image atomically with OpenImageIO, in the dtype given.

    ``image`` is written as-is (uint8, uint16 or float32). ``attributes`` are
    OpenImageIO spec attributes, e.g. a fixed ``DateTime`` so that the same
    pixels give the same bytes (OpenImageIO stamps the current time otherwise).
    ``file_format`` is an OpenImageIO format name (``"tiff"``, ``"png"``, ...);
    by default the suffix of ``path`` chooses.
    """
    import OpenImageIO as oiio

    image = np.ascontiguousarray(image)
    fmt = _OIIO_DTYPE.get(image.dtype)
    if fmt is None:
        raise InputError(f"write_still: unsupported dtype {image.dtype} for {path}")

    def _write(tmp):
        out = oiio.ImageOutput.create(file_format or tmp)
        if out is None:
            raise InputError(f"{path}: no writer for this format ({oiio.geterror()})")
        spec = oiio.ImageSpec(image.shape[1], image.shape[0], 1, fmt)
        for name, value in (attributes or {}).items():
            spec.attribute(name, value)
        # OIIO misreads a 2-D array's strides: pass (H, W, 1)
        if not out.open(tmp, spec) or not out.write_image(image.reshape(image.shape[0], image.shape[1], 1)):
            raise InputError(f"{path}: write failed ({out.geterror()})")
        out.close()

    atomic_write(path, _write)


def write_like(source: Path, frames: list[Radiograph], out_path: Path) -> None:
    """One frame, in the source's bit depth and image type (TIFF, PNG, ...: what OpenImageIO read it as)."""
    if len(frames) != 1:
        raise InputError(f"{source}: writing {len(frames)} frames to a still image is not supported")
    inp = _open(source)
    file_format = inp.format_name()
    inp.close()
    write_still(out_path, to_source_dtype(frames[0]), file_format=file_format)
