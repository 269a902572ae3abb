"""Result values as table text, tables and strict JSON: the one writer of the
harness's numbers, used by the report pages (:mod:`hlbvh.comparison.report`) and the
README's figures (:mod:`hlbvh.comparison.readme_figures`).

- :func:`flatten`: nested rows to one level with dotted keys (``build_ms.native``);
- :func:`format_value`: one value as the text a table shows;
- :func:`column_title`: the readable header of a key (the JSON and CSV keep the keys);
- :func:`markdown_table`: rows as a Markdown table;
- :func:`to_json` / :func:`read_results`: strict JSON (a browser parses it): the
  non-finite floats a comparison can produce (a PSNR of ``inf`` for identical images)
  are written as the strings ``"inf"``, ``"-inf"`` and ``"nan"`` and read back as floats.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

_NONFINITE_STRINGS = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}

#: Headers of the keys whose readable name is not their words (:func:`column_title`).
COLUMN_TITLES = {
    "decision": "our update",
    "build_speedup": "build speedup (native / ours)",
    "sah_cost": "SAH cost",
    "build_cold_ms": "first build [ms]",
    "mrays_primary": "primary rays [M/s]",
    "mrays_secondary": "secondary rays [M/s]",
    "image.max_abs_diff": "largest pixel difference",
    "image.mean_abs_diff": "mean pixel difference",
    "image.fraction_identical": "pixels bit-identical",
    "image.fraction_within_tolerance": "pixels within tolerance",
    "image.psnr_db": "PSNR [dB]",
    "image.nonfinite_mismatch_pixels": "pixels NaN/inf in one render only",
    "noise.passed": "within noise",
    "noise.largest_z": "largest block z",
    "noise.largest_z_block": "its block",
    "noise.image_z": "whole-image z",
    "noise.blocks_over_limit": "blocks over the limit",
    "noise.nonfinite_pixels": "pixels NaN/inf in hlbvh's alone",
    "noise.noise_rms": "native's noise [rms]",
    "noise.seed": "noise render's seed",
    "hits.fraction_agree": "camera hits agree",
    "hits.fraction_shape_agree": "camera hits on the same shape",
    "hits.differ_pixels": "pixels hitting another primitive",
}


def format_value(value, digits: int = 6) -> str:
    """The table text of one result value.

    Integers and strings as they are; floats with ``digits`` significant digits (six
    by default; a page for people passes fewer), but never
    rounded to a whole number they are not (``0.9999995`` stays ``0.9999995``, not
    ``1``), so a fraction just below one cannot read as "all"; non-finite floats as
    ``inf``, ``-inf``, ``nan``; ``None`` as ``-``; booleans as ``yes``/``no``; lists
    element by element.
    """
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
        text = f"{value:.{digits}g}"
        while float(text) != value and float(text) == round(float(text)) and digits < 17:
            digits += 1
            text = f"{value:.{digits}g}"
        return text
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(format_value(item, digits) for item in value) + "]"
    return str(value)


def column_title(key: str) -> str:
    """The header a table shows for a row key: :data:`COLUMN_TITLES`, else the key's
    words (``build_ms.native`` -> ``build, native [ms]``, ``frame_ms_spp16`` ->
    ``frame at 16 spp [ms]``, ``hits.differ_pixels`` -> ``hits: differ pixels``)."""
    if key in COLUMN_TITLES:
        return COLUMN_TITLES[key]
    head, _, rest = key.partition(".")
    unit = ""
    at = re.fullmatch(r"(\w+)_ms_spp(\d+)", head)
    if at:
        head, unit = f"{at.group(1)} at {at.group(2)} spp", " [ms]"
    elif head.endswith("_ms"):
        head, unit = head[:-3], " [ms]"
    words = head.replace("_", " ")
    if rest:
        words += (", " if unit else ": ") + rest.replace("_", " ").replace(".", " ")
    return words + unit


def markdown_table(rows: Sequence[Mapping], columns: Sequence[str] | None = None,
                   digits: int = 6) -> str:
    """A Markdown table of flat ``rows`` (``columns``: their keys, by default every key
    in order of first appearance), headed by :func:`column_title`, cells by
    :func:`format_value` with ``digits`` significant digits."""
    columns = column_keys(rows) if columns is None else list(columns)
    lines = ["| " + " | ".join(_md_escape(column_title(c)) for c in columns) + " |",
             "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(_md_escape(format_value(row.get(c), digits)) for c in columns)
              + " |"
              for row in rows]
    return "\n".join(lines)


def read_results(path) -> dict:
    """``results.json`` back as Python values, the strings ``"inf"``, ``"-inf"`` and
    ``"nan"`` turned back into floats."""
    return _from_json(json.loads(Path(path).read_text()))


def flatten(row: Mapping, prefix: str = "") -> dict:
    """Nested dicts -> one level with dotted keys (``{"a": {"b": 1}}`` -> ``{"a.b":
    1}``); numpy scalars and paths -> Python values."""
    flat = {}
    for key, value in row.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten(value, f"{name}."))
        else:
            flat[name] = _plain(value)
    return flat


def _plain(value):
    if hasattr(value, "item") and getattr(value, "ndim", None) == 0:
        return value.item()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, (list, tuple)) or hasattr(value, "tolist"):
        return [_plain(item) for item in (value.tolist() if hasattr(value, "tolist") else value)]
    return value


def column_keys(rows: Sequence[Mapping]) -> list[str]:
    """Every key of ``rows``, in order of first appearance."""
    return list(dict.fromkeys(key for row in rows for key in row))


def is_number(value) -> bool:
    """An int or float, not a bool."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def csv_value(value):
    """A value as a CSV cell: exact floats (``repr``), lists as JSON, ``None`` empty."""
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list):
        return json.dumps(to_json(value))
    return value


def to_json(value):
    """``value`` as strict JSON values: non-finite floats as the strings ``"inf"``,
    ``"-inf"``, ``"nan"`` (:func:`read_results` reads them back), tuples as lists."""
    if isinstance(value, float) and not math.isfinite(value):
        return format_value(value)
    if isinstance(value, Mapping):
        return {str(key): to_json(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(item) for item in value]
    return value


def _from_json(value):
    if isinstance(value, str) and value in _NONFINITE_STRINGS:
        return _NONFINITE_STRINGS[value]
    if isinstance(value, dict):
        return {key: _from_json(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_from_json(item) for item in value]
    return value
