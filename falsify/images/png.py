"""Read and write 8-bit PNG images with zlib and numpy: no imaging dependency.

Writing is deterministic RGB. Reading handles what cameras (KITTI's frames) and our encoder
write: bit depth 8, grey, grey+alpha, RGB or RGBA, not interlaced, all five row filters (Sub
and Up vectorised; Average and Paeth per pixel).
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from falsify.errors import FalsifyError
from falsify.fileio import read_bytes

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}


def read_png(path: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a PNG file (grey is repeated, alpha dropped)."""
    data = read_bytes(path)
    try:
        return decode_png(data)
    except ValueError as exc:
        raise FalsifyError(f"{path}: {exc}") from None


def png_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from a PNG's header, without decoding it."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            head = fh.read(24)
    except OSError as exc:
        raise FalsifyError(f"{path}: cannot read ({exc.strerror})") from None
    if head[:8] != _SIGNATURE or head[12:16] != b"IHDR":
        raise FalsifyError(f"{path}: not a PNG file")
    w, h = struct.unpack(">II", head[16:24])
    return int(w), int(h)


def decode_png(data: bytes) -> np.ndarray:
    """Decode PNG bytes to (H, W, 3) uint8; ValueError names what is not supported."""
    if data[:8] != _SIGNATURE:
        raise ValueError("not a PNG file")
    pos, idat, header = 8, [], None
    while pos + 8 <= len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        tag = data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + length]
        pos += 12 + length
        if tag == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif tag == b"IDAT":
            idat.append(body)
        elif tag == b"IEND":
            break
    if header is None:
        raise ValueError("PNG without IHDR")
    w, h, depth, colour, _, _, interlace = header
    if depth != 8 or colour not in _CHANNELS or interlace:
        raise ValueError(f"unsupported PNG (bit depth {depth}, colour type {colour}, interlace "
                         f"{interlace}); supported: 8-bit grey, RGB, RGBA, not interlaced")
    ch = _CHANNELS[colour]
    try:
        raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8)
    except zlib.error as exc:
        raise ValueError(f"corrupt PNG data ({exc})") from None
    stride = w * ch
    if raw.size != h * (stride + 1):
        raise ValueError(f"PNG data holds {raw.size} bytes, expected {h * (stride + 1)}")
    rows = raw.reshape(h, stride + 1)
    out = np.zeros((h, stride), np.uint8)
    prev = np.zeros(stride, np.uint8)
    for r in range(h):
        kind, line = rows[r, 0], rows[r, 1:]
        if kind == 0:
            cur = line.copy()
        elif kind == 1:  # Sub: running sum along each channel, modulo 256
            cur = np.cumsum(line.reshape(w, ch), axis=0, dtype=np.uint8).reshape(stride)
        elif kind == 2:
            cur = line + prev
        elif kind in (3, 4):
            cur = _sequential(line, prev, ch, kind)
        else:
            raise ValueError(f"unknown PNG row filter {kind}")
        out[r] = cur
        prev = cur
    img = out.reshape(h, w, ch)
    if ch in (1, 2):
        return np.repeat(img[..., :1], 3, axis=2)
    return np.ascontiguousarray(img[..., :3])


def _sequential(line: np.ndarray, prev: np.ndarray, ch: int, kind: int) -> np.ndarray:
    """Average (3) and Paeth (4) filters: each byte depends on the decoded byte to its left."""
    cur = [0] * len(line)
    up = prev.tolist()
    src = line.tolist()
    for i in range(len(src)):
        a = cur[i - ch] if i >= ch else 0
        b = up[i]
        if kind == 3:
            cur[i] = (src[i] + (a + b) // 2) & 0xFF
        else:
            c = up[i - ch] if i >= ch else 0
            p = a + b - c
            pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
            pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            cur[i] = (src[i] + pred) & 0xFF
    return np.array(cur, np.uint8)


def encode_png(rgb: np.ndarray) -> bytes:
    """Encode an (H, W, 3) uint8 array as a PNG (deterministic bytes)."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    h, w, _ = rgb.shape
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rgb.reshape(h, w * 3)], axis=1).tobytes()

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + tag + data
                + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return (_SIGNATURE + chunk(b"IHDR", header)
            + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))
