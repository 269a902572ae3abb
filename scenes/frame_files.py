"""The files of a frames directory as :class:`hlbvh.scenes.SequenceScene` reads them:
which entries are frame files, why an entry is not a readable file, and the check
Mitsuba's PLY loader does not make (a negative vertex index, which it reads as another
vertex)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

#: What a frame file is called: ``frame_<number>.<ply|obj>``, any zero padding.
FRAME_FILE = re.compile(r"^frame_(\d+)\.(ply|obj)$", re.IGNORECASE)


def entries(directory: Path) -> list[Path]:
    """The entries of a frames directory, sorted.

    Raises:
        ValueError: naming the directory, when it cannot be listed (no permission).
    """
    try:
        return sorted(directory.iterdir())
    except OSError as error:
        raise ValueError(f"frames directory {str(directory)!r}: cannot be listed "
                         f"({error.strerror})") from None


def not_a_file(path: Path) -> str:
    """Why an entry named like a frame file is not a regular file, in words."""
    if path.is_symlink():
        try:
            path.stat()
        except OSError as error:
            return f"a symbolic link that leads to no file ({error.strerror})"
    return "a directory" if path.is_dir() else "not a regular file"


#: numpy types of PLY's scalar types.
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
              "double": "f8", "float64": "f8"}


def ply_negative_index(path: Path) -> tuple[int, int] | None:
    """``(face, index)`` of the first negative vertex index in a PLY file's faces, or
    ``None``. Mitsuba's loader reads such an index as another vertex without a word, so
    it is looked for before the file reaches Mitsuba. Indices of an unsigned type
    cannot be negative and are not read; a header this does not follow is left to
    Mitsuba."""
    data = path.read_bytes()
    end = data.find(b"end_header")
    if end < 0:
        return None
    body = data[data.index(b"\n", end) + 1:]
    form, elements = None, []
    for line in data[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if words[:1] == ["format"] and len(words) > 1:
            form = words[1]
        elif words[:1] == ["element"] and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[:1] == ["property"] and elements:
            elements[-1][2].append(words[1:])
    faces = [e for e in elements if e[0] == "face"]
    if form is None or not faces:
        return None
    index_type = next((p[2] for p in faces[0][2] if p[0] == "list" and len(p) == 4), None)
    if index_type is None or _PLY_TYPES.get(index_type, "u")[0] == "u":
        return None
    try:
        return _ply_first_negative(body, form, elements)
    except (ValueError, IndexError, KeyError):
        return None


def _ply_first_negative(body: bytes, form: str, elements) -> tuple[int, int] | None:
    """``(face, index)`` of the first negative index of a PLY body whose faces hold
    only their vertex-index list, the elements before them skipped (raises
    ``ValueError`` for a layout it does not follow). Binary faces that all have as many
    corners as the first are read as one numpy table, others face by face."""
    if form == "ascii":
        lines = body.split(b"\n")
        start = 0
        for name, count, properties in elements:
            if name == "face":
                (_,) = properties
                chosen = lines[start:start + count]
                if b"-" not in b" ".join(chosen):
                    return None
                for k, line in enumerate(chosen):
                    negative = [int(v) for v in line.split()[1:] if int(v) < 0]
                    if negative:
                        return k, negative[0]
                return None
            start += count
        return None
    order = "<" if form == "binary_little_endian" else ">"
    offset = 0
    for name, count, properties in elements:
        if name == "face":
            ((_, count_type, index_type, _),) = properties
            count_dtype = np.dtype(order + _PLY_TYPES[count_type])
            index_dtype = np.dtype(order + _PLY_TYPES[index_type])
            corners = int(np.frombuffer(body, count_dtype, 1, offset)[0])
            row = np.dtype([("n", count_dtype), ("i", index_dtype, (corners,))])
            if count and len(body) - offset >= count * row.itemsize:
                table = np.frombuffer(body, row, count, offset)
                if (table["n"] == corners).all():
                    bad = np.flatnonzero((table["i"] < 0).any(axis=1))
                    if not len(bad):
                        return None
                    indices = table["i"][bad[0]]
                    return int(bad[0]), int(indices[indices < 0][0])
            for k in range(count):
                corners = int(np.frombuffer(body, count_dtype, 1, offset)[0])
                offset += count_dtype.itemsize
                indices = np.frombuffer(body, index_dtype, corners, offset)
                offset += corners * index_dtype.itemsize
                if (indices < 0).any():
                    return k, int(indices[indices < 0][0])
            return None
        if any(p[0] == "list" for p in properties):
            raise ValueError("a list property before the faces")
        offset += count * sum(np.dtype(_PLY_TYPES[p[0]]).itemsize for p in properties)
    return None
