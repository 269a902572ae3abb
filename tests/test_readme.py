"""README.md, run as written: every fenced ``python`` block executes in a fresh namespace
(a reader copies one block at a time), and every ``hlbvh`` command line it shows is one
command that the command line's parser takes.

A block may leave to the reader only what it marks as a placeholder, a line of the
form ``NAME = ...  # what the reader supplies``; this test gives such a name a small
value of its own (:data:`PLACEHOLDERS`). Any other ``...`` in a block, or a name no
line defines, fails the block."""

import ast
import re
import shlex
from pathlib import Path

import pytest

import hlbvh  # noqa: F401  (the variant, before a block's own import)
from hlbvh.cli.command import _parser

README = Path(__file__).resolve().parents[1] / "README.md"

#: The values this test gives the placeholders README's blocks mark, by name: small
#: stand-ins for what a reader supplies.
PLACEHOLDERS: dict[str, str] = {}

#: A placeholder line: ``NAME = ...`` followed by a comment saying what goes there.
_PLACEHOLDER = re.compile(r"^\s*(\w+) = \.\.\.\s+#\s*\S")


def fenced_blocks(text: str, language: str) -> list[tuple[int, str]]:
    """``(first line number, source)`` of every fenced block of ``language``."""
    blocks, lines = [], text.splitlines()
    inside = None
    for number, line in enumerate(lines, 1):
        if inside is None and line.strip() == f"```{language}":
            inside, start = [], number + 1
        elif inside is not None and line.strip() == "```":
            blocks.append((start, "\n".join(inside) + "\n"))
            inside = None
        elif inside is not None:
            inside.append(line)
    return blocks


def with_placeholders(source: str, where: str) -> str:
    """``source`` with each marked placeholder given its value from
    :data:`PLACEHOLDERS`; fails on an unmarked ``...`` or a placeholder this test has no
    value for."""
    lines = source.splitlines()
    for number, line in enumerate(lines):
        marked = _PLACEHOLDER.match(line)
        if marked:
            name = marked.group(1)
            assert name in PLACEHOLDERS, f"{where}: placeholder {name!r} has no test value"
            lines[number] = f"{name} = {PLACEHOLDERS[name]}"
    source = "\n".join(lines) + "\n"
    left = [node.lineno for node in ast.walk(ast.parse(source))
            if isinstance(node, ast.Constant) and node.value is Ellipsis]
    assert not left, f"{where}: '...' not marked as a placeholder on block line(s) {left}"
    return source


BLOCKS = fenced_blocks(README.read_text(), "python")


def test01_readme_has_python_blocks():
    assert len(BLOCKS) >= 4, "README's Python examples were not found"


@pytest.mark.parametrize("start, source", BLOCKS, ids=[f"line{start}" for start, _ in BLOCKS])
def test02_every_python_block_runs_as_written(start, source, tmp_path, monkeypatch):
    """Each block on its own, in an empty folder (blocks write their images there)."""
    where = f"README.md:{start}"
    code = compile(with_placeholders(source, where), where, "exec")
    monkeypatch.chdir(tmp_path)
    exec(code, {"__name__": "__readme__"})


def command_lines(text: str) -> list[tuple[int, str]]:
    """``(line number, command)`` of every ``hlbvh`` command README shows as one: an
    indented code line or a line of a fenced shell block that starts with ``hlbvh``."""
    commands, fence = [], None
    for number, line in enumerate(text.splitlines(), 1):
        if line.strip().startswith("```"):
            fence = None if fence is not None else line.strip()[3:]
            continue
        shown = (line.startswith("    ") if fence is None
                 else fence in ("bash", "sh", "shell", "console"))
        if shown and line.strip().startswith("hlbvh "):
            commands.append((number, line.strip()))
    return commands


COMMANDS = command_lines(README.read_text())


def test03_readme_shows_commands():
    assert any(command.startswith("hlbvh bench ") for _, command in COMMANDS)


@pytest.mark.parametrize("number, command", COMMANDS, ids=[f"line{n}" for n, _ in COMMANDS])
def test04_every_command_line_is_one_command_the_parser_takes(number, command):
    """Typed as shown, a line runs one ``hlbvh`` command: no pipe, redirection or list
    the shell would act on (``build|trace|frame`` is three commands piped), no
    ``[optional]`` brackets, and ``hlbvh``'s parser takes its words."""
    lexer = shlex.shlex(command, posix=True, punctuation_chars=True)
    lexer.whitespace_split, lexer.commenters = True, "#"
    words = list(lexer)
    shell = [word for word in words if word and set(word) <= set("|&;<>()")]
    assert not shell, f"README.md:{number}: the shell acts on {shell} in {command!r}"
    assert not any(word.startswith("[") for word in words), f"README.md:{number}: {command!r}"
    try:
        _parser().parse_args(words[1:])
    except SystemExit:
        pytest.fail(f"README.md:{number}: hlbvh's parser refuses {command!r}")


def test05_only_marked_placeholders_are_given_values(monkeypatch):
    """A marked ``NAME = ...  # ...`` line takes the test's value; an unmarked ``...``
    (inside a dict, a bare ``x = ...``) and a marked name without a test value fail
    the block, so no block leaves the reader a hole it does not name."""
    monkeypatch.setitem(PLACEHOLDERS, "faces", "[0, 1, 2]")
    given = with_placeholders("faces = ...  # your mesh's triangles\nprint(faces)\n", "block")
    assert given == "faces = [0, 1, 2]\nprint(faces)\n"
    for source, message in (("scene = {'type': 'scene', 'flag': ...}\n", "not marked"),
                            ("faces = ...\n", "not marked"),
                            ("rays = ...  # your camera's rays\n", "no test value")):
        with pytest.raises(AssertionError, match=message):
            with_placeholders(source, "block")
