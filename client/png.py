"""A fast reader for the PNGs hivemap's renderer writes (``cv2.imencode``): 8-bit grayscale, not
interlaced, every row filtered with "None" or "Sub".

Decoding is most of an image's read time: libpng inflates with the system zlib, then undoes the row
filters byte by byte. Here the inflate is ISA-L's (``isal``: the same bytes, about three times as fast)
and the "Sub" filter is undone for all rows at once, which halves the decode. Without ``isal`` there is
nothing to gain (``FAST`` is False) and the readers use OpenCV. Any other PNG, or a damaged one, gives
None and is left to OpenCV too, so what an image decodes to never depends on this module
(``tests/client/test_png.py`` compares it with ``cv2.imread``).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

Inflate = Callable[[bytes], bytes]
_errors: tuple[type[Exception], ...] = (zlib.error, ValueError)
_isal: Inflate | None
try:
    from isal import isal_zlib

    _isal = isal_zlib.decompress
    _errors += (isal_zlib.error,)
except ImportError:
    _isal = None
FAST = _isal is not None  # worth using instead of cv2.imread

SIGNATURE = b"\x89PNG\r\n\x1a\n"
# chunks that do not change the pixels OpenCV returns; a PNG with any other (tRNS, sBIT, gAMA, PLTE, ...)
# is left to OpenCV
_PASSIVE = frozenset({b"tEXt", b"zTXt", b"iTXt", b"tIME", b"pHYs"})
_FILTER_NONE, _FILTER_SUB = 0, 1


def read_gray8(path: str | Path, inflate: Inflate | None = None) -> NDArray[np.uint8] | None:
    """The (H, W) image of an 8-bit grayscale, non-interlaced PNG whose rows are filtered with None or Sub,
    equal to ``cv2.imread(path, cv2.IMREAD_UNCHANGED)``; None for any other file (read it with OpenCV).
    ``inflate``: zlib's ``decompress`` or an equivalent (default: ISA-L's, zlib's without ``isal``)."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        return None
    chunks = _chunks(data)
    if chunks is None:
        return None
    header, idat = chunks
    width, height, depth, colour, compression, filtering, interlace = struct.unpack(">IIBBBBB", header)
    if (depth, colour, compression, filtering, interlace) != (8, 0, 0, 0, 0) or not width or not height:
        return None
    try:
        raw = (inflate or _isal or zlib.decompress)(idat)
    except _errors:
        return None
    if len(raw) != height * (width + 1):
        return None
    rows = np.frombuffer(raw, np.uint8).reshape(height, width + 1)
    filters = rows[:, 0]
    if np.any(filters > _FILTER_SUB):
        return None  # Up, Average or Paeth rows: OpenCV's path
    img = rows[:, 1:].copy()
    sub = filters == _FILTER_SUB
    if sub.all():
        _undo_sub(img)
    elif sub.any():
        part = img[sub]
        _undo_sub(part)
        img[sub] = part
    return img


def _chunks(data: bytes) -> tuple[bytes, bytes] | None:
    """(IHDR data, the IDAT data joined) of a well-formed PNG with no chunk that changes its pixels."""
    if not data.startswith(SIGNATURE):
        return None
    view = memoryview(data)
    pos, header, idat = len(SIGNATURE), b"", []
    while pos + 12 <= len(data):
        (n,) = struct.unpack_from(">I", data, pos)
        kind = bytes(view[pos + 4 : pos + 8])
        end = pos + 8 + n
        if end + 4 > len(data):
            return None
        body = view[pos + 8 : end]
        (crc,) = struct.unpack_from(">I", data, end)
        if zlib.crc32(body, zlib.crc32(kind)) != crc:
            return None  # damaged: OpenCV reports it
        if kind == b"IHDR":
            if header or n != 13:
                return None
            header = bytes(body)
        elif kind == b"IDAT" and header:
            idat.append(body)
        elif kind == b"IEND":
            return (header, b"".join(idat)) if header and idat else None
        elif kind not in _PASSIVE:
            return None
        pos = end + 4
    return None


def _undo_sub(img: NDArray[np.uint8]) -> None:
    """Each row's "Sub" filter undone in place: a running sum modulo 256 along the row, by doubling
    strides (log2(W) vectorised additions instead of one per pixel)."""
    tmp = np.empty_like(img)
    step = 1
    while step < img.shape[1]:
        np.add(img[:, step:], img[:, :-step], out=tmp[:, step:])
        img[:, step:] = tmp[:, step:]
        step *= 2
