"""The documentation holds: every relative link and picture of the README and ``docs/`` resolves, and every
``threedq ...`` command the README shows parses and names configs that exist.

Fast (a few seconds): the commands are parsed in this process, never run; the Lightning ones with
``--print_config`` (which stops after parsing), the others by the ``threedq`` parser alone.
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
#: Options of ``threedq`` commands whose value is a config file.
CONFIG_OPTIONS = ("--config", "--data_config", "--extra_configs", "--quantizer_config", "--detector_config",
                  "--mining_config", "--self_labelling_config")

FENCE = re.compile(r"^(```|~~~).*?^\1", flags=re.S | re.M)
INLINE_CODE = re.compile(r"`[^`\n]*`")
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def links(text: str) -> list[str]:
    """Targets of markdown links and pictures outside code (fenced blocks and inline code spans)."""
    prose = INLINE_CODE.sub("", FENCE.sub("", text))
    return LINK.findall(prose)


def test_links_helper() -> None:
    text = "see [a](x.md#part) and ![p](img/a.png)\n```\n[no](skip.md)\n```\n`[no](skip2.md)` [web](https://x.org)"
    assert links(text) == ["x.md#part", "img/a.png", "https://x.org"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page: Path) -> None:
    missing = []
    for target in links(page.read_text(encoding="utf-8")):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):  # a URL, or an anchor of this page
            continue
        path = target.split("#", 1)[0]
        if not (page.parent / path).exists():
            missing.append(target)
    assert not missing, f"{page.relative_to(ROOT)}: links to nothing: {missing}"


def readme_commands() -> list[tuple[str, set[str]]]:
    """Each ``threedq ...`` line of the README's code blocks (continuations joined), with the files the lines
    before it in its block create (``> file``), and each ``threedq ...`` command of its tables."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    out = []
    for block in re.findall(r"^```[a-z]*\n(.*?)^```", text, flags=re.S | re.M):
        created: set[str] = set()
        pending = ""
        for line in block.splitlines():
            if line.rstrip().endswith("\\"):
                pending += line.rstrip()[:-1] + " "
                continue
            line, pending = pending + line, ""
            code = line.split(" #", 1)[0].strip()
            created.update(re.findall(r">\s*(\S+)\s*$", code))
            if code.startswith("threedq "):
                out.append((code, set(created)))
    # and the commands of its tables (a cell that is one `threedq ...` code span)
    out += [(c, set()) for c in re.findall(r"^\| `(threedq [^`]*)` \|", text, flags=re.M)]
    return out


def test_readme_shows_commands() -> None:
    cmds = [c for c, _ in readme_commands()]
    assert any(c.startswith("threedq em ") for c in cmds) and any(c.startswith("threedq fit ") for c in cmds)


def test_readme_commands_parse(monkeypatch) -> None:
    from threedq.cli import LIGHTNING_SUBCOMMANDS, build_parser, main
    from threedq.pipeline.lightning_cli import resolve_config

    monkeypatch.chdir(ROOT)
    failures = []
    for command, created in readme_commands():
        argv = shlex.split(command)[1:]
        for i, a in enumerate(argv[:-1]):  # every config it names exists (here or among the packaged configs)
            if a in CONFIG_OPTIONS and argv[i + 1] not in created and argv[i + 1] != "none":
                try:
                    resolve_config(argv[i + 1])
                except FileNotFoundError as e:
                    failures.append(f"{command}: {e}")
        out = io.StringIO()
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
                if "--help" in argv:
                    code = main(argv)
                elif argv and argv[0] in LIGHTNING_SUBCOMMANDS:  # parses every option, instantiates nothing
                    code = main(argv if "--print_config" in argv else [*argv, "--print_config"])
                else:
                    build_parser(argv[0]).parse_args(argv)  # parsed, not run
                    code = 0
        except SystemExit as e:  # --help and --print_config end the parse here
            code = e.code or 0
        except Exception as e:  # noqa: BLE001 - any failure to parse is the finding
            failures.append(f"{command}: {type(e).__name__}: {e}")
            continue
        if code:
            failures.append(f"{command}: exit status {code}: {out.getvalue()[-300:]}")
    assert not failures, "\n".join(failures)
