"""A small, strict reader and writer for binary PLY containers.

Splat files are binary PLYs with fixed-size scalar properties, so each element is one numpy
structured array read with ``np.frombuffer``. Everything malformed (bad header, unknown types,
list properties, short data) becomes an :class:`InputError` with one clear message.
The INRIA and SuperSplat layouts are interpreted on top of this in ``ply.py`` and
``compressed_ply.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import BinaryIO

import numpy as np

from virgi_ns.errors import InputError

# PLY scalar type names (both spellings) -> numpy type code without byte order.
PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}
_WRITE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
                "f4": "float", "f8": "double"}
MAX_HEADER_BYTES = 1 << 20


@dataclass
class PlyElement:
    name: str
    count: int
    props: list[tuple[str, str]] = field(default_factory=list)  # (name, numpy code without byte order)
    data: np.ndarray | None = None

    def dtype(self, byteorder: str) -> np.dtype:
        return np.dtype([(n, byteorder + t) for n, t in self.props])

    @property
    def names(self) -> list[str]:
        return [n for n, _ in self.props]


@dataclass
class PlyData:
    elements: list[PlyElement]
    comments: list[str]

    def get(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)


def is_ply(head: bytes) -> bool:
    return head.startswith(b"ply\n") or head.startswith(b"ply\r\n")


def parse_header(buf: bytes, where: str = "file") -> tuple[list[PlyElement], list[str], str, int]:
    """Parse the header; returns (elements, comments, numpy byte order, offset of the body)."""
    if not buf:
        raise InputError(f"{where} is empty")
    if not is_ply(buf[:5]):
        raise InputError(f"{where} is not a PLY file (it does not start with 'ply')")
    end = buf.find(b"end_header", 0, MAX_HEADER_BYTES)
    if end < 0:
        raise InputError(f"{where}: PLY header has no 'end_header' line (truncated or not a PLY)")
    nl = buf.find(b"\n", end)
    if nl < 0 or buf[end:nl].strip(b"\r ") != b"end_header":
        raise InputError(f"{where}: PLY header ends without a newline after 'end_header' (truncated)")
    try:
        text = buf[:end].decode("ascii")
    except UnicodeDecodeError:
        raise InputError(f"{where}: PLY header holds non-ASCII bytes (corrupt file)") from None

    elements: list[PlyElement] = []
    comments: list[str] = []
    fmt = None
    for lineno, raw in enumerate(text.splitlines()[1:], start=2):
        words = raw.split()
        if not words or words[0] in ("obj_info",):
            continue
        key = words[0]
        if key == "comment":
            comments.append(raw.strip()[len("comment"):].strip())
        elif key == "format":
            if len(words) != 3:
                raise InputError(f"{where}: malformed PLY format line {lineno}: {raw.strip()!r}")
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise InputError(f"{where}: malformed PLY element line {lineno}: {raw.strip()!r}")
            elements.append(PlyElement(words[1], int(words[2])))
        elif key == "property":
            if not elements:
                raise InputError(f"{where}: PLY property before any element on line {lineno}")
            if len(words) >= 2 and words[1] == "list":
                raise InputError(
                    f"{where}: PLY element '{elements[-1].name}' has a list property, which splat files never hold"
                )
            if len(words) != 3:
                raise InputError(f"{where}: malformed PLY property line {lineno}: {raw.strip()!r}")
            if words[1] not in PLY_TYPES:
                raise InputError(f"{where}: unknown PLY property type '{words[1]}' for '{words[2]}' (line {lineno})")
            if words[2] in elements[-1].names:
                raise InputError(f"{where}: PLY property '{words[2]}' appears twice in element '{elements[-1].name}'")
            elements[-1].props.append((words[2], PLY_TYPES[words[1]]))
        else:
            raise InputError(f"{where}: unknown PLY header keyword '{key}' on line {lineno}")
    if fmt is None:
        raise InputError(f"{where}: PLY header has no format line")
    if fmt == "ascii":
        raise InputError(f"{where}: ASCII PLY is not supported; splat files are binary_little_endian")
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise InputError(f"{where}: unknown PLY format '{fmt}'")
    for e in elements:
        if e.count > 0 and not e.props:
            raise InputError(f"{where}: PLY element '{e.name}' has {e.count} rows but no properties")
    return elements, comments, ("<" if fmt == "binary_little_endian" else ">"), nl + 1


def read_ply_bytes(buf: bytes, where: str = "file") -> PlyData:
    """Parse a whole binary PLY held in memory."""
    elements, comments, order, offset = parse_header(buf, where)
    for e in elements:
        dt = e.dtype(order)
        need = dt.itemsize * e.count
        if offset + need > len(buf):
            have = max(0, (len(buf) - offset) // max(dt.itemsize, 1))
            raise InputError(
                f"{where} is truncated: element '{e.name}' declares {e.count:,} rows but the file holds {have:,}"
            )
        e.data = np.frombuffer(buf, dtype=dt, count=e.count, offset=offset)
        offset += need
    if offset != len(buf):
        raise InputError(f"{where}: {len(buf) - offset:,} unexpected bytes after the last PLY element (corrupt header?)")
    return PlyData(elements, comments)


def _ply_parts(elements: list[tuple[str, np.ndarray]], comments: tuple[str, ...]) -> tuple[bytes, list[np.ndarray]]:
    """The header of binary little-endian PLY for structured arrays (one per element) and the arrays
    in little-endian, contiguous form, in the file's order."""
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comments]
    parts: list[np.ndarray] = []
    for name, arr in elements:
        lines.append(f"element {name} {len(arr)}")
        le = []
        for prop in arr.dtype.names:
            code = arr.dtype[prop].base.str[1:]
            lines.append(f"property {_WRITE_NAMES[code]} {prop}")
            le.append((prop, "<" + code))
        parts.append(np.ascontiguousarray(arr.astype(np.dtype(le), copy=False)))
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii"), parts


def ply_bytes(elements: list[tuple[str, np.ndarray]], comments: tuple[str, ...] = ()) -> bytes:
    """Serialise structured arrays (one per element) as binary little-endian PLY."""
    header, parts = _ply_parts(elements, comments)
    return header + b"".join(p.tobytes() for p in parts)


def write_ply(f: BinaryIO, elements: list[tuple[str, np.ndarray]], comments: tuple[str, ...] = ()) -> None:
    """Write what :func:`ply_bytes` returns to the open binary file ``f``, without first copying the
    arrays into one byte string (a large splat's table is written as it is held)."""
    header, parts = _ply_parts(elements, comments)
    f.write(header)
    for p in parts:
        f.write(p.reshape(-1).view(np.uint8).data)  # its bytes, whatever its fields are named
