"""The fast PNG reader decodes what cv2.imread decodes, and leaves every other PNG to OpenCV."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from hivemap.client import png
from hivemap.client.dataset import _load_gray


def _image(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ramp = np.add.outer(np.arange(h), 3 * np.arange(w)) % 256
    return np.asarray((ramp + rng.integers(0, 40, (h, w))) % 256, dtype=np.uint8)


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(body, zlib.crc32(kind)))


def _png(img: np.ndarray, filters: list[int], extra: bytes = b"") -> bytes:
    """A gray PNG with the given row filters (0 None, 1 Sub, 4 Paeth written as raw bytes)."""
    h, w = img.shape
    rows = []
    for y, f in enumerate(filters):
        row = img[y].astype(np.int16)
        if f == 1:
            row = np.diff(row, prepend=0)
        rows.append(bytes([f]) + (row % 256).astype(np.uint8).tobytes())
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    body = _chunk(b"IHDR", ihdr) + extra
    return png.SIGNATURE + body + _chunk(b"IDAT", zlib.compress(b"".join(rows))) + _chunk(b"IEND", b"")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_same_as_opencv_on_its_own_pngs(tmp_path: Path, seed: int) -> None:
    img = _image(seed=seed)
    path = tmp_path / "a.png"
    assert cv2.imwrite(str(path), img)
    ref = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    out = png.read_gray8(path, inflate=zlib.decompress)
    assert out is not None and out.dtype == np.uint8 and np.array_equal(out, ref)
    if png.FAST:  # ISA-L's inflate gives the same bytes
        assert np.array_equal(png.read_gray8(path), ref)
    assert np.array_equal(_load_gray(path), ref)


def test_rows_with_none_and_sub_filters(tmp_path: Path) -> None:
    img = _image(h=9, w=13)
    path = tmp_path / "mixed.png"
    path.write_bytes(_png(img, [0, 1, 1, 0, 1, 0, 0, 1, 1]))
    assert np.array_equal(png.read_gray8(path, inflate=zlib.decompress), img)
    assert np.array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), img)


def test_other_pngs_are_left_to_opencv(tmp_path: Path) -> None:
    img = _image(h=4, w=5)
    cases = {
        "paeth.png": _png(img, [1, 4, 1, 1]),  # a filter this reader does not undo
        "trns.png": _png(img, [1] * 4, extra=_chunk(b"tRNS", b"\x00\x07")),  # changes what OpenCV returns
    }
    good = _png(img, [1] * 4)
    cases["crc.png"] = good[:-5] + bytes([good[-5] ^ 1]) + good[-4:]  # IEND's CRC damaged
    cases["cut.png"] = good[: len(good) // 2]
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        assert png.read_gray8(tmp_path / name, inflate=zlib.decompress) is None, name
    deep = tmp_path / "deep.png"
    assert cv2.imwrite(str(deep), (_image().astype(np.uint16) * 257))
    colour = tmp_path / "colour.png"
    assert cv2.imwrite(str(colour), np.dstack([_image()] * 3))
    for path in (deep, colour, tmp_path / "missing.png"):
        assert png.read_gray8(path, inflate=zlib.decompress) is None
