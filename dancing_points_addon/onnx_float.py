"""The shipped int8 networks multiplied in float32, rewritten in memory at load.

The networks in ``models/`` store their weights as 8-bit blocks run by ONNX
Runtime's ``MatMulNBits`` at accuracy level 4, which also quantises each
layer's *input* to int8 at run time. That input quantisation makes a network a
step function of its input: 2 µm on a tracked position flips some rounding
and changes the outputs by about a millimetre, which the frame loop's
autoregressive trackers and its threshold decisions (foot locks, steps) carry
on to centimetres. ONNX Runtime has no float-compute path for 8-bit blocks, so
:func:`float_compute` rewrites the graph instead: every symmetric 8-bit
``MatMulNBits`` becomes a float32 ``MatMul`` of the same dequantized weight
values (``(q − 128) · scale``). The files are not changed.

It works on the serialised model (protobuf wire format) with numpy alone, so
the extension needs no ``onnx`` package; only the fields it rewrites are
decoded, everything else is copied byte for byte. ``training.export``'s
``dequantize_int8`` (with the ``onnx`` package) is the same rewrite.
"""
from __future__ import annotations

import numpy as np

# protobuf wire types
_VARINT, _I64, _LEN, _I32 = 0, 1, 2, 5

# field numbers (onnx.proto)
_MODEL_GRAPH = 7
_GRAPH_NODE, _GRAPH_INIT, _GRAPH_OUTPUT = 1, 5, 12
_NODE_INPUT, _NODE_OUTPUT, _NODE_NAME, _NODE_OP, _NODE_ATTR, _NODE_DOMAIN = 1, 2, 3, 4, 5, 7
_ATTR_NAME, _ATTR_I = 1, 3
_T_DIMS, _T_TYPE, _T_FLOAT, _T_INT32, _T_NAME, _T_RAW = 1, 2, 4, 5, 8, 9
_FLOAT, _UINT8 = 1, 2  # TensorProto.DataType


class OnnxRewriteError(ValueError):
    """The model is not one this rewrite understands."""


def _varint(buf, i):
    v = shift = 0
    while True:
        if i >= len(buf):
            raise OnnxRewriteError("truncated varint")
        b = buf[i]
        i += 1
        v |= (b & 0x7F) << shift
        if b < 0x80:
            return v, i
        shift += 7
        if shift > 63:
            raise OnnxRewriteError("varint too long")


def _fields(buf):
    """``[(field, wire type, value, raw bytes of the whole field)]`` of one message:
    value is an int (varint, fixed) or the bytes of a length-delimited field."""
    out, i, n = [], 0, len(buf)
    while i < n:
        start = i
        key, i = _varint(buf, i)
        field, wt = key >> 3, key & 7
        if wt == _VARINT:
            v, i = _varint(buf, i)
        elif wt == _I64:
            v, i = int.from_bytes(buf[i:i + 8], "little"), i + 8
        elif wt == _I32:
            v, i = int.from_bytes(buf[i:i + 4], "little"), i + 4
        elif wt == _LEN:
            ln, i = _varint(buf, i)
            v, i = bytes(buf[i:i + ln]), i + ln
        else:
            raise OnnxRewriteError(f"unsupported wire type {wt}")
        if i > n:
            raise OnnxRewriteError("truncated field")
        out.append((field, wt, v, bytes(buf[start:i])))
    return out


def _enc_varint(v):
    out = bytearray()
    v &= (1 << 64) - 1
    while True:
        b = v & 0x7F
        v >>= 7
        if v:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _key(field, wt):
    return _enc_varint((field << 3) | wt)


def _len_field(field, data: bytes):
    return _key(field, _LEN) + _enc_varint(len(data)) + data


def _str_field(field, s: str):
    return _len_field(field, s.encode("utf-8"))


def _signed(v):
    return v - (1 << 64) if v >= 1 << 63 else v


def _node(buf):
    d = {"input": [], "output": [], "name": "", "op": "", "domain": "", "attr": {}}
    for f, wt, v, _ in _fields(buf):
        if f == _NODE_INPUT and wt == _LEN:
            d["input"].append(v.decode("utf-8"))
        elif f == _NODE_OUTPUT and wt == _LEN:
            d["output"].append(v.decode("utf-8"))
        elif f == _NODE_NAME and wt == _LEN:
            d["name"] = v.decode("utf-8")
        elif f == _NODE_OP and wt == _LEN:
            d["op"] = v.decode("utf-8")
        elif f == _NODE_DOMAIN and wt == _LEN:
            d["domain"] = v.decode("utf-8")
        elif f == _NODE_ATTR and wt == _LEN:
            name, ival = None, None
            for af, awt, av, _ in _fields(v):
                if af == _ATTR_NAME and awt == _LEN:
                    name = av.decode("utf-8")
                elif af == _ATTR_I and awt == _VARINT:
                    ival = _signed(av)
            if name is not None:
                d["attr"][name] = ival
    return d


def _tensor(buf):
    """``(name, numpy array)`` of an initializer (raw data, or packed float / int32 data)."""
    dims, dtype, name, raw, floats, ints = [], None, "", None, None, None
    for f, wt, v, _ in _fields(buf):
        if f == _T_DIMS:
            if wt == _VARINT:
                dims.append(_signed(v))
            elif wt == _LEN:  # packed
                i = 0
                while i < len(v):
                    x, i = _varint(v, i)
                    dims.append(_signed(x))
        elif f == _T_TYPE and wt == _VARINT:
            dtype = v
        elif f == _T_NAME and wt == _LEN:
            name = v.decode("utf-8")
        elif f == _T_RAW and wt == _LEN:
            raw = v
        elif f == _T_FLOAT and wt == _LEN:
            floats = np.frombuffer(v, dtype="<f4")
        elif f == _T_INT32 and wt == _LEN:
            vals, i = [], 0
            while i < len(v):
                x, i = _varint(v, i)
                vals.append(x)
            ints = np.array(vals, dtype=np.int64)
    np_type = {_FLOAT: "<f4", _UINT8: "u1"}.get(dtype)
    if np_type is None:
        return name, None
    if raw is not None:
        arr = np.frombuffer(raw, dtype=np_type)
    elif dtype == _FLOAT and floats is not None:
        arr = floats
    elif dtype == _UINT8 and ints is not None:
        arr = ints.astype(np.uint8)
    else:
        arr = np.zeros(0, dtype=np_type)
    return name, arr.reshape(dims) if dims else arr


def _float_tensor(name, arr):
    arr = np.ascontiguousarray(arr, dtype="<f4")
    out = b"".join(_key(_T_DIMS, _VARINT) + _enc_varint(int(d)) for d in arr.shape)
    out += _key(_T_TYPE, _VARINT) + _enc_varint(_FLOAT)
    out += _str_field(_T_NAME, name) + _len_field(_T_RAW, arr.tobytes())
    return out


def _node_bytes(op, inputs, outputs, name):
    out = b"".join(_str_field(_NODE_INPUT, s) for s in inputs)
    out += b"".join(_str_field(_NODE_OUTPUT, s) for s in outputs)
    return out + _str_field(_NODE_NAME, name) + _str_field(_NODE_OP, op)


def dequantized_weight(q, scales, K, N, block_size):
    """The ``(K, N)`` float32 weight (input-major, as ``MatMul`` reads it) of a
    symmetric 8-bit ``MatMulNBits``: ``q (N, blocks, block_size)`` uint8 with
    128 as the zero, one scale per block."""
    q = np.asarray(q, dtype=np.float32).reshape(N, -1, block_size)
    s = np.asarray(scales, dtype=np.float32).reshape(N, -1)
    if s.shape[1] != q.shape[1]:
        raise OnnxRewriteError("scales do not match the weight blocks")
    w = ((q - 128.0) * s[:, :, None]).reshape(N, -1)[:, :K]
    return np.ascontiguousarray(w.T)


def _rewrite_graph(graph: bytes):
    fields = _fields(graph)
    inits = {}
    for f, wt, v, _ in fields:
        if f == _GRAPH_INIT and wt == _LEN:
            name, arr = _tensor(v)
            inits[name] = arr
    new_fields, new_inits, replaced, used = [], [], 0, set()
    for f, wt, v, raw in fields:
        if f != _GRAPH_NODE or wt != _LEN:
            new_fields.append((f, v, raw))
            continue
        node = _node(v)
        if node["op"] != "MatMulNBits":
            used.update(node["input"])
            new_fields.append((f, v, raw))
            continue
        a = node["attr"]
        ins = node["input"]
        if a.get("bits") != 8 or (len(ins) > 3 and ins[3]) or (len(ins) > 4 and ins[4]):
            raise OnnxRewriteError(f"{node['name']}: only symmetric 8-bit blocks are rewritten")
        q, scales = inits.get(ins[1]), inits.get(ins[2])
        if q is None or scales is None:
            raise OnnxRewriteError(f"{node['name']}: weights are not initializers")
        w = dequantized_weight(q, scales, int(a["K"]), int(a["N"]), int(a["block_size"]))
        wname = ins[1] + "_float"
        new_inits.append(_len_field(_GRAPH_INIT, _float_tensor(wname, w)))
        out = node["output"][0]
        if len(ins) > 5 and ins[5]:  # a bias
            mid = out + "_mm"
            new_fields.append((f, None, _len_field(_GRAPH_NODE, _node_bytes("MatMul", [ins[0], wname], [mid],
                                                                             node["name"] + "_float"))))
            new_fields.append((f, None, _len_field(_GRAPH_NODE, _node_bytes("Add", [mid, ins[5]], [out],
                                                                             node["name"] + "_bias"))))
            used.add(ins[5])
        else:
            new_fields.append((f, None, _len_field(_GRAPH_NODE, _node_bytes("MatMul", [ins[0], wname], [out],
                                                                             node["name"] + "_float"))))
        used.add(ins[0])
        replaced += 1
    if not replaced:
        return None
    for f, wt, v, _ in fields:
        if f == _GRAPH_OUTPUT and wt == _LEN:  # (ValueInfoProto: name = 1)
            used.update(x.decode("utf-8") for xf, xwt, x, _ in _fields(v) if xf == 1 and xwt == _LEN)
    parts = []
    for f, v, raw in new_fields:
        if f == _GRAPH_INIT and v is not None and _tensor(v)[0] not in used:
            continue  # an 8-bit weight or its scales, read by nothing now
        parts.append(raw)
    return b"".join(parts + new_inits)


def float_compute(model: bytes) -> bytes:
    """The serialised ONNX ``model`` with every symmetric 8-bit ``MatMulNBits``
    replaced by a float32 ``MatMul`` (and ``Add`` for a bias) of its dequantized
    weights, the initializers no node reads any more dropped; the model as it
    was when it has none. :class:`OnnxRewriteError` when it cannot be parsed or
    holds a ``MatMulNBits`` of another kind."""
    fields = _fields(model)
    out, changed = [], False
    for f, wt, v, raw in fields:
        if f == _MODEL_GRAPH and wt == _LEN:
            g = _rewrite_graph(v)
            if g is not None:
                out.append(_len_field(_MODEL_GRAPH, g))
                changed = True
                continue
        out.append(raw)
    return b"".join(out) if changed else bytes(model)
