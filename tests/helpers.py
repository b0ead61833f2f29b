"""Helpers shared by the test modules: one DICOM builder and one "error modulo a homography".

Test modules import helpers from here (or from the other helper modules of tests/: ``toy``, ``ba_synthetic``,
``_synthetic``, ``orientation_toys``, ``plate_synthetic``, ``plate_truth``, ``label_truth``), never from another
test module or from ``benchmarks/``.
"""

from __future__ import annotations

import numpy as np


def xa_dataset(
    rows: int,
    cols: int,
    *,
    bits_stored: int = 12,
    photometric: str = "MONOCHROME2",
    syntax: str = "ExplicitVRLittleEndian",
    sop_class: str = "XRayAngiographicImageStorage",
    **tags,
):
    """A minimal monochrome X-ray data set of ``rows`` x ``cols`` 16-bit pixels, without pixel data.

    It carries new study, series and instance UIDs, a patient id, an image type and a series description;
    ``tags`` set more attributes, or delete one when given as None. ``syntax`` and ``sop_class`` are names
    in :mod:`pydicom.uid`. Write it with :func:`save_dicom` (or with the writer under test).
    """
    import pydicom
    from pydicom import uid
    from pydicom.dataset import FileMetaDataset

    ds = pydicom.Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = getattr(uid, syntax)
    ds.file_meta.MediaStorageSOPClassUID = ds.SOPClassUID = getattr(uid, sop_class)
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID = uid.generate_uid()
    ds.StudyInstanceUID, ds.SeriesInstanceUID = uid.generate_uid(), uid.generate_uid()
    ds.Modality, ds.PatientID, ds.PhotometricInterpretation = "XA", "P1", photometric
    ds.ImageType, ds.SeriesDescription = ["ORIGINAL", "PRIMARY", "SINGLE PLANE"], "Spine AP"
    ds.Rows, ds.Columns, ds.SamplesPerPixel = rows, cols, 1
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, bits_stored, bits_stored - 1, 0
    ds.ImagerPixelSpacing = [0.25, 0.25]
    for tag, value in tags.items():
        if value is None:
            delattr(ds, tag)
        else:
            setattr(ds, tag, value)
    return ds


def save_dicom(path, frames: np.ndarray, **dataset_options):
    """Save ``frames`` ``(F, H, W)`` uint16 as an :func:`xa_dataset` (options passed on) at ``path``; the data set."""
    frames = np.asarray(frames)
    ds = xa_dataset(*frames.shape[1:], **dataset_options)
    if len(frames) > 1:
        ds.NumberOfFrames = len(frames)
    ds.PixelData = np.ascontiguousarray(frames, dtype="<u2").tobytes()
    ds.save_as(path, enforce_file_format=True)
    return ds


def homography_residual_px(src: np.ndarray, dst: np.ndarray, *, refine: bool = False) -> np.ndarray:
    """``dst - H(src)`` ``(N, 2)``, ``H`` the least-squares homography taking ``src`` (px or mm) to ``dst`` (px).

    ``H`` is OpenCV's direct linear transform (an algebraic least-squares fit); with ``refine`` it is then refined
    to the least squares of the residuals themselves (px).
    """
    import cv2

    src = np.asarray(src, dtype=np.float64)
    H, _ = cv2.findHomography(src, dst, 0)

    def residual(h):
        return dst - cv2.perspectiveTransform(src[None], np.append(h, 1.0).reshape(3, 3))[0]

    h = (H / H[2, 2]).ravel()[:8]
    if refine:
        from scipy.optimize import least_squares

        h = least_squares(lambda p: residual(p).ravel(), h, x_scale="jac").x
    return residual(h)


def rms_length(residual_px: np.ndarray) -> float:
    """RMS of the lengths of ``(N, 2)`` residuals, px."""
    return float(np.sqrt(np.mean(np.sum(np.asarray(residual_px) ** 2, axis=1))))


def rms_modulo_homography(src: np.ndarray, dst: np.ndarray, *, refine: bool = False) -> float:
    """RMS length (px) of ``dst`` about the best homography of ``src`` (:func:`homography_residual_px`)."""
    return rms_length(homography_residual_px(src, dst, refine=refine))
