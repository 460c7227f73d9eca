"""Every code block in the README and the docs runs as shown, or says on its first line that it is a sketch.

The rule, by the block's language:

* ``python``: runs on its own in a fresh namespace (one torch thread, so seeded output repeats);
  a ``text`` block right after it is what it prints, compared exactly.
* ``bash`` / ``console`` / ``shell`` / ``sh``: each line is an ``smcd-rl ... --help`` command,
  which runs; any other shell block starts with ``# sketch: <why>``, and its ``smcd-rl`` commands
  must still parse with the current options.
* ``text``, ``json``, ``yaml``, ``toml`` and unlabelled blocks are data.

A python block that cannot run here (a run of minutes, a user's own data) starts with
``# sketch: <why>`` too. The experiment reports included into the docs (``report.md``) are the
commands' own output and are checked by their fingerprints instead.
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").rglob("*.md") if p.name != "report.md")]
SHELL = {"bash", "console", "shell", "sh"}
DATA = {"", "text", "json", "yaml", "toml", "csv"}
FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})\s*(?P<lang>[\w+-]*)[^\n]*$")


@dataclass(frozen=True)
class Block:
    page: Path
    line: int  # 1-based line of the opening fence
    lang: str
    code: str

    @property
    def id(self) -> str:
        page = self.page.relative_to(ROOT) if self.page.is_relative_to(ROOT) else self.page
        return f"{page}:{self.line}"

    @property
    def sketch(self) -> bool:
        first = next((line for line in self.code.splitlines() if line.strip()), "")
        return first.strip().lower().startswith("# sketch")


def blocks(page: Path) -> list[Block]:
    """The fenced blocks of ``page`` in order (fences indented inside admonitions and tabs included)."""
    found, lines, i = [], page.read_text().splitlines(), 0
    while i < len(lines):
        opening = FENCE.match(lines[i])
        if not opening:
            i += 1
            continue
        indent, fence = opening["indent"], opening["fence"]
        body, j = [], i + 1
        while j < len(lines) and not re.match(rf"^{re.escape(indent)}{fence[0]}{{{len(fence)},}}\s*$", lines[j]):
            body.append(lines[j][len(indent) :] if lines[j].startswith(indent) else lines[j].lstrip())
            j += 1
        found.append(Block(page, i + 1, opening["lang"].lower(), "\n".join(body) + "\n"))
        i = j + 1
    return found


def _output_block(page_blocks: list[Block], index: int) -> Block | None:
    """The ``text`` block right after block ``index`` (only blank lines between), if any."""
    if index + 1 >= len(page_blocks):
        return None
    block, after = page_blocks[index], page_blocks[index + 1]
    lines = block.page.read_text().splitlines()
    end = block.line + len(block.code.splitlines())  # the closing fence's index
    between = lines[end + 1 : after.line - 1]
    return after if after.lang == "text" and not any(line.strip() for line in between) else None


ALL = [(b, i, page_blocks) for page in PAGES for page_blocks in [blocks(page)] for i, b in enumerate(page_blocks)]
PYTHON = [(b, _output_block(pb, i)) for b, i, pb in ALL if b.lang in ("python", "py") and not b.sketch]
SHELL_BLOCKS = [b for b, _, _ in ALL if b.lang in SHELL]


def test_the_pages_have_code_blocks() -> None:
    assert len(PAGES) > 1 and PYTHON and SHELL_BLOCKS  # the scan itself works: README and docs found


@pytest.mark.parametrize("block", [b for b, _, _ in ALL], ids=lambda b: b.id)
def test_every_block_is_runnable_data_or_a_sketch(block: Block) -> None:
    known = {"python", "py", *SHELL, *DATA}
    assert block.lang in known, f"{block.id}: a ```{block.lang} block: use one of {sorted(known - {''})}"


@pytest.mark.slow
@pytest.mark.parametrize(("block", "output"), PYTHON, ids=[b.id for b, _ in PYTHON])
def test_python_block_runs_and_prints_what_the_page_shows(block: Block, output: Block | None, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a block that writes files writes them here
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    printed = io.StringIO()
    try:
        with contextlib.redirect_stdout(printed):
            exec(compile(block.code, block.id, "exec"), {"__name__": "__docs__"})
    finally:
        torch.set_num_threads(threads)
    if output is not None:
        assert printed.getvalue().strip() == output.code.strip(), f"{block.id} printed something else"


def _commands(block: Block) -> list[list[str]]:
    """Each ``smcd-rl`` command of a shell block as argv (after ``&&``, a ``.venv/bin/`` prefix or ``$ ``)."""
    found = []
    for line in block.code.replace("\\\n", " ").splitlines():  # a trailing backslash continues the command
        line = line.split(" #", 1)[0].strip().removeprefix("$ ")
        if line.startswith("#"):
            continue
        for part in line.split("&&"):
            words = shlex.split(part)
            if words and Path(words[0]).name == "smcd-rl":
                found.append(words[1:])
    return found


@pytest.mark.parametrize("block", SHELL_BLOCKS, ids=lambda b: b.id)
def test_shell_block_is_help_or_a_sketch_and_its_commands_parse(block: Block, capsys) -> None:
    from smcd_rl.cli import build_parser

    commands = _commands(block)
    lines = [line for line in block.code.splitlines() if line.strip()]
    if not block.sketch:
        assert len(commands) == len(lines) and all(c[-1:] == ["--help"] for c in commands), (
            f"{block.id}: a shell block that is not an `smcd-rl ... --help` list must start with '# sketch: <why>'"
        )
    for argv in commands:
        try:
            build_parser().parse_args(argv)
        except SystemExit as stop:  # --help exits 0 after printing; a bad option exits 2
            assert stop.code == 0, f"{block.id}: `smcd-rl {' '.join(argv)}` does not parse: {capsys.readouterr().err}"


def test_the_checks_catch_a_stale_option_and_an_unmarked_block(tmp_path, capsys) -> None:
    page = tmp_path / "page.md"
    page.write_text("```bash\n# sketch: long\nsmcd-rl two-link --no-such-option\n```\n\n```bash\npip install x\n```\n")
    stale, unmarked = blocks(page)
    assert _commands(stale) == [["two-link", "--no-such-option"]] and stale.sketch and not unmarked.sketch
    for block in (stale, unmarked):
        with pytest.raises(AssertionError):
            test_shell_block_is_help_or_a_sketch_and_its_commands_parse(block, capsys)
