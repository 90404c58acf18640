"""The README is a front door and docs/ holds the rest (issue #37): the README stays short, every
relative link lands on a file and heading that exist, every result file says when, where, at which
commit and by which commands it was measured, and every ``omg`` command the README, the guide and the
family pages show is one the CLI accepts.

The command check is what a user would run, short of running it: the subcommand is one ``omg.cli``
knows; a tool command's flags appear in its own ``--help``; a Lightning command's config files exist
and ``omg <fit|test|...> --config ... --KEY VALUE ... --print_config`` accepts its keys. All of it runs
in one child process forked from the tests' preloaded server (``helpers.forked``: the CLI's imports
are there already; each command runs in-process), so the check takes seconds, not a Python start-up per
command."""

from __future__ import annotations

import json
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest

from omg.cli import COMMANDS, LIGHTNING

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
README = ROOT / "README.md"
README_MAX_LINES = 300  # issue #37: the README is a front door
FAMILIES = ("omg", "omgpt", "habit")
OUTPUT_DIRS = ("runs/", "out/")  # where commands write: a config named there is an output, not a file of the repo
PLACEHOLDER = re.compile(r"\.\.\.|…|CKPT|<[^>]*>")

pytestmark = pytest.mark.xdist_group("docs")  # the tests share the `checked` fixture's child process


def markdown_files() -> list[Path]:
    return [README, *sorted(DOCS.rglob("*.md"))]


def shown_command_files() -> list[Path]:
    """The pages whose commands a user copies: the README, the guide and the family pages (results
    record what was run, placeholders and all)."""
    return [README, *sorted((DOCS / "guide").glob("*.md")), *sorted((DOCS / "families").glob("*.md"))]


def rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


# -- markdown ------------------------------------------------------------------------------------

FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)


def without_code(text: str, inline: bool = True) -> str:
    """The text with fenced blocks (and inline code) blanked: a link or heading inside code is none."""
    text = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    return re.sub(r"`[^`\n]*`", "``", text) if inline else text


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: link text kept, markup dropped, lower case, punctuation other than
    '-' and '_' removed, each space a '-'."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip())
    text = text.replace("`", "").replace("*", "").lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    found: set[str] = set()
    for line in without_code(path.read_text(), inline=False).splitlines():
        if match := re.match(r"#{1,6} (.+)", line):
            base = slug(match.group(1))
            name, n = base, 0
            while name in found:  # GitHub numbers repeated headings: x, x-1, x-2
                n += 1
                name = f"{base}-{n}"
            found.add(name)
    return found


def relative_links(path: Path) -> list[tuple[int, str]]:
    links = []
    for number, line in enumerate(without_code(path.read_text()).splitlines(), 1):
        for target in re.findall(r"\]\(([^)\s]+)\)", line):
            if not re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: are not checked here
                links.append((number, target))
    return links


def test_readme_is_a_front_door_and_docs_hold_the_rest():
    lines = README.read_text().count("\n")
    assert lines <= README_MAX_LINES, f"README.md has {lines} lines; at most {README_MAX_LINES}: move text into docs/"
    assert sorted((DOCS / "guide").glob("*.md")), "docs/guide/ holds the guide"
    for family in FAMILIES:
        assert (DOCS / "families" / f"{family}.md").is_file(), f"docs/families/{family}.md is missing"
    assert (DOCS / "architecture.md").is_file()
    assert sorted((DOCS / "results").glob("*.md")), "docs/results/ holds one file per study"
    linked = {(page.parent / target.partition("#")[0]).resolve()
              for page in markdown_files() for _, target in relative_links(page) if target.partition("#")[0]}
    orphans = [rel(page) for page in sorted(DOCS.rglob("*.md")) if page.resolve() not in linked]
    assert not orphans, f"no page links to {orphans}: link them from the README or another docs page"


def test_every_relative_link_lands_on_a_file_and_heading():
    problems = []
    for page in markdown_files():
        for number, target in relative_links(page):
            file, _, anchor = target.partition("#")
            destination = (page.parent / file).resolve() if file else page
            where = f"{rel(page)}:{number}: {target}"
            if not destination.exists():
                problems.append(f"{where}: no such file")
            elif anchor and (destination.suffix != ".md" or anchor not in anchors(destination)):
                problems.append(f"{where}: no heading #{anchor} in {rel(destination)}")
    assert not problems, "\n".join(problems)


def test_slug_follows_github():
    assert slug("Text-conditioned stage (Motion ControlNet + Mixture-of-Controllers)") == \
        "text-conditioned-stage-motion-controlnet--mixture-of-controllers"
    assert slug("A mixture read through `pipe:cat`") == "a-mixture-read-through-pipecat"
    assert slug('Does "left" vs "right" survive?') == "does-left-vs-right-survive"


# -- results -----------------------------------------------------------------------------------------

RESULT_HEADER = re.compile(
    r"\A# .+\n\n"
    r"\*\*Date\*\*: (?P<date>.+?) *\n"
    r"\*\*Commit\*\*: (?P<commit>.+?) *\n"
    r"\*\*Machine\*\*: (?P<machine>.+?) *\n"
    r"\*\*Commands\*\*:\n\n```bash\n(?P<commands>.*?)^```\n", re.S | re.M)


def test_every_result_starts_with_date_commit_machine_and_commands():
    results = sorted((DOCS / "results").glob("*.md"))
    assert results
    problems = []
    for page in results:
        header = RESULT_HEADER.match(page.read_text())
        if header is None:
            problems.append(f"{rel(page)}: does not start with '# title', then **Date**, **Commit**, **Machine** and "
                            "**Commands** (a bash block)")
            continue
        if not re.search(r"\b20\d\d-[01]\d-[0-3]\d\b", header["date"]):
            problems.append(f"{rel(page)}: **Date** holds no ISO date (YYYY-MM-DD): {header['date']!r}")
        if not re.search(r"\b[0-9a-f]{7,40}\b", header["commit"]):
            problems.append(f"{rel(page)}: **Commit** holds no commit sha (7+ hex digits): {header['commit']!r}")
        if not header["machine"].strip():
            problems.append(f"{rel(page)}: **Machine** is empty")
        if not any(line.strip() and not line.lstrip().startswith("#") for line in header["commands"].splitlines()):
            problems.append(f"{rel(page)}: **Commands** holds no command")
    assert not problems, "\n".join(problems)


# -- the commands the docs show -----------------------------------------------------------------------

@dataclass(frozen=True)
class Shown:
    where: str  # file:line
    argv: tuple[str, ...]  # after "omg"
    created: frozenset[str]  # files the same block writes (cat > mix.yaml)


def shown_commands(path: Path) -> list[Shown]:
    return shown_commands_in(path.read_text(), rel(path))


def shown_commands_in(text: str, page: str) -> list[Shown]:
    """Every ``omg ...`` line of the page's bash blocks, continuations joined; comments, and lines with a
    placeholder (``...``, ``CKPT``, ``<file>``), are left out."""
    commands = []
    for block in FENCE.finditer(text):
        if block.group(1) != "bash":
            continue
        first = text.count("\n", 0, block.start(2)) + 1
        created = frozenset(re.findall(r"cat > (\S+)", block.group(2)))
        lines = block.group(2).splitlines()
        number = 0
        while number < len(lines):
            start, line = number, lines[number]
            while line.rstrip().endswith("\\") and number + 1 < len(lines):
                number += 1
                line = line.rstrip()[:-1] + " " + lines[number].strip()
            number += 1
            line = line.strip()
            if not line.startswith("omg ") or PLACEHOLDER.search(line):
                continue
            argv = tuple(shlex.split(line, comments=True))[1:]
            commands.append(Shown(f"{page}:{first + start}", argv, created))
    return commands


def flags(argv: tuple[str, ...]) -> list[str]:
    return [a.split("=", 1)[0] for a in argv if a.startswith("--")]


def help_argv(argv: tuple[str, ...]) -> tuple[str, ...]:
    """The ``--help`` of the parser that reads this command: ``omg shards build --help``, ``omg generate --help``."""
    command = argv[0]
    if command in ("shards", "bench") and len(argv) > 1 and not argv[1].startswith("-"):
        return (command, argv[1], "--help")
    return (command, "--help")


def print_config_argv(shown: Shown) -> tuple[str, ...]:
    """``omg <fit|...> --config C ... --KEY VALUE ... --print_config`` for a Lightning command: its
    repository configs and its setting keys; checkpoints to resume or test are outputs and left out."""
    argv = shown.argv
    out: list[str] = [argv[0]]
    i = 1
    while i < len(argv):
        flag, value = argv[i], argv[i + 1] if i + 1 < len(argv) else None
        if flag == "--print_config":
            i += 1
            continue
        if value is None or value.startswith("--"):
            raise AssertionError(f"{shown.where}: {flag} has no value")
        i += 2
        if flag == "--ckpt_path":
            continue
        if flag == "--config" and (value.startswith(OUTPUT_DIRS) or value in shown.created):
            continue
        out += [flag, value]
    return (*out, "--print_config")


CHILD = r"""
import contextlib, io, json, sys
from omg.cli import main

results = []
for argv in json.loads(open(sys.argv[1]).read()):
    out, err = io.StringIO(), io.StringIO()
    code = 0
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main(list(argv))
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except Exception as e:  # a traceback is a failure of the command's check, reported with the others
            code, err = 1, io.StringIO(f"{type(e).__name__}: {e}")
    results.append({"code": code, "stdout": out.getvalue(), "stderr": err.getvalue()[-2000:]})
print(json.dumps(results))
"""


def run_in_child(argvs: list[tuple[str, ...]], folder: Path) -> dict[tuple[str, ...], dict]:
    """Each argv through ``omg.cli.main`` in one child process (in the repository, as a user runs them)."""
    from helpers.forked import OmgProcess

    (folder / "check.py").write_text(CHILD)
    (folder / "argvs.json").write_text(json.dumps(argvs))
    out, err = folder / "results.out", folder / "check.err"
    child = OmgProcess([str(folder / "argvs.json")], script=folder / "check.py", cwd=ROOT, stdout=out, stderr=err)
    assert child.wait(timeout=600) == 0, err.read_text()[-3000:]
    return dict(zip(argvs, json.loads(out.read_text().strip().splitlines()[-1])))


# a renamed flag and a misspelt key, as a page would show them: the check must catch both
BROKEN_PAGE = """```bash
# a comment, and a placeholder line: neither is checked
omg generate "a person waves" --ckpt CKPT --out ...
omg shards inspect shards/mini/human263/train \\
    --timout 5          # --timeout, renamed
omg fit --config configs/mini/pretrain.yaml --trainer.max_stepz 3
```
"""


def _broken() -> list[Shown]:
    return shown_commands_in(BROKEN_PAGE, "example.md")


BROKEN = _broken()


@pytest.fixture(scope="session")
def shown() -> list[Shown]:
    commands = [c for page in shown_command_files() for c in shown_commands(page)]
    assert len(commands) > 20, "the pages show their commands in ```bash blocks"
    return commands


@pytest.fixture(scope="session")
def checked(shown, tmp_path_factory) -> dict[tuple[str, ...], dict]:
    """Each tool parser's --help and each Lightning command's --print_config, run once."""
    argvs = sorted({help_argv(c.argv) for c in shown if c.argv[0] in COMMANDS}
                   | {print_config_argv(c) for c in shown if c.argv[0] in LIGHTNING}
                   | {help_argv(c.argv) if c.argv[0] in COMMANDS else print_config_argv(c) for c in BROKEN})
    return run_in_child(argvs, tmp_path_factory.mktemp("docs_commands"))


def test_shown_commands_name_a_command_of_the_cli(shown):
    problems = [f"{c.where}: omg {c.argv[0]}: not a command of omg.cli ({', '.join([*LIGHTNING, *COMMANDS])})"
                for c in shown if c.argv[0] not in LIGHTNING and c.argv[0] not in COMMANDS]
    assert not problems, "\n".join(problems)


def test_shown_tool_commands_use_flags_their_parser_accepts(shown, checked):
    problems = []
    for c in shown:
        if c.argv[0] not in COMMANDS:
            continue
        result = checked[help_argv(c.argv)]
        name = " ".join(help_argv(c.argv)[:-1])
        if result["code"] != 0:
            problems.append(f"{c.where}: omg {name} --help failed: {result['stderr'].strip()}")
            continue
        for flag in flags(c.argv):
            base = flag.split(".", 1)[0]  # --option.body_model is the --option dict's key
            if not re.search(rf"(?<![\w-]){re.escape(base)}(?![\w-])", result["stdout"]):
                problems.append(f"{c.where}: omg {name} has no option {flag}")
    assert not problems, "\n".join(problems)


def test_shown_lightning_commands_name_configs_that_exist_and_keys_that_resolve(shown, checked):
    problems = []
    for c in shown:
        if c.argv[0] not in LIGHTNING:
            continue
        for flag, value in zip(c.argv, c.argv[1:]):
            if flag == "--config" and not value.startswith(OUTPUT_DIRS) and value not in c.created \
                    and not (ROOT / value).is_file():
                problems.append(f"{c.where}: --config {value}: no such file in the repository")
        result = checked[print_config_argv(c)]
        if result["code"] != 0:
            problems.append(f"{c.where}: omg {shlex.join(c.argv)}: {result['stderr'].strip().splitlines()[-1:]}")
    assert not problems, "\n".join(problems)


def test_the_command_check_catches_a_wrong_flag_and_key(checked):
    """A renamed tool flag and a misspelt Lightning key are found, not waved through."""
    inspect, fit = BROKEN  # the comment and the placeholder line are left out, the continuation joined
    assert inspect.argv == ("shards", "inspect", "shards/mini/human263/train", "--timout", "5")
    assert (inspect.where, fit.where) == ("example.md:4", "example.md:6")
    help_text = checked[help_argv(inspect.argv)]
    assert help_text["code"] == 0 and re.search(r"(?<![\w-])--timeout(?![\w-])", help_text["stdout"])
    assert not re.search(r"(?<![\w-])--timout(?![\w-])", help_text["stdout"])
    wrong_key = checked[print_config_argv(fit)]
    assert wrong_key["code"] == 2 and "max_stepz" in wrong_key["stderr"], wrong_key
