"""Image input/output through OpenImageIO, with Mitsuba 3's sRGB conventions.

* 8-bit and 16-bit (integer) images -- PNG, JPEG, ... -- hold sRGB-encoded values: they are
  decoded to linear on read (color channels only, alpha stays as stored) unless
  ``raw=True``, and encoded on write. Mitsuba's decoding is the exact piecewise IEC
  61966-2-1 curve (checked against ``mi.Bitmap.convert`` in Mitsuba 3.9.1).
* Floating-point images (EXR, HDR, PFM, float TIFF) hold linear values and are returned
  and written as they are.
"""

from __future__ import annotations

from pathlib import Path
from typing import Union

import numpy as np
import torch

__all__ = [
    "ImageError",
    "srgb_to_linear",
    "linear_to_srgb",
    "read_image",
    "write_image",
    "READ_EXTENSIONS",
    "WRITE_EXTENSIONS",
]

#: File extensions :func:`read_image` accepts (lower case, with the dot).
READ_EXTENSIONS = (".exr", ".hdr", ".pfm", ".png", ".jpg", ".jpeg", ".bmp", ".tga", ".tif",
                   ".tiff")
#: Extensions :func:`write_image` writes as linear float data.
FLOAT_WRITE_EXTENSIONS = (".exr", ".hdr", ".pfm")
#: Extensions :func:`write_image` writes as 8-bit sRGB data.
LDR_WRITE_EXTENSIONS = (".png", ".jpg", ".jpeg")
#: File extensions :func:`write_image` accepts.
WRITE_EXTENSIONS = FLOAT_WRITE_EXTENSIONS + LDR_WRITE_EXTENSIONS

ArrayLike = Union[torch.Tensor, np.ndarray]


class ImageError(ValueError):
    """An image could not be read or written; the message names the path."""


# ---------------------------------------------------------------------------------------
# sRGB transfer function
# ---------------------------------------------------------------------------------------


def _check_float_tensor(x, name: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if not torch.is_floating_point(x):
        raise TypeError(f"{name}: expected a floating-point tensor, got {x.dtype}")
    return x


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    """Decode sRGB values to linear (IEC 61966-2-1), elementwise.

    ``x / 12.92`` for ``x <= 0.04045``, else ``((x + 0.055) / 1.055) ** 2.4``. Values
    outside [0, 1] follow the same two pieces (no clamping). Differentiable.

    Args:
        x: floating-point tensor of any shape.

    Returns:
        Tensor of the same shape, dtype and device.
    """
    x = _check_float_tensor(x, "srgb_to_linear")
    low = x / 12.92
    high = ((torch.clamp(x, min=0.04045) + 0.055) / 1.055) ** 2.4
    return torch.where(x <= 0.04045, low, high)


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """Encode linear values as sRGB (IEC 61966-2-1), elementwise; inverse of
    :func:`srgb_to_linear`.

    ``12.92 * x`` for ``x <= 0.0031308``, else ``1.055 * x ** (1 / 2.4) - 0.055``. No
    clamping. Differentiable.

    Args:
        x: floating-point tensor of any shape.

    Returns:
        Tensor of the same shape, dtype and device.
    """
    x = _check_float_tensor(x, "linear_to_srgb")
    low = x * 12.92
    high = 1.055 * torch.clamp(x, min=0.0031308) ** (1.0 / 2.4) - 0.055
    return torch.where(x <= 0.0031308, low, high)


# ---------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------


def _oiio():
    import OpenImageIO as oiio  # imported lazily: only image I/O needs it

    return oiio


def read_image(path, raw: bool = False) -> torch.Tensor:
    """Read an image file into a linear float32 tensor.

    Integer-valued files (8/16-bit PNG, JPEG, ...) are scaled to [0, 1] and, unless
    ``raw`` is True, sRGB-decoded to linear (all channels but alpha). Float files (EXR,
    HDR, PFM) are returned as stored. Color is not premultiplied by alpha (PNG stores
    unassociated alpha; Mitsuba keeps it so). The first subimage, all its channels, in
    the file's channel order (OpenImageIO orders EXR channels R, G, B, A).

    Args:
        path: str or Path; extension one of :data:`READ_EXTENSIONS`.
        raw: skip the sRGB decoding of integer files (e.g. for normal or roughness maps).

    Returns:
        float32 tensor of shape (H, W, C), C = number of channels in the file (1 for a
        grayscale PNG, 3 for RGB, 4 with alpha).

    Raises:
        ImageError: missing file, unsupported extension, or a file OpenImageIO cannot read.
    """
    path = Path(path)
    if path.suffix.lower() not in READ_EXTENSIONS:
        raise ImageError(f"{path}: unsupported image extension {path.suffix!r}, expected one "
                         f"of {', '.join(READ_EXTENSIONS)}")
    if not path.is_file():
        raise ImageError(f"{path}: image file not found")
    oiio = _oiio()
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # keep color as stored, as Mitsuba does
    try:
        inp = oiio.ImageInput.open(str(path), config)
        if inp is None:
            raise ImageError(f"{path}: cannot open image ({oiio.geterror()})")
    except UnicodeDecodeError as e:  # the binding decodes header strings and errors as UTF-8
        raise ImageError(f"{path}: cannot open image (a header string is not UTF-8: {e})") from None
    try:
        spec = inp.spec()
        integer = _is_integer_format(oiio, spec.format)
        pixels = inp.read_image(0, 0, 0, spec.nchannels,
                                oiio.UNKNOWN if integer else "float")
        if pixels is None:
            raise ImageError(f"{path}: cannot read pixels ({inp.geterror()})")
    finally:
        inp.close()
    image = np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels)
    if integer:
        image = _normalize_integers(image)
    if integer and not raw:
        image = _decode_color_channels(image, spec.alpha_channel)
    return torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32))


def _is_integer_format(oiio, type_desc) -> bool:
    """True if an OpenImageIO TypeDesc stores integers (then sRGB-encoded data).

    Compares enum values: this binding has distinct members for aliases (UCHAR, UINT8).
    """
    names = ("UINT8", "INT8", "UINT16", "INT16", "UINT32", "INT32", "UINT64", "INT64")
    integer_values = {getattr(oiio.BASETYPE, name).value for name in names}
    return type_desc.basetype.value in integer_values


def _normalize_integers(codes: np.ndarray) -> np.ndarray:
    """Integer codes -> float64 in [0, 1] (unsigned: code / max; signed: code / max,
    clamped at 0), computed in float64 so that later decoding rounds only once."""
    info = np.iinfo(codes.dtype)
    return np.maximum(codes.astype(np.float64) / info.max, 0.0)


def _decode_color_channels(image: np.ndarray, alpha_channel: int) -> np.ndarray:
    """sRGB-decode every channel of (H, W, C) float64 ``image`` except ``alpha_channel``."""
    decoded = srgb_to_linear(torch.from_numpy(image.astype(np.float64))).numpy()
    if 0 <= alpha_channel < image.shape[2]:
        decoded[:, :, alpha_channel] = image[:, :, alpha_channel]
    return decoded


# ---------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------


def _to_hwc_numpy(path: Path, image: ArrayLike) -> np.ndarray:
    """Validate and convert to a float64 (H, W, C) array with C in {1, 3, 4}."""
    if isinstance(image, torch.Tensor):
        array = image.detach().cpu().to(torch.float64).numpy()
    elif isinstance(image, np.ndarray):
        if not (np.issubdtype(image.dtype, np.floating) or np.issubdtype(image.dtype,
                                                                         np.integer)):
            raise ImageError(f"{path}: expected a numeric image, got dtype {image.dtype}")
        array = image.astype(np.float64)
    else:
        raise ImageError(f"{path}: expected a torch.Tensor or numpy array of shape (H, W, 3), "
                         f"(H, W, 4), (H, W, 1) or (H, W), got {type(image).__name__}")
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[2] not in (1, 3, 4) or 0 in array.shape[:2]:
        raise ImageError(f"{path}: expected an image of shape (H, W, 3), (H, W, 4), (H, W, 1) "
                         f"or (H, W) with H, W > 0, got {tuple(array.shape)}")
    return array


_CHANNEL_NAMES = {1: ["Y"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}


def write_image(path, image: ArrayLike, half: bool = False, raw: bool = False,
                quality: int = 95) -> None:
    """Write an image file; the format follows the extension.

    * ``.exr``: linear float32 (``half=True``: float16), values as given; channels named
      Y, or R G B, or R G B A. ``.hdr`` / ``.pfm``: linear float as the format allows.
    * ``.png``, ``.jpg``, ``.jpeg``: sRGB-encoded (unless ``raw``; alpha never), clamped
      to [0, 1], scaled by 255 and rounded to nearest, 8 bits per channel. JPEG cannot
      store alpha: 4 channels are rejected.

    Args:
        path: str or Path; extension one of :data:`WRITE_EXTENSIONS`. Parent folder must
            exist.
        image: torch tensor or numpy array, shape (H, W, 3), (H, W, 4), (H, W, 1) or
            (H, W); linear values.
        half: write EXR as float16 instead of float32.
        raw: for 8-bit formats, store values without sRGB encoding.
        quality: JPEG quality (1..100).

    Raises:
        ImageError: unsupported extension, wrong shape or dtype, or a write failure.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in WRITE_EXTENSIONS:
        raise ImageError(f"{path}: unsupported image extension {path.suffix!r}, expected one "
                         f"of {', '.join(WRITE_EXTENSIONS)}")
    array = _to_hwc_numpy(path, image)
    height, width, channels = array.shape
    if suffix in FLOAT_WRITE_EXTENSIONS:
        pixel_type = "half" if (half and suffix == ".exr") else "float"
        pixels = array.astype(np.float32)
    else:
        if suffix in (".jpg", ".jpeg") and channels == 4:
            raise ImageError(f"{path}: JPEG cannot store alpha, expected shape (H, W, 3), "
                             f"(H, W, 1) or (H, W), got {tuple(array.shape)}")
        pixel_type = "uint8"
        pixels = _encode_ldr(array, raw)
    _write_pixels(path, pixels, pixel_type, channels, quality)


def _encode_ldr(array: np.ndarray, raw: bool) -> np.ndarray:
    """Linear float64 (H, W, C) -> uint8 sRGB codes (alpha, channel 3 of 4, not encoded)."""
    encoded = np.nan_to_num(array, nan=0.0, posinf=1.0, neginf=0.0)
    if not raw:
        color = slice(0, 3) if encoded.shape[2] == 4 else slice(None)
        encoded = encoded.copy()
        encoded[:, :, color] = linear_to_srgb(torch.from_numpy(encoded[:, :, color])).numpy()
    return np.floor(np.clip(encoded, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _write_pixels(path: Path, pixels: np.ndarray, pixel_type: str, channels: int,
                  quality: int) -> None:
    """Write (H, W, C) ``pixels`` with OpenImageIO as ``pixel_type`` data."""
    oiio = _oiio()
    height, width = pixels.shape[:2]
    spec = oiio.ImageSpec(width, height, channels, pixel_type)
    spec.channelnames = tuple(_CHANNEL_NAMES[channels])
    if channels == 4:
        spec.alpha_channel = 3
        spec.attribute("oiio:UnassociatedAlpha", 1)  # store color as given, not divided
    if path.suffix.lower() in (".jpg", ".jpeg"):
        spec.attribute("Compression", f"jpeg:{int(quality)}")
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise ImageError(f"{path}: no writer for this format ({oiio.geterror()})")
    try:
        if not out.open(str(path), spec):
            raise ImageError(f"{path}: cannot open for writing ({out.geterror()})")
        if not out.write_image(np.ascontiguousarray(pixels)):
            raise ImageError(f"{path}: write failed ({out.geterror()})")
    finally:
        out.close()
