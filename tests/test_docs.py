"""The documentation holds to the tree: README.md and every docs/*.md page.

- every relative link and image (Markdown or HTML) names a file or folder that exists, and
  a ``#anchor`` into a Markdown file names one of its headings (GitHub's slugs);
- every ``swarm ...`` command line they quote parses with the CLI's own parser (click's
  ``make_context``, command by command down the tree; nothing runs): the command exists,
  every option is one of its options and every value converts. A line of a shell block is a
  whole command line, so its required arguments must be there too; inline code may be a
  fragment (`swarm mc --runs 30`), so it may leave required ones out. A usage synopsis's
  ``[optional]`` brackets are dropped. A line or paragraph holding ``docs-test: skip`` is
  not checked (for a command quoted as an example of an error);
- every ``make TARGET`` they quote is a target of the Makefile;
- every repository file they name in code (`tests/test_x.py`, `swarmrt/tuning.py`, with
  ``::name`` a function of it) exists;
- README.md stays a front door: at most 250 lines, and its command table names every
  command of the CLI.

A few checks of the checker (a wrong link, anchor, command, option, value, target, file)
show that it can fail.
"""

from __future__ import annotations

import re
import shlex
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SKIP = "docs-test: skip"
SHELL = {"", "sh", "bash", "console", "shell"}
README_MAX_LINES = 250


# -- reading Markdown ---------------------------------------------------------------------
def split_markdown(text: str) -> tuple[str, list[tuple[str, int, list[str]]]]:
    """The prose (fenced blocks blanked, so that line numbers hold) and the fenced blocks as
    ``(language, first line number, lines)``."""
    prose, blocks, block = [], [], None
    for no, line in enumerate(text.splitlines(), 1):
        fence = re.match(r"^\s*(```+|~~~+)\s*([\w+-]*)", line)
        if block is None and fence:
            block = (fence.group(2).lower(), no + 1, [], fence.group(1))
            prose.append("")
        elif block is not None and line.strip().startswith(block[3]):
            blocks.append(block[:3])
            block = None
            prose.append("")
        elif block is not None:
            block[2].append(line)
            prose.append("")
        else:
            prose.append(line)
    return "\n".join(prose), blocks


INLINE_CODE = re.compile(r"(?<!`)(`+)(?!`)(.+?)(?<!`)\1(?!`)", re.S)


def inline_code(prose: str) -> list[tuple[int, str, str]]:
    """``(line number, code with its whitespace collapsed, its paragraph)`` of every inline
    code span (a span may cross a line break)."""
    out = []
    for m in INLINE_CODE.finditer(prose):
        start = prose.rfind("\n\n", 0, m.start()) + 2
        end = prose.find("\n\n", m.end())
        para = prose[start : end if end >= 0 else len(prose)]
        out.append((prose.count("\n", 0, m.start()) + 1, " ".join(m.group(2).split()), para))
    return out


LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HTML_LINK = re.compile(r"""<(?:a|img)\b[^>]*?\b(?:href|src)=["']([^"']+)["']""", re.I)
REF_LINK = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)", re.M)


def links(prose: str) -> list[tuple[int, str]]:
    """``(line number, target)`` of every link and image outside code."""
    text = INLINE_CODE.sub(lambda m: "`" + "x" * (len(m.group(0)) - 2) + "`" if "\n" not in m.group(0) else m.group(0), prose)
    out = []
    for rx in (LINK, HTML_LINK, REF_LINK):
        out += [(text.count("\n", 0, m.start()) + 1, m.group(1)) for m in rx.finditer(text)]
    return out


def github_slug(heading: str) -> str:
    """The anchor GitHub gives a heading: its text (links and code marks removed) in lower
    case, without punctuation but hyphens and underscores, spaces made hyphens."""
    s = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    s = s.replace("`", "").replace("*", "").strip().lower()
    return re.sub(r"[^\w\- ]", "", s).replace(" ", "-")


@cache
def anchors(path: Path) -> frozenset[str]:
    prose, _ = split_markdown(path.read_text())
    seen: dict[str, int] = {}
    out = set(re.findall(r"""<a\s+(?:id|name)=["']([^"']+)["']""", prose))
    for m in re.finditer(r"^ {0,3}#{1,6}\s+(.*?)\s*#*\s*$", prose, re.M):
        slug = github_slug(m.group(1))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return frozenset(out)


# -- the checks ---------------------------------------------------------------------------
def link_problem(page: Path, target: str) -> str | None:
    if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) or target.startswith("//"):
        return None  # a web address: not this test's business
    path, _, anchor = target.partition("#")
    dest = (page.parent / path).resolve() if path else page
    if not dest.exists():
        return f"links to {target}: no such file"
    if ROOT not in (dest, *dest.parents):
        return f"links to {target}: outside the repository"
    if anchor and dest.suffix == ".md" and anchor not in anchors(dest):
        return f"links to {target}: {dest.relative_to(ROOT)} has no heading with anchor #{anchor}"
    return None


@cache
def cli_root():
    import typer

    from swarm.cli import app

    return typer.main.get_command(app)


def command_problem(words: list[str], whole: bool) -> str | None:
    """Parse ``swarm WORDS`` as the CLI would, without running anything. ``whole``: a
    complete command line (its required arguments must be there)."""
    from swarm.cli import optional_values

    words = optional_values(list(words))  # what `swarm`'s entry point does first (`--live` alone)
    if "--help" in words:
        words, whole = [w for w in words if w != "--help"], False
    cmd, name, parent, path = cli_root(), "swarm", None, ()
    while True:
        group = hasattr(cmd, "commands")
        where = " ".join(("swarm", *path))
        if group and not words:
            return f"`{where}` is a group: name one of its commands" if whole else None
        try:
            ctx = cmd.make_context(name, list(words), parent=parent)
        except Exception as e:
            # click's exceptions, or typer's copy of them (typer >= 0.2x carries its own click):
            # told apart by name. A missing parameter is a usage error too, and a bad value.
            kinds = {c.__name__ for c in type(e).__mro__}
            if "UsageError" not in kinds:
                raise
            if "MissingParameter" in kinds and not whole:
                return None  # a fragment: required arguments may be left out
            return f"`{where}`: {e.format_message()}"  # type: ignore[attr-defined]
        if not group:
            return None
        rest = [*ctx._protected_args, *ctx.args]
        if not rest:
            return f"`{where}` is a group: name one of its commands" if whole else None
        sub = cmd.get_command(ctx, rest[0])
        if sub is None or getattr(sub, "hidden", False):
            return f"`{where} {rest[0]}` is not a command (`{where}` has {', '.join(sorted(cmd.commands))})"
        path, parent, cmd, name, words = (*path, rest[0]), ctx, sub, rest[0], rest[1:]


@cache
def make_targets() -> frozenset[str]:
    return frozenset(re.findall(r"^([A-Za-z0-9_.-]+)\s*:(?!=)", (ROOT / "Makefile").read_text(), re.M))


OURS = re.compile(r"^\s*(?:[A-Za-z_][A-Za-z0-9_]*=\S*\s+)*(?:\.venv/bin/)?(?:swarm|make)(?:\s|$)")


def shell_commands(lines: list[str]) -> list[tuple[int, str, list[str]]]:
    """``(offset, raw line, words)`` of each simple command of a shell block: continuation
    lines joined, comments dropped, split at ``&&``, ``||``, ``;`` and ``|``, leading
    ``VAR=value`` assignments dropped."""
    out, i = [], 0
    while i < len(lines):
        start, raw = i, lines[i]
        while raw.rstrip().endswith("\\") and i + 1 < len(lines):
            i += 1
            raw = raw.rstrip()[:-1] + " " + lines[i]
        i += 1
        line = re.sub(r"^\s*\$\s+", "", raw)
        if SKIP in raw or not any(OURS.match(part) for part in re.split(r"&&|\|\||;|\|", line)):
            continue  # no command of ours (another program, a diagram)
        try:
            words = shlex.split(line, comments=True)
        except ValueError as e:
            out.append((start, raw, ["<unparsable>", str(e)]))
            continue
        if " [-" in line:  # a usage synopsis: [--option VALUE] is optional syntax
            words = [w.removeprefix("[").removesuffix("]") for w in words]
        seg: list[str] = []
        for w in [*words, ";"]:
            if w in ("&&", "||", ";", "|"):
                while seg and re.match(r"^[A-Za-z_][A-Za-z0-9_]*=", seg[0]):
                    seg.pop(0)
                if seg:
                    out.append((start, raw, seg))
                seg = []
            else:
                seg.append(w)
    return out


def file_problem(code: str) -> str | None:
    """A code span that names a repository file (a path under a top-level folder, with an
    extension; ``::name`` a function or class in it) must name one that exists."""
    first = code.split()[0].rstrip(",;:)")
    path, _, member = first.partition("::")
    path = path.removeprefix("./")
    top = path.split("/", 1)[0]
    if "/" not in path or not (ROOT / top).is_dir() or top in ("runs", "keys") or top.startswith(".venv"):
        return None
    if re.search(r"[<>{}*$]", path) or not re.search(r"\.[A-Za-z0-9]+$", path.rsplit("/", 1)[-1]):
        return None  # a pattern or a placeholder, or not a file
    if not (ROOT / path).exists():
        return f"names {path}: no such file"
    if member and not re.search(rf"^\s*(?:async\s+)?(?:def|class)\s+{re.escape(member.split('[')[0])}\b", (ROOT / path).read_text(), re.M):
        return f"names {first}: {path} defines no {member}"
    return None


def table_problems(prose: str) -> list[tuple[int, str]]:
    """A table (consecutive lines starting with ``|``) needs its header separator as its
    second line and as many cells in every row as in its header (GitHub's rule: every
    unescaped ``|`` splits, in code too)."""
    out, lines = [], prose.splitlines()
    i = 0
    while i < len(lines):
        if not lines[i].startswith("|"):
            i += 1
            continue
        j = i
        while j < len(lines) and lines[j].startswith("|"):
            j += 1

        def cells(row: str) -> int:
            return len(re.split(r"(?<!\\)\|", row.strip().strip("|")))

        if j - i < 2 or not re.fullmatch(r"\|(\s*:?-{3,}:?\s*\|)+\s*", lines[i + 1]):
            out.append((i + 1, "a table without its header separator (| --- |) as its second line"))
        else:
            for k in range(i + 2, j):
                if cells(lines[k]) != cells(lines[i]):
                    out.append((k + 1, f"a table row of {cells(lines[k])} cells under a header of {cells(lines[i])}"))
        i = j
    return out


def page_problems(page: Path, text: str | None = None) -> list[str]:
    text = page.read_text() if text is None else text
    prose, blocks = split_markdown(text)
    rel = page.relative_to(ROOT) if ROOT in page.parents else page.name
    problems = []

    def say(no: int, what: str) -> None:
        problems.append(f"{rel}:{no}: {what}")

    for no, what in table_problems(prose):
        say(no, what)
    for no, target in links(prose):
        if (p := link_problem(page, target)) is not None:
            say(no, p)
    for lang, first, lines in blocks:
        if lang not in SHELL:
            continue
        for offset, raw, words in shell_commands(lines):
            if words[0] == "<unparsable>":
                say(first + offset, f"`{raw.strip()}`: {words[1]}")
            elif words[0] in ("swarm", ".venv/bin/swarm"):
                if (p := command_problem(words[1:], whole=True)) is not None:
                    say(first + offset, f"`{raw.strip()}`: {p}")
            elif words[0] == "make":
                for t in (w for w in words[1:] if not w.startswith("-") and "=" not in w):
                    if t not in make_targets():
                        say(first + offset, f"`{raw.strip()}`: the Makefile has no target {t}")
    for no, code, para in inline_code(prose):
        if SKIP in para:
            continue
        if re.match(r"^(?:\.venv/bin/)?swarm (?=-|[a-z])", code):
            try:
                words = shlex.split(code)[1:]
            except ValueError as e:
                say(no, f"`{code}`: {e}")
                continue
            if (p := command_problem(words, whole=False)) is not None:
                say(no, f"`{code}`: {p}")
        elif m := re.match(r"^make ([a-z][\w-]*)$", code):
            if m.group(1) not in make_targets():
                say(no, f"`{code}`: the Makefile has no target {m.group(1)}")
        elif (p := file_problem(code)) is not None:
            say(no, p)
    return problems


# -- the tests ----------------------------------------------------------------------------
def test_pages_were_found():
    names = {p.name for p in PAGES}
    assert {"README.md", "architecture.md", "agent-contract.md", "estimators.md"} <= names, names
    assert len(PAGES) >= 10


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_links_commands_and_files_of_a_page_resolve(page):
    problems = page_problems(page)
    assert not problems, "\n".join(problems)


def test_readme_is_a_front_door_that_names_every_command():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= README_MAX_LINES, f"README.md has {len(text.splitlines())} lines (at most {README_MAX_LINES})"
    named = {code for _, code, _ in inline_code(split_markdown(text)[0])}

    def leaves(cmd, path):
        if hasattr(cmd, "commands"):
            for name, sub in cmd.commands.items():
                if not sub.hidden:
                    yield from leaves(sub, (*path, name))
        else:
            yield path

    every = {" ".join(("swarm", *p)) for p in leaves(cli_root(), ())}
    assert len(every) >= 40, every  # the walk found the tree
    missing = every - named
    assert not missing, f"README.md's command table lacks {sorted(missing)}"


def _problems_of(snippet: str, tmp_path: Path) -> list[str]:
    page = ROOT / "docs" / "_snippet.md"  # as if it were a page of docs/ (links resolve from there)
    return page_problems(page, snippet)


@pytest.mark.parametrize(
    ("snippet", "says"),
    [
        ("See [the faults](faults-and-chaos.md).", None),
        ("See [the faults](no-such-page.md).", "no-such-page.md: no such file"),
        ("See [stalls](faults-and-chaos.md#a-stalled-process-sigstop-docker-pause).", None),
        ("See [stalls](faults-and-chaos.md#a-stalled-proces).", "has no heading with anchor #a-stalled-proces"),
        ("![a picture](live-view.png) and ![none](dead-view.png)", "dead-view.png: no such file"),
        ("```sh\nswarm sim scenarios/demo.yaml --out runs/x --set n_sats=6\n```", None),
        ("```sh\nswarm simulate scenarios/demo.yaml --out runs/x\n```", "`swarm simulate` is not a command"),
        ("```sh\nswarm bench filter --satellites 3,6\n```", "No such option: --satellites"),
        ("```sh\nswarm mc scenarios/size-6.yaml --runs many --out runs/m\n```", "Invalid value for '--runs'"),
        ("```sh\nswarm sim scenarios/demo.yaml\n```", "Missing option '--out'"),
        ("```sh\nswarm fault --run-dir runs/x explode 2\n```", "`swarm fault explode` is not a command"),
        ("```sh\nswarm fault --hostname h kill-agent 2\n```", "No such option: --hostname"),
        ("```sh\nswarm sim scenarios/demo.yaml --out runs/x --bogus  # docs-test: skip\n```", None),
        ("Inline `swarm mc --runs 30` is a fragment.", None),
        ("Inline `swarm mc --rnus 30` is wrong.", "No such option: --rnus"),
        ("Inline `swarm live layout --sats N` has a placeholder.", "Invalid value for '--sats'"),
        ("```sh\nswarm run scenarios/demo.yaml --out runs/l --live\n```", None),
        ("An error quoted on purpose: `swarm mc --rnus 30` (docs-test: skip).", None),
        ("```sh\nSWARM_N=8 make demo && make bogus-target\n```", "no target bogus-target"),
        ("`make soak` and `make sock`", "no target sock"),
        ("`swarmrt/tuning.py` and `swarmcore/tuning.py`", "names swarmcore/tuning.py: no such file"),
        ("`tests/test_chaos.py::test_no_such_test`", "defines no test_no_such_test"),
        ("`runs/demo/report/report.html`, `swarmrt/bus/v1/*_pb2.py`", None),
        ("| a | b |\n| --- | --- |\n| 1 | 2 |", None),
        ("| 1 | 2 |\n| 3 | 4 |", "without its header separator"),
        ("| a | b |\n| --- | --- |\n| 1 | 2 | 3 |", "a table row of 3 cells under a header of 2"),
    ],
)
def test_the_checker_fails_on_what_is_wrong(snippet, says, tmp_path):
    problems = _problems_of(snippet, tmp_path)
    if says is None:
        assert problems == []
    else:
        assert len(problems) == 1 and says in problems[0], problems
