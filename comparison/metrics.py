"""How far a test image is from a reference image, and how often two renders hit the same
primitive first.

Definitions used by :func:`image_metrics` (a *pixel* is all C channels at one position;
differences are taken per channel in float64 from the float32 values):

- *bit-identical*: every channel of the pixel has the same 32-bit pattern in both images
  (so ``-0.0`` differs from ``0.0``, and a NaN equals only the same NaN).
- *compared pixels*: pixels whose channels are all finite in both images. The maximum and
  mean absolute difference, the squared error and PSNR are taken over these only.
- *non-finite pixels*: a pixel with a NaN or infinite channel. They are counted for each
  image, and ``nonfinite_mismatch_pixels`` counts those that are not bit-identical; such
  a pixel is never within tolerance. A clean comparison has that count at zero.
- *within tolerance*: bit-identical, or compared with every channel's absolute
  difference at most ``tolerance``.
- *PSNR*: ``10 log10(peak^2 / MSE)`` in dB, MSE over the compared pixels' channels.
  The peak defaults to the largest finite absolute value of the reference (1 when that
  is 0), so an HDR render is judged against its own range. Images without a difference
  on any compared pixel get ``inf``; the result is never NaN.
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from hlbvh.render.images import as_image


def image_metrics(reference, test, tolerance: float, peak: float | None = None) -> dict:
    """Difference statistics of ``test`` against ``reference`` (definitions in the module
    docstring).

    Args:
        reference, test: images of the same shape, ``(H, W)`` or ``(H, W, C)``
            (``mi.TensorXf`` or numpy; compared as float32).
        tolerance: largest absolute per-channel difference a pixel may have to count as
            within tolerance (finite, >= 0).
        peak: the PSNR peak; ``None`` for the reference's largest finite magnitude.

    Returns:
        A flat dict of plain Python numbers: ``pixels``, ``channels``, ``compared_pixels``,
        ``max_abs_diff``, ``mean_abs_diff``, ``identical_pixels``,
        ``fraction_identical``, ``tolerance``, ``within_tolerance_pixels``,
        ``fraction_within_tolerance``, ``psnr_db``, ``psnr_peak``,
        ``nonfinite_pixels_reference``, ``nonfinite_pixels_test``,
        ``nonfinite_mismatch_pixels``.

    Raises:
        ValueError: shapes differ, or ``tolerance`` / ``peak`` is not a valid number.
    """
    reference = as_image(reference, "reference")
    test = as_image(test, "test")
    _check_same_shape(reference.shape, test.shape)
    if not (_is_real(tolerance) and math.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"tolerance={tolerance!r}: expected a finite number >= 0")

    # ---- Per-pixel classification ----
    height, width, channels = reference.shape
    pixels = height * width
    identical, finite_reference, finite_test, difference, within = _classified(
        reference, test, tolerance)
    compared = finite_reference & finite_test
    max_abs_diff = float(difference.max()) if difference.size else 0.0
    mean_abs_diff = float(difference.sum() / difference.size) if difference.size else 0.0
    mse = float(np.square(difference).sum() / difference.size) if difference.size else 0.0

    # ---- PSNR ----
    if peak is None:
        finite_values = np.abs(reference[np.isfinite(reference)])
        peak = float(finite_values.max()) if finite_values.size else 0.0
        peak = peak if peak > 0.0 else 1.0
    elif not (_is_real(peak) and math.isfinite(peak) and peak > 0):
        raise ValueError(f"peak={peak!r}: expected a finite number > 0, or None")
    # In logarithms, so that neither peak**2 nor peak**2 / mse can overflow.
    psnr_db = math.inf if mse == 0.0 else 20.0 * math.log10(peak) - 10.0 * math.log10(mse)

    return {
        "pixels": pixels,
        "channels": channels,
        "compared_pixels": int(compared.sum()),
        "max_abs_diff": max_abs_diff,
        "mean_abs_diff": mean_abs_diff,
        "identical_pixels": int(identical.sum()),
        "fraction_identical": float(identical.sum() / pixels),
        "tolerance": float(tolerance),
        "within_tolerance_pixels": int(within.sum()),
        "fraction_within_tolerance": float(within.sum() / pixels),
        "psnr_db": psnr_db,
        "psnr_peak": float(peak),
        "nonfinite_pixels_reference": int((~finite_reference).sum()),
        "nonfinite_pixels_test": int((~finite_test).sum()),
        "nonfinite_mismatch_pixels": int((~compared & ~identical).sum()),
    }


def within_tolerance(reference, test, tolerance: float) -> np.ndarray:
    """``(H, W)`` bool: each pixel of ``test`` within ``tolerance`` of ``reference``'s
    (the module docstring's definition, the one :func:`image_metrics` counts)."""
    reference = as_image(reference, "reference")
    test = as_image(test, "test")
    _check_same_shape(reference.shape, test.shape)
    return _classified(reference, test, tolerance)[4]


def _classified(reference: np.ndarray, test: np.ndarray, tolerance: float) -> tuple:
    """Per pixel: ``(bit-identical, finite in the reference, finite in the test, the
    absolute differences of the compared pixels' channels (float64, (N, C)), within
    tolerance)``."""
    identical = np.all(reference.view(np.uint32) == test.view(np.uint32), axis=2)
    finite_reference = np.all(np.isfinite(reference), axis=2)
    finite_test = np.all(np.isfinite(test), axis=2)
    compared = finite_reference & finite_test
    difference = np.abs(test[compared].astype(np.float64) - reference[compared].astype(np.float64))
    within = identical.copy()
    within[compared] |= np.all(difference <= tolerance, axis=1)
    return identical, finite_reference, finite_test, difference, within


def hit_agreement(ref_aov, test_aov) -> dict:
    """How many pixels hit the same shape and the same primitive first.

    Args:
        ref_aov, test_aov: per-pixel primary-hit indices, each either an array of shape
            ``(H, W, 2)`` holding (shape index, primitive index) or a pair of ``(H, W)``
            arrays ``(shape_index, prim_index)``. Integer arrays, or float arrays holding
            whole numbers (as Mitsuba's AOV films store them). However misses are encoded
            (e.g. shape index -1), a miss agrees with a miss encoded the same way.

    Returns:
        ``pixels``, ``agree_pixels`` and ``fraction_agree`` (shape and primitive both
        equal), ``shape_agree_pixels`` and ``fraction_shape_agree`` (shape equal),
        ``nonfinite_pixels`` (pixels with a NaN or infinite index in either input;
        they never agree).

    Raises:
        ValueError: shapes differ, an input is not (H, W, 2) / a pair of (H, W), or a
            float index is not a whole number.
    """
    reference, reference_finite = _hit_indices(ref_aov, "ref_aov")
    test, test_finite = _hit_indices(test_aov, "test_aov")
    _check_same_shape(reference.shape, test.shape)
    finite = reference_finite & test_finite
    shape_agree = finite & (reference[..., 0] == test[..., 0])
    agree = shape_agree & (reference[..., 1] == test[..., 1])
    pixels = int(finite.size)
    return {
        "pixels": pixels,
        "agree_pixels": int(agree.sum()),
        "fraction_agree": float(agree.sum() / pixels),
        "shape_agree_pixels": int(shape_agree.sum()),
        "fraction_shape_agree": float(shape_agree.sum() / pixels),
        "nonfinite_pixels": int((~finite).sum()),
    }


def _hit_indices(aov, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(int64 array (H, W, 2) with non-finite entries zeroed, bool (H, W) all-finite)."""
    if isinstance(aov, (tuple, list)):
        if len(aov) != 2:
            raise ValueError(f"{name}: expected a pair (shape_index, prim_index), got {len(aov)} arrays")
        shapes = {np.shape(part) for part in aov}
        if len(shapes) != 1:
            raise ValueError(f"{name}: shape_index and prim_index have different shapes {shapes}")
        aov = np.stack([np.asarray(part) for part in aov], axis=-1)
    indices = np.asarray(aov)
    if indices.ndim != 3 or indices.shape[2] != 2 or 0 in indices.shape:
        raise ValueError(
            f"{name}: expected per-pixel (shape index, primitive index) of shape (H, W, 2) "
            f"or a pair of (H, W) arrays, got shape {indices.shape}"
        )
    if indices.dtype.kind in "iub":
        return indices.astype(np.int64), np.ones(indices.shape[:2], dtype=bool)
    if indices.dtype.kind != "f":
        raise ValueError(f"{name}: expected integer or float indices, got dtype {indices.dtype}")
    finite_entries = np.isfinite(indices)
    whole = np.where(finite_entries, indices, 0.0)
    if np.any(whole != np.round(whole)):
        raise ValueError(f"{name}: float indices must be whole numbers; this is not an index image")
    return whole.astype(np.int64), np.all(finite_entries, axis=2)


def _is_real(value) -> bool:
    """A real number (Python or numpy scalar), not a bool or a string."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _check_same_shape(reference_shape: tuple, test_shape: tuple) -> None:
    if reference_shape != test_shape:
        raise ValueError(
            f"reference has shape {reference_shape} but test has {test_shape}; compare "
            "renders of the same resolution and channel count"
        )
