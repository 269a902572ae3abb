"""Report directories: the numbers of a comparison or a sweep as tables (Markdown and
HTML), the images side by side, the plots, and the raw numbers as JSON and CSV.

Every report directory holds ``report.md``, ``report.html``, ``results.json`` and
``results.csv``. A comparison's page leads with its verdict (a paragraph the caller
writes), then the plots, then each frame's images (the difference map's scale written
beside it), then the tables. Tables and JSON are written by
:mod:`hlbvh.comparison.tables` from exactly the rows written to ``results.json``, so a
number on the page is the JSON number, shortened; columns are the rows' keys in order of
first appearance: a new statistic shows up without touching this module.

Links in the HTML and Markdown are relative and percent-encoded; images and plots
outside the report directory are copied into it (``images/``, ``plots/``), so the
directory can be moved or archived whole and still opens from ``file://``.
``results.json`` holds the same links as plain relative paths.
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
import os
import shutil
import urllib.parse
from collections.abc import Mapping, Sequence
from pathlib import Path

from hlbvh.comparison.tables import (column_keys, column_title, csv_value, flatten, format_value,
                                    is_number, markdown_table, to_json)
from hlbvh.render.images import atomic_output

#: Image formats a browser shows; EXR is not one of them.
BROWSER_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".gif", ".webp", ".svg")

#: Captions of the per-frame images, in the order they are shown; other roles follow.
IMAGE_ROLES = {"native": "native", "hlbvh": "hlbvh (ours)", "diff": "difference"}

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em; color: #222; }
.scroll { overflow-x: auto; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr.winner td { background: #e6f4e6; font-weight: bold; }
.images { display: flex; gap: 1em; flex-wrap: wrap; }
.images figure { margin: 0; max-width: 320px; }
.images img { width: 320px; image-rendering: pixelated; border: 1px solid #ccc; }
img.plot { max-width: 100%; }
p.warning { color: #a00; }
"""


def winner(rows: Sequence[Mapping], objective: str = "frame_ms") -> Mapping:
    """The row with the smallest finite ``objective`` (the first such row on ties).

    Raises:
        ValueError: no row has a finite number under ``objective``.
    """
    candidates = [
        row for row in rows
        if isinstance(row.get(objective), (int, float)) and math.isfinite(row[objective])
    ]
    if not candidates:
        raise ValueError(
            f"objective={objective!r}: no row has a finite number under that key; "
            f"the rows have keys {column_keys(rows)}"
        )
    return min(candidates, key=lambda row: row[objective])


def write_report(
    out_dir,
    title: str,
    frames: Sequence[Mapping],
    images: Mapping[int, Mapping[str, os.PathLike | str]],
    settings: Mapping,
    plots: Sequence[os.PathLike | str] = (),
    verdict: str | None = None,
    captions: Mapping[str, str] | None = None,
) -> dict[str, Path]:
    """Write the report of a native-vs-hlbvh comparison of an animation: the verdict,
    the plots, the images per frame, then the settings and per-frame tables.

    Args:
        out_dir: the report directory (created if needed).
        title: the page title.
        frames: one dict per frame with at least ``"frame"`` (its number) and any other
            numbers (image metrics, build and render ms, SAH cost ...); nested dicts are
            flattened to dotted keys. Rows with ``nonfinite_mismatch_pixels`` > 0 (at
            any depth, e.g. ``image.nonfinite_mismatch_pixels``) are called out on the
            page.
        images: frame number -> ``{"native": png, "hlbvh": png, "diff": png}`` (further
            roles are shown after these), paths to images a browser shows.
        settings: what was run (scene, resolution, spp, integrator, builder options ...).
        plots: PNG plots, shown after the verdict.
        verdict: the paragraph the page opens with (``None``: none).
        captions: per image role, the caption under it (default :data:`IMAGE_ROLES`;
            e.g. the difference map's scale).

    Returns:
        ``{"md": ..., "html": ..., "json": ..., "csv": ...}``: the files written.

    Raises:
        ValueError: a frame without ``"frame"``, images of a frame not in ``frames``, or
            an image or plot that is missing or not a browser image format.
    """
    out_dir = Path(out_dir)
    rows = [flatten(row) for row in frames]
    frame_numbers = [row.get("frame") for row in rows]
    if None in frame_numbers:
        raise ValueError("frames: every row needs a 'frame' key with the frame number")
    unknown = sorted(set(images) - set(frame_numbers), key=str)
    if unknown:
        raise ValueError(f"images: frame(s) {unknown} have images but no row in frames")
    links = {
        frame: {
            role: _local_link(out_dir, path, f"images/frame_{frame}_{role}")
            for role, path in _ordered_roles(roles)
        }
        for frame, roles in images.items()
    }
    plot_links = _plot_links(out_dir, plots)

    page = _Page(title)
    if verdict:
        page.paragraph(verdict, strong=True)
    flagged = [row["frame"] for row in rows if _nonfinite_mismatch(row)]
    if flagged:
        page.warning(
            f"Frames {', '.join(map(format_value, flagged))} have pixels that are NaN or "
            "infinite in one render and not the other (nonfinite_mismatch_pixels); their "
            "differences and PSNR cover the finite pixels only."
        )
    page.plots(plot_links)
    for frame in frame_numbers:
        if frame in links:
            page.images(f"Frame {format_value(frame)}", links[frame], captions)
    page.table("Settings", _setting_rows(settings))
    page.table("Frames", rows)
    results = {
        "kind": "compare",
        "title": title,
        "settings": dict(flatten(settings)),
        "rows": rows,
        "images": {str(frame): roles for frame, roles in links.items()},
        "plots": plot_links,
    }
    return _write_files(out_dir, page, results)


def write_sweep_report(
    out_dir,
    title: str,
    rows: Sequence[Mapping],
    settings: Mapping,
    plots: Sequence[os.PathLike | str] = (),
    objective: str = "frame_ms",
    label: str = "setting",
    lead: str | None = None,
    digits: int = 4,
) -> dict[str, Path]:
    """Write the report of a sweep over builder settings and name the winner.

    Args:
        out_dir: the report directory (created if needed).
        title: the page title.
        rows: one dict per setting, with a ``label`` key naming it and its numbers
            (e.g. ``build_ms``, ``sah_cost``, ``mrays_per_s``, ``frame_ms``,
            ``max_abs_diff``); a row for native may be among them.
        settings: what is fixed across the rows (scene, spp, resolution ...).
        plots: PNG plots to show under the table.
        objective: the key minimised to pick the winner (the fastest setting per frame
            by default).
        label: the key that names a row's setting.
        lead: the page's first sentence, for a person (by default it names the
            winner by ``objective``).
        digits: significant digits of the page's table cells (the JSON and CSV keep
            every digit).

    Returns:
        ``{"md": ..., "html": ..., "json": ..., "csv": ...}``; ``results.json`` also
        holds ``"winner": {"label": ..., "objective": ..., "value": ...}``.

    Raises:
        ValueError: a row without ``label``, no row with a finite ``objective``, or a
            plot that is missing or not a browser image format.
    """
    out_dir = Path(out_dir)
    flat = [flatten(row) for row in rows]
    if any(label not in row for row in flat):
        raise ValueError(f"rows: every row needs a {label!r} key naming its setting")
    best = winner(flat, objective)
    plot_links = _plot_links(out_dir, plots)

    page = _Page(title)
    page.paragraph(lead or (f"Fastest by {objective}: {format_value(best[label])} "
                            f"({objective} = {format_value(best[objective], digits)})"),
                   strong=True)
    page.plots(plot_links)
    page.table("Sweep", flat, highlight=flat.index(best), digits=digits)
    page.table("Settings", _setting_rows(settings))
    results = {
        "kind": "sweep",
        "title": title,
        "settings": dict(flatten(settings)),
        "rows": flat,
        "winner": {"label": best[label], "objective": objective, "value": best[objective]},
        "plots": plot_links,
    }
    return _write_files(out_dir, page, results)


# ---- The page: Markdown and HTML built side by side ----


class _Page:
    """A report page built once and rendered twice: Markdown and HTML parts appended
    together, so both always show the same content."""

    def __init__(self, title: str):
        self.markdown = [f"# {title}\n"]
        self.html = [f"<h1>{html.escape(title)}</h1>"]
        self.title = title

    def paragraph(self, text: str, strong: bool = False) -> None:
        self.markdown.append(f"**{text}**\n" if strong else f"{text}\n")
        body = f"<strong>{html.escape(text)}</strong>" if strong else html.escape(text)
        self.html.append(f"<p>{body}</p>")

    def warning(self, text: str) -> None:
        self.markdown.append(f"> **Warning:** {text}\n")
        self.html.append(f'<p class="warning">Warning: {html.escape(text)}</p>')

    def table(self, heading: str, rows: Sequence[Mapping], highlight: int | None = None,
              digits: int = 6) -> None:
        columns = column_keys(rows)
        self.markdown.append(f"## {heading}\n")
        self.html.append(f"<h2>{html.escape(heading)}</h2>")
        if not rows:
            self.paragraph("(none)")
            return
        cells = [[format_value(row.get(column), digits) for column in columns] for row in rows]
        self.markdown.append(markdown_table(rows, columns, digits) + "\n")
        body = []
        for index, (row, line) in enumerate(zip(rows, cells)):
            tds = "".join(
                f'<td class="num">{html.escape(text)}</td>'
                if is_number(row.get(column))
                else f"<td>{html.escape(text)}</td>"
                for column, text in zip(columns, line)
            )
            body.append(f'<tr class="winner">{tds}</tr>' if index == highlight else f"<tr>{tds}</tr>")
        head = "".join(f"<th>{html.escape(column_title(column))}</th>" for column in columns)
        self.html.append(
            f'<div class="scroll"><table><thead><tr>{head}</tr></thead>'
            f"<tbody>{''.join(body)}</tbody></table></div>"
        )

    def images(self, heading: str, links: Mapping[str, str],
               named: Mapping[str, str] | None = None) -> None:
        names = {**IMAGE_ROLES, **(named or {})}
        captions = [names.get(role, role) for role in links]
        self.markdown.append(f"### {heading}\n")
        self.markdown.append(
            "| " + " | ".join(captions) + " |\n|" + "|".join("---" for _ in links) + "|\n| "
            + " | ".join(f"![{caption}]({_url(link)})"
                         for caption, link in zip(captions, links.values()))
            + " |\n"
        )
        figures = "".join(
            f'<figure><img src="{html.escape(_url(link))}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>"
            for caption, link in zip(captions, links.values())
        )
        self.html.append(f'<h3>{html.escape(heading)}</h3><div class="images">{figures}</div>')

    def plots(self, links: Sequence[str]) -> None:
        if not links:
            return
        self.markdown.append("## Plots\n")
        self.html.append("<h2>Plots</h2>")
        for link in links:
            self.markdown.append(f"![{Path(link).stem}]({_url(link)})\n")
            self.html.append(
                f'<p><img class="plot" src="{html.escape(_url(link))}" '
                f'alt="{html.escape(Path(link).stem)}"></p>'
            )

    def render_html(self) -> str:
        return (
            '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f"<title>{html.escape(self.title)}</title><style>{_CSS}</style></head>\n<body>\n"
            + "\n".join(self.html)
            + "\n</body></html>\n"
        )


# ---- Files ----


def _write_files(out_dir: Path, page: _Page, results: dict) -> dict[str, Path]:
    """Write report.md, report.html, results.json and results.csv atomically."""
    columns = column_keys(results["rows"])
    table = io.StringIO()
    writer = csv.writer(table, lineterminator="\n")
    writer.writerow(columns)
    for row in results["rows"]:
        writer.writerow([csv_value(row.get(column)) for column in columns])
    texts = {
        "md": ("report.md", "\n".join(page.markdown)),
        "html": ("report.html", page.render_html()),
        "json": ("results.json", json.dumps(to_json(results), indent=2, allow_nan=False) + "\n"),
        "csv": ("results.csv", table.getvalue()),
    }
    written = {}
    for key, (name, text) in texts.items():
        with atomic_output(out_dir / name) as temporary:
            temporary.write_text(text, encoding="utf-8")
        written[key] = out_dir / name
    return written


def _local_link(out_dir: Path, path, copy_stem: str) -> str:
    """A relative link from ``out_dir`` to ``path``; a file outside ``out_dir`` is first
    copied to ``out_dir / (copy_stem + suffix)``."""
    source = Path(path)
    if source.suffix.lower() not in BROWSER_IMAGE_SUFFIXES:
        raise ValueError(
            f"{source}: a browser cannot show {source.suffix or 'this'} files; pass the PNG "
            f"(one of {BROWSER_IMAGE_SUFFIXES})"
        )
    if not source.is_file():
        raise ValueError(f"{source}: no such image file; write it before the report")
    root = out_dir.resolve()
    resolved = source.resolve()
    if not resolved.is_relative_to(root):
        target = root / f"{copy_stem}{source.suffix.lower()}"
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(target) as temporary:
            shutil.copyfile(resolved, temporary)
        resolved = target
    return resolved.relative_to(root).as_posix()


def _url(link: str) -> str:
    """A relative file path as a link target: percent-encoded, so that a space, ``#``,
    ``%``, ``?`` or a parenthesis in a folder name neither breaks the Markdown link nor
    makes the browser read a fragment or an escape."""
    return urllib.parse.quote(link)


def _plot_links(out_dir: Path, plots: Sequence) -> list[str]:
    return [_local_link(out_dir, plot, f"plots/{index}_{Path(plot).stem}") for index, plot in enumerate(plots)]


def _ordered_roles(roles: Mapping) -> list[tuple[str, object]]:
    """Per-frame images: native, hlbvh, diff first, then any other roles as given."""
    known = [(role, roles[role]) for role in IMAGE_ROLES if role in roles]
    return known + [(role, path) for role, path in roles.items() if role not in IMAGE_ROLES]


def _nonfinite_mismatch(row: Mapping) -> bool:
    """Whether a flattened row counts pixels non-finite in one render only."""
    return any(
        (key == "nonfinite_mismatch_pixels" or key.endswith(".nonfinite_mismatch_pixels"))
        and is_number(value) and value > 0
        for key, value in row.items()
    )


def _setting_rows(settings: Mapping) -> list[dict]:
    return [{"setting": key, "value": value} for key, value in flatten(settings).items()]
