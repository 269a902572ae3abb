"""How far a test image is from a reference image, whether it differs from it by more
than Monte Carlo noise, and how often two renders hit the same primitive first.

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

:func:`noise_judge` decides whether a test image is another Monte Carlo sample of the
reference's image (its module of rules is there); the figures above describe, they do
not judge: two unbiased renders may share few bit-identical pixels.
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


#: The smallest block side :func:`noise_judge` sums over: 64 pixels, enough that the
#: native pair's sum of squares is a steady estimate of the noise (over smaller blocks a
#: few quiet pixels make it one).
SMALLEST_BLOCK = 8

#: The largest ``|z|`` of any block :func:`noise_judge` passes. Measured (docs/judge.md):
#: over 1,200 native-vs-native triples (three seeds, so the test is an independent
#: sample: the judge's hardest unbiased case) of cloth, world and rigid:instanced=true
#: frames, the largest ``|z|`` of a frame over every block, side and channel had median
#: 3.0, 99th percentile 4.3 and maximum 4.9; hlbvh against native with the same seed
#: (paths parting on ties) reached 0.52. A Gaussian passes 6 with probability 2e-9 a
#: block.
NOISE_LIMIT = 6.0

#: Differences this small relative to the reference's pixel are rounding (two
#: accelerators' hit points differ in the last bits), not noise: a per-pixel standard
#: deviation of this much times the pixel's magnitude is added to every block's noise,
#: so that a region without Monte Carlo noise (a constant sky, where native's two
#: renders agree to the bit) does not fail on rounding.
ROUNDING = 1e-4


def noise_judge(test, reference, reference_again=None, limit: float = NOISE_LIMIT) -> dict:
    """Whether ``test`` is another Monte Carlo sample of the image ``reference`` samples,
    judged against the noise two references with different seeds show.

    The rule. With ``D = test - reference`` and ``N = reference_again - reference`` (the
    noise: two renders of one image with different seeds), per channel and per square
    block of pixels::

        z = sum(D) / sqrt(sum(N**2) + max(D**2) + sum((ROUNDING * reference)**2))

    over blocks of every power-of-two side from :data:`SMALLEST_BLOCK` up to the one that
    covers the image (blocks tile from the top left; the last row and column may be
    narrower): the largest side is the bias test over the whole image, the middle ones
    per region. The test passes when no block reaches ``|z| >= limit`` and no pixel is
    NaN or infinite in the test where both references are finite.

    Why. If the test is an unbiased sample of the same image, each pixel's ``D`` has
    mean 0 and a variance at most ``N``'s: equal when the test's paths are independent of
    the reference's (another seed, a sub-frame accumulation), smaller when it shares the
    reference's seed and its paths part only here and there (a ray through a shared edge
    hitting the neighbouring triangle: what follows is another sample). So
    ``sum(N**2)`` estimates (conservatively) the variance of ``sum(D)``, and ``z`` is a
    block mean in units of its noise. A biased test (other geometry, a stale frame, a
    wrong shading) moves the mean of many pixels one way, and ``|z|`` grows with the
    block. ``max(D**2)``, the block's largest single difference, keeps one outlier from
    failing a frame: a firefly in the test where the native pair happens to be quiet
    reaches ``|z|`` 1 at most (without it such blocks reached ``z`` of thousands on
    native-vs-native triples); ``ROUNDING`` keeps last-bit differences from failing a
    block without noise. Differences below the noise at the render's spp pass (a vertex
    moved by one pixel on a 16 spp render moves a block mean by about 2.5 noise units:
    render more spp to see such a defect). The fraction of bit-identical pixels is
    returned as a figure: a render whose paths part on ties has few and is still right.

    Args:
        test: the image under test, ``(H, W)`` or ``(H, W, C)`` (``mi.TensorXf`` or numpy).
        reference: the reference image, same shape.
        reference_again: the reference's image rendered with another seed, same shape;
            ``None`` when ``test`` is bit-identical to ``reference`` (nothing to judge).
        limit: the ``|z|`` a block may not reach (default :data:`NOISE_LIMIT`).

    Returns:
        ``passed`` (bool); ``largest_z`` (the block whose ``|z|`` is largest: its signed
        ``z``), ``largest_z_block`` (``"SxS at x,y channel C"``, its side, top left corner
        and channel), ``image_z`` (the whole image's ``z`` of largest ``|z|`` over the
        channels: the bias test); ``blocks_over_limit`` (blocks, over every side and
        channel, with ``|z| >= limit``); ``nonfinite_pixels`` (NaN or infinite in the
        test where both references are finite; left out of the sums, as every pixel
        non-finite in any of the three is); ``noise_rms`` (one render's per-pixel
        noise, ``rms(N) / sqrt(2)`` over the channels; 0 without ``reference_again``);
        ``fraction_identical`` (pixels of ``test`` bit-identical to ``reference``'s);
        ``limit``.

    Raises:
        ValueError: shapes differ, ``limit`` is not a finite number > 0, or
            ``reference_again`` is ``None`` while ``test`` differs from ``reference``.
    """
    test = as_image(test, "test")
    reference = as_image(reference, "reference")
    _check_same_shape(reference.shape, test.shape)
    if not (_is_real(limit) and math.isfinite(limit) and limit > 0):
        raise ValueError(f"limit={limit!r}: expected a finite number > 0")
    identical = np.all(reference.view(np.uint32) == test.view(np.uint32), axis=2)
    if reference_again is None:
        if not identical.all():
            raise ValueError("reference_again: needed (the noise) where the test differs "
                             "from the reference")
        again = reference
    else:
        again = as_image(reference_again, "reference_again")
        _check_same_shape(reference.shape, again.shape)

    # ---- Pixels judged: finite in all three ----
    finite = [np.all(np.isfinite(image), axis=2) for image in (test, reference, again)]
    judged = finite[0] & finite[1] & finite[2]
    nonfinite = ~finite[0] & finite[1] & finite[2]
    mask = judged[:, :, np.newaxis]
    base = np.where(mask, reference.astype(np.float64), 0.0)
    difference = np.where(mask, test - base, 0.0)
    noise = np.where(mask, again - base, 0.0)
    variance = np.square(noise) + np.square(ROUNDING * base)

    # ---- Block z at every side ----
    height, width, channels = test.shape
    largest, where, over, image_z = 0.0, "none", 0, 0.0
    side = SMALLEST_BLOCK
    while True:
        z = _block_z(difference, variance, side)
        over += int((np.abs(z) >= limit).sum())
        k = int(np.argmax(np.abs(z)))
        if abs(z.flat[k]) > abs(largest):
            row, column, channel = np.unravel_index(k, z.shape)
            largest = float(z.flat[k])
            where = f"{side}x{side} at {column * side},{row * side} channel {channel}"
        if side >= max(height, width):
            image_z = float(z[0, 0, np.argmax(np.abs(z[0, 0]))])
            break
        side *= 2
    count = int(judged.sum()) * channels
    return {
        "passed": abs(largest) < limit and not nonfinite.any(),
        "largest_z": largest,
        "largest_z_block": where,
        "image_z": image_z,
        "blocks_over_limit": over,
        "nonfinite_pixels": int(nonfinite.sum()),
        "noise_rms": float(np.sqrt(np.square(noise).sum() / (2 * count))) if count else 0.0,
        "fraction_identical": float(identical.sum() / identical.size),
        "limit": float(limit),
    }


def _block_z(difference: np.ndarray, variance: np.ndarray, side: int) -> np.ndarray:
    """:func:`noise_judge`'s ``z`` of every ``side`` x ``side`` block and channel, an
    array ``(rows of blocks, columns of blocks, C)``, from the per-pixel differences and
    noise variances; 0 where a block has neither."""
    def blocks(values):
        height, width, channels = values.shape
        rows, columns = -(-height // side), -(-width // side)
        padded = np.pad(values, ((0, rows * side - height), (0, columns * side - width), (0, 0)))
        return padded.reshape(rows, side, columns, side, channels)

    total = blocks(difference).sum(axis=(1, 3))
    noise = blocks(variance).sum(axis=(1, 3)) + np.square(blocks(difference)).max(axis=(1, 3))
    return np.divide(total, np.sqrt(noise), out=np.zeros_like(total), where=noise > 0)


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
