"""The opset_import of an ONNX file, read from its protobuf without the onnx package (not a runtime dependency).

The loader checks each graph's declared opset against the manifest before onnxruntime sees the file.
"""

from __future__ import annotations

from pathlib import Path


def onnx_opsets(path: Path) -> dict[str, int]:
    """domain -> version; ValueError on a file that is not a well-formed ONNX protobuf."""
    buf = memoryview(path.read_bytes())

    def varint(i: int) -> tuple[int, int]:
        shift = value = 0
        while True:
            if i >= len(buf):
                raise ValueError(f"{path.name}: truncated ONNX file")
            b = buf[i]
            value |= (b & 0x7F) << shift
            i, shift = i + 1, shift + 7
            if not b & 0x80:
                return value, i

    def fields(lo: int, hi: int):
        i = lo
        while i < hi:
            tag, i = varint(i)
            field, wire = tag >> 3, tag & 7
            if wire == 0:
                value, i = varint(i)
                yield field, value
            elif wire == 2:
                n, i = varint(i)
                yield field, (i, i + n)
                i += n
            elif wire in (1, 5):
                i += 8 if wire == 1 else 4
            else:
                raise ValueError(f"{path.name}: not an ONNX model (protobuf wire type {wire})")
        if i != hi:
            raise ValueError(f"{path.name}: truncated ONNX file")

    out = {}
    for field, value in fields(0, len(buf)):
        if field == 8:  # ModelProto.opset_import: OperatorSetIdProto {1: domain, 2: version}
            domain, version = "", None
            for f, v in fields(*value):
                if f == 1:
                    domain = bytes(buf[v[0]:v[1]]).decode()
                elif f == 2:
                    version = v
            out[domain or "ai.onnx"] = version
    return out
