"""The Dockerfile agrees with the README's commands and the package layout.

CI builds no image (``scripts/docker_check.sh`` builds and runs it: a maintainer's check before a release); this
parses the Dockerfile instead: the same torch pin as the README's two set-up commands and ``.ci/run``, the base image
and torch index as build arguments, the same extras as the README's test command, every file and folder the wheel is
built from (``tests/test_packaging.py``'s layout) copied before ``pip wheel``, no package source in the final image
(the tests there import the installed wheel), and the entry point the one ``pyproject.toml`` declares.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
tomllib = pytest.importorskip("tomllib")


def dockerfile_instructions(text: str) -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` per instruction: comments dropped, ``\\`` continuations joined."""
    out: list[tuple[str, str]] = []
    pending = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not pending and (not line or line.startswith("#")):
            continue
        if line.endswith("\\"):
            pending += line[:-1].rstrip() + " "
            continue
        line = pending + line
        pending = ""
        word, _, rest = line.partition(" ")
        out.append((word.upper(), rest.strip()))
    return out


def readme_commands() -> dict[str, str]:
    """The README's two set-up commands: ``main`` (``threedq em``) and ``tests`` (``pytest``)."""
    blocks = re.findall(r"```bash\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)
    lines = [ln for b in blocks for ln in b.splitlines() if ln.startswith("pip install")]
    main = [ln for ln in lines if "threedq em" in ln]
    tests = [ln for ln in lines if "pytest" in ln]
    assert len(main) == 1 and len(tests) == 1, lines
    return {"main": main[0], "tests": tests[0]}


def torch_pin(command: str) -> str:
    m = re.search(r"torch==([\w.+]+)", command)
    assert m, command
    return m.group(1)


def extras(command: str) -> set[str]:
    for word in shlex.split(command):
        m = re.fullmatch(r"(?:-e\s*)?\.(?:\[([\w,\s-]*)\])?", word)
        if m:
            return {e.strip() for e in (m.group(1) or "").split(",") if e.strip()}
    raise AssertionError(f"no local install in {command!r}")


class TestDockerfileParser:
    def test_continuations_and_comments(self) -> None:
        text = "# c\nFROM x\n\nRUN a \\\n    && b\nARG V=1\n"
        assert dockerfile_instructions(text) == [("FROM", "x"), ("RUN", "a && b"), ("ARG", "V=1")]

    def test_extras(self) -> None:
        assert extras('pip install torch==2.13.0 -e ".[test]"') == {"test"}
        assert extras("pip install .") == set()
        assert extras('pip install ".[test, baselines]"') == {"test", "baselines"}


class TestDockerfile:
    @pytest.fixture(scope="class")
    def docker(self) -> list[tuple[str, str]]:
        return dockerfile_instructions((ROOT / "Dockerfile").read_text())

    def test_same_torch_pin_everywhere(self, docker) -> None:
        args = dict(a.split("=", 1) for ins, a in docker if ins == "ARG" and "=" in a)
        pins = {torch_pin(c) for c in readme_commands().values()}
        pins.add(torch_pin((ROOT / ".ci" / "run").read_text()))
        assert pins == {args["TORCH_VERSION"]}
        # and the torch install uses that ARG
        assert any(ins == "RUN" and 'torch==${TORCH_VERSION}' in a for ins, a in docker)

    def test_base_image_and_torch_index_are_build_arguments(self, docker) -> None:
        args = dict(a.split("=", 1) for ins, a in docker if ins == "ARG" and "=" in a)
        assert args["BASE_IMAGE"] == "python:3.11-slim"
        assert args["TORCH_INDEX"] == "https://download.pytorch.org/whl/cpu"
        froms = [a.split()[0] for ins, a in docker if ins == "FROM"]
        assert froms and set(froms) == {"${BASE_IMAGE}"}
        assert any(ins == "RUN" and '--index-url "${TORCH_INDEX}"' in a for ins, a in docker)

    def test_same_extras_as_the_test_command(self, docker) -> None:
        installs = [a for ins, a in docker if ins == "RUN" and "pip install" in a and "threedq-*.whl" in a]
        assert len(installs) == 1
        spec = re.search(r'"\$\(ls [^)]*threedq-\*\.whl\)(\[[\w,]*\])?"', installs[0])
        assert spec, installs[0]
        assert extras("." + (spec.group(1) or "")) == extras(readme_commands()["tests"])
        declared = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"])
        assert extras(readme_commands()["tests"]) <= declared

    def test_wheel_sources_copied_before_the_wheel_is_built(self, docker) -> None:
        from test_packaging import BUILD_FILES, LAYOUT

        needed = {*BUILD_FILES, *LAYOUT}
        build_at = next(i for i, (ins, a) in enumerate(docker) if ins == "RUN" and "pip wheel" in a)
        copied: set[str] = set()
        for ins, a in docker[:build_at]:
            if ins == "COPY":
                *sources, _dest = shlex.split(a)
                copied |= {s.rstrip("/") for s in sources}
        assert needed <= copied, needed - copied
        from threedq.pipeline.lightning_cli import packaged_configs_dir

        assert (packaged_configs_dir() / "trainer" / "ddp_cpu.yaml").is_file()  # the configs folder is the one copied

    def test_final_image_holds_the_tests_not_the_sources(self, docker) -> None:
        from test_packaging import LAYOUT

        last_from = max(i for i, (ins, _a) in enumerate(docker) if ins == "FROM")
        copied = set()
        for ins, a in docker[last_from:]:
            if ins == "COPY" and not a.startswith("--from"):
                *sources, _dest = shlex.split(a)
                copied |= {s.rstrip("/") for s in sources}
        assert "tests" in copied and not copied & set(LAYOUT), copied
        workdirs = [a for ins, a in docker[last_from:] if ins == "WORKDIR"]
        assert workdirs[-1] == "/work"  # where `pytest` finds the tests and the entry point's runs land

    def test_entrypoint_is_the_declared_script(self, docker) -> None:
        scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
        entry = [a for ins, a in docker if ins == "ENTRYPOINT"]
        assert len(entry) == 1 and entry[0].strip('[]" ') in scripts
