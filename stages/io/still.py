"""Still images through OpenImageIO: TIFF (multi-page too), PNG, JPEG and whatever else OpenImageIO reads."""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterable
from functools import lru_cache
from pathlib import Path

import numpy as np
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError
from fluorocal.stages.io.atomic import atomic_write
from fluorocal.stages.io.pixels import Derivation, StoredFrames, check_stored, checked_indices, to_source_dtype

NAME = "still image (OpenImageIO)"
#: the suffixes named in messages; any extension OpenImageIO has a reader for is accepted
COMMON_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".bmp", ".exr", "...")
#: file signatures: TIFF (both byte orders, and BigTIFF), PNG, JPEG, BMP, OpenEXR, JPEG 2000, PNM/PGM
_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+", b"\x89PNG", b"\xff\xd8\xff", b"BM", b"v/1\x01")
_MAGIC_JP2 = b"\x00\x00\x00\x0cjP  "
_OIIO_DTYPE = {np.dtype(np.uint8): "uint8", np.dtype(np.uint16): "uint16", np.dtype(np.float32): "float"}
_STORED_DTYPE = {"uint8": np.dtype(np.uint8), "uint16": np.dtype(np.uint16)}
#: OpenImageIO's format names that OpenCV encodes as fast as cv2.imwrite, with OpenCV's suffix for them
_CV2_SUFFIX = {"tiff": ".tiff", "png": ".png"}
#: OpenImageIO's format names of the single images OpenCV reads as OpenImageIO does (one grey channel, as stored)
_CV2_READS = ("tiff", "png", "jpeg", "bmp", "pnm")


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


def read(path: Path, indices: list[int] | None = None) -> list[Radiograph]:
    """Subimages ``indices`` (every one when None) as monochrome frames (RGB via Rec. 601 luma), in stored bit depth."""
    inp = _open(path)
    try:
        frames = []
        wanted = itertools.count() if indices is None else iter(checked_indices(path, indices, None))
        for subimage in wanted:
            if not inp.seek_subimage(subimage, 0):
                if indices is None:
                    break
                raise InputError(f"{path}: holds fewer than {subimage + 1} frames; frame {subimage} asked for")
            spec = inp.spec()
            pixels = inp.read_image(spec.format)
            if pixels is None:
                raise InputError(f"{path}: cannot decode subimage {subimage} ({inp.geterror()})")
            frames.append(_to_radiograph(path, subimage, spec, pixels, inp.format_name()))
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


def open_stored(path: Path) -> StoredFrames | None:
    """The frames as stored, read one at a time; None unless every subimage is one channel of 8 or 16 bits in full.

    A single TIFF, PNG, JPEG, BMP or PNM image is read by OpenCV (which releases the GIL while it
    decodes), other types and the subimages of a multi-page TIFF by OpenImageIO. Stills display
    their stored values: black is 0. Colour images, floats and bit depths below their container's
    (which OpenImageIO rescales) take the general path (:func:`read`, :func:`write_like`).
    """
    inp = _open(path)
    try:
        specs = []
        while inp.seek_subimage(len(specs), 0):
            specs.append(inp.spec())
        by_opencv = len(specs) == 1 and inp.format_name() in _CV2_READS
    finally:
        inp.close()
    dtype = _STORED_DTYPE.get(str(specs[0].format)) if specs else None
    if dtype is None or any(
        spec.nchannels != 1
        or str(spec.format) != str(specs[0].format)
        or (spec.width, spec.height) != (specs[0].width, specs[0].height)
        or spec.get_int_attribute("oiio:BitsPerSample", dtype.itemsize * 8) != dtype.itemsize * 8
        for spec in specs
    ):
        return None
    size = (specs[0].width, specs[0].height)
    frames = (
        check_stored(path, f, dtype, size, i) for i, f in enumerate(_iter_stored(path, len(specs), dtype, by_opencv))
    )
    return StoredFrames(len(specs), size, dtype, 0.0, frames)


def _iter_stored(path: Path, n_frames: int, dtype: np.dtype, by_opencv: bool):
    import cv2

    if by_opencv:
        frame = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if frame is None:
            raise InputError(f"{path}: OpenCV cannot decode this image")
        yield frame
        return
    inp = _open(path)
    try:
        for i in range(n_frames):
            if not inp.seek_subimage(i, 0):
                raise InputError(f"{path}: cannot seek to subimage {i} ({inp.geterror()})")
            yield np.asarray(inp.read_image(_OIIO_DTYPE[dtype])).reshape(inp.spec().height, inp.spec().width)
    finally:
        inp.close()


def write_stored(
    source: Path, frames: Iterable[np.ndarray], out_path: Path, n_frames: int, derivation: Derivation | None = None
) -> None:
    """Write ``n_frames`` frames in ``source``'s image type, atomically, as fast as OpenCV writes them.

    One frame of TIFF or PNG: encoded by OpenCV (TIFF with LZW, PNG with zlib at OpenCV's level),
    the only uint8/uint16 path as fast as ``cv2.imwrite`` (OpenImageIO's default zip TIFF is ~5x
    slower). Several frames (the subimages of a multi-page TIFF), other types and float32 frames:
    OpenImageIO, TIFF with LZW, one subimage at a time.

    Raises
    ------
    InputError
        A frame count other than the source's, or a format that cannot hold the frames.

    Notes
    -----
    ``derivation`` is not recorded: a still's header has no place fluorocal writes it.
    """
    import cv2

    inp = _open(source)
    file_format = inp.format_name()
    n_source = 1
    while inp.seek_subimage(n_source, 0):
        n_source += 1
    inp.close()
    if n_frames != n_source:
        raise InputError(f"{source}: writing {n_frames} frames to a still image of {n_source} is not supported")
    frames = iter(frames)
    if n_frames == 1 and file_format in _CV2_SUFFIX:
        frame = next(frames, None)
        if frame is None:
            raise InputError(f"{out_path}: expected 1 frame like {source}; got none")
        if frame.dtype in (np.uint8, np.uint16) and frame.ndim == 2:
            ok, encoded = cv2.imencode(_CV2_SUFFIX[file_format], frame)
            if not ok:
                raise InputError(f"{out_path}: OpenCV cannot encode the frame as {file_format}")
            atomic_write(out_path, lambda tmp: Path(tmp).write_bytes(encoded.data))
            return
        frames = iter([frame])
    atomic_write(out_path, lambda tmp: _write_subimages(tmp, file_format, frames, n_frames, out_path))


def _write_subimages(tmp: str, file_format: str, frames, n_frames: int, out_path: Path) -> None:
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(file_format)
    if out is None:
        raise InputError(f"{out_path}: no writer for this format ({oiio.geterror()})")
    count = 0
    for frame in frames:
        frame = np.ascontiguousarray(frame)
        fmt = _OIIO_DTYPE.get(frame.dtype)
        if frame.ndim != 2 or fmt is None:
            raise InputError(f"{out_path}: frame {count} must be 2-D uint8, uint16 or float32; got {frame.dtype}")
        spec = oiio.ImageSpec(frame.shape[1], frame.shape[0], 1, fmt)
        if file_format == "tiff":
            spec.attribute("compression", "lzw")
        mode = "Create" if count == 0 else "AppendSubimage"
        # OIIO misreads a 2-D array's strides: pass (H, W, 1)
        if not out.open(tmp, spec, mode) or not out.write_image(frame.reshape(frame.shape[0], frame.shape[1], 1)):
            raise InputError(f"{out_path}: write failed ({out.geterror()})")
        count += 1
    out.close()
    if count != n_frames:
        raise InputError(f"{out_path}: expected {n_frames} frame(s); got {count}")


def write_like(source: Path, frames: list[Radiograph], out_path: Path, derivation: Derivation | None = None) -> None:
    """The frames in the source's bit depth and image type (TIFF, PNG, ...: what OpenImageIO read it as)."""
    write_stored(source, map(to_source_dtype, frames), out_path, len(frames), derivation)
