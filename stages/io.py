"""Frame and table readers and writers: the only place where stages' data meets files.

Frames reach the stages as :class:`stages.artifacts.Radiograph` (float32,
larger = brighter) with their source bit depth and metadata beside them.

- DICOM (single and multi-frame) via pydicom; the modality LUT is applied and
  MONOCHROME1 is inverted to MONOCHROME2.
- TIFF, PNG and other stills via OpenImageIO.
- Video (``.avi``, ``.mp4``, ``.mov``, ``.mkv``) via OpenCV.
"""

from __future__ import annotations

import csv
import os
import tempfile
from pathlib import Path

import numpy as np
from fluorocal.stages.artifacts import Phantom, Radiograph
from fluorocal.stages.errors import InputError

VIDEO_SUFFIXES = {".avi", ".mp4", ".mov", ".mkv", ".m4v", ".wmv"}
DICOM_SUFFIXES = {".dcm", ".ima", ".dicom"}


def _is_dicom(path: Path) -> bool:
    if path.suffix.lower() in DICOM_SUFFIXES:
        return True
    try:
        with open(path, "rb") as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except OSError:
        return False


def read_frames(path: str | os.PathLike) -> list[Radiograph]:
    """Read every frame of an image, DICOM or video file.

    Raises
    ------
    InputError
        The file is missing, unreadable or holds no monochrome frame.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        if _is_dicom(path):
            return _read_dicom(path)
        if path.suffix.lower() in VIDEO_SUFFIXES:
            return _read_video(path)
        return _read_still(path)
    except InputError:
        raise
    except Exception as exc:  # library errors differ by format; name the file
        raise InputError(f"{path}: cannot read as an image ({type(exc).__name__}: {exc})") from exc


def probe_frames(path: str | os.PathLike) -> tuple[int, tuple[int, int]]:
    """Number of frames in a file and their size ``(width, height)`` px, from the header where possible.

    Raises
    ------
    InputError
        The file is missing or unreadable.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        if _is_dicom(path):
            import pydicom

            ds = pydicom.dcmread(path, stop_before_pixels=True)
            return int(getattr(ds, "NumberOfFrames", 1) or 1), (int(ds.Columns), int(ds.Rows))
        if path.suffix.lower() in VIDEO_SUFFIXES:
            frames = _read_video(path)
            return len(frames), (frames[0].shape[1], frames[0].shape[0])
        import OpenImageIO as oiio

        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise InputError(f"{path}: cannot read as an image ({oiio.geterror()})")
        size = (inp.spec().width, inp.spec().height)
        n = 0
        while inp.seek_subimage(n, 0):
            n += 1
        inp.close()
        return n, size
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"{path}: cannot read as an image ({type(exc).__name__}: {exc})") from exc


def _read_dicom(path: Path) -> list[Radiograph]:
    import pydicom
    from pydicom.pixels import apply_modality_lut

    ds = pydicom.dcmread(path)
    if "PixelData" not in ds:
        raise InputError(f"{path}: DICOM file has no pixel data")
    pixels = apply_modality_lut(ds.pixel_array, ds).astype(np.float32)
    n_frames = int(getattr(ds, "NumberOfFrames", 1) or 1)
    frames = pixels.reshape((n_frames,) + pixels.shape[-2:]) if pixels.ndim >= 2 else pixels
    if frames.ndim != 3:
        raise InputError(f"{path}: expected monochrome frames; got pixel array of shape {pixels.shape}")
    bit_depth = int(getattr(ds, "BitsStored", 16))
    if str(getattr(ds, "PhotometricInterpretation", "MONOCHROME2")) == "MONOCHROME1":
        frames = float(2**bit_depth - 1) - frames
    meta = {
        "format": "dicom",
        "modality": str(getattr(ds, "Modality", "")),
        "photometric": str(getattr(ds, "PhotometricInterpretation", "")),
    }
    for tag in ("PixelSpacing", "ImagerPixelSpacing", "DistanceSourceToDetector", "FieldOfViewDimensions"):
        if tag in ds and ds.data_element(tag).value not in (None, ""):
            value = ds.data_element(tag).value
            meta[tag] = (
                [float(v) for v in value]
                if isinstance(value, (list, tuple, pydicom.multival.MultiValue))
                else float(value)
            )
    return [Radiograph(np.ascontiguousarray(f), bit_depth, str(path), i, meta) for i, f in enumerate(frames)]


def _read_still(path: Path) -> list[Radiograph]:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read as an image ({oiio.geterror()})")
    try:
        frames = []
        subimage = 0
        while inp.seek_subimage(subimage, 0):
            spec = inp.spec()
            pixels = inp.read_image(spec.format)
            if pixels is None:
                raise InputError(f"{path}: cannot decode subimage {subimage} ({inp.geterror()})")
            frames.append(_still_to_radiograph(path, subimage, spec, pixels))
            subimage += 1
    finally:
        inp.close()
    return frames


def _still_to_radiograph(path: Path, index: int, spec, pixels: np.ndarray) -> Radiograph:
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
    meta = {"format": spec.get_string_attribute("oiio:Format", "") or path.suffix.lstrip(".").lower()}
    return Radiograph(image, int(bits), str(path), index, meta)


def _read_video(path: Path) -> list[Radiograph]:
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputError(f"{path}: cannot open as a video")
    frames = []
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            grey = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            bits = 16 if grey.dtype == np.uint16 else 8
            frames.append(Radiograph(grey.astype(np.float32), bits, str(path), len(frames), {"format": "video"}))
    finally:
        cap.release()
    if not frames:
        raise InputError(f"{path}: video holds no decodable frame")
    return frames


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: str | os.PathLike, writer) -> None:
    """Call ``writer(tmp_path)`` then rename the temporary file onto ``path``.

    The temporary file sits in the same directory (same file system) and keeps
    the suffix, so format detection by extension still works; it is removed if
    ``writer`` fails, so nothing half-written is ever left under ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        writer(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the file the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_still(path: str | os.PathLike, image: np.ndarray, *, attributes: dict | None = None) -> None:
    """Write a monochrome image atomically with OpenImageIO, in the dtype given.

    ``image`` is written as-is (uint8, uint16 or float32). ``attributes`` are
    OpenImageIO spec attributes, e.g. a fixed ``DateTime`` so that the same
    pixels give the same bytes (OpenImageIO stamps the current time otherwise).
    """
    import OpenImageIO as oiio

    image = np.ascontiguousarray(image)
    fmt = {np.dtype(np.uint8): "uint8", np.dtype(np.uint16): "uint16", np.dtype(np.float32): "float"}.get(image.dtype)
    if fmt is None:
        raise InputError(f"write_still: unsupported dtype {image.dtype} for {path}")

    def _write(tmp):
        out = oiio.ImageOutput.create(tmp)
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


def read_phantom(path: str | os.PathLike, *, lattice: str = "", pitch_mm: float = 0.0) -> Phantom:
    """Read a phantom CSV ``id,x,y,z[,diameter][,role]`` (mm).

    Raises
    ------
    InputError
        Missing file, missing column, or a value that is not a number, naming the line.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: phantom file not found")
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        header = [h.strip() for h in (reader.fieldnames or [])]
        missing = [c for c in ("id", "x", "y", "z") if c not in header]
        if missing:
            raise InputError(
                f"{path}: phantom CSV needs columns id,x,y,z[,diameter][,role]; missing {','.join(missing)}"
            )
        ids, xyz, diam, role = [], [], [], []
        for line_no, row in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
            try:
                ids.append(int(row["id"]))
                xyz.append([float(row["x"]), float(row["y"]), float(row["z"])])
                diam.append(float(row["diameter"]) if row.get("diameter") else np.nan)
            except ValueError as exc:
                raise InputError(f"{path}:{line_no}: not a number ({exc})") from exc
            role.append(row.get("role", ""))
    if not ids:
        raise InputError(f"{path}: phantom CSV has no beads")
    try:
        return Phantom(np.array(ids), np.array(xyz), np.array(diam), np.array(role), lattice, pitch_mm)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from exc


def read_seeds(path: str | os.PathLike) -> dict:
    """Manual seeds ``id,x,y[,file[,frame]]`` (px): ``{(file name or "", frame): ((id, x, y), ...)}``.

    Rows without a file belong to the first frame of the sequence (key ``("", 0)``).

    Raises
    ------
    InputError
        Missing file or column, or a value that is not a number, naming the line.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: seeds file not found")
    seeds: dict = {}
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        header = [h.strip() for h in (reader.fieldnames or [])]
        missing = [c for c in ("id", "x", "y") if c not in header]
        if missing:
            raise InputError(f"{path}: seeds CSV needs columns id,x,y[,file,frame]; missing {','.join(missing)}")
        for line_no, row in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
            try:
                seed = (float(int(row["id"])), float(row["x"]), float(row["y"]))
                key = (Path(row["file"]).name, int(row.get("frame") or 0)) if row.get("file") else ("", 0)
            except ValueError as exc:
                raise InputError(f"{path}:{line_no}: not a number ({exc})") from exc
            seeds.setdefault(key, []).append(seed)
    return {k: tuple(v) for k, v in seeds.items()}


def write_csv(path: str | os.PathLike, header: list[str], rows) -> None:
    """Write a CSV table atomically (floats with 6 decimals)."""

    def fmt(v):
        return f"{v:.6f}" if isinstance(v, (float, np.floating)) else str(v)

    def _write(tmp):
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(header)
            for row in rows:
                w.writerow([fmt(v) for v in row])

    atomic_write(path, _write)


def _to_source_dtype(radiograph: Radiograph) -> np.ndarray:
    """Round and clip a frame back to the integer type of its bit depth (float32 for float sources)."""
    if radiograph.bit_depth > 16:
        return radiograph.image.astype(np.float32)
    dtype = np.uint8 if radiograph.bit_depth <= 8 else np.uint16
    return np.clip(np.rint(radiograph.image), 0, 2**radiograph.bit_depth - 1).astype(dtype)


def write_frames_like(source: str | os.PathLike, frames: list[Radiograph], out_path: str | os.PathLike) -> None:
    """Write ``frames`` to ``out_path`` in the format, bit depth and metadata of ``source``, atomically.

    DICOM: the source's data set is copied with new pixel data (uncompressed),
    a new SOP Instance UID and a derivation note. Stills: the same type via
    OpenImageIO. Video: the same container and codec via OpenCV.
    """
    source, out_path = Path(source), Path(out_path)
    if _is_dicom(source):
        _write_dicom_like(source, frames, out_path)
    elif source.suffix.lower() in VIDEO_SUFFIXES:
        _write_video_like(source, frames, out_path)
    else:
        if len(frames) != 1:
            raise InputError(f"{source}: writing {len(frames)} frames to a still image is not supported")
        write_still(out_path, _to_source_dtype(frames[0]))


def _write_dicom_like(source: Path, frames: list[Radiograph], out_path: Path) -> None:
    import pydicom
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    ds = pydicom.dcmread(source)
    pixels = np.stack([_to_source_dtype(f) for f in frames])
    if str(getattr(ds, "PhotometricInterpretation", "")) == "MONOCHROME1":
        pixels = (2 ** frames[0].bit_depth - 1 - pixels.astype(np.int64)).astype(pixels.dtype)
    slope, intercept = float(getattr(ds, "RescaleSlope", 1) or 1), float(getattr(ds, "RescaleIntercept", 0) or 0)
    if (slope, intercept) != (1.0, 0.0):  # store raw values so the modality LUT gives the output back
        pixels = np.clip(np.rint((pixels - intercept) / slope), 0, 2 ** int(ds.BitsStored) - 1).astype(np.uint16)
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.PixelData = (
        (pixels[0] if len(frames) == 1 else pixels).astype(np.uint16 if ds.BitsAllocated == 16 else np.uint8).tobytes()
    )
    if len(frames) > 1:
        ds.NumberOfFrames = len(frames)
    ds.SOPInstanceUID = generate_uid()
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    ds.DerivationDescription = "geometric distortion corrected by fluorocal"
    ds.ImageType = ["DERIVED", "SECONDARY"] + list(getattr(ds, "ImageType", [])[2:])
    atomic_write(out_path, lambda tmp: ds.save_as(tmp, enforce_file_format=True))


def _write_video_like(source: Path, frames: list[Radiograph], out_path: Path) -> None:
    import cv2

    cap = cv2.VideoCapture(str(source))
    fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
    fourcc = int(cap.get(cv2.CAP_PROP_FOURCC)) or cv2.VideoWriter_fourcc(*"MJPG")
    cap.release()
    h, w = frames[0].shape

    def _write(tmp):
        writer = cv2.VideoWriter(tmp, fourcc, fps, (w, h), isColor=False)
        if not writer.isOpened():
            raise InputError(f"{out_path}: cannot open a video writer for this codec")
        for f in frames:
            writer.write(np.clip(np.rint(f.image), 0, 255).astype(np.uint8))
        writer.release()

    atomic_write(out_path, _write)
