"""ficap_ros.io.image_codec: every raw encoding decoded to grey (padded rows, both byte orders, Bayer
mosaics, YUV), JPEG and PNG payloads, the pixel budget, and bad data (random or damaged) raising
only ``ImageError``."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mutations import mutated

from ficap_ros.errors import ConfigError, ImageError
from ficap_ros.io.image_codec import ENCODINGS, decode_compressed, decode_image

W, H = 64, 48
IMAGE = np.random.default_rng(1).integers(0, 256, (48, 64), dtype=np.uint8)
JPEG = cv2.imencode(".jpg", IMAGE)[1].tobytes()
PNG = cv2.imencode(".png", IMAGE)[1].tobytes()


def test_decode_image_encodings() -> None:
    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    rgb = bgr[:, :, ::-1].copy()
    bgra = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA)
    rgba = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGBA)
    for enc, arr in (("bgr8", bgr), ("rgb8", rgb), ("bgra8", bgra), ("rgba8", rgba)):
        out = decode_image(enc, H, W, arr.strides[0], arr.tobytes(), False)
        assert np.abs(out.astype(int) - grey).max() <= 1, enc
    # Padded rows (step > width) and 16-bit in both byte orders.
    padded = np.zeros((H, W + 8), np.uint8)
    padded[:, :W] = grey
    np.testing.assert_array_equal(decode_image("mono8", H, W, W + 8, padded.tobytes()), grey)
    m16 = grey.astype(np.uint16) * 257
    np.testing.assert_array_equal(decode_image("mono16", H, W, 2 * W, m16.astype("<u2").tobytes(), 0), m16)
    np.testing.assert_array_equal(decode_image("mono16", H, W, 2 * W, m16.astype(">u2").tobytes(), 1), m16)
    # Bayer RGGB of a flat colour demosaics to a flat grey close to the colour's luminance.
    bayer = np.zeros((H, W), np.uint8)
    bayer[0::2, 0::2], bayer[0::2, 1::2], bayer[1::2, 0::2], bayer[1::2, 1::2] = 200, 100, 100, 40
    out = decode_image("bayer_rggb8", H, W, W, bayer.tobytes())
    expect = 0.299 * 200 + 0.587 * 100 + 0.114 * 40
    assert abs(float(np.median(out)) - expect) < 3
    with pytest.raises(ImageError, match="encoding"):
        decode_image("32FC1", H, W, 4 * W, b"\x00" * 4 * W * H)
    with pytest.raises(ImageError, match="bytes"):
        decode_image("mono8", H, W, W, b"\x00" * 10)
    with pytest.raises(ImageError):
        decode_compressed(b"not an image")


@settings(suppress_health_check=[HealthCheck.too_slow])
@given(encoding=st.one_of(st.sampled_from(ENCODINGS), st.text(max_size=12)),
       height=st.integers(-3, 70), width=st.integers(-3, 70), step=st.integers(-3, 300),
       data=st.binary(max_size=6000), big_endian=st.booleans())
def test_decode_image_raises_only_image_error(encoding: str, height: int, width: int, step: int,
                                              data: bytes, big_endian: bool) -> None:
    try:
        img = decode_image(encoding, height, width, step, data, big_endian)
    except ImageError:
        return
    assert img.shape == (height, width)


@given(data=st.one_of(st.binary(max_size=3000), mutated(JPEG), mutated(PNG)))
def test_decode_compressed_raises_only_image_error(data: bytes) -> None:
    try:
        img = decode_compressed(data, "jpeg")
    except ImageError:
        return
    assert img.ndim == 2 and img.dtype == np.uint8


def test_the_pixel_budget_follows_ficap_max_pixels(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FICAP_MAX_PIXELS", "1000")
    with pytest.raises(ImageError, match="budget"):
        decode_image("mono8", 48, 64, 64, bytes(48 * 64))


def _bgr(seed: int = 2) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)


def _raw(encoding: str, bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the raw array of ``bgr`` in ``encoding``, the grey image a correct decoder gives)."""
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    if encoding in ("mono8", "8uc1"):
        return grey, grey
    if encoding in ("mono16", "16uc1"):
        return grey.astype(np.uint16) * 257, grey.astype(np.uint16) * 257
    if encoding in ("bgr8", "8uc3"):
        return bgr, grey
    if encoding == "rgb8":
        return bgr[..., ::-1].copy(), grey
    if encoding in ("bgra8", "8uc4"):
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA), grey
    if encoding == "rgba8":
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGBA), grey
    if encoding.endswith("16") and not encoding.startswith(("mono", "bayer")):
        eight, _ = _raw(encoding[:-2] + "8", bgr)
        return eight.astype(np.uint16) * 257, grey.astype(np.uint16) * 257
    if encoding in ("yuv422", "uyvy", "yuv422_yuy2", "yuyv"):
        # A flat colour: every Y sample is its luma, U and V its chroma (BT.601, as OpenCV).
        y = np.full((H, W), grey[0, 0], np.uint8)
        c = np.full((H, W), 128, np.uint8)
        pairs = np.stack([c, y], axis=-1) if encoding in ("yuv422", "uyvy") else np.stack([y, c], axis=-1)
        return pairs, y
    raise AssertionError(encoding)


@pytest.mark.parametrize("encoding", [e for e in ENCODINGS if not e.startswith("bayer_")])
@pytest.mark.parametrize("pad", [0, 6])
def test_every_encoding_decodes_to_its_grey_with_padded_rows(encoding: str, pad: int) -> None:
    """Each raw encoding (channels, order, depth, little-endian) to the grey OpenCV would make."""
    bgr = _bgr()
    if encoding in ("yuv422", "uyvy", "yuv422_yuy2", "yuyv"):
        bgr[:] = bgr[0, 0]
    arr, want = _raw(encoding, bgr)
    rows = arr.reshape(H, -1).view(np.uint8) if arr.dtype == np.uint16 else arr.reshape(H, -1)
    step = rows.shape[1] + pad
    data = np.full((H, step), 99, np.uint8)  # padding bytes that must be ignored
    data[:, : rows.shape[1]] = rows
    out = decode_image(encoding.upper() if pad else encoding, H, W, step, data.tobytes())
    assert out.shape == (H, W)
    # 16-bit samples stay 16 bit (``as_gray`` scales them), colour ones too.
    assert out.dtype == (np.uint16 if encoding.endswith("16") or encoding == "16uc1" else np.uint8)
    tolerance = 257 if out.dtype == np.uint16 else 1
    assert np.abs(out.astype(int) - want.astype(int)).max() <= tolerance, encoding


def test_a_last_row_without_its_padding_and_bad_sizes() -> None:
    grey = _bgr()[..., 0].copy()
    padded = np.zeros((H, W + 4), np.uint8)
    padded[:, :W] = grey
    short = padded.tobytes()[:-4]  # the last row's padding left off, as some drivers send
    np.testing.assert_array_equal(decode_image("mono8", H, W, W + 4, short), grey)
    with pytest.raises(ImageError, match="more than"):
        decode_image("mono8", H, W, W, grey.tobytes() + b"\0")
    with pytest.raises(ImageError, match="no pixels"):
        decode_image("mono8", 0, W, W, b"")
    with pytest.raises(ImageError, match="smaller than a bgr8 row"):
        decode_image("bgr8", H, W, W, bytes(3 * W * H))
    with pytest.raises(ImageError, match="not integers"):
        decode_image("mono8", "tall", W, W, grey.tobytes())
    with pytest.raises(ImageError, match="unsupported image encoding"):
        decode_image("32FC1", H, W, 4 * W, bytes(4 * W * H))
    # A numpy array is a byte buffer too (rclpy's data field is one).
    np.testing.assert_array_equal(decode_image("mono8", H, W, W, grey.reshape(-1)), grey)


def test_encoding_layouts() -> None:
    from ficap_ros.io.image_codec import encoding_layout

    assert encoding_layout("MONO8") == (1, 1) and encoding_layout("rgba16") == (4, 2)
    assert encoding_layout(" yuyv ") == (2, 1) and encoding_layout("bayer_gbrg16") == (1, 2)
    assert len(ENCODINGS) == len(set(ENCODINGS)) and "bayer_rggb8" in ENCODINGS
    with pytest.raises(ImageError):
        encoding_layout("hsv8")


def test_jpeg_and_png_decode_to_grey() -> None:
    colour = cv2.GaussianBlur(_bgr(), (5, 5), 0)
    grey = cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)
    png = cv2.imencode(".png", colour)[1].tobytes()
    out = decode_compressed(png, "png")
    assert out.dtype == np.uint8 and out.shape == (H, W)
    assert np.abs(out.astype(int) - grey).max() <= 1  # lossless, then OpenCV's own grey
    jpg = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, 95])[1]
    out = decode_compressed(jpg)  # a numpy buffer, no format given: OpenCV sniffs the codec
    assert np.abs(out.astype(int) - grey).mean() < 3
    with pytest.raises(ImageError, match="JPEG header is damaged"):
        decode_compressed(b"\xff\xd8 not a jpeg", "jpeg")
    with pytest.raises(ImageError, match="neither JPEG nor PNG"):
        decode_compressed(cv2.imencode(".bmp", grey)[1].tobytes())
    with pytest.raises(ImageError, match="empty"):
        decode_compressed(b"")


def test_the_pixel_budget_and_its_environment_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    from ficap_ros.io.image_codec import (
        DEFAULT_MAX_PIXELS,
        check_pixel_budget,
        max_pixels,
    )

    for text, budget in (("", DEFAULT_MAX_PIXELS), ("5000", 5000), (" 77 ", 77),
                         ("1e3", 1000), ("4e7", 40_000_000)):
        monkeypatch.setenv("FICAP_MAX_PIXELS", text)
        assert max_pixels() == budget, text
    for text in ("-5", "0", "lots", "inf", "nan"):  # refused in one line, never ignored
        monkeypatch.setenv("FICAP_MAX_PIXELS", text)
        with pytest.raises(ConfigError, match=f"FICAP_MAX_PIXELS='{text}' is not a number"):
            max_pixels()
    monkeypatch.delenv("FICAP_MAX_PIXELS")
    assert max_pixels() == DEFAULT_MAX_PIXELS == 40_000_000
    check_pixel_budget(100, 50, budget=5000)  # exactly the budget: taken
    with pytest.raises(ImageError, match=r"frame is 100x51 \(0.0 MP\), above the 0.0 MP budget"):
        check_pixel_budget(100, 51, "frame", budget=5000)
    png = cv2.imencode(".png", np.zeros((60, 100), np.uint8))[1].tobytes()
    monkeypatch.setenv("FICAP_MAX_PIXELS", "5999")
    with pytest.raises(ImageError, match="PNG image is 100x60 .* budget"):
        decode_compressed(png)  # checked on the size in its header, before decoding


@pytest.mark.parametrize("options", [
    [cv2.IMWRITE_JPEG_QUALITY, 1], [cv2.IMWRITE_JPEG_QUALITY, 50], [cv2.IMWRITE_JPEG_QUALITY, 100],
    [cv2.IMWRITE_JPEG_PROGRESSIVE, 1], [cv2.IMWRITE_JPEG_OPTIMIZE, 1],
    [cv2.IMWRITE_JPEG_RST_INTERVAL, 4], [cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                                         cv2.IMWRITE_JPEG_SAMPLING_FACTOR_411],
], ids=["q1", "q50", "q100", "progressive", "optimized", "restarts", "411"])
def test_every_kind_of_intact_jpeg_decodes_and_its_damage_is_found(options: list[int]) -> None:
    """No false alarm on an intact JPEG of any encoder setting (colour or grey), and 50 bytes of
    its entropy-coded data changed are found: a reason, never an image."""
    from probe_cases import flip_bytes

    from ficap_ros.io.image_codec import DamagedImageError, compressed_size

    colour = cv2.resize(_bgr(), (320, 240), interpolation=cv2.INTER_NEAREST)
    for image in (colour, cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)):
        jpeg = cv2.imencode(".jpg", image, options)[1].tobytes()
        assert compressed_size(jpeg) == ("jpeg", 320, 240)
        assert decode_compressed(jpeg).shape == (240, 320)
        found = 0
        for seed in range(5):
            try:
                decode_compressed(flip_bytes(jpeg, 50, seed))
            except DamagedImageError as err:
                assert str(err).startswith("damaged JPEG (")
                found += 1
            except ImageError:
                found += 1  # damaged beyond decoding: undecodable, also no image
        assert found == 5


def test_sizes_come_from_headers_and_bad_headers_are_one_line() -> None:
    from ficap_ros.io.image_codec import check_compressed, compressed_size

    png = cv2.imencode(".png", IMAGE)[1].tobytes()
    assert compressed_size(png) == ("png", W, H) and compressed_size(JPEG) == ("jpeg", W, H)
    assert compressed_size(np.frombuffer(JPEG, np.uint8)) == ("jpeg", W, H)
    for data, says in ((png[:20], "without its header"), (JPEG[:30], "without a frame header"),
                       (b"\xff\xd8\x00\x00\x00\x00", "no marker at byte 2"), (b"GIF89a", "neither")):
        with pytest.raises(ImageError, match=says):
            compressed_size(data)
        with pytest.raises(ImageError, match="cannot decode compressed image"):
            check_compressed(data)


# -- the simplejpeg decoder: the very pixels and verdicts of OpenCV's, or OpenCV's own -------------
def _opencv_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """``simplejpeg`` made unimportable for the rest of the test (the cv2 decoder alone)."""
    import sys

    from ficap_ros.io import image_codec

    monkeypatch.setitem(sys.modules, "simplejpeg", None)  # `import simplejpeg` raises ImportError
    image_codec._simplejpeg.cache_clear()


@pytest.fixture
def opencv_only(monkeypatch: pytest.MonkeyPatch):  # noqa: ANN201
    """The decoder without ``simplejpeg``; the module's cached import is forgotten after."""
    from ficap_ros.io import image_codec

    _opencv_only(monkeypatch)
    yield
    monkeypatch.undo()
    image_codec._simplejpeg.cache_clear()


def _with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """``jpeg`` with an APP1 Exif segment after its start of image holding one tag, Orientation."""
    tiff = (b"II*\x00" + (8).to_bytes(4, "little") + (1).to_bytes(2, "little")
            + (0x0112).to_bytes(2, "little") + (3).to_bytes(2, "little")
            + (1).to_bytes(4, "little") + orientation.to_bytes(2, "little") + b"\x00\x00"
            + (0).to_bytes(4, "little"))
    payload = b"Exif\x00\x00" + tiff
    return jpeg[:2] + b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload + jpeg[2:]


def _outcome(data: bytes) -> tuple[str, object]:
    """What ``decode_compressed`` makes of ``data``: ("image", pixels) or (error type, line)."""
    try:
        return "image", decode_compressed(data).tobytes()
    except ImageError as err:
        return type(err).__name__, str(err)


SAMPLING = {"420": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420, "422": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422,
            "444": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444, "411": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_411}


@pytest.mark.parametrize("quality", [5, 50, 75, 95, 100])
@pytest.mark.parametrize("sampling", sorted(SAMPLING))
@pytest.mark.parametrize("coding", ["baseline", "progressive", "optimized", "restarts"])
def test_simplejpeg_decodes_every_plain_jpeg_to_opencvs_very_pixels(
        quality: int, sampling: str, coding: str) -> None:
    """Colour (every chroma subsampling) and grey JPEGs of every quality and coding decode through
    simplejpeg, bit for bit what ``cv2.imdecode(..., IMREAD_GRAYSCALE)`` gives."""
    pytest.importorskip("simplejpeg")
    from ficap_ros.io.image_codec import _decode_jpeg_fast, _fast_decodable

    extra = {"baseline": [], "progressive": [cv2.IMWRITE_JPEG_PROGRESSIVE, 1],
             "optimized": [cv2.IMWRITE_JPEG_OPTIMIZE, 1],
             "restarts": [cv2.IMWRITE_JPEG_RST_INTERVAL, 3]}[coding]
    options = [cv2.IMWRITE_JPEG_QUALITY, quality,
               cv2.IMWRITE_JPEG_SAMPLING_FACTOR, SAMPLING[sampling], *extra]
    colour = cv2.resize(cv2.GaussianBlur(_bgr(), (3, 3), 0), (203, 117))  # odd sizes: partial MCUs
    for image in (colour, cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)):
        buf = cv2.imencode(".jpg", image, options)[1]
        assert _fast_decodable(buf)
        fast = _decode_jpeg_fast(buf)
        assert fast is not None and fast.shape == (117, 203) and fast.flags.c_contiguous
        np.testing.assert_array_equal(fast, cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE))
        np.testing.assert_array_equal(decode_compressed(buf.tobytes()), fast)


def test_jpegs_simplejpeg_would_decode_otherwise_go_to_opencv() -> None:
    """An Exif orientation (OpenCV turns the image, simplejpeg would not), other frame codings,
    12-bit samples, four components and headers cut before the scan are left to OpenCV."""
    from ficap_ros.io.image_codec import _decode_jpeg_fast, _fast_decodable

    jpeg = cv2.imencode(".jpg", cv2.resize(_bgr(), (80, 40)))[1].tobytes()
    assert _fast_decodable(np.frombuffer(jpeg, np.uint8))
    turned = _with_exif_orientation(jpeg, 6)  # 90 degrees clockwise
    assert not _fast_decodable(np.frombuffer(turned, np.uint8))
    assert _decode_jpeg_fast(np.frombuffer(turned, np.uint8)) is None
    assert decode_compressed(turned).shape == (80, 40)  # OpenCV's, turned
    np.testing.assert_array_equal(decode_compressed(turned),
                                  cv2.imdecode(np.frombuffer(turned, np.uint8), 0))
    sof = jpeg.index(b"\xff\xc0")
    for offset, value in ((1, 0xC3), (1, 0xC9), (4, 12), (9, 4)):  # lossless, arithmetic, 12 bit, CMYK
        changed = bytearray(jpeg)
        changed[sof + offset] = value
        assert not _fast_decodable(np.frombuffer(bytes(changed), np.uint8)), (offset, value)
    assert not _fast_decodable(np.frombuffer(jpeg[: jpeg.index(b"\xff\xda")], np.uint8))
    assert not _fast_decodable(np.frombuffer(jpeg[:sof] + b"\x00" + jpeg[sof:], np.uint8))


def test_without_simplejpeg_opencv_decodes_the_same(opencv_only: None) -> None:
    from ficap_ros.io.image_codec import _decode_jpeg_fast, _simplejpeg

    assert _simplejpeg() is None
    buf = cv2.imencode(".jpg", _bgr(), [cv2.IMWRITE_JPEG_QUALITY, 90])[1]
    assert _decode_jpeg_fast(buf) is None
    np.testing.assert_array_equal(decode_compressed(buf.tobytes()),
                                  cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE))


def test_damaged_and_cut_jpegs_get_the_same_verdict_with_or_without_simplejpeg(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Changed entropy-coded bytes, a stream cut short and trailing bytes: the same image or the
    same error (type and line) through either decoder; every damage libjpeg warns about is
    refused as ``DamagedImageError`` either way."""
    pytest.importorskip("simplejpeg")
    from probe_cases import flip_bytes

    from ficap_ros.io import image_codec

    colour = cv2.resize(_bgr(), (160, 120))
    cases = []
    for options in ([], [cv2.IMWRITE_JPEG_PROGRESSIVE, 1], [cv2.IMWRITE_JPEG_RST_INTERVAL, 2]):
        for image in (colour, cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)):
            jpeg = cv2.imencode(".jpg", image, options)[1].tobytes()
            cases += [flip_bytes(jpeg, count, seed) for count in (1, 4, 30) for seed in range(4)]
            cases += [jpeg[:cut] for cut in np.linspace(len(jpeg) // 2, len(jpeg) - 1, 4, dtype=int)]
            cases += [jpeg + b"\x00trailing"]
    image_codec._simplejpeg.cache_clear()
    with_simplejpeg = [_outcome(data) for data in cases]
    _opencv_only(monkeypatch)
    try:
        assert [_outcome(data) for data in cases] == with_simplejpeg
    finally:
        monkeypatch.undo()
        image_codec._simplejpeg.cache_clear()
    kinds = {kind for kind, _ in with_simplejpeg}
    assert {"image", "DamagedImageError"} <= kinds


def test_jpeg_decoder_names_the_decoder_decode_compressed_takes() -> None:
    """``jpeg_decoder``: a plain JPEG goes to simplejpeg (installed here), one with an Exif
    orientation to OpenCV (which turns it by it)."""
    from ficap_ros.io.image_codec import jpeg_decoder

    ok, jpeg = cv2.imencode(".jpg", np.full((16, 16), 128, np.uint8))
    assert ok
    assert jpeg_decoder(jpeg.reshape(-1)) == "simplejpeg"
    turned = np.frombuffer(_with_exif_orientation(jpeg.tobytes(), 6), np.uint8)
    assert jpeg_decoder(turned) == "cv2.imdecode"


def test_jpeg_decoder_without_simplejpeg_is_opencv(opencv_only: None) -> None:
    """Without ``simplejpeg`` every JPEG goes to OpenCV."""
    from ficap_ros.io.image_codec import jpeg_decoder

    ok, jpeg = cv2.imencode(".jpg", np.full((16, 16), 128, np.uint8))
    assert ok and jpeg_decoder(jpeg.reshape(-1)) == "cv2.imdecode"
