"""Fenced code blocks of the project's Markdown, and the shell commands inside them (pure; tests/docs checks them)."""
from __future__ import annotations

import re
import shlex
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DOC_FILES = ("README.md", "docs/*.md", "docker/README.md", "examples/**/*.md", "deploy/**/*.md")
_FENCE = re.compile(r"^(?P<indent>\s*)(?P<fence>```+|~~~+)(?P<info>.*)$")


@dataclass(frozen=True)
class Block:
    """One fenced block: where it is (``line`` of its opening fence), its tag, and its text."""

    path: str  # relative to the repository
    line: int
    tag: str
    text: str

    @property
    def where(self) -> str:
        return f"{self.path}:{self.line} [{self.tag or 'untagged'}]"


def doc_paths(repo: Path = REPO) -> list[Path]:
    return sorted({p for pattern in DOC_FILES for p in repo.glob(pattern) if p.is_file()})


def blocks_in(path: Path, repo: Path = REPO) -> Iterator[Block]:
    """Every fenced block of a Markdown file; an unterminated fence is a block to the end of the file."""
    lines = path.read_text(encoding="utf-8").splitlines()
    opened: tuple[int, str, str, str] | None = None  # line, fence, indent, tag
    body: list[str] = []
    for number, line in enumerate(lines, 1):
        match = _FENCE.match(line)
        if opened is None:
            if match:
                tag = match["info"].strip().split(" ")[0] if match["info"].strip() else ""
                opened, body = (number, match["fence"], match["indent"], tag), []
            continue
        if match and match["fence"].startswith(opened[1]) and not match["info"].strip():
            yield Block(str(path.relative_to(repo)), opened[0], opened[3], "\n".join(body) + "\n")
            opened = None
            continue
        body.append(line.removeprefix(opened[2]))
    if opened is not None:
        yield Block(str(path.relative_to(repo)), opened[0], opened[3], "\n".join(body) + "\n")


def all_blocks(repo: Path = REPO) -> list[Block]:
    return [block for path in doc_paths(repo) for block in blocks_in(path, repo)]


_SUBSTITUTION = re.compile(r"\$\(([^()]*)\)")
_OPERATORS = {";", "&&", "||", "|", "&", ";;"}


def shell_commands(script: str) -> list[tuple[int, list[str]]]:
    """(line within the script, words) of every simple command, command substitutions included;
    leading ``NAME=value`` assignments are dropped (a line of only assignments is no command)."""
    commands: list[tuple[int, list[str]]] = []
    logical: list[tuple[int, str]] = []
    pending, start = "", 1
    for number, line in enumerate(script.splitlines(), 1):
        if not pending:
            start = number
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        logical.append((start, pending + line))
        pending = ""
    if pending:
        logical.append((start, pending))
    for number, line in logical:
        parts = [_SUBSTITUTION.sub("SUBSTITUTED", line), *_SUBSTITUTION.findall(line)]
        for part in parts:
            lexer = shlex.shlex(part, posix=True, punctuation_chars=";&|")
            lexer.whitespace_split = True
            lexer.commenters = "#"
            try:
                tokens = list(lexer)
            except ValueError:
                continue  # unbalanced quotes: `bash -n` reports those with their line
            words: list[str] = []
            for token in [*tokens, ";"]:
                if token in _OPERATORS:
                    while words and re.match(r"^[A-Za-z_][A-Za-z0-9_]*=", words[0]):
                        words.pop(0)
                    if words:
                        commands.append((number, words))
                    words = []
                else:
                    words.append(token)
    return commands
