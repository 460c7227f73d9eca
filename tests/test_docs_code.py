"""Every code block in the README and the docs runs as shown, or is marked as a sketch.

The rule, by the block's language:

* ``python``: runs on its own in a fresh namespace (one torch thread, so seeded output repeats);
  a ``text`` block right after it is what it prints, compared exactly, unless the block states a
  tolerance (below).
* ``bash`` / ``console`` / ``shell`` / ``sh``: each line is an ``smcd-rl ... --help`` command,
  which runs; any other shell block is a sketch, and its ``smcd-rl`` commands must still parse
  with the current options.
* ``text``, ``json``, ``yaml``, ``toml`` and unlabelled blocks are data.

A python block that cannot run here (a run of minutes, a user's own data) is a sketch too. A
sketch is marked by an HTML comment on the line right above its fence, which the rendered page
does not show::

    <!-- sketch: <why it does not run here> -->
    ```bash
    smcd-rl two-link --full
    ```

 The experiment reports included into the docs (``report.md``) are the
commands' own output and are checked by their fingerprints instead.

Tolerances. A seeded run repeats bit for bit on one CPU model, but float kernels differ between
CPU models (AVX-512 or AVX2, MKL's code paths), and a particle filter turns a last-digit change
into another random path: a printed RMSE of one filter run can move in its 2nd digit. Such a block
prints averages over several runs and says how far its printed numbers may move, in a comment
anywhere in the block::

    # tolerance: ±0.02            every decimal number within 0.02 of the page's
    # tolerance: ±10%             within 10% of the page's number
    # tolerance: ±0.02 or ±10%    within the larger of the two

Then the output is compared in pieces: the text between numbers exactly, integers (counts, steps,
sizes) exactly, and each number with a decimal point within the tolerance. A tolerance is chosen
from the spread measured across CPU kernels (``docs/performance.md`` lists it) and kept well below
the change a different setting makes (``test_a_tolerance_still_catches_a_changed_setting``).
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from dataclasses import dataclass, replace
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").rglob("*.md") if p.name != "report.md")]
SHELL = {"bash", "console", "shell", "sh"}
DATA = {"", "text", "json", "yaml", "toml", "csv"}
FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})\s*(?P<lang>[\w+-]*)[^\n]*$")


TOLERANCE = re.compile(r"#\s*tolerance:(?P<terms>[^(\n]*)")
#: A number with a decimal point (an integer is compared as text), not part of a name like ``v1.5``.
DECIMAL = re.compile(r"(?<![\w.])[-+]?\d+\.\d+(?:[eE][-+]?\d+)?(?![\w.])")


@dataclass(frozen=True)
class Tolerance:
    """How far a printed decimal number may be from the page's: the larger of ``absolute`` and ``relative * |page's|``."""

    absolute: float = 0.0
    relative: float = 0.0

    @classmethod
    def parse(cls, terms: str) -> Tolerance:
        """``"±0.02"``, ``"±10%"`` or ``"±0.02 or ±10%"``."""
        absolute = relative = 0.0
        for term in terms.split(" or "):
            found = re.fullmatch(r"\s*±\s*(\d+(?:\.\d+)?)\s*(%?)\s*", term)
            if found is None:
                raise ValueError(f"a tolerance is '±0.02', '±10%' or '±0.02 or ±10%', got {terms.strip()!r}")
            if found[2]:
                relative = float(found[1]) / 100
            else:
                absolute = float(found[1])
        return cls(absolute, relative)

    def allows(self, printed: float, shown: float) -> bool:
        return abs(printed - shown) <= max(self.absolute, self.relative * abs(shown)) + 1e-12


def compare_output(printed: str, shown: str, tolerance: Tolerance | None) -> list[str]:
    """What differs between a block's output and the page's text block (nothing: they match).

    Without a tolerance the two are compared exactly (after stripping); with one, the text and
    integers exactly and each decimal number within the tolerance.
    """
    printed, shown = printed.strip(), shown.strip()
    if tolerance is None:
        return [] if printed == shown else [f"printed:\n{printed}\npage:\n{shown}"]
    if DECIMAL.sub("#", printed) != DECIMAL.sub("#", shown):
        return [
            f"the text differs (numbers as #):\nprinted:\n{DECIMAL.sub('#', printed)}\npage:\n{DECIMAL.sub('#', shown)}"
        ]
    differences = []
    for line_printed, line_shown in zip(printed.splitlines(), shown.splitlines(), strict=True):
        for a, b in zip(DECIMAL.findall(line_printed), DECIMAL.findall(line_shown), strict=True):
            if not tolerance.allows(float(a), float(b)):
                differences.append(f"{a} where the page shows {b} (tolerance {tolerance}): {line_printed!r}")
    return differences


#: The sketch marker: the line right above a block's opening fence.
SKETCH = re.compile(r"^\s*<!--\s*sketch:\s*(?P<why>.*?)\s*-->\s*$")
#: The widest code line the docs site shows without cutting it (docs/ruff.toml, docs/stylesheets/extra.css).
PAGE_WIDTH = 88


@dataclass(frozen=True)
class Block:
    page: Path
    line: int  # 1-based line of the opening fence
    lang: str
    code: str
    sketch_reason: str | None = None  # from the ``<!-- sketch: why -->`` line above the fence

    @property
    def id(self) -> str:
        page = self.page.relative_to(ROOT) if self.page.is_relative_to(ROOT) else self.page
        return f"{page}:{self.line}"

    @property
    def sketch(self) -> bool:
        return self.sketch_reason is not None

    @property
    def tolerance(self) -> Tolerance | None:
        """The ``# tolerance: ...`` the block states for its printed numbers, if any."""
        found = TOLERANCE.search(self.code)
        return None if found is None else Tolerance.parse(found["terms"])


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
        marker = SKETCH.match(lines[i - 1]) if i > 0 else None
        found.append(Block(page, i + 1, opening["lang"].lower(), "\n".join(body) + "\n", marker and marker["why"]))
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
    first = next((line.strip() for line in block.code.splitlines() if line.strip()), "")
    assert not first.lower().startswith("# sketch"), (
        f"{block.id}: readers would see the marker; put '<!-- sketch: why -->' on the line above the fence instead"
    )
    assert block.sketch_reason != "", f"{block.id}: say why the block is a sketch: '<!-- sketch: why -->'"


@pytest.mark.parametrize("block", [b for b, _, _ in ALL if b.page.is_relative_to(ROOT / "docs")], ids=lambda b: b.id)
def test_no_code_line_is_wider_than_the_docs_page(block: Block) -> None:
    wide = [line for line in block.code.splitlines() if len(line) > PAGE_WIDTH]
    assert not wide, f"{block.id}: {len(wide)} line(s) over {PAGE_WIDTH} columns, cut off on the page: {wide[0]!r}"


def _run(block: Block) -> str:
    """What ``block`` prints, run in a fresh namespace with one torch thread."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    printed = io.StringIO()
    try:
        with contextlib.redirect_stdout(printed):
            exec(compile(block.code, block.id, "exec"), {"__name__": "__docs__"})
    finally:
        torch.set_num_threads(threads)
    return printed.getvalue()


@pytest.mark.slow
@pytest.mark.parametrize(("block", "output"), PYTHON, ids=[b.id for b, _ in PYTHON])
def test_python_block_runs_and_prints_what_the_page_shows(block: Block, output: Block | None, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a block that writes files writes them here
    printed = _run(block)
    if output is not None:
        differences = compare_output(printed, output.code, block.tolerance)
        assert not differences, f"{block.id} printed something else:\n" + "\n".join(differences)


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
            f"{block.id}: a shell block that is not an `smcd-rl ... --help` list is a sketch: put '<!-- sketch: why -->' on the line above its fence"
        )
    for argv in commands:
        try:
            build_parser().parse_args(argv)
        except SystemExit as stop:  # --help exits 0 after printing; a bad option exits 2
            assert stop.code == 0, f"{block.id}: `smcd-rl {' '.join(argv)}` does not parse: {capsys.readouterr().err}"


def test_the_checks_catch_a_stale_option_and_an_unmarked_block(tmp_path, capsys) -> None:
    page = tmp_path / "page.md"
    page.write_text(
        "<!-- sketch: long -->\n```bash\nsmcd-rl two-link --no-such-option\n```\n\n```bash\npip install x\n```\n"
    )
    stale, unmarked = blocks(page)
    assert _commands(stale) == [["two-link", "--no-such-option"]] and stale.sketch and not unmarked.sketch
    for block in (stale, unmarked):
        with pytest.raises(AssertionError):
            test_shell_block_is_help_or_a_sketch_and_its_commands_parse(block, capsys)


def test_a_tolerance_compares_text_and_integers_exactly_and_decimals_within_it() -> None:
    page = "no adaptation: RMSE 0.258 (sd 0.000 over 16 runs)\nSMCD: RMSE 0.160 (sd 0.024 over 16 runs)\n"
    within = Tolerance.parse("±0.03")
    assert within == Tolerance(absolute=0.03) and Tolerance.parse("±0.01 or ±10%") == Tolerance(0.01, 0.1)
    assert not compare_output(page.replace("0.160", "0.185").replace("0.024", "0.005"), page, within)
    assert compare_output(page.replace("0.160", "0.195"), page, within)  # beyond the tolerance
    assert compare_output(page.replace("16 runs", "15 runs"), page, within)  # an integer: exact
    assert compare_output(page.replace("SMCD:", "SMCD, calibrated:"), page, within)  # the text: exact
    assert compare_output(page + "one more line\n", page, within)
    assert compare_output(page.replace("0.160", "0.161"), page, None)  # no tolerance: exact
    assert not compare_output("log evidence -4.3", "log evidence -3.9", Tolerance.parse("±0.01 or ±15%"))
    assert compare_output("log evidence -4.6", "log evidence -3.9", Tolerance.parse("±0.01 or ±15%"))
    with pytest.raises(ValueError, match="a tolerance is"):
        Block(Path("page.md"), 1, "python", "print(0.5)  # tolerance: 0.03\n").tolerance  # noqa: B018


def test_every_stated_tolerance_parses() -> None:
    stated = [block for block, _ in PYTHON if TOLERANCE.search(block.code)]
    assert stated and all(block.tolerance is not None for block in stated)
    assert all(output is not None for block, output in PYTHON if block in stated)  # it has an output to compare


@pytest.mark.slow
def test_a_tolerance_still_catches_a_changed_setting(tmp_path, monkeypatch) -> None:
    """The README example's ±0.03 passes the spread between CPU kernels (SMCD's mean RMSE 0.160-0.172
    over 16 filters) but not a filter that no longer adapts: with a likelihood noise of 5 instead of
    0.02 every mask explains the data about as well, and SMCD's mean RMSE is the unadapted 0.258."""
    monkeypatch.chdir(tmp_path)
    block, output = next((b, o) for b, o in PYTHON if b.page.name == "README.md" and b.tolerance is not None)
    assert output is not None and "noise_std=0.02)" in block.code
    changed = replace(block, code=block.code.replace("noise_std=0.02)", "noise_std=5.0)"))
    differences = compare_output(_run(changed), output.code, changed.tolerance)
    assert differences and all("'SMCD: RMSE" in d for d in differences), differences  # the SMCD line only
