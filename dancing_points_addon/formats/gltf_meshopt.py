"""Decode ``EXT_meshopt_compression`` glTF binaries (numpy only, no ``bpy``).

Blender's glTF importer refuses files that *require*
``EXT_meshopt_compression`` ("Extension EXT_meshopt_compression is not
available on this addon version"; checked 2026-11-28 with ``bpy`` 5.0.1 on the
avatars of ``../shared/assets``), which is how many avatar libraries ship their
``.glb`` files (glTF-Transform / gltfpack output). Upstream support was merged
for Blender 5.2 or later (KhronosGroup/glTF-Blender-IO pull request 2701, issue
2690), so every version this extension supports (4.2 LTS to 5.1) needs this
module; drop it when 5.2 is the oldest supported version. :func:`decompress_glb` rewrites such a file
as a plain ``.glb`` (every buffer view decoded into one binary chunk, the
extension removed) that the importer reads; everything else in the file is kept
as it is.

The bitstreams are the ones of the extension's specification (Khronos glTF
repository, ``extensions/2.0/Vendor/EXT_meshopt_compression``, Appendix A and B):
mode 0 (attributes, header ``0xa0``), mode 1 (triangles, ``0xe0``/``0xe1``),
mode 2 (indices, ``0xd0``/``0xd1``), filters NONE / OCTAHEDRAL / QUATERNION /
EXPONENTIAL. The attribute decoder scans the group headers in Python (a few
integer operations per group of 16 bytes) and decodes the bytes with numpy.
"""
from __future__ import annotations

import json
import os
import struct

import numpy as np

from ..errors import UserError
from .files import atomic_output

EXTENSION = "EXT_meshopt_compression"
_GLB_MAGIC = 0x46546C67
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942


class MeshoptError(UserError, ValueError):
    """A malformed or unsupported compressed stream (one line)."""


# --------------------------------------------------------------------------- attributes (mode 0)

def _popcount_sentinels():
    b = np.arange(256)
    two = sum(((b >> s) & 3) == 3 for s in (0, 2, 4, 6)).astype(np.int64)
    four = ((b & 15) == 15).astype(np.int64) + ((b >> 4) == 15).astype(np.int64)
    return two, four


_SENT2, _SENT4 = _popcount_sentinels()


def decode_attributes(data: bytes, count: int, stride: int) -> np.ndarray:
    """Mode 0: ``count`` elements of ``stride`` bytes -> ``uint8 (count, stride)``."""
    buf = np.frombuffer(data, dtype=np.uint8)
    n = len(buf)
    if n < 1 or (buf[0] & 0xF0) != 0xA0:
        raise MeshoptError("not a meshopt attribute stream (header {:#x})".format(int(buf[0]) if n else -1))
    if (buf[0] & 0x0F) != 0:
        raise MeshoptError("unsupported meshopt attribute stream version {:d}".format(int(buf[0] & 0x0F)))
    if stride <= 0 or stride > 256 or stride % 4:
        raise MeshoptError("invalid byteStride {:d}".format(stride))
    tail = max(32, stride)
    if n < 1 + tail:
        raise MeshoptError("meshopt attribute stream too short")
    baseline = buf[n - stride:].copy()
    if count == 0:
        return np.zeros((0, stride), dtype=np.uint8)
    max_block = min((8192 // stride) & ~15, 256)
    c2 = np.concatenate([[0], np.cumsum(_SENT2[buf])]).tolist()
    c4 = np.concatenate([[0], np.cumsum(_SENT4[buf])]).tolist()
    raw = buf.tolist()
    starts, modes = [], []  # per group, in stream order
    pos = 1
    end = n - tail
    remaining = count
    block_sizes = []
    while remaining > 0:
        nb = min(remaining, max_block)
        block_sizes.append(nb)
        groups = (nb + 15) // 16
        hsize = (groups + 3) // 4
        for _k in range(stride):
            hdr = raw[pos:pos + hsize]
            pos += hsize
            for g in range(groups):
                m = (hdr[g >> 2] >> ((g & 3) << 1)) & 3
                starts.append(pos)
                modes.append(m)
                if m == 1:
                    pos += 4 + c2[pos + 4] - c2[pos]
                elif m == 2:
                    pos += 8 + c4[pos + 8] - c4[pos]
                elif m == 3:
                    pos += 16
            if pos > end:
                raise MeshoptError("meshopt attribute stream overruns its data")
        remaining -= nb
    if pos != end:
        raise MeshoptError("meshopt attribute stream has {:d} unread bytes".format(end - pos))
    starts = np.asarray(starts, dtype=np.int64)
    modes = np.asarray(modes, dtype=np.int64)
    padded = np.concatenate([buf, np.zeros(32, dtype=np.uint8)])
    out = np.zeros((len(starts), 16), dtype=np.uint8)
    i16 = np.arange(16)
    sel = modes == 3
    if sel.any():
        out[sel] = padded[starts[sel, None] + i16]
    for m, bits, nfix in ((1, 2, 4), (2, 4, 8)):
        sel = modes == m
        if not sel.any():
            continue
        s = starts[sel]
        per = 8 // bits
        byte = padded[s[:, None] + i16 // per]
        shift = (8 - bits) - bits * (i16 % per)
        v = (byte >> shift) & ((1 << bits) - 1)
        sentinel = v == (1 << bits) - 1
        rank = np.cumsum(sentinel, axis=1) - sentinel
        extra = padded[s[:, None] + nfix + rank]
        out[sel] = np.where(sentinel, extra, v).astype(np.uint8)
    # Deltas (zigzag) back to elements: a running sum per byte lane over the whole stream.
    delta = np.empty((count, stride), dtype=np.uint8)
    gi = 0
    ei = 0
    for nb in block_sizes:
        groups = (nb + 15) // 16
        blk = out[gi:gi + stride * groups].reshape(stride, groups * 16)[:, :nb]
        delta[ei:ei + nb] = blk.T
        gi += stride * groups
        ei += nb
    d = delta.astype(np.int64)
    d = ((d >> 1) ^ -(d & 1)) & 0xFF
    d[0] = (d[0] + baseline) & 0xFF
    return np.cumsum(d, axis=0, dtype=np.int64).astype(np.uint8)  # wraps modulo 256


# --------------------------------------------------------------------------- triangles (mode 1) and indices (mode 2)

def _vbyte(raw, p):
    lead = raw[p]
    p += 1
    if lead < 128:
        return lead, p
    result = lead & 127
    shift = 7
    for _ in range(4):
        g = raw[p]
        p += 1
        result |= (g & 127) << shift
        shift += 7
        if g < 128:
            break
    return result, p


def _unzig32(v):
    d = (v >> 1) ^ (-(v & 1))
    return d


def decode_triangles(data: bytes, count: int) -> np.ndarray:
    """Mode 1: ``count`` indices (a multiple of 3) -> ``uint32 (count,)``."""
    raw = bytes(data)
    n = len(raw)
    if count % 3:
        raise MeshoptError("triangle index count {:d} is not a multiple of 3".format(count))
    if n < 1 + count // 3 + 16 or (raw[0] & 0xF0) != 0xE0 or (raw[0] & 0x0F) > 1:
        raise MeshoptError("not a meshopt triangle stream")
    version = raw[0] & 0x0F
    fecmax = 13 if version >= 1 else 15
    edge_a = [0xFFFFFFFF] * 16
    edge_b = [0xFFFFFFFF] * 16
    vfifo = [0xFFFFFFFF] * 16
    eo = vo = 0
    nxt = last = 0
    code = 1
    dp = 1 + count // 3
    safe_end = n - 16
    aux = raw[safe_end:]
    out = [0] * count
    M = 0xFFFFFFFF
    for i in range(0, count, 3):
        if dp > safe_end:
            raise MeshoptError("meshopt triangle stream overruns its data")
        ct = raw[code]
        code += 1
        if ct < 0xF0:
            e = (eo - 1 - (ct >> 4)) & 15
            a, b = edge_a[e], edge_b[e]
            fec = ct & 15
            if fec < fecmax:
                if fec == 0:
                    c = nxt
                    nxt += 1
                    vfifo[vo] = c
                    vo = (vo + 1) & 15
                else:
                    c = vfifo[(vo - 1 - fec) & 15]
            else:
                if fec != 15:
                    c = (last + (fec - (fec ^ 3))) & M
                else:
                    v, dp = _vbyte(raw, dp)
                    c = (last + _unzig32(v)) & M
                last = c
                vfifo[vo] = c
                vo = (vo + 1) & 15
            edge_a[eo], edge_b[eo] = c, b
            eo = (eo + 1) & 15
            edge_a[eo], edge_b[eo] = a, c
            eo = (eo + 1) & 15
        else:
            # a triangle of three vertices, each new (the next index), from the
            # vertex FIFO, or (0xFE/0xFF codes only, nibble 15) an explicit index
            explicit = ct >= 0xFE
            if explicit:
                ca = raw[dp]
                dp += 1
                fea = 0 if ct == 0xFE else 15
                if ca == 0:
                    nxt = 0
            else:
                ca = aux[ct & 15]
                fea = 0
            feb, fec = ca >> 4, ca & 15
            if fea == 0:
                a = nxt
                nxt += 1
            else:
                a = 0
            if feb == 0:
                b = nxt
                nxt += 1
            else:
                b = vfifo[(vo - feb) & 15]
            if fec == 0:
                c = nxt
                nxt += 1
            else:
                c = vfifo[(vo - fec) & 15]
            if explicit:
                if fea == 15:
                    v, dp = _vbyte(raw, dp)
                    last = a = (last + _unzig32(v)) & M
                if feb == 15:
                    v, dp = _vbyte(raw, dp)
                    last = b = (last + _unzig32(v)) & M
                if fec == 15:
                    v, dp = _vbyte(raw, dp)
                    last = c = (last + _unzig32(v)) & M
            vfifo[vo] = a
            vo = (vo + 1) & 15
            if feb == 0 or (explicit and feb == 15):
                vfifo[vo] = b
                vo = (vo + 1) & 15
            if fec == 0 or (explicit and fec == 15):
                vfifo[vo] = c
                vo = (vo + 1) & 15
            edge_a[eo], edge_b[eo] = b, a
            eo = (eo + 1) & 15
            edge_a[eo], edge_b[eo] = c, b
            eo = (eo + 1) & 15
            edge_a[eo], edge_b[eo] = a, c
            eo = (eo + 1) & 15
        out[i], out[i + 1], out[i + 2] = a, b, c
    if dp != safe_end:
        raise MeshoptError("meshopt triangle stream has {:d} unread bytes".format(safe_end - dp))
    return np.asarray(out, dtype=np.uint32)


def decode_indices(data: bytes, count: int) -> np.ndarray:
    """Mode 2: ``count`` indices -> ``uint32 (count,)``."""
    raw = bytes(data)
    if len(raw) < 1 + 4 or (raw[0] & 0xF0) != 0xD0 or (raw[0] & 0x0F) > 1:
        raise MeshoptError("not a meshopt index stream")
    last = [0, 0]
    p = 1
    out = [0] * count
    for i in range(count):
        v, p = _vbyte(raw, p)
        cur = v & 1
        v >>= 1
        last[cur] = (last[cur] + _unzig32(v)) & 0xFFFFFFFF
        out[i] = last[cur]
    return np.asarray(out, dtype=np.uint32)


# --------------------------------------------------------------------------- filters

def _filter(elems: np.ndarray, stride: int, name: str) -> np.ndarray:
    if name in ("", "NONE", None):
        return elems
    if name == "OCTAHEDRAL":
        if stride not in (4, 8):
            raise MeshoptError("OCTAHEDRAL filter needs byteStride 4 or 8")
        it = np.int8 if stride == 4 else np.int16
        v = np.ascontiguousarray(elems).view(it).reshape(-1, 4).astype(np.float32)
        one = np.where(v[:, 2] == 0, 1.0, v[:, 2])
        x, y = v[:, 0] / one, v[:, 1] / one
        z = 1.0 - np.abs(x) - np.abs(y)
        t = np.minimum(z, 0.0)
        x = x - np.copysign(t, x)
        y = y - np.copysign(t, y)
        ln = np.sqrt(x * x + y * y + z * z)
        ln = np.where(ln > 0, ln, 1.0)
        mx = 127.0 if stride == 4 else 32767.0
        o = np.empty_like(v)
        o[:, 0], o[:, 1], o[:, 2] = np.round(x / ln * mx), np.round(y / ln * mx), np.round(z / ln * mx)
        o[:, 3] = v[:, 3]
        return o.astype(it).view(np.uint8).reshape(elems.shape)
    if name == "QUATERNION":
        if stride != 8:
            raise MeshoptError("QUATERNION filter needs byteStride 8")
        v = np.ascontiguousarray(elems).view(np.int16).reshape(-1, 4)
        one = (v[:, 3].astype(np.int32) | 3).astype(np.float32)
        r = np.float32(1.0 / np.sqrt(2.0))
        xyz = v[:, :3].astype(np.float32) / one[:, None] * r
        w = np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyz * xyz, axis=1)))
        mc = (v[:, 3] & 3).astype(np.int64)
        o = np.empty((len(v), 4), dtype=np.float32)
        rows = np.arange(len(v))
        for j in range(3):
            o[rows, (mc + 1 + j) % 4] = np.round(xyz[:, j] * 32767.0)
        o[rows, mc % 4] = np.round(w * 32767.0)
        return o.astype(np.int16).view(np.uint8).reshape(elems.shape)
    if name == "EXPONENTIAL":
        v = np.ascontiguousarray(elems).view(np.int32).astype(np.int64)
        e = v >> 24
        m = ((v << 8) & 0xFFFFFFFF)
        m = np.where(m >= 1 << 31, m - (1 << 32), m) >> 8
        out = np.ldexp(m.astype(np.float64), e.astype(np.int64)).astype(np.float32)
        return out.view(np.uint8).reshape(elems.shape)
    raise MeshoptError("unknown meshopt filter {!r}".format(name))


def decode_buffer_view(data: bytes, ext: dict) -> bytes:
    """The decoded bytes of one compressed buffer view (its extension object ``ext``)."""
    count, stride = int(ext["count"]), int(ext["byteStride"])
    mode = ext.get("mode", "ATTRIBUTES")
    if mode == "ATTRIBUTES":
        out = _filter(decode_attributes(data, count, stride), stride, ext.get("filter", "NONE"))
        return out.tobytes()
    if mode in ("TRIANGLES", "INDICES"):
        idx = decode_triangles(data, count) if mode == "TRIANGLES" else decode_indices(data, count)
        if stride == 2:
            return idx.astype(np.uint16).tobytes()
        if stride == 4:
            return idx.astype(np.uint32).tobytes()
        raise MeshoptError("index byteStride must be 2 or 4, not {:d}".format(stride))
    raise MeshoptError("unknown meshopt mode {!r}".format(mode))


# --------------------------------------------------------------------------- GLB

def read_glb(path):
    """``(json dict, binary chunk bytes or b"")`` of a ``.glb`` file."""
    with open(path, "rb") as fh:
        blob = fh.read()
    if len(blob) < 20:
        raise MeshoptError("{:s}: not a binary glTF file".format(os.fspath(path)))
    magic, version, _length = struct.unpack_from("<III", blob, 0)
    if magic != _GLB_MAGIC or version != 2:
        raise MeshoptError("{:s}: not a binary glTF 2.0 file".format(os.fspath(path)))
    off = 12
    doc, binary = None, b""
    while off + 8 <= len(blob):
        clen, ctype = struct.unpack_from("<II", blob, off)
        chunk = blob[off + 8: off + 8 + clen]
        if ctype == _CHUNK_JSON and doc is None:
            doc = json.loads(chunk.decode("utf-8"))
        elif ctype == _CHUNK_BIN and not binary:
            binary = chunk
        off += 8 + clen
    if doc is None:
        raise MeshoptError("{:s}: no JSON chunk".format(os.fspath(path)))
    return doc, binary


def needs_decompression(path) -> bool:
    """Whether a ``.glb`` uses ``EXT_meshopt_compression``."""
    try:
        doc, _ = read_glb(path)
    except (OSError, MeshoptError, ValueError):
        return False
    return EXTENSION in (doc.get("extensionsUsed") or [])


def decompress_glb(src, dst) -> str:
    """Write ``src`` (a ``.glb`` using ``EXT_meshopt_compression``) as a plain
    ``.glb`` at ``dst``; returns ``dst``. Buffers other than the GLB binary chunk
    must be absent (fallback placeholders) — external ``.bin`` files are not read."""
    doc, binary = read_glb(src)
    buffers = doc.get("buffers") or []
    views = doc.get("bufferViews") or []
    out = bytearray()
    new_views = []
    for i, bv in enumerate(views):
        ext = (bv.get("extensions") or {}).get(EXTENSION)
        if ext is not None:
            if int(ext.get("buffer", 0)) != 0 or "uri" in buffers[int(ext.get("buffer", 0))]:
                raise MeshoptError("buffer view {:d}: compressed data outside the GLB chunk".format(i))
            o = int(ext.get("byteOffset", 0))
            data = decode_buffer_view(binary[o:o + int(ext["byteLength"])], ext)
            if len(data) != int(bv["byteLength"]):
                raise MeshoptError("buffer view {:d}: decoded {:d} bytes, expected {:d}".format(
                    i, len(data), int(bv["byteLength"])))
        else:
            b = int(bv.get("buffer", 0))
            if b != 0 or "uri" in buffers[b]:
                raise MeshoptError("buffer view {:d}: data outside the GLB chunk".format(i))
            o = int(bv.get("byteOffset", 0))
            data = binary[o:o + int(bv["byteLength"])]
        while len(out) % 4:
            out.append(0)
        nv = {k: v for k, v in bv.items() if k != "extensions"}
        other = {k: v for k, v in (bv.get("extensions") or {}).items() if k != EXTENSION}
        if other:
            nv["extensions"] = other
        nv["buffer"] = 0
        nv["byteOffset"] = len(out)
        nv["byteLength"] = len(data)
        out += data
        new_views.append(nv)
    while len(out) % 4:
        out.append(0)
    doc = dict(doc)
    doc["bufferViews"] = new_views
    doc["buffers"] = [{"byteLength": len(out)}]
    for key in ("extensionsUsed", "extensionsRequired"):
        if key in doc:
            doc[key] = [e for e in doc[key] if e != EXTENSION]
            if not doc[key]:
                del doc[key]
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * ((4 - len(js) % 4) % 4)
    total = 12 + 8 + len(js) + 8 + len(out)
    with atomic_output(dst, "wb") as fh:
        fh.write(struct.pack("<III", _GLB_MAGIC, 2, total))
        fh.write(struct.pack("<II", len(js), _CHUNK_JSON))
        fh.write(js)
        fh.write(struct.pack("<II", len(out), _CHUNK_BIN))
        fh.write(bytes(out))
    return os.fspath(dst)
