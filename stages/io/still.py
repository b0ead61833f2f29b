"""Still images through OpenImageIO: TIFF (multi-page too), PNG, JPEG and whatever else OpenImageIO reads."""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError
from fluorocal.stages.io.atomic import atomic_write
from fluorocal.stages.io.names import native_name
from fluorocal.stages.io.pixels import Derivation, StoredFrames, check_stored, checked_indices

NAME = "still image (OpenImageIO)"
#: the suffixes named in messages; any extension OpenImageIO has a reader for is accepted
COMMON_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".bmp", ".exr", "...")
#: file signatures: TIFF (both byte orders, and BigTIFF), PNG, JPEG, BMP, OpenEXR, JPEG 2000, PNM/PGM
_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+", b"\x89PNG", b"\xff\xd8\xff", b"BM", b"v/1\x01")
_MAGIC_JP2 = b"\x00\x00\x00\x0cjP  "
_OIIO_DTYPE = {np.dtype(np.uint8): "uint8", np.dtype(np.uint16): "uint16", np.dtype(np.float32): "float"}
#: OpenImageIO's names of the formats whose frames are written back sample for sample (the round trip tests
#: prove each); JPEG and the other lossy codecs cannot be, and OpenImageIO's writers of the rest change the
#: sample type or channels of some (EXR: uint8 as half, FITS: uint16 as int16, GIF and ICO: RGBA)
_EXACT_FORMATS = ("tiff", "png", "pnm")
#: OpenImageIO's names of the lossless formats OpenCV decodes as it does and encodes fast, with OpenCV's suffix
_CV2_SUFFIX = {"tiff": ".tiff", "png": ".png"}


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


#: OpenImageIO's names of the sample types read, and their numpy types (all but half written back exactly)
_TYPES = {
    "half": np.dtype(np.float16),
    "uint8": np.dtype(np.uint8),
    "int8": np.dtype(np.int8),
    "uint16": np.dtype(np.uint16),
    "int16": np.dtype(np.int16),
    "uint": np.dtype(np.uint32),
    "int": np.dtype(np.int32),
    "float": np.dtype(np.float32),
    "double": np.dtype(np.float64),
}


@dataclass(frozen=True)
class _Layout:
    """What a still holds, page by page alike: the facts its frames are read and written back with.

    ``bits``: significant bits of an integer sample (PNM: of its maxval; else OpenImageIO's
    BitsPerSample); ``maxval``: a PNM's, else None; ``refusal``: why its frames cannot be written
    back exactly (None: they can).
    """

    format_name: str
    n_frames: int
    size_px: tuple[int, int]
    n_channels: int
    type_name: str
    bits: int
    min_is_white: bool
    alpha_channel: int
    maxval: int | None
    refusal: str | None

    @property
    def dtype(self) -> np.dtype:
        return _TYPES[self.type_name]

    @property
    def black(self) -> float:
        """The stored value displayed darkest: the border to resample with."""
        if self.dtype.kind == "f":
            return 0.0
        low, high = _int_range(self)
        return float(high if self.min_is_white else low)


def _int_range(layout: _Layout) -> tuple[int, int]:
    if layout.dtype.kind == "i":
        return -(2 ** (layout.bits - 1)), 2 ** (layout.bits - 1) - 1
    return 0, (layout.maxval or 2**layout.bits - 1)


def _hints():
    """Open with alpha as stored: OpenImageIO premultiplies colour by an unassociated alpha otherwise."""
    import OpenImageIO as oiio

    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    return config


def _open(path: Path):
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(native_name(path), _hints())
    if inp is None:
        raise InputError(f"{path}: cannot read as an image ({oiio.geterror()})")
    return inp


def _layout(path: Path) -> _Layout:
    """The file's :class:`_Layout`, from its headers (pixels not read).

    Raises
    ------
    InputError
        Pages of different sizes, channel counts or sample types, more than 4 channels, or a
        sample type without a numpy equivalent, naming the file.
    """
    inp = _open(path)
    try:
        specs = []
        while inp.seek_subimage(len(specs), 0):
            specs.append(inp.spec())
        format_name = inp.format_name()
    finally:
        inp.close()
    if not specs:
        raise InputError(f"{path}: holds no image")
    first = specs[0]
    pages = {((s.width, s.height), s.nchannels, str(s.format)) for s in specs}
    if len(pages) > 1:
        shown = ", ".join(f"{w}x{h} px {t} x{c}" for (w, h), c, t in sorted(pages))
        raise InputError(f"{path}: pages differ ({shown}); a frame file must hold frames of one size and type")
    type_name = str(first.format)
    if type_name not in _TYPES or not 1 <= first.nchannels <= 4:
        raise InputError(f"{path}: {first.nchannels} channel(s) of {type_name} samples are not supported")
    container = _TYPES[type_name].itemsize * 8
    maxval = _pnm_maxval(path) if format_name == "pnm" else None
    bits = int(maxval).bit_length() if maxval else first.get_int_attribute("oiio:BitsPerSample", container) or container
    return _Layout(
        format_name,
        len(specs),
        (first.width, first.height),
        first.nchannels,
        type_name,
        int(bits),
        first.get_int_attribute("tiff:PhotometricInterpretation", 1) == 0,
        first.alpha_channel,
        maxval,
        _refusal(format_name, type_name, maxval, int(bits)),
    )


def _refusal(format_name: str, type_name: str, maxval: int | None, bits: int) -> str | None:
    """Why frames of this format and sample type cannot be written back as they came, and what to do; None: they can.

    Examples
    --------
    >>> _refusal("jpeg", "uint8", None, 8)
    'JPEG is lossy: its frames cannot be written back as they came; convert it to TIFF or PNG first'
    >>> _refusal("tiff", "uint16", None, 16) is None
    True
    """
    if format_name not in _EXACT_FORMATS:
        what = (
            "JPEG is lossy: its frames cannot be written back as they came"
            if format_name == "jpeg"
            else (f"{format_name or 'this format'}: fluorocal writes frames back exactly only as TIFF, PNG or PGM/PPM")
        )
        return f"{what}; convert it to TIFF or PNG first"
    container = _TYPES[type_name].itemsize * 8
    if type_name == "half":
        why = "half-float samples cannot be written back as stored (OpenImageIO writes them as float)"
    elif format_name == "pnm" and not maxval:
        why = "a bitmap (PBM) cannot be written back as stored"
    elif maxval is None and _TYPES[type_name].kind == "u" and bits < container:
        why = f"{bits}-bit samples in {container}-bit words cannot be written back as stored"
    else:
        return None
    return why + "; convert it to 8- or 16-bit samples first"


def _pnm_maxval(path: Path) -> int | None:
    """The maxval of a PGM/PPM (P2, P3, P5, P6) header; None for a bitmap (P1, P4) or another PNM."""
    with open(path, "rb") as fh:
        head = fh.read(1024)
    tokens = b" ".join(line.partition(b"#")[0] for line in head.split(b"\n")).split()
    if len(tokens) < 4 or tokens[0] not in (b"P2", b"P3", b"P5", b"P6") or not tokens[3].isdigit():
        return None
    return int(tokens[3])


def _writable_layout(path: Path) -> _Layout:
    """:func:`_layout`, refusing in one line a file whose frames cannot be written back as stored."""
    layout = _layout(path)
    if layout.refusal is not None:
        raise InputError(f"{path}: {layout.refusal}")
    return layout


def probe(path: Path) -> tuple[int, tuple[int, int]]:
    """Number of subimages and their ``(width, height)`` px, from the headers (pages of two sizes refused)."""
    layout = _layout(path)
    return layout.n_frames, layout.size_px


def _decode(path: Path, inp, subimage: int, layout: _Layout) -> np.ndarray:
    """Subimage ``subimage`` as stored: ``(H, W)`` or ``(H, W, C)`` of the layout's dtype, alpha unpremultiplied."""
    if not inp.seek_subimage(subimage, 0):
        raise InputError(f"{path}: holds fewer than {subimage + 1} frames; frame {subimage} asked for")
    pixels = inp.read_image(layout.type_name)
    if pixels is None:
        raise InputError(f"{path}: cannot decode subimage {subimage} ({inp.geterror()})")
    pixels = np.asarray(pixels).reshape(layout.size_px[1], layout.size_px[0], layout.n_channels)
    if layout.min_is_white and layout.type_name == "uint8":
        # OpenImageIO's TIFF reader (every version's invert_photometric; no open hint turns it off) gives a
        # MinIsWhite file's samples read as uint8 (1-, 4-, 8-bit, alpha too) inverted, wider ones as stored:
        # back to the stored values (tests/stages/test_io_roundtrip.py holds this against tifffile's truth)
        pixels = np.subtract(255, pixels, out=pixels)
    if layout.maxval is not None and layout.maxval != np.iinfo(layout.dtype).max:
        # OpenImageIO scales a PNM's 0..maxval to its word's full range, floor(v * top / maxval): the stored v is
        # the smallest reaching the word, ceil(word * maxval / top) (rounding is off by one when top < 2 maxval)
        top = int(np.iinfo(layout.dtype).max)
        pixels = ((pixels.astype(np.int64) * layout.maxval + top - 1) // top).astype(layout.dtype)
    elif layout.dtype.kind == "u" and layout.bits < layout.dtype.itemsize * 8:
        pixels = np.rint(pixels * ((2**layout.bits - 1) / np.iinfo(layout.dtype).max)).astype(layout.dtype)
    return pixels[..., 0] if layout.n_channels == 1 else pixels


def display(stored: np.ndarray, layout: _Layout) -> np.ndarray:
    """A stored frame as one grey plane, larger = brighter, 0 at the darkest value the type holds, float32.

    Colour is Rec. 601 luma; an alpha channel is dropped (grey + alpha: the grey); MinIsWhite is
    inverted; signed integers are offset by their type's smallest value. Floats are kept as stored.
    """
    if layout.n_channels == 1 and layout.dtype.kind in "iu" and layout.dtype.itemsize <= 2:
        # values, offset and result are integers below 2**24, exact in float32: the float64 route's result, at
        # a quarter of its memory traffic (4 of the 5 ms of a 1024 px frame)
        low, high = _int_range(layout)
        values = stored.astype(np.float32)
        return np.subtract(high, values, out=values) if layout.min_is_white else np.subtract(values, low, out=values)
    values = stored.astype(np.float64)
    if layout.n_channels == 2:
        values = values[..., 0]
    elif layout.n_channels >= 3:
        values = values[..., :3] @ np.array([0.299, 0.587, 0.114])
    if layout.dtype.kind in "iu":
        low, high = _int_range(layout)
        values = high - values if layout.min_is_white else values - low
    return values.astype(np.float32)


def read(path: Path, indices: list[int] | None = None) -> list[Radiograph]:
    """Subimages ``indices`` (all when None) decoded as :func:`open_stored` does, as :func:`display` shows them."""
    layout = _layout(path)
    wanted = range(layout.n_frames) if indices is None else checked_indices(path, indices, layout.n_frames)
    bits = layout.bits if layout.dtype.kind in "iu" else 32
    meta = {"format": layout.format_name or path.suffix.lstrip(".").lower()}  # OpenImageIO's name: "tiff", ...
    inp = _open(path)
    try:
        return [Radiograph(display(_decode(path, inp, i, layout), layout), bits, str(path), i, meta) for i in wanted]
    finally:
        inp.close()


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
        out = oiio.ImageOutput.create(file_format or native_name(tmp))
        if out is None:
            raise InputError(f"{path}: no writer for this format ({oiio.geterror()})")
        spec = oiio.ImageSpec(image.shape[1], image.shape[0], 1, fmt)
        for name, value in (attributes or {}).items():
            spec.attribute(name, value)
        # OIIO misreads a 2-D array's strides: pass (H, W, 1)
        if not out.open(native_name(tmp), spec) or not out.write_image(
            image.reshape(image.shape[0], image.shape[1], 1)
        ):
            raise InputError(f"{path}: write failed ({out.geterror()})")
        out.close()

    atomic_write(path, _write)


def open_stored(path: Path) -> StoredFrames:
    """The frames as stored (every channel, the file's sample type), read one at a time.

    A single grey 8- or 16-bit TIFF or PNG is decoded by OpenCV (which releases the GIL while it
    decodes, and reads these exactly as OpenImageIO does); other files by OpenImageIO, alpha unpremultiplied.

    Raises
    ------
    InputError
        A file whose frames cannot be written back as stored (:func:`_layout`), naming the file and why.
    """
    layout = _writable_layout(path)
    frames = (
        check_stored(path, f, layout.dtype, layout.size_px, i, layout.n_channels)
        for i, f in enumerate(_iter_stored(path, layout, _by_opencv(layout)))
    )
    return StoredFrames(layout.n_frames, layout.size_px, layout.dtype, layout.black, frames, layout.n_channels)


def _iter_stored(path: Path, layout: _Layout, by_opencv: bool):
    import cv2

    if by_opencv:
        frame = cv2.imread(native_name(path), cv2.IMREAD_UNCHANGED)
        if frame is None:
            raise InputError(f"{path}: OpenCV cannot decode this image")
        yield frame
        return
    inp = _open(path)
    try:
        for i in range(layout.n_frames):
            yield _decode(path, inp, i, layout)
    finally:
        inp.close()


def write_stored(
    source: Path, frames: Iterable[np.ndarray], out_path: Path, n_frames: int, derivation: Derivation | None = None
) -> None:
    """Write ``n_frames`` frames as stored in ``source``'s layout (type, channels, photometric, maxval), atomically.

    One grey 8- or 16-bit frame of TIFF or PNG: encoded by OpenCV (TIFF with LZW, PNG with zlib at
    OpenCV's level), the only path as fast as ``cv2.imwrite`` (OpenImageIO's default zip TIFF is ~5x
    slower). PGM/PPM: written here, binary, with the source's maxval. Others (TIFF and PNG): OpenImageIO
    (TIFF with LZW), one subimage at a time, alpha unassociated; a MinIsWhite TIFF's pages are marked
    MinIsWhite again. Other formats (JPEG and the rest) are refused: :data:`_EXACT_FORMATS`.

    Raises
    ------
    InputError
        A frame count other than the source's, a frame unlike the source's, or a source whose frames
        cannot be written back as stored.

    Notes
    -----
    ``derivation`` is not recorded: a still's header has no place fluorocal writes it.
    """
    layout = _writable_layout(source)
    if n_frames != layout.n_frames:
        raise InputError(f"{source}: writing {n_frames} frames to a still image of {layout.n_frames} is not supported")
    checked = (
        check_stored(out_path, f, layout.dtype, layout.size_px, i, layout.n_channels) for i, f in enumerate(frames)
    )
    if layout.maxval is not None:
        atomic_write(out_path, lambda tmp: _write_pnm(tmp, checked, layout, out_path))
    elif _by_opencv(layout):
        _write_cv2(out_path, checked, layout)
    else:
        atomic_write(out_path, lambda tmp: _write_subimages(tmp, checked, layout, out_path))


def _by_opencv(layout: _Layout) -> bool:
    """Whether OpenCV reads and writes the file as OpenImageIO does: one grey 8- or 16-bit TIFF or PNG image."""
    return (
        layout.n_frames == 1
        and layout.format_name in _CV2_SUFFIX
        and layout.n_channels == 1
        and layout.type_name in ("uint8", "uint16")
        and not layout.min_is_white
    )


def _write_cv2(out_path: Path, frames, layout: _Layout) -> None:
    import cv2

    frame = next(frames, None)
    if frame is None:
        raise InputError(f"{out_path}: expected 1 frame; got none")
    ok, encoded = cv2.imencode(_CV2_SUFFIX[layout.format_name], frame)
    if not ok:
        raise InputError(f"{out_path}: OpenCV cannot encode the frame as {layout.format_name}")
    atomic_write(out_path, lambda tmp: Path(tmp).write_bytes(encoded.data))


def _write_pnm(tmp: str, frames, layout: _Layout, out_path: Path) -> None:
    """Binary PGM (P5) or PPM (P6) with the layout's maxval: big-endian words above 255."""
    frame = next(frames, None)
    if frame is None or layout.n_channels not in (1, 3):
        raise InputError(f"{out_path}: expected 1 grey or RGB frame for a PNM file")
    magic = b"P5" if layout.n_channels == 1 else b"P6"
    header = b"%s\n%d %d\n%d\n" % (magic, layout.size_px[0], layout.size_px[1], layout.maxval)
    word = ">u2" if layout.maxval > 255 else "u1"
    Path(tmp).write_bytes(header + np.ascontiguousarray(frame, dtype=word).tobytes())


def _write_subimages(tmp: str, frames, layout: _Layout, out_path: Path) -> None:
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(layout.format_name)
    if out is None:
        raise InputError(f"{out_path}: no writer for this format ({oiio.geterror()})")
    count = 0
    for frame in frames:
        spec = oiio.ImageSpec(layout.size_px[0], layout.size_px[1], layout.n_channels, layout.type_name)
        spec.alpha_channel = layout.alpha_channel
        spec.attribute("oiio:UnassociatedAlpha", 1)
        if layout.format_name == "tiff":
            spec.attribute("compression", "lzw")
        mode = "Create" if count == 0 else "AppendSubimage"
        pixels = np.ascontiguousarray(frame).reshape(layout.size_px[1], layout.size_px[0], layout.n_channels)
        if not out.open(native_name(tmp), spec, mode) or not out.write_image(pixels):
            raise InputError(f"{out_path}: write failed ({out.geterror()})")
        count += 1
    out.close()
    if count != layout.n_frames:
        raise InputError(f"{out_path}: expected {layout.n_frames} frame(s); got {count}")
    if layout.min_is_white:
        _mark_min_is_white(tmp)


def _mark_min_is_white(path: str) -> None:
    """Set every page's PhotometricInterpretation to MinIsWhite (0) in place: OpenImageIO writes MinIsBlack only."""
    import tifffile

    with tifffile.TiffFile(path, mode="r+b") as tif:
        for page in tif.pages:
            page.tags["PhotometricInterpretation"].overwrite(0)


def write_like(source: Path, frames: list[Radiograph], out_path: Path, derivation: Derivation | None = None) -> None:
    """Grey frames (as :func:`read` gives them) back in a grey source's type: rounded, clipped, MinIsWhite re-inverted.

    Raises
    ------
    InputError
        A colour source (its frames were read as luma), or one :func:`write_stored` refuses.
    """
    layout = _layout(source)
    if layout.n_channels != 1:
        raise InputError(f"{source}: a colour image cannot be written back from grey frames")

    def stored(frame: Radiograph) -> np.ndarray:
        if layout.dtype.kind == "f":
            return frame.image.astype(layout.dtype)
        low, high = _int_range(layout)
        values = high - frame.image if layout.min_is_white else frame.image + low
        return np.clip(np.rint(values), low, high).astype(layout.dtype)

    write_stored(source, map(stored, frames), out_path, len(frames), derivation)
