"""Image files of rendered frames: linear EXR, tonemapped PNG, false-colour difference
maps, all written through OpenImageIO and atomically.

A rendered image is an ``mi.TensorXf`` or a numpy array of shape ``(H, W, C)`` (or
``(H, W)`` for one channel); :func:`as_image` turns either into a float32 numpy array of
shape ``(H, W, C)``. Every writer goes through :func:`atomic_output`: the file is written
under a temporary name in its own directory, flushed to disk and then renamed over the
destination with ``os.replace``, so a reader (or a resumed render) never sees a
half-written frame, and a failed write leaves the previous file untouched.

Conventions:

- EXR holds the linear float32 values bit for bit, non-finite values included;
  :func:`read_exr` gives them back.
- PNG holds 8-bit sRGB: colour channels clamped to [0, 1], encoded with the sRGB
  transfer function (IEC 61966-2-1) and rounded; an alpha channel (the 2nd of 2 or the
  4th of 4) is clamped and stored linearly. NaN becomes 0, +inf becomes 1.
- The difference map shows, per pixel, the largest absolute difference over the
  channels, scaled into a matplotlib colormap linearly up to ``vmax`` or
  logarithmically from ``vmin`` to ``vmax``; pixels where either image is non-finite
  (and the two are not bit-identical) are painted in one flag colour.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

#: Colour (8-bit RGB) of difference-map pixels that are non-finite in either image.
NONFINITE_COLOUR = (0, 255, 255)

_PNG_CHANNELS = {1: "grey", 2: "grey + alpha", 3: "RGB", 4: "RGBA"}


def as_image(image, name: str = "image") -> np.ndarray:
    """The image as a float32 numpy array of shape ``(H, W, C)``.

    Args:
        image: ``mi.TensorXf``, ``mi.Bitmap`` or anything ``numpy.asarray`` accepts, of
            shape ``(H, W)`` or ``(H, W, C)`` with a numeric dtype. float64 and integer
            values are converted to float32.
        name: how error messages call the image.

    Raises:
        TypeError: the values are not numbers.
        ValueError: the shape is not ``(H, W)`` or ``(H, W, C)`` with H, W, C > 0.
    """
    array = np.asarray(image)
    if array.dtype.kind not in "fiub":
        raise TypeError(f"{name}: expected numeric pixel values, got dtype {array.dtype}")
    if array.ndim == 2:
        array = array[:, :, np.newaxis]
    if array.ndim != 3 or 0 in array.shape:
        raise ValueError(
            f"{name}: expected an image of shape (H, W) or (H, W, C) with no empty axis, "
            f"got shape {array.shape}"
        )
    return np.ascontiguousarray(array, dtype=np.float32)


@contextlib.contextmanager
def atomic_output(path) -> Iterator[Path]:
    """Write a file whole or not at all.

    Yields a temporary path next to ``path`` (same directory, hidden name ending in
    ``.tmp``, so globs for ``*.exr`` or ``*.png`` never match it). When the ``with`` body
    returns, the temporary file is flushed to disk and renamed over ``path``; when the
    body raises, the temporary file is removed and ``path`` keeps its previous content.
    The parent directory is created if needed.

    Example::

        with atomic_output("frame_0001.json") as tmp:
            tmp.write_text(text)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        yield temporary
        if not temporary.exists():
            raise OSError(f"{path}: nothing was written to the temporary file {temporary}")
        with open(temporary, "rb") as written:
            os.fsync(written.fileno())
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    _fsync_directory(path.parent)


def write_exr(path, image, channel_names: Sequence[str] | None = None) -> Path:
    """Write the image as a linear float32 OpenEXR file, atomically.

    Args:
        path: destination, conventionally ending in ``.exr``.
        image: ``(H, W)`` or ``(H, W, C)`` values (see :func:`as_image`), stored bit for
            bit.
        channel_names: one name per channel. The default (:func:`default_channel_names`)
            reads back in the order written; EXR stores channels sorted by name, so with
            other names pass the same names to :func:`read_exr` to get this order back.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    pixels = as_image(image)
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], oiio.FLOAT)
    if channel_names is None:
        channel_names = default_channel_names(pixels.shape[2])
    if len(channel_names) != pixels.shape[2]:
        raise ValueError(
            f"channel_names: {len(channel_names)} names for an image of "
            f"{pixels.shape[2]} channels; give one name per channel"
        )
    spec.channelnames = tuple(channel_names)
    return _write_with_oiio(Path(path), "openexr", spec, pixels)


def default_channel_names(channels: int) -> list[str]:
    """EXR channel names for an image of ``channels`` channels that OpenImageIO reads
    back in the same order: ``Y``; ``R, G``; ``R, G, B``; ``R, G, B, A``; beyond four,
    ``R, G, B, A`` then ``channel04, channel05, ...`` (zero-padded, because the file
    keeps its channels sorted by name and readers list R, G, B, A first, then the rest
    in that sorted order)."""
    if channels <= 4:
        return ["Y"] if channels == 1 else ["R", "G", "B", "A"][:channels]
    digits = len(str(channels - 1))
    return ["R", "G", "B", "A"] + [f"channel{k:0{digits}d}" for k in range(4, channels)]


def write_png(path, image) -> Path:
    """Write the image as an 8-bit sRGB PNG, atomically (tonemapping in the module
    docstring).

    Args:
        path: destination, conventionally ending in ``.png``.
        image: ``(H, W)`` or ``(H, W, C)`` linear values with C in 1..4 (grey, grey +
            alpha, RGB, RGBA).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    pixels = as_image(image)
    channels = pixels.shape[2]
    if channels not in _PNG_CHANNELS:
        raise ValueError(
            f"image: a PNG holds 1 to 4 channels, this image has {channels}; pass the "
            "colour channels (e.g. image[..., :3]) or write it with write_exr"
        )
    encoded = srgb_encode(pixels)
    if channels in (2, 4):
        alpha = np.nan_to_num(pixels[..., -1], nan=0.0, posinf=1.0, neginf=0.0)
        encoded[..., -1] = np.round(np.clip(alpha, 0.0, 1.0) * 255.0).astype(np.uint8)
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], channels, oiio.UINT8)
    if channels in (2, 4):
        # PNG stores straight (unassociated) alpha, as the codes above are; without this
        # OpenImageIO divides the colour by alpha, taking it for premultiplied.
        spec.alpha_channel = channels - 1
        spec.attribute("oiio:UnassociatedAlpha", 1)
    return _write_with_oiio(Path(path), "png", spec, encoded)


def read_exr(path, channel_names: Sequence[str] | None = None) -> np.ndarray:
    """Read an EXR (or any float image OpenImageIO reads) into numpy.

    Args:
        path: the file.
        channel_names: if given, return exactly these channels in this order (EXR files
            store channels sorted by name); otherwise the file's order.

    Returns:
        float32 array of shape ``(H, W, C)``.
    """
    path = Path(path)
    source = oiio.ImageInput.open(str(path))
    if source is None:
        raise OSError(f"{path}: cannot open as an image: {oiio.geterror()}")
    try:
        pixels = source.read_image(oiio.FLOAT)
        spec = source.spec()
        if pixels is None:
            raise OSError(f"{path}: cannot read its pixels: {source.geterror()}")
    finally:
        source.close()
    stored = list(spec.channelnames)
    pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, len(stored))
    if channel_names is None:
        return pixels
    missing = [channel for channel in channel_names if channel not in stored]
    if missing:
        raise ValueError(f"{path}: no channel(s) {missing}; the file has {stored}")
    return pixels[..., [stored.index(channel) for channel in channel_names]]


def srgb_encode(image) -> np.ndarray:
    """Linear values -> 8-bit sRGB codes, per channel (clamp to [0, 1], the sRGB
    transfer function, round). NaN maps to 0, +inf to 255.

    Returns:
        uint8 array of the input's ``(H, W, C)`` shape.
    """
    linear = np.nan_to_num(as_image(image).astype(np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    linear = np.clip(linear, 0.0, 1.0)
    # In float64, so the rounding matches the transfer function's exact value.
    encoded = np.where(
        linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1.0 / 2.4) - 0.055
    )
    return np.round(encoded * 255.0).astype(np.uint8)


def write_difference_map(
    path, reference, test, vmax: float | None = None, colormap: str = "inferno",
    vmin: float | None = None,
) -> Path:
    """Write a false-colour PNG of where and how much two images differ.

    Args:
        path: destination PNG.
        reference, test: images of equal shape (see :func:`as_image`).
        vmax: the difference shown at the top of the colormap; defaults to the largest
            finite per-pixel difference (which is ``max_abs_diff`` of
            :func:`hlbvh.comparison.metrics.image_metrics`), or 1 when the images agree.
        colormap: a matplotlib colormap name.
        vmin: ``None`` for a linear scale from 0 to ``vmax``; a positive number below
            ``vmax`` for a logarithmic one, ``vmin`` (and below) at the bottom of the
            colormap: differences many decades under the largest stay visible.

    Returns:
        ``path`` as a :class:`~pathlib.Path`. Bit-identical pixels get the colormap's
        lowest colour; pixels non-finite in either image, unless bit-identical, get
        :data:`NONFINITE_COLOUR`.
    """
    import matplotlib

    reference = as_image(reference, "reference")
    test = as_image(test, "test")
    if reference.shape != test.shape:
        raise ValueError(
            f"reference has shape {reference.shape} but test has {test.shape}; "
            "compare images rendered at the same resolution and channel count"
        )
    identical = np.all(reference.view(np.uint32) == test.view(np.uint32), axis=2)
    finite = np.all(np.isfinite(reference) & np.isfinite(test), axis=2)
    with np.errstate(invalid="ignore"):  # inf - inf: such pixels are set below
        difference = np.max(
            np.abs(test.astype(np.float64) - reference.astype(np.float64)), axis=2
        )
    difference[identical] = 0.0
    flagged = ~finite & ~identical
    difference[flagged] = 0.0
    if vmax is None:
        vmax = float(difference.max()) or 1.0
    if not np.isfinite(vmax) or vmax <= 0.0:
        raise ValueError(f"vmax={vmax!r}: expected a finite positive number")
    if colormap not in matplotlib.colormaps:
        raise ValueError(f"colormap={colormap!r}: not a matplotlib colormap (e.g. 'inferno')")
    if vmin is None:
        position = difference / vmax
    elif np.isfinite(vmin) and 0.0 < vmin < vmax:
        with np.errstate(divide="ignore"):  # log(0): clipped to the bottom below
            position = np.log(difference / vmin) / np.log(vmax / vmin)
    else:
        raise ValueError(f"vmin={vmin!r}: expected None or a number in (0, vmax={vmax!r})")
    colours = matplotlib.colormaps[colormap](np.clip(position, 0.0, 1.0))
    rgb = np.round(colours[..., :3] * 255.0).astype(np.uint8)
    rgb[flagged] = NONFINITE_COLOUR
    spec = oiio.ImageSpec(rgb.shape[1], rgb.shape[0], 3, oiio.UINT8)
    return _write_with_oiio(Path(path), "png", spec, rgb)


def _write_with_oiio(path: Path, format_name: str, spec, pixels: np.ndarray) -> Path:
    """Write ``pixels`` (matching ``spec``) to ``path`` in the named OpenImageIO format,
    through :func:`atomic_output`."""
    with atomic_output(path) as temporary:
        output = oiio.ImageOutput.create(format_name)
        if output is None:
            raise OSError(f"OpenImageIO has no {format_name} writer: {oiio.geterror()}")
        if not output.open(str(temporary), spec):
            raise OSError(f"{path}: cannot open for writing: {output.geterror()}")
        written = output.write_image(pixels)
        closed = output.close()
        if not (written and closed):
            raise OSError(f"{path}: writing the {format_name} failed: {output.geterror()}")
        # A full disk can cut the file short while the writer reports success: only a
        # file that decodes whole, at its size and channels, is renamed into place.
        check_image(temporary, spec.width, spec.height, spec.nchannels, name=path)
    return path


def check_image(path, width: int | None = None, height: int | None = None,
                channels: int | None = None, name=None) -> tuple[int, int, int]:
    """Decode every pixel of an image file and check its size and channel count.

    Args:
        path: the file (EXR, PNG, anything OpenImageIO reads).
        width, height, channels: what the file must hold; ``None`` accepts any.
        name: how the message calls the file (default ``path``).
    Returns:
        ``(width, height, channels)`` of the file.
    Raises:
        OSError: the file cannot be opened, does not decode whole (a truncated or
            corrupt file), or holds another size or channel count; the message names it.
    """
    name = path if name is None else name
    source = oiio.ImageInput.open(str(path))
    if source is None:
        raise OSError(f"{name}: not a readable image ({_first_line(oiio.geterror()) or 'unknown format'})")
    try:
        spec = source.spec()
        pixels = source.read_image(oiio.FLOAT)
        error = source.geterror()
    finally:
        source.close()
    found = (spec.width, spec.height, spec.nchannels)
    if pixels is None or error:
        raise OSError(f"{name}: the image does not decode whole ({_first_line(error) or 'no pixels'})")
    expected = (width, height, channels)
    if any(want is not None and want != got for want, got in zip(expected, found)):
        raise OSError(f"{name}: holds {found[0]}x{found[1]} pixels of {found[2]} channels, "
                      f"expected {width}x{height} of {channels}")
    return found


def _first_line(text: str) -> str:
    """The first non-empty line of an OpenImageIO error (they span several lines)."""
    return next((line.strip() for line in text.splitlines() if line.strip()), "")


def _fsync_directory(directory: Path) -> None:
    """Make a rename inside ``directory`` durable (a no-op where directories cannot be
    opened, e.g. on Windows)."""
    try:
        handle = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(handle)
    finally:
        os.close(handle)
