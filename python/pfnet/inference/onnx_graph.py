"""What a pfnet ONNX file is (its metadata's :data:`FORMAT` and :data:`VERSION`, the digest of
its source) and what an ONNX model file from elsewhere may do, checked before ONNX Runtime
loads it.

A pfnet export is a feed-forward graph of a few operators (:data:`ALLOWED_OPS`, those
torch's exporter writes for every registered model). A file that passes the signature check
can still hold any other graph: a forged 36 KB model with a ``Loop`` of trip count 2**62 made
``complete`` hang, one ``ConstantOfShape(4e8)`` allocated 1.7 GB (issue 36). So before a
session is made the graph is read (the protobuf wire format, read here: the light install
has ONNX Runtime but not the ``onnx`` package) and refused, naming the file, if it

* uses an operator outside :data:`ALLOWED_OPS` or another operator domain (control flow,
  ``ConstantOfShape``, ``Range``, ``Tile``, custom ops are none of them),
* holds a subgraph or a model-local function (where such operators would hide),
* or a constant (initializer or ``Constant``, or a ``Concat`` of them) of int64 values that,
  read as a shape, would make more than :data:`MAX_SHAPE_ELEMENTS` elements: what an
  ``Expand`` or ``Reshape`` could allocate from a constant.

This bounds what a file may make ORT do to the graphs pfnet writes; it is not a sandbox.
"""

from __future__ import annotations

import hashlib
import os
import struct
from pathlib import Path

from pfnet.errors import DataError

__all__ = [
    "ALLOWED_OPS",
    "FORMAT",
    "MAX_SHAPE_ELEMENTS",
    "VERSION",
    "check_graph",
    "file_sha256",
]

# The metadata of the ONNX files ``pfnet export`` writes (:mod:`pfnet.inference.onnx_export`).
FORMAT = "pfnet-onnx"
VERSION = "1"

ALLOWED_OPS = frozenset(
    {
        # what torch's dynamo exporter writes for pfnet, pfnet-vanilla, mr-cmlp, cmlp, mlp
        "Add", "Cast", "Concat", "Conv", "Div", "Expand", "GatherElements", "Gemm",
        "ReduceMax", "Relu", "Reshape", "Shape", "Slice", "Squeeze", "Transpose", "Unsqueeze",
        # and what other exporter versions write for the same layers
        "Constant", "Identity", "Mul", "Sub", "MatMul", "Flatten", "Gather", "Max",
        # pfnet-mirror's plane search: element-wise, reductions, and gathers and scatters
        # into tensors that already exist (it makes none from a shape: no ConstantOfShape)
        "Abs", "And", "ArgMax", "Floor", "GatherND", "GreaterOrEqual", "Less", "LessOrEqual",
        "Min", "ReduceMean", "ReduceMin", "ReduceSum", "ScatterElements", "Where",
        # pfnet-edge's edge score: the nearest neighbours (TopK's outputs are no larger than
        # its input, whatever K a file gives) and their distances
        "TopK", "Sqrt", "Clip", "ReduceL2",
    }
)  # fmt: skip
"""Operators a pfnet ONNX export may use (default domain)."""

MAX_SHAPE_ELEMENTS = 1 << 28
"""Elements a constant shape may describe (2**28 float32 are 1 GiB; a batch of 32 clouds of
50,000 points is 4.8 million values)."""

_INT64 = 7  # TensorProto.DataType.INT64
_MAX_GRAPH_BYTES = 1 << 30


def _fields(data: bytes, start: int = 0, end: int | None = None):
    """Yield ``(field number, wire type, value)``: an int, or ``(start, end)`` of a LEN."""
    pos, end = start, len(data) if end is None else end
    while pos < end:
        key, pos = _varint(data, pos)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _varint(data, pos)
        elif wire == 1:
            value, pos = struct.unpack_from("<Q", data, pos)[0], pos + 8
        elif wire == 2:
            length, pos = _varint(data, pos)
            value, pos = (pos, pos + length), pos + length
        elif wire == 5:
            value, pos = struct.unpack_from("<I", data, pos)[0], pos + 4
        else:
            raise ValueError(f"wire type {wire}")
        if pos > end:
            raise ValueError("a field runs past its message")
        yield number, wire, value


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if pos >= len(data) or shift > 63:
            raise ValueError("a truncated varint")
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, pos
        shift += 7


def _signed(value: int) -> int:
    return value - (1 << 64) if value >= 1 << 63 else value


def _int64_tensor(data: bytes, span: tuple[int, int]) -> list[int] | None:
    """The values of an int64 TensorProto (``None`` for another type)."""
    kind, values, raw = None, [], None
    for number, wire, value in _fields(data, *span):
        if number == 2 and wire == 0:
            kind = value
        elif number == 7 and wire == 2:  # packed int64_data
            pos = value[0]
            while pos < value[1]:
                item, pos = _varint(data, pos)
                values.append(_signed(item))
        elif number == 7 and wire == 0:
            values.append(_signed(value))
        elif number == 9 and wire == 2:
            raw = data[value[0] : value[1]]
    if kind != _INT64:
        return None
    if raw is not None:
        if len(raw) > 8 * 64:  # a weight, not a shape
            return None
        values = list(struct.unpack(f"<{len(raw) // 8}q", raw[: len(raw) // 8 * 8]))
    return values if len(values) <= 64 else None


def _text(data: bytes, span: tuple[int, int]) -> str:
    return data[span[0] : span[1]].decode("utf-8", errors="replace")


def _shape_elements(values: list[int]) -> int:
    total = 1
    for value in values:
        total *= max(value, 1)
    return total


def check_graph(path: str | os.PathLike[str]) -> None:
    """Refuse an ONNX file whose graph is not one a pfnet export could be (module doc).

    Raises:
        DataError: Naming the file and what is refused (the operator, the constant).
    """
    file = Path(path)
    try:
        if file.stat().st_size > _MAX_GRAPH_BYTES:
            raise DataError(f"ONNX model {file} is larger than {_MAX_GRAPH_BYTES} bytes")
        data = file.read_bytes()
    except OSError as err:
        raise DataError(f"ONNX model {file} cannot be read: {err.strerror or err}") from None
    try:
        _check_model(file, data)
    except DataError:  # a ValueError too
        raise
    except (ValueError, struct.error, IndexError):
        raise DataError(f"ONNX model {file} cannot be read: not an ONNX protobuf") from None


def _check_model(file: Path, data: bytes) -> None:
    graphs = []
    for number, wire, value in _fields(data):
        if number == 7 and wire == 2:
            graphs.append(value)
        elif number in (20, 25):  # training_info, functions
            raise DataError(
                f"ONNX model {file} defines functions or training steps; a pfnet export has none"
            )
    if len(graphs) != 1:
        raise DataError(f"ONNX model {file} holds {len(graphs)} graphs, not one")
    _check_graph(file, data, graphs[0])


def _check_graph(file: Path, data: bytes, span: tuple[int, int]) -> None:
    initializers, nodes = [], []
    for number, wire, value in _fields(data, *span):
        if number == 5 and wire == 2:
            initializers.append(value)
        elif number == 1 and wire == 2:
            nodes.append(_node(data, value))
    for op, domain, _, _, attributes in nodes:  # the operators first: the plainer refusal
        if domain not in ("", "ai.onnx") or op not in ALLOWED_OPS:
            shown = f"{domain}.{op}" if domain else op
            raise DataError(
                f"ONNX model {file} uses the operator {shown[:60]!r}, which no pfnet export "
                "does; pfnet runs only the graphs it exports (a model from elsewhere may "
                "loop or allocate without bound)"
            )
        for attribute in attributes:
            if any(number in (6, 11) for number, _, _ in _fields(data, *attribute)):
                raise DataError(f"ONNX model {file}: operator {op} holds a subgraph")
    constants: dict[str, list[int]] = {}
    for tensor in initializers:
        name = next((_text(data, v) for n, w, v in _fields(data, *tensor) if n == 8), "")
        _remember(file, constants, name, _int64_tensor(data, tensor))
    for op, _, inputs, outputs, attributes in nodes:  # in order: a Concat after its inputs
        if op == "Constant" and outputs:
            for attribute in attributes:
                for number, wire, value in _fields(data, *attribute):
                    if number == 5 and wire == 2:
                        _remember(file, constants, outputs[0], _int64_tensor(data, value))
        if op == "Concat" and inputs and all(name in constants for name in inputs) and outputs:
            joined = [v for name in inputs for v in constants[name]]
            _remember(file, constants, outputs[0], joined if len(joined) <= 64 else None)


def _node(data: bytes, span: tuple[int, int]):
    """``(op_type, domain, inputs, outputs, attribute spans)`` of a NodeProto."""
    op, domain, inputs, outputs, attributes = "", "", [], [], []
    for number, wire, value in _fields(data, *span):
        if wire != 2:
            continue
        if number == 4:
            op = _text(data, value)
        elif number == 7:
            domain = _text(data, value)
        elif number == 1:
            inputs.append(_text(data, value))
        elif number == 2:
            outputs.append(_text(data, value))
        elif number == 5:
            attributes.append(value)
    return op, domain, inputs, outputs, attributes


def _remember(file: Path, constants: dict, name: str, values: list[int] | None) -> None:
    if values is None:
        return
    if _shape_elements(values) > MAX_SHAPE_ELEMENTS:
        raise DataError(
            f"ONNX model {file}: the constant {name[:60]!r} {values[:8]} would, as a shape, "
            f"make {_shape_elements(values):,} elements (at most {MAX_SHAPE_ELEMENTS:,})"
        )
    constants[name] = values


def file_sha256(path: str | os.PathLike[str]) -> str:
    """The hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
