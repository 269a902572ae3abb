"""``hlbvh.comparison.metrics``: image differences and primary-hit agreement on hand-made
arrays whose answers are known exactly (values chosen to be exact in float32, so the
expected numbers are written down, not recomputed the way the module does)."""

import math

import numpy as np
import pytest

from hlbvh.comparison.metrics import NOISE_LIMIT, hit_agreement, image_metrics, noise_judge

H, W, C = 6, 5, 3
PIXELS = H * W


def ramp() -> np.ndarray:
    """A (6, 5, 3) float32 image of distinct values in [0, 2), with negatives."""
    return (np.arange(PIXELS * C, dtype=np.float32).reshape(H, W, C) / 64.0 - 0.25)


def with_one_pixel(image, row, column, channel, amount) -> np.ndarray:
    changed = image.copy()
    changed[row, column, channel] += np.float32(amount)
    return changed


# ---- image_metrics ----


@pytest.mark.parametrize("image", [ramp(), np.zeros((H, W, C), np.float32),
                                   np.full((H, W), 7.5, np.float32)],
                         ids=["ramp", "black", "grey"])
def test01_identical_images_have_no_difference(image):
    metrics = image_metrics(image, image.copy(), tolerance=0.0)
    assert metrics["max_abs_diff"] == 0.0 and metrics["mean_abs_diff"] == 0.0
    assert metrics["identical_pixels"] == metrics["pixels"] == PIXELS
    assert metrics["fraction_identical"] == 1.0
    assert metrics["within_tolerance_pixels"] == PIXELS
    assert metrics["fraction_within_tolerance"] == 1.0
    assert metrics["psnr_db"] == math.inf  # never NaN, even for an all-black image
    assert metrics["nonfinite_pixels_reference"] == metrics["nonfinite_pixels_test"] == 0
    assert metrics["nonfinite_mismatch_pixels"] == 0


def test02_one_pixel_changed_by_a_known_amount():
    amount = 0.125  # exact in float32 at these magnitudes
    reference = ramp()
    test = with_one_pixel(reference, 2, 3, 1, amount)
    metrics = image_metrics(reference, test, tolerance=0.0)
    assert metrics["pixels"] == PIXELS and metrics["channels"] == C
    assert metrics["compared_pixels"] == PIXELS
    assert metrics["max_abs_diff"] == amount
    assert metrics["mean_abs_diff"] == amount / (PIXELS * C)
    assert metrics["identical_pixels"] == PIXELS - 1
    assert metrics["fraction_identical"] == 1 - 1 / PIXELS
    # PSNR by its definition: the peak is the reference's largest magnitude.
    peak = float(np.abs(reference).max())
    assert metrics["psnr_peak"] == peak
    mse = amount**2 / (PIXELS * C)
    assert metrics["psnr_db"] == pytest.approx(10 * math.log10(peak**2 / mse))
    # The sign of the change does not matter.
    assert image_metrics(reference, with_one_pixel(reference, 2, 3, 1, -amount), 0.0)[
        "max_abs_diff"] == amount


def test03_within_tolerance_on_both_sides_of_the_tolerance():
    amount = 0.125
    reference = ramp()
    test = with_one_pixel(reference, 0, 0, 2, amount)
    at = image_metrics(reference, test, tolerance=amount)
    assert at["within_tolerance_pixels"] == PIXELS and at["fraction_within_tolerance"] == 1.0
    below = image_metrics(reference, test, tolerance=math.nextafter(amount, 0.0))
    assert below["within_tolerance_pixels"] == PIXELS - 1
    assert below["fraction_within_tolerance"] == 1 - 1 / PIXELS
    # Per channel, not summed over channels: two channels each off by 0.125 are within 0.125.
    two = with_one_pixel(test, 0, 0, 0, amount)
    assert image_metrics(reference, two, tolerance=amount)["fraction_within_tolerance"] == 1.0
    assert image_metrics(reference, two, tolerance=0.1)["within_tolerance_pixels"] == PIXELS - 1


def test04_bit_identical_means_the_same_bits():
    """-0.0 and 0.0 differ by nothing but are not bit-identical; a pixel counts as
    identical only when all its channels are."""
    reference = np.zeros((H, W, C), np.float32)
    test = reference.copy()
    test[1, 1, 2] = -0.0
    metrics = image_metrics(reference, test, tolerance=0.0)
    assert metrics["max_abs_diff"] == 0.0 and metrics["psnr_db"] == math.inf
    assert metrics["identical_pixels"] == PIXELS - 1
    assert metrics["fraction_within_tolerance"] == 1.0


def test05_nonfinite_pixels_are_counted_not_propagated():
    amount = 0.25
    reference = ramp()
    test = with_one_pixel(reference, 4, 4, 0, amount)
    test[0, 1, 0] = np.nan          # only in test
    test[0, 2, 2] = np.inf          # only in test
    reference[5, 0, 1] = -np.inf    # only in reference
    reference[3, 3, 0] = test[3, 3, 0] = np.nan  # the same NaN in both: bit-identical
    metrics = image_metrics(reference, test, tolerance=1.0)
    for key, value in metrics.items():
        assert not (isinstance(value, float) and math.isnan(value)), key
    assert metrics["nonfinite_pixels_reference"] == 2
    assert metrics["nonfinite_pixels_test"] == 3
    assert metrics["nonfinite_mismatch_pixels"] == 3
    assert metrics["compared_pixels"] == PIXELS - 4
    # Differences over the finite pixels only: exactly the one changed channel.
    assert metrics["max_abs_diff"] == amount
    assert metrics["mean_abs_diff"] == amount / ((PIXELS - 4) * C)
    assert math.isfinite(metrics["psnr_db"])
    # A mismatched non-finite pixel is never within tolerance, however large it is.
    assert metrics["within_tolerance_pixels"] == PIXELS - 3
    assert metrics["identical_pixels"] == PIXELS - 4  # the shared NaN pixel counts
    # The PSNR peak ignores the reference's infinity.
    assert metrics["psnr_peak"] == float(np.abs(reference[np.isfinite(reference)]).max())


def test06_all_pixels_nonfinite_gives_numbers_not_nan():
    reference = np.full((2, 2, 3), np.nan, np.float32)
    test = np.full((2, 2, 3), np.inf, np.float32)
    metrics = image_metrics(reference, test, tolerance=0.5)
    assert metrics["compared_pixels"] == 0
    assert metrics["nonfinite_mismatch_pixels"] == 4
    assert metrics["fraction_within_tolerance"] == 0.0
    for key, value in metrics.items():
        assert not (isinstance(value, float) and math.isnan(value)), key


def test07_psnr_with_a_given_peak_and_huge_values():
    reference = np.zeros((2, 2), np.float32)
    test = reference.copy()
    test[0, 0] = 2.0  # MSE = 4 / 4 = 1
    assert image_metrics(reference, test, 0.0, peak=10.0)["psnr_db"] == pytest.approx(20.0)
    # The reference is black: the default peak is 1, so PSNR = 10 log10(1 / 1) = 0.
    assert image_metrics(reference, test, 0.0)["psnr_db"] == 0.0
    # Float32's extremes and a huge peak: a finite number, no overflow.
    big = np.full((2, 2), 3e38, np.float32)
    assert math.isfinite(image_metrics(big, -big, 0.0)["psnr_db"])
    assert image_metrics(reference, test, 0.0, peak=1e200)["psnr_db"] == pytest.approx(4000.0)


def test08_accepts_mitsuba_tensors_and_grey_images():
    import mitsuba as mi

    reference = ramp()
    test = with_one_pixel(reference, 1, 2, 0, 0.5)
    metrics = image_metrics(mi.TensorXf(reference), mi.TensorXf(test), 0.0)
    assert metrics["max_abs_diff"] == 0.5 and metrics["identical_pixels"] == PIXELS - 1
    grey = image_metrics(reference[..., 0], test[..., 0], 0.0)
    assert grey["channels"] == 1 and grey["mean_abs_diff"] == 0.5 / PIXELS


@pytest.mark.parametrize("reference_shape, test_shape", [
    ((H, W, C), (H, W, 4)), ((H, W, C), (W, H, C)), ((H, W), (H, W, 3)), ((H, W, C), (H + 1, W, C)),
])
def test09_shape_mismatch_is_a_value_error(reference_shape, test_shape):
    with pytest.raises(ValueError, match="shape"):
        image_metrics(np.zeros(reference_shape, np.float32), np.zeros(test_shape, np.float32), 0.0)


@pytest.mark.parametrize("kwargs, message", [
    ({"tolerance": -1.0}, "tolerance"), ({"tolerance": math.nan}, "tolerance"),
    ({"tolerance": math.inf}, "tolerance"), ({"tolerance": "0.1"}, "tolerance"),
    ({"tolerance": True}, "tolerance"), ({"tolerance": 0.0, "peak": 0.0}, "peak"),
    ({"tolerance": 0.0, "peak": math.inf}, "peak"), ({"tolerance": 0.0, "peak": -2.0}, "peak"),
])
def test10_bad_tolerance_or_peak_is_a_value_error(kwargs, message):
    with pytest.raises(ValueError, match=message):
        image_metrics(ramp(), ramp(), **kwargs)


@pytest.mark.parametrize("bad", [np.zeros((0, 4, 3)), np.zeros(12), np.zeros((2, 2, 2, 2))])
def test11_not_an_image_is_a_value_error(bad):
    with pytest.raises(ValueError, match="shape"):
        image_metrics(bad, bad, 0.0)


def test12_numpy_scalars_are_accepted_as_tolerance():
    reference = ramp()
    test = with_one_pixel(reference, 0, 0, 0, 0.125)
    for tolerance in (np.float32(0.125), np.float64(0.125), 1):
        assert image_metrics(reference, test, tolerance)["fraction_within_tolerance"] == 1.0


# ---- hit_agreement ----


def test13_hit_agreement_on_hand_made_indices():
    # shape index per pixel (-1: miss) and primitive index per pixel, 2 x 3 pixels.
    shapes = np.array([[0, 0, 1], [1, -1, 2]])
    prims = np.array([[5, 6, 7], [8, 0, 9]])
    test_shapes = np.array([[0, 0, 1], [2, -1, 2]])   # (1, 0): other shape
    test_prims = np.array([[5, 4, 7], [8, 0, 9]])     # (0, 1): same shape, other primitive
    result = hit_agreement((shapes, prims), (test_shapes, test_prims))
    assert result == {
        "pixels": 6,
        "agree_pixels": 4,
        "fraction_agree": 4 / 6,
        "shape_agree_pixels": 5,
        "fraction_shape_agree": 5 / 6,
        "nonfinite_pixels": 0,
    }
    # The same as (H, W, 2) arrays, and as floats (how AOV films store them).
    stacked = np.stack([shapes, prims], axis=-1)
    test_stacked = np.stack([test_shapes, test_prims], axis=-1)
    assert hit_agreement(stacked, test_stacked) == result
    assert hit_agreement(stacked.astype(np.float32), test_stacked.astype(np.float32)) == result
    assert hit_agreement(stacked, stacked)["fraction_agree"] == 1.0


def test14_hit_agreement_counts_nonfinite_indices_as_disagreeing():
    reference = np.zeros((2, 2, 2), np.float32)
    test = reference.copy()
    test[0, 0, 1] = np.nan
    reference[1, 1, 0] = np.inf
    result = hit_agreement(reference, test)
    assert result["nonfinite_pixels"] == 2
    assert result["agree_pixels"] == result["shape_agree_pixels"] == 2
    # NaN vs NaN is not an agreement either: a NaN is not an index.
    both = np.full((1, 1, 2), np.nan, np.float32)
    assert hit_agreement(both, both)["agree_pixels"] == 0


@pytest.mark.parametrize("reference, test, message", [
    (np.zeros((2, 3, 2)), np.zeros((3, 2, 2)), "shape"),
    (np.zeros((2, 3, 3)), np.zeros((2, 3, 3)), r"\(H, W, 2\)"),
    (np.zeros((2, 3)), np.zeros((2, 3)), r"\(H, W, 2\)"),
    ((np.zeros((2, 3)),), (np.zeros((2, 3)),), "pair"),
    ((np.zeros((2, 3)), np.zeros((3, 2))), (np.zeros((2, 3)), np.zeros((2, 3))),
     "different shapes"),
    (np.full((1, 1, 2), 0.5), np.zeros((1, 1, 2)), "whole numbers"),
    (np.array([[["a", "b"]]]), np.array([[["a", "b"]]]), "dtype"),
])
def test15_hit_agreement_rejects_what_is_not_an_index_image(reference, test, message):
    with pytest.raises(ValueError, match=message):
        hit_agreement(reference, test)


# ---- noise_judge ----


def _renders(seed: int, samples: int = 4, shape=(48, 40, 3)) -> np.ndarray:
    """A Monte Carlo render of a fixed image (a ramp): the mean of ``samples``
    exponential samples per pixel, so that independent seeds differ by noise alone."""
    mean = np.linspace(0.1, 2.0, shape[0] * shape[1] * shape[2]).reshape(shape)
    rng = np.random.default_rng(seed)
    return (mean * rng.exponential(size=(samples, *shape)).mean(axis=0)).astype(np.float32)


def test16_noise_judge_passes_other_seeds_and_fails_a_bias():
    reference, again, test = _renders(0), _renders(1), _renders(2)
    judged = noise_judge(test, reference, again)
    assert judged["passed"] and abs(judged["largest_z"]) < NOISE_LIMIT
    assert judged["fraction_identical"] == 0.0
    # A 16x16 region brighter by one render's noise (sigma): its block sum moves by
    # 256 sigma against a noise of sqrt(256 * 2 sigma^2), z about 11.
    biased = test.copy()
    biased[16:32, 16:32] += np.float32(judged["noise_rms"])
    failed = noise_judge(biased, reference, again)
    assert not failed["passed"] and failed["largest_z"] > NOISE_LIMIT
    assert failed["largest_z_block"].startswith(("16x16 at 16,16", "8x8 at"))


def test17_noise_judge_one_outlier_passes_a_nan_fails():
    reference = _renders(0)
    quiet = reference.copy()  # a native pair that agrees to the bit: no noise at all
    outlier = reference.copy()
    outlier[5, 5, 1] += 1000.0  # a firefly on a parted path
    assert noise_judge(outlier, reference, quiet)["passed"]
    rounding = reference * np.float32(1 + 2e-7)  # last bits, one way everywhere
    assert noise_judge(rounding, reference, quiet)["passed"]
    nan = reference.copy()
    nan[3, 4, 0] = np.nan
    judged = noise_judge(nan, reference, _renders(1))
    assert not judged["passed"] and judged["nonfinite_pixels"] == 1
    assert noise_judge(reference.copy(), reference)["passed"]  # bit-identical: no noise needed
    with pytest.raises(ValueError, match="reference_again"):
        noise_judge(outlier, reference)
