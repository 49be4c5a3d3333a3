"""Tests for torch_rbpt.images: sRGB transfer functions and image I/O."""

import numpy as np
import OpenImageIO as oiio
import pytest
import torch

from torch_rbpt.images import (
    ImageError,
    linear_to_srgb,
    read_image,
    srgb_to_linear,
    write_image,
)


def exact_srgb_to_linear(x):
    """IEC 61966-2-1 decoding in float64 (Mitsuba 3.9.1's mi.Bitmap conversion of 8-bit
    and 16-bit PNG/JPEG agrees with it to 4e-7)."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def write_raw(path, pixels: np.ndarray, type_name: str, alpha_channel: int = -1):
    """Write integer pixels (H, W, C) with OpenImageIO directly, bypassing write_image."""
    h, w, c = pixels.shape
    spec = oiio.ImageSpec(w, h, c, type_name)
    spec.alpha_channel = alpha_channel
    spec.attribute("oiio:UnassociatedAlpha", 1)  # PNG stores unassociated alpha as given
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(pixels)
    out.close()


# ---------------------------------------------------------------------------------------
# sRGB
# ---------------------------------------------------------------------------------------


def test_srgb_functions_are_inverse():
    x = torch.linspace(0, 1, 10001, dtype=torch.float64)
    assert torch.allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-12)
    assert torch.allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    x32 = x.float()
    assert torch.allclose(linear_to_srgb(srgb_to_linear(x32)), x32, atol=1e-6)


def test_srgb_known_values_and_pieces():
    x = torch.tensor([0.0, 0.04, 0.04045, 0.5, 1.0, 2.0], dtype=torch.float64)
    assert np.allclose(srgb_to_linear(x).numpy(), exact_srgb_to_linear(x.numpy()), rtol=0,
                       atol=1e-15)
    assert srgb_to_linear(torch.tensor(0.5, dtype=torch.float64)).item() == pytest.approx(
        0.21404114048223255, abs=1e-15)
    assert srgb_to_linear(torch.tensor(0.04, dtype=torch.float64)).item() == pytest.approx(
        0.04 / 12.92, abs=1e-15)
    assert linear_to_srgb(torch.tensor(0.002, dtype=torch.float64)).item() == pytest.approx(
        0.002 * 12.92, abs=1e-15)
    assert linear_to_srgb(torch.tensor(0.18, dtype=torch.float64)).item() == pytest.approx(
        1.055 * 0.18 ** (1 / 2.4) - 0.055, abs=1e-15)
    # Linear segment extends to negatives, no clamping above 1.
    assert srgb_to_linear(torch.tensor(-0.1, dtype=torch.float64)).item() == pytest.approx(
        -0.1 / 12.92)
    assert linear_to_srgb(torch.tensor(4.0, dtype=torch.float64)).item() > 1.0


def test_srgb_keeps_shape_dtype_and_gradients_finite():
    x = torch.tensor([[-0.5, 0.0, 0.001], [0.02, 0.5, 1.5]], requires_grad=True)
    for f in (srgb_to_linear, linear_to_srgb):
        y = f(x)
        assert y.shape == x.shape and y.dtype == torch.float32
        (grad,) = torch.autograd.grad(y.sum(), x)
        assert torch.all(torch.isfinite(grad)) and torch.all(grad > 0)


def test_srgb_rejects_non_float():
    with pytest.raises(TypeError):
        srgb_to_linear(torch.tensor([1, 2]))
    with pytest.raises(TypeError):
        linear_to_srgb(np.zeros(3))


# ---------------------------------------------------------------------------------------
# EXR
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(5, 7, 3), (4, 6, 1), (3, 8, 4)])
def test_exr_round_trip_is_exact(tmp_path, shape):
    rng = np.random.default_rng(1)
    image = (rng.standard_normal(shape) * 10).astype(np.float32)
    image.flat[0] = 1e-30
    image.flat[1] = 65504.0 * 3
    path = tmp_path / "img.exr"
    write_image(path, torch.from_numpy(image))
    back = read_image(path)
    assert isinstance(back, torch.Tensor) and back.dtype == torch.float32
    assert back.shape == shape
    assert np.array_equal(back.numpy(), image)


def test_exr_accepts_numpy_and_2d(tmp_path):
    image = np.arange(12, dtype=np.float64).reshape(3, 4) / 7
    write_image(tmp_path / "gray.exr", image)
    back = read_image(tmp_path / "gray.exr")
    assert back.shape == (3, 4, 1)
    assert np.array_equal(back.numpy()[:, :, 0], image.astype(np.float32))


def test_exr_half_option(tmp_path):
    image = np.array([[[0.1, 1 / 3, 1000.123]]], dtype=np.float32)
    write_image(tmp_path / "h.exr", image, half=True)
    back = read_image(tmp_path / "h.exr").numpy()
    assert np.array_equal(back, image.astype(np.float16).astype(np.float32))
    assert not np.array_equal(back, image)


def test_exr_values_are_not_srgb_decoded(tmp_path):
    image = np.full((2, 2, 3), 0.5, dtype=np.float32)
    write_image(tmp_path / "lin.exr", image)
    assert np.array_equal(read_image(tmp_path / "lin.exr").numpy(), image)
    assert np.array_equal(read_image(tmp_path / "lin.exr", raw=True).numpy(), image)


def test_write_accepts_tensor_requiring_grad(tmp_path):
    image = torch.rand(3, 3, 3, requires_grad=True)
    write_image(tmp_path / "g.exr", image)
    assert torch.equal(read_image(tmp_path / "g.exr"), image.detach())


# ---------------------------------------------------------------------------------------
# PNG / JPEG
# ---------------------------------------------------------------------------------------


def test_png_round_trip_within_one_code(tmp_path):
    rng = np.random.default_rng(2)
    image = rng.random((16, 16, 3)).astype(np.float32) ** 2.2
    write_image(tmp_path / "img.png", image)
    back = read_image(tmp_path / "img.png")
    assert back.shape == (16, 16, 3) and back.dtype == torch.float32
    want = linear_to_srgb(torch.from_numpy(image).double())
    got = linear_to_srgb(back.double())
    assert torch.max(torch.abs(want - got)).item() <= 0.5 / 255 + 1e-6


def test_png_clamps_and_rounds(tmp_path):
    codes = np.arange(256, dtype=np.float64) / 255
    image = exact_srgb_to_linear(codes).reshape(1, 256, 1)
    image = np.concatenate([image, np.full((1, 256, 1), 7.0), np.full((1, 256, 1), -3.0)],
                           axis=2)
    write_image(tmp_path / "codes.png", image)
    raw = read_image(tmp_path / "codes.png", raw=True).numpy()
    assert np.array_equal(np.round(raw[0, :, 0] * 255), np.arange(256))  # exact codes
    assert np.all(raw[:, :, 1] == 1.0) and np.all(raw[:, :, 2] == 0.0)


def test_png_8bit_is_srgb_decoded(tmp_path):
    codes = np.arange(256, dtype=np.uint8).reshape(1, 256, 1).repeat(3, axis=2)
    write_raw(tmp_path / "ramp.png", codes, "uint8")
    linear = read_image(tmp_path / "ramp.png").numpy()
    assert np.allclose(linear, exact_srgb_to_linear(codes / 255.0), rtol=0, atol=1e-7)
    assert linear[0, 128, 0] == pytest.approx(0.2158605, abs=1e-6)
    raw = read_image(tmp_path / "ramp.png", raw=True).numpy()
    assert np.allclose(raw, codes / 255.0, rtol=0, atol=1e-7)


def test_png_16bit_is_srgb_decoded(tmp_path):
    codes = (np.arange(64, dtype=np.uint16) * 1040).reshape(1, 64, 1).repeat(3, axis=2)
    write_raw(tmp_path / "ramp16.png", codes, "uint16")
    linear = read_image(tmp_path / "ramp16.png").numpy()
    assert np.allclose(linear, exact_srgb_to_linear(codes / 65535.0), rtol=0, atol=1e-7)


def test_grayscale_png_has_one_channel(tmp_path):
    gray = np.arange(20, dtype=np.uint8).reshape(4, 5, 1) * 10
    write_raw(tmp_path / "gray.png", gray, "uint8")
    image = read_image(tmp_path / "gray.png")
    assert image.shape == (4, 5, 1)
    assert np.allclose(image.numpy(), exact_srgb_to_linear(gray / 255.0), atol=1e-7)


def test_rgba_png_alpha_is_linear_and_not_premultiplied(tmp_path):
    pixels = np.array([[[255, 128, 0, 69], [10, 20, 30, 255]]], dtype=np.uint8)
    write_raw(tmp_path / "rgba.png", pixels, "uint8", alpha_channel=3)
    image = read_image(tmp_path / "rgba.png").numpy()
    assert image.shape == (1, 2, 4)
    assert np.allclose(image[..., :3], exact_srgb_to_linear(pixels[..., :3] / 255.0),
                       atol=1e-7)
    assert np.allclose(image[..., 3], pixels[..., 3] / 255.0, atol=1e-7)
    # And write_image leaves alpha unencoded too.
    write_image(tmp_path / "again.png", image)
    raw = read_image(tmp_path / "again.png", raw=True).numpy()
    assert np.array_equal(np.round(raw * 255), pixels.astype(np.float32))


def test_jpeg_round_trip_is_close(tmp_path):
    image = np.full((16, 16, 3), 0.2, dtype=np.float32)
    image[:, :, 1] = 0.05
    write_image(tmp_path / "img.jpg", image)
    back = read_image(tmp_path / "img.jpg").numpy()
    assert back.shape == (16, 16, 3)
    got = linear_to_srgb(torch.from_numpy(back).double()).numpy()
    want = linear_to_srgb(torch.from_numpy(image).double()).numpy()
    assert np.abs(got - want).max() < 3 / 255


# ---------------------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------------------


def test_missing_file(tmp_path):
    with pytest.raises(ImageError, match=r"nothing\.exr: image file not found"):
        read_image(tmp_path / "nothing.exr")


def test_unsupported_extensions(tmp_path):
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(ImageError, match=r"notes\.txt: unsupported image extension '\.txt'"):
        read_image(tmp_path / "notes.txt")
    with pytest.raises(ImageError, match=r"out\.gif: unsupported image extension"):
        write_image(tmp_path / "out.gif", np.zeros((2, 2, 3)))


@pytest.mark.parametrize("shape", [(4, 4, 2), (4, 4, 3, 1), (4,), (0, 4, 3)])
def test_wrong_shapes_name_path_and_expected_shape(tmp_path, shape):
    with pytest.raises(ImageError, match=r"bad\.exr: expected an image of shape \(H, W, 3\)"):
        write_image(tmp_path / "bad.exr", np.zeros(shape, dtype=np.float32))


def test_other_bad_inputs(tmp_path):
    with pytest.raises(ImageError, match=r"x\.png: expected a torch\.Tensor or numpy array"):
        write_image(tmp_path / "x.png", [[0.0, 1.0]])
    with pytest.raises(ImageError, match=r"x\.jpg: JPEG cannot store alpha"):
        write_image(tmp_path / "x.jpg", np.zeros((2, 2, 4)))
    with pytest.raises(ImageError, match=r"missing_dir.*x\.exr"):
        write_image(tmp_path / "missing_dir" / "x.exr", np.zeros((2, 2, 3)))
    (tmp_path / "fake.png").write_bytes(b"not a png at all")
    with pytest.raises(ImageError, match=r"fake\.png: cannot open image"):
        read_image(tmp_path / "fake.png")
    assert issubclass(ImageError, ValueError)


# Found by fuzz/fuzz_image.py: an EXR header whose channel name is not UTF-8 made
# OpenImageIO's binding raise UnicodeDecodeError, which did not name the file.
FUZZ_EXR_BAD_UTF8 = (
    "di8xAQIAAABjYXBEYXRlAHN0cmluZwATAAAAMjAyNjoxMToyMiAxMToyOTowOWNoYW5uZWxzAGNobGm/dAA3AAAA"
    "QgACAAAAAAAAAAEAAAABAAAARwACAAAAAAAAAAEAAAABAAAAUgACAAAIAAAAAAAAAAAAAAAAAQAAAFIAAgAAAAAA"
    "AAABAAAAAQAAAABjb21wcmVzc2lvbgBjb21wcmVzc2lvbgABAAAAA2RhdGFXaW5kb3cAYm94NGkAAAA/AAAAAJqZ"
    "mT4AAAAAZmZmPwAAgD/NzMw9")


def test_fuzzed_exr_with_non_utf8_header_is_an_image_error(tmp_path):
    import base64
    path = tmp_path / "bad.exr"
    path.write_bytes(base64.b64decode(FUZZ_EXR_BAD_UTF8))
    with pytest.raises(ImageError, match=r"bad\.exr: cannot open image"):
        read_image(path)
