"""``hlbvh.render.images``: EXR keeps float32 values bit for bit, PNG is 8-bit sRGB by the IEC
61966-2-1 formula, difference maps paint what differs, and every write is atomic: no
temporary file left behind, an existing file intact when a write fails."""

import math

import numpy as np
import OpenImageIO as oiio
import pytest

from hlbvh.render import images


def awkward_values(height=5, width=7, channels=3) -> np.ndarray:
    """float32 values a lossy or clamping writer would change: negatives, > 1, huge,
    tiny, subnormal, -0.0, and the non-finite ones."""
    rng = np.random.default_rng(7)
    values = (rng.standard_normal((height, width, channels)) * 50).astype(np.float32)
    flat = values.reshape(-1)
    flat[:10] = [-0.0, 1e-42, -3.0e38, 3.4e38, 1.0 + 2**-23, -1e-30, 65504.0 * 3, np.nan,
                 np.inf, -np.inf]
    return values


def file_spec(path):
    source = oiio.ImageInput.open(str(path))
    assert source is not None, f"{path} is not an image"
    spec = source.spec()
    pixels = source.read_image(oiio.UINT8 if spec.format == oiio.UINT8 else oiio.FLOAT)
    source.close()
    return spec, pixels


def no_temporary_files(directory) -> bool:
    return not [p for p in directory.iterdir() if p.name.endswith(".tmp")]


def srgb_code(linear: float) -> int:
    """The IEC 61966-2-1 encoding of one value, written out for this test."""
    linear = min(max(linear, 0.0), 1.0)
    encoded = 12.92 * linear if linear <= 0.0031308 else 1.055 * linear ** (1 / 2.4) - 0.055
    return round(encoded * 255)


# ---- EXR ----


@pytest.mark.parametrize("channels", [1, 2, 3, 4, 5, 12])
def test01_exr_round_trip_is_bit_exact(tmp_path, channels):
    image = awkward_values(channels=channels)
    path = images.write_exr(tmp_path / "frame.exr", image)
    spec, _ = file_spec(path)
    assert spec.format == oiio.FLOAT and (spec.width, spec.height) == (7, 5)
    back = images.read_exr(path)
    assert back.dtype == np.float32 and back.shape == image.shape
    # Channel order included: the default names read back in the order written.
    assert np.array_equal(back.view(np.uint32), image.view(np.uint32))
    assert no_temporary_files(tmp_path)


def test02_exr_named_channels_come_back_in_the_asked_order(tmp_path):
    image = awkward_values(channels=2)
    path = images.write_exr(tmp_path / "hits.exr", image, ["shape_index", "prim_index"])
    back = images.read_exr(path, ["shape_index", "prim_index"])
    assert np.array_equal(back.view(np.uint32), image.view(np.uint32))
    swapped = images.read_exr(path, ["prim_index", "shape_index"])
    assert np.array_equal(swapped[..., 0].view(np.uint32), image[..., 1].view(np.uint32))
    with pytest.raises(ValueError, match="depth"):
        images.read_exr(path, ["depth"])
    with pytest.raises(ValueError, match="one name per channel"):
        images.write_exr(tmp_path / "bad.exr", image, ["only_one"])
    assert not (tmp_path / "bad.exr").exists() and no_temporary_files(tmp_path)


def test03_exr_accepts_mitsuba_tensors_and_grey(tmp_path):
    import mitsuba as mi

    image = awkward_values(channels=3)
    back = images.read_exr(images.write_exr(tmp_path / "t.exr", mi.TensorXf(image)))
    assert np.array_equal(back.view(np.uint32), image.view(np.uint32))
    grey = images.read_exr(images.write_exr(tmp_path / "g.exr", image[..., 0]))
    assert grey.shape == (5, 7, 1)
    assert np.array_equal(grey[..., 0].view(np.uint32), image[..., 0].view(np.uint32))


# ---- PNG ----


def test04_png_is_8_bit_srgb_of_the_right_size(tmp_path):
    linear = [0.0, 0.001, 0.0031308, 0.01, 0.18, 0.2140, 0.5, 0.99, 1.0, 1.5, -0.5, math.nan,
              math.inf, -math.inf, 0.7353569]
    image = np.zeros((3, len(linear), 3), np.float32)
    image[0, :, 0] = linear
    image[1, :, 1] = linear[::-1]
    image[2] = np.linspace(0.0, 1.0, len(linear) * 3, dtype=np.float32).reshape(-1, 3)
    path = images.write_png(tmp_path / "frame.png", image)
    spec, pixels = file_spec(path)
    assert (spec.width, spec.height, spec.nchannels) == (len(linear), 3, 3)
    assert spec.format == oiio.UINT8
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert pixels.dtype == np.uint8
    # NaN shows black, +inf white, -inf black (the clamp), as the module promises.
    expected = [0 if math.isnan(v) else srgb_code(v) for v in linear]
    assert pixels[0, :, 0].tolist() == expected
    assert pixels[1, :, 1].tolist() == expected[::-1]
    assert pixels[0, :, 1:].max() == 0
    assert pixels[2].reshape(-1).tolist() == [srgb_code(float(v)) for v in image[2].reshape(-1)]
    assert [srgb_code(v) for v in (0.18, 0.5, 1.0)] == [118, 188, 255]  # the formula itself


def test05_png_grey_and_alpha(tmp_path):
    grey = np.array([[0.0, 0.5], [1.0, 2.0]], np.float32)
    spec, pixels = file_spec(images.write_png(tmp_path / "grey.png", grey))
    assert (spec.width, spec.height, spec.nchannels) == (2, 2, 1)
    assert pixels[..., 0].tolist() == [[0, 188], [255, 255]]
    # Alpha is stored straight and linear: 0.5 -> 128 (round(127.5)), 0.25 -> 64, 0 -> 0;
    # the colour is sRGB, whatever the alpha (read by Pillow, which does not premultiply).
    from PIL import Image

    rgba = np.full((1, 3, 4), 0.5, np.float32)
    rgba[0, 1, 3], rgba[0, 2, 3] = 0.25, 0.0
    with Image.open(images.write_png(tmp_path / "rgba.png", rgba)) as png:
        assert png.mode == "RGBA"
        assert np.asarray(png).tolist() == [[[188, 188, 188, 128], [188, 188, 188, 64],
                                             [188, 188, 188, 0]]]
    grey_alpha = np.array([[[0.5, 1.0], [1.0, 0.5]]], np.float32)
    with Image.open(images.write_png(tmp_path / "la.png", grey_alpha)) as png:
        assert png.mode == "LA" and np.asarray(png).tolist() == [[[188, 255], [255, 128]]]
    with pytest.raises(ValueError, match="1 to 4 channels"):
        images.write_png(tmp_path / "five.png", np.zeros((2, 2, 5), np.float32))


def test06_write_frame_writes_exr_and_png_of_one_frame(tmp_path):
    """hlbvh.render.output.write_frame (what a render writes per frame): every channel to the
    EXR bit for bit, R, G, B to the PNG, then the row recorded."""
    from hlbvh.render.output import write_frame

    class Renderer:
        def channel_names(self, pixels):
            return ["R", "G", "B", "depth", "prim_index"][:pixels.shape[2]]

    image = np.clip(awkward_values(channels=5), -1, 2)
    recorded = []
    (tmp_path / "out").mkdir()
    write_frame(tmp_path / "out", 3, image, Renderer(), {"frame": 3}, recorded.append)
    files = {"exr": tmp_path / "out/frame_0003.exr", "png": tmp_path / "out/frame_0003.png"}
    assert recorded == [{"frame": 3}]
    names = Renderer().channel_names(image)
    assert np.array_equal(images.read_exr(files["exr"], names).view(np.uint32),
                          image.view(np.uint32))
    spec, pixels = file_spec(files["png"])
    assert spec.nchannels == 3 and pixels.shape == (5, 7, 3)
    assert np.array_equal(pixels, images.srgb_encode(image[..., :3]))


# ---- Difference maps ----


def test07_difference_map_marks_what_differs(tmp_path):
    import matplotlib

    reference = np.zeros((3, 4, 3), np.float32)
    test = reference.copy()
    test[0, 1, 2] = 0.5     # the largest difference: top of the colormap
    test[1, 2, 0] = 0.25    # half of it
    test[2, 3, 1] = np.nan  # non-finite in one image: the flag colour
    reference[2, 0] = test[2, 0] = np.inf  # non-finite in both, bit-identical: no difference
    _, pixels = file_spec(images.write_difference_map(tmp_path / "diff.png", reference, test))
    colormap = matplotlib.colormaps["inferno"]

    def colour(value):
        return [round(c * 255) for c in colormap(value)[:3]]

    assert pixels.shape == (3, 4, 3)
    assert pixels[0, 1].tolist() == colour(1.0)
    assert pixels[1, 2].tolist() == colour(0.5)
    assert pixels[2, 3].tolist() == list(images.NONFINITE_COLOUR)
    for row, column in [(0, 0), (1, 1), (2, 0), (2, 2)]:
        assert pixels[row, column].tolist() == colour(0.0)
    # A fixed scale (several frames on one scale): 0.5 of vmax=1 is mid-colormap.
    _, scaled = file_spec(images.write_difference_map(tmp_path / "d1.png", reference, test,
                                                      vmax=1.0))
    assert scaled[0, 1].tolist() == colour(0.5)
    # Identical images: all the lowest colour.
    _, same = file_spec(images.write_difference_map(tmp_path / "d0.png", test, test))
    assert (same.reshape(-1, 3) == colour(0.0)).all()
    with pytest.raises(ValueError, match="shape"):
        images.write_difference_map(tmp_path / "d2.png", reference, test[:, :3])
    with pytest.raises(ValueError, match="vmax"):
        images.write_difference_map(tmp_path / "d3.png", reference, test, vmax=0.0)
    with pytest.raises(ValueError, match="colormap"):
        images.write_difference_map(tmp_path / "d4.png", reference, test, colormap="nope")
    # A logarithmic scale from vmin: 0.5 of vmax=5 over vmin=0.005 is 2 of 3 decades;
    # a difference at or below vmin, and none, the bottom colour.
    test[1, 1, 1] = 0.004
    _, log = file_spec(images.write_difference_map(tmp_path / "d5.png", reference, test,
                                                   vmax=5.0, vmin=0.005))
    assert log[0, 1].tolist() == colour(2 / 3) and log[1, 1].tolist() == colour(0.0)
    assert log[0, 0].tolist() == colour(0.0)
    with pytest.raises(ValueError, match="vmin"):
        images.write_difference_map(tmp_path / "d6.png", reference, test, vmax=1.0, vmin=2.0)
    assert not (tmp_path / "d2.png").exists() and no_temporary_files(tmp_path)


# ---- Atomic writes ----


class _FailingOutput:
    """An OpenImageIO writer that writes part of the file and then fails."""

    @staticmethod
    def create(format_name):
        return _FailingOutput()

    def open(self, filename, spec):
        self.filename = filename
        with open(filename, "wb") as half:
            half.write(b"half a frame")
        return True

    def write_image(self, pixels):
        raise OSError("disk full (simulated)")

    def close(self):
        return True

    def geterror(self):
        return "simulated"


class _RefusingOutput(_FailingOutput):
    """A writer whose write reports failure (returns False) instead of raising."""

    def write_image(self, pixels):
        return False


@pytest.mark.parametrize("output", [_FailingOutput, _RefusingOutput])
@pytest.mark.parametrize("writer", ["exr", "png", "diff"])
def test08_failed_write_keeps_the_existing_file(tmp_path, monkeypatch, output, writer):
    image = awkward_values()
    write = {
        "exr": lambda path: images.write_exr(path, image),
        "png": lambda path: images.write_png(path, image),
        "diff": lambda path: images.write_difference_map(path, image, image + 1),
    }[writer]
    path = write(tmp_path / f"frame.{'exr' if writer == 'exr' else 'png'}")
    before = path.read_bytes()
    monkeypatch.setattr(images.oiio, "ImageOutput", output)
    with pytest.raises(OSError):
        write(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary file


def test09_failed_first_write_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(images.oiio, "ImageOutput", _FailingOutput)
    with pytest.raises(OSError, match="disk full"):
        images.write_exr(tmp_path / "new" / "frame.exr", awkward_values())
    assert list((tmp_path / "new").iterdir()) == []


def test10_atomic_output_replaces_whole_or_not_at_all(tmp_path):
    path = tmp_path / "stats.json"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with images.atomic_output(path) as temporary:
            assert temporary.parent == tmp_path and temporary.name.endswith(".tmp")
            temporary.write_text("new but half")
            raise RuntimeError("interrupted")
    assert path.read_text() == "old" and no_temporary_files(tmp_path)
    with pytest.raises(OSError, match="nothing was written"):
        with images.atomic_output(path):
            pass
    assert path.read_text() == "old" and no_temporary_files(tmp_path)
    with images.atomic_output(path) as temporary:
        temporary.write_text("new")
        assert path.read_text() == "old"  # not visible before the body returns
    assert path.read_text() == "new" and no_temporary_files(tmp_path)
    # An invalid image never reaches the file system.
    with pytest.raises(ValueError, match="shape"):
        images.write_png(path.with_suffix(".png"), np.zeros((2, 2, 2, 2), np.float32))
    with pytest.raises(TypeError, match="numeric"):
        images.write_exr(path.with_suffix(".exr"), np.array([["a"]]))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stats.json"]
